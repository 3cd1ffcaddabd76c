"""Stopping a run cleanly: Ctrl-C or ``SIGTERM`` ends it at the next epoch boundary, checkpointed.

A benchmark cell of 1M steps runs for half an hour; a cluster job is preempted with ``SIGTERM`` and
a user stops a run with Ctrl-C. Killed mid-epoch, a run would lose everything since its last
periodic checkpoint (up to ``checkpoint_every`` epochs), and its networks are half-updated then,
so no consistent state exists to save. :class:`StopRequests` turns the first ``SIGINT`` /
``SIGTERM`` into a request that the training loop honours after the current epoch: it saves a
checkpoint there and raises :class:`TrainingInterrupted`, so ``sg-train --resume`` continues
bit-identically. A second signal stops at once (Python's default behaviour).
"""

from __future__ import annotations

import signal
import sys
import threading
from pathlib import Path
from types import FrameType, TracebackType

__all__ = ["StopRequests", "TrainingInterrupted"]

#: The signals that request a stop at the next epoch boundary.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class TrainingInterrupted(KeyboardInterrupt):
    """A run stopped on request after a whole epoch, with a checkpoint of that epoch.

    A :class:`KeyboardInterrupt`, so code that already catches Ctrl-C keeps working.

    Attributes:
        signum: the signal that asked for the stop.
        epoch: the last completed (and checkpointed) epoch.
        checkpoint: the checkpoint file written at that epoch.
    """

    def __init__(self, signum: int, epoch: int, checkpoint: Path) -> None:
        self.signum = signum
        self.epoch = epoch
        self.checkpoint = checkpoint
        super().__init__(f"{signal.Signals(signum).name} received: stopped after epoch {epoch}, "
                         f"checkpoint {checkpoint}")

    @property
    def exit_code(self) -> int:
        """The shell's convention for a process ended by a signal: 128 + its number (130 for Ctrl-C)."""
        return 128 + self.signum


class StopRequests:
    """Context manager that records the first ``SIGINT`` / ``SIGTERM`` instead of dying on it.

    Inside the ``with`` block the first such signal sets :attr:`signum` (and prints what happens
    next); the loop checks :attr:`requested` between epochs. The previous handlers come back on
    the first signal (so a second one acts as it would have: ``KeyboardInterrupt`` / termination)
    and when the block exits. Outside the main thread, where Python cannot install handlers, the
    block does nothing and signals keep their usual effect.
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, object] = {}

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def __enter__(self) -> StopRequests:
        if threading.current_thread() is threading.main_thread():
            for signum in STOP_SIGNALS:
                self._previous[signum] = signal.signal(signum, self._on_signal)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self._restore()

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        self.signum = signum
        self._restore()  # a second signal takes the usual, immediate path
        print(f"\n{signal.Signals(signum).name} received: finishing this epoch, saving a checkpoint, "
              "then stopping (send it again to stop at once)", file=sys.stderr, flush=True)

    def _restore(self) -> None:
        for signum, handler in self._previous.items():
            # None: the handler was not installed from Python; the default is the closest we can restore.
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)
        self._previous.clear()
