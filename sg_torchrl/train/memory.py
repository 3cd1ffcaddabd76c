"""Keep freed heap memory in the process (glibc on Linux), for the seed group's large per-epoch temporaries.

The stacked trust-region step of a seed group (:mod:`sg_torchrl.objectives.stacked_trust_region`) allocates
and frees tensors of a few to tens of MB many times per call (S seeds' activations, their
double-backward graphs, the line search's candidates). With glibc's defaults, blocks above the
dynamic mmap threshold are mapped and unmapped on every allocation, and the top of the heap is
trimmed back to the OS when freed, so each call faults the same pages in again: 400,000-650,000
minor page faults per call at 20,000 samples per seed (``benchmarks/trust_region_group.py``), time the
single-seed steps, whose temporaries are smaller, do not pay. :func:`keep_freed_memory` tells malloc
to keep what it frees (``mallopt``: no trimming, no mmap below 32 MiB); it is what
``MALLOC_TRIM_THRESHOLD_`` / ``MALLOC_MMAP_THRESHOLD_`` in the environment would do, set from inside
the process. The cost: the process's resident memory stays at its peak instead of shrinking between
epochs (the peak itself does not change).

Measured (2-core CPU shared with other work, one torch thread, HalfCheetah, S = 3 seeds of 20,000
steps per epoch, update of each epoch after the first): CPO 355,000-600,000 minor page faults per
update and 6.8-7.4 CPU s with glibc's defaults, 0-100,000 and 6.1-6.7 CPU s kept; PPO-Lag
300,000-330,000 and 26.8-27.6 CPU s against 0-15,000 and 24.5-24.8 CPU s; the peak resident memory
the same within 6 % (1.01 against 0.95-0.97 GB, 0.59 against 0.61 GB).

It is process-wide, so it is called once, where a process starts training the on-policy family
(:class:`~sg_torchrl.train.seed_group.OnPolicyGroupTrainer`), and does nothing off Linux or without glibc
(musl, macOS, Windows).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform
import sys

__all__ = ["keep_freed_memory"]

# mallopt's parameter numbers (glibc's malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD = 32 * 1024 * 1024  # the largest glibc accepts on 64-bit (HEAP_MAX_SIZE / 2)


def keep_freed_memory() -> bool:
    """Ask glibc's malloc to keep freed memory in the process; returns whether it was applied.

    Sets ``M_MMAP_THRESHOLD`` to 32 MiB (blocks below it come from the heap, not from ``mmap``)
    and ``M_TRIM_THRESHOLD`` to ``2**31 - 1`` (the heap is never given back).
    Idempotent; a no-op returning ``False`` off Linux, without glibc or when ``mallopt`` refuses.
    """
    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)) & bool(mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))
