"""The training engine behind ``sg-train``: :class:`SeedGroupTrainer`, S >= 1 seeds of one algorithm in one process.

Every ``sg-train`` run trains on it, one seed (``--seed s``) or a seed group (``--seeds 0 1 2``): S runs
side by side, one batched env of ``S * num_envs`` simulators (seed ``s``'s the ``s``-th block), collected
at once. How the seeds' networks are held and updated is the algorithm family's business, one small
subclass each (:func:`sg_torchrl.train.trainer_class` picks it):

* on-policy single agent (:class:`~sg_torchrl.train.seed_group.OnPolicyGroupTrainer`): networks stacked
  along a leading seed dimension, one group update for all seeds;
* multi agent (:class:`~sg_torchrl.train.multi_agent_group.MultiAgentGroupTrainer`): the seeds' teams
  stacked along a leading seed dimension, one seed-batched round for all seeds;
* off-policy (:class:`~sg_torchrl.train.off_policy.OffPolicyGroupTrainer`): stacked networks, the gradient
  steps inside collection.

Where the runs write is not a subclass either: the config picks a layout
(:func:`~sg_torchrl.train.seed_runs.run_layout`; a group's ``seed-XXX/`` directories or a single run's
directory, :mod:`sg_torchrl.train.seed_runs`), which the engine asks for the seeds, each seed's config
and the end of the run. One seed trains exactly as seed ``s`` of ``--seeds s``.

One epoch (SafePO's loop, Safety-Gymnasium paper appendix):

1. collect ``steps_per_epoch`` transitions per seed from ``num_envs`` batched simulators each;
2. each seed's finished-episode cost from its block, which its multiplier follows (before the policy
   update, as SafePO does; SafePO feeds a doubly smoothed 50-episode window mean instead, a quirk we
   do not reproduce);
3. the family's update (:meth:`SeedGroupTrainer._learn`; on-policy: reward and cost GAE, batch-level
   advantage normalisation, :mod:`sg_torchrl.train.group_updates`);
4. each seed's ``progress.csv`` row under SafePO's names, checkpoint.

A seed whose parameters or update turn non-finite is frozen (no more updates, multiplier or logs; its
simulators idle with zero actions) and reported on stderr and in its ``summary.json``; the others go on,
and when none is left the run ends early. Ctrl-C or ``SIGTERM`` stops a run at the end of the epoch
under way, with a checkpoint (:mod:`sg_torchrl.train.interrupt`).

Checkpoints hold everything that influences the future (each seed's networks, optimiser, multiplier,
observation normaliser, generators and episode statistics; the simulators' states, the collector's
carry, torch RNG states), so ``--resume`` continues bit-identically. They are written in
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
"""

from __future__ import annotations

import abc
import contextlib
import gc
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor
from tqdm.auto import tqdm

from sg_torchrl import seeding
from sg_torchrl.collectors import EpisodeStats, RolloutCollector
from sg_torchrl.train import checkpoint as checkpoint_files
from sg_torchrl.train.checkpoint import CHECKPOINT_NAME, CheckpointError
from sg_torchrl.train.config import TrainConfig
from sg_torchrl.train.interrupt import StopRequests, TrainingInterrupted
from sg_torchrl.train.seed_runs import (
    SeedRun,
    epoch_row,
    finished_episode_cost,
    mean_row,
    open_run_logger,
    run_layout,
    write_run_summary,
)
from sg_torchrl.train.writes import make_dirs

__all__ = ["CHECKPOINT_NAME", "CheckpointError", "CheckpointSchedule", "SeedGroupTrainer"]


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


@contextlib.contextmanager
def _older_objects_out_of_gc_scans() -> Iterator[None]:
    """Leave the objects that exist before an epoch out of the cyclic GC's scans during it (``gc.freeze``).

    A training process holds about half a million GC-tracked objects (the libraries' functions, modules,
    specs); an epoch's TensorDicts promote enough of its own objects to trigger a full collection about
    every epoch or two, which scans all of them (0.25 CPU s of an 8 s multi-agent epoch on the 2-core
    machine). They are frozen for the epoch and unfrozen after it, so nothing is kept from collection
    beyond the epoch (a caller that froze objects itself keeps its freeze: then nothing is done here).
    """
    if gc.get_freeze_count():
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


class CheckpointSchedule:
    """Which finished epochs of one :meth:`SeedGroupTrainer.run` call are checkpointed.

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


class SeedGroupTrainer(abc.ABC):
    """The engine: S >= 1 seeds of one algorithm trained side by side, in the layout ``cfg`` picks.

    ``cfg.seeds`` trains that seed group (:class:`~sg_torchrl.train.seed_runs.GroupLayout`), ``cfg.seed``
    alone one run (:class:`~sg_torchrl.train.seed_runs.SingleRunLayout`): :attr:`layout`. A family subclass
    calls ``super().__init__(cfg)`` first (which sets the thread count and seeds torch, so networks are
    initialised from ``cfg.seed``), builds its env, :attr:`policy` (with a ``frozen`` attribute: ``None``
    or an ``(S,)`` bool of the seeds acting with zeros), :attr:`collector`, :attr:`title` and :attr:`runs`
    (one :class:`~sg_torchrl.train.seed_runs.SeedRun` per seed of :attr:`seeds`, its config
    :meth:`_seed_config`), then calls :meth:`_start` to restore a checkpoint and open the logs. It implements:

    * :meth:`_learn`: update every live seed from the epoch's batch;
    * :meth:`_finite_seeds`: which seeds' parameters are finite;
    * :meth:`_evaluate_seed`: a seed's deterministic evaluation;
    * :meth:`_seed_state` / :meth:`_load_seed_state`: a seed's algorithm entries of the checkpoint;

    and, where the family had a single-seed trainer of its own before, :meth:`_single_run_checkpoint`
    (applied to a checkpoint given to a single run; a group's is restored as it is).
    """

    title: str
    collector: RolloutCollector
    runs: list[SeedRun]
    policy: Any  # a TensorDict policy with a ``frozen`` attribute (``None`` or ``(S,)`` bool)

    def __init__(self, cfg: TrainConfig) -> None:
        self.layout = run_layout(cfg)
        self.seeds = self.layout.seeds
        self.cfg = cfg
        torch.set_num_threads(cfg.threads)
        seeding.seed_torch(cfg.seed)  # the init stream: the networks are built from it
        self.epoch = 0
        self.total_steps = 0
        self.train_seconds = 0.0
        self._schedule: CheckpointSchedule | None = None  # set while :meth:`run` runs

    def _seed_config(self, seed: int) -> TrainConfig:
        """Seed ``seed``'s own run (its :attr:`SeedRun.cfg`, whose ``run_dir`` receives its logs): the layout's."""
        return self.layout.seed_config(seed)

    @property
    def stats(self) -> EpisodeStats:
        """A one-seed run's episode statistics (its one :class:`~sg_torchrl.train.seed_runs.SeedRun`'s).

        Raises:
            AttributeError: a seed group (each seed's are ``runs[i].stats``).
        """
        if self.cfg.group:
            raise AttributeError("a seed group has no one run's episode statistics: each seed's is runs[i].stats")
        return self.runs[0].stats

    def _start(self, checkpoint: dict[str, Any] | None) -> None:
        """Restore ``checkpoint`` (when given) and open the runs' logs; the last step of a subclass's ``__init__``.

        Without a checkpoint this is a new run: a run directory that already holds a run is refused
        (:class:`~sg_torchrl.train.checkpoint.RunDirectoryError`) unless ``cfg.overwrite``, which
        removes the old run's files first.

        Raises:
            RunDirectoryError: a new run over an existing one without ``cfg.overwrite``.
        """
        cfg = self.cfg
        if checkpoint is not None:
            if not cfg.group:
                checkpoint = self._single_run_checkpoint(checkpoint)
            self._restore(checkpoint)
        else:
            checkpoint_files.check_new_run_dir(cfg.run_dir, cfg.overwrite)
            if checkpoint_files.existing_run_files(cfg.run_dir):  # cfg.overwrite: start over
                checkpoint_files.clear_run_dir(cfg.run_dir)
        self._open_logs(checkpoint)

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

    def _single_run_checkpoint(self, checkpoint: dict[str, Any]) -> dict[str, Any]:
        """A single run's checkpoint in the engine's form (the family's reading of an earlier trainer's, if any)."""
        return checkpoint

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

    def _exhausted(self) -> bool:
        """Whether every seed is frozen, after freezing the live seeds whose parameters are not finite (set from
        outside, or loaded so)."""
        bad = (self.alive & ~self._finite_seeds()).tolist()
        if any(bad):
            self._freeze(bad, self.epoch + 1, "non-finite parameters at the start of the epoch")
        return not any(run.alive for run in self.runs)

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
        """One epoch: collect, update (multipliers and networks), checkpoint when due (in :meth:`run`), log.

        The checkpoint comes before the log, so ``progress.csv`` never shows a checkpoint epoch that
        is not on disk yet; the checkpoint carries the epoch's rows, which a resumed run writes to
        ``progress.csv`` if the process died between the two.
        """
        with _without_distribution_validation(), _older_objects_out_of_gc_scans():
            metrics = self._train_epoch()
        schedule = self._schedule
        if schedule is not None and schedule.due(self.epoch):
            self.save_checkpoint()
            schedule.saved(self.epoch)
        self._log_epoch(metrics)
        return metrics

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
        """Each seed's evaluation, ``summary.json`` and ``curves.png`` in its directory, then the layout's end of
        the run (a group's summary and figure); returns what ``sg-train`` prints
        (:meth:`~sg_torchrl.train.seed_runs.RunLayout.finish`)."""
        summaries = [self._finish_seed(index) for index in range(len(self.runs))]
        return self.layout.finish(self.runs, summaries, title=self.title, total_steps=self.total_steps,
                                  train_seconds=self.train_seconds)

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

    def _run_state(self) -> dict[str, Any]:
        """Every seed's entry under ``"seeds"``: its algorithm state (:meth:`_seed_state`) and its own record;
        ``"seed_group"`` names the seeds (a group's checkpoint and a single run's alike)."""
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
        """Restore every seed's entry (the checkpoint must hold these seeds, in this order)."""
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
