"""How one epoch's batch moves a seed group's networks: the update loops of SafePO for S seeds at once.

Every single-agent run trains through these (``--seed`` is a group of one). The group trainer
(:mod:`sg_torchrl.train.seed_group`) computes every seed's advantages (normalised per seed) and
hands the algorithm's :class:`GroupUpdate` the epoch's samples as ``(S, n, k)`` tensors, seed ``s``'s
on row ``s``: ``observation``, ``action``, ``action_log_prob``, ``loc`` and ``scale`` (the rollout
policy), ``advantage``, ``cost_advantage``, ``value_target``, ``cost_value_target``. The update is
chosen by the algorithm table (``Algorithm.make_group_update`` in :mod:`sg_torchrl.train.algorithms`):

* :class:`FirstOrderGroupUpdate` (PG, PPO, PPO-Lag, CPPO-PID, FOCOPS): SafePO's first-order loop,
  every seed's minibatch step fused into one (:class:`~sg_torchrl.train.fused.FusedFirstOrderStep`);
* :class:`TwoStageGroupUpdate` (CUP): that loop on the reward stage, then actor-only passes of the
  projection loss towards each seed's stage-one policy;
* :class:`TrustRegionGroupUpdate` (NPG, TRPO, TRPO-Lag, RCPO, CPO, PCPO): the stacked trust-region
  step of every seed's actor (:mod:`sg_torchrl.objectives.stacked_trust_region`), then critics-only passes.

All run :func:`seed_passes`, a group's minibatch passes through the package's one update loop
(:func:`~sg_torchrl.objectives.passes.run_passes`): each seed follows its single-seed run (its own
minibatch order and KL early stop; a seed that stopped is masked and draws no more orders).

**Divergence.** A seed whose loss, KL or parameters turn non-finite during a pass is flagged in
:attr:`GroupResult.diverged`, stops at the end of that pass and is put back to its state before the
update (parameters, Adam moments, step counts: :class:`SeedSnapshot`); the trainer then freezes it
for the rest of the run. Seeds share no parameter and no reduction, so the others train exactly as
they would without it.

Host syncs: none per minibatch step (the losses, the masked Adam and the metric sums stay on the
networks' device), one per pass (which seeds are still active, :class:`SeedStops`) and, for the
trust-region step, its own few per epoch (conjugate-gradient residuals, line-search trials, the
per-seed proposals); metrics come back as ``(S,)`` tensors, which the trainer reads once per epoch.
``tests/test_device.py`` counts them.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import Tensor

from sg_torchrl.modules.stacked import StackedActorCritic, in_chunks
from sg_torchrl.objectives.passes import RowMeans, run_passes
from sg_torchrl.objectives.surrogates import SeedBatchedObjective, combine_advantages
from sg_torchrl.train.fused import FusedFirstOrderStep, SeedBatch, SeedShuffler, batch_kl
from sg_torchrl.train.seed_adam import SeedMaskedAdam
from sg_torchrl.objectives.stacked_trust_region import StackedTrustRegionStep

__all__ = [
    "FirstOrderGroupUpdate", "GroupParts", "GroupResult", "GroupUpdate", "MaskedSeedStep", "PassesResult",
    "SeedSnapshot", "SeedStops", "finite_seeds", "seed_passes", "TrustRegionGroupUpdate", "TwoStageGroupUpdate",
]

#: The per-seed fields every update receives (``(S, n, k)`` each).
FIELDS = ("observation", "action", "action_log_prob", "loc", "scale", "advantage", "cost_advantage", "value_target",
          "cost_value_target")


@dataclass
class GroupParts:
    """What every group update works with (built by the group trainer).

    Attributes:
        model: the seed group's actors and critics.
        optimizer: the masked Adam over ``model.flat_actor`` (group 0) and ``model.flat_critics``
            (group 1), clipping each seed's gradient at the config's ``max_grad_norm`` (over the
            groups a step moves). Second order never steps group 0: its actor moves by the
            trust-region step.
        shuffler: one minibatch-order generator per seed (checkpointed by the trainer).
        passes, minibatch_size, target_kl: the config's values (the same for every seed).
        compile: run the fused minibatch losses through ``torch.compile``.
    """

    model: StackedActorCritic
    optimizer: SeedMaskedAdam
    shuffler: SeedShuffler
    passes: int
    minibatch_size: int
    target_kl: float
    compile: bool = False


@dataclass
class GroupResult:
    """One epoch's update of a seed group.

    Attributes:
        metrics: each seed's update metrics under SafePO's names, ``(S,)`` tensors.
        diverged: ``(S,)`` bool, the seeds whose update turned non-finite (put back to their state
            before the update; the trainer freezes them).
    """

    metrics: dict[str, Tensor]
    diverged: Tensor


def finite_seeds(model: StackedActorCritic) -> Tensor:
    """Which seeds' parameters (actor and both critics) are all finite, ``(S,)`` bool."""
    return torch.isfinite(model.flat_actor).all(1) & torch.isfinite(model.flat_critics).all(1)


class SeedSnapshot:
    """Every seed's parameters, Adam moments and step counts at one moment, to put some seeds back.

    Two parameter buffers and the optimiser's moments, ``(S, P)`` each: a few MB at most, copied once
    per update.
    """

    def __init__(self, model: StackedActorCritic, optimizer: SeedMaskedAdam) -> None:
        self.model, self.optimizer = model, optimizer
        self.params = [tensor.detach().clone() for tensor in model.flat_groups]
        self.state = optimizer.state_dict()

    @torch.no_grad()
    def restore(self, seeds: Tensor) -> None:
        """Put the rows of the seeds where ``seeds`` (``(S,)`` bool) is true back to the snapshot."""
        if not bool(seeds.any()):
            return
        for current, saved in zip(self.model.flat_groups, self.params):
            current.copy_(torch.where(seeds.view(-1, *([1] * (current.dim() - 1))), saved, current))
        self.optimizer.restore_seeds(seeds, self.state)


@dataclass
class PassesResult:
    """What :func:`seed_passes` reports per seed, ``(S,)`` each (``means``: ``(terms, S)``), float64."""

    passes: Tensor
    kl: Tensor
    means: Tensor
    diverged: Tensor


class SeedStops:
    """Which seeds of a group still step during :func:`seed_passes`, and what stopped the others.

    The seed group's ``go_on`` for :func:`~sg_torchrl.objectives.passes.run_passes`: after each pass
    it counts the pass for the seeds that took it, flags a seed whose parameters, summed losses or
    KL turned non-finite (:attr:`diverged`), records each stepping seed's KL and drops from
    :attr:`active` every flagged seed and, given ``kl``, every seed over ``target_kl``; then it
    says whether any seed is left. One host sync per pass (:attr:`flags`, read by the per-seed
    orders); :attr:`mask` (``None`` while every seed steps: the unmasked Adam is the cheaper one)
    and ``means.weight`` are set for the next pass.

    Args:
        model: the group's networks (checked for finite parameters).
        means: the passes' per-seed loss sums (:class:`~sg_torchrl.objectives.passes.RowMeans`,
            metric ``"losses"``); its weight follows :attr:`active`.
        active: ``(S,)`` bool, the seeds that step in the first pass (copied).
        kl: ``None`` (no KL stop: critics-only passes), or a callable returning each seed's KL to
            the reference policy, ``(S,)``.
        target_kl: the KL stop's threshold.
    """

    def __init__(self, model: StackedActorCritic, means: RowMeans, active: Tensor,
                 kl: Callable[[], Tensor] | None, target_kl: float) -> None:
        self.model, self.means, self.kl_fn, self.target_kl = model, means, kl, target_kl
        f64 = dict(dtype=torch.float64, device=active.device)
        self.active = active.clone()
        self.passes, self.kl = torch.zeros(active.shape[0], **f64), torch.zeros(active.shape[0], **f64)
        self.diverged = torch.zeros_like(self.active)
        self.flags = self.active.tolist()
        self._next_pass()

    def _next_pass(self) -> None:
        self.mask = None if all(self.flags) else self.active
        self.means.weight = self.active.to(torch.float64)

    def go_on(self) -> bool:
        """After a pass: count it, flag and stop seeds (see the class docstring); whether any seed steps on."""
        active = self.active
        self.passes += self.means.weight
        finite = finite_seeds(self.model) & torch.isfinite(self.means.sums["losses"]).all(0)
        if self.kl_fn is not None:
            kl = self.kl_fn().to(torch.float64)
            self.kl = torch.where(active, kl, self.kl)
            finite &= torch.isfinite(kl)
        bad = active & ~finite
        self.diverged |= bad
        active &= ~bad
        if self.kl_fn is not None:
            active &= ~(kl > self.target_kl)
        self.flags = active.tolist()
        if not any(self.flags):
            return False
        self._next_pass()
        return True


class MaskedSeedStep:
    """The seed group's :data:`~sg_torchrl.objectives.passes.Step`: a fused step of every seed, stopped seeds masked.

    Backward of ``step``'s losses on the minibatch, then the optimiser step under ``stops.mask``.
    Returns ``{"losses": (terms, S)}``, the per-seed losses as the single-seed losses report them
    (the critics' with their L2 term at the parameters before the step), and no clip-group norms.
    """

    def __init__(self, step: FusedFirstOrderStep, lam: Tensor, stops: SeedStops) -> None:
        self.step, self.lam, self.stops = step, lam, stops
        spec = step.spec
        self.l2 = spec.critic_l2 if not spec.actor_only else 0.0

    def __call__(self, minibatch: SeedBatch) -> tuple[dict[str, Tensor], tuple[()]]:
        values = torch.stack(self.step.backward(minibatch, self.lam))
        if self.l2:  # the critics' losses as reported: with the L2 term at the step's parameters
            norms = torch.stack(self.step.model.critic_squared_norms())
            values = torch.cat((values[:-2], values[-2:] + self.l2 * norms))  # the critics' are the last two
        self.step.update(self.stops.mask)
        return {"losses": values}, ()


def seed_passes(
    parts: GroupParts,
    step: FusedFirstOrderStep,
    data: Mapping[str, Tensor],
    lam: Tensor,
    active: Tensor,
    reference: tuple[Tensor, Tensor] | None,
) -> PassesResult:
    """Up to ``parts.passes`` shuffled passes of ``step`` for the ``active`` seeds, each with its own KL stop.

    The package's one loop (:func:`~sg_torchrl.objectives.passes.run_passes`) with the group's
    pieces: the data is a :class:`SeedBatch`, the order each seed's minibatches from its own
    generator (:class:`SeedShuffler`; a seed that stopped draws none), the step
    :class:`MaskedSeedStep`, the metrics :class:`~sg_torchrl.objectives.passes.RowMeans` and the
    stop :meth:`SeedStops.go_on`. A pass takes one fused gradient step per minibatch (seeds that
    are no longer active masked), then computes each active seed's mean KL(``reference`` ||
    current policy) over its batch: a seed whose KL exceeds ``parts.target_kl`` (SafePO's early
    stop), or whose KL, losses or parameters are not finite (flagged diverged), takes no further
    step. A critics-only step (``spec.kl_stop`` false: the second-order algorithms' critic passes)
    runs every pass with no KL (``reference`` unused, reported KL 0); non-finite losses or
    parameters still stop and flag a seed.

    Args:
        parts: the group's model, optimiser, shuffler and loop settings.
        step: the fused step of the objective (its spec names the fields it reads from ``data``).
        data: the per-seed fields, ``(S, n, k)`` each.
        lam: each seed's multiplier value, ``(S,)``.
        active: ``(S,)`` bool, the seeds that train (frozen seeds do not).
        reference: ``(loc, scale)`` of the policy the KL is measured from, ``(S, n, A)`` each
            (``None`` for a critics-only step).

    Returns:
        Per seed: the passes taken (SafePO's ``StopIter``), the KL after its last pass, the mean of
        each loss term over its steps (the objective unless critics only, then unless actor-only
        each critic's loss with its L2 term, as the single-seed losses report them), and whether it
        diverged.
    """
    model, spec = parts.model, step.spec
    if spec.kl_stop and reference is None:
        raise ValueError(f"the passes of {spec.surrogate!r} stop on the KL to a reference policy: give reference")
    batch = SeedBatch.pack({name: data[name] for name in spec.fields})
    observation = data["observation"]
    means = RowMeans(("losses",), (spec.num_losses, batch.num_seeds), data["advantage"].device)
    kl = (lambda: batch_kl(model, observation, *reference, chunk_size=model.chunk_size)) if spec.kl_stop else None
    stops = SeedStops(model, means, active, kl, parts.target_kl)

    def order(size: int, generator: torch.Generator | None) -> Iterator[Tensor]:
        return parts.shuffler.minibatches(size, parts.minibatch_size, stops.flags, device=batch.data.device)

    report = run_passes(batch, MaskedSeedStep(step, lam, stops), passes=parts.passes if any(stops.flags) else 0,
                        order=order, metrics=means, go_on=stops.go_on)
    return PassesResult(stops.passes, stops.kl, report.means["losses"], stops.diverged)


def _first_order_metrics(result: PassesResult) -> dict[str, Tensor]:
    return {
        "Train/KL": result.kl,
        "Train/StopIter": result.passes,
        "Loss/Loss_actor": result.means[0],
        "Loss/Loss_reward_critic": result.means[1],
        "Loss/Loss_cost_critic": result.means[2],
    }


class GroupUpdate(abc.ABC):
    """One epoch's update of a seed group's networks from its per-seed batch (see the module docstring)."""

    def __init__(self, parts: GroupParts) -> None:
        self.parts = parts

    @abc.abstractmethod
    def __call__(self, data: Mapping[str, Tensor], lam: Tensor, cost_violation: Tensor, active: Tensor
                 ) -> GroupResult:
        """Update the ``active`` seeds on ``data``.

        Args:
            data: the per-seed fields of :data:`FIELDS`, ``(S, n, k)`` each, advantages normalised per seed.
            lam: each seed's multiplier value, ``(S,)``.
            cost_violation: :math:`J_c - d` per seed, ``(S,)`` float64 (read by CPO and PCPO).
            active: ``(S,)`` bool; the other seeds are frozen and must not move.
        """


class FirstOrderGroupUpdate(GroupUpdate):
    """SafePO's first-order loop for every seed: fused minibatch steps of actor and critics, KL stop per seed."""

    def __init__(self, parts: GroupParts, spec: SeedBatchedObjective) -> None:
        super().__init__(parts)
        self.step = FusedFirstOrderStep(parts.model, parts.optimizer, spec, compile=parts.compile)

    def __call__(self, data: Mapping[str, Tensor], lam: Tensor, cost_violation: Tensor, active: Tensor
                 ) -> GroupResult:
        snapshot = SeedSnapshot(self.parts.model, self.parts.optimizer)
        result = seed_passes(self.parts, self.step, data, lam, active, (data["loc"], data["scale"]))
        snapshot.restore(result.diverged)
        return GroupResult(_first_order_metrics(result), result.diverged)


class TwoStageGroupUpdate(GroupUpdate):
    """CUP's epoch for every seed.

    Stage one runs :func:`seed_passes` on ``reward_spec`` (PPO on the reward advantage, both critics,
    no multiplier); each seed's stage-one policy is then evaluated on its batch (``stage1_loc`` /
    ``stage1_scale``) and stage two takes actor-only passes of ``projection_spec`` (Adam's actor
    group only, as the single-seed update steps the actor's parameters only) until each seed's
    KL(stage one || current) exceeds ``target_kl``. Every seed that did not diverge runs stage two,
    whenever its stage one stopped.
    """

    def __init__(self, parts: GroupParts, reward_spec: SeedBatchedObjective, projection_spec: SeedBatchedObjective) -> None:
        super().__init__(parts)
        if not projection_spec.actor_only:
            raise ValueError(f"CUP's projection stage is actor-only, got {projection_spec.surrogate!r}")
        self.reward_step = FusedFirstOrderStep(parts.model, parts.optimizer, reward_spec, compile=parts.compile)
        self.projection_step = FusedFirstOrderStep(parts.model, parts.optimizer, projection_spec,
                                                   compile=parts.compile)

    def __call__(self, data: Mapping[str, Tensor], lam: Tensor, cost_violation: Tensor, active: Tensor
                 ) -> GroupResult:
        model = self.parts.model
        snapshot = SeedSnapshot(model, self.parts.optimizer)
        first = seed_passes(self.parts, self.reward_step, data, torch.zeros_like(lam), active,
                            (data["loc"], data["scale"]))
        with torch.no_grad():
            loc, = in_chunks(lambda obs: model.dist_params(obs)[:1], data["observation"], model.chunk_size)
            scale = model.scale().expand_as(loc)
        stage_two = {**data, "stage1_loc": loc, "stage1_scale": scale}
        second = seed_passes(self.parts, self.projection_step, stage_two, lam, active & ~first.diverged, (loc, scale))
        diverged = first.diverged | second.diverged
        snapshot.restore(diverged)
        metrics = _first_order_metrics(first)
        metrics.update({"Train/ProjectionStopIter": second.passes, "Train/ProjectionKL": second.kl,
                        "Loss/Loss_projection": second.means[0]})
        return GroupResult(metrics, diverged)


class TrustRegionGroupUpdate(GroupUpdate):
    """The second-order epoch for every seed.

    NPG, TRPO, TRPO-Lag, RCPO, CPO and PCPO: one trust-region step of the actors on the whole batch
    (``policy_step``, a :class:`~sg_torchrl.objectives.stacked_trust_region.StackedTrustRegionStep`
    moving every live seed's row of ``model.flat_actor`` at once), then ``parts.passes`` passes of
    critics-only minibatch steps (``critic_spec``, the loss's objective with ``critics_only``: Adam's
    critic group only, no KL stop) through :func:`seed_passes`. Per seed, the step sees the advantage its single-seed
    update hands its step: ``combine_advantages`` with the seed's multiplier value and the
    multiplier's rule ``critic_spec.combine`` (the reward advantage itself under ``NoMultiplier``), the
    cost advantage, and the seed's ``cost_violation`` :math:`J_{c,s} - d` (``Multiplier.violation``,
    float64, read by CPO and PCPO).

    **Frozen and diverged seeds.** When some seeds are frozen, the step runs on a copy of the live
    seeds' rows only (:meth:`~sg_torchrl.objectives.stacked_trust_region.StackedTrustRegionStep.for_rows`)
    and their moved rows are copied back: a frozen seed's actor is never touched (nor computed on).
    A live seed whose actor row is not finite after the step takes no critic pass; it, and any seed
    whose critic passes turn non-finite, is flagged in :attr:`GroupResult.diverged` and put back to
    its state before the update (:class:`SeedSnapshot`), as the first-order group update does.

    Metrics, ``(S,)`` float64 per seed, under the single-seed names: the step's (``Misc/...``,
    ``Train/KL``, ``Loss/Loss_actor``; NaN for frozen seeds), then ``Train/StopIter`` (the critic
    passes taken), ``Loss/Loss_reward_critic`` and ``Loss/Loss_cost_critic`` (mean over the
    critic steps, with their L2 term).
    """

    def __init__(self, parts: GroupParts, policy_step: StackedTrustRegionStep, critic_spec: SeedBatchedObjective
                 ) -> None:
        super().__init__(parts)
        if not critic_spec.critics_only:
            raise ValueError(f"the second-order passes train the critics only, got {critic_spec.surrogate!r}")
        if policy_step.model is not parts.model:
            raise ValueError("the trust-region step must move the group's own model (parts.model)")
        self.policy_step = policy_step
        self.critic_step = FusedFirstOrderStep(parts.model, parts.optimizer, critic_spec, compile=parts.compile)
        self.combine = critic_spec.combine

    def __call__(self, data: Mapping[str, Tensor], lam: Tensor, cost_violation: Tensor, active: Tensor
                 ) -> GroupResult:
        model = self.parts.model
        snapshot = SeedSnapshot(model, self.parts.optimizer)
        metrics = self._actor_step(data, lam, torch.as_tensor(cost_violation, dtype=torch.float64), active)
        bad = active & ~torch.isfinite(model.flat_actor).all(1)
        critics = seed_passes(self.parts, self.critic_step, data, lam, active & ~bad, None)
        diverged = bad | critics.diverged
        snapshot.restore(diverged)
        metrics.update({"Train/StopIter": critics.passes, "Loss/Loss_reward_critic": critics.means[0],
                        "Loss/Loss_cost_critic": critics.means[1]})
        return GroupResult(metrics, diverged)

    def _actor_step(self, data: Mapping[str, Tensor], lam: Tensor, violation: Tensor, active: Tensor
                    ) -> dict[str, Tensor]:
        """The trust-region step of the ``active`` seeds' actors; its metrics, ``(S,)`` each (NaN where frozen)."""
        model = self.parts.model
        advantage = combine_advantages(data["advantage"], data["cost_advantage"], lam, self.combine)
        if bool(active.all()):
            return self.policy_step.step(data, advantage, data["cost_advantage"], violation)
        rows = active.nonzero().squeeze(1)
        if rows.numel() == 0:
            return {}
        step = self.policy_step.for_rows(rows)

        def pick(value: Tensor | TensorDictBase) -> Tensor | TensorDictBase:
            return value.index_select(0, rows) if isinstance(value, Tensor) else value[rows]

        batch = {name: pick(data[name]) for name in ("observation", "action", "action_log_prob")}
        moved = step.step(batch, pick(advantage), pick(data["cost_advantage"]), violation[active.to(violation.device)])
        with torch.no_grad():
            model.flat_actor.index_copy_(0, rows, step.model.flat_actor)
        full = dict(dtype=torch.float64, device=rows.device)
        return {name: torch.full((model.num_seeds,), math.nan, **full).index_copy_(0, rows, value.to(**full))
                for name, value in moved.items()}
