"""The sweep's driver: every unfinished cell of a :class:`~sg_torchrl.sweep.grid.SweepGrid` as a Ray task.

:func:`run_sweep` starts a local Ray instance (or joins ``address``), skips the cells whose
``summary.json`` exists, submits the others as tasks asking for ``cpus_per_cell`` CPUs (and
``gpus_per_cell`` GPUs), and reports as it goes: a line per cell that starts, restarts from its
checkpoint, finishes or fails, and every ``progress_every`` seconds the counts and the env steps per
second of the running cells. Cells run :func:`sg_torchrl.sweep.cell.run_cell`; read its docstring for
what happens when a worker dies.

Fault tolerance is Ray's task retry: a task whose worker process or node dies is resubmitted (up to
``max_retries`` times), as is one whose ``sg-train`` was killed by a signal; the new attempt resumes the
cell from its checkpoint. Ctrl-C cancels the tasks: each running cell finishes its epoch, checkpoints
and stops, and the same command continues the sweep. A second Ctrl-C stops at once (at most the work
since the cells' last checkpoints is lost).

The output directory is the whole state: ``sweep.json`` (the grid, its shared options, a storage
token), one directory per cell (``sg-train``'s files, ``sweep.log``, ``attempts.jsonl``) and, once
cells finish, ``report/``. It can be copied anywhere and reported on there (:mod:`sg_torchrl.sweep.report`).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import secrets
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

from sg_torchrl.sweep.cell import CellInterrupted, CellKilled, check_storage, run_cell
from sg_torchrl.sweep.grid import Cell, SweepGrid, SweepGridError, merge_records
from sg_torchrl.sweep.records import SWEEP_RECORD, AttemptLog, latest, read_progress
from sg_torchrl.train.writes import make_dirs, write_atomic, writing

__all__ = ["ClusterUnreachable", "SweepOutcome", "cell_finished", "cell_steps", "run_sweep", "prepare_output"]

#: Seconds a Ctrl-C'd sweep waits for its running cells to checkpoint before it gives up on them.
STOP_GRACE_S = 600.0


class ClusterUnreachable(ConnectionError):
    """The driver could not join the Ray cluster at ``address`` (wrong address, cluster down, or a missing or
    wrong authentication token: Ray clusters require one by default)."""


@dataclass
class SweepOutcome:
    """What a call of :func:`run_sweep` did: cells finished now, found finished, failed (with why), stopped."""

    finished: list[Cell] = field(default_factory=list)
    skipped: list[Cell] = field(default_factory=list)
    failed: dict[Cell, str] = field(default_factory=dict)
    #: Cells whose ``sg-train`` was stopped (SIGINT / SIGTERM) from outside the sweep, checkpointed.
    stopped: list[Cell] = field(default_factory=list)
    interrupted: bool = False

    @property
    def ok(self) -> bool:
        return not self.failed and not self.stopped and not self.interrupted


def prepare_output(grid: SweepGrid) -> str:
    """Create the output directory and write (or extend) its ``sweep.json``; returns the storage token.

    Raises:
        SweepGridError: the directory holds a sweep with another budget or other shared options.
    """
    make_dirs(grid.output_dir)
    path = grid.output_dir / SWEEP_RECORD
    previous = json.loads(path.read_text()) if path.exists() else None
    record = merge_records(previous, grid)
    record["token"] = (previous or {}).get("token") or secrets.token_hex(8)
    write_atomic(path, json.dumps(record, indent=2))
    return record["token"]


def cell_steps(grid: SweepGrid, cell: Cell) -> int:
    """Env steps per seed that ``cell`` has logged so far (its first seed's latest ``Train/TotalSteps``)."""
    steps = latest(read_progress(grid.cell_dir(cell) / f"seed-{cell.seeds[0]:03d}" / "progress.csv"),
                   "Train/TotalSteps")
    return int(steps) if math.isfinite(steps) else 0


def cell_finished(grid: SweepGrid, cell: Cell) -> bool:
    return (grid.cell_dir(cell) / "summary.json").exists()


def _summary_line(grid: SweepGrid, cell: Cell) -> str:
    path = grid.cell_dir(cell) / "summary.json"
    try:
        mean = json.loads(path.read_text()).get("mean", {})
        return f"J^R {mean['Final/EpRetLast10']:.2f}  J^C {mean['Final/EpCostLast10']:.2f}"
    except (OSError, ValueError, KeyError, TypeError):
        return ""


class _Progress:
    """The driver's reports: cell events as they happen and a status line every ``every`` seconds."""

    def __init__(self, grid: SweepGrid, cells: list[Cell], every: float, out: Callable[[str], None]) -> None:
        self.grid, self.every, self.out = grid, every, out
        self.seen_attempts = {cell: len(AttemptLog(grid.cell_dir(cell)).read()) for cell in cells}
        self.last_line = time.monotonic()
        # each running cell's (time, env steps of all seeds) when last measured: at the status line before, or
        # when it was first seen running, so the first line after a start or restart already has a rate
        self.measured: dict[Cell, tuple[float, int]] = {}

    def poll(self, open_cells: list[Cell], done: int, failed: int, force: bool = False) -> None:
        running = []
        for cell in open_cells:
            attempts = AttemptLog(self.grid.cell_dir(cell)).read()
            if len(attempts) > self.seen_attempts[cell]:
                self.seen_attempts[cell] = len(attempts)
                attempt = attempts[-1]
                verb = "restart" if attempt.get("resumed") else "start"
                detail = (f" from its checkpoint (attempt {attempt['attempt']}, {attempt.get('epochs_before', 0)} "
                          "epochs logged before)") if attempt.get("resumed") else ""
                node = attempt.get("node") + (f" (node {attempt['node_id'][:8]})" if attempt.get("node_id") else "")
                self.out(f"[{verb}] {cell.label} on {node}{detail}; log {self.grid.cell_dir(cell)}/sweep.log")
            if attempts and attempts[-1].get("status") == "running":
                running.append(cell)
        now = time.monotonic()
        for cell in running:
            if cell not in self.measured:  # progress files are read once at a cell's start, then per status line
                self.measured[cell] = (now, cell_steps(self.grid, cell) * len(cell.seeds))
        if force or now - self.last_line >= self.every:
            # Rows come once per epoch (a minute or more at the paper's sizes): each cell's rate is over the time
            # since it was last measured (a resumed cell's log may step back, hence the floor at 0).
            rate, timed = 0.0, False
            for cell in running:
                since, steps_then = self.measured[cell]
                if now > since:  # else first seen at this very poll: just measured, nothing to rate yet
                    steps = cell_steps(self.grid, cell) * len(cell.seeds)
                    rate, timed = rate + max(steps - steps_then, 0) / (now - since), True
                    self.measured[cell] = (now, steps)
            self.measured = {cell: self.measured[cell] for cell in running}
            self.last_line = now
            speed = f"{rate:,.0f} env steps/s" if timed or not running else "env steps/s from the next line"
            self.out(f"[sweep {time.strftime('%H:%M:%S')}] {done} done, {len(running)} running, {failed} failed, "
                     f"{len(open_cells) - len(running)} waiting; {speed}")


def _init_ray(address: str | None, num_cpus: int | None) -> None:
    """Start or join Ray, keeping the caller's ``SIGTERM`` handler.

    ``ray.init`` replaces it with one that exits at once (and Ray's core dumps a stack): ``sg-sweep``'s handler,
    which makes a scheduler's ``SIGTERM`` a Ctrl-C (cells checkpoint, then the sweep stops), would be lost.
    """
    import ray

    main_thread = threading.current_thread() is threading.main_thread()
    sigterm = signal.getsignal(signal.SIGTERM) if main_thread else None
    try:
        if address:  # join a running cluster (``ray start --head`` elsewhere); its resources are its own
            try:
                ray.init(address=address, log_to_driver=False, logging_level="warning")
            except ConnectionError as error:
                raise ClusterUnreachable(_join_failure(address, error)) from error
        else:  # a private local instance: never attach silently to another user's cluster on this machine
            ray.init(address="local", num_cpus=num_cpus, include_dashboard=False, log_to_driver=False,
                     logging_level="warning")
    finally:
        if main_thread and sigterm is not None:
            signal.signal(signal.SIGTERM, sigterm)


def _join_failure(address: str, error: BaseException) -> str:
    """Why joining ``address`` failed, in a line: Ray buries a refused token under a chain of connection errors
    (Ray 2.60: as the text of the last one's cause), and an explicit address, unlike ``auto``, never turns token
    authentication on by itself."""
    from ray.exceptions import AuthenticationError

    cause: BaseException | None = error
    while cause is not None and not (isinstance(cause, AuthenticationError) or "InvalidAuthToken" in str(cause)):
        cause = cause.__cause__ or cause.__context__
    if cause is None:
        return f"cannot join the Ray cluster at {address}: {error}"
    return (f"the Ray cluster at {address} refused this driver's authentication token. Ray clusters require one by "
            "default: set RAY_AUTH_MODE=token and give the cluster's token (RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH or "
            "~/.ray/auth_token; `ray get-auth-token` on the head node prints it)")


@contextlib.contextmanager
def _driver_lock(output_dir: Path) -> Iterator[None]:
    """Hold ``<output_dir>/.sweep.lock`` while a driver runs the sweep there.

    Two drivers on one output directory would submit every cell twice (the cells' own locks keep the
    attempts apart, but each would train a cell the other had queued). Holding the lock also makes the
    driver the only one that marks attempts left ``"running"`` by a killed sweep as ``"lost"``.

    Raises:
        SweepGridError: another ``sg-sweep`` holds the lock (its pid is in the message).
    """
    with writing(output_dir / ".sweep.lock"):
        lock = open(output_dir / ".sweep.lock", "a+")
    with lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.seek(0)
            holder = lock.read().strip() or "unknown"
            raise SweepGridError(f"another sg-sweep (pid {holder}) is running on {output_dir}; wait for it or stop "
                                 "it (Ctrl-C) first") from None
        lock.seek(0)
        lock.truncate()
        lock.write(str(os.getpid()))
        lock.flush()
        yield


def run_sweep(grid: SweepGrid, *, address: str | None = None, num_cpus: int | None = None,
              cpus_per_cell: float = 1.0, gpus_per_cell: float = 0.0, max_retries: int = 3,
              progress_every: float = 30.0, out: Callable[[str], None] = print) -> SweepOutcome:
    """Run every unfinished cell of ``grid`` on Ray; see the module docstring.

    Args:
        grid: the cells, their shared options and the output directory.
        address: a running Ray cluster to join (``"auto"``, ``"10.0.0.1:6379"``); None starts a local instance.
        num_cpus: CPUs of the local instance (default: all of this machine's).
        cpus_per_cell, gpus_per_cell: what each cell's task asks Ray for.
        max_retries: how often a cell whose worker died (or whose ``sg-train`` was killed) is resubmitted.
        progress_every: seconds between status lines.
        out: where reports go (``print``).

    Raises:
        SweepGridError: a bad cell command line, or an output directory holding another kind of sweep.
        RunWriteError: the output directory (its ``sweep.json``, its lock) cannot be written. A cell that
            cannot write is a failed cell (``outcome.failed``, with ``sg-train``'s line), the others go on.
        ClusterUnreachable: ``address`` could not be joined.
        KeyboardInterrupt: after a Ctrl-C, once the running cells have checkpointed (``outcome.interrupted``
            is not returned then: the exception is the report).
    """
    grid.validate()
    make_dirs(grid.output_dir)
    with _driver_lock(grid.output_dir):
        token = prepare_output(grid)
        outcome = SweepOutcome()
        todo = []
        for cell in grid.cells:
            if cell_finished(grid, cell):
                outcome.skipped.append(cell)
                out(f"[skip] {cell.label}: finished ({_summary_line(grid, cell)})")
            else:
                todo.append(cell)
                AttemptLog(grid.cell_dir(cell)).mark_lost()  # "running" left by a sweep that was killed
        if not todo:
            return outcome
        import ray

        _init_ray(address, num_cpus)
        try:
            check_storage(grid.output_dir, token)
            task = ray.remote(run_cell)
            resources = {"num_cpus": cpus_per_cell, "num_gpus": gpus_per_cell, "max_retries": max_retries,
                         "retry_exceptions": [CellKilled]}
            refs = {task.options(name=cell.run_name, **resources).remote(
                        str(grid.output_dir), token, cell.run_name, list(cell.seeds), grid.train_arguments(cell)): cell
                    for cell in todo}
            out(f"[sweep] {len(refs)} cell(s) submitted, {len(outcome.skipped)} already finished; output {grid.output_dir}")
            progress = _Progress(grid, todo, progress_every, out)
            try:
                _wait_all(refs, grid, outcome, progress, out)
            except KeyboardInterrupt:
                _stop(refs, progress, outcome, out)
                outcome.interrupted = True
                raise
        finally:
            ray.shutdown()
        return outcome


def _collect(ref: Any, cell: Cell, grid: SweepGrid, outcome: SweepOutcome, out: Callable[[str], None]) -> None:
    import ray

    try:
        ray.get(ref)
    except ray.exceptions.RayError as error:
        cause = getattr(error, "cause", None) or error
        if isinstance(cause, CellInterrupted):  # its sg-train was stopped from outside the sweep, checkpointed
            outcome.stopped.append(cell)
            out(f"[stopped] {cell.label}: {cause}; the same command continues it")
            return
        reason = str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__
        outcome.failed[cell] = str(cause)
        AttemptLog(grid.cell_dir(cell)).mark_lost()  # a worker that died on the last retry left its attempt open
        out(f"[failed] {cell.label}: {reason}; log {grid.cell_dir(cell)}/sweep.log")
        return
    outcome.finished.append(cell)
    out(f"[done] {cell.label}: {_summary_line(grid, cell)}")


def _wait_all(refs: dict[Any, Cell], grid: SweepGrid, outcome: SweepOutcome, progress: _Progress,
              out: Callable[[str], None]) -> None:
    import ray

    remaining = dict(refs)
    while remaining:
        ready, _ = ray.wait(list(remaining), num_returns=1, timeout=min(progress.every, 5.0))
        progress.poll(list(remaining.values()), len(outcome.finished), len(outcome.failed))
        for ref in ready:
            _collect(ref, remaining.pop(ref), grid, outcome, out)
    progress.poll([], len(outcome.finished), len(outcome.failed), force=True)


def _stop(refs: dict[Any, Cell], progress: _Progress, outcome: SweepOutcome, out: Callable[[str], None]) -> None:
    """Cancel every open task; wait (up to :data:`STOP_GRACE_S`) for the running cells to checkpoint."""
    import ray

    open_refs = [ref for ref, cell in refs.items() if cell not in outcome.finished and cell not in outcome.failed]
    out(f"[stopping] {len(open_refs)} open cell(s): the running ones finish their epoch and checkpoint; "
        "run the same command again to continue (Ctrl-C again stops at once)")
    for ref in open_refs:
        ray.cancel(ref, force=False)
    deadline = time.monotonic() + STOP_GRACE_S
    while open_refs and time.monotonic() < deadline:
        ready, open_refs = ray.wait(open_refs, num_returns=len(open_refs), timeout=2.0)
    if open_refs:
        out(f"[stopping] {len(open_refs)} cell(s) did not stop within {STOP_GRACE_S:.0f} s; they continue from their "
            "last checkpoint")
