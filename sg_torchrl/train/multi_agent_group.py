"""The multi-agent training engine: S runs of MAPPO, HAPPO, MAPPO-Lag or MACPO in one process, S >= 1.

``sg-train --algo mappo_lag --seeds 0 1 2`` trains S seeds side by side (:class:`MultiAgentGroupTrainer`),
each exactly as the group of that seed alone, which is its single-seed run: ``sg-train --algo mappo_lag
--seed s`` is the same class with S = 1, in a single run's layout (the config picks it:
:func:`~sg_torchrl.train.seed_runs.run_layout`). Per seed:

* **simulators**: one batched env of ``S * num_envs`` simulators, seed ``s``'s the ``s``-th block of
  ``num_envs``, seeded as a ``num_envs``-simulator env with seed ``s`` (``sg_torchrl.make(...,
  seed=[s0, s1, ...])``), collected at once by one :class:`~sg_torchrl.collectors.RolloutCollector`;
* **team**: per seed its own :class:`~sg_torchrl.train.multi_agent.MultiAgentTeam` (networks, both
  GAEs), built by :meth:`~sg_torchrl.train.multi_agent.MultiAgentTeam.build` after ``torch.manual_seed(s)``
  (:func:`~sg_torchrl.seeding.seed_torch`);
* **stacked networks**: the teams' parameters then move into ``(S, A, ...)`` tensors, one per layer
  (:class:`~sg_torchrl.modules.stacked_multi_agent.StackedMultiAgentNetworks`, :attr:`networks`); each
  team's parameters are views of its rows, so its checkpoint entry and evaluation work on the stack;
* **observation normalisers**: one row of running statistics per seed for ``("agents",
  "observation")`` (per agent and feature) and ``"state"`` (``RunningObservationNorm(groups=S)``);
* **action noise**: one actor call per collection step for every seed
  (:class:`~sg_torchrl.modules.stacked_multi_agent.StackedMultiAgentPolicy`), seed ``s``'s noise
  from a ``torch.Generator`` of its own started at the state its global RNG has once its team is
  built, drawing what its single-seed actor drew from the global RNG. Nothing else in a multi-agent
  run draws random numbers from the global RNG (the simulators and the rounds use generators of
  their own, the evaluation is deterministic);
* **update**: per live seed its GAEs on its block of the batch, then one round for every live seed
  (:attr:`round`, built by the algorithm's round class for all seeds, ``for_seeds``; each seed's agent
  orders and minibatch shuffles from its own generator, seeded as its single-seed run seeds it).
  At each stage the agent of every seed is updated in one call
  (:class:`~sg_torchrl.train.multi_agent_round.SeedBatchedRound`: MAPPO, HAPPO and MAPPO-Lag's clipped-PPO
  epochs, MACPO's stacked CPO step and critic epochs).

The S = 1 run is the same code as a group's, and every operation of the seed-batched round rounds a row
as it rounds it alone (``addmm`` per row, per-seed reductions), so seed ``s`` of a group is its
single-seed run bit for bit (``tests/test_multi_agent_group.py``). One caveat: a reduction over more than
32,768 elements of a row (a batch past that many samples per seed) may be split across threads
differently for different S, and a seed then follows its single-seed run to float rounding.

**Device** (``--device``, :mod:`sg_torchrl.train.devices`). Each team is built on the CPU (from its seed's
global RNG, so the initial numbers are the same on every device) and moved to ``cfg.device`` before it is
stacked: the stacks, the rounds' Adam moments, step counts, PopArt statistics and multipliers, both GAEs,
the epoch's batch (one copy per epoch) and every update step live there. The simulators, the observation
normalisers (they run in the env's transform during collection) and every generator stay on the host:
the policy copies each step's observation and noise to the device and its outputs back once, and the
rounds move each pass's minibatch order once. A round reads back to the host once per pass (which seeds
are still active) and once per stage (its metrics), never per minibatch. Checkpoints hold CPU tensors, so a
run continues on another device.

Layout, logs, summaries, ``--resume`` / ``--overwrite`` and divergence (a seed whose parameters or
update turn non-finite is put back to its parameters before that update and frozen; its simulators
idle with zero actions; the others go on) are the engine's
(:class:`~sg_torchrl.train.trainer.SeedGroupTrainer`). A seed's checkpoint entry under ``"seeds"``
(:func:`~sg_torchrl.train.seed_runs.seed_entry`) holds its single-seed run's algorithm entries under the
same names (``"networks"``, ``"update"``, ``"obs_norms"`` as ungrouped normalisers' state dicts,
``"torch_rng"``) and its own record. A single run's checkpoint of the trainer this engine replaced (those
entries at its top level, no ``"seeds"``) is read as the engine's (:func:`team_checkpoint_as_group`).
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor
from torchrl.envs import Compose, EnvBase, TransformedEnv

import sg_torchrl
from sg_torchrl import seeding
from sg_torchrl.collectors import EpisodeStats, RolloutCollector
from sg_torchrl.envs.multi_agent import GROUP
from sg_torchrl.modules.stacked_multi_agent import StackedMultiAgentNetworks, StackedMultiAgentPolicy
from sg_torchrl.train.checkpoint import host_copy
from sg_torchrl.train.config import TrainConfig
from sg_torchrl.train.devices import training_device
from sg_torchrl.train.evaluate import evaluate_policy
from sg_torchrl.train.multi_agent import MULTI_AGENT_ALGORITHMS, MultiAgentTeam, observation_norms
from sg_torchrl.train.seed_runs import SeedRun
from sg_torchrl.train.trainer import SeedGroupTrainer

__all__ = ["MultiAgentGroupTrainer", "team_checkpoint_as_group"]


class MultiAgentGroupTrainer(SeedGroupTrainer):
    """Build and run a multi-agent algorithm: a seed group (``cfg.seeds``) or one run (``cfg.seed``).

    See the module docstring; a one-seed run's one team is ``teams[0]``.

    Attributes: ``teams`` (one :class:`~sg_torchrl.train.multi_agent.MultiAgentTeam` per seed),
    ``networks`` (their parameters stacked), ``round`` (every seed's round state), ``obs_norms`` (grouped normalisers, a row per seed),
    ``policy`` (every seed's actor in one call, with each seed's noise generator), ``collector``,
    ``env`` / ``base_env``, ``runs``.

    Args:
        cfg: the run's config (a multi-agent ``algo``; ``seeds`` for a group, else ``seed``; ``num_envs``,
            ``steps_per_epoch``, ``total_steps`` per seed).
        checkpoint: a checkpoint of this trainer (:meth:`load_checkpoint`) to continue from; for one run
            also one of the single-seed trainer this engine replaced (:func:`team_checkpoint_as_group`).

    Raises:
        ValueError: not a multi-agent algorithm.
    """

    def __init__(self, cfg: TrainConfig, checkpoint: dict[str, Any] | None = None) -> None:
        if not cfg.multi_agent:
            raise ValueError(f"{type(self).__name__} trains the multi-agent algorithms, not {cfg.algo!r} "
                             f"(trainer_class(cfg) picks the trainer of a config)")
        self.device = training_device(cfg)  # refuses a device this machine lacks before anything is built
        super().__init__(cfg)
        self.algorithm = MULTI_AGENT_ALGORITHMS[cfg.algo]
        self.title = self.algorithm.title
        groups = len(self.seeds)
        self.base_env = sg_torchrl.make(cfg.env_id, num_envs=groups * cfg.num_envs,
                                        seed=[seeding.env_seed(s, seeding.Purpose.SIMULATORS) for s in self.seeds],
                                        **cfg.env_options)
        self.obs_norms = observation_norms(self.base_env, groups=groups) if cfg.normalize_obs else []
        self.env: EnvBase = TransformedEnv(self.base_env, Compose(*self.obs_norms)) if self.obs_norms else self.base_env
        self.runs = [SeedRun(seed, self._seed_config(seed),
                             stats=EpisodeStats(reward_key=("next", GROUP, "reward"), agent_dim=-2))
                     for seed in self.seeds]
        self.teams: list[MultiAgentTeam] = []
        generators = []
        for run in self.runs:  # each seed's team from torch.manual_seed(seed), as the group of that seed alone
            seeding.seed_torch(run.seed)
            team = MultiAgentTeam.build(self.base_env, run.cfg)
            # where that run's action noise starts: its global RNG's state once its team is built
            generators.append(torch.Generator().set_state(torch.get_rng_state()))
            self.teams.append(team.to(self.device))
        self.networks = StackedMultiAgentNetworks([team.networks for team in self.teams])
        self.round = self.algorithm.make_round(
            self.networks, cfg, [seeding.generator(run.seed, seeding.Purpose.MINIBATCHES) for run in self.runs])
        self.policy = StackedMultiAgentPolicy(self.networks, generators, cfg.num_envs)
        self.collector = RolloutCollector(self.env, self.policy, steps=cfg.steps_per_epoch // cfg.num_envs)
        self._start(checkpoint)

    # ------------------------------------------------------------------ seeds and epochs
    def _finite_seeds(self) -> Tensor:
        return self.networks.finite_seeds().cpu()

    def _learn(self, batch: TensorDictBase) -> tuple[list[dict[str, float] | None], list[bool]]:
        """Each live seed's GAEs on its block, then one round of every live seed.

        A seed whose networks or round state (optimiser moments, multipliers, value normalisers) turn
        non-finite is put back to its state before the round and flagged (:meth:`_train_epoch`
        freezes it).
        """
        batch = batch.to(self.device, non_blocking=True)  # the epoch's one copy to the networks' device
        blocks = [block if run.alive else None for run, block in zip(self.runs, batch.split(self.cfg.num_envs, 0))]
        before = {}
        for index, (team, block) in enumerate(zip(self.teams, blocks)):
            if block is not None:
                team.estimate_advantages(block)
                before[index] = copy.deepcopy(self._seed_update_state(index))
        outs = self.round.step_seeds(blocks, [run.last_mean_cost for run in self.runs])
        rows: list[dict[str, float] | None] = []
        diverged: list[bool] = []
        for index, out in enumerate(outs):
            bad = out is not None and not _finite(self._seed_update_state(index))
            if bad:
                self.teams[index].networks.load_state_dict(before[index]["networks"])
                self.round.load_seed_state_dict(index, before[index]["update"])
            rows.append(None if out is None else
                        {"Train/LagrangeMultiplier": out.pop("Train/LagrangeMultiplier"), "Train/LR": self.cfg.actor_lr,
                         **out})
            diverged.append(bad)
        return rows, diverged

    def _seed_update_state(self, index: int) -> dict[str, Any]:
        """Seed ``index``'s networks and round state dicts (what an update changes)."""
        return {"networks": self.teams[index].networks.state_dict(), "update": self.round.seed_state_dict(index)}

    # ------------------------------------------------------------------ evaluation
    def _evaluate_seed(self, index: int) -> dict[str, float]:
        """Seed ``index``'s deterministic evaluation: a CPU copy of its actor, its normaliser rows, env seed + 10_000."""
        cfg, seed = self.cfg, self.seeds[index]
        norms = [norm.group_copy(index) for norm in self.obs_norms]
        actor = copy.deepcopy(self.teams[index].networks.actor).to("cpu")
        return evaluate_policy(cfg.env_id, actor, cfg.eval_episodes,
                               seed=seeding.env_seed(seed, seeding.Purpose.EVALUATION), obs_norm=norms,
                               env_options=cfg.env_options)

    # ------------------------------------------------------------------ checkpoints
    def _single_run_checkpoint(self, checkpoint: dict[str, Any]) -> dict[str, Any]:
        """A single run's checkpoint, this engine's or the replaced trainer's (:func:`team_checkpoint_as_group`)."""
        return team_checkpoint_as_group(checkpoint)

    def _seed_state(self, index: int) -> dict[str, Any]:
        """Seed ``index``'s entries under the single-seed run's names: networks, round, normaliser rows, torch RNG;
        CPU tensors whatever ``cfg.device``."""
        return {
            "networks": host_copy(self.teams[index].networks.state_dict()),
            "update": host_copy(self.round.seed_state_dict(index)),
            "obs_norms": [norm.group_state_dict(index) for norm in self.obs_norms],
            "torch_rng": self.policy.generators[index].get_state(),
        }

    def _load_seed_state(self, index: int, entry: dict[str, Any]) -> None:
        self.teams[index].networks.load_state_dict(entry["networks"])
        self.round.load_seed_state_dict(index, entry["update"])
        for norm, state in zip(self.obs_norms, entry["obs_norms"], strict=True):
            norm.load_group_state_dict(index, state)
        self.policy.generators[index].set_state(entry["torch_rng"])


#: Entries of a single team's checkpoint (the replaced single-seed trainer's) that belong to its seed.
_TEAM_ENTRIES = ("networks", "update", "obs_norms", "stats", "last_mean_cost", "progress_row")


def team_checkpoint_as_group(checkpoint: dict[str, Any]) -> dict[str, Any]:
    """A single-seed multi-agent checkpoint in the one-seed group's form; a group's is returned as it is.

    The single-seed trainer this engine replaced kept one team's entries at the top level (``networks``,
    ``update``, ``obs_norms`` as ungrouped normalisers' state dicts, ``stats``, ``last_mean_cost``,
    ``progress_row``) and drew its action noise from the global torch RNG (``torch_rng``). The group keeps
    the same entries under ``"seeds"`` (one per seed, with the seed's ``torch_rng`` stream) and says so
    with ``"seed_group"``; the simulators, the collector's carry and the counters are the same. So the
    mapping moves those entries into the one seed's entry, and a resumed run continues bit for bit.
    """
    if "seeds" in checkpoint or "networks" not in checkpoint:
        return checkpoint
    seed = checkpoint["config"]["seed"]
    entry = {"seed": seed, **{name: checkpoint[name] for name in _TEAM_ENTRIES},
             "torch_rng": checkpoint["torch_rng"], "diverged": None}
    rest = {name: value for name, value in checkpoint.items() if name not in _TEAM_ENTRIES}
    return {**rest, "seeds": [entry], "seed_group": {"seeds": [seed]}}


def _tensors(value: Any) -> list[Tensor]:
    """Every tensor in ``value`` (nested dicts, lists, tuples)."""
    if isinstance(value, Tensor):
        return [value]
    if isinstance(value, dict):
        return [t for item in value.values() for t in _tensors(item)]
    if isinstance(value, (list, tuple)):
        return [t for item in value for t in _tensors(item)]
    return []


def _finite(value: Any) -> bool:
    """Whether every floating-point tensor in ``value`` (nested dicts, lists, tuples) is finite (one read per device)."""
    flags: dict[torch.device, list[Tensor]] = {}
    for tensor in _tensors(value):
        if tensor.is_floating_point():
            flags.setdefault(tensor.device, []).append(torch.isfinite(tensor).all())
    return all(bool(torch.stack(found).all()) for found in flags.values())
