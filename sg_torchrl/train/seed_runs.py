"""A seed's run in the training engine: its record, its epoch rows, logs and summary, and where its files go.

The engine (:class:`~sg_torchrl.train.trainer.SeedGroupTrainer`) trains S >= 1 seeds side by side; each
seed is a :class:`SeedRun` (config, run directory, episode statistics, :math:`J_c`, last row, logger,
divergence). Its ``progress.csv`` rows are :func:`epoch_row`'s, under SafePO's names; its logger is
:func:`open_run_logger`'s; its end of run is :func:`write_run_summary`.

**Layouts.** Where the runs write is a choice the config makes (:func:`run_layout`), not a trainer class:

* :class:`GroupLayout` (``cfg.seeds``, ``sg-train --seeds 0 1 2``): ``cfg.run_dir`` holds the group's
  ``config.json``, ``checkpoint.pt``, ``summary.json`` (every seed's summary, their mean, the diverged
  seeds) and ``curves.png`` (every seed's curves and their mean), and one ``seed-XXX/`` directory per seed
  with a single run's files (:meth:`TrainConfig.for_seed`);
* :class:`SingleRunLayout` (``cfg.seed`` alone, ``sg-train --seed s``): ``cfg.run_dir`` itself is the
  run's directory with a single run's files (``config.json``, ``progress.csv``, ``csv/``, ``wandb/``,
  ``summary.json``, ``curves.png``, ``checkpoint.pt``); no ``seed-XXX/`` level, no group summary or figure.

Either way the engine trains the same: a ``--seed s`` run is seed ``s`` of ``--seeds s`` exactly (the same
progress rows but their ``Time/*`` columns, the same parameters and checkpoint entry). Both write a
group's checkpoint (one entry per seed under ``"seeds"``, a ``"seed_group"`` entry naming the seeds, which
also tells a single run's checkpoint from one of the retired ``LossModule`` trainer); :func:`seed_entry`
reads a seed's entry out of either, with its single-seed config.
"""

from __future__ import annotations

import abc
import json
from dataclasses import dataclass, field
from typing import Any

from tensordict import TensorDictBase

from sg_torchrl.collectors import EpisodeStats
from sg_torchrl.train.config import TrainConfig
from sg_torchrl.train.logging import RunLogger
from sg_torchrl.train.plot import plot_curves, plot_group_curves
from sg_torchrl.train.writes import write_atomic

__all__ = [
    "GroupLayout", "RunLayout", "SeedRun", "SingleRunLayout", "epoch_row", "finished_episode_cost", "mean_row",
    "open_run_logger", "run_layout", "seed_entry", "write_run_summary",
]


@dataclass
class SeedRun:
    """One seed's own record: its config and directory, episode statistics, row, logger, fate."""

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


def finished_episode_cost(stats: EpisodeStats, batch: TensorDictBase, previous: float) -> float:
    """Feed ``batch`` to ``stats``; the mean cost of the episodes it finished, ``previous`` when none did.

    SafePO's :math:`J_c`, which the multiplier follows (kept from the last epoch that finished an episode).
    """
    stats.update(batch)
    finished = stats.pop_finished()
    return finished["cost"].mean().item() if finished["cost"].numel() else previous


def epoch_row(
    stats: EpisodeStats, last_mean_cost: float, epoch: int, total_steps: int, learned: dict[str, float], *,
    rollout_time: float, update_time: float, total_time: float, fps: float,
) -> dict[str, float]:
    """One epoch's ``progress.csv`` row under SafePO's names, in the order every run logs them.

    Episode metrics are 50-episode moving averages of ``stats`` (NaN before the first finished episode);
    ``learned`` holds the multiplier, learning rate and update metrics of the epoch.
    """
    window = stats.window(50)
    return {
        "Metrics/EpRet": window.get("return", float("nan")),
        "Metrics/EpCost": window.get("cost", float("nan")),
        "Metrics/EpLen": window.get("length", float("nan")),
        "Metrics/EpochEpCost": last_mean_cost,
        "Train/Epoch": epoch,
        "Train/TotalSteps": total_steps,
        **learned,
        "Time/Rollout": rollout_time,
        "Time/Update": update_time,
        "Time/Total": total_time,
        "Time/FPS": fps,
    }


def open_run_logger(cfg: TrainConfig, checkpoint: dict[str, Any] | None, progress_row: dict[str, float] | None
                    ) -> RunLogger:
    """The :class:`RunLogger` of the run ``cfg`` describes (its ``run_dir`` and ``seed``).

    With a ``checkpoint`` (a resumed run) ``progress.csv`` is cut back to the checkpoint's epoch and
    ``progress_row``, the checkpointed epoch's row, is appended when the file lacks it.
    """
    return RunLogger(
        cfg.run_dir, exp_name=f"{cfg.algo}-{cfg.env_id}-s{cfg.seed}", wandb_mode=cfg.wandb, config=cfg.to_dict(),
        resume_epoch=None if checkpoint is None else checkpoint["epoch"],
        resume_row=None if checkpoint is None else progress_row,
    )


def write_run_summary(
    cfg: TrainConfig, logger: RunLogger, stats: EpisodeStats, evaluation: dict[str, float] | None, *, title: str,
    total_steps: int, train_seconds: float, extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """End one run: log ``evaluation``, write ``summary.json`` and ``curves.png`` in ``cfg.run_dir``, close the logger.

    The summary holds the mean return and cost of the last 10 training episodes, the evaluation and
    ``extra`` (a seed group's note that a seed diverged); returns it (without the totals the file adds).
    """
    last10 = stats.window(10)
    summary: dict[str, Any] = {
        "Final/EpRetLast10": last10.get("return", float("nan")),
        "Final/EpCostLast10": last10.get("cost", float("nan")),
    }
    if evaluation:
        logger.log({**evaluation, "Train/TotalSteps": total_steps}, step=total_steps)
        summary.update(evaluation)
    summary.update(extra or {})
    write_atomic(cfg.run_dir / "summary.json", json.dumps({**summary, "Train/TotalSteps": total_steps,
                                                            "Time/Total": train_seconds}, indent=2))
    history = [row for row in logger.history() if row.get("Metrics/EpRet") == row.get("Metrics/EpRet")]
    plot_curves(history, cfg.run_dir / "curves.png", cost_limit=cfg.cost_limit,
                title=f"{title} on {cfg.env_id} (seed {cfg.seed})")
    logger.close()
    return summary


class RunLayout(abc.ABC):
    """Where the engine's runs write and how their end is reported: :class:`GroupLayout` or :class:`SingleRunLayout`.

    What the engine asks of it: the seeds to train (:attr:`seeds`), each seed's own config
    (:meth:`seed_config`, whose ``run_dir`` receives its logs), the end of the run once every seed has
    written its summary (:meth:`finish`).
    """

    def __init__(self, cfg: TrainConfig) -> None:
        self.cfg = cfg
        #: The seeds the engine trains, in the order of its runs and of the checkpoint's entries.
        self.seeds: list[int] = []

    @abc.abstractmethod
    def seed_config(self, seed: int) -> TrainConfig:
        """Seed ``seed``'s own run config (its :attr:`SeedRun.cfg`)."""

    @abc.abstractmethod
    def finish(self, runs: list[SeedRun], summaries: list[dict[str, Any]], *, title: str, total_steps: int,
               train_seconds: float) -> dict[str, Any]:
        """The end of the run, after each seed's ``summary.json`` (``summaries``, in the order of ``runs``);
        returns what ``sg-train`` prints."""


class GroupLayout(RunLayout):
    """A seed group (``cfg.seeds``): the group's files in ``cfg.run_dir``, each seed's in its ``seed-XXX/``."""

    def __init__(self, cfg: TrainConfig) -> None:
        if not cfg.group:
            raise ValueError(f"a seed group's layout needs cfg.seeds (cfg.seed {cfg.seed} alone is a single run)")
        super().__init__(cfg)
        self.seeds = list(cfg.seeds)

    def seed_config(self, seed: int) -> TrainConfig:
        """The group's ``seed-XXX/`` (:meth:`TrainConfig.for_seed`)."""
        return self.cfg.for_seed(seed)

    def finish(self, runs: list[SeedRun], summaries: list[dict[str, Any]], *, title: str, total_steps: int,
               train_seconds: float) -> dict[str, Any]:
        """The group's ``summary.json`` and ``curves.png``.

        Returns the live seeds' mean summary, and every seed's summary and last row under
        ``seed-XXX/<name>`` (what ``sg-train`` prints).
        """
        cfg = self.cfg
        mean = mean_row([summary for run, summary in zip(runs, summaries) if run.alive])
        write_atomic(cfg.run_dir / "summary.json", json.dumps(
            {"seeds": {str(run.seed): summary for run, summary in zip(runs, summaries)}, "mean": mean,
             "diverged": [run.seed for run in runs if not run.alive], "Train/TotalSteps": total_steps,
             "Time/Total": train_seconds}, indent=2))
        # The group's figure: every seed's curves and their mean in one picture (seed-XXX/ holds each alone).
        plot_group_curves({run.seed: run.logger.history() for run in runs}, cfg.run_dir / "curves.png",
                          cost_limit=cfg.cost_limit,
                          title=f"{title} on {cfg.env_id} (seeds {' '.join(map(str, self.seeds))})")
        out: dict[str, Any] = dict(mean)
        for run, summary in zip(runs, summaries):
            prefix = f"seed-{run.seed:03d}/"
            out.update({prefix + name: value for name, value in {**(run.last_row or {}), **summary}.items()})
        return out


class SingleRunLayout(RunLayout):
    """One run (``cfg.seed``; no ``cfg.seeds``): ``cfg.run_dir`` itself is its directory, with a single run's files.

    The engine trains it as a group of that one seed; only where things are written differs. A diverged run
    (its parameters or update turned non-finite) ends early, reported on stderr and in ``summary.json``
    (``Diverged``).
    """

    def __init__(self, cfg: TrainConfig) -> None:
        if cfg.group:
            raise ValueError(f"a single run's layout takes cfg.seed alone; the seeds {cfg.seeds} are a group's "
                             f"(GroupLayout)")
        super().__init__(cfg)
        self.seeds = [cfg.seed]

    def seed_config(self, seed: int) -> TrainConfig:
        """The run's config itself: no ``seed-XXX/`` level."""
        return self.cfg

    def finish(self, runs: list[SeedRun], summaries: list[dict[str, Any]], *, title: str, total_steps: int,
               train_seconds: float) -> dict[str, Any]:
        """The run's summary (with ``Diverged``, ``DivergedEpoch``, ``DivergedReason`` when it diverged); its
        ``summary.json`` and ``curves.png`` are all the run writes at its end."""
        return summaries[0]


def run_layout(cfg: TrainConfig) -> RunLayout:
    """The layout ``cfg`` asks for: :class:`GroupLayout` with ``cfg.seeds``, :class:`SingleRunLayout` without."""
    return GroupLayout(cfg) if cfg.group else SingleRunLayout(cfg)


def mean_row(rows: list[dict[str, Any]]) -> dict[str, float]:
    """The mean over ``rows`` of each numeric entry they all hold (an empty dict for none)."""
    if not rows:
        return {}
    return {name: sum(row[name] for row in rows) / len(rows) for name, value in rows[0].items()
            if isinstance(value, (int, float)) and not isinstance(value, bool) and all(name in row for row in rows)}


def seed_entry(checkpoint: dict[str, Any], seed: int) -> dict[str, Any]:
    """Seed ``seed``'s entry of an engine checkpoint (``SeedGroupTrainer.load_checkpoint(path)``), with its config:
    a group's (one entry per seed) or a single run's (one entry).

    The entry holds what that seed's run needs to be used alone: ``"config"`` (its single-seed config
    as a dict: :meth:`RunLayout.seed_config` of the checkpoint's layout), its episode statistics,
    ``"last_mean_cost"``, ``"progress_row"`` and ``"diverged"``, and its algorithm state. On-policy
    single agent (:class:`~sg_torchrl.train.seed_group.OnPolicyGroupTrainer`):
    ``"networks"`` (``actor`` / ``critic`` / ``cost_critic`` state dicts of the modules
    ``make_actor_critics`` builds), ``"obs_norm"`` (an ungrouped ``RunningObservationNorm`` state dict,
    or ``None``), ``"multiplier"``, ``"optimizer"`` (its Adam rows of the flat actor and critic buffers)
    and its generators' states. Multi agent
    (:class:`~sg_torchrl.train.multi_agent_group.MultiAgentGroupTrainer`): ``"networks"`` (the team's),
    ``"update"`` (the round's state dict), ``"obs_norms"`` and ``"torch_rng"`` (its action-noise stream).

    Raises:
        KeyError: the checkpoint is not the engine's, or does not hold ``seed``.
    """
    entries = checkpoint.get("seeds") or []
    for entry in entries:
        if entry["seed"] == seed:
            cfg = TrainConfig.from_saved(checkpoint["config"])
            return {**entry, "config": run_layout(cfg).seed_config(seed).to_dict()}
    raise KeyError(f"seed {seed} is not in this checkpoint (seeds: {[entry['seed'] for entry in entries]})")
