"""The on-policy single-agent family on the training engine: :class:`OnPolicyGroupTrainer` (stacked networks).

``sg-train --seeds 0 1 2`` trains S independent runs of one algorithm side by side in one process, and
``sg-train --seed s`` is the same engine with S = 1 in a single run's layout; the config picks the layout
(:func:`~sg_torchrl.train.seed_runs.run_layout`), not the class. Multi-agent algorithms
(:class:`~sg_torchrl.train.multi_agent_group.MultiAgentGroupTrainer`) keep one team and one round per
seed: the per-seed updates run one after another, not stacked, while simulation and collection are
batched as here. What every family shares (the seeds' records, epochs, logs, summaries, divergence
freezing, checkpoint entries, the layouts) is the engine, :class:`~sg_torchrl.train.trainer.SeedGroupTrainer`.

DESIGN.md ("Many seeds in one process"): SafePO's networks are so small that a gradient step is
per-operator overhead, so S seeds whose networks are stacked along a leading seed dimension and
stepped together cost little more than one. Nothing is shared between the seeds; seed ``s`` of a
group trains exactly as the group of that seed alone (``--seeds s``) does, which is its single-seed
run in every respect that is not float rounding:

* **simulators**: one batched env of ``S * num_envs`` simulators, seed ``s``'s the ``s``-th block of
  ``num_envs``, seeded exactly as a ``num_envs``-simulator env with seed ``s``
  (``sg_torchrl.make(..., seed=[s0, s1, ...])``);
* **networks**: ``torch.manual_seed(s)`` (:func:`~sg_torchrl.seeding.seed_torch`) then
  ``make_actor_critics`` (the TorchRL modules users build; with CNN encoders on pixel observations),
  stacked in a :class:`~sg_torchrl.modules.stacked.StackedActorCritic`;
* **observation normaliser**: one row of running statistics per seed (``RunningObservationNorm(groups=S)``),
  over the flat vector only (images are scaled in the networks and stay ``uint8`` in the batch);
* **random streams** (:mod:`sg_torchrl.seeding`): action noise from one ``torch.Generator`` per seed
  (the ``actions`` purpose, :func:`~sg_torchrl.seeding.action_seed`), minibatch order from another
  (:class:`~sg_torchrl.train.fused.SeedShuffler`, seeded with ``s`` as the single-seed trainer seeds
  its own: the ``minibatches`` purpose);
* **multiplier, advantages, update**: one multiplier per seed, updated from its own episodes'
  mean cost; GAE per simulator, advantage normalisation per seed; the algorithm's group update
  (:mod:`sg_torchrl.train.group_updates`) with per-seed clip, Adam state and KL early stop (second
  order: each seed's trust-region step from its own multiplier and :math:`J_c - d`, then its critic
  passes);
* **logs and summary**: its own run directory with exactly a single run's files and metric names.

So within an epoch a seed's env trajectory is bit-identical whatever the group (the per-seed
generators and simulator blocks draw the same numbers, and the stacked actor computes each seed's
actions as for S = 1); across epochs the seeds' updates agree to float rounding (batched matmuls
of the critics' one-wide output sum in another order for S = 1 and S > 1, about 1e-7).

**Layout, checkpoint, divergence.** The engine's (:mod:`sg_torchrl.train.seed_runs`,
:mod:`sg_torchrl.train.trainer`; the directory tree is in the README). This family's checkpoint entry
per seed (networks as single-seed modules' state dicts, Adam rows, multiplier, normaliser row,
generators) is :meth:`OnPolicyGroupTrainer._seed_state`'s.

**Device** (``--device``, :mod:`sg_torchrl.train.devices`). The networks, the masked Adam's state,
the multiplier values the losses read, GAE, the epoch's batch and the whole update live on
``cfg.device``; the simulators, the observation normaliser (it runs in the env's transform during
collection, never in the update) and the multipliers' own state (each follows a host-side
:math:`J_c` once per epoch) stay on the host. :class:`StackedPolicy` copies each step's observation
to the device and its outputs back once; the batch crosses once per epoch; the update reads back
once per pass and per epoch (:mod:`sg_torchrl.train.group_updates`). Checkpoints hold CPU tensors.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, exploration_type

import sg_torchrl
from sg_torchrl import seeding
from sg_torchrl.collectors import RolloutCollector
from sg_torchrl.envs.normalization import RunningObservationNorm
from sg_torchrl.objectives import make_cost_gae, make_gae
from sg_torchrl.train.algorithms import ALGORITHMS
from sg_torchrl.train.config import TrainConfig
from sg_torchrl.train.devices import training_device
from sg_torchrl.train.evaluate import evaluate_policy
from sg_torchrl.train.fused import FusedFirstOrderStep, SeedShuffler, multiplier_values
from sg_torchrl.train.group_updates import FIELDS, GroupParts, finite_seeds
from sg_torchrl.train.memory import keep_freed_memory
from sg_torchrl.modules.mlp import ObservationLayout, make_actor_critics
from sg_torchrl.train.seed_runs import SeedRun, seed_entry
from sg_torchrl.train.trainer import SeedGroupTrainer
from sg_torchrl.seeding import action_seed  # re-exported (the actions rule)
from sg_torchrl.modules.stacked import StackedActorCritic, in_chunks

__all__ = ["OnPolicyGroupTrainer", "SeedRun", "StackedPolicy", "action_seed", "seed_entry"]

#: Update metrics logged as integers, as the single-seed trainer logs them.
_COUNTS = ("Train/StopIter", "Train/ProjectionStopIter")


class StackedPolicy(TensorDictModuleBase):
    """A seed group's actors as one TensorDict policy of its batched env (what :class:`RolloutCollector` calls).

    Reads ``observation`` ``(S * N, obs_dim)`` (or the images the networks read), views it per seed
    (:meth:`~sg_torchrl.modules.stacked.StackedActorCritic.read_observation`: seed ``s``'s simulators are
    block ``s``) and writes ``loc``, ``scale``, ``action`` and ``action_log_prob``
    as the single-seed actor does, seed ``s``'s noise drawn from ``generators[s]``
    (:meth:`~sg_torchrl.modules.stacked.StackedActorCritic.sample`). Under a deterministic exploration
    type it returns the means. Seeds in :attr:`frozen` act with zeros (a diverged seed's actions may
    not be finite, which the env refuses).

    With the networks on another device than the env's observations (``--device cuda``), a step
    copies the observation to the networks' device once and its four outputs back in one tensor.
    """

    def __init__(self, model: StackedActorCritic, generators: list[torch.Generator]) -> None:
        super().__init__()
        self.model = model
        self.generators = generators
        self.in_keys = ["observation"]
        self.out_keys = ["loc", "scale", "action", "action_log_prob"]
        self._frozen: Tensor | None = None
        self._frozen_mask: Tensor | None = None  # on the networks' device, copied once per change

    @property
    def frozen(self) -> Tensor | None:
        """``(S,)`` bool of the seeds acting with zeros, or ``None`` when every seed acts."""
        return self._frozen

    @frozen.setter
    def frozen(self, value: Tensor | None) -> None:
        self._frozen = value
        self._frozen_mask = None if value is None else value.to(self.model.flat_actor.device).view(-1, 1, 1)

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = self.model.read_observation(tensordict)
        rows = obs.shape[0] * obs.shape[1]
        device, host = self.model.flat_actor.device, _device_of(obs)
        if device != host:
            obs = obs.to(device, non_blocking=True)
        deterministic = exploration_type() in (ExplorationType.DETERMINISTIC, ExplorationType.MODE,
                                               ExplorationType.MEAN)
        action, log_prob, loc, scale = self.model.sample(obs, self.generators, deterministic=deterministic)
        if self._frozen_mask is not None:
            action = torch.where(self._frozen_mask, torch.zeros_like(action), action)
        if device != host:  # the step's one copy back: what the env steps with and the batch keeps
            width = action.shape[-1]
            packed = torch.cat((action, loc, scale, log_prob.unsqueeze(-1)), dim=-1).to(host)
            action, loc, scale, log_prob = packed.split((width, width, width, 1), dim=-1)
            log_prob = log_prob.squeeze(-1)
        tensordict.set("loc", loc.reshape(rows, -1))
        tensordict.set("scale", scale.reshape(rows, -1))
        tensordict.set("action", action.reshape(rows, -1))
        tensordict.set("action_log_prob", log_prob.reshape(rows))
        return tensordict


def _device_of(value: Tensor | TensorDictBase) -> torch.device:
    """Where a tensor, or the first entry of a TensorDict (the env's observations), lives."""
    return value.device if isinstance(value, Tensor) else next(iter(value.values(True, True))).device


class OnPolicyGroupTrainer(SeedGroupTrainer):
    """Build and run a single-agent on-policy algorithm: a seed group (``cfg.seeds``) or one run (``cfg.seed``).

    See the module docstring.

    Args:
        cfg: the run's config (``seeds`` for a group, else ``seed``; ``num_envs``, ``steps_per_epoch``,
            ``total_steps`` per seed).
        checkpoint: a checkpoint of this trainer (:meth:`load_checkpoint`) to continue from.

    Raises:
        ValueError: a multi-agent algorithm (:class:`~sg_torchrl.train.multi_agent_group.MultiAgentGroupTrainer`
            trains those).
    """

    def __init__(self, cfg: TrainConfig, checkpoint: dict[str, Any] | None = None) -> None:
        if cfg.multi_agent:
            raise ValueError(f"OnPolicyGroupTrainer trains the single-agent algorithms, not {cfg.algo!r} "
                             f"(use MultiAgentGroupTrainer)")
        self.device = training_device(cfg)  # refuses a device this machine lacks before anything is built
        super().__init__(cfg)
        # glibc would hand the updates' MB-sized temporaries back to the OS after every use and fault them
        # in again: S = 3, 20,000 steps per seed, 350,000-600,000 minor faults per CPO update, 300,000 per
        # PPO-Lag update; kept, about none and 7-10 % less update CPU time, the same peak memory.
        keep_freed_memory()
        self.algorithm = ALGORITHMS[cfg.algo]
        self.title = self.algorithm.title
        groups = len(self.seeds)
        self.base_env = sg_torchrl.make(cfg.env_id, num_envs=groups * cfg.num_envs,
                                        seed=[seeding.env_seed(s, seeding.Purpose.SIMULATORS) for s in self.seeds],
                                        **cfg.env_options)
        # What the networks read (flat vector, pixels, depth) comes from the env's observation spec; the
        # running normaliser applies to the flat vector only (images are scaled in the networks).
        layout = ObservationLayout.from_spec(self.base_env.observation_spec)
        normalize = cfg.normalize_obs and layout.vector_dim is not None
        self.obs_norm = RunningObservationNorm((layout.vector_dim,), groups=groups) if normalize else None
        self.env: EnvBase = TransformedEnv(self.base_env, self.obs_norm) if self.obs_norm else self.base_env

        singles = []
        for seed in self.seeds:  # each seed's networks as make_actor_critics initialises them after seed_torch(seed)
            seeding.seed_torch(seed)
            singles.append(make_actor_critics(layout, self.base_env.action_spec, cfg.network_sizes))
        self.model = StackedActorCritic.from_single(singles, layout=layout, device=self.device)
        self.multipliers = [self.algorithm.make_multiplier(cfg) for _ in self.seeds]
        # One seed's single-seed loss names the objective and its hyper-parameters for the group update.
        loss = self.algorithm.make_loss(*singles[0], self.multipliers[0], cfg)
        self.reward_gae = make_gae(None, gamma=cfg.gamma, lmbda=cfg.gae_lambda).to(self.device)
        self.cost_gae = make_cost_gae(None, gamma=cfg.gamma, lmbda=cfg.cost_gae_lambda).to(self.device)
        # Second order has no actor learning rate (SafePO's Adam holds the critics alone): the actor's
        # group is kept at lr 0 and never stepped, its trust-region step moves it.
        self.actor_lr = 0.0 if cfg.second_order else cfg.actor_lr
        self.optimizer = FusedFirstOrderStep.make_optimizer(self.model, self.actor_lr, cfg.critic_lr,
                                                            max_grad_norm=cfg.max_grad_norm, compile=cfg.compile)
        self.shuffler = SeedShuffler(self.seeds)
        self.action_generators = [seeding.generator(seed, seeding.Purpose.ACTIONS) for seed in self.seeds]
        parts = GroupParts(self.model, self.optimizer, self.shuffler, passes=cfg.update_iters,
                           minibatch_size=cfg.minibatch_size, target_kl=cfg.target_kl, compile=cfg.compile)
        self.group_update = self.algorithm.make_group_update(parts, loss, cfg)
        self.policy = StackedPolicy(self.model, self.action_generators)
        self.collector = RolloutCollector(self.env, self.policy, steps=cfg.steps_per_epoch // cfg.num_envs)
        self.runs = [SeedRun(seed, self._seed_config(seed)) for seed in self.seeds]
        self._start(checkpoint)

    # ------------------------------------------------------------------ seeds and epochs
    def _finite_seeds(self) -> Tensor:
        return finite_seeds(self.model).cpu()

    def _learn(self, batch: TensorDictBase) -> tuple[list[dict[str, float]], list[bool]]:
        """Multipliers, advantages and the group update; each seed's learned metrics and whether it diverged.

        Every live seed's multiplier follows its own mean episode cost (before the update, as SafePO),
        the actor learning rate is annealed as the single-seed trainer's scheduler does (first order;
        second order has none and logs 0), and the algorithm's group update moves the live seeds, each
        with its :math:`J_{c,s} - d` from its multiplier (``Multiplier.violation``). The multipliers
        follow their host-side :math:`J_c` and hand the update their values on the networks' device
        (with the batch and the live-seed mask, one copy each per epoch); :math:`J_c - d` stays on the
        host, where the trust-region proposals read it. One host read of the metrics per epoch.
        """
        cfg, device = self.cfg, self.device
        alive = self.alive.to(device)
        lagrange = [float(m.update(run.last_mean_cost) if run.alive else m.value)
                    for m, run in zip(self.multipliers, self.runs)]
        data, raw_advantages = self._seed_data(batch.to(device, non_blocking=True))
        self.optimizer.param_groups[0]["lr"] = self.actor_lr * max(0.0, 1.0 - self.epoch / cfg.epochs)
        violation = torch.tensor([m.violation(run.last_mean_cost) for m, run in zip(self.multipliers, self.runs)],
                                 dtype=torch.float64)
        result = self.group_update(data, multiplier_values(self.multipliers).to(device), violation, alive)
        names = list(result.metrics)
        values = torch.stack([result.metrics[name].to(device, torch.float64) for name in names]
                             + [raw_advantages[0].double(), raw_advantages[1].double()]).tolist()
        next_lr = self.actor_lr * max(0.0, 1.0 - (self.epoch + 1) / cfg.epochs)  # as the trainer logs its scheduler's
        rows = []
        for index, lam in enumerate(lagrange):
            update = {name: int(values[i][index]) if name in _COUNTS else values[i][index]
                      for i, name in enumerate(names)}
            rows.append({"Train/LagrangeMultiplier": lam, "Train/LR": next_lr, **update,
                         "Value/RewardAdv": values[-2][index], "Value/CostAdv": values[-1][index]})
        return rows, (result.diverged & alive).tolist()

    @torch.no_grad()
    def _seed_data(self, batch: TensorDictBase) -> tuple[dict[str, Tensor], Tensor]:
        """Values, both GAEs and per-seed advantage normalisation on the ``(S * N, T)`` batch.

        Returns the update's fields (:data:`~sg_torchrl.train.group_updates.FIELDS`) as ``(S, N * T, k)``
        tensors, and the raw (pre-normalisation) mean reward and cost advantage per seed, ``(2, S)``.
        The GAEs run per simulator, so per seed; the normalisation is SafePO's
        (:func:`~sg_torchrl.objectives.normalize_advantages`: reward standardised, cost centred) over
        each seed's own samples.
        """
        groups, shape = len(self.seeds), batch.shape

        def per_seed(value: Tensor) -> Tensor:
            return value.reshape(groups, -1, *value.shape[len(shape):])

        model = self.model
        for prefix in ((), ("next",)):  # with images in chunks: an epoch's frames are never all float at once
            value, cost_value = in_chunks(model.values, model.read_observation(batch, prefix), model.chunk_size)
            batch.set((*prefix, "state_value"), value.reshape(*shape, 1))
            batch.set((*prefix, "cost_value"), cost_value.reshape(*shape, 1))
        self.reward_gae(batch)
        self.cost_gae(batch)
        data = {name: per_seed(batch.get(name)) for name in FIELDS if name != "observation"}
        data["observation"] = model.read_observation(batch)
        data["action_log_prob"] = data["action_log_prob"].unsqueeze(-1)
        advantage, cost_advantage = data["advantage"], data["cost_advantage"]
        raw = torch.stack((advantage.mean((1, 2)), cost_advantage.mean((1, 2))))
        data["advantage"] = (advantage - advantage.mean((1, 2), keepdim=True)) / (
            advantage.std((1, 2), keepdim=True) + 1e-8)
        data["cost_advantage"] = cost_advantage - cost_advantage.mean((1, 2), keepdim=True)
        return data, raw

    # ------------------------------------------------------------------ evaluation
    def _evaluate_seed(self, index: int) -> dict[str, float]:
        """Seed ``index``'s deterministic evaluation, its actor and normaliser, env seed + 10_000."""
        cfg, seed = self.cfg, self.seeds[index]
        actor = self.model.export_seed(index, self.base_env.action_spec, device="cpu")[0]
        norm = None if self.obs_norm is None else self.obs_norm.group_copy(index)
        return evaluate_policy(cfg.env_id, actor, cfg.eval_episodes,
                               seed=seeding.env_seed(seed, seeding.Purpose.EVALUATION), obs_norm=norm,
                               env_options=cfg.env_options)

    # ------------------------------------------------------------------ checkpoints
    def _seed_state(self, index: int) -> dict[str, Any]:
        """Seed ``index``'s networks (as single-seed modules' state dicts), Adam rows, multiplier, normaliser row, generators.

        CPU tensors whatever ``cfg.device``: a checkpoint loads, and continues, on any device."""
        actor, critic, cost_critic = self.model.export_seed(index, self.base_env.action_spec, device="cpu")
        return {
            "networks": {"actor": actor.state_dict(), "critic": critic.state_dict(),
                         "cost_critic": cost_critic.state_dict()},
            # Adam's rows of the flat groups (actor, critics): per group the step count and both moments.
            "optimizer": self.optimizer.seed_state_dict(index),
            "multiplier": self.multipliers[index].state_dict(),
            "obs_norm": None if self.obs_norm is None else self.obs_norm.group_state_dict(index),
            "minibatch_rng": self.shuffler.generators[index].get_state(),
            "action_rng": self.action_generators[index].get_state(),
        }

    @torch.no_grad()
    def _load_seed_state(self, index: int, entry: dict[str, Any]) -> None:
        triple = self.model.export_seed(index, self.base_env.action_spec, device="cpu")
        for module, name in zip(triple, ("actor", "critic", "cost_critic")):
            module.load_state_dict(entry["networks"][name])
        self.model.load_seed(index, *triple)
        self.optimizer.load_seed_state_dict(index, entry["optimizer"])
        self.multipliers[index].load_state_dict(entry["multiplier"])
        if self.obs_norm is not None:
            self.obs_norm.load_group_state_dict(index, entry["obs_norm"])
        self.shuffler.generators[index].set_state(entry["minibatch_rng"])
        self.action_generators[index].set_state(entry["action_rng"])
