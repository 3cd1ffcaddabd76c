"""How one epoch's batch moves the networks: the three update loops of SafePO, as objects.

The trainer computes both advantages once per epoch (GAE, then SafePO's batch normalisation) and
hands the flat batch to the algorithm's :class:`PolicyUpdate`:

* :class:`FirstOrderUpdate` (PG, PPO, PPO-Lag, CPPO-PID, FOCOPS): shuffled minibatch passes of
  one Adam step on actor + reward critic + cost critic, stopping once the batch KL to the rollout
  policy exceeds ``target_kl`` (Safety-Gymnasium paper, appendix; SafePO's first-order loop).
* :class:`TwoStageUpdate` (CUP, Yang et al. 2022): the first-order loop on the reward-only stage,
  then actor-only passes of the projection loss towards the stage-one policy.
* :class:`TrustRegionUpdate` (NPG, TRPO, TRPO-Lag, RCPO, CPO, PCPO): one trust-region step of the
  actor on the whole batch (:mod:`sg_torchrl.objectives.trust_region`), then minibatch passes on
  the two critics only.

All three go through :func:`minibatch_passes`, the trainer's form of the package's one minibatch
loop (:func:`sg_torchrl.objectives.passes.run_passes`, which the multi-agent rounds share). Passes over the
whole batch that need no gradient (the critics' values for GAE, the KL early stop, CUP's stage-one
policy) go through :func:`forward_in_chunks`, so a batch of images is converted to float one slice at a time.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor, nn

from sg_torchrl.objectives import gaussian_kl
from sg_torchrl.train.models import forward_in_chunks, write_values
from sg_torchrl.objectives.passes import (
    ClipGroup, GradientStep, LossFn, PassesReport, run_passes, shuffled_slices,
)

__all__ = [
    "FirstOrderUpdate", "PolicyUpdate", "TrustRegionUpdate", "TwoStageUpdate", "UpdateParts", "forward_in_chunks",
    "loss_inputs", "minibatch_passes", "write_values",
]


@dataclass
class UpdateParts:
    """What every update loop works with (built by the trainer).

    Attributes:
        actor: the policy (writes ``loc`` / ``scale``).
        critics: reward and cost critics.
        loss: the algorithm's loss module.
        optimizer: Adam over the actor (first order only) and the critics.
        rng: generator of the minibatch order (checkpointed by the trainer).
        passes, minibatch_size, target_kl, max_grad_norm: the config's values.
        chunk_size: samples per no-grad pass of the actor over the whole batch (``None``: all at
            once; images: :data:`~sg_torchrl.train.models.IMAGE_CHUNK`).
        compile: run the minibatch losses through ``torch.compile`` (:meth:`loss_step`).
    """

    actor: nn.Module
    critics: Sequence[nn.Module]
    loss: nn.Module
    optimizer: torch.optim.Optimizer
    rng: torch.Generator
    passes: int
    minibatch_size: int
    target_kl: float
    max_grad_norm: float
    chunk_size: int | None = None
    compile: bool = False
    _compiled: dict[LossFn, LossFn] = field(default_factory=dict, init=False, repr=False)

    def loss_step(self, loss_fn: LossFn) -> LossFn:
        """``loss_fn`` as the minibatch loop calls it: itself, or with ``compile`` its compiled form.

        A first-order minibatch step on SafePO's 64-sample batches and 64x64 networks is a few
        hundred tiny tensor operations, so eager PyTorch spends most of it dispatching; inductor
        fuses the loss's forward and backward into a few C++ kernels. Each loss is compiled once
        per run (kept here) with static shapes: one graph for full minibatches and one for the
        shorter last minibatch of a pass. The optimiser step stays eager, and the multiplier and the
        losses' coefficients are read as tensors, so later epochs reuse the graphs without recompiling
        (:func:`loss_inputs` keeps the input's keys in one order, which the graphs also guard on).
        """
        if not self.compile:
            return loss_fn
        compiled = self._compiled.get(loss_fn)
        if compiled is None:
            # TorchRL losses fill their in_keys / out_keys caches on first use; filled before
            # compiling, the graph does not guard on an empty cache that the first call then fills.
            owner = _loss_module(loss_fn)
            for name in ("in_keys", "out_keys"):
                getattr(owner, name, None)
            compiled = self._compiled[loss_fn] = torch.compile(loss_fn, dynamic=False)
        return compiled

    def dist_params(self, data: TensorDictBase) -> tuple[Tensor, Tensor]:
        """The current policy's ``loc`` and ``scale`` on every sample of the flat ``data`` (no gradient)."""
        out = forward_in_chunks(self.actor.get_dist_params, data, self.actor.in_keys, ("loc", "scale"),
                                self.chunk_size)
        return out["loc"], out["scale"]

    def policy_kl(self, data: TensorDictBase, loc: Tensor, scale: Tensor) -> float:
        """Mean KL(reference || current policy) over ``data``; ``loc`` / ``scale`` are the reference's."""
        current_loc, current_scale = self.dist_params(data)
        return gaussian_kl(loc, scale, current_loc, current_scale).mean().item()


def _loss_module(loss_fn: LossFn) -> object:
    """The loss behind ``loss_fn``: the module itself, or the owner of a bound method (``loss.critic_losses``)."""
    return getattr(loss_fn, "__self__", loss_fn)


def loss_inputs(loss_fn: LossFn, data: TensorDictBase) -> TensorDictBase:
    """The entries of ``data`` that ``loss_fn`` reads, in the order of its loss's ``in_keys``.

    ``loss_fn`` is a TorchRL loss or one of its bound methods (``loss.critic_losses``); a callable
    without ``in_keys`` gets ``data`` itself. Minibatches gathered from the selection copy only what
    the loss reads (not the ``"next"`` observations, values, rewards, ...), and their keys come in
    the same order every epoch, which compiled losses guard on.
    """
    in_keys = getattr(_loss_module(loss_fn), "in_keys", None)
    return data if in_keys is None else data.select(*in_keys)


def minibatch_passes(
    parts: UpdateParts,
    data: TensorDictBase,
    loss_fn: LossFn,
    terms: Sequence[str],
    parameters: Sequence[Tensor],
    *,
    passes: int,
    minibatch_size: int,
    stop: Callable[[], float] | None = None,
) -> PassesReport:
    """The trainer's passes of the shared loop (:func:`~sg_torchrl.objectives.passes.run_passes`).

    Up to ``passes`` shuffled passes (a fresh permutation from ``parts.rng`` per pass, slices of
    ``minibatch_size``) of one step of ``parts.optimizer`` per minibatch on the sum of ``terms``,
    with the gradients of ``parameters`` norm-clipped together at ``parts.max_grad_norm``. After
    each pass ``stop()`` (a KL) is compared with ``parts.target_kl`` and the loop ends once it is
    exceeded, SafePO's early stop. Minibatches are gathered from :func:`loss_inputs` only (not the
    whole shuffled batch at once: with images and their ``"next"`` frames, that copy alone is
    hundreds of MB per pass), and the loss runs through :meth:`UpdateParts.loss_step`.

    Returns:
        ``(passes run, last stop() value or 0, mean of each term over the steps)``.
    """
    step = GradientStep(parts.loss_step(loss_fn), parts.optimizer, tuple(terms), (ClipGroup(parameters),),
                        parts.max_grad_norm, foreach=True)
    return run_passes(loss_inputs(loss_fn, data), step, passes=passes, order=shuffled_slices(minibatch_size),
                      generator=parts.rng, metrics=terms, stop=stop, target_kl=parts.target_kl)


def _critic_parameters(parts: UpdateParts) -> list[Tensor]:
    return [p for critic in parts.critics for p in critic.parameters()]


_ALL_TERMS = ("loss_objective", "loss_critic", "loss_cost_critic")


class PolicyUpdate(abc.ABC):
    """One epoch's update of the networks from the prepared batch."""

    def __init__(self, parts: UpdateParts) -> None:
        self.parts = parts

    @abc.abstractmethod
    def __call__(self, data: TensorDictBase, cost_violation: float) -> dict[str, float]:
        """Update on ``data`` (flat, advantages normalised, rollout ``loc`` / ``scale`` inside).

        ``cost_violation`` is :math:`J_c - d`, the epoch's mean episode cost minus the limit (read by
        CPO and PCPO). Returns the epoch's update metrics under SafePO's names.
        """

    def _first_order(self, data: TensorDictBase, loss: nn.Module) -> dict[str, float]:
        parts = self.parts
        old_loc, old_scale = data["loc"].clone(), data["scale"].clone()
        parameters = [*parts.actor.parameters(), *_critic_parameters(parts)]
        passes, kl, means = minibatch_passes(
            parts, data, loss, _ALL_TERMS, parameters, passes=parts.passes, minibatch_size=parts.minibatch_size,
            stop=lambda: parts.policy_kl(data, old_loc, old_scale),
        )
        return {
            "Train/KL": kl,
            "Train/StopIter": passes,
            "Loss/Loss_actor": means["loss_objective"],
            "Loss/Loss_reward_critic": means["loss_critic"],
            "Loss/Loss_cost_critic": means["loss_cost_critic"],
        }


class FirstOrderUpdate(PolicyUpdate):
    """SafePO's first-order loop: minibatch Adam steps on the actor and both critics, KL early stop."""

    def __call__(self, data: TensorDictBase, cost_violation: float) -> dict[str, float]:
        return self._first_order(data, self.parts.loss)


class TwoStageUpdate(PolicyUpdate):
    """CUP's epoch (Yang et al. 2022, "Constrained Update Projection Approach to Safe Policy Optimization").

    Stage one runs the first-order loop on ``loss.reward_stage`` (PPO on the reward advantage, both
    critics trained). The stage-one policy's ``loc`` / ``scale`` are then written into the batch
    (``stage1_loc`` / ``stage1_scale``) and stage two takes actor-only passes of the projection
    loss ``loss`` until KL(stage one || current) exceeds ``target_kl``.
    """

    def __call__(self, data: TensorDictBase, cost_violation: float) -> dict[str, float]:
        parts = self.parts
        metrics = self._first_order(data, parts.loss.reward_stage)
        loc, scale = parts.dist_params(data)
        data.set("stage1_loc", loc)
        data.set("stage1_scale", scale)
        passes, kl, means = minibatch_passes(
            parts, data, parts.loss, ("loss_objective",), list(parts.actor.parameters()), passes=parts.passes,
            minibatch_size=parts.minibatch_size, stop=lambda: parts.policy_kl(data, loc, scale),
        )
        metrics.update({"Train/ProjectionStopIter": passes, "Train/ProjectionKL": kl,
                        "Loss/Loss_projection": means["loss_objective"]})
        return metrics


class TrustRegionUpdate(PolicyUpdate):
    """Second-order epoch: one trust-region step of the actor, then the critics' minibatch passes.

    The step (``policy_step``, e.g. :class:`~sg_torchrl.objectives.CPOStep`) sees the whole batch with
    the Lagrangian advantage ``multiplier.combine(A_r, A_c)`` (the reward advantage itself for the
    unconstrained and projection methods, whose multiplier is :class:`~sg_torchrl.objectives.NoMultiplier`).
    Critics then take ``passes`` passes of minibatch Adam steps (SafePO: 10 of 128 at lr 1e-3) with
    no early stop.
    """

    def __init__(self, parts: UpdateParts, policy_step, multiplier) -> None:
        super().__init__(parts)
        self.policy_step = policy_step
        self.multiplier = multiplier

    def __call__(self, data: TensorDictBase, cost_violation: float) -> dict[str, float]:
        parts = self.parts
        advantage = self.multiplier.combine(data["advantage"], data["cost_advantage"])
        metrics = dict(self.policy_step.step(data, advantage, data["cost_advantage"], cost_violation))
        _, _, means = minibatch_passes(
            parts, data, parts.loss.critic_losses, ("loss_critic", "loss_cost_critic"), _critic_parameters(parts),
            passes=parts.passes, minibatch_size=parts.minibatch_size,
        )
        metrics.update({"Train/StopIter": parts.passes, "Loss/Loss_reward_critic": means["loss_critic"],
                        "Loss/Loss_cost_critic": means["loss_cost_critic"]})
        return metrics
