"""What the ``--device`` tests share: counting the calls that read a tensor back to the host, and a
checkpoint's tensors.

:func:`counting_host_reads` patches the tensor methods that hand a value to Python (on a GPU, each waits
for the device) so that a test can count them while a block runs; ``paused`` leaves out what a block
does inside the functions it names (the replay buffers, which live on the host).
"""

from __future__ import annotations

import collections
import contextlib
import functools
import warnings
from collections.abc import Callable, Iterator

import torch

#: The tensor methods that hand a value to Python, which on a GPU waits for the device.
HOST_READS = ("item", "tolist", "cpu", "numpy", "__float__", "__int__", "__bool__")
CUDA = "needs a CUDA device"


@contextlib.contextmanager
def counting_host_reads(monkeypatch) -> Iterator[collections.Counter[str]]:
    """Count calls of :data:`HOST_READS` on any tensor while the block runs."""
    counts: collections.Counter[str] = collections.Counter()
    with monkeypatch.context() as patch:
        for name in HOST_READS:
            original = getattr(torch.Tensor, name)

            def counted(self, *args, _name=name, _original=original, **kwargs):
                if not counts.get("<paused>"):
                    counts[_name] += 1
                return _original(self, *args, **kwargs)

            patch.setattr(torch.Tensor, name, counted)
        yield counts
    counts.pop("<paused>", None)


def only_within(monkeypatch, counts: collections.Counter[str], owner: type, method: str,
                paused: tuple[tuple[type, str], ...] = ()) -> None:
    """Count only inside ``owner.method`` (pausing the count elsewhere), and not inside the ``paused`` methods."""

    def wrap(cls: type, name: str, counting: bool) -> None:
        original: Callable = getattr(cls, name)

        @functools.wraps(original)
        def wrapped(self, *args, **kwargs):
            before = counts.get("<paused>", 0)
            counts["<paused>"] = 0 if counting else 1
            try:
                return original(self, *args, **kwargs)
            finally:
                counts["<paused>"] = before

        monkeypatch.setattr(cls, name, wrapped)

    counts["<paused>"] = 1
    wrap(owner, method, True)
    for cls, name in paused:
        wrap(cls, name, False)


def tensors(tree) -> Iterator[torch.Tensor]:
    """Every tensor in a checkpoint's nested dicts and lists."""
    if isinstance(tree, torch.Tensor):
        yield tree
    elif isinstance(tree, dict):
        for value in tree.values():
            yield from tensors(value)
    elif isinstance(tree, (list, tuple)):
        for value in tree:
            yield from tensors(value)


def synchronising_calls(work: Callable[[], object]) -> int:
    """CUDA calls that synchronise with the host (``torch.cuda.set_sync_debug_mode("warn")``) while ``work`` runs."""
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            work()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    return sum("synchroniz" in str(w.message) for w in caught)
