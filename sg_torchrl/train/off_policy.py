"""The off-policy family (SAC, TD3, DDPG; -Lag and -PID) on the seed-group engine: ``sg-train --algo sac_lag``.

:class:`OffPolicyGroupTrainer` is a :class:`~sg_torchrl.train.trainer.SeedGroupTrainer`: the layouts,
the seeds' records, ``progress.csv`` rows under the single-seed names, logs, summaries, divergence
freezing and checkpoint entries are the on-policy engine's. What differs is the epoch's work, which runs
inside collection (OmniSafe's loop): after each env step every seed's transitions go into its replay
buffer (:class:`~sg_torchrl.train.replay.SeedReplay`), and once ``warmup_steps`` of random actions are
done, ``utd_ratio`` gradient steps per env step update every seed at once:

* the networks are S seeds' copies stacked as rows (:class:`~sg_torchrl.modules.off_policy.StackedOffPolicyNets`),
  initialised per seed as :func:`~sg_torchrl.modules.off_policy.make_off_policy_networks` builds them after
  ``torch.manual_seed(seed)``;
* the losses are the loss object's :class:`~sg_torchrl.objectives.off_policy.OffPolicyObjective`
  (``loss.seed_batched_objective()``: the math ``SACLagLoss`` / ``TD3LagLoss`` / ``DDPGLagLoss`` evaluate),
  on every seed's minibatch of ``minibatch_size`` with ``seed_dims=1``;
* one :class:`~sg_torchrl.train.seed_adam.SeedMaskedAdam` per network kind (actor, reward critics, cost
  critics; OmniSafe's optimisers), each clipping each seed's gradient at ``max_grad_norm``; the actor and
  the targets (Polyak ``polyak``) move every ``policy_delay`` gradient steps;
* the multiplier moves once per epoch from the epoch's mean episode cost (on-policy engine's rule; its new
  value weighs the next epoch's actor steps).

Random streams per seed (:mod:`sg_torchrl.seeding`): ``actions`` (warm-up actions, exploration noise),
``replay`` (the buffer's sampling), ``updates`` (SAC's sampled actions, TD3's smoothing noise), so seed
``k`` of a group trains as its ``--seed k`` run (the same class with S = 1 in a single run's layout; the
same numbers up to the batched matmuls' float rounding). A seed whose loss turns non-finite stops stepping at
once and is put back to its state at the start of the epoch, then frozen. ``--resume`` continues bit for
bit: the checkpoint holds the rows, targets, optimisers, multipliers and generators, and the replay
buffers' state (their memory maps and undo files in the run directory, :mod:`sg_torchrl.train.replay`).

**Device** (``--device``, :mod:`sg_torchrl.train.devices`). The rows and targets, the Adam moments, the
multiplier values the actor loss reads, every gradient step and the epoch's loss sums live on ``cfg.device``;
the simulators and the replay buffers (memory maps in the run directory) stay on the host. A collection step
copies the observation to the device and the action back once; a gradient step copies its sampled rows to
the device in one tensor (:meth:`~sg_torchrl.train.replay.SeedReplay.sample`) and its standard-normal draws
(CPU generators, so a run draws the same numbers on every device) once each. Nothing in a gradient step
reads back to the host: a seed whose loss turns non-finite is masked on the device
(:class:`~sg_torchrl.train.seed_adam.SeedMaskedAdam`'s ``active``); the flags and the sums are read once
per epoch. Checkpoints hold CPU tensors, so a run continues on another device.
"""

from __future__ import annotations

import time
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor
from torchrl.envs.utils import ExplorationType, exploration_type

import sg_torchrl
from sg_torchrl import seeding
from sg_torchrl.algorithms import manifest
from sg_torchrl.collectors import RolloutCollector
from sg_torchrl.modules.off_policy import StackedOffPolicyNets, make_off_policy_networks
from sg_torchrl.objectives.off_policy import OffPolicyObjective
from sg_torchrl.train.algorithms import make_multiplier
from sg_torchrl.train.checkpoint import host_copy
from sg_torchrl.train.config import TrainConfig
from sg_torchrl.train.devices import training_device
from sg_torchrl.train.evaluate import evaluate_policy
from sg_torchrl.train.fused import multiplier_values
from sg_torchrl.train.replay import SeedReplay
from sg_torchrl.train.seed_adam import SeedMaskedAdam
from sg_torchrl.train.seed_runs import SeedRun
from sg_torchrl.train.trainer import SeedGroupTrainer

__all__ = ["OffPolicyGroupTrainer", "make_loss", "off_policy_network_options", "off_policy_objective_of"]

_METRICS = ("Loss/Loss_reward_critic", "Loss/Loss_cost_critic", "Loss/Loss_pi", "Value/reward_critic",
            "Value/cost_critic")


def off_policy_objective_of(loss) -> OffPolicyObjective:
    """The seed-batched form of an off-policy loss, from the loss object (the engine's only way to get one).

    Raises:
        TypeError: the loss has no ``seed_batched_objective()`` returning an :class:`OffPolicyObjective`.
    """
    method = getattr(loss, "seed_batched_objective", None)
    objective = method() if method is not None else None
    if not isinstance(objective, OffPolicyObjective):
        raise TypeError(f"{type(loss).__name__} has no seed_batched_objective() giving an OffPolicyObjective: the "
                        f"off-policy engine trains SACLagLoss, TD3LagLoss, DDPGLagLoss (or subclasses)")
    return objective


def off_policy_network_options(algo: str) -> dict[str, Any]:
    """The :func:`make_off_policy_networks` keywords of an off-policy row: SAC's stochastic actor, DDPG's one
    critic of each kind (TD3's and SAC's two), cost critics for a constrained row (a run's networks and a
    loaded policy's actor are built from these alone)."""
    entry = manifest.get(algo)
    return {"stochastic": entry.loss.endswith(":SACLagLoss"),
            "num_critics": 1 if entry.loss.endswith(":DDPGLagLoss") else 2,
            "constrained": entry.multiplier != "none"}


def make_loss(cfg: TrainConfig, networks, multiplier, action_spec):
    """The row's loss over one run's :func:`make_off_policy_networks` modules, its options from the config
    (TD3 also takes the action bounds, for its target smoothing)."""
    entry = manifest.get(cfg.algo)
    actor, critics, costs = networks
    options = cfg.keyword_options(entry.loss_options)
    if "policy_noise" in options:
        options["action_spec"] = action_spec
    single = len(critics) == 1  # DDPG: one critic of each kind, given as a module
    cost = (costs[0] if single else costs) if costs else None
    loss = entry.loss_class()(actor, critics[0] if single else critics, cost,
                              multiplier if entry.multiplier != "none" else None, **options)
    loss.make_value_estimator(gamma=cfg.gamma)
    return loss


def _row_spec(env) -> Any:
    """One simulator's action spec (the batched env's first row)."""
    return env.action_spec[0]


def _flat_adam_rows(rows: list[dict[str, Any]]) -> dict[str, Tensor]:
    """One seed's :meth:`~sg_torchrl.train.seed_adam.SeedMaskedAdam.seed_state_dict` in this family's checkpoint
    format: each optimiser holds one parameter group of one stacked tensor, saved as its three rows."""
    (row,) = rows
    (exp_avg,), (exp_avg_sq,) = row["exp_avg"], row["exp_avg_sq"]
    return {"step": row["step"], "exp_avg": exp_avg, "exp_avg_sq": exp_avg_sq}


class OffPolicyStackedPolicy(TensorDictModuleBase):
    """S seeds' actors acting on their simulator blocks: uniform random (warm-up), sampled (SAC), or the
    deterministic action plus Gaussian ``noise`` clamped to the bounds (TD3, DDPG); means under a
    deterministic exploration type; frozen seeds act with zeros.

    The draws come from the seeds' CPU generators; the observation goes to the networks' device and the
    action comes back to the env's in one copy each (none when both are the CPU)."""

    def __init__(self, nets: StackedOffPolicyNets, generators: list[torch.Generator], noise: float) -> None:
        super().__init__()
        self.nets, self.generators, self.noise = nets, generators, float(noise)
        self.in_keys, self.out_keys = ["observation"], ["action"]
        self.random = True
        self.frozen: Tensor | None = None

    def _draw(self, batch: int, kind: str) -> Tensor:
        draw = torch.rand if kind == "rand" else torch.randn
        draws = torch.stack([draw(batch, self.nets.action_dim, generator=g) for g in self.generators])
        return draws.to(self.nets.device, non_blocking=True)

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        nets = self.nets
        host_obs = tensordict.get("observation")
        obs = host_obs.reshape(nets.num_seeds, -1, nets.obs_dim).to(nets.device, non_blocking=True)
        batch = obs.shape[1]
        deterministic = exploration_type() in (ExplorationType.DETERMINISTIC, ExplorationType.MODE,
                                               ExplorationType.MEAN)
        if deterministic:
            action = nets.action(nets.actor, obs)
        elif self.random:
            action = nets.low + (nets.high - nets.low) * self._draw(batch, "rand")
        elif nets.stochastic:
            action = nets.sample(nets.actor, obs, self._draw(batch, "randn"))[0]
        else:
            action = (nets.action(nets.actor, obs) + self.noise * self._draw(batch, "randn")).clamp(nets.low, nets.high)
        action = action.to(host_obs.device)  # the step's one copy back
        if self.frozen is not None:
            action = torch.where(self.frozen.view(-1, 1, 1), torch.zeros_like(action), action)
        tensordict.set("action", action.reshape(-1, nets.action_dim))
        return tensordict


class InterleavedCollector(RolloutCollector):
    """:class:`~sg_torchrl.collectors.RolloutCollector` whose :meth:`after_step` hands every step's transitions to
    ``after_step`` (the replay buffers and the gradient steps), with gradients enabled there."""

    def __init__(self, env, policy, steps: int, after_step) -> None:
        super().__init__(env, policy, steps)
        self._after_step = after_step

    def after_step(self, transition: TensorDictBase) -> None:
        with torch.enable_grad():
            self._after_step(transition)


class OffPolicyGroupTrainer(SeedGroupTrainer):
    """An off-policy algorithm: a seed group (``cfg.seeds``) or one run (``cfg.seed``); see the module docstring.

    Raises:
        ValueError: ``cfg`` is not an off-policy algorithm.
    """

    def __init__(self, cfg: TrainConfig, checkpoint: dict[str, Any] | None = None) -> None:
        if not cfg.off_policy:
            raise ValueError(f"{type(self).__name__} trains the off-policy algorithms, not {cfg.algo!r}")
        self.device = training_device(cfg)  # refuses a device this machine lacks before anything is built
        super().__init__(cfg)
        entry = manifest.get(cfg.algo)
        self.title, seeds = entry.title, self.seeds
        self.base_env = sg_torchrl.make(cfg.env_id, num_envs=len(seeds) * cfg.num_envs,
                                        seed=[seeding.env_seed(s, seeding.Purpose.SIMULATORS) for s in seeds],
                                        **cfg.env_options)
        self.env = self.base_env
        spec, obs_dim = _row_spec(self.base_env), self.base_env.observation_spec["observation"].shape[-1]
        options = off_policy_network_options(cfg.algo)
        singles = []
        for seed in seeds:  # each seed's networks as its --seed run builds them
            seeding.seed_torch(seed)
            singles.append(make_off_policy_networks(obs_dim, spec, cfg.network_sizes, **options))
        self.multipliers = [make_multiplier(entry.multiplier, cfg) for _ in seeds]
        # One seed's loss, the LossModule users compose, names the objective and its hyper-parameters.
        self.objective = off_policy_objective_of(make_loss(cfg, singles[0], self.multipliers[0], spec))
        self.nets = StackedOffPolicyNets.from_single(singles, obs_dim, spec, cfg.network_sizes,
                                                     stochastic=options["stochastic"], device=self.device)
        self.optimizers = {name: SeedMaskedAdam([{"params": [rows], "lr": cfg.actor_lr if name == "actor"
                                                  else cfg.critic_lr}], max_grad_norm=cfg.max_grad_norm)
                           for name, rows in self.nets.trained().items()}
        self.action_generators = [seeding.generator(s, seeding.Purpose.ACTIONS) for s in seeds]
        self.replay_generators = [seeding.generator(s, seeding.Purpose.REPLAY) for s in seeds]
        self.update_generators = [seeding.generator(s, seeding.Purpose.UPDATES) for s in seeds]
        self.replay = SeedReplay(cfg.run_dir, seeds, self.replay_generators, capacity=cfg.replay_size,
                                 batch_size=cfg.minibatch_size, obs_dim=obs_dim, action_dim=self.nets.action_dim)
        self.gradient_steps = 0
        self.policy = OffPolicyStackedPolicy(self.nets, self.action_generators, cfg.exploration_noise)
        self.collector = InterleavedCollector(self.env, self.policy, cfg.steps_per_epoch // cfg.num_envs,
                                              self._after_step)
        self.runs = [SeedRun(seed, self._seed_config(seed)) for seed in seeds]
        self._start(checkpoint)
        self._new_epoch_state()

    # ------------------------------------------------------------------ the steps
    def _new_epoch_state(self) -> None:
        """Per-epoch sums and flags, the multiplier values in force, the live seeds, the policy's warm-up flag
        (on the networks' device, one copy each per epoch)."""
        S, device = len(self.seeds), self.device
        self.lam = multiplier_values(self.multipliers).to(device)
        self.sums = {name: torch.zeros(S, dtype=torch.float64, device=device) for name in _METRICS}
        self.counts = {"critic": 0, "actor": 0}
        self.bad = torch.zeros(S, dtype=torch.bool, device=device)
        self.live = self.alive.to(device)
        self.update_seconds = 0.0
        self.policy.random = self.total_steps < self.cfg.warmup_steps
        self.snapshot = self._rows_and_moments()

    def _noise(self, like: Tensor) -> Tensor:
        """Every seed's standard-normal draw shaped as ``like``'s rows, from its CPU generator, on ``like``'s device."""
        noise = torch.stack([torch.randn(like.shape[1:], generator=g) for g in self.update_generators])
        return noise.to(like.device, non_blocking=True)

    def _after_step(self, transition: TensorDictBase) -> None:
        """Store every seed's transitions, then take the gradient steps now due (``utd_ratio`` per env step)."""
        cfg, nets, S = self.cfg, self.nets, len(self.seeds)

        def per_seed(value: Tensor) -> Tensor:
            return value.reshape(S, cfg.num_envs, -1).float()

        nxt = transition.get("next")
        self.replay.extend(per_seed(transition.get("observation")), per_seed(transition.get("action")),
                           per_seed(nxt.get("reward")), per_seed(nxt.get("cost")), per_seed(nxt.get("terminated")),
                           per_seed(nxt.get("observation")))
        self._steps_in_epoch = getattr(self, "_steps_in_epoch", 0) + cfg.num_envs
        done = self.total_steps + self._steps_in_epoch  # env steps per seed so far
        self.policy.random = done < cfg.warmup_steps
        due = int(max(0, done - cfg.warmup_steps) * cfg.utd_ratio) - self.gradient_steps
        if due > 0:
            start = time.perf_counter()
            for _ in range(due):
                self._gradient_step(nets)
            self.update_seconds += time.perf_counter() - start

    def _gradient_step(self, nets: StackedOffPolicyNets) -> None:
        """One gradient step of every seed (module docstring)."""
        cfg, objective = self.cfg, self.objective
        obs, action, reward, cost, terminated, next_obs = self.replay.sample(self.device)
        self.gradient_steps += 1
        actor_due = self.gradient_steps % cfg.policy_delay == 0
        with torch.no_grad():
            if objective.stochastic:
                next_action, next_log_prob = nets.sample(nets.actor, next_obs, self._noise(action))
            else:
                next_log_prob = None
                noise = self._noise(action) if objective.policy_noise else None  # drawn first, as TD3Loss
                next_action = nets.action(nets.target_actor, next_obs)
                if noise is not None:
                    next_action = objective.smoothed_action(next_action, noise, nets.low, nets.high)
            next_q = nets.q(nets.target_critic, next_obs, next_action)
            next_cost_q = nets.q(nets.target_cost_critic, next_obs, next_action) if nets.constrained else None
        q = nets.q(nets.critic, obs, action)
        cost_q = nets.q(nets.cost_critic, obs, action) if nets.constrained else None
        actor_terms = {}
        if actor_due:
            if objective.stochastic:
                pi_action, log_prob = nets.sample(nets.actor, obs, self._noise(action))
            else:
                pi_action, log_prob = nets.action(nets.actor, obs), None
            actor_terms = dict(actor_q=nets.q(nets.critic.detach(), obs, pi_action), actor_log_prob=log_prob,
                               actor_cost_q=nets.q(nets.cost_critic.detach(), obs, pi_action)
                               if nets.constrained else None)
        out = objective.losses(q=q, next_q=next_q, reward=reward, terminated=terminated, seed_dims=1,
                               next_log_prob=next_log_prob, cost_q=cost_q, next_cost_q=next_cost_q, cost=cost,
                               lam=self.lam, **actor_terms)
        losses = {"critic": out["loss_qvalue"]}
        if nets.constrained:
            losses["cost_critic"] = out["loss_cost_qvalue"]
        if actor_due:
            losses["actor"] = out["loss_actor"]
        trained = nets.trained()
        for name in losses:
            trained[name].grad = None
        torch.stack(list(losses.values())).sum().backward()
        finite = torch.isfinite(torch.stack(list(losses.values()))).all(0)
        self.bad |= ~finite
        active = self.live & ~self.bad  # masked on the device: no read back per step
        for name in losses:  # a frozen or failed seed's gradient may not be finite: zeroed
            trained[name].grad = torch.where(active.view(-1, 1), trained[name].grad, 0.0)
            self.optimizers[name].step(active)
        if actor_due:
            nets.soft_update(cfg.polyak, list(nets.targets()))
        with torch.no_grad():
            self.counts["critic"] += 1
            self.sums["Loss/Loss_reward_critic"] += out["loss_qvalue"].double()
            self.sums["Value/reward_critic"] += q.mean((1, 2)).double()
            if nets.constrained:
                self.sums["Loss/Loss_cost_critic"] += out["loss_cost_qvalue"].double()
                self.sums["Value/cost_critic"] += cost_q.mean((1, 2)).double()
            if actor_due:
                self.counts["actor"] += 1
                self.sums["Loss/Loss_pi"] += out["loss_actor"].double()

    # ------------------------------------------------------------------ epochs
    def _rows_and_moments(self) -> dict[str, Any]:
        nets = self.nets
        rows = {**{name: t.detach().clone() for name, t in nets.trained().items()},
                **{"target_" + name: t.clone() for name, t in nets.targets().items()}}
        moments = {name: opt.state_dict() for name, opt in self.optimizers.items()}
        return {"rows": rows, "moments": moments}

    @torch.no_grad()
    def _restore_seeds(self, seeds: Tensor) -> None:
        """Put the rows and Adam moments of the seeds where ``seeds`` is true back to the epoch's start."""
        nets, saved = self.nets, self.snapshot
        seeds = seeds.to(self.device)
        current = {**nets.trained(), **{"target_" + n: t for n, t in nets.targets().items()}}
        for name, tensor in current.items():
            tensor.copy_(torch.where(seeds.view(-1, 1), saved["rows"][name], tensor))
        for name, opt in self.optimizers.items():
            opt.restore_seeds(seeds, saved["moments"][name])

    def _train_epoch(self) -> dict[str, float]:
        """The shared epoch (collection with the gradient steps inside it); the update time is moved from the
        rows' ``Time/Rollout`` to ``Time/Update``."""
        self._steps_in_epoch = 0
        metrics = super()._train_epoch()
        for row in [run.last_row for run in self.runs if run.last_row] + [metrics]:
            if row.get("Train/Epoch", self.epoch) == self.epoch and "Time/Rollout" in row:
                row["Time/Rollout"] -= self.update_seconds
                row["Time/Update"] += self.update_seconds
        self._new_epoch_state()
        return metrics

    def _learn(self, batch: TensorDictBase) -> tuple[list[dict[str, float]], list[bool]]:
        """Freeze the seeds whose steps failed (back to the epoch's start), move the multipliers, build the rows."""
        diverged = self.bad.cpu() & self.alive
        self._restore_seeds(diverged)
        lagrange = [float(m.update(run.last_mean_cost) if run.alive else m.value)
                    for m, run in zip(self.multipliers, self.runs)]
        critic, actor = max(self.counts["critic"], 1), max(self.counts["actor"], 1)
        sums = torch.stack([self.sums[name] for name in _METRICS]).tolist()  # the epoch's one read of them
        means = {name: [value / (actor if name == "Loss/Loss_pi" else critic) for value in row]
                 for name, row in zip(_METRICS, sums)}
        rows = [{"Train/LagrangeMultiplier": lam, "Train/LR": self.cfg.actor_lr,
                 "Train/GradientSteps": self.gradient_steps, **{name: means[name][i] for name in _METRICS}}
                for i, lam in enumerate(lagrange)]
        return rows, diverged.tolist()

    def _finite_seeds(self) -> Tensor:
        return torch.stack([torch.isfinite(t).all(1) for t in self.nets.trained().values()]).all(0).cpu()

    def _evaluate_seed(self, index: int) -> dict[str, float]:
        """Seed ``index``'s deterministic evaluation (its exported TorchRL actor), env seed + 10_000."""
        cfg, seed = self.cfg, self.seeds[index]
        actor = self.nets.export_seed(index)[0]
        return evaluate_policy(cfg.env_id, actor, cfg.eval_episodes,
                               seed=seeding.env_seed(seed, seeding.Purpose.EVALUATION), env_options=cfg.env_options)

    # ------------------------------------------------------------------ checkpoints
    def _seed_state(self, index: int) -> dict[str, Any]:
        """Seed ``index``'s networks (its :func:`make_off_policy_networks` modules' state dicts), targets and Adam
        rows, multiplier and generators; CPU tensors whatever ``cfg.device``."""
        actor, critics, costs = self.nets.export_seed(index)
        return {
            "networks": {"actor": actor.state_dict(), "critics": [c.state_dict() for c in critics],
                         "cost_critics": [c.state_dict() for c in costs]},
            "targets": {name: host_copy(t[index]) for name, t in self.nets.targets().items()},
            "optimizer": {name: _flat_adam_rows(opt.seed_state_dict(index)) for name, opt in self.optimizers.items()},
            "multiplier": self.multipliers[index].state_dict(),
            "action_rng": self.action_generators[index].get_state(),
            "replay_rng": self.replay_generators[index].get_state(),
            "update_rng": self.update_generators[index].get_state(),
        }

    @torch.no_grad()
    def _load_seed_state(self, index: int, entry: dict[str, Any]) -> None:
        actor, critics, costs = self.nets.export_seed(index)
        actor.load_state_dict(entry["networks"]["actor"])
        for modules, states in ((critics, entry["networks"]["critics"]), (costs, entry["networks"]["cost_critics"])):
            for module, state in zip(modules, states, strict=True):
                module.load_state_dict(state)
        self.nets.load_seed(index, actor, critics, costs)
        for name, target in self.nets.targets().items():
            target[index].copy_(entry["targets"][name])
        for name, opt in self.optimizers.items():
            saved = entry["optimizer"][name]
            opt.load_seed_state_dict(index, [{"step": saved["step"], "exp_avg": [saved["exp_avg"]],
                                              "exp_avg_sq": [saved["exp_avg_sq"]]}])
        self.multipliers[index].load_state_dict(entry["multiplier"])
        for generators, key in ((self.action_generators, "action_rng"), (self.replay_generators, "replay_rng"),
                                (self.update_generators, "update_rng")):
            generators[index].set_state(entry[key])

    def _run_state(self) -> dict[str, Any]:
        """The seeds' entries, the gradient-step count, and the replay buffers' state (flushed to their memory
        maps in the run directory: :meth:`SeedReplay.checkpoint`)."""
        return {**super()._run_state(), "off_policy": {"gradient_steps": self.gradient_steps,
                                                       "replay": self.replay.checkpoint(self.epoch)}}

    def save_checkpoint(self, path=None):
        saved = super().save_checkpoint(path)
        self.replay.commit()  # the checkpoint is on disk: its undo files take over, older ones go
        return saved

    def _load_run_state(self, state: dict[str, Any]) -> None:
        super()._load_run_state(state)
        self.gradient_steps = int(state["off_policy"]["gradient_steps"])
        self.replay.load(state["off_policy"]["replay"])
