"""The package's one minibatch update loop, shared by single- and multi-agent training.

Every gradient-based update in SafePO (Safety-Gymnasium paper, appendix) has the same shape: a
number of passes over a batch, each pass split into minibatches, one optimiser step per minibatch
on a sum of loss terms with norm-clipped gradients, and after each pass an optional early stop on
the KL between the policy before the update and now. What differs between the algorithms is only:

* the **order** of the minibatches (:data:`Order`): :func:`shuffled_slices` (a fresh permutation
  per pass cut into slices of a size: the single-agent trainer), :func:`shuffled_chunks` (a
  permutation cut into ``k`` chunks: the multi-agent rounds) and :func:`whole_batch` (one step on
  the batch as it is, drawing nothing from the generator: ``shuffled_chunks(1)``);
* the **step** (:class:`GradientStep`): which loss terms are summed, which parameter groups are
  clipped separately (one group over the actor and both critics in the single-agent trainer; the
  actor, the reward critic and the cost critic each on its own in the multi-agent rounds), and an
  after-step hook (MAPPO-Lag steps each agent's multiplier after every minibatch step);
* the **metrics** averaged over the steps (loss outputs, and the pre-clip norms of named groups);
* the **stop**: ``stop()`` (a KL) compared with ``target_kl`` after each pass.

:func:`run_passes` is that loop; the trainer's first-order, two-stage and trust-region updates
(:mod:`sg_torchrl.train.updates`), the multi-agent PPO agent update and the critic epochs of MACPO
(:mod:`sg_torchrl.objectives.multi_agent.updates`) are its callers, so a change to the loop (the
order of the random draws, of the float operations, of the hooks) happens in one place for all.
The stacked seed-group passes (:mod:`sg_torchrl.train.group_updates`) are a separate loop over
per-seed masked tensors, not over TensorDicts.

It lives in :mod:`sg_torchrl.objectives` (not in :mod:`sg_torchrl.train`) because the
multi-agent rounds are objectives and must not import the trainer.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
from tensordict import TensorDictBase
from torch import Tensor

__all__ = [
    "ClipGroup", "GradientStep", "LossFn", "Order", "PassesReport", "run_passes", "shuffled_chunks", "shuffled_slices",
    "whole_batch",
]

#: A loss: a minibatch in, its named outputs (a dict or a TensorDict of tensors) out.
LossFn = Callable[[TensorDictBase], Mapping[str, Tensor]]

#: The minibatches of one pass: ``order(size, generator)`` yields index tensors into the batch's
#: first dim, or ``None`` for the whole batch as it is (no gather, no copy). It is called once at
#: the start of each pass, so a shuffled order draws its permutation there.
Order = Callable[[int, "torch.Generator | None"], Iterable["Tensor | None"]]


def whole_batch(size: int, generator: torch.Generator | None) -> tuple[None]:
    """One minibatch, the whole batch in its own order; draws nothing from ``generator``."""
    return (None,)


def shuffled_slices(minibatch_size: int) -> Order:
    """A fresh permutation per pass, cut into slices of ``minibatch_size`` (the last may be shorter).

    The single-agent trainer's order (SafePO's first-order loop): the permutation is drawn even
    when one slice covers the whole batch (that minibatch is then the batch shuffled).
    """
    if minibatch_size < 1:
        raise ValueError(f"minibatch_size must be >= 1, got {minibatch_size}.")

    def order(size: int, generator: torch.Generator | None) -> Iterable[Tensor]:
        permutation = torch.randperm(size, generator=generator)
        return (permutation[start : start + minibatch_size] for start in range(0, size, minibatch_size))

    return order


def shuffled_chunks(num_minibatches: int) -> Order:
    """``num_minibatches`` chunks of a fresh permutation per pass; one "chunk" is :func:`whole_batch`.

    The multi-agent rounds' order: with one minibatch (the paper's setting) each step sees the
    batch unshuffled and no permutation is drawn, so the generator (shared with the rounds' agent
    orders) only moves when there is something to shuffle. ``k`` chunks of a permutation of ``n``
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


class PassesReport(NamedTuple):
    """What :func:`run_passes` reports (a tuple: ``passes, kl, means = run_passes(...)``).

    Attributes:
        passes: passes run (SafePO's ``StopIter``).
        kl: the last ``stop()`` value, ``0.0`` when it never ran.
        means: each metric averaged over the optimiser steps (``0.0`` when none ran).
    """

    passes: int
    kl: float
    means: dict[str, float]


def run_passes(
    data: TensorDictBase,
    step: GradientStep,
    *,
    passes: int,
    order: Order,
    generator: torch.Generator | None = None,
    metrics: Mapping[str, str] | Sequence[str] = (),
    stop: Callable[[], float] | None = None,
    target_kl: float | None = None,
) -> PassesReport:
    """Up to ``passes`` passes of ``step`` over the minibatches of ``data`` that ``order`` yields.

    Args:
        data: the batch; minibatches are gathered along its first batch dim.
        step: the optimiser step per minibatch.

    Keyword Args:
        passes: the most passes (epochs) to run.
        order: the minibatches of a pass (:func:`shuffled_slices`, :func:`shuffled_chunks`,
            :func:`whole_batch`), drawn from ``generator``.
        generator: the minibatch shuffles' generator (the caller checkpoints it).
        metrics: averaged loss outputs, as ``{metric name: output name}`` or a sequence of output
            names reported under their own name; the norms of ``step``'s named clip groups follow.
        stop: after a pass, e.g. the mean KL(policy before the update || now). With ``target_kl``
            it runs after every pass and the loop ends once it exceeds ``target_kl`` (SafePO's
            early stop); without, it runs after the last pass only (for the metric).
        target_kl: the stop's threshold (``None``: no early stop).

    Returns:
        :class:`PassesReport`.
    """
    names = dict(metrics) if isinstance(metrics, Mapping) else {name: name for name in metrics}
    norm_names = {index: group.norm_metric for index, group in enumerate(step.clip_groups)
                  if group.norm_metric is not None}
    sums = dict.fromkeys([*names, *norm_names.values()], 0.0)
    size = data.batch_size[0]
    steps, kl, done = 0, 0.0, 0
    for done in range(1, passes + 1):
        for index in order(size, generator):
            out, norms = step(data if index is None else data[index])
            for name, key in names.items():
                sums[name] += out[key].item()
            for position, name in norm_names.items():
                sums[name] += norms[position].item()
            steps += 1
        if stop is not None and (target_kl is not None or done == passes):
            kl = stop()
            if target_kl is not None and kl > target_kl:
                break
    return PassesReport(done, kl, {name: total / max(steps, 1) for name, total in sums.items()})
