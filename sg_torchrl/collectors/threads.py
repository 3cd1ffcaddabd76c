"""Thread settings for collection on small CPU machines.

On 2-core machines torch's default intra-op thread count makes the small-MLP forward passes of a
collection loop about 10x slower (stack notes, pitfall 1: 0.8k vs 7.5k frames/s). Collection
should therefore run with ``torch.set_num_threads(1)``. sg_torchrl's collector factory does not
change this global setting behind the caller's back; wrap the collection loop instead::

    with single_thread():
        for batch in collector:
            ...
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

__all__ = ["single_thread"]


@contextmanager
def single_thread() -> Iterator[None]:
    """Run the block with ``torch.set_num_threads(1)``; restore the previous count on exit.

    Also usable as a function decorator.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
