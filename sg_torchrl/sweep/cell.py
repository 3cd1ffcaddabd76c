"""One sweep cell on a Ray worker: ``sg-train`` in a child process, resumed from its checkpoint when one exists.

:func:`run_cell` is the body of the sweep's Ray task. It starts ``python -m sg_torchrl.train`` for the
cell (``--resume`` when the cell's directory holds a checkpoint, else a fresh run), sends its output to
the cell's ``sweep.log`` and records each attempt in ``attempts.jsonl``. The child process rather than
the worker itself trains because:

* a retried task must never run beside its predecessor in the same directory. The task holds an
  exclusive ``flock`` on ``<cell>/.lock`` and the child inherits it, so a new attempt waits until an
  orphaned ``sg-train`` has checkpointed and exited;
* the child dies with the worker (``PR_SET_PDEATHSIG``). It gets ``SIGTERM``, which ``sg-train`` turns into
  "finish this epoch, checkpoint, stop" (:mod:`sg_torchrl.train.interrupt`), so a killed worker loses at
  most the epoch under way and whatever ran since the last checkpoint;
* Ray's cancel (the sweep's Ctrl-C) raises ``KeyboardInterrupt`` in the task, which passes it on to the
  child as ``SIGINT``: the same checkpointed stop. Ray raises it as a simulated ``SIGINT``
  (``_thread.interrupt_main``), which does nothing where ``SIGINT`` is ignored, as it is in a sweep started in
  the background (``sg-sweep ... &``, ``nohup``) and in the local Ray workers it starts; so the task takes
  ``SIGINT`` back (:func:`accept_cancel`) before it waits for its child;
* the child runs in its own session, so a Ctrl-C at the sweep's terminal reaches it only through the sweep.

How a child's exit maps to the task's outcome: 0, or 1 with a summary (every seed diverged), is a finished
cell; a death by a signal (``SIGKILL``, the OOM killer) raises :class:`CellKilled`, which Ray retries;
130 / 143 (a stop request) raises :class:`CellInterrupted`; any other exit raises :class:`CellFailed` whose
first line is ``sg-train`` 's own error line when it printed one (exit 3: a file of the cell could not be
written, ``cannot write <file>: <cause>``), then the end of the log. A finished cell is never trained again:
the task returns at once when the cell's ``summary.json`` exists.
"""

from __future__ import annotations

import ctypes
import fcntl
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from sg_torchrl.sweep.records import SWEEP_RECORD, AttemptLog, epochs_logged
from sg_torchrl.train.writes import EXIT_WRITE_FAILED, check_run_name, make_dirs, writing

__all__ = ["CellFailed", "CellInterrupted", "CellKilled", "SweepStorageError", "check_storage", "run_cell"]

#: Exit codes of an ``sg-train`` stopped on request (128 + SIGINT / SIGTERM), checkpointed.
STOPPED_CODES = frozenset({128 + signal.SIGINT, 128 + signal.SIGTERM})
_PR_SET_PDEATHSIG = 1


class CellKilled(RuntimeError):
    """``sg-train`` was killed by a signal it did not ask for: the cell is retried from its checkpoint."""


class CellFailed(RuntimeError):
    """``sg-train`` exited with an error (a bad config, a crash): retrying would fail again."""


class CellInterrupted(RuntimeError):
    """The cell stopped on request after a checkpointed epoch; running the sweep again continues it."""


class SweepStorageError(RuntimeError):
    """A worker cannot see the sweep's output directory: cells need storage every node shares."""


def _node_address() -> str:
    try:
        import ray

        return ray.util.get_node_ip_address()
    except Exception:  # outside Ray (tests call run_cell directly)
        return socket.gethostname()


def _node_id() -> str | None:
    """The Ray node running this task (None outside Ray): unlike the address, it tells apart two nodes of
    one machine, and a node restarted on the same host."""
    try:
        import ray

        return ray.get_runtime_context().get_node_id() if ray.is_initialized() else None
    except Exception:
        return None


#: libc, loaded once at import: the child's ``preexec_fn`` must not load libraries after ``fork`` in a
#: threaded worker (a lock held by another thread at fork time would never be released there).
_LIBC = ctypes.CDLL(None, use_errno=True)


def _die_with_parent() -> None:
    """In the child before ``exec``: receive ``SIGTERM`` when the worker dies (a checkpointed stop)."""
    parent = os.getppid()
    _LIBC.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    if os.getppid() != parent:  # the worker died before the request took effect
        os.kill(os.getpid(), signal.SIGTERM)


def _keep_niceness(pid: int) -> None:
    """Give child ``pid``'s new session this process's niceness.

    Linux with autogroup scheduling (the default on desktops and many servers) shares the CPU between
    sessions first and applies a process's nice value only within its session. A child in its own session
    (``start_new_session``) would compete at full weight with everything else on the machine, so that
    ``nice sg-sweep`` would not yield to other work; its session's nice value (``/proc/<pid>/autogroup``)
    restores that. A no-op where autogroup is absent.
    """
    niceness = os.getpriority(os.PRIO_PROCESS, 0)
    try:
        Path(f"/proc/{pid}/autogroup").write_text(str(niceness))
    except OSError:
        pass


def _wait(pid: int, poll: bool = True) -> tuple[int, Any]:
    """The wait status and resource usage of child ``pid`` once it exits.

    Polled (``poll``) rather than blocking: Ray cancels a task by raising ``KeyboardInterrupt`` in its
    thread (``_thread.interrupt_main``), which only takes effect between Python instructions, never
    inside a blocking ``wait4``.
    """
    while poll:
        done, status, usage = os.wait4(pid, os.WNOHANG)
        if done:
            return status, usage
        time.sleep(0.25)
    _, status, usage = os.wait4(pid, 0)
    return status, usage


def _figures(status: int, usage: Any, start: float) -> dict[str, Any]:
    """An ended attempt's record: the child's exit code, wall seconds since ``start`` and CPU seconds."""
    return {"code": os.waitstatus_to_exitcode(status), "wall_s": time.monotonic() - start,
            "cpu_s": usage.ru_utime + usage.ru_stime}


def _log_tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""


def check_storage(output_dir: Path, token: str) -> None:
    """Raise :class:`SweepStorageError` unless this node sees the sweep's own ``sweep.json`` (same token)."""
    record = output_dir / SWEEP_RECORD
    try:
        seen = json.loads(record.read_text()).get("token")
    except (OSError, ValueError):
        seen = None
    if seen != token:
        raise SweepStorageError(
            f"node {_node_address()} cannot see this sweep's {record}: a sweep's output directory must be on "
            "storage every node of the cluster shares (the same path on each), since cells resume from their "
            "checkpoints wherever Ray runs them")


def accept_cancel() -> None:
    """Let Ray's cancel reach this task: restore Python's ``SIGINT`` handler where ``SIGINT`` is ignored.

    Only in the main thread (where Ray runs a task and where a handler can be set); elsewhere nothing changes.
    """
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def run_cell(output_dir: str, token: str, run_name: str, seeds: list[int], arguments: list[str]) -> dict[str, Any]:
    """Train one cell to its end (or continue it), in ``<output_dir>/<run_name>``.

    Args:
        output_dir: the sweep's root folder (the same path on every node).
        token: the sweep's storage token (:func:`check_storage`).
        run_name: the cell's directory relative to ``output_dir``.
        seeds: the cell's seeds (for the progress count of a resumed attempt).
        arguments: the ``sg-train`` arguments of a fresh start (:meth:`SweepGrid.train_arguments`).

    Returns:
        ``{"status": "done", "ran": bool, "attempt": n, "wall_s": ..., "cpu_s": ...}``.

    Raises:
        CellKilled / CellFailed / CellInterrupted / SweepStorageError: see the module docstring.
        RunWriteError: the cell's directory, lock, log or attempt record cannot be written (the cell fails).
        ValueError: ``run_name`` leaves ``output_dir`` (absolute, or a ``..`` part).
    """
    accept_cancel()
    root = Path(output_dir)
    check_storage(root, token)
    check_run_name(run_name)  # a cell's files stay inside the sweep's output directory
    directory = make_dirs(root / run_name)
    with writing(directory / ".lock"):
        lock = open(directory / ".lock", "a+")
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # an orphaned sg-train of a lost attempt may still be checkpointing
        if (directory / "summary.json").exists():
            return {"status": "done", "ran": False}
        resume = (directory / "checkpoint.pt").exists()
        if resume:
            command = ["--resume", str(directory), "--progress", "false"]
        else:  # a new cell, or one whose first attempt died before its first checkpoint: start it over
            command = [*arguments, "--overwrite", "--progress", "false"]
        attempts, node = AttemptLog(directory), _node_address()
        number = attempts.begin(node=node, node_id=_node_id(), pid=os.getpid(), resumed=resume,
                                epochs_before=epochs_logged(directory, seeds))
        start = time.monotonic()
        with writing(directory / "sweep.log"):
            log = open(directory / "sweep.log", "ab")
            try:
                log.write(f"\n=== attempt {number} on {node} ({time.ctime()}): sg-train "
                          f"{' '.join(command)}\n".encode())
                log.flush()
            except OSError:
                log.close()
                raise
        with log:
            child = subprocess.Popen([sys.executable, "-m", "sg_torchrl.train", *command], stdout=log,
                                     stderr=subprocess.STDOUT, start_new_session=True, pass_fds=(lock.fileno(),),
                                     preexec_fn=_die_with_parent)
            _keep_niceness(child.pid)
            try:
                status, usage = _wait(child.pid)
            except KeyboardInterrupt:  # Ray's cancel (the sweep's Ctrl-C): a checkpointed stop
                child.send_signal(signal.SIGINT)
                status, usage = _wait(child.pid, poll=False)
                attempts.end(number, "interrupted", **_figures(status, usage, start))
                raise
        figures = _figures(status, usage, start)
        child.returncode = code = figures["code"]
        if code == 0 or (code == 1 and (directory / "summary.json").exists()):  # 1: every seed diverged
            attempts.end(number, "done", **figures)
            return {"status": "done", "ran": True, "attempt": number, **figures}
        if code < 0:
            attempts.end(number, "killed", **figures)
            raise CellKilled(f"sg-train was killed by {signal.Signals(-code).name} (attempt {number}); "
                             f"log: {directory / 'sweep.log'}")
        if code in STOPPED_CODES:
            attempts.end(number, "interrupted", **figures)
            raise CellInterrupted(f"stopped on request after a checkpointed epoch (exit {code})")
        attempts.end(number, "failed", **figures)
        tail = _log_tail(directory / "sweep.log")
        # sg-train's own one-line error first (a full disk: exit 3, "cannot write ..."), then the log's end.
        said = next((line for line in reversed(tail.splitlines()) if line.startswith("sg-train: error:")), None)
        what = "could not write a file" if code == EXIT_WRITE_FAILED else f"exited with {code}"
        raise CellFailed(f"{said or 'sg-train ' + what} (exit {code}); log: {directory / 'sweep.log'}\n{tail}")
