"""How one epoch's batch moves a seed group's networks: the update loops of SafePO for S seeds at once.

The seed-group counterpart of :mod:`sg_torchrl.train.updates`. The group trainer
(:mod:`sg_torchrl.train.seed_group`) computes every seed's advantages (normalised per seed) and
hands the algorithm's :class:`GroupUpdate` the epoch's samples as ``(S, n, k)`` tensors, seed ``s``'s
on row ``s``: ``observation``, ``action``, ``action_log_prob``, ``loc`` and ``scale`` (the rollout
policy), ``advantage``, ``cost_advantage``, ``value_target``, ``cost_value_target``. The update is
chosen by the algorithm table (``Algorithm.make_group_update`` in :mod:`sg_torchrl.train.algorithms`),
so another kind (the stacked trust-region step of :mod:`sg_torchrl.train.stacked_trust_region`)
plugs in there without touching the trainer:

* :class:`FirstOrderGroupUpdate` (PG, PPO, PPO-Lag, CPPO-PID, FOCOPS): SafePO's first-order loop,
  every seed's minibatch step fused into one (:class:`~sg_torchrl.train.fused.FusedFirstOrderStep`);
* :class:`TwoStageGroupUpdate` (CUP): that loop on the reward stage, then actor-only passes of the
  projection loss towards each seed's stage-one policy.

Both run :func:`seed_passes`, the minibatch loop of a group. Each seed follows its single-seed run:
its own minibatch order (:class:`~sg_torchrl.train.fused.SeedShuffler`), its own KL early stop (after
every pass, KL(reference || current) over the seed's batch against ``target_kl``). A seed that
stopped takes no further step: its later steps are masked (:class:`~sg_torchrl.train.seed_adam.SeedMaskedAdam`),
so its parameters, Adam moments and step counts stay exactly as they are, and its shuffler draws no
more orders, as its single run would not; the passes end when no seed is active.

**Divergence.** A seed whose loss, KL or parameters turn non-finite during a pass is flagged in
:attr:`GroupResult.diverged`, stops at the end of that pass and is put back to its state before the
update (parameters, Adam moments, step counts: :class:`SeedSnapshot`); the trainer then freezes it
for the rest of the run. Seeds share no parameter and no reduction, so the others train exactly as
they would without it.

Host syncs: one per pass (which seeds are still active); metrics come back as ``(S,)`` tensors,
which the trainer reads once per epoch.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from sg_torchrl.train.fused import FirstOrderSpec, FusedFirstOrderStep, SeedBatch, SeedShuffler, batch_kl
from sg_torchrl.train.seed_adam import SeedMaskedAdam
from sg_torchrl.train.stacked import StackedActorCritic

__all__ = [
    "FirstOrderGroupUpdate", "GroupParts", "GroupResult", "GroupUpdate", "PassesResult", "SeedSnapshot",
    "finite_seeds", "seed_passes", "TwoStageGroupUpdate",
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
            (group 1), clipping each seed's gradient at the config's ``max_grad_norm``.
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
        self.state = [{"step": state["step"].clone(), "exp_avg": [t.clone() for t in state["exp_avg"]],
                       "exp_avg_sq": [t.clone() for t in state["exp_avg_sq"]]} for state in optimizer.state]

    @torch.no_grad()
    def restore(self, seeds: Tensor) -> None:
        """Put the rows of the seeds where ``seeds`` (``(S,)`` bool) is true back to the snapshot."""
        if not bool(seeds.any()):
            return

        def put(current: Tensor, saved: Tensor) -> None:
            current.copy_(torch.where(seeds.view(-1, *([1] * (current.dim() - 1))), saved, current))

        for current, saved in zip(self.model.flat_groups, self.params):
            put(current, saved)
        for state, saved in zip(self.optimizer.state, self.state):
            put(state["step"], saved["step"])
            for name in ("exp_avg", "exp_avg_sq"):
                for current, old in zip(state[name], saved[name]):
                    put(current, old)


@dataclass
class PassesResult:
    """What :func:`seed_passes` reports per seed, ``(S,)`` each (``means``: ``(terms, S)``), float64."""

    passes: Tensor
    kl: Tensor
    means: Tensor
    diverged: Tensor


def seed_passes(
    parts: GroupParts,
    step: FusedFirstOrderStep,
    data: Mapping[str, Tensor],
    lam: Tensor,
    active: Tensor,
    reference: tuple[Tensor, Tensor],
) -> PassesResult:
    """Up to ``parts.passes`` shuffled passes of ``step`` for the ``active`` seeds, each with its own KL stop.

    A pass gathers each seed's minibatches from its own order, takes one fused gradient step per
    minibatch (seeds that are no longer active masked), then computes each active seed's mean
    KL(``reference`` || current policy) over its batch: a seed whose KL exceeds ``parts.target_kl``
    (SafePO's early stop), or whose KL, losses or parameters are not finite (flagged diverged),
    takes no further step.

    Args:
        parts: the group's model, optimiser, shuffler and loop settings.
        step: the fused step of the objective (its spec names the fields it reads from ``data``).
        data: the per-seed fields, ``(S, n, k)`` each.
        lam: each seed's multiplier value, ``(S,)``.
        active: ``(S,)`` bool, the seeds that train (frozen seeds do not).
        reference: ``(loc, scale)`` of the policy the KL is measured from, ``(S, n, A)`` each.

    Returns:
        Per seed: the passes taken (SafePO's ``StopIter``), the KL after its last pass, the mean of
        each loss term over its steps (the objective, and unless actor-only each critic's loss with
        its L2 term, as the single-seed losses report them), and whether it diverged.
    """
    model = parts.model
    spec = step.spec
    batch = SeedBatch.pack({name: data[name] for name in spec.fields})
    observation, (old_loc, old_scale) = data["observation"], reference
    seeds, size = batch.num_seeds, batch.num_samples
    with_critics, l2 = not spec.actor_only, spec.critic_l2
    width = model.reward_critic_width
    f64 = dict(dtype=torch.float64, device=observation.device)
    sums = torch.zeros(3 if with_critics else 1, seeds, **f64)
    steps, passes, kl_last = (torch.zeros(seeds, **f64) for _ in range(3))
    diverged = torch.zeros(seeds, dtype=torch.bool, device=observation.device)
    active = active.clone()
    flags = active.tolist()
    for _ in range(parts.passes):
        if not any(flags):
            break
        mask = None if all(flags) else active  # the unmasked Adam is the cheaper one
        weight = active.to(torch.float64)
        for index in parts.shuffler.minibatches(size, parts.minibatch_size, flags):
            losses = step.backward(batch.gather(index), lam)
            values = torch.stack(losses)
            if with_critics and l2:  # the critics' losses as reported: with the L2 term at the step's parameters
                squares = model.flat_critics.detach().square()
                norms = torch.stack((squares[:, :width].sum(1), squares[:, width:].sum(1)))
                values = torch.cat((values[:1], values[1:] + l2 * norms))
            step.update(mask)
            sums += values.to(torch.float64) * weight
            steps += weight
        passes += weight
        kl = batch_kl(model, observation, old_loc, old_scale).to(torch.float64)
        kl_last = torch.where(active, kl, kl_last)
        bad = active & ~(torch.isfinite(kl) & finite_seeds(model) & torch.isfinite(sums).all(0))
        diverged |= bad
        active &= ~bad & ~(kl > parts.target_kl)
        flags = active.tolist()
    return PassesResult(passes, kl_last, sums / steps.clamp_min(1.0), diverged)


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

    def __init__(self, parts: GroupParts, spec: FirstOrderSpec) -> None:
        super().__init__(parts)
        self.step = FusedFirstOrderStep(parts.model, parts.optimizer, spec, compile=parts.compile)

    def __call__(self, data: Mapping[str, Tensor], lam: Tensor, cost_violation: Tensor, active: Tensor
                 ) -> GroupResult:
        snapshot = SeedSnapshot(self.parts.model, self.parts.optimizer)
        result = seed_passes(self.parts, self.step, data, lam, active, (data["loc"], data["scale"]))
        snapshot.restore(result.diverged)
        return GroupResult(_first_order_metrics(result), result.diverged)


class TwoStageGroupUpdate(GroupUpdate):
    """CUP's epoch (as :class:`~sg_torchrl.train.updates.TwoStageUpdate`) for every seed.

    Stage one runs :func:`seed_passes` on ``reward_spec`` (PPO on the reward advantage, both critics,
    no multiplier); each seed's stage-one policy is then evaluated on its batch (``stage1_loc`` /
    ``stage1_scale``) and stage two takes actor-only passes of ``projection_spec`` (Adam's actor
    group only, as the single-seed update steps the actor's parameters only) until each seed's
    KL(stage one || current) exceeds ``target_kl``. Every seed that did not diverge runs stage two,
    whenever its stage one stopped.
    """

    def __init__(self, parts: GroupParts, reward_spec: FirstOrderSpec, projection_spec: FirstOrderSpec) -> None:
        super().__init__(parts)
        if not projection_spec.actor_only:
            raise ValueError(f"CUP's projection stage is actor-only, got objective {projection_spec.objective!r}")
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
            loc, scale = model.dist_params(data["observation"])
            scale = scale.expand_as(loc)
        stage_two = {**data, "stage1_loc": loc, "stage1_scale": scale}
        second = seed_passes(self.parts, self.projection_step, stage_two, lam, active & ~first.diverged, (loc, scale))
        diverged = first.diverged | second.diverged
        snapshot.restore(diverged)
        metrics = _first_order_metrics(first)
        metrics.update({"Train/ProjectionStopIter": second.passes, "Train/ProjectionKL": second.kl,
                        "Loss/Loss_projection": second.means[0]})
        return GroupResult(metrics, diverged)
