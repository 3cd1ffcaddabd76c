"""The trust-region policy step (NPG, TRPO, CPO, PCPO) of S seeds at once: the one implementation.

Every trust-region step of the package runs through :class:`TrustRegionEngine`, over a
:class:`StackedActor`: S seeds' Gaussian policies whose trainable parameters are the rows of one
``(S, P)`` buffer. A seed group's networks
(:class:`~sg_torchrl.modules.stacked.StackedActorCritic`) are one, stepped by
:class:`StackedTrustRegionStep`; a single TorchRL actor is the case S = 1, stepped by the classes of
:mod:`sg_torchrl.objectives.trust_region` (``TRPOStep(actor)``, ``CPOStep(actor)``, ..., MACPO's per
agent) through a one-seed view of the actor. Each seed moves as if stepped alone:

* **surrogates and KL** (:class:`SeedSurrogates`): one stacked actor pass gives each seed's reward
  and cost surrogate and its mean KL (averaged over samples and, by default, action dimensions),
  ``(S,)`` each. Seeds share no parameter, so the gradient of the *sum over seeds* of a per-seed
  quantity has seed ``s``'s own gradient in row ``s``: one backward gives :math:`g` (and :math:`b`)
  for every seed;
* **Fisher-vector products, conjugate gradient, linearisation**
  (:mod:`sg_torchrl.objectives.second_order`: :class:`~sg_torchrl.objectives.second_order.SeedFisherVectorProduct`,
  :func:`~sg_torchrl.objectives.second_order.seed_linearise`): block-diagonal double-backward and a
  row-wise conjugate gradient that freezes a seed once its residual is below the tolerance;
* **directions**: each method's proposal (:mod:`sg_torchrl.objectives.step_rules`) is called seed by
  seed on :meth:`~sg_torchrl.objectives.second_order.Linearisation.seeds`, so each seed takes its
  CPO case from its own violation;
* **line search** (:func:`~sg_torchrl.objectives.second_order.seed_line_search`): trial ``k`` writes
  :math:`\\theta_{\\text{old}} + 0.8^{k-1} d_s` into every row still searching and evaluates those
  seeds in one stacked pass; a seed accepts its first acceptable candidate (finite surrogates and
  KL, :math:`\\mathrm{KL} \\le \\delta`, the proposal's improvement / cost tests,
  :meth:`TrustRegionEngine.acceptable`); seeds that never accept get their old row back.

Metrics come back as ``(S,)`` float64 tensors under SafePO's names (``Misc/xHx``, ``Misc/H_inv_g``,
``Misc/AcceptanceStep``, ``Misc/FinalStepNorm``, ``Misc/CPOCase``, ...).
``tests/test_stacked_trust_region.py`` checks every algorithm seed by seed against one-seed steps;
``benchmarks/trust_region_group.py`` times the group against S one-seed steps.
"""

from __future__ import annotations

import abc
import copy
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol

import torch
from torch import Tensor

from sg_torchrl.modules.gaussian import gaussian_log_prob
from sg_torchrl.objectives.kl import gaussian_kl
from sg_torchrl.objectives.second_order import (
    Linearisation,
    SeedFisherVectorProduct,
    natural_step_size,
    seed_flat_grad,
    seed_line_search,
    seed_linearise,
)
from sg_torchrl.objectives.step_rules import CPORule, NaturalRule, PCPORule, Proposal, TRPORule, TrustRegionOptions

__all__ = [
    "SeedProposals",
    "SeedSurrogates",
    "StackedActor",
    "StackedCPOStep",
    "StackedNaturalPolicyStep",
    "StackedPCPOStep",
    "StackedTRPOStep",
    "StackedTrustRegionStep",
    "TrustRegionEngine",
]


class StackedActor(Protocol):
    """What a trust-region step needs of S seeds' diagonal-Gaussian policies.

    Attributes:
        flat_actor: ``(S, P)`` every seed's trainable actor parameters, one row per seed; the step
            writes candidate rows into it (in place) and :meth:`dist_params` must see them.
    """

    flat_actor: Tensor

    @property
    def num_seeds(self) -> int:
        """S."""

    def actor_parameters(self) -> Sequence[Tensor]:
        """The leaves whose gradients, reshaped to ``(S, -1)`` and concatenated, line up with :attr:`flat_actor`."""

    def dist_params(self, obs: Any) -> tuple[Tensor, Tensor]:
        """``(loc, scale)`` of each seed's policy on its observations: ``(S, N, A)`` and broadcastable to it."""

    def actor_rows(self, rows: Tensor) -> StackedActor:
        """A stacked actor of the same networks holding copies of the rows ``rows`` only (a smaller group)."""


def _per_sample(value: Tensor, shape: torch.Size | tuple[int, ...], name: str) -> Tensor:
    """``value`` reshaped to the per-sample ``shape`` (drops one trailing singleton dim)."""
    if value.shape == shape:
        return value
    if value.shape == (*shape, 1):
        return value.squeeze(-1)
    raise ValueError(
        f"{name} has shape {tuple(value.shape)}; expected {tuple(shape)} or {(*shape, 1)} "
        f"(one value per sample, no silent broadcasting)."
    )


class SeedSurrogates:
    """Each seed's reward surrogate, cost surrogate and mean KL on its batch, ``(S,)`` each.

    Per seed, with :math:`r_\\theta = \\exp(\\log\\pi_\\theta(a|s) - \\log\\pi_{\\text{behaviour}}(a|s))`:
    reward :math:`\\mathbb E[r_\\theta A]`, cost :math:`\\mathbb E[r_\\theta A^c]` (zeros without a cost
    advantage) and :math:`\\mathbb E_s[\\mathrm{KL}(\\pi_{\\text{old}} \\| \\pi_\\theta)]`, per sample
    divided by the action dimension for ``kl_action_reduction="mean"`` (SafePO) or not (``"sum"``).
    The quantities of :class:`~sg_torchrl.objectives.TrustRegionLoss` (which has the reward
    surrogate's sign flipped). Calling it runs the model's actor once, with gradients unless under
    :func:`torch.no_grad`.

    Args:
        observation: what ``model.dist_params`` reads, with leading ``(S, N)`` dims (a tensor
            ``(S, N, obs_dim)`` or a TensorDict of batch ``[S, N]``).
        action: ``(S, N, A)``.
        log_prob: behaviour log-probabilities ``(S, N)``.
        advantage, cost_advantage: ``(S, N)`` (``cost_advantage`` may be ``None``).
        old_loc, old_scale: the anchor policy :math:`\\pi_{\\text{old}}`, broadcastable to ``(S, N, A)``.
        kl_action_reduction: ``"mean"`` or ``"sum"`` over action dimensions.
    """

    def __init__(self, observation: Any, action: Tensor, log_prob: Tensor, advantage: Tensor,
                 cost_advantage: Tensor | None, old_loc: Tensor, old_scale: Tensor,
                 kl_action_reduction: Literal["mean", "sum"] = "mean") -> None:
        self.observation, self.action, self.log_prob = observation, action, log_prob
        self.advantage, self.cost_advantage = advantage, cost_advantage
        self.old_loc, self.old_scale = old_loc, old_scale
        self.kl_action_reduction = kl_action_reduction

    def rows(self, index: Tensor) -> SeedSurrogates:
        """The same quantities for the seeds ``index`` only (their batches copied), for a smaller group."""
        def pick(value: Any) -> Any:
            if value is None:
                return None
            return value.index_select(0, index) if isinstance(value, Tensor) else value[index]

        return SeedSurrogates(pick(self.observation), pick(self.action), pick(self.log_prob), pick(self.advantage),
                              pick(self.cost_advantage), pick(self.old_loc), pick(self.old_scale),
                              self.kl_action_reduction)

    def __call__(self, model: StackedActor) -> tuple[Tensor, Tensor, Tensor]:
        return self.evaluate(*model.dist_params(self.observation))

    def evaluate(self, loc: Tensor, scale: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The three quantities for policies of ``loc`` ``(S, N, A)`` and ``scale`` (broadcastable)."""
        ratio = (gaussian_log_prob(self.action, loc, scale) - self.log_prob).exp()
        reward = (ratio * self.advantage).mean(1)
        cost = torch.zeros_like(reward) if self.cost_advantage is None else (ratio * self.cost_advantage).mean(1)
        kl = gaussian_kl(self.old_loc, self.old_scale, loc, scale)
        if self.kl_action_reduction == "mean":
            kl = kl / loc.shape[-1]
        return reward, cost, kl.mean(1)


@dataclass(frozen=True)
class SeedProposals:
    """The seeds' :class:`~sg_torchrl.objectives.step_rules.Proposal`\\ s, stacked.

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


class TrustRegionEngine(TrustRegionOptions, abc.ABC):
    """The trust-region step of every seed of a :class:`StackedActor`; subclasses only name the per-seed proposal.

    :meth:`step_seeds` (see the module docstring for how the seeds are batched):

    1. one stacked pass of :class:`SeedSurrogates` with gradients: every seed's :math:`g` (and
       :math:`b` for CPO / PCPO) and the Fisher-vector product of its KL;
    2. :func:`~sg_torchrl.objectives.second_order.seed_linearise` (batched conjugate gradient);
    3. the proposal of each seed (:meth:`_propose`, a rule of :mod:`sg_torchrl.objectives.step_rules`)
       on its own linearisation and violation :math:`c_s = J_{c,s} - d`;
    4. applies each seed's direction directly (``line_search_steps=0``, NPG) or backtracks all seeds
       together, a seed stopping at its first acceptable trial; a seed with none keeps its row.

    Keyword Args:
        **options: :class:`~sg_torchrl.objectives.step_rules.TrustRegionOptions` (``target_kl`` 0.01,
            ``cg_iters`` 15, ``cg_damping`` 0.1, ``line_search_steps`` (``None``: the method's
            default), ``step_fraction`` 0.8, ``cg_residual_tol``, ``cg_eps``, ``kl_action_reduction``
            ``"mean"``), the same for every seed.

    Returned metrics, ``(S,)`` float64 each (SafePO's names): ``Misc/Alpha`` (:math:`\\sqrt{2\\delta/q}`),
    ``Misc/FinalStepNorm`` (norm of the proposed direction, 0 when rejected; SafePO's definition,
    before backtracking), ``Misc/xHx``, ``Misc/gradient_norm`` (:math:`\\|g\\|`), ``Misc/H_inv_g``
    (:math:`\\|x\\|`), ``Misc/AcceptanceStep`` (accepted trial from 1, 0 when rejected), ``Train/KL``
    (KL after the step, 0 when rejected), ``Loss/Loss_actor`` (minus the surrogate before the step),
    plus ``Misc/cost_gradient_norm`` for the constrained steps and the proposal's extras.
    """

    model: StackedActor

    # ------------------------------------------------------------------ hook
    @abc.abstractmethod
    def _propose(self, lin: Linearisation, cost_violation: float) -> Proposal:
        """One seed's step direction and acceptance tests (the only algorithm-specific part)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ body
    def step_seeds(self, surrogates: SeedSurrogates, violations: Sequence[float]) -> dict[str, Tensor]:
        """One trust-region update of every row of ``self.model.flat_actor`` (in place).

        Args:
            surrogates: the seeds' batches, anchored at the policies as they are (``old_loc`` /
                ``old_scale`` detached, so :math:`H` is exactly the Fisher matrix at :math:`\\theta_k`).
            violations: :math:`c_s = J_{c,s} - d` per seed, as Python floats (unused by NPG / TRPO).
        """
        if self.uses_cost and surrogates.cost_advantage is None:
            raise ValueError(f"{type(self).__name__} needs the cost advantage.")
        lin, before_reward, before_cost = self._linearise(surrogates)
        proposals = SeedProposals.stack([self._propose(seed_lin, c) for seed_lin, c in zip(lin.seeds(), violations)])
        step_index, kl_after = self._apply(surrogates, proposals, before_reward, before_cost)
        return self._metrics(lin, proposals, step_index, kl_after, before_reward)

    def _linearise(self, surrogates: SeedSurrogates) -> tuple[Linearisation, Tensor, Tensor]:
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
        """Which seeds' candidates pass the acceptance tests, ``(S,)`` bool.

        In double precision: finite surrogates and KL, :math:`\\mathrm{KL} \\le \\delta`, no decrease
        of the reward surrogate when the proposal requires it, and an increase of the cost surrogate
        within its tolerance.
        """
        reward, cost, kl = reward.double(), cost.double(), kl.double()
        ok = torch.isfinite(reward) & torch.isfinite(cost) & torch.isfinite(kl) & (kl <= self.target_kl)
        ok &= ~(proposals.require_improvement & (reward < before_reward.double()))
        return ok & (~proposals.checks_cost | (cost - before_cost.double() <= proposals.cost_tolerance))

    @torch.no_grad()
    def _apply(self, surrogates: SeedSurrogates, proposals: SeedProposals, before_reward: Tensor,
               before_cost: Tensor) -> tuple[Tensor, Tensor]:
        """Moves the rows of ``flat_actor``; returns each seed's accepted trial (0: none) and KL after.

        A trial evaluates only the seeds still searching: the whole group while none has stopped,
        then a smaller group of just those rows (``model.actor_rows``), so a seed that backtracks far
        (PCPO tries up to 200 fractions) does not make every seed pay for each trial.
        """
        model = self.model
        theta_old = model.flat_actor.clone()
        if self.line_search_steps == 0:
            model.flat_actor.copy_(theta_old + proposals.direction)
            kl = surrogates(model)[2].double()
            return torch.ones_like(kl), kl
        kl_after = torch.zeros(theta_old.shape[0], dtype=torch.float64, device=theta_old.device)
        group, part, tests = model, surrogates, proposals

        def accept(searching: Tensor, candidates: Tensor) -> Tensor:
            nonlocal group, part, tests
            if searching.numel() != group.num_seeds:  # some seeds stopped: the others alone
                group, part, tests = model.actor_rows(searching), surrogates.rows(searching), proposals.rows(searching)
            group.flat_actor.copy_(candidates)
            reward, cost, kl = part(group)
            ok = self.acceptable(reward, cost, kl, before_reward[searching], before_cost[searching], tests)
            kl_after[searching[ok]] = kl[ok].double()
            return ok

        result = seed_line_search(theta_old, proposals.direction, accept, max_trials=self.line_search_steps,
                                  step_fraction=self.step_fraction)
        model.flat_actor.copy_(result.theta)
        return result.step_index, kl_after

    def _metrics(self, lin: Linearisation, proposals: SeedProposals, step_index: Tensor, kl_after: Tensor,
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


class StackedTrustRegionStep(TrustRegionEngine):
    """The trust-region step of a seed group: :class:`TrustRegionEngine` on stacked ``(S, N, ...)`` batches.

    Args:
        model: the seed group's networks (a :class:`StackedActor`, e.g.
            :class:`~sg_torchrl.modules.stacked.StackedActorCritic`); rows of ``model.flat_actor`` are
            changed in place.

    Keyword Args:
        **options: see :class:`TrustRegionEngine`.
    """

    def __init__(self, model: StackedActor, **options) -> None:
        super().__init__(**options)
        self.model = model

    def for_rows(self, rows: Tensor) -> StackedTrustRegionStep:
        """This step (same class and options) on a copy of the actor rows ``rows`` alone.

        A seed group steps only its live seeds with it: a frozen seed's row may not be finite, and
        would otherwise search all its line-search trials every epoch. Copy the moved rows back.
        """
        part = copy.copy(self)
        part.model = self.model.actor_rows(rows)
        return part

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
                tensor (the proposals read Python floats; float32 would round them). Unused by
                NPG / TRPO.

        Returns:
            The metrics of :class:`TrustRegionEngine`, ``(S,)`` each.
        """
        model = self.model
        observation, action = batch["observation"], batch["action"]
        seeds = model.num_seeds
        shape = observation.shape[:2]
        if shape[0] != seeds or action.shape[:2] != shape:
            raise ValueError(f"expected (S={seeds}, N, ...) observations and actions, got "
                             f"{tuple(observation.shape)} and {tuple(action.shape)}.")
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
        return self.step_seeds(surrogates, violations)


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
