"""What a sweep's output directory holds, read and written in one place.

The runner (:mod:`sg_torchrl.sweep.runner`), each cell's task (:mod:`sg_torchrl.sweep.cell`) and the report
(:mod:`sg_torchrl.sweep.report`) all read the same files: the sweep's ``sweep.json``, a cell's
``attempts.jsonl`` and its seeds' ``progress.csv``. Their formats live here, with no Ray, torch or
platform-specific import, so the report stays runnable on a copy of the directory anywhere.
"""

from __future__ import annotations

import csv
import json
import math
import time
from pathlib import Path
from typing import Any, Iterable

from sg_torchrl.train.writes import write_atomic

__all__ = [
    "AttemptLog", "SWEEP_RECORD", "epochs_logged", "finite_mean", "finite_ratio", "is_finite_number", "latest",
    "parse_float", "read_progress",
]

#: The sweep's record at the root of its output directory (grid, shared options, cells, storage token).
SWEEP_RECORD = "sweep.json"
NAN = float("nan")


def parse_float(value: Any) -> float:
    """``value`` as a float; NaN for ``None``, an empty CSV field or anything that is not a number."""
    try:
        return float(value) if value not in (None, "") else NAN
    except (TypeError, ValueError):
        return NAN


def is_finite_number(value: Any) -> bool:
    """Whether ``value`` is a finite int or float (a bool, NaN, infinity or anything else is not)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def finite_mean(values: Iterable[Any]) -> float:
    """Mean of the finite numbers among ``values`` (NaN if none): a seed or epoch without a figure is left out."""
    finite = [float(value) for value in values if is_finite_number(value)]
    return sum(finite) / len(finite) if finite else NAN


def finite_ratio(numerator: Any, denominator: Any) -> float:
    """``numerator / denominator`` when both are finite numbers and the denominator is not 0, else NaN."""
    if is_finite_number(numerator) and is_finite_number(denominator) and denominator:
        return numerator / denominator
    return NAN


def read_progress(path: Path) -> list[dict[str, float]]:
    """The rows of a ``progress.csv`` with numbers parsed (an empty field is NaN); ``[]`` if absent."""
    if not path.is_file():
        return []
    with path.open() as handle:
        return [{key: parse_float(value) for key, value in row.items() if key is not None}
                for row in csv.DictReader(handle)]


def latest(rows: list[dict[str, float]], key: str) -> float:
    """The last finite ``key`` of ``rows`` (NaN if none): the final evaluation row, for one, holds no epoch."""
    return next((row[key] for row in reversed(rows) if math.isfinite(row.get(key, NAN))), NAN)


def epochs_logged(directory: Path, seeds: list[int]) -> int:
    """Epoch rows in the first seed's ``progress.csv`` (training rows: those with an epoch number)."""
    rows = read_progress(directory / f"seed-{seeds[0]:03d}" / "progress.csv")
    return sum(1 for row in rows if math.isfinite(row.get("Train/Epoch", NAN)))


class AttemptLog:
    """``<cell>/attempts.jsonl``: one JSON line per attempt at the cell (node address and Ray node id, worker pid,
    start, end, status, ...).

    Written only by the task that holds the cell's lock, rewritten whole (it has a few lines). An
    attempt still ``"running"`` when the next one begins was lost with its worker: it is marked ``"lost"``.
    """

    def __init__(self, directory: Path) -> None:
        self.path = directory / "attempts.jsonl"

    def read(self) -> list[dict[str, Any]]:
        """The attempts so far (a line cut short by a crash is skipped)."""
        try:
            lines = self.path.read_text().splitlines()
        except OSError:
            return []
        attempts = []
        for line in lines:
            try:
                attempts.append(json.loads(line))
            except ValueError:
                continue
        return [attempt for attempt in attempts if isinstance(attempt, dict)]

    def _write(self, attempts: list[dict[str, Any]]) -> None:
        write_atomic(self.path, "".join(json.dumps(a) + "\n" for a in attempts), sync=False)

    @staticmethod
    def _mark_lost(attempts: list[dict[str, Any]]) -> bool:
        lost = [attempt for attempt in attempts if attempt.get("status") == "running"]
        for attempt in lost:
            attempt["status"] = "lost"
        return bool(lost)

    def mark_lost(self) -> None:
        """Mark attempts still ``"running"`` as ``"lost"``: their task ended without saying how (its worker
        died). The next attempt does it when it begins; the driver does it for a cell whose retries ran out."""
        attempts = self.read()
        if self._mark_lost(attempts):
            self._write(attempts)

    def begin(self, **fields: Any) -> int:
        attempts = self.read()
        self._mark_lost(attempts)
        number = len(attempts) + 1
        attempts.append({"attempt": number, "start": time.time(), "end": None, "status": "running", **fields})
        self._write(attempts)
        return number

    def end(self, number: int, status: str, **fields: Any) -> None:
        attempts = self.read()
        attempts[number - 1].update(end=time.time(), status=status, **fields)
        self._write(attempts)
