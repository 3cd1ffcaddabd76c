"""Shared output helpers of the benchmark scripts (run as ``python benchmarks/<script>.py``)."""

from __future__ import annotations

import json
import platform

import mujoco
import torch

import sg_torchrl


def write_json(path: str, rows: list[dict], *, threads: int) -> None:
    """Write benchmark rows with the software versions they were measured with."""
    meta = {
        "python": platform.python_version(), "torch": torch.__version__, "mujoco": mujoco.__version__,
        "sg_torchrl": sg_torchrl.__version__, "threads": threads, "machine": platform.machine(),
    }
    with open(path, "w") as handle:
        json.dump({"meta": meta, "results": rows}, handle, indent=2)
