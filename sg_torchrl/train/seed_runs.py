"""What every seed group's trainer shares: S runs' records, their epochs, logs, summaries and checkpoint entries.

A seed group (``sg-train --seeds``) trains S runs side by side in one process: one batched env of
``S * num_envs`` simulators (seed ``s``'s the ``s``-th block), collected at once. How the seeds'
networks are held and updated is the algorithm family's business:

* single agent (:class:`~sg_torchrl.train.seed_group.GroupTrainer`): networks stacked along a
  leading seed dimension, one group update for all seeds;
* multi agent (:class:`~sg_torchrl.train.multi_agent_group.MultiAgentGroupTrainer`): one team of
  networks and one round per seed, the rounds run one after another.

Everything else is the same for both and lives here, in :class:`SeedGroupTrainer`: each seed's
:class:`SeedRun` record (config, run directory, episode statistics, :math:`J_c`, last row, logger,
divergence), freezing a seed whose parameters or update turn non-finite (the others go on), the epoch
(collect once, each seed's finished-episode cost from its block, :meth:`~SeedGroupTrainer._learn`,
each seed's ``progress.csv`` row under the single-seed names), each seed's logs, the end of the run
(each seed's evaluation, ``summary.json`` and ``curves.png`` in its ``seed-XXX/``; the group's
``summary.json`` and ``curves.png``), and the per-seed part of the checkpoint entries (episode
statistics, :math:`J_c`, the last row, divergence; the seed list is checked on load).

Where the runs write is a layout decided by two hooks, :meth:`~SeedGroupTrainer._run_seeds` and
:meth:`~SeedGroupTrainer._seed_config` (default: the group's ``seed-XXX/`` directories), and :meth:`finish`:
:class:`SingleSeedLayout` overrides them to run one seed in the single-seed layout. ``sg-train --seed s``
is that layout over either family's group engine:
:class:`~sg_torchrl.train.seed_group.SingleSeedGroupTrainer` (single agent, fused engine) and
:class:`~sg_torchrl.train.multi_agent_group.SingleSeedMultiAgentTrainer` (multi agent).

A subclass builds its env, :attr:`~SeedGroupTrainer.policy` (with a ``frozen`` attribute: ``None``
or an ``(S,)`` bool of the seeds acting with zeros), :attr:`~SeedGroupTrainer.collector` and
:attr:`~SeedGroupTrainer.runs`, then calls ``_start(checkpoint)``; it implements :meth:`_learn`,
:meth:`_finite_seeds`, :meth:`_evaluate_seed` and :meth:`_seed_state` / :meth:`_load_seed_state`.
"""

from __future__ import annotations

import abc
import json
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor
from tqdm.auto import tqdm

from sg_torchrl.collectors import EpisodeStats, RolloutCollector
from sg_torchrl.train.config import TrainConfig
from sg_torchrl.train.logging import RunLogger
from sg_torchrl.train.plot import plot_group_curves
from sg_torchrl.train.trainer import EpochTrainer, epoch_row, finished_episode_cost, open_run_logger, write_run_summary
from sg_torchrl.train.writes import make_dirs, write_atomic

__all__ = ["SeedGroupTrainer", "SeedRun", "SingleSeedLayout", "mean_row", "seed_entry"]


@dataclass
class SeedRun:
    """One seed's own record in a group: its config and directory, episode statistics, row, logger, fate."""

    seed: int
    cfg: TrainConfig
    stats: EpisodeStats = field(default_factory=EpisodeStats)
    last_mean_cost: float = 0.0
    last_row: dict[str, float] | None = None
    logger: RunLogger | None = None
    #: ``None`` while training; ``{"epoch": k, "reason": ...}`` once frozen.
    diverged: dict[str, Any] | None = None

    @property
    def alive(self) -> bool:
        return self.diverged is None


class SeedGroupTrainer(EpochTrainer):
    """The loop of a seed group (``cfg.seeds``); see the module docstring for what a subclass supplies.

    Raises:
        ValueError: ``cfg`` is not a seed group (no ``seeds``).
    """

    runs: list[SeedRun]
    collector: RolloutCollector
    policy: Any  # a TensorDict policy with a ``frozen`` attribute (``None`` or ``(S,)`` bool)

    def __init__(self, cfg: TrainConfig) -> None:
        seeds = self._run_seeds(cfg)
        super().__init__(cfg)
        self.seeds = seeds

    # ------------------------------------------------------------------ layout
    def _run_seeds(self, cfg: TrainConfig) -> list[int]:
        """The seeds this trainer runs: the group's ``cfg.seeds`` (a layout hook, as :meth:`_seed_config`)."""
        if not cfg.group:
            raise ValueError(f"{type(self).__name__} trains a seed group: give cfg.seeds")
        return list(cfg.seeds)

    def _seed_config(self, seed: int) -> TrainConfig:
        """Seed ``seed``'s own run (its :attr:`SeedRun.cfg`, whose ``run_dir`` receives its logs): the group's
        ``seed-XXX/`` (:meth:`TrainConfig.for_seed`). A single-seed layout returns the config itself."""
        return self.cfg.for_seed(seed)

    # ------------------------------------------------------------------ hooks
    @abc.abstractmethod
    def _learn(self, batch: TensorDictBase) -> tuple[list[dict[str, float] | None], list[bool]]:
        """Update every live seed from the ``(S * N, T)`` batch.

        Returns each seed's learned metrics (multiplier, learning rate, update metrics; anything for a
        frozen seed, whose row is not built) and whether its update turned non-finite (it is frozen).
        """

    @abc.abstractmethod
    def _finite_seeds(self) -> Tensor:
        """``(S,)`` bool: which seeds' parameters are all finite."""

    @abc.abstractmethod
    def _evaluate_seed(self, index: int) -> dict[str, float]:
        """Seed ``index``'s deterministic evaluation, as its single-seed run evaluates (env seed + 10_000)."""

    @abc.abstractmethod
    def _seed_state(self, index: int) -> dict[str, Any]:
        """Seed ``index``'s algorithm entries of the checkpoint (networks, optimisers, normalisers, streams)."""

    @abc.abstractmethod
    def _load_seed_state(self, index: int, entry: dict[str, Any]) -> None:
        """Restore what :meth:`_seed_state` saved for seed ``index``."""

    # ------------------------------------------------------------------ seeds
    @property
    def alive(self) -> Tensor:
        """``(S,)`` bool: the seeds still training."""
        return torch.tensor([run.alive for run in self.runs])

    def _sync_frozen(self) -> None:
        """Tell the policy which seeds act with zeros (``None`` while every seed trains)."""
        alive = self.alive
        self.policy.frozen = None if bool(alive.all()) else ~alive

    def _freeze(self, flags: list[bool], epoch: int, reason: str) -> None:
        """Freeze the seeds flagged, diverged in ``epoch``: no more updates, multiplier or logs; say so on stderr."""
        for run, flag in zip(self.runs, flags):
            if flag and run.alive:
                run.diverged = {"epoch": epoch, "reason": reason}
                others = [str(r.seed) for r in self.runs if r.alive]
                tqdm.write(f"sg-train: seed {run.seed} diverged in epoch {epoch} ({reason}); it is frozen, "
                           f"{'seeds ' + ', '.join(others) + ' go on' if others else 'no seed is left'}",
                           file=sys.stderr)
        self._sync_frozen()

    def _freeze_nonfinite(self) -> None:
        """Freeze the live seeds whose parameters are not finite (set from outside, or loaded so)."""
        bad = (self.alive & ~self._finite_seeds()).tolist()
        if any(bad):
            self._freeze(bad, self.epoch + 1, "non-finite parameters at the start of the epoch")

    def _exhausted(self) -> bool:
        """Freeze seeds with non-finite parameters first; then whether every seed is frozen."""
        self._freeze_nonfinite()
        return not any(run.alive for run in self.runs)

    # ------------------------------------------------------------------ epochs
    def _train_epoch(self) -> dict[str, float]:
        """Collect every seed's simulators at once, update every live seed, build each seed's row.

        Returns the mean of the live seeds' rows (the progress bar's figures); each seed's own row,
        under the single-seed names, is in its :attr:`SeedRun.last_row`, logged by :meth:`_log_epoch`.
        """
        cfg = self.cfg
        if self._exhausted():
            raise RuntimeError("every seed of the group has diverged: nothing left to train")
        start = time.perf_counter()
        batch = self.collector.collect()
        rollout_time = time.perf_counter() - start
        training = [run for run in self.runs if run.alive]
        for run, block in zip(self.runs, batch.split(cfg.num_envs, dim=0)):
            if run.alive:
                run.last_mean_cost = finished_episode_cost(run.stats, block, run.last_mean_cost)
        update_start = time.perf_counter()
        learned, diverged = self._learn(batch)
        update_time = time.perf_counter() - update_start
        self.epoch += 1
        steps = batch.numel() // len(self.seeds)
        self.total_steps += steps
        epoch_time = time.perf_counter() - start
        self.train_seconds += epoch_time
        for run, row in zip(self.runs, learned):
            if run.alive:
                run.last_row = epoch_row(run.stats, run.last_mean_cost, self.epoch, self.total_steps, row,
                                         rollout_time=rollout_time, update_time=update_time,
                                         total_time=self.train_seconds, fps=steps / epoch_time)
        self._freeze(diverged, self.epoch, "its update turned non-finite; kept at its parameters before that update")
        return mean_row([run.last_row for run in training])

    # ------------------------------------------------------------------ logs
    def _open_logs(self, checkpoint: dict[str, Any] | None) -> None:
        """Each seed's directory: its single-seed ``config.json`` and its logger (cut back to the checkpoint)."""
        for run in self.runs:
            make_dirs(run.cfg.run_dir)
            run.cfg.save(run.cfg.run_dir / "config.json")
            run.logger = open_run_logger(run.cfg, checkpoint, run.last_row)

    def _log_epoch(self, metrics: dict[str, float]) -> None:
        """Each seed that trained this epoch logs its own row (a frozen seed's log ends with its last epoch)."""
        for run in self.runs:
            if run.last_row is not None and run.last_row["Train/Epoch"] == self.epoch:
                run.logger.log(run.last_row, step=self.total_steps)

    def finish(self) -> dict[str, float]:
        """Each seed's evaluation, summary and plot in its directory; the group's ``summary.json`` and ``curves.png``.

        Returns the live seeds' mean summary, and every seed's summary and last row under
        ``seed-XXX/<name>`` (what ``sg-train`` prints).
        """
        cfg = self.cfg
        summaries = {run.seed: self._finish_seed(index) for index, run in enumerate(self.runs)}
        mean = mean_row([s for run, s in zip(self.runs, summaries.values()) if run.alive])
        write_atomic(cfg.run_dir / "summary.json", json.dumps(
            {"seeds": {str(seed): summary for seed, summary in summaries.items()}, "mean": mean,
             "diverged": [run.seed for run in self.runs if not run.alive], "Train/TotalSteps": self.total_steps,
             "Time/Total": self.train_seconds}, indent=2))
        # The group's figure: every seed's curves and their mean in one picture (seed-XXX/ holds each alone).
        plot_group_curves({run.seed: run.logger.history() for run in self.runs}, cfg.run_dir / "curves.png",
                          cost_limit=cfg.cost_limit,
                          title=f"{self.title} on {cfg.env_id} (seeds {' '.join(map(str, self.seeds))})")
        out: dict[str, Any] = dict(mean)
        for run in self.runs:
            prefix = f"seed-{run.seed:03d}/"
            figures = {**(run.last_row or {}), **summaries[run.seed]}
            out.update({prefix + name: value for name, value in figures.items()})
        return out

    def _finish_seed(self, index: int) -> dict[str, Any]:
        """Seed ``index``'s end of run in its directory: evaluation (a live seed), ``summary.json`` (a frozen seed's
        with ``Diverged``, ``DivergedEpoch``, ``DivergedReason``), ``curves.png``; returns its summary."""
        run = self.runs[index]
        evaluation = self._evaluate_seed(index) if self.cfg.eval_episodes > 0 and run.alive else None
        extra = {} if run.alive else {"Diverged": True, "DivergedEpoch": run.diverged["epoch"],
                                      "DivergedReason": run.diverged["reason"]}
        steps = self.total_steps if run.alive else int((run.last_row or {}).get("Train/TotalSteps", 0))
        return write_run_summary(run.cfg, run.logger, run.stats, evaluation, title=self.title, total_steps=steps,
                                 train_seconds=self.train_seconds, extra=extra)

    # ------------------------------------------------------------------ checkpoints
    def _run_state(self) -> dict[str, Any]:
        """Every seed's entry under ``"seeds"``: its algorithm state (:meth:`_seed_state`) and its own record;
        ``"seed_group"`` marks a seed group's checkpoint."""
        entries = []
        for index, run in enumerate(self.runs):
            entries.append({
                "seed": run.seed,
                **self._seed_state(index),
                "stats": run.stats.state_dict(),
                "last_mean_cost": run.last_mean_cost,
                "progress_row": None if run.last_row is None else {k: float(v) for k, v in run.last_row.items()},
                "diverged": run.diverged,
            })
        return {"seeds": entries, "seed_group": {"seeds": list(self.seeds)}}

    @torch.no_grad()
    def _load_run_state(self, state: dict[str, Any]) -> None:
        """Restore every seed's entry (the checkpoint must hold this group's seeds, in its order)."""
        if "seed_group" not in state:
            raise ValueError("not a seed group's checkpoint (no 'seed_group' entry)")
        entries = state["seeds"]
        if [entry["seed"] for entry in entries] != self.seeds:
            raise ValueError(f"the checkpoint holds seeds {[e['seed'] for e in entries]}, this group {self.seeds}")
        for index, (run, entry) in enumerate(zip(self.runs, entries)):
            self._load_seed_state(index, entry)
            run.stats.load_state_dict(entry["stats"])
            run.last_mean_cost = entry["last_mean_cost"]
            run.last_row = entry["progress_row"]
            run.diverged = entry["diverged"]
        self._sync_frozen()


class SingleSeedLayout:
    """One run (``cfg.seed``; no ``cfg.seeds``) of a seed-group engine, in the single-seed layout: ``sg-train --seed s``.

    Mixed in before a :class:`SeedGroupTrainer` subclass (``class SingleSeedGroupTrainer(SingleSeedLayout,
    GroupTrainer)``), it runs that engine with S = 1, so the run is seed ``s`` of ``--seeds s`` exactly (the
    same progress rows but their ``Time/*`` columns, the same parameters and checkpoint entry). Only where
    things are written differs from a group of one: ``cfg.run_dir`` itself is the run's directory and holds
    what a single run writes there (``config.json``, ``progress.csv``, ``csv/``, ``wandb/``, ``summary.json``,
    ``curves.png``, ``checkpoint.pt``), with the same metric names; there is no ``seed-XXX/`` level and no
    group summary or group figure. The checkpoint is a group's with one entry under ``"seeds"``
    (:func:`seed_entry` reads it). A diverged run (its parameters or update turned non-finite) ends early,
    reported on stderr and in ``summary.json`` (``Diverged``).

    Raises:
        ValueError: ``cfg`` is a seed group (the group trainer trains those).
    """

    cfg: TrainConfig

    def _run_seeds(self, cfg: TrainConfig) -> list[int]:
        if cfg.group:
            group = next(c for c in type(self).__mro__
                         if issubclass(c, SeedGroupTrainer) and not issubclass(c, SingleSeedLayout))
            raise ValueError(f"{type(self).__name__} trains one seed (cfg.seed); the seed group {cfg.seeds} is "
                             f"{group.__name__}'s")
        return [cfg.seed]

    def _seed_config(self, seed: int) -> TrainConfig:
        return self.cfg  # the run's directory is the trainer's: no seed-XXX/ level

    @property
    def stats(self):
        """The run's episode statistics (its one seed's record)."""
        return self.runs[0].stats

    def finish(self) -> dict[str, float]:
        """The run's evaluation, ``summary.json`` and ``curves.png`` in its directory; returns its summary (with
        ``Diverged``, ``DivergedEpoch``, ``DivergedReason`` when it diverged)."""
        return self._finish_seed(0)


def mean_row(rows: list[dict[str, Any]]) -> dict[str, float]:
    """The mean over ``rows`` of each numeric entry they all hold (an empty dict for none)."""
    if not rows:
        return {}
    return {name: sum(row[name] for row in rows) / len(rows) for name, value in rows[0].items()
            if isinstance(value, (int, float)) and not isinstance(value, bool) and all(name in row for row in rows)}


def seed_entry(checkpoint: dict[str, Any], seed: int) -> dict[str, Any]:
    """Seed ``seed``'s entry of a group checkpoint (``EpochTrainer.load_checkpoint(path)``), with its config;
    also of a single-seed run's on a group engine (:class:`SingleSeedLayout`: one entry).

    The entry holds what that seed's run needs to be used alone: ``"config"`` (its single-seed config
    as a dict), its episode statistics, ``"last_mean_cost"``, ``"progress_row"`` and ``"diverged"``, and
    its algorithm state. Single agent (:class:`~sg_torchrl.train.seed_group.GroupTrainer`):
    ``"networks"`` (``actor`` / ``critic`` / ``cost_critic`` state dicts of the modules
    ``make_actor_critics`` builds), ``"obs_norm"`` (an ungrouped ``RunningObservationNorm`` state dict,
    or ``None``), ``"multiplier"``, ``"optimizer"`` (its Adam rows of the flat actor and critic buffers)
    and its generators' states. Multi agent
    (:class:`~sg_torchrl.train.multi_agent_group.MultiAgentGroupTrainer`): ``"networks"`` (the team's),
    ``"update"`` (the round's state dict), ``"obs_norms"`` and ``"torch_rng"`` (its action-noise stream).

    Raises:
        KeyError: the checkpoint is not a group's, or does not hold ``seed``.
    """
    entries = checkpoint.get("seeds") or []
    for entry in entries:
        if entry["seed"] == seed:
            cfg = TrainConfig.from_saved(checkpoint["config"])
            cfg = cfg.for_seed(seed) if cfg.group else cfg  # a single-seed run's config is its seed's
            return {**entry, "config": cfg.to_dict()}
    raise KeyError(f"seed {seed} is not in this checkpoint (seeds: {[entry['seed'] for entry in entries]})")
