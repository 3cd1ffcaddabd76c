"""The second-order methods' step rules as pure functions of a linearisation, and their step settings.

Split out of :mod:`sg_torchrl.objectives.trust_region` so that one definition serves the single-seed
steps (:class:`~sg_torchrl.objectives.TRPOStep`, :class:`~sg_torchrl.objectives.CPOStep`, ...) and the
seed group's stacked steps (:mod:`sg_torchrl.objectives.stacked_trust_region`):

* :func:`cpo_direction` / :func:`pcpo_direction`: the CPO QP's solution and PCPO's projected step
  (functions of :math:`g, b, H, c, \\delta`, unit-tested against an independent QP solver);
* :class:`NaturalRule`, :class:`TRPORule`, :class:`CPORule`, :class:`PCPORule`: small mixins holding a
  method's :class:`Proposal` (a step direction with the line-search tests it must pass), options (``safepo_dual``, ``use_hx_direction``), default line-search length and
  whether it needs the cost gradient; a step class is a rule plus a step engine.

See :mod:`sg_torchrl.objectives.trust_region` for the conventions (KL averaged over action dims) and
where we follow the papers rather than SafePO (**[quirk]** marks).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar, Literal, NamedTuple

import torch
from torch import Tensor

from sg_torchrl.objectives.second_order import Linearisation, natural_step_size

__all__ = [
    "TrustRegionOptions", "CPODirection", "CPORule", "NaturalRule", "PCPORule", "Proposal", "TRPORule",
    "cpo_direction", "pcpo_direction",
]

_EPS = 1e-8  # SafePO's guard in the CPO / PCPO divisions by s and lambda


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


class TrustRegionOptions:
    """The settings of a trust-region step engine, checked and stored once for the single-seed
    :class:`~sg_torchrl.objectives.TrustRegionStep` and the seed group's stacked step.

    Keyword Args:
        target_kl (float): trust-region radius :math:`\\delta`. Defaults to ``0.01``.
        cg_iters (int): conjugate-gradient iterations. Defaults to ``15``.
        cg_damping (float): damping added to the Fisher-vector product. Defaults to ``0.1``.
        line_search_steps (int, optional): backtracking trials; ``0`` applies the step without a line
            search; ``None`` uses the method's default (:attr:`default_line_search_steps`).
        step_fraction (float): backtracking shrink factor. Defaults to ``0.8``.
        cg_residual_tol (float): CG residual tolerance. Defaults to ``1e-10``.
        cg_eps (float): CG denominator guard. Defaults to ``1e-6``.
        kl_action_reduction (str): ``"mean"`` (SafePO) or ``"sum"`` over action dims.
    """

    default_line_search_steps: ClassVar[int] = 0
    uses_cost: ClassVar[bool] = False

    def __init__(self, *, target_kl: float = 0.01, cg_iters: int = 15, cg_damping: float = 0.1,
                 line_search_steps: int | None = None, step_fraction: float = 0.8, cg_residual_tol: float = 1e-10,
                 cg_eps: float = 1e-6, kl_action_reduction: Literal["mean", "sum"] = "mean") -> None:
        if line_search_steps is None:
            line_search_steps = self.default_line_search_steps
        if not target_kl > 0:
            raise ValueError(f"target_kl must be > 0, got {target_kl}.")
        if cg_iters < 1 or line_search_steps < 0:
            raise ValueError(f"need cg_iters >= 1 and line_search_steps >= 0, got {cg_iters}, {line_search_steps}.")
        if cg_damping < 0 or not 0.0 < step_fraction < 1.0:
            raise ValueError(f"need cg_damping >= 0 and 0 < step_fraction < 1, got {cg_damping}, {step_fraction}.")
        if kl_action_reduction not in ("mean", "sum"):
            raise ValueError(f"kl_action_reduction must be 'mean' or 'sum', got {kl_action_reduction!r}.")
        self.target_kl = float(target_kl)
        self.cg_iters = int(cg_iters)
        self.cg_damping = float(cg_damping)
        self.line_search_steps = int(line_search_steps)
        self.step_fraction = float(step_fraction)
        self.cg_residual_tol = float(cg_residual_tol)
        self.cg_eps = float(cg_eps)
        self.kl_action_reduction = kl_action_reduction


class NaturalRule:
    """What NPG / RCPO add to a trust-region step (mixed into :class:`NaturalPolicyStep` and the seed
    group's stacked step, so the two share one definition): the natural step :math:`\\sqrt{2\\delta/q}\\, x`
    with TRPO's tests (NPG, without a line search, applies it untested); ``cost_violation`` is unused."""

    def _propose(self, lin: Linearisation, cost_violation: float) -> Proposal:
        return Proposal(direction=natural_step_size(lin.q, self.target_kl) * lin.x)


class TRPORule(NaturalRule):
    """TRPO / TRPO-Lag: the natural proposal backtracked over 15 trials by default."""

    default_line_search_steps = 15


class CPORule:
    """CPO's settings and proposal (:func:`cpo_direction`; ``safepo_dual``): the cost gradient is needed,
    15 backtracking trials by default. Shared by :class:`CPOStep` and the seed group's stacked step.

    The cost surrogate may grow by at most :math:`\\max(-c, 0)`; the reward surrogate must not
    decrease in cases 2-4 (feasible policy). Logs the case and the optimal duals.
    """

    default_line_search_steps = 15
    uses_cost = True

    def __init__(self, *args, safepo_dual: bool = False, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.safepo_dual = bool(safepo_dual)

    def _propose(self, lin: Linearisation, cost_violation: float) -> Proposal:
        sol = cpo_direction(lin, cost_violation, self.target_kl, safepo_dual=self.safepo_dual)
        return Proposal(
            direction=sol.direction,
            require_improvement=sol.case >= 2,
            cost_tolerance=max(-cost_violation, 0.0),
            metrics={"Misc/CPOCase": float(sol.case), "Misc/Lambda_star": sol.lam, "Misc/Nu_star": sol.nu},
        )


class PCPORule:
    """PCPO's settings and proposal (:func:`pcpo_direction`; ``use_hx_direction``) with CPO's cost test and
    no reward test: the cost gradient is needed, 200 backtracking trials by default. Shared by
    :class:`PCPOStep` and the stacked step."""

    default_line_search_steps = 200
    uses_cost = True

    def __init__(self, *args, use_hx_direction: bool = False, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.use_hx_direction = bool(use_hx_direction)

    def _propose(self, lin: Linearisation, cost_violation: float) -> Proposal:
        direction = pcpo_direction(lin, cost_violation, self.target_kl, use_hx=self.use_hx_direction)
        return Proposal(direction=direction, require_improvement=False, cost_tolerance=max(-cost_violation, 0.0))
