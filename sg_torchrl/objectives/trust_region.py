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
  unit-tested against an independent QP solver);
* the step strategies the trainer calls once per epoch, one small class each over the common
  :class:`TrustRegionStep`: :class:`NaturalPolicyStep` (Kakade 2002), :class:`TRPOStep` (Schulman et
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
from dataclasses import dataclass, field
from typing import ClassVar, Literal, NamedTuple

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

_EPS = 1e-8  # SafePO's guard in the CPO / PCPO divisions by s and lambda


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
class CPODirection(NamedTuple):
    """CPO's step direction, its case (0-4, see :func:`cpo_direction`) and the optimal duals."""

    direction: Tensor
    case: int
    lam: float
    nu: float


def _cpo_lambda(q: float, r: float, s: float, c: float, delta: float, *, safepo: bool = False) -> float:
    """Optimal :math:`\\lambda^*` of CPO's dual in cases 1 and 2 (Achiam et al. 2017, section 6.1, appendix 10.2).

    For :math:`\\max_d g^\\top d` s.t. :math:`\\tfrac12 d^\\top H d \\le \\delta`, :math:`c + b^\\top d \\le 0`
    the dual is :math:`\\max_{\\lambda, \\nu \\ge 0} -\\frac{1}{2\\lambda}(q - 2r\\nu + s\\nu^2) + \\nu c -
    \\lambda\\delta` (:math:`q = g^\\top H^{-1} g`, :math:`r = g^\\top H^{-1} b`, :math:`s = b^\\top H^{-1} b`),
    with :math:`\\nu^*(\\lambda) = (\\lambda c + r)_+ / s` and the primal step
    :math:`d = H^{-1}(g - \\nu b) / \\lambda`. Eliminating :math:`\\nu` leaves a piecewise function:
    :math:`f_a(\\lambda) = -\\tfrac12 (A/\\lambda + B\\lambda) + rc/s` where :math:`\\lambda c + r > 0`
    and :math:`f_b(\\lambda) = -\\tfrac12 (q/\\lambda + 2\\delta\\lambda)` elsewhere, with
    :math:`A = q - r^2/s`, :math:`B = 2\\delta - c^2/s`. Each piece's maximiser
    (:math:`\\sqrt{A/B}`, :math:`\\sqrt{q/2\\delta}`) is projected onto its interval, split at
    :math:`\\lambda_{\\text{mid}} = -r/c`, and the better piece wins; when
    :math:`\\lambda_{\\text{mid}} \\le 0` one piece covers every :math:`\\lambda \\ge 0` (:math:`f_b` if
    :math:`c < 0`, :math:`f_a` otherwise), as in Achiam's reference implementation.

    Here :math:`g` is the *ascent* direction of the reward surrogate. The paper's appendix writes the
    same formulas for a loss gradient to minimise, :math:`-g`, hence its :math:`\\nu^* = (\\lambda c -
    r)_+/s`, :math:`\\lambda_{\\text{mid}} = r/c` and :math:`-rc/s`. SafePO (like OmniSafe) uses those
    loss-convention formulas with the ascent gradient, i.e. with the sign of :math:`r` flipped, and
    projects onto :math:`[0, r/c]` even when that interval is empty **[quirk]**; its direction then
    does not solve the QP whenever :math:`r \\neq 0` (it can leave the trust region or step against
    the reward). We solve the QP of the paper; ``tests/test_trust_region.py`` checks the step
    against an independent QP solver. ``safepo=True`` (with ``r`` negated by the caller) reproduces
    SafePO's arithmetic: no :math:`\\lambda_{\\text{mid}} \\le 0` branch and :math:`c + 10^{-8}` in
    :math:`\\lambda_{\\text{mid}}`.
    """
    A = max(q - r * r / (s + _EPS), 0.0)  # >= 0 by Cauchy-Schwarz; clipped against CG round-off
    B = max(2.0 * delta - c * c / (s + _EPS), _EPS)  # >= 0 in cases 1 and 2
    lam_a = math.sqrt(A / B)
    lam_b = math.sqrt(q / (2.0 * delta))
    if safepo:  # torch.clamp onto an empty interval returns its upper end, as below
        lam_mid = -r / (c + _EPS)
    else:
        lam_mid = -r / c if c != 0.0 else math.copysign(math.inf, -r)
        if lam_mid <= 0.0:
            return lam_b if c < 0.0 else lam_a
    if c < 0.0:  # nu > 0 (piece f_a) on [0, lam_mid), nu = 0 (piece f_b) on [lam_mid, inf)
        lam_a, lam_b = min(lam_a, lam_mid), max(lam_b, lam_mid)
    else:  # f_a on (lam_mid, inf), f_b on [0, lam_mid]
        lam_a, lam_b = max(lam_a, lam_mid), min(lam_b, lam_mid)

    def f_a(lam: float) -> float:
        return -0.5 * (A / (lam + _EPS) + B * lam) + r * c / (s + _EPS)

    def f_b(lam: float) -> float:
        return -0.5 * (q / (lam + _EPS) + 2.0 * delta * lam)

    return lam_a if f_a(lam_a) >= f_b(lam_b) else lam_b


def cpo_direction(lin: Linearisation, c: float, delta: float, *, safepo_dual: bool = False) -> CPODirection:
    """CPO's step: the solution of the trust-region QP with the linearised cost constraint.

    Solves :math:`\\max_d g^\\top d` s.t. :math:`\\tfrac12 d^\\top H d \\le \\delta`,
    :math:`c + b^\\top d \\le 0` through its dual (Achiam et al. 2017, section 6.1 and appendix
    10.2), with SafePO's case numbering:

    * **4**: :math:`\\|b\\|^2 \\le 10^{-6}` and :math:`c < 0`: no usable cost gradient and the
      policy is feasible; the TRPO step :math:`\\sqrt{2\\delta/q}\\,x`;
    * **3**: :math:`c < 0` and :math:`B = 2\\delta - c^2/s < 0`: the whole trust region is feasible,
      the constraint is inactive; the TRPO step;
    * **2**: :math:`c < 0 \\le B`: feasible, the constraint may bind; dual solution
      :math:`d = (x - \\nu^* p)/\\lambda^*` (:func:`_cpo_lambda`);
    * **1**: :math:`c \\ge 0` and :math:`B \\ge 0`: infeasible but the trust region reaches the
      feasible set ("feasible recovery"); same dual solution;
    * **0**: :math:`c \\ge 0 > B`: infeasible and out of reach ("infeasible recovery"); the pure
      cost-descent step :math:`-\\sqrt{2\\delta/s}\\,p` of the paper's equation (14).

    Args:
        lin (Linearisation): from :func:`linearise` *with* a cost gradient.
        c (float): constraint value :math:`J_c - d`. SafePO uses the undiscounted mean episode cost
            minus the limit (no :math:`(1-\\gamma)` scaling); the caller decides.
        delta (float): trust-region size :math:`\\delta`.

    Keyword Args:
        safepo_dual (bool): reproduce SafePO's dual for cases 1 and 2, which uses the paper's
            loss-convention formulas with the ascent gradient (the sign of :math:`r` flipped, see
            :func:`_cpo_lambda`) **[quirk]**: ``nu = max(lam * c - r, 0) / s``. Its direction does
            not solve the QP; only for side-by-side comparison with SafePO's numbers. Defaults to
            ``False`` (the paper).
    """
    if lin.p is None or lin.b is None or lin.r is None or lin.s is None:
        raise ValueError("cpo_direction needs a linearisation with a cost gradient (linearise(..., b=...)).")
    x, p, q, r, s = lin.x, lin.p, lin.q, lin.r, lin.s
    B = 2.0 * delta - c * c / (s + _EPS)
    no_cost_gradient = float(torch.dot(lin.b, lin.b)) <= 1e-6
    if c < 0.0 and (no_cost_gradient or B < 0.0):
        alpha = natural_step_size(q, delta)
        return CPODirection(alpha * x, 4 if no_cost_gradient else 3, 1.0 / alpha, 0.0)
    if B < 0.0:
        nu = math.sqrt(2.0 * delta / (s + _EPS))
        return CPODirection(-nu * p, 0, 0.0, nu)
    if safepo_dual:
        r = -r
    lam = _cpo_lambda(q, r, s, c, delta, safepo=safepo_dual)
    nu = max(lam * c + r, 0.0) / (s + _EPS)
    return CPODirection((x - nu * p) / (lam + _EPS), 2 if c < 0.0 else 1, lam, nu)


def pcpo_direction(lin: Linearisation, c: float, delta: float, *, use_hx: bool = False) -> Tensor:
    """PCPO's step: a natural reward step, then a KL projection onto the linearised cost constraint.

    Yang et al. 2020 (eq. 8, KL projection):

    .. math::

        d = \\alpha\\, v - \\max\\Big(0, \\frac{\\alpha\\, r + c}{s}\\Big)\\, p, \\qquad
        \\alpha = \\sqrt{2\\delta/q},\\; v = x = H^{-1} g,

    so :math:`c + b^\\top d = \\min(c + \\alpha\\, b^\\top x, 0) \\le 0` (with exact solves,
    :math:`b^\\top x = r`): the projection moves the natural step onto the constraint's boundary when
    it violates the constraint and leaves it unchanged otherwise.

    Args:
        lin (Linearisation): from :func:`linearise` with a cost gradient.
        c (float): constraint value :math:`J_c - d`.
        delta (float): trust-region size.

    Keyword Args:
        use_hx (bool): use :math:`v = Hx` (:math:`\\approx g`) instead of :math:`x`, as SafePO's
            ``pcpo.py`` does **[quirk]** (its variable is named ``H_inv_g`` but holds the Fisher
            product of :math:`x`). Defaults to ``False``: the paper's :math:`v = H^{-1} g`.
    """
    if lin.p is None or lin.r is None or lin.s is None:
        raise ValueError("pcpo_direction needs a linearisation with a cost gradient (linearise(..., b=...)).")
    alpha = natural_step_size(lin.q, delta)
    v = lin.hx if use_hx else lin.x
    nu = max((alpha * lin.r + c) / (lin.s + _EPS), 0.0)
    return alpha * v - nu * lin.p


# ============================================================================ step strategies
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


@dataclass(frozen=True)
class Proposal:
    """A step direction and the line-search tests it must pass.

    Attributes:
        direction: the full step (flat).
        require_improvement: the reward surrogate must not decrease (TRPO; CPO cases 2-4).
        cost_tolerance: maximum allowed increase of the cost surrogate (CPO / PCPO:
            :math:`\\max(-c, 0)`); ``None`` for no cost test.
        metrics: extra values to log.
    """

    direction: Tensor
    require_improvement: bool = True
    cost_tolerance: float | None = None
    metrics: dict[str, float] = field(default_factory=dict)


def natural_proposal(lin: Linearisation, cost_violation: float, delta: float) -> Proposal:
    """The natural step :math:`\\sqrt{2\\delta/q}\\, x` with TRPO's tests (NPG applies it without any).

    The per-step proposal of :class:`NaturalPolicyStep` and :class:`TRPOStep` as a function of the
    linearisation, so that seed-group steps (:mod:`sg_torchrl.train.stacked_trust_region`) apply it
    seed by seed; ``cost_violation`` is unused.
    """
    return Proposal(direction=natural_step_size(lin.q, delta) * lin.x)


def cpo_proposal(lin: Linearisation, cost_violation: float, delta: float, *, safepo_dual: bool = False) -> Proposal:
    """:func:`cpo_direction` with CPO's acceptance tests: the proposal of :class:`CPOStep`.

    The cost surrogate may grow by at most :math:`\\max(-c, 0)`; the reward surrogate must not
    decrease in cases 2-4 (feasible policy). Logs the case and the optimal duals.
    """
    sol = cpo_direction(lin, cost_violation, delta, safepo_dual=safepo_dual)
    return Proposal(
        direction=sol.direction,
        require_improvement=sol.case >= 2,
        cost_tolerance=max(-cost_violation, 0.0),
        metrics={"Misc/CPOCase": float(sol.case), "Misc/Lambda_star": sol.lam, "Misc/Nu_star": sol.nu},
    )


def pcpo_proposal(lin: Linearisation, cost_violation: float, delta: float, *, use_hx: bool = False) -> Proposal:
    """:func:`pcpo_direction` with CPO's cost test and no reward test: the proposal of :class:`PCPOStep`."""
    direction = pcpo_direction(lin, cost_violation, delta, use_hx=use_hx)
    return Proposal(direction=direction, require_improvement=False, cost_tolerance=max(-cost_violation, 0.0))


class TrustRegionStep(abc.ABC):
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
        target_kl (float): trust-region size :math:`\\delta`. Defaults to ``0.01``.
        cg_iters (int): conjugate-gradient iterations. Defaults to ``15``.
        cg_damping (float): Fisher damping :math:`\\beta`. Defaults to ``0.1``.
        line_search_steps (int, optional): backtracking trials; ``0`` applies the step without a
            line search. ``None`` uses the class default.
        step_fraction (float): backtracking shrink factor. Defaults to ``0.8``.
        cg_residual_tol (float): CG residual tolerance. Defaults to ``1e-10``.
        cg_eps (float): CG denominator guard. Defaults to ``1e-6``.
        kl_action_reduction (str): ``"mean"`` (SafePO) or ``"sum"`` over action dims, see the module
            docstring.

    Returned metrics (SafePO's names): ``Misc/Alpha`` (:math:`\\sqrt{2\\delta/q}`),
    ``Misc/FinalStepNorm`` (norm of the proposed direction, 0 when rejected; SafePO's definition,
    before backtracking), ``Misc/xHx``, ``Misc/gradient_norm`` (:math:`\\|g\\|`), ``Misc/H_inv_g``
    (:math:`\\|x\\|`), ``Misc/AcceptanceStep`` (accepted trial from 1, 0 when rejected),
    ``Train/KL`` (KL after the step), ``Loss/Loss_actor`` (minus the surrogate before the step),
    plus ``Misc/cost_gradient_norm`` for the constrained steps and subclass extras.
    """

    default_line_search_steps: ClassVar[int] = 0
    uses_cost: ClassVar[bool] = False

    def __init__(
        self,
        actor: ProbabilisticTensorDictSequential,
        *,
        target_kl: float = 0.01,
        cg_iters: int = 15,
        cg_damping: float = 0.1,
        line_search_steps: int | None = None,
        step_fraction: float = 0.8,
        cg_residual_tol: float = 1e-10,
        cg_eps: float = 1e-6,
        kl_action_reduction: Literal["mean", "sum"] = "mean",
    ) -> None:
        if line_search_steps is None:
            line_search_steps = self.default_line_search_steps
        if not target_kl > 0:
            raise ValueError(f"target_kl must be > 0, got {target_kl}.")
        if cg_iters < 1 or line_search_steps < 0:
            raise ValueError(f"need cg_iters >= 1 and line_search_steps >= 0, got {cg_iters}, {line_search_steps}.")
        if cg_damping < 0 or not 0.0 < step_fraction < 1.0:
            raise ValueError(f"need cg_damping >= 0 and 0 < step_fraction < 1, got {cg_damping}, {step_fraction}.")
        self.loss = TrustRegionLoss(actor, kl_action_reduction=kl_action_reduction)
        self.params = [p for p in actor.parameters() if p.requires_grad]
        self.target_kl = float(target_kl)
        self.cg_iters = int(cg_iters)
        self.cg_damping = float(cg_damping)
        self.line_search_steps = int(line_search_steps)
        self.step_fraction = float(step_fraction)
        self.cg_residual_tol = float(cg_residual_tol)
        self.cg_eps = float(cg_eps)

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


class NaturalPolicyStep(TrustRegionStep):
    """Natural policy gradient step :math:`\\theta \\leftarrow \\theta + \\sqrt{2\\delta/x^\\top Hx}\\; x`.

    Kakade 2002, "A Natural Policy Gradient", with the step length that puts the quadratic KL model
    on the trust-region boundary; no line search (``line_search_steps=0``). Fed the Lagrangian
    advantage this is SafePO's RCPO. ``Misc/AcceptanceStep`` is 1 (the step is always taken).
    """

    def _propose(self, lin: Linearisation, cost_violation: float) -> Proposal:
        return natural_proposal(lin, cost_violation, self.target_kl)


class TRPOStep(NaturalPolicyStep):
    """TRPO (Schulman et al. 2015): the natural step, backtracked until it improves and stays in the region.

    Up to ``line_search_steps`` (15) trials of :math:`0.8^k` of the natural step; a trial is accepted
    when the surrogate did not decrease and :math:`\\mathrm{KL} \\le \\delta`; otherwise no update.
    Fed the Lagrangian advantage this is TRPO-Lag.
    """

    default_line_search_steps = 15


class CPOStep(TrustRegionStep):
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

    default_line_search_steps = 15
    uses_cost = True

    def __init__(self, actor: ProbabilisticTensorDictSequential, *, safepo_dual: bool = False, **kwargs) -> None:
        super().__init__(actor, **kwargs)
        self.safepo_dual = bool(safepo_dual)

    def _propose(self, lin: Linearisation, cost_violation: float) -> Proposal:
        return cpo_proposal(lin, cost_violation, self.target_kl, safepo_dual=self.safepo_dual)


class PCPOStep(TrustRegionStep):
    """Projection-based CPO (Yang et al. 2020): :func:`pcpo_direction`, backtracked.

    Up to ``line_search_steps`` (200) trials of :math:`0.8^k`, with CPO's acceptance tests minus the
    reward-improvement test (SafePO fixes the CPO case to 0 for PCPO).

    Keyword Args:
        use_hx_direction (bool): ``False`` (default) uses the paper's reward step
            :math:`\\sqrt{2\\delta/q}\\, H^{-1} g`; ``True`` reproduces SafePO's **[quirk]** of
            stepping along :math:`Hx \\approx g` instead.
        **kwargs: see :class:`TrustRegionStep`.
    """

    default_line_search_steps = 200
    uses_cost = True

    def __init__(self, actor: ProbabilisticTensorDictSequential, *, use_hx_direction: bool = False, **kwargs) -> None:
        super().__init__(actor, **kwargs)
        self.use_hx_direction = bool(use_hx_direction)

    def _propose(self, lin: Linearisation, cost_violation: float) -> Proposal:
        return pcpo_proposal(lin, cost_violation, self.target_kl, use_hx=self.use_hx_direction)
