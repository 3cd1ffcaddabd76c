"""The package's one minibatch update loop, shared by the seed-group passes and the multi-agent rounds.

Every gradient-based update in SafePO (Safety-Gymnasium paper, appendix) has the same shape: a
number of passes over a batch, each pass split into minibatches, one optimiser step per minibatch
on a sum of loss terms with norm-clipped gradients, and after each pass an optional early stop on
the KL between the policy before the update and now. What differs between the callers is only:

* the **order** of the minibatches (:data:`Order`, any callable yielding minibatch indices):
  :func:`whole_batch` (one step on the batch as it is, drawing nothing from a generator) or a seed
  group's per-seed orders (``(S, mb)`` index blocks from :class:`~sg_torchrl.train.fused.SeedShuffler`,
  one generator per seed);
* the **step** (:data:`Step`): a seed group's fused step of S seeds at once, or a multi-agent round's
  step of its rows, seeds that stopped masked;
* the **metrics** averaged over the steps (:class:`RowMeans`: ``(S,)`` tensors, each seed averaged over
  the steps it took, no host sync: the caller reads them once per epoch);
* the **stop**: ``go_on()`` after each pass, any decision whether to run another (each seed's KL stop
  and divergence shrink its active mask there, and the passes end when no seed is left).

:func:`run_passes` is that loop; the multi-agent rounds' epochs (:mod:`sg_torchrl.train.multi_agent_round`)
and the seed group's passes (:func:`sg_torchrl.train.group_updates.seed_passes`) are its callers, so a
change to the loop (the order of the random draws, of the float operations, of the hooks) happens in one
place for all. What stays with the caller is what only it has: the fused step's masking and per-seed
clipping (:class:`~sg_torchrl.train.seed_adam.SeedMaskedAdam`), its per-seed stop bookkeeping and the
snapshot that puts a diverged seed back.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor

__all__ = ["Order", "PassesReport", "RowMeans", "Step", "run_passes", "whole_batch"]

#: The minibatches of one pass: ``order(size, generator)`` yields indices ``data[index]`` gathers
#: (``size = len(data)``), or ``None`` for the whole batch as it is (no gather, no copy). It is
#: called once at the start of each pass, so a shuffled order draws its permutation there. Any
#: callable will do: a seed group's yields ``(S, mb)`` blocks from its own per-seed generators.
Order = Callable[[int, "torch.Generator | None"], Iterable["Tensor | None"]]

#: One optimiser step on a minibatch: returns the outputs the metrics read and (unused by
#: :class:`RowMeans`) a sequence of gradient norms.
Step = Callable[[Any], tuple[Mapping[str, Tensor], Sequence[Tensor]]]


def whole_batch(size: int, generator: torch.Generator | None) -> tuple[None]:
    """One minibatch, the whole batch in its own order; draws nothing from ``generator``."""
    return (None,)


class RowMeans:
    """What :func:`run_passes` averages: metrics kept as float64 tensors with one entry per row (per seed),
    never read back per step (one :meth:`add` per optimiser step, :meth:`result` at the end).

    Each step adds ``output * weight`` to a metric's sum and ``weight`` to the row counts, so a row
    whose weight is 0 (a seed that no longer steps) is not averaged over those steps; :meth:`result`
    divides each row's sum by its own count (1 when it took none). :attr:`weight` is the owner's to
    set between passes (a seed group: its active mask as float64); :attr:`sums` can be read between
    steps without a sync (a seed group checks them for non-finite losses after each pass).

    Args:
        metrics: averaged step outputs, as ``{metric name: output name}`` or a sequence of output names
            reported under their own name; each output must broadcast with ``weight`` to ``shape``.
        shape: each metric's shape; the rows are its last dim (e.g. ``(terms, S)`` for a stack of
            ``terms`` per-seed losses).
        device: where the sums live.
    """

    def __init__(self, metrics: Mapping[str, str] | Sequence[str], shape: Sequence[int],
                 device: torch.device | str | None = None) -> None:
        self.names = dict(metrics) if isinstance(metrics, Mapping) else {name: name for name in metrics}
        f64 = dict(dtype=torch.float64, device=device)
        self.sums = {name: torch.zeros(*shape, **f64) for name in self.names}
        self.steps = torch.zeros(shape[-1], **f64)
        self.weight = torch.ones(shape[-1], **f64)

    def add(self, out: Mapping[str, Tensor], norms: Sequence[Tensor]) -> None:
        weight = self.weight
        for name, key in self.names.items():
            self.sums[name] += out[key].to(torch.float64) * weight
        self.steps += weight

    def result(self) -> dict[str, Tensor]:
        """Each metric's per-row mean over the steps that row took."""
        steps = self.steps.clamp_min(1.0)
        return {name: total / steps for name, total in self.sums.items()}


class PassesReport(NamedTuple):
    """What :func:`run_passes` reports (a tuple: ``passes, means = run_passes(...)``).

    Attributes:
        passes: passes run (SafePO's ``StopIter`` when every row ran them all).
        means: each metric averaged over the optimiser steps (:meth:`RowMeans.result`).
    """

    passes: int
    means: dict[str, Any]


def run_passes(
    data: Any,
    step: Step,
    *,
    passes: int,
    order: Order,
    metrics: RowMeans,
    generator: torch.Generator | None = None,
    go_on: Callable[[], bool] | None = None,
) -> PassesReport:
    """Up to ``passes`` passes of ``step`` over the minibatches of ``data`` that ``order`` yields.

    Args:
        data: the batch: a TensorDict (minibatches gathered along its first batch dim) or anything
            with ``len(data)`` (what the indices range over) and ``data[index]`` (the minibatch), as
            a seed group's :class:`~sg_torchrl.train.fused.SeedBatch`.
        step: the optimiser step per minibatch (any :data:`Step`).

    Keyword Args:
        passes: the most passes (epochs) to run.
        order: the minibatches of a pass (:func:`whole_batch` or any :data:`Order`), drawn from ``generator``.
        metrics: what averages the steps' outputs (:class:`RowMeans`: per-seed tensors, no host sync).
        generator: handed to ``order`` (the caller checkpoints it).
        go_on: after every pass, whether to run another; ``False`` ends the loop (per-seed stops shrink
            their mask there). ``None``: always.

    Returns:
        :class:`PassesReport`.
    """
    size = len(data)
    done = 0
    for done in range(1, passes + 1):
        for index in order(size, generator):
            metrics.add(*step(data if index is None else data[index]))
        if go_on is not None and not go_on():
            break
    return PassesReport(done, metrics.result())
