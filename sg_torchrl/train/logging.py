"""Per-epoch metric logging to CSV, wandb and TensorBoard through TorchRL's loggers.

Metric names follow SafePO's (``Metrics/EpRet``, ``Metrics/EpCost``, ``Train/LagrangeMultiplier``,
``Loss/Loss_actor``, ``Time/FPS`` ...) so curves compare side by side with the reference runs.
Besides TorchRL's loggers, every epoch is appended as one row to ``progress.csv`` (SafePO's file)
which the plot and the benchmark tables read.
"""

from __future__ import annotations

import csv
import importlib.util
import io
import os
from pathlib import Path
from typing import Any

from torchrl.record.loggers import CSVLogger, Logger

from sg_torchrl.train.writes import append_text, make_dirs, write_atomic, writing

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

    Every write goes through :mod:`sg_torchrl.train.writes`: a row is appended to ``progress.csv`` whole or
    not at all, and cutting the file back replaces it atomically.

    Raises:
        FileExistsError: a new run (no ``resume_epoch``) over an existing ``progress.csv``.
        RunWriteError: a file could not be written (here or in :meth:`log`).
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
        make_dirs(self.run_dir)
        self.progress_path = self.run_dir / "progress.csv"
        if resume_epoch is None and self.progress_path.exists():
            raise FileExistsError(f"{self.progress_path} exists: a new run does not overwrite another run's log")
        with writing(self.run_dir / "csv"):
            self.backends: list[Logger] = [CSVLogger(exp_name=exp_name, log_dir=str(self.run_dir / "csv"))]
        if importlib.util.find_spec("tensorboard") is not None:
            from torchrl.record.loggers import TensorboardLogger

            with writing(self.run_dir / "tb"):
                self.backends.append(TensorboardLogger(exp_name=exp_name, log_dir=str(self.run_dir / "tb")))
        if wandb_mode != "disabled":
            with writing(self.run_dir / "wandb"):
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
        kept = [row for row in rows[1:] if len(row) > epoch and row[epoch] != "" and float(row[epoch]) <= last_epoch]
        write_atomic(self.progress_path, _csv_text([self._columns, *kept]))
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
        """Log one row: ``progress.csv`` first (the file resumed runs and reports read), then the backends."""
        self._append_progress(metrics)
        for backend in self.backends:
            with writing(getattr(backend, "log_dir", self.run_dir)):
                for name, value in metrics.items():
                    backend.log_scalar(name, float(value), step=step)

    def _append_progress(self, metrics: dict[str, float]) -> None:
        rows = [] if self._columns is not None else [list(metrics)]
        columns = self._columns or rows[0]
        append_text(self.progress_path, _csv_text([*rows, [metrics.get(name, "") for name in columns]]))
        self._columns = columns

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


def _csv_text(rows: list[list[Any]]) -> str:
    """``rows`` as CSV text (what ``csv.writer`` would write to a file)."""
    buffer = io.StringIO()
    csv.writer(buffer).writerows(rows)
    return buffer.getvalue()
