"""The on-policy safe training loop behind ``sg-train``: :class:`EpochTrainer`, what every trainer shares.

Single-agent runs, one seed or a group, train on the seed-group engine
(:mod:`sg_torchrl.train.seed_group`), multi-agent runs in :mod:`sg_torchrl.train.multi_agent` and
:mod:`sg_torchrl.train.multi_agent_group`; :func:`sg_torchrl.train.trainer_class` picks the trainer.

One epoch (SafePO's loop, Safety-Gymnasium paper appendix):

1. collect ``steps_per_epoch`` transitions from ``num_envs`` batched simulators;
2. update the multiplier from the mean cost of the episodes finished in the epoch (before the
   policy update, as SafePO does; SafePO feeds a doubly smoothed 50-episode window mean instead,
   a quirk we do not reproduce);
3. reward and cost GAE, batch-level advantage normalisation;
4. the algorithm's update (:mod:`sg_torchrl.train.group_updates`): first-order minibatch passes with KL
   early stop, CUP's two stages, or a trust-region step of the actor followed by critic passes;
5. log SafePO's metrics, checkpoint.

Ctrl-C or ``SIGTERM`` stops a run at the end of the epoch under way, with a checkpoint
(:mod:`sg_torchrl.train.interrupt`).

Checkpoints hold everything that influences the future (networks, optimiser, scheduler, multiplier,
observation normaliser, simulator states and generators, the collector's carry, episode
statistics, torch RNG states), so ``--resume`` continues bit-identically. They are written in
:mod:`sg_torchrl.train.checkpoint`'s format (a sha256-checked header, a payload of tensors and plain
data that loads with ``weights_only=True``): loading one never runs code, and a damaged one is refused.

When checkpoints are written (:class:`CheckpointSchedule`): after the first epoch a process trains,
every ``checkpoint_every`` epochs, once ``checkpoint_minutes`` of wall time have passed since the
last one, after the run's last epoch, and on a stop request. A scheduled checkpoint is written
before the epoch's row reaches ``progress.csv``, so a row there always has its checkpoint or a
later one on disk when it was a checkpoint epoch. **The most a SIGKILL (or a power cut) can lose**
is the epoch under way plus the epochs finished since the last checkpoint, which are fewer than
``checkpoint_every`` (10) and all ended less than ``checkpoint_minutes`` (1) after that checkpoint:
with the paper's epochs (minutes each on a CPU) only the epoch under way. Once a process has
finished its first epoch there is always a checkpoint to resume. A checkpoint costs milliseconds
(a few hundred kB to a few MB).

A new run refuses a run directory that already holds a run (a checkpoint, ``progress.csv`` or
``summary.json``) unless ``cfg.overwrite`` asks to start over (which removes the old run's files):
re-running a command never deletes results silently.

:class:`EpochTrainer` is the loop every ``sg-train`` run goes through (the epoch counters, the
progress bar, the checkpoint schedule and files). Its one subclass,
:class:`~sg_torchrl.train.seed_runs.SeedGroupTrainer` (single agent, multi agent, and their one-seed
runs), trains S runs in that loop and hands each seed's row, logger and summary to the helpers here
(:func:`finished_episode_cost`, :func:`epoch_row`, :func:`open_run_logger`, :func:`write_run_summary`).
"""

from __future__ import annotations

import abc
import contextlib
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tqdm.auto import tqdm

from sg_torchrl import seeding
from sg_torchrl.collectors import EpisodeStats, RolloutCollector
from sg_torchrl.train import checkpoint as checkpoint_files
from sg_torchrl.train.checkpoint import CHECKPOINT_NAME, CheckpointError
from sg_torchrl.train.config import TrainConfig
from sg_torchrl.train.interrupt import StopRequests, TrainingInterrupted
from sg_torchrl.train.logging import RunLogger
from sg_torchrl.train.plot import plot_curves
from sg_torchrl.train.writes import make_dirs, write_atomic

__all__ = [
    "CHECKPOINT_NAME", "CheckpointError", "CheckpointSchedule", "EpochTrainer", "epoch_row",
    "finished_episode_cost", "open_run_logger", "write_run_summary",
]


@contextlib.contextmanager
def _without_distribution_validation() -> Iterator[None]:
    """Skip ``torch.distributions`` argument checks (about 30 % of a minibatch step here).

    The trainer's distributions are built from its own networks' outputs; a diverging network
    still shows up as non-finite losses and an env error on the first non-finite action.
    """
    previous = torch.distributions.Distribution._validate_args
    torch.distributions.Distribution.set_default_validate_args(False)
    try:
        yield
    finally:
        torch.distributions.Distribution.set_default_validate_args(previous)


class CheckpointSchedule:
    """Which finished epochs of one :meth:`EpochTrainer.run` call are checkpointed.

    The first epoch the call trains (so a killed run always has something to resume, whether new or
    resumed), every ``every``-th epoch, the call's ``last_epoch``, and any epoch that ends
    ``minutes`` or more of wall time after the last checkpoint (0: every epoch).
    """

    def __init__(self, every: int, minutes: float, last_epoch: int) -> None:
        self.every, self.seconds, self.last_epoch = every, minutes * 60.0, last_epoch
        self._saved_at: float | None = None  # time.monotonic() of this call's last checkpoint
        #: Epoch of the last checkpoint written during this call (None before the first).
        self.saved_epoch: int | None = None

    def due(self, epoch: int) -> bool:
        if self._saved_at is None or epoch % self.every == 0 or epoch == self.last_epoch:
            return True
        return time.monotonic() - self._saved_at >= self.seconds

    def saved(self, epoch: int) -> None:
        self._saved_at, self.saved_epoch = time.monotonic(), epoch


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


class EpochTrainer(abc.ABC):
    """The epoch loop of ``sg-train``; the subclass (:class:`~sg_torchrl.train.seed_runs.SeedGroupTrainer`)
    supplies the runs and the algorithm.

    A subclass builds its env, networks and :attr:`collector` after calling ``super().__init__(cfg)``
    (which sets the thread count and seeds torch first, so networks are initialised from ``cfg.seed``),
    then calls :meth:`_start` to restore a checkpoint and open the logs. It implements the hooks:

    * :meth:`_train_epoch`: collect, update, build the epoch's metrics (``Metrics/EpRet``,
      ``Metrics/EpCost``, ``Train/LagrangeMultiplier`` for the progress bar);
    * :meth:`_open_logs` / :meth:`_log_epoch`: the run's loggers and what an epoch writes to them;
    * :meth:`finish`: the end of the run (evaluation, summaries, plots);
    * :meth:`_run_state` / :meth:`_load_run_state`: the checkpoint entries beyond the shared ones
      (epoch counters, collector, torch RNG);
    * :meth:`_exhausted`: whether nothing is left to train.
    """

    title: str
    collector: RolloutCollector

    def __init__(self, cfg: TrainConfig) -> None:
        self.cfg = cfg
        torch.set_num_threads(cfg.threads)
        seeding.seed_torch(cfg.seed)  # the init stream: the networks are built from it
        self.epoch = 0
        self.total_steps = 0
        self.train_seconds = 0.0
        self._schedule: CheckpointSchedule | None = None  # set while :meth:`run` runs

    def _start(self, checkpoint: dict[str, Any] | None) -> None:
        """Restore ``checkpoint`` (when given) and open the run's logs; the last step of ``__init__``.

        Without a checkpoint this is a new run: a run directory that already holds a run is refused
        (:class:`~sg_torchrl.train.checkpoint.RunDirectoryError`) unless ``cfg.overwrite``, which
        removes the old run's files first.

        Raises:
            RunDirectoryError: a new run over an existing one without ``cfg.overwrite``.
        """
        cfg = self.cfg
        if checkpoint is not None:
            self._restore(checkpoint)
        else:
            checkpoint_files.check_new_run_dir(cfg.run_dir, cfg.overwrite)
            if checkpoint_files.existing_run_files(cfg.run_dir):  # cfg.overwrite: start over
                checkpoint_files.clear_run_dir(cfg.run_dir)
        self._open_logs(checkpoint)

    # ------------------------------------------------------------------ hooks
    @abc.abstractmethod
    def _train_epoch(self) -> dict[str, float]:
        """Collect, update and count one epoch; returns its metrics."""

    @abc.abstractmethod
    def _open_logs(self, checkpoint: dict[str, Any] | None) -> None:
        """Open the run's loggers, after the checkpoint (if any) is restored."""

    @abc.abstractmethod
    def _log_epoch(self, metrics: dict[str, float]) -> None:
        """Log the epoch (after its checkpoint, when one was due)."""

    @abc.abstractmethod
    def finish(self) -> dict[str, float]:
        """Final evaluation, summaries and learning-curve plots."""

    @abc.abstractmethod
    def _run_state(self) -> dict[str, Any]:
        """The checkpoint entries of the runs: networks, optimisers, multipliers, episode statistics, ..."""

    @abc.abstractmethod
    def _load_run_state(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`_run_state` saved."""

    def _exhausted(self) -> bool:
        """Whether nothing is left to train before the budget is spent (every seed of a group diverged)."""
        return False

    # ------------------------------------------------------------------ epochs
    def run(self, max_epochs: int | None = None) -> dict[str, float]:
        """Train until the budget is spent (or ``max_epochs`` more epochs), checkpointing on the way.

        Checkpoints follow :class:`CheckpointSchedule` (the first epoch of the call, every
        ``cfg.checkpoint_every`` epochs, every ``cfg.checkpoint_minutes``, the last epoch).
        Returns the last epoch's metrics, plus the evaluation summary when the run finished.

        Raises:
            TrainingInterrupted: on Ctrl-C or ``SIGTERM`` (:mod:`~sg_torchrl.train.interrupt`),
                after the epoch under way has finished and been checkpointed.
            RunWriteError: a file of the run could not be written (:mod:`~sg_torchrl.train.writes`); the
                last checkpoint written and the logs up to it are intact.
        """
        cfg = self.cfg
        make_dirs(cfg.run_dir)
        cfg.save(cfg.run_dir / "config.json")
        last_epoch = cfg.epochs if max_epochs is None else min(cfg.epochs, self.epoch + max_epochs)
        metrics: dict[str, float] = {}
        bar = tqdm(total=cfg.epochs * cfg.steps_per_epoch, initial=self.total_steps, unit="step",
                   disable=not cfg.progress, desc=f"{self.title} {cfg.env_id}", dynamic_ncols=True)
        schedule = self._schedule = CheckpointSchedule(cfg.checkpoint_every, cfg.checkpoint_minutes, last_epoch)
        try:
            with StopRequests() as stop:
                while self.epoch < last_epoch and not self._exhausted():
                    metrics = self.train_epoch()  # checkpoints (when due) before it logs the epoch
                    bar.update(cfg.steps_per_epoch)
                    bar.set_postfix(EpRet=f"{metrics['Metrics/EpRet']:.1f}",
                                    EpCost=f"{metrics['Metrics/EpCost']:.1f}",
                                    lam=f"{metrics['Train/LagrangeMultiplier']:.3f}")
                    if stop.requested:
                        saved = schedule.saved_epoch == self.epoch
                        raise TrainingInterrupted(stop.signum, self.epoch,
                                                  self.checkpoint_path if saved else self.save_checkpoint())
            if self.epoch >= cfg.epochs or self._exhausted():
                metrics.update(self.finish())
        finally:
            self._schedule = None
            bar.close()
        return metrics

    def train_epoch(self) -> dict[str, float]:
        """One epoch: collect, update (multiplier and networks), checkpoint when due (in :meth:`run`), log.

        The checkpoint comes before the log, so ``progress.csv`` never shows a checkpoint epoch that
        is not on disk yet; the checkpoint carries the epoch's row, which a resumed run writes to
        ``progress.csv`` if the process died between the two.
        """
        with _without_distribution_validation():
            metrics = self._train_epoch()
        schedule = self._schedule
        if schedule is not None and schedule.due(self.epoch):
            self.save_checkpoint()
            schedule.saved(self.epoch)
        self._log_epoch(metrics)
        return metrics

    # ------------------------------------------------------------------ checkpoints
    @property
    def checkpoint_path(self) -> Path:
        return self.cfg.run_dir / CHECKPOINT_NAME

    def save_checkpoint(self, path: Path | None = None) -> Path:
        """Write everything that influences the future to ``path`` (default ``<run dir>/checkpoint.pt``).

        Atomic and verified on load (:func:`sg_torchrl.train.checkpoint.save_checkpoint`). The run directory
        is not created again here: one that vanished during the run (an unmounted disk) is an error
        (:class:`~sg_torchrl.train.writes.RunWriteError`), not a new empty run directory.
        """
        if path is None:
            path = self.checkpoint_path
        else:
            make_dirs(path.parent)
        state = {
            "config": self.cfg.to_dict(),
            "epoch": self.epoch,
            "total_steps": self.total_steps,
            "train_seconds": self.train_seconds,
            **self._run_state(),
            "collector": self.collector.state_dict(),
            "torch_rng": torch.get_rng_state(),
        }
        return checkpoint_files.save_checkpoint(state, path)

    @staticmethod
    def load_checkpoint(path: str | Path) -> dict[str, Any]:
        """Read a checkpoint file, or ``<run dir>/checkpoint.pt`` when given a run directory.

        The file is verified (header, length, sha256) and unpickled with ``weights_only=True``, so
        it cannot run code.

        Raises:
            FileNotFoundError: no checkpoint there.
            CheckpointError: an empty, truncated, corrupted, foreign or unsafe file (the message
                names the file and the problem).
        """
        return checkpoint_files.load_checkpoint(path)

    def _restore(self, state: dict[str, Any]) -> None:
        self.epoch = state["epoch"]
        self.total_steps = state["total_steps"]
        self.train_seconds = state["train_seconds"]
        self._load_run_state(state)
        self.collector.load_state_dict(state["collector"])
        torch.set_rng_state(state["torch_rng"])
