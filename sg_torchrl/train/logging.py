"""Per-epoch metric logging to CSV, wandb and TensorBoard through TorchRL's loggers.

Metric names follow SafePO's (``Metrics/EpRet``, ``Metrics/EpCost``, ``Train/LagrangeMultiplier``,
``Loss/Loss_actor``, ``Time/FPS`` ...) so curves compare side by side with the reference runs.
Besides TorchRL's loggers, every epoch is appended as one row to ``progress.csv`` (SafePO's file)
which the plot and the benchmark tables read.
"""

from __future__ import annotations

import csv
import importlib.util
import os
from pathlib import Path
from typing import Any

from torchrl.record.loggers import CSVLogger, Logger

__all__ = ["RunLogger"]


class RunLogger:
    """Fan one dict of scalars per epoch out to every configured backend.

    Args:
        run_dir: the run directory (created if missing).
        exp_name: experiment name for the loggers.
        wandb_mode: ``"offline"`` (default: no account, no network), ``"online"`` or ``"disabled"``.
        config: stored with the wandb run.
        resume_epoch: the epoch a resumed run continues from (its checkpoint's). ``progress.csv``
            keeps its rows up to that epoch and drops later ones, which an interrupted run logged
            after its last checkpoint and is about to log again; ``None`` starts a new file, and
            refuses to replace an existing one (the trainer clears a run directory only when told to
            start over, :func:`sg_torchrl.train.checkpoint.check_new_run_dir`).
        resume_row: the metrics of epoch ``resume_epoch`` saved with the checkpoint. The trainer
            checkpoints an epoch before logging it, so a process killed in between left a checkpoint
            whose row ``progress.csv`` lacks: it is appended here (to ``progress.csv`` only; the
            TorchRL loggers' files miss that epoch).

    Raises:
        FileExistsError: a new run (no ``resume_epoch``) over an existing ``progress.csv``.
    """

    def __init__(
        self,
        run_dir: Path,
        exp_name: str,
        *,
        wandb_mode: str = "offline",
        config: dict[str, Any] | None = None,
        resume_epoch: int | None = None,
        resume_row: dict[str, float] | None = None,
    ) -> None:
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.progress_path = self.run_dir / "progress.csv"
        if resume_epoch is None and self.progress_path.exists():
            raise FileExistsError(f"{self.progress_path} exists: a new run does not overwrite another run's log")
        self.backends: list[Logger] = [CSVLogger(exp_name=exp_name, log_dir=str(self.run_dir / "csv"))]
        if importlib.util.find_spec("tensorboard") is not None:
            from torchrl.record.loggers import TensorboardLogger

            self.backends.append(TensorboardLogger(exp_name=exp_name, log_dir=str(self.run_dir / "tb")))
        if wandb_mode != "disabled":
            self.backends.append(self._wandb(exp_name, wandb_mode, config))
        self._columns: list[str] | None = None
        if resume_epoch is not None:
            logged = self._truncate_progress(resume_epoch) if self.progress_path.exists() else None
            if resume_row is not None and logged != resume_epoch and resume_row.get("Train/Epoch") == resume_epoch:
                self._append_progress(resume_row)

    def _truncate_progress(self, last_epoch: int) -> float | None:
        """Keep the header and the rows of epochs ``<= last_epoch`` of ``progress.csv`` (drop the rest).

        Returns the epoch of the last row kept (None when none is).
        """
        with self.progress_path.open(newline="") as handle:
            rows = list(csv.reader(handle))
        if not rows:
            return None
        self._columns = rows[0]
        epoch = self._columns.index("Train/Epoch") if "Train/Epoch" in self._columns else None
        if epoch is None:
            return None
        # Rows without an epoch are a finished run's final summary: the resumed run writes its own.
        kept = [row for row in rows[1:] if row[epoch] != "" and float(row[epoch]) <= last_epoch]
        with self.progress_path.open("w", newline="") as handle:
            csv.writer(handle).writerows([self._columns, *kept])
        return float(kept[-1][epoch]) if kept else None

    def _wandb(self, exp_name: str, mode: str, config: dict[str, Any] | None) -> Logger:
        from torchrl.record.loggers import WandbLogger

        # torchrl's offline=True sets WANDB_MODE=dryrun, which wandb 0.31 rejects; pass mode instead.
        os.environ.pop("WANDB_MODE", None)
        os.environ.setdefault("WANDB_SILENT", "true")
        # reinit="create_new": a seed group logs its S runs from one process, each to its own wandb run
        # (wandb's default would hand the second logger the first run back).
        return WandbLogger(
            exp_name=exp_name, offline=False, save_dir=str(self.run_dir), project="sg_torchrl", mode=mode,
            config=config, reinit="create_new",
        )

    def log(self, metrics: dict[str, float], step: int) -> None:
        for backend in self.backends:
            for name, value in metrics.items():
                backend.log_scalar(name, float(value), step=step)
        self._append_progress(metrics)

    def _append_progress(self, metrics: dict[str, float]) -> None:
        if self._columns is None:
            self._columns = list(metrics)
            with self.progress_path.open("w", newline="") as handle:
                csv.writer(handle).writerow(self._columns)
        with self.progress_path.open("a", newline="") as handle:
            csv.writer(handle).writerow([metrics.get(name, "") for name in self._columns])

    def history(self) -> list[dict[str, float]]:
        """All rows of ``progress.csv`` so far (numbers parsed)."""
        if not self.progress_path.exists():
            return []
        with self.progress_path.open() as handle:
            return [{k: float(v) if v != "" else float("nan") for k, v in row.items()} for row in csv.DictReader(handle)]

    def close(self) -> None:
        for backend in self.backends:
            experiment = getattr(backend, "experiment", None)
            finish = getattr(experiment, "finish", None)
            if callable(finish):
                finish()
