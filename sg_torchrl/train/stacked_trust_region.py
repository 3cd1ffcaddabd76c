"""The second-order policy step of a seed group: NPG, TRPO, CPO and PCPO for S seeds at once.

A seed group (DESIGN.md, "Many seeds in one process") keeps S seeds' actors stacked in
:attr:`~sg_torchrl.train.stacked.StackedActorCritic.flat_actor`, one row per seed. This module
takes the trust-region step of :mod:`sg_torchrl.objectives.trust_region` for every row together,
with each seed moving exactly as its single-seed :class:`~sg_torchrl.objectives.TrustRegionStep`
would move it (same conventions, hyper-parameters and metric names):

* **surrogates and KL** (:class:`SeedSurrogates`): one stacked actor pass gives each seed's reward
  and cost surrogate and its mean KL (averaged over samples and, by default, action dimensions),
  ``(S,)`` each. Seeds share no parameter, so the gradient of the *sum over seeds* of a per-seed
  quantity has seed ``s``'s own gradient in row ``s``: one backward gives :math:`g` (and
  :math:`b`) for every seed;
* **Fisher-vector products** (:class:`SeedFisherVectorProduct`): the Hessian of the sum over seeds
  of the per-seed KLs is block diagonal, so one double-backward of :math:`\\sum_s \\nabla
  \\mathrm{KL}_s \\cdot v_s` gives :math:`H_s v_s` for every seed (plus the damping);
* **conjugate gradient** (:func:`seed_conjugate_gradient`):
  :func:`~sg_torchrl.objectives.second_order.conjugate_gradient` row by row, with per-seed
  :math:`\\alpha, \\beta` and a mask that freezes a seed once its residual is below the tolerance
  (where the single-seed loop breaks);
* **directions**: the single-seed proposals (:func:`~sg_torchrl.objectives.trust_region.natural_proposal`,
  :func:`~sg_torchrl.objectives.trust_region.cpo_proposal`, :func:`~sg_torchrl.objectives.trust_region.pcpo_proposal`,
  over :func:`~sg_torchrl.objectives.trust_region.cpo_direction` and
  :func:`~sg_torchrl.objectives.trust_region.pcpo_direction`) are called seed by seed on
  :meth:`SeedLinearisation.seeds`: a handful of scalars and ``(P,)`` vectors per seed, so each formula
  keeps its one home and the group takes each seed's CPO case from that seed's own violation;
* **line search**: trial ``k`` writes :math:`\\theta_{\\text{old}} + 0.8^{k-1} d_s` into every row
  still searching and evaluates those seeds in one stacked pass; a seed accepts its first acceptable
  candidate (finite surrogates and KL, :math:`\\mathrm{KL} \\le \\delta`, the proposal's
  improvement / cost tests, :meth:`StackedTrustRegionStep.acceptable`) and is not moved by later
  trials; seeds that never accept get their old row back.

Metrics come back as ``(S,)`` float64 tensors under the single-seed names (``Misc/xHx``,
``Misc/H_inv_g``, ``Misc/AcceptanceStep``, ``Misc/FinalStepNorm``, ``Misc/CPOCase``, ...).
``tests/test_stacked_trust_region.py`` checks every algorithm seed by seed against the single-seed
step classes; ``benchmarks/trust_region_group.py`` times the group against S single-seed steps.
"""

from __future__ import annotations

import abc
import copy
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from sg_torchrl.objectives.kl import gaussian_kl
from sg_torchrl.objectives.second_order import Linearisation, natural_step_size
from sg_torchrl.objectives.trust_region import (
    CPORule,
    CPOStep,
    NaturalPolicyStep,
    NaturalRule,
    PCPORule,
    PCPOStep,
    Proposal,
    TRPORule,
    TRPOStep,
    TrustRegionOptions,
    _per_sample,  # value reshaped to (S, N) per sample, refusing silent broadcasting
)
from sg_torchrl.objectives.surrogates import gaussian_log_prob
from sg_torchrl.train.stacked import StackedActorCritic

__all__ = [
    "STACKED_STEPS",
    "SeedFisherVectorProduct",
    "SeedLinearisation",
    "SeedProposals",
    "SeedSurrogates",
    "StackedCPOStep",
    "StackedNaturalPolicyStep",
    "StackedPCPOStep",
    "StackedTRPOStep",
    "StackedTrustRegionStep",
    "seed_conjugate_gradient",
    "seed_flat_grad",
    "seed_linearise",
]


# ============================================================================ gradients per seed
def seed_flat_grad(output: Tensor, params: Sequence[Tensor], num_seeds: int, *, retain_graph: bool | None = None,
                   create_graph: bool = False) -> Tensor:
    """Gradient of the scalar ``output`` w.r.t. seed-stacked ``params``, as ``(S, P)`` rows.

    ``params`` are the stacked parameters in flat-buffer order (each of shape ``(S, ...)``, e.g.
    :meth:`~sg_torchrl.train.stacked.StackedActorCritic.actor_parameters`), so row ``s`` lines up
    with row ``s`` of the flat buffer. With ``output`` a sum over seeds of per-seed terms, row ``s``
    is the gradient of seed ``s``'s term. Unused parameters get zeros; ``.grad`` is not touched.
    """
    grads = torch.autograd.grad(output, tuple(params), retain_graph=retain_graph, create_graph=create_graph,
                                allow_unused=True, materialize_grads=True)
    return torch.cat([grad.reshape(num_seeds, -1) for grad in grads], dim=1)


class SeedSurrogates:
    """Each seed's reward surrogate, cost surrogate and mean KL on its batch, ``(S,)`` each.

    The quantities of :class:`~sg_torchrl.objectives.TrustRegionLoss` (with the sign of the reward
    surrogate flipped: here :math:`\\mathbb E[r_\\theta A]`, there its negative), per seed:
    :math:`r_\\theta = \\exp(\\log\\pi_\\theta(a|s) - \\log\\pi_{\\text{behaviour}}(a|s))`, reward
    :math:`\\mathbb E[r_\\theta A]`, cost :math:`\\mathbb E[r_\\theta A^c]` (zeros without a cost
    advantage) and :math:`\\mathbb E_s[\\mathrm{KL}(\\pi_{\\text{old}} \\| \\pi_\\theta)]`, per sample
    divided by the action dimension for ``kl_action_reduction="mean"`` (SafePO) or not (``"sum"``).
    Calling it runs the model's actor once, with gradients unless under :func:`torch.no_grad`.

    Args:
        observation, action: ``(S, N, obs_dim)``, ``(S, N, A)``.
        log_prob: behaviour log-probabilities ``(S, N)``.
        advantage, cost_advantage: ``(S, N)`` (``cost_advantage`` may be ``None``).
        old_loc, old_scale: the anchor policy :math:`\\pi_{\\text{old}}`, broadcastable to ``(S, N, A)``.
        kl_action_reduction: ``"mean"`` or ``"sum"`` over action dimensions.
    """

    def __init__(self, observation: Tensor, action: Tensor, log_prob: Tensor, advantage: Tensor,
                 cost_advantage: Tensor | None, old_loc: Tensor, old_scale: Tensor,
                 kl_action_reduction: Literal["mean", "sum"] = "mean") -> None:
        self.observation, self.action, self.log_prob = observation, action, log_prob
        self.advantage, self.cost_advantage = advantage, cost_advantage
        self.old_loc, self.old_scale = old_loc, old_scale
        self.kl_action_reduction = kl_action_reduction

    def rows(self, index: Tensor) -> SeedSurrogates:
        """The same quantities for the seeds ``index`` only (their batches copied), for a smaller group."""
        def pick(value: Tensor | None) -> Tensor | None:
            return None if value is None else value.index_select(0, index)

        return SeedSurrogates(pick(self.observation), pick(self.action), pick(self.log_prob), pick(self.advantage),
                              pick(self.cost_advantage), pick(self.old_loc), pick(self.old_scale),
                              self.kl_action_reduction)

    def __call__(self, model: StackedActorCritic) -> tuple[Tensor, Tensor, Tensor]:
        loc, scale = model.dist_params(self.observation)
        ratio = (gaussian_log_prob(self.action, loc, scale) - self.log_prob).exp()
        reward = (ratio * self.advantage).mean(1)
        cost = torch.zeros_like(reward) if self.cost_advantage is None else (ratio * self.cost_advantage).mean(1)
        kl = gaussian_kl(self.old_loc, self.old_scale, loc, scale)
        if self.kl_action_reduction == "mean":
            kl = kl / loc.shape[-1]
        return reward, cost, kl.mean(1)


class SeedFisherVectorProduct:
    """Every seed's damped Fisher-vector product :math:`v_s \\mapsto (H_s + \\beta I) v_s` in one double-backward.

    :class:`~sg_torchrl.objectives.second_order.FisherVectorProduct` for a seed group. ``kl`` is the
    ``(S,)`` per-seed mean KL with its first argument detached; the Hessian of ``kl.sum()`` is block
    diagonal (seed ``s``'s KL depends on row ``s`` only), so with :math:`G = \\nabla \\sum_s
    \\mathrm{KL}_s` built once with its graph, the gradient of :math:`\\sum_s G_s \\cdot v_s` has
    :math:`H_s v_s` in row ``s``. The graph of ``kl`` lives as long as the object: build one per step.

    Args:
        kl: ``(S,)`` per-seed KLs with a graph to ``params``.
        params: the stacked actor parameters in flat-buffer order.
        damping: :math:`\\beta \\ge 0` (SafePO: 0.1), the same for every seed.
    """

    def __init__(self, kl: Tensor, params: Sequence[Tensor], damping: float = 0.1) -> None:
        if damping < 0:
            raise ValueError(f"damping must be >= 0, got {damping}.")
        self.params = tuple(params)
        self.num_seeds = kl.shape[0]
        self.damping = float(damping)
        self._kl_grad = seed_flat_grad(kl.sum(), self.params, self.num_seeds, create_graph=True)

    def __call__(self, v: Tensor) -> Tensor:
        v = v.detach().to(self._kl_grad.dtype)
        directional = (self._kl_grad * v).sum()
        if directional.requires_grad:
            hv = seed_flat_grad(directional, self.params, self.num_seeds, retain_graph=True)
        else:  # the KL is (locally) linear in the parameters: zero curvature
            hv = torch.zeros_like(v)
        return hv + self.damping * v


def _rowdot(a: Tensor, b: Tensor) -> Tensor:
    """Row-wise dot products of ``(S, P)`` tensors, ``(S,)``."""
    return (a * b).sum(1)


def seed_conjugate_gradient(Avp: Callable[[Tensor], Tensor], b: Tensor, iters: int = 15,
                            residual_tol: float = 1e-10, eps: float = 1e-6) -> Tensor:
    """Solves :math:`A_s x_s = b_s` for every row ``s`` of ``b`` ``(S, P)`` by conjugate gradient.

    :func:`~sg_torchrl.objectives.second_order.conjugate_gradient` row by row: from :math:`x_0 = 0`,
    at most ``iters`` iterations, ``eps`` in both denominators, per-seed :math:`\\alpha` and
    :math:`\\beta`. The single-seed loop breaks once its residual norm is below ``residual_tol``
    (after updating :math:`x`); here that seed is masked instead, so its :math:`x` stays what the
    single-seed loop returns while the other rows go on (the loop ends when none is left).
    ``Avp`` maps ``(S, P)`` to ``(S, P)`` row by row (a :class:`SeedFisherVectorProduct`).
    """
    if iters < 1:
        raise ValueError(f"iters must be >= 1, got {iters}.")
    x = torch.zeros_like(b)
    r = b.clone()
    p = r.clone()
    rdotr = _rowdot(r, r)
    running = torch.ones(b.shape[0], dtype=torch.bool, device=b.device)
    for _ in range(iters):
        z = Avp(p)
        alpha = (rdotr / (_rowdot(p, z) + eps)).unsqueeze(1)
        live = running.unsqueeze(1)
        x = torch.where(live, x + alpha * p, x)
        r = torch.where(live, r - alpha * z, r)
        new_rdotr = _rowdot(r, r)
        # the single-seed test, float(sqrt) < tol, in double precision
        running = running & ~(new_rdotr.sqrt().double() < residual_tol)
        if not bool(running.any()):
            break
        p = torch.where(running.unsqueeze(1), r + (new_rdotr / (rdotr + eps)).unsqueeze(1) * p, p)
        rdotr = torch.where(running, new_rdotr, rdotr)
    return x


@dataclass(frozen=True)
class SeedLinearisation:
    """:class:`~sg_torchrl.objectives.second_order.Linearisation` for S seeds: ``(S, P)`` vectors and ``(S,)`` scalars.

    Attributes:
        g, x, hx, q: reward gradient, :math:`H^{-1} g`, :math:`Hx`, :math:`x^\\top H x`.
        b, p, r, s: cost gradient, :math:`H^{-1} b`, :math:`g^\\top p`, :math:`b^\\top p` (``None``
            without a cost gradient).
    """

    g: Tensor
    x: Tensor
    hx: Tensor
    q: Tensor
    b: Tensor | None = None
    p: Tensor | None = None
    r: Tensor | None = None
    s: Tensor | None = None

    def seeds(self) -> list[Linearisation]:
        """Each seed's single-seed :class:`Linearisation` (its rows; scalars as Python floats).

        The scalars cross to the host in one transfer per kind (``q``, ``r``, ``s``), whatever S is.
        """
        q = self.q.tolist()
        if self.b is None:
            return [Linearisation(g=self.g[i], x=self.x[i], hx=self.hx[i], q=q[i]) for i in range(len(q))]
        r, s = self.r.tolist(), self.s.tolist()
        return [Linearisation(g=self.g[i], x=self.x[i], hx=self.hx[i], q=q[i], b=self.b[i], p=self.p[i], r=r[i],
                              s=s[i]) for i in range(len(q))]


def seed_linearise(hvp: Callable[[Tensor], Tensor], g: Tensor, b: Tensor | None = None, *, cg_iters: int = 15,
                   residual_tol: float = 1e-10, eps: float = 1e-6) -> SeedLinearisation:
    """:func:`~sg_torchrl.objectives.second_order.linearise` for every seed.

    :math:`x = H^{-1} g` and :math:`p = H^{-1} b` by :func:`seed_conjugate_gradient`, then
    :math:`q = x^\\top Hx`, :math:`r = g^\\top p`, :math:`s = b^\\top p` per seed.
    """
    x = seed_conjugate_gradient(hvp, g, cg_iters, residual_tol, eps)
    hx = hvp(x)
    q = _rowdot(x, hx)
    if b is None:
        return SeedLinearisation(g=g, x=x, hx=hx, q=q)
    p = seed_conjugate_gradient(hvp, b, cg_iters, residual_tol, eps)
    return SeedLinearisation(g=g, x=x, hx=hx, q=q, b=b, p=p, r=_rowdot(g, p), s=_rowdot(b, p))


# ============================================================================ the step
@dataclass(frozen=True)
class SeedProposals:
    """The seeds' :class:`~sg_torchrl.objectives.trust_region.Proposal`\\ s, stacked.

    Attributes:
        direction: ``(S, P)`` full steps.
        require_improvement: ``(S,)`` bool, the reward surrogate must not decrease.
        checks_cost: ``(S,)`` bool, the proposal has a cost tolerance.
        cost_tolerance: ``(S,)`` float64, the allowed increase of the cost surrogate (0 where unchecked).
        metrics: the proposals' extra metrics, ``(S,)`` float64 each.
    """

    direction: Tensor
    require_improvement: Tensor
    checks_cost: Tensor
    cost_tolerance: Tensor
    metrics: dict[str, Tensor]

    @classmethod
    def stack(cls, proposals: Sequence[Proposal]) -> SeedProposals:
        direction = torch.stack([proposal.direction for proposal in proposals])
        options = dict(device=direction.device)
        tolerances = [proposal.cost_tolerance for proposal in proposals]
        names = dict.fromkeys(name for proposal in proposals for name in proposal.metrics)
        return cls(
            direction=direction,
            require_improvement=torch.tensor([proposal.require_improvement for proposal in proposals], **options),
            checks_cost=torch.tensor([tolerance is not None for tolerance in tolerances], **options),
            cost_tolerance=torch.tensor([tolerance or 0.0 for tolerance in tolerances], dtype=torch.float64,
                                        **options),
            metrics={name: torch.tensor([proposal.metrics.get(name, math.nan) for proposal in proposals],
                                        dtype=torch.float64, **options) for name in names},
        )

    def rows(self, index: Tensor) -> SeedProposals:
        """The proposals of the seeds ``index`` (a subset, in that order)."""
        return SeedProposals(
            direction=self.direction[index], require_improvement=self.require_improvement[index],
            checks_cost=self.checks_cost[index], cost_tolerance=self.cost_tolerance[index],
            metrics={name: value[index] for name, value in self.metrics.items()},
        )


def _actor_rows(model: StackedActorCritic, rows: Tensor) -> StackedActorCritic:
    """A group of the networks' shape for the seeds ``rows`` of ``model`` (its actor rows are set by the caller).

    The line search evaluates candidates of the seeds still searching in one of these, so the
    forward pass is ``model``'s own (:meth:`StackedActorCritic.dist_params`) on fewer rows.
    """
    weight = model.flat_actor
    return StackedActorCritic(rows.numel(), model.obs_dim, model.action_dim, model.hidden_sizes,
                              scale_lb=model.scale_lb, device=weight.device, dtype=weight.dtype)


class StackedTrustRegionStep(TrustRegionOptions, abc.ABC):
    """The trust-region step of every seed of a group; subclasses only name the per-seed proposal.

    :meth:`step` follows :meth:`~sg_torchrl.objectives.TrustRegionStep.step` for each row of
    ``model.flat_actor`` (see the module docstring for how the seeds are batched):

    1. anchors :math:`\\pi_{\\text{old}}` at the actor as it is (detached ``loc`` / ``scale``);
    2. one stacked pass of :class:`SeedSurrogates` with gradients: every seed's :math:`g` (and
       :math:`b` for CPO / PCPO) and the :class:`SeedFisherVectorProduct` of its KL;
    3. :func:`seed_linearise` (batched conjugate gradient);
    4. the single-seed proposal of each seed (:meth:`_propose`) on its own linearisation and
       violation :math:`c_s = J_{c,s} - d`;
    5. applies each seed's direction directly (``line_search_steps=0``, NPG) or backtracks all seeds
       together, a seed stopping at its first acceptable trial; a seed with none keeps its row.

    Args:
        model: the seed group's networks; rows of ``model.flat_actor`` are changed in place.

    Keyword Args:
        target_kl, cg_iters, cg_damping, line_search_steps, step_fraction, cg_residual_tol, cg_eps,
        kl_action_reduction: as :class:`~sg_torchrl.objectives.TrustRegionStep` (the same for every
            seed; SafePO's defaults).

    Returned metrics: those of the single-seed step, each a ``(S,)`` float64 tensor on the model's
    device (``Misc/Alpha``, ``Misc/FinalStepNorm``, ``Misc/xHx``, ``Misc/gradient_norm``,
    ``Misc/H_inv_g``, ``Misc/AcceptanceStep``, ``Train/KL``, ``Loss/Loss_actor``, plus
    ``Misc/cost_gradient_norm`` and the proposal's extras such as ``Misc/CPOCase``).
    """

    def __init__(self, model: StackedActorCritic, **options) -> None:
        super().__init__(**options)
        self.model = model

    def for_rows(self, rows: Tensor) -> StackedTrustRegionStep:
        """This step (same class and options) on a copy of the actor rows ``rows`` alone.

        A seed group steps only its live seeds with it: a frozen seed's row may not be finite, and
        would otherwise search all its line-search trials every epoch. Copy the moved rows back.
        """
        part = copy.copy(self)
        part.model = _actor_rows(self.model, rows)
        with torch.no_grad():
            part.model.flat_actor.copy_(self.model.flat_actor.index_select(0, rows))
        return part

    # ------------------------------------------------------------------ hook
    @abc.abstractmethod
    def _propose(self, lin: Linearisation, cost_violation: float) -> Proposal:
        """One seed's step direction and acceptance tests (the single-seed class's proposal)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ body
    def step(self, batch: Mapping[str, Tensor], advantage: Tensor, cost_advantage: Tensor | None,
             cost_violation: Tensor | Sequence[float]) -> dict[str, Tensor]:
        """One trust-region update of every seed's actor on its whole batch.

        Args:
            batch: ``"observation"`` ``(S, N, obs_dim)``, ``"action"`` ``(S, N, A)`` and
                ``"action_log_prob"`` ``(S, N)`` or ``(S, N, 1)`` (e.g. :meth:`SeedBatch.fields`).
            advantage: each seed's (Lagrangian, normalised) reward advantage, ``(S, N)`` or
                ``(S, N, 1)``: ``combine_advantages`` with the seed's multiplier for TRPO-Lag / RCPO.
            cost_advantage: the mean-centred cost advantage (same shape), or ``None`` (then the cost
                surrogate is 0; CPO / PCPO need it).
            cost_violation: :math:`c_s = J_{c,s} - d` per seed, ``(S,)``: Python floats or a float64
                tensor (the single-seed step reads a Python float; float32 would round it). Unused by
                NPG / TRPO.

        Returns:
            The metrics of the class docstring, ``(S,)`` each.
        """
        model = self.model
        observation, action = batch["observation"], batch["action"]
        seeds = model.num_seeds
        shape = observation.shape[:2]
        if shape[0] != seeds or action.shape[:2] != shape:
            raise ValueError(f"expected (S={seeds}, N, ...) observations and actions, got "
                             f"{tuple(observation.shape)} and {tuple(action.shape)}.")
        if self.uses_cost and cost_advantage is None:
            raise ValueError(f"{type(self).__name__} needs the cost advantage.")
        violations = torch.as_tensor(cost_violation, dtype=torch.float64).reshape(-1).tolist()
        if len(violations) != seeds:
            raise ValueError(f"expected one cost violation per seed ({seeds}), got {len(violations)}.")
        with torch.no_grad():
            old_loc, old_scale = model.dist_params(observation)
        surrogates = SeedSurrogates(
            observation, action, _per_sample(batch["action_log_prob"], shape, "action_log_prob"),
            _per_sample(advantage.detach(), shape, "advantage"),
            None if cost_advantage is None else _per_sample(cost_advantage.detach(), shape, "cost_advantage"),
            old_loc, old_scale, self.kl_action_reduction,
        )
        lin, before_reward, before_cost = self._linearise(surrogates)
        proposals = SeedProposals.stack([self._propose(seed_lin, c) for seed_lin, c in zip(lin.seeds(), violations)])
        step_index, kl_after = self._apply(surrogates, proposals, before_reward, before_cost)
        return self._metrics(lin, proposals, step_index, kl_after, before_reward)

    def _linearise(self, surrogates: SeedSurrogates) -> tuple[SeedLinearisation, Tensor, Tensor]:
        """Every seed's linearisation and its reward and cost surrogates before the step."""
        model = self.model
        reward, cost, kl = surrogates(model)
        params, seeds = model.actor_parameters(), model.num_seeds
        fvp = SeedFisherVectorProduct(kl, params, self.cg_damping)
        g = seed_flat_grad(reward.sum(), params, seeds, retain_graph=True)
        b = seed_flat_grad(cost.sum(), params, seeds, retain_graph=True) if self.uses_cost else None
        lin = seed_linearise(fvp, g, b, cg_iters=self.cg_iters, residual_tol=self.cg_residual_tol, eps=self.cg_eps)
        return lin, reward.detach(), cost.detach()

    def acceptable(self, reward: Tensor, cost: Tensor, kl: Tensor, before_reward: Tensor, before_cost: Tensor,
                   proposals: SeedProposals) -> Tensor:
        """Which seeds' candidates pass the single-seed acceptance tests, ``(S,)`` bool.

        ``TrustRegionStep._acceptable`` per seed, in double precision as its Python floats: finite
        surrogates and KL, :math:`\\mathrm{KL} \\le \\delta`, no decrease of the reward surrogate when
        the proposal requires it, and an increase of the cost surrogate within its tolerance.
        """
        reward, cost, kl = reward.double(), cost.double(), kl.double()
        ok = torch.isfinite(reward) & torch.isfinite(cost) & torch.isfinite(kl) & (kl <= self.target_kl)
        ok &= ~(proposals.require_improvement & (reward < before_reward.double()))
        return ok & (~proposals.checks_cost | (cost - before_cost.double() <= proposals.cost_tolerance))

    @torch.no_grad()
    def _apply(self, surrogates: SeedSurrogates, proposals: SeedProposals, before_reward: Tensor,
               before_cost: Tensor) -> tuple[Tensor, Tensor]:
        """Moves the rows of ``flat_actor``; returns each seed's accepted trial (0: none) and KL after.

        Trial ``k`` evaluates only the seeds still searching: the whole group while none has
        stopped, then a smaller group of just those rows (:func:`_actor_rows`), so a seed that
        backtracks far (PCPO tries up to 200 fractions) does not make every seed pay for each trial.
        """
        model, direction = self.model, proposals.direction
        theta_old = model.flat_actor.clone()
        if self.line_search_steps == 0:
            model.flat_actor.copy_(theta_old + direction)
            kl = surrogates(model)[2].double()
            return torch.ones_like(kl), kl
        final = theta_old.clone()  # a seed that accepts nothing keeps its row
        step_index = torch.zeros(theta_old.shape[0], dtype=torch.float64, device=theta_old.device)
        kl_after = torch.zeros_like(step_index)
        searching = torch.arange(theta_old.shape[0], device=theta_old.device)
        group, part, tests = model, surrogates, proposals
        fraction = 1.0
        for trial in range(1, self.line_search_steps + 1):
            group.flat_actor.copy_(theta_old[searching] + fraction * direction[searching])
            reward, cost, kl = part(group)
            ok = self.acceptable(reward, cost, kl, before_reward[searching], before_cost[searching], tests)
            if bool(ok.any()):
                accepted = searching[ok]
                final[accepted] = group.flat_actor[ok]
                step_index[accepted] = float(trial)
                kl_after[accepted] = kl[ok].double()
                searching = searching[~ok]
                if searching.numel() == 0:
                    break
                group, part = _actor_rows(model, searching), surrogates.rows(searching)
                tests = proposals.rows(searching)
            fraction *= self.step_fraction
        model.flat_actor.copy_(final)
        return step_index, kl_after

    def _metrics(self, lin: SeedLinearisation, proposals: SeedProposals, step_index: Tensor, kl_after: Tensor,
                 before_reward: Tensor) -> dict[str, Tensor]:
        def f64(value: Tensor) -> Tensor:
            return value.detach().to(torch.float64)

        alpha = [natural_step_size(q, self.target_kl) for q in lin.q.tolist()]
        metrics = {
            "Misc/Alpha": torch.tensor(alpha, dtype=torch.float64, device=step_index.device),
            "Misc/FinalStepNorm": torch.where(step_index > 0, f64(proposals.direction.norm(dim=1)), 0.0),
            "Misc/xHx": f64(lin.q),
            "Misc/gradient_norm": f64(lin.g.norm(dim=1)),
            "Misc/H_inv_g": f64(lin.x.norm(dim=1)),
            "Misc/AcceptanceStep": step_index,
            "Train/KL": kl_after,
            "Loss/Loss_actor": -f64(before_reward),
        }
        if lin.b is not None:
            metrics["Misc/cost_gradient_norm"] = f64(lin.b.norm(dim=1))
        metrics.update(proposals.metrics)
        return metrics


class StackedNaturalPolicyStep(NaturalRule, StackedTrustRegionStep):
    """:class:`~sg_torchrl.objectives.NaturalPolicyStep` for a seed group (NPG; RCPO with the Lagrangian advantage)."""


class StackedTRPOStep(TRPORule, StackedNaturalPolicyStep):
    """:class:`~sg_torchrl.objectives.TRPOStep` for a seed group (TRPO; TRPO-Lag with the Lagrangian advantage)."""


class StackedCPOStep(CPORule, StackedTrustRegionStep):
    """:class:`~sg_torchrl.objectives.CPOStep` for a seed group; each seed takes its own CPO case.

    Keyword Args:
        safepo_dual (bool): see :func:`~sg_torchrl.objectives.cpo_direction`. Defaults to ``False``.
    """


class StackedPCPOStep(PCPORule, StackedTrustRegionStep):
    """:class:`~sg_torchrl.objectives.PCPOStep` for a seed group.

    Keyword Args:
        use_hx_direction (bool): see :class:`~sg_torchrl.objectives.PCPOStep`. Defaults to ``False``.
    """


#: The group step of each single-seed step class (what an algorithm row names, e.g. ``TRPOStep``).
STACKED_STEPS: dict[type, type[StackedTrustRegionStep]] = {
    NaturalPolicyStep: StackedNaturalPolicyStep,
    TRPOStep: StackedTRPOStep,
    CPOStep: StackedCPOStep,
    PCPOStep: StackedPCPOStep,
}
