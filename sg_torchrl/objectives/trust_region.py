"""Trust-region policy steps: NPG / RCPO, TRPO / TRPO-Lag, CPO and PCPO.

Second-order methods do not minimise a loss with an optimiser. Once per epoch they linearise the
objective (and the cost) around the current policy :math:`\\theta_k`, model the KL divergence to
it by its quadratic form :math:`\\tfrac12 d^\\top H d` (:math:`H` the Fisher information matrix)
and move the actor's parameters directly:

.. math::

    \\max_d\\; g^\\top d \\quad \\text{s.t.} \\quad \\tfrac12 d^\\top H d \\le \\delta
    \\;\\;[\\text{and } c + b^\\top d \\le 0 \\text{ for CPO / PCPO}],

with :math:`g` and :math:`b` the gradients of the reward and cost surrogates
:math:`\\mathbb E[r_\\theta A]`, :math:`\\mathbb E[r_\\theta A^c]`
(:math:`r_\\theta = \\pi_\\theta(a|s) / \\pi_{\\text{behaviour}}(a|s)`) and
:math:`c = J_c - d` the constraint violation.

This module splits the work in three layers so that each can be checked alone:

* :class:`TrustRegionLoss`, a TorchRL :class:`~torchrl.objectives.LossModule` that computes the two
  surrogates and the mean KL in one actor pass (reused by the multi-agent MACPO);
* the pure step computations :func:`cpo_direction` and :func:`pcpo_direction` over
  :func:`~sg_torchrl.objectives.second_order.linearise` (functions of :math:`g, b, H, c, \\delta`,
  unit-tested against an independent QP solver), with each method's proposal and settings as a rule
  mixin, in :mod:`sg_torchrl.objectives.step_rules` (shared with the seed groups' stacked steps);
* the step strategies the trainer calls once per epoch, one small class each (a rule over the common
  :class:`TrustRegionStep`): :class:`NaturalPolicyStep` (Kakade 2002), :class:`TRPOStep` (Schulman et
  al. 2015), :class:`CPOStep` (Achiam et al. 2017) and :class:`PCPOStep` (Yang et al. 2020).

Lagrangian variants are not separate classes: TRPO-Lag is :class:`TRPOStep` fed the Lagrangian
advantage :math:`(A_r - \\lambda A_c)/(1 + \\lambda)` (``multiplier.combine``), and RCPO as SafePO
implements it (an NPG-Lagrangian, not Tessler et al.'s reward shaping) is :class:`NaturalPolicyStep`
fed the same. Defaults are the Safety-Gymnasium paper's (Ji et al. 2023): :math:`\\delta = 0.01`,
15 conjugate-gradient iterations, damping 0.1, 15 backtracking steps of 0.8 (PCPO 200).

**KL convention.** As in SafePO, the KL that defines :math:`H`, is checked by the line search and
is logged as ``Train/KL`` is averaged over samples *and action dimensions*
(``kl_action_reduction="mean"``). The TRPO / CPO papers use the KL of the joint action
distribution (summed over dimensions, ``"sum"``), for which the same :math:`\\delta` is a trust
region ``action_dim`` times tighter. We keep SafePO's convention by default because the paper's
:math:`\\delta = 0.01` was tuned with it.

**Where we follow the papers instead of SafePO** (SafePO's behaviour marked **[quirk]**):

* CPO's dual (cases 1, 2): SafePO applies the paper's loss-convention formulas to the ascent
  gradient, flipping the sign of :math:`r`, and projects onto empty intervals when
  :math:`r/c \\le 0`; its direction then is not the QP's solution. We solve the QP
  (:func:`cpo_direction`; ``safepo_dual=True`` reproduces SafePO).
* PCPO's reward step uses :math:`H^{-1} g` (Yang et al. 2020), not SafePO's :math:`H (H^{-1} g)`
  (``use_hx_direction=True`` reproduces SafePO).
* Line search: a candidate with a non-finite surrogate or KL is rejected and the step shrinks
  (SafePO retries the same fraction after a non-finite KL, and accepts non-finite surrogates).
* ``Loss/Loss_actor`` is minus the reward surrogate before the step for every method (SafePO logs
  the last line-search trial's loss for TRPO and reward + cost losses for CPO / PCPO).
"""
from __future__ import annotations

import abc
import math
from dataclasses import dataclass
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.objectives import LossModule

from sg_torchrl.objectives.kl import gaussian_kl
from sg_torchrl.objectives.second_order import (
    backtracking_line_search,
    FisherVectorProduct,
    flat_grad,
    flat_params,
    linearise,
    Linearisation,
    LineSearchResult,
    natural_step_size,
    set_flat_params,
)
from sg_torchrl.objectives.step_rules import (  # re-exported: the step rules' home
    CPODirection,
    CPORule,
    NaturalRule,
    PCPORule,
    Proposal,
    TRPORule,
    TrustRegionOptions,
    cpo_direction,
    cpo_proposal,
    natural_proposal,
    pcpo_direction,
    pcpo_proposal,
)

__all__ = [
    "CPODirection",
    "CPOStep",
    "NaturalPolicyStep",
    "PCPOStep",
    "TRPOStep",
    "TrustRegionLoss",
    "TrustRegionStep",
    "cpo_direction",
    "cpo_proposal",
    "natural_proposal",
    "pcpo_direction",
    "pcpo_proposal",
]



def _per_sample(value: Tensor, shape: torch.Size, name: str) -> Tensor:
    """``value`` reshaped to the per-sample ``shape`` (drops one trailing singleton dim)."""
    if value.shape == shape:
        return value
    if value.shape == (*shape, 1):
        return value.squeeze(-1)
    raise ValueError(
        f"{name} has shape {tuple(value.shape)}; expected {tuple(shape)} or {(*shape, 1)} "
        f"(one value per sample, no silent broadcasting)."
    )


# ============================================================================ loss module
class TrustRegionLoss(LossModule):
    """Reward / cost surrogates and the mean KL of a Gaussian policy, for trust-region steps.

    With :math:`r_\\theta = \\exp(\\log\\pi_\\theta(a|s) - \\log\\pi_{\\text{behaviour}}(a|s))`
    (the behaviour log-prob is the collector's ``"action_log_prob"``):

    * ``loss_objective`` :math:`= -\\mathbb E[r_\\theta A]` (minus the reward surrogate of TRPO,
      Schulman et al. 2015, eq. 14; ``A`` may be a Lagrangian advantage);
    * ``loss_cost`` :math:`= \\mathbb E[r_\\theta A^c]`, the cost surrogate of CPO (Achiam et al.
      2017), only when the cost advantage is in the input;
    * ``kl`` :math:`= \\mathbb E_s[\\mathrm{KL}(\\pi_{\\text{old}}(\\cdot|s) \\,\\|\\, \\pi_\\theta(\\cdot|s))]`,
      with :math:`\\pi_{\\text{old}}` read from the input's ``"loc"`` / ``"scale"``; per sample
      averaged over action dimensions (``kl_action_reduction="mean"``, SafePO) or summed
      (``"sum"``, the joint-distribution KL of the papers).

    All three come from one forward pass of the actor and keep their graphs, so a step can
    differentiate them (gradients, Fisher-vector products) or evaluate them under
    :func:`torch.no_grad` during a line search. The actor is held as a plain sub-module (not
    functionalised): trust-region steps write its parameters in place.

    Args:
        actor_network (ProbabilisticTensorDictSequential): diagonal-Gaussian policy (e.g. a
            :class:`~torchrl.modules.ProbabilisticActor` with
            :class:`~torchrl.modules.IndependentNormal`); its distribution's ``mean`` / ``stddev``
            are the new ``loc`` / ``scale``.

    Keyword Args:
        kl_action_reduction (str): ``"mean"`` (default, SafePO) or ``"sum"`` over action dims.

    Input keys (configurable with :meth:`set_keys`): the actor's ``in_keys``, ``"action"``,
    ``"action_log_prob"`` (the actor's own ``log_prob_key`` when it has one), ``"advantage"``,
    optionally ``"cost_advantage"``, and the old policy's ``"loc"`` / ``"scale"``. Advantages may be
    ``[*B]`` or ``[*B, 1]``. The loss holds no critic, so it cannot compute a missing advantage
    (TorchRL's convention for losses with a critic): a missing ``"advantage"`` raises a ``KeyError``
    that says how to compute it.
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable input keys of :class:`TrustRegionLoss`."""

        advantage: NestedKey = "advantage"
        cost_advantage: NestedKey = "cost_advantage"
        action: NestedKey = "action"
        sample_log_prob: NestedKey = "action_log_prob"
        loc: NestedKey = "loc"
        scale: NestedKey = "scale"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    actor_network: ProbabilisticTensorDictSequential

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        *,
        kl_action_reduction: Literal["mean", "sum"] = "mean",
    ) -> None:
        if kl_action_reduction not in ("mean", "sum"):
            raise ValueError(f"kl_action_reduction must be 'mean' or 'sum', got {kl_action_reduction!r}.")
        super().__init__()
        self.actor_network = actor_network
        self.kl_action_reduction = kl_action_reduction
        log_prob_key = getattr(actor_network, "log_prob_key", None)
        if isinstance(log_prob_key, (str, tuple)):
            self.set_keys(sample_log_prob=log_prob_key)
        self._set_in_keys()
        self.out_keys = ["loss_objective", "loss_cost", "kl"]

    @property
    def functional(self) -> bool:
        return False

    def _set_in_keys(self) -> None:
        tk = self.tensor_keys
        keys = [*self.actor_network.in_keys, tk.action, tk.sample_log_prob, tk.advantage,
                tk.cost_advantage, tk.loc, tk.scale]
        self.in_keys = list(dict.fromkeys(keys))

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        self._set_in_keys()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes ``loss_objective``, ``loss_cost`` (if the cost advantage is given) and ``kl``."""
        tk = self.tensor_keys
        dist = self.actor_network.get_dist(tensordict.select(*self.actor_network.in_keys))
        log_prob = dist.log_prob(tensordict.get(tk.action))
        old_log_prob = _per_sample(tensordict.get(tk.sample_log_prob), log_prob.shape, "action_log_prob")
        ratio = (log_prob - old_log_prob).exp()
        advantage = tensordict.get(tk.advantage, None)
        if advantage is None:
            raise KeyError(
                f"TrustRegionLoss did not find {tk.advantage!r} in the input. It has no critics, so "
                f"unlike the first-order losses it cannot compute advantages: compute them on the "
                f"whole batch first (PPOLagLoss.estimate_advantages, or make_gae / make_cost_gae and "
                f"normalize_advantages), or remap the key with loss.set_keys(...)."
            )
        advantage = _per_sample(advantage, log_prob.shape, "advantage")
        out = {"loss_objective": -(ratio * advantage).mean()}
        cost_advantage = tensordict.get(tk.cost_advantage, None)
        if cost_advantage is not None:
            cost_advantage = _per_sample(cost_advantage, log_prob.shape, "cost_advantage")
            out["loss_cost"] = (ratio * cost_advantage).mean()
        kl = gaussian_kl(tensordict.get(tk.loc), tensordict.get(tk.scale), dist.mean, dist.stddev)
        if self.kl_action_reduction == "mean":
            kl = kl / dist.mean.shape[-1]
        out["kl"] = kl.mean()
        return TensorDict(out, batch_size=[])


# ============================================================================ pure step maths
@dataclass(frozen=True)
class _Evaluation:
    """Reward surrogate, cost surrogate and mean KL of the policy as it currently is."""

    reward: float
    cost: float
    kl: float

    @classmethod
    def of(cls, losses: TensorDictBase) -> _Evaluation:
        cost = losses.get("loss_cost", None)
        return cls(
            reward=-float(losses.get("loss_objective")),
            cost=float(cost) if cost is not None else 0.0,
            kl=float(losses.get("kl")),
        )

    def finite(self) -> bool:
        return all(math.isfinite(v) for v in (self.reward, self.cost, self.kl))


class TrustRegionStep(TrustRegionOptions, abc.ABC):
    """Common body of the trust-region policy steps; subclasses only propose a direction.

    :meth:`step` (called by the trainer once per epoch on the whole flattened batch):

    1. anchors :math:`\\pi_{\\text{old}}` at the actor as it is (detached ``loc`` / ``scale``; for
       on-policy data this equals the behaviour policy the collector stored, and it keeps
       :math:`H` exactly the Fisher matrix at :math:`\\theta_k`);
    2. evaluates :class:`TrustRegionLoss` once with gradients: :math:`g`, optionally :math:`b`, and
       the damped Fisher-vector product of its KL
       (:class:`~sg_torchrl.objectives.second_order.FisherVectorProduct`);
    3. :func:`~sg_torchrl.objectives.second_order.linearise`: :math:`x = H^{-1}g` (and :math:`p = H^{-1}b`) by conjugate gradient;
    4. :meth:`_propose` (the subclass): the step direction and its acceptance tests;
    5. applies the direction directly (``line_search_steps=0``) or backtracks
       (:func:`~sg_torchrl.objectives.second_order.backtracking_line_search`), accepting a candidate
       when its surrogates and KL are finite, :math:`\\mathrm{KL} \\le \\delta`, and the proposal's
       improvement / cost tests pass; if none passes the actor is left unchanged.

    Args:
        actor (ProbabilisticTensorDictSequential): the Gaussian policy; its parameters are changed
            in place (under :func:`torch.no_grad`).

    Keyword Args:
        **options: :class:`~sg_torchrl.objectives.step_rules.TrustRegionOptions` (``target_kl`` 0.01,
            ``cg_iters`` 15, ``cg_damping`` 0.1, ``line_search_steps`` (``None``: the method's default),
            ``step_fraction`` 0.8, ``cg_residual_tol``, ``cg_eps``, ``kl_action_reduction`` ``"mean"``, see
            the module docstring).

    Returned metrics (SafePO's names): ``Misc/Alpha`` (:math:`\\sqrt{2\\delta/q}`),
    ``Misc/FinalStepNorm`` (norm of the proposed direction, 0 when rejected; SafePO's definition,
    before backtracking), ``Misc/xHx``, ``Misc/gradient_norm`` (:math:`\\|g\\|`), ``Misc/H_inv_g``
    (:math:`\\|x\\|`), ``Misc/AcceptanceStep`` (accepted trial from 1, 0 when rejected),
    ``Train/KL`` (KL after the step), ``Loss/Loss_actor`` (minus the surrogate before the step),
    plus ``Misc/cost_gradient_norm`` for the constrained steps and subclass extras.
    """

    def __init__(self, actor: ProbabilisticTensorDictSequential, **options) -> None:
        super().__init__(**options)
        self.loss = TrustRegionLoss(actor, kl_action_reduction=self.kl_action_reduction)
        self.params = [p for p in actor.parameters() if p.requires_grad]

    # ------------------------------------------------------------------ hook
    @abc.abstractmethod
    def _propose(self, lin: Linearisation, cost_violation: float) -> Proposal:
        """The step direction and its acceptance tests (the only algorithm-specific part)."""

    # ------------------------------------------------------------------ body
    def step(
        self,
        data: TensorDictBase,
        advantage: Tensor,
        cost_advantage: Tensor,
        cost_violation: float,
    ) -> dict[str, float]:
        """One trust-region update of the actor on the whole batch.

        Args:
            data (TensorDictBase): flattened batch ``[B]`` with ``"observation"``, ``"action"`` and
                ``"action_log_prob"`` (behaviour log-prob). Its ``"loc"`` / ``"scale"`` are replaced,
                in a shallow copy, by the actor's current ones (see the class docstring).
            advantage (Tensor): the (Lagrangian, normalised) reward advantage ``[B, 1]``.
            cost_advantage (Tensor): the mean-centred cost advantage ``[B, 1]``.
            cost_violation (float): :math:`c = J_c - d` (unused by NPG / TRPO).

        Returns:
            The metrics listed in the class docstring, as Python floats.
        """
        batch = self._batch(data, advantage, cost_advantage)
        losses = self.loss(batch)
        before = _Evaluation.of(losses.detach())
        lin = self._linearise(losses)
        proposal = self._propose(lin, float(cost_violation))
        result, kl_after = self._apply(batch, proposal, before)
        return self._metrics(lin, proposal, result, kl_after, before)

    def _batch(self, data: TensorDictBase, advantage: Tensor, cost_advantage: Tensor | None) -> TensorDictBase:
        tk, actor = self.loss.tensor_keys, self.loss.actor_network
        with torch.no_grad():
            dist = actor.get_dist(data.select(*actor.in_keys))
            loc, scale = dist.mean.detach(), dist.stddev.detach()
        batch = data.copy()
        batch.set(tk.loc, loc)
        batch.set(tk.scale, scale)
        batch.set(tk.advantage, advantage.detach())
        if cost_advantage is not None:
            batch.set(tk.cost_advantage, cost_advantage.detach())
        return batch

    def _linearise(self, losses: TensorDictBase) -> Linearisation:
        fvp = FisherVectorProduct(losses.get("kl"), self.params, self.cg_damping)
        g = -flat_grad(losses.get("loss_objective"), self.params, retain_graph=True)
        b = flat_grad(losses.get("loss_cost"), self.params, retain_graph=True) if self.uses_cost else None
        return linearise(fvp, g.detach(), None if b is None else b.detach(), cg_iters=self.cg_iters,
                         residual_tol=self.cg_residual_tol, eps=self.cg_eps)

    @torch.no_grad()
    def _evaluate(self, batch: TensorDictBase) -> _Evaluation:
        return _Evaluation.of(self.loss(batch))

    def _acceptable(self, after: _Evaluation, before: _Evaluation, proposal: Proposal) -> bool:
        if not after.finite() or after.kl > self.target_kl:
            return False
        if proposal.require_improvement and after.reward < before.reward:
            return False
        return proposal.cost_tolerance is None or after.cost - before.cost <= proposal.cost_tolerance

    def _apply(self, batch: TensorDictBase, proposal: Proposal, before: _Evaluation) -> tuple[LineSearchResult, float]:
        theta_old = flat_params(self.params)
        if self.line_search_steps == 0:
            set_flat_params(self.params, theta_old + proposal.direction)
            return LineSearchResult(step_index=1, step_fraction=1.0), self._evaluate(batch).kl
        trials: list[_Evaluation] = []

        def accept() -> bool:
            trials.append(self._evaluate(batch))
            return self._acceptable(trials[-1], before, proposal)

        result = backtracking_line_search(self.params, theta_old, proposal.direction, accept,
                                          max_trials=self.line_search_steps, step_fraction=self.step_fraction)
        return result, trials[-1].kl if result.accepted else 0.0

    def _metrics(self, lin: Linearisation, proposal: Proposal, result: LineSearchResult, kl_after: float,
                 before: _Evaluation) -> dict[str, float]:
        metrics = {
            "Misc/Alpha": natural_step_size(lin.q, self.target_kl),
            "Misc/FinalStepNorm": float(proposal.direction.norm()) if result.accepted else 0.0,
            "Misc/xHx": lin.q,
            "Misc/gradient_norm": float(lin.g.norm()),
            "Misc/H_inv_g": float(lin.x.norm()),
            "Misc/AcceptanceStep": float(result.step_index),
            "Train/KL": kl_after,
            "Loss/Loss_actor": -before.reward,
        }
        if lin.b is not None:
            metrics["Misc/cost_gradient_norm"] = float(lin.b.norm())
        metrics.update(proposal.metrics)
        return metrics


class NaturalPolicyStep(NaturalRule, TrustRegionStep):
    """Natural policy gradient step :math:`\\theta \\leftarrow \\theta + \\sqrt{2\\delta/x^\\top Hx}\\; x`.

    Kakade 2002, "A Natural Policy Gradient", with the step length that puts the quadratic KL model
    on the trust-region boundary; no line search (``line_search_steps=0``). Fed the Lagrangian
    advantage this is SafePO's RCPO. ``Misc/AcceptanceStep`` is 1 (the step is always taken).
    """


class TRPOStep(TRPORule, NaturalPolicyStep):
    """TRPO (Schulman et al. 2015): the natural step, backtracked until it improves and stays in the region.

    Up to ``line_search_steps`` (15) trials of :math:`0.8^k` of the natural step; a trial is accepted
    when the surrogate did not decrease and :math:`\\mathrm{KL} \\le \\delta`; otherwise no update.
    Fed the Lagrangian advantage this is TRPO-Lag.
    """


class CPOStep(CPORule, TrustRegionStep):
    """Constrained Policy Optimization (Achiam et al. 2017): the step of :func:`cpo_direction`, backtracked.

    Up to ``line_search_steps`` (15) trials of :math:`0.8^k` of the direction, accepted when the KL is
    finite and :math:`\\le \\delta`, the cost surrogate grew by at most :math:`\\max(-c, 0)` and, in
    cases 2-4 (feasible policy), the reward surrogate did not decrease; otherwise no update.
    Extra metrics: ``Misc/cost_gradient_norm``, ``Misc/CPOCase``, ``Misc/Lambda_star``,
    ``Misc/Nu_star``.

    The direction solves the paper's QP; SafePO's dual has the sign of :math:`r` flipped
    **[quirk]** (see :func:`_cpo_lambda`), available for comparison with ``safepo_dual=True``.

    Keyword Args:
        safepo_dual (bool): see :func:`cpo_direction`. Defaults to ``False``.
        **kwargs: see :class:`TrustRegionStep`.
    """


class PCPOStep(PCPORule, TrustRegionStep):
    """Projection-based CPO (Yang et al. 2020): :func:`pcpo_direction`, backtracked.

    Up to ``line_search_steps`` (200) trials of :math:`0.8^k`, with CPO's acceptance tests minus the
    reward-improvement test (SafePO fixes the CPO case to 0 for PCPO).

    Keyword Args:
        use_hx_direction (bool): ``False`` (default) uses the paper's reward step
            :math:`\\sqrt{2\\delta/q}\\, H^{-1} g`; ``True`` reproduces SafePO's **[quirk]** of
            stepping along :math:`Hx \\approx g` instead.
        **kwargs: see :class:`TrustRegionStep`.
    """

