"""The package's one minibatch update loop, shared by the seed-group passes and the multi-agent rounds.

Every gradient-based update in SafePO (Safety-Gymnasium paper, appendix) has the same shape: a
number of passes over a batch, each pass split into minibatches, one optimiser step per minibatch
on a sum of loss terms with norm-clipped gradients, and after each pass an optional early stop on
the KL between the policy before the update and now. What differs between the algorithms is only:

* the **order** of the minibatches (:data:`Order`, any callable yielding minibatch indices):
  :func:`shuffled_slices` (a fresh permutation per pass cut into slices of a size: SafePO's
  single-agent loop), :func:`shuffled_chunks` (a permutation cut into ``k`` chunks),
  :func:`whole_batch` (one step on the batch as it is, drawing nothing from the generator:
  ``shuffled_chunks(1)``) and a seed group's per-seed orders (``(S, mb)`` index blocks from
  :class:`~sg_torchrl.train.fused.SeedShuffler`, one generator per seed);
* the **step** (:data:`Step`): :class:`GradientStep` (a LossModule's step: which loss terms are summed,
  which parameter groups are clipped separately, an after-step hook), or a seed group's fused step of S
  seeds at once, seeds that stopped masked (the single-agent groups' and the multi-agent rounds');
* the **metrics** averaged over the steps: :class:`StepMeans` (loss outputs and the pre-clip norms
  of named clip groups, read with one ``.item()`` each per step) or :class:`RowMeans` (a seed
  group's ``(S,)`` tensors, each seed averaged over the steps it took, no host sync: the group
  reads them once per epoch);
* the **stop**: ``stop()`` (a KL) compared with ``target_kl`` after each pass, and ``go_on()``,
  any decision whether to run another pass (a seed group's: each seed's KL stop and divergence
  shrink its active mask there, and the passes end when no seed is left).

:func:`run_passes` is that loop; the multi-agent rounds' epochs
(:mod:`sg_torchrl.train.multi_agent_round`) and the seed group's passes
(:func:`sg_torchrl.train.group_updates.seed_passes`) are its callers, so a change to the loop (the
order of the random draws, of the float operations, of the hooks) happens in one place for all.
What stays with the seed group is what only a group has: the fused step's masking and per-seed
clipping (:class:`~sg_torchrl.train.seed_adam.SeedMaskedAdam`), its per-seed stop bookkeeping
(``SeedStops``) and the snapshot that puts a diverged seed back. Going through this loop costs the
group nothing on its hot path: the same tensor ops per step as its former private loop (the same
aten op count per step), no host read per step (:class:`RowMeans`), one per pass (its ``go_on``),
and a few Python calls per step, below the noise of a ~1 ms step.

It lives in :mod:`sg_torchrl.objectives` (not in :mod:`sg_torchrl.train`): a user's own loop over the
LossModules runs it too (:class:`GradientStep`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol, runtime_checkable

import torch
from tensordict import TensorDictBase
from torch import Tensor

__all__ = [
    "ClipGroup", "GradientStep", "LossFn", "Means", "Order", "PassesReport", "RowMeans", "Step", "StepMeans",
    "run_passes", "shuffled_chunks", "shuffled_slices", "whole_batch",
]

#: A loss: a minibatch in, its named outputs (a dict or a TensorDict of tensors) out.
LossFn = Callable[[TensorDictBase], Mapping[str, Tensor]]

#: The minibatches of one pass: ``order(size, generator)`` yields indices ``data[index]`` gathers
#: (``size = len(data)``), or ``None`` for the whole batch as it is (no gather, no copy). It is
#: called once at the start of each pass, so a shuffled order draws its permutation there. Any
#: callable will do: a seed group's yields ``(S, mb)`` blocks from its own per-seed generators.
Order = Callable[[int, "torch.Generator | None"], Iterable["Tensor | None"]]

#: One optimiser step on a minibatch: returns the outputs the metrics read and the pre-clip norm of
#: each clip group (:class:`GradientStep`; a seed group's masked fused step returns no norms).
Step = Callable[[Any], tuple[Mapping[str, Tensor], Sequence[Tensor]]]


def whole_batch(size: int, generator: torch.Generator | None) -> tuple[None]:
    """One minibatch, the whole batch in its own order; draws nothing from ``generator``."""
    return (None,)


def shuffled_slices(minibatch_size: int) -> Order:
    """A fresh permutation per pass, cut into slices of ``minibatch_size`` (the last may be shorter).

    SafePO's first-order order: the permutation is drawn even when one slice covers the whole batch
    (that minibatch is then the batch shuffled).
    """
    if minibatch_size < 1:
        raise ValueError(f"minibatch_size must be >= 1, got {minibatch_size}.")

    def order(size: int, generator: torch.Generator | None) -> Iterable[Tensor]:
        permutation = torch.randperm(size, generator=generator)
        return (permutation[start : start + minibatch_size] for start in range(0, size, minibatch_size))

    return order


def shuffled_chunks(num_minibatches: int) -> Order:
    """``num_minibatches`` chunks of a fresh permutation per pass; one "chunk" is :func:`whole_batch`.

    With one minibatch (the multi-agent paper's setting) each step sees the batch unshuffled and no
    permutation is drawn, so a generator shared with other draws only moves when there is something
    to shuffle (the multi-agent rounds cut each seed's permutation the same way). ``k`` chunks of a permutation of ``n``
    are its slices of ``ceil(n / k)`` samples (``torch.chunk``), fewer than ``k`` when ``n`` is small.
    """
    if num_minibatches < 1:
        raise ValueError(f"num_minibatches must be >= 1, got {num_minibatches}.")
    if num_minibatches == 1:
        return whole_batch

    def order(size: int, generator: torch.Generator | None) -> Iterable[Tensor]:
        return torch.randperm(size, generator=generator).chunk(num_minibatches)

    return order


@dataclass(frozen=True)
class ClipGroup:
    """Parameters whose gradient norm is clipped together (one ``clip_grad_norm_`` call).

    ``norm_metric`` names the metric under which :func:`run_passes` averages the group's norm
    before clipping (``None``: not reported).
    """

    parameters: Sequence[Tensor]
    norm_metric: str | None = None


@dataclass(frozen=True)
class GradientStep:
    """One optimiser step on a minibatch: loss, sum of ``terms``, backward, per-group clip, step, hook.

    Attributes:
        loss: the minibatch loss (its outputs include every name in ``terms``).
        optimizer: steps the parameters the loss reaches (zeroed before each backward).
        terms: outputs summed, in this order, into the loss that is backpropagated.
        clip_groups: each group's gradients are norm-clipped at ``max_grad_norm`` separately, in
            this order, between backward and the optimiser step.
        max_grad_norm: the clip threshold.
        foreach: ``clip_grad_norm_``'s ``foreach`` (``None``: PyTorch's default kernel choice).
        after_step: called with the loss outputs after each optimiser step (MAPPO-Lag's
            multiplier step), or ``None``.
    """

    loss: LossFn
    optimizer: torch.optim.Optimizer
    terms: Sequence[str]
    clip_groups: Sequence[ClipGroup]
    max_grad_norm: float
    foreach: bool | None = None
    after_step: Callable[[Mapping[str, Tensor]], None] | None = None

    def __post_init__(self) -> None:
        if not self.terms:
            raise ValueError("GradientStep needs at least one loss term to backpropagate.")

    def __call__(self, minibatch: TensorDictBase) -> tuple[Mapping[str, Tensor], list[Tensor]]:
        """Takes the step; returns the loss outputs and each clip group's pre-clip gradient norm."""
        out = self.loss(minibatch)
        total = out[self.terms[0]]
        for name in self.terms[1:]:
            total = total + out[name]
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        norms = [
            torch.nn.utils.clip_grad_norm_(group.parameters, self.max_grad_norm, foreach=self.foreach)
            for group in self.clip_groups
        ]
        self.optimizer.step()
        if self.after_step is not None:
            self.after_step(out)
        return out, norms


@runtime_checkable
class Means(Protocol):
    """What :func:`run_passes` averages: one :meth:`add` per optimiser step, :meth:`result` at the end."""

    def add(self, out: Mapping[str, Tensor], norms: Sequence[Tensor]) -> None:
        """Take one step's outputs and clip-group norms into the sums."""

    def result(self) -> dict[str, Any]:
        """Each metric averaged over the steps."""


class StepMeans:
    """Metrics as Python floats: one ``.item()`` per metric per step, the mean over all steps taken.

    Args:
        metrics: averaged step outputs, as ``{metric name: output name}`` or a sequence of output
            names reported under their own name.
        clip_groups: the step's clip groups; the norms of those with a ``norm_metric`` follow.
    """

    def __init__(self, metrics: Mapping[str, str] | Sequence[str], clip_groups: Sequence[ClipGroup] = ()) -> None:
        self.names = dict(metrics) if isinstance(metrics, Mapping) else {name: name for name in metrics}
        self.norm_names = {index: group.norm_metric for index, group in enumerate(clip_groups)
                           if group.norm_metric is not None}
        self.sums = dict.fromkeys([*self.names, *self.norm_names.values()], 0.0)
        self.steps = 0

    def add(self, out: Mapping[str, Tensor], norms: Sequence[Tensor]) -> None:
        sums = self.sums
        for name, key in self.names.items():
            sums[name] += out[key].item()
        for position, name in self.norm_names.items():
            sums[name] += norms[position].item()
        self.steps += 1

    def result(self) -> dict[str, float]:
        """Each metric's mean over the steps (``0.0`` when none ran)."""
        return {name: total / max(self.steps, 1) for name, total in self.sums.items()}


class RowMeans:
    """Metrics kept as float64 tensors with one entry per row (per seed), never read back per step.

    Each step adds ``output * weight`` to a metric's sum and ``weight`` to the row counts, so a row
    whose weight is 0 (a seed that no longer steps) is not averaged over those steps; :meth:`result`
    divides each row's sum by its own count (1 when it took none). :attr:`weight` is the owner's to
    set between passes (a seed group: its active mask as float64); :attr:`sums` can be read between
    steps without a sync (a seed group checks them for non-finite losses after each pass).

    Args:
        metrics: as :class:`StepMeans`; each output must broadcast with ``weight`` to ``shape``.
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
    """What :func:`run_passes` reports (a tuple: ``passes, kl, means = run_passes(...)``).

    Attributes:
        passes: passes run (SafePO's ``StopIter``).
        kl: the last ``stop()`` value, ``0.0`` when it never ran.
        means: each metric averaged over the optimiser steps (:meth:`Means.result`: floats, ``0.0``
            when no step ran, for :class:`StepMeans`; per-row tensors for :class:`RowMeans`).
    """

    passes: int
    kl: float
    means: dict[str, Any]


def run_passes(
    data: Any,
    step: Step,
    *,
    passes: int,
    order: Order,
    generator: torch.Generator | None = None,
    metrics: Mapping[str, str] | Sequence[str] | Means = (),
    stop: Callable[[], float] | None = None,
    target_kl: float | None = None,
    go_on: Callable[[], bool] | None = None,
) -> PassesReport:
    """Up to ``passes`` passes of ``step`` over the minibatches of ``data`` that ``order`` yields.

    Args:
        data: the batch: a TensorDict (minibatches gathered along its first batch dim) or anything
            with ``len(data)`` (what the indices range over) and ``data[index]`` (the minibatch), as
            a seed group's :class:`~sg_torchrl.train.fused.SeedBatch`.
        step: the optimiser step per minibatch (:class:`GradientStep` or any :data:`Step`).

    Keyword Args:
        passes: the most passes (epochs) to run.
        order: the minibatches of a pass (:func:`shuffled_slices`, :func:`shuffled_chunks`,
            :func:`whole_batch`, or any :data:`Order`), drawn from ``generator``.
        generator: the minibatch shuffles' generator (the caller checkpoints it).
        metrics: a :class:`Means` (:class:`RowMeans`: per-seed tensors, no host sync), or the names
            of averaged step outputs for a :class:`StepMeans`, as ``{metric name: output name}`` or
            a sequence of output names reported under their own name; the norms of ``step``'s named
            clip groups follow.
        stop: after a pass, e.g. the mean KL(policy before the update || now). With ``target_kl``
            it runs after every pass and the loop ends once it exceeds ``target_kl`` (SafePO's
            early stop); without, it runs after the last pass only (for the metric).
        target_kl: the stop's threshold (``None``: no early stop).
        go_on: after every pass (after ``stop``), whether to run another; ``False`` ends the
            loop (a seed group's per-seed stops shrink their mask there). ``None``: always.

    Returns:
        :class:`PassesReport`.
    """
    means = metrics if isinstance(metrics, Means) else StepMeans(metrics, getattr(step, "clip_groups", ()))
    size = len(data)
    kl, done = 0.0, 0
    for done in range(1, passes + 1):
        for index in order(size, generator):
            means.add(*step(data if index is None else data[index]))
        if stop is not None and (target_kl is not None or done == passes):
            kl = stop()
            if target_kl is not None and kl > target_kl:
                break
        if go_on is not None and not go_on():
            break
    return PassesReport(done, kl, means.result())
