"""Second-order machinery of the trust-region policy steps (NPG, TRPO, CPO, PCPO, MACPO), for S seeds at once.

The natural policy gradient (Kakade 2002, "A Natural Policy Gradient"), TRPO (Schulman et al. 2015,
"Trust Region Policy Optimization", https://arxiv.org/abs/1502.05477), CPO (Achiam et al. 2017,
"Constrained Policy Optimization", https://arxiv.org/abs/1705.10528) and PCPO (Yang et al. 2020,
"Projection-Based Constrained Policy Optimization", https://arxiv.org/abs/2010.03152) all solve a
quadratic model of the policy update in the metric of the Fisher information matrix :math:`H`,
the Hessian of the mean KL divergence between the old and the new policy.

Every tool here is written once, for a leading *seed* dimension: S independent problems, one per
row of an ``(S, P)`` tensor (a seed group's stacked actors, :mod:`sg_torchrl.objectives.stacked_trust_region`).
One seed (one TorchRL actor) is the case S = 1, and the single-problem names that users and tests
import are thin views of the batched ones on ``[None]`` rows:

* :func:`seed_flat_grad` (view: :func:`flat_grad`), with :func:`flat_params` /
  :func:`set_flat_params` for a list of parameters as one vector;
* :class:`SeedFisherVectorProduct` (view: :class:`FisherVectorProduct`): :math:`v_s \\mapsto (H_s +
  \\beta I) v_s` for every seed in one double-backward (never forming :math:`H`);
* :func:`seed_conjugate_gradient` (view: :func:`conjugate_gradient`): :math:`H_s^{-1} g_s` from
  Fisher-vector products only;
* :func:`seed_linearise` (view: :func:`linearise`): :math:`x = H^{-1} g`, :math:`p = H^{-1} b` and the
  scalars :math:`q, r, s` every step is built from;
* :func:`seed_line_search` (view: :func:`backtracking_line_search`): each seed tries :math:`0.8^k`
  of its direction until its acceptance test passes;
* :func:`natural_step_size`: :math:`\\sqrt{2\\delta / x^\\top H x}`, the natural step's length.

Defaults are SafePO's (Ji et al. 2023, "Safety-Gymnasium: A Unified Safe Reinforcement Learning
Benchmark"): damping 0.1, 15 conjugate-gradient iterations with residual tolerance 1e-10 and
``eps=1e-6`` in the denominators, step fraction 0.8.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "FisherVectorProduct",
    "LineSearchResult",
    "Linearisation",
    "SeedFisherVectorProduct",
    "SeedLineSearch",
    "backtracking_line_search",
    "conjugate_gradient",
    "flat_grad",
    "flat_params",
    "linearise",
    "natural_step_size",
    "seed_conjugate_gradient",
    "seed_flat_grad",
    "seed_line_search",
    "seed_linearise",
    "set_flat_params",
]

MatrixVectorProduct = Callable[[Tensor], Tensor]


def _rows(apply: MatrixVectorProduct) -> MatrixVectorProduct:
    """A one-problem product ``v -> A v`` as the batched tools call it, on ``(1, P)`` rows."""
    return lambda v: apply(v[0]).unsqueeze(0)


def _rowdot(a: Tensor, b: Tensor) -> Tensor:
    """Row-wise dot products of ``(S, P)`` tensors, ``(S,)``."""
    return (a * b).sum(1)


# ============================================================================ flat views
def flat_params(params: Sequence[Tensor]) -> Tensor:
    """The parameters as one detached vector (a copy), in the order of ``params``."""
    if len(params) == 0:
        raise ValueError("flat_params needs at least one parameter.")
    return torch.cat([p.detach().reshape(-1) for p in params])


@torch.no_grad()
def set_flat_params(params: Sequence[Tensor], flat: Tensor) -> None:
    """Writes the vector ``flat`` into ``params`` in place (inverse of :func:`flat_params`).

    Raises:
        ValueError: if ``flat`` is not a vector with exactly as many elements as ``params``.
    """
    total = sum(p.numel() for p in params)
    if flat.dim() != 1 or flat.numel() != total:
        raise ValueError(
            f"set_flat_params: expected a vector of {total} elements, got shape {tuple(flat.shape)}."
        )
    offset = 0
    for p in params:
        n = p.numel()
        p.copy_(flat[offset : offset + n].view_as(p))
        offset += n


def seed_flat_grad(output: Tensor, params: Sequence[Tensor], num_seeds: int, *, retain_graph: bool | None = None,
                   create_graph: bool = False) -> Tensor:
    """Gradient of the scalar ``output`` w.r.t. seed-stacked ``params``, as ``(S, P)`` rows.

    ``params`` are the stacked parameters in flat-buffer order (each of shape ``(S, ...)``, e.g.
    :meth:`~sg_torchrl.modules.stacked.StackedActorCritic.actor_parameters`), so row ``s`` lines up
    with row ``s`` of the flat buffer. With ``output`` a sum over seeds of per-seed terms, row ``s``
    is the gradient of seed ``s``'s term (seeds share no parameter). Unused parameters get zeros;
    ``.grad`` is not touched. With ``num_seeds=1`` any parameters qualify (one row of all of them).
    """
    if output.numel() != 1:
        raise ValueError(f"the gradient needs a scalar output, got shape {tuple(output.shape)}.")
    if output.dim():
        output = output.reshape(())
    grads = torch.autograd.grad(output, tuple(params), retain_graph=retain_graph,
                                create_graph=create_graph, allow_unused=True, materialize_grads=True)
    return torch.cat([grad.reshape(num_seeds, -1) for grad in grads], dim=1)


def flat_grad(output: Tensor, params: Sequence[Tensor], *, retain_graph: bool | None = None,
              create_graph: bool = False) -> Tensor:
    """Gradient of the scalar ``output`` w.r.t. ``params`` as one vector: :func:`seed_flat_grad`'s one row.

    Parameters that ``output`` does not depend on get zeros (rather than ``None``), so the vector
    always lines up with :func:`flat_params`. Does not touch ``.grad``.
    """
    return seed_flat_grad(output, params, 1, retain_graph=retain_graph, create_graph=create_graph)[0]


# ============================================================================ Fisher products
class SeedFisherVectorProduct:
    """Every seed's damped Fisher-vector product :math:`v_s \\mapsto (H_s + \\beta I) v_s` in one double-backward.

    ``kl`` is the ``(S,)`` per-seed mean divergence :math:`\\overline{\\mathrm{KL}}(\\pi_{\\text{fixed}}
    \\,\\|\\, \\pi_\\theta)`, evaluated at the current parameters with the first argument detached (so
    its value and gradient are zero and its Hessian is the Fisher information matrix, Schulman et
    al. 2015, appendix C). The Hessian of ``kl.sum()`` is block diagonal (seed ``s``'s KL depends on
    row ``s`` only), so with :math:`G = \\nabla \\sum_s \\mathrm{KL}_s` built once with its graph, the
    gradient of :math:`\\sum_s G_s \\cdot v_s` has :math:`H_s v_s` in row ``s`` (Pearlmutter's
    double-backprop trick). Damping :math:`\\beta` (SafePO: 0.1) keeps conjugate gradient well
    conditioned. The graph of ``kl`` lives as long as the object: build one per step.

    Args:
        kl: ``(S,)`` per-seed KLs with a graph to ``params``.
        params: the stacked actor parameters in flat-buffer order.
        damping: :math:`\\beta \\ge 0`, the same for every seed.
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


class FisherVectorProduct:
    """One policy's damped Fisher-vector product :math:`v \\mapsto (H + \\beta I)\\, v`.

    :class:`SeedFisherVectorProduct` for S = 1 (``kl`` a scalar, ``v`` a vector).

    Args:
        kl (Tensor): scalar mean KL with a graph to ``params`` (first argument detached).
        params (sequence of Tensor): the policy parameters (their order defines the flat layout).
        damping (float): :math:`\\beta \\ge 0`. Defaults to ``0.1``.
    """

    def __init__(self, kl: Tensor, params: Sequence[Tensor], damping: float = 0.1) -> None:
        self._seeds = SeedFisherVectorProduct(kl.reshape(1), params, damping)
        self.params, self.damping = self._seeds.params, self._seeds.damping

    def __call__(self, v: Tensor) -> Tensor:
        return self._seeds(v.unsqueeze(0))[0]


# ============================================================================ conjugate gradient
def seed_conjugate_gradient(Avp: MatrixVectorProduct, b: Tensor, iters: int = 15, residual_tol: float = 1e-10,
                            eps: float = 1e-6) -> Tensor:
    """Solves :math:`A_s x_s = b_s` for every row ``s`` of ``b`` ``(S, P)`` by conjugate gradient.

    Plain conjugate gradient from :math:`x_0 = 0` (Hestenes and Stiefel 1952), per-seed
    :math:`\\alpha` and :math:`\\beta`, at most ``iters`` iterations. As in SafePO, ``eps`` is added to
    both denominators (:math:`p^\\top A p` and :math:`r^\\top r`) against division by zero. A seed
    whose residual norm falls below ``residual_tol`` (after updating its :math:`x`) is frozen while the
    other rows go on; the loop ends when none is left. ``Avp`` maps ``(S, P)`` to ``(S, P)`` row by
    row (a :class:`SeedFisherVectorProduct`), so each seed's :math:`A_s` is symmetric positive definite.
    """
    if iters < 1:
        raise ValueError(f"iters must be >= 1, got {iters}.")
    x = torch.zeros_like(b)
    r = b.clone()  # residual b - A x0 with x0 = 0
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
        # the residual test, float(sqrt) < tol, in double precision
        running = running & ~(new_rdotr.sqrt().double() < residual_tol)
        if not bool(running.any()):
            break
        p = torch.where(running.unsqueeze(1), r + (new_rdotr / (rdotr + eps)).unsqueeze(1) * p, p)
        rdotr = torch.where(running, new_rdotr, rdotr)
    return x


def conjugate_gradient(Avp: MatrixVectorProduct, b: Tensor, iters: int = 15, residual_tol: float = 1e-10,
                       eps: float = 1e-6) -> Tensor:
    """Approximately solves :math:`A x = b` (one vector ``b``) with :func:`seed_conjugate_gradient` on one row.

    Args:
        Avp (callable): :math:`v \\mapsto A v` on vectors, e.g. a :class:`FisherVectorProduct`.
        b (Tensor): right-hand side (a vector).
        iters, residual_tol, eps: see :func:`seed_conjugate_gradient` (SafePO: 15, 1e-10, 1e-6).

    Returns:
        The approximate solution :math:`x`, same shape and dtype as ``b``.
    """
    return seed_conjugate_gradient(_rows(Avp), b.unsqueeze(0), iters, residual_tol, eps)[0]


def natural_step_size(xHx: Tensor | float, delta: float) -> float:
    """:math:`\\alpha = \\sqrt{2\\delta / (x^\\top H x + 10^{-8})}`.

    The step :math:`\\alpha x` with :math:`x = H^{-1} g` maximises the linear model
    :math:`g^\\top d` on the boundary of the quadratic trust region
    :math:`\\tfrac12 d^\\top H d \\le \\delta` (Schulman et al. 2015, appendix C).
    """
    return math.sqrt(2.0 * delta / (float(xHx) + 1e-8))


# ============================================================================ linearised problem
@dataclass(frozen=True)
class Linearisation:
    """The quantities every step is built from (notation of Achiam et al. 2017, section 6.1).

    One seed's (what the step rules of :mod:`sg_torchrl.objectives.step_rules` read, from :func:`linearise`)
    holds vectors and Python floats; S seeds' (from :func:`seed_linearise`) ``(S, P)`` rows and ``(S,)``
    tensors, and :meth:`seeds` gives each seed's.

    Attributes:
        g: reward-surrogate gradient; x: :math:`H^{-1} g` (conjugate gradient); hx: :math:`Hx`;
        q: :math:`x^\\top H x \\approx g^\\top H^{-1} g`.
        b: cost-surrogate gradient; p: :math:`H^{-1} b`; r: :math:`g^\\top p`;
        s: :math:`b^\\top p` (``None`` when no cost gradient was given).
    """

    g: Tensor
    x: Tensor
    hx: Tensor
    q: Tensor | float
    b: Tensor | None = None
    p: Tensor | None = None
    r: Tensor | float | None = None
    s: Tensor | float | None = None

    def seeds(self) -> list[Linearisation]:
        """Each seed's linearisation of S seeds' (its rows; scalars as Python floats).

        The scalars cross to the host in one transfer per kind (``q``, ``r``, ``s``), whatever S is.
        """
        q = self.q.tolist()
        if self.b is None:
            return [Linearisation(g=self.g[i], x=self.x[i], hx=self.hx[i], q=q[i]) for i in range(len(q))]
        r, s = self.r.tolist(), self.s.tolist()
        return [Linearisation(g=self.g[i], x=self.x[i], hx=self.hx[i], q=q[i], b=self.b[i], p=self.p[i], r=r[i],
                              s=s[i]) for i in range(len(q))]


def seed_linearise(hvp: MatrixVectorProduct, g: Tensor, b: Tensor | None = None, *, cg_iters: int = 15,
                   residual_tol: float = 1e-10, eps: float = 1e-6) -> Linearisation:
    """Every seed's linearised problem: :math:`x = H^{-1} g`, :math:`p = H^{-1} b` and :math:`q, r, s`.

    The solves are :func:`seed_conjugate_gradient`'s; then :math:`q = x^\\top Hx`, :math:`r = g^\\top
    p`, :math:`s = b^\\top p` per seed. ``hvp`` maps ``(S, P)`` rows to ``(S, P)``.
    """
    x = seed_conjugate_gradient(hvp, g, cg_iters, residual_tol, eps)
    hx = hvp(x)
    q = _rowdot(x, hx)
    if b is None:
        return Linearisation(g=g, x=x, hx=hx, q=q)
    p = seed_conjugate_gradient(hvp, b, cg_iters, residual_tol, eps)
    return Linearisation(g=g, x=x, hx=hx, q=q, b=b, p=p, r=_rowdot(g, p), s=_rowdot(b, p))


def linearise(hvp: MatrixVectorProduct | Tensor, g: Tensor, b: Tensor | None = None, *, cg_iters: int = 15,
              residual_tol: float = 1e-10, eps: float = 1e-6) -> Linearisation:
    """One problem's :class:`Linearisation`: :func:`seed_linearise` on one row.

    Args:
        hvp (callable or Tensor): :math:`v \\mapsto Hv` on vectors (e.g. a
            :class:`FisherVectorProduct`) or the matrix itself.
        g (Tensor): reward gradient (flat).
        b (Tensor, optional): cost gradient (flat).

    Keyword Args:
        cg_iters, residual_tol, eps: see :func:`seed_conjugate_gradient`.
    """
    apply = (lambda v: hvp @ v) if isinstance(hvp, Tensor) else hvp
    lin = seed_linearise(_rows(apply), g.unsqueeze(0), None if b is None else b.unsqueeze(0), cg_iters=cg_iters,
                         residual_tol=residual_tol, eps=eps)
    return lin.seeds()[0]


# ============================================================================ line search
@dataclass(frozen=True)
class SeedLineSearch:
    """Outcome of :func:`seed_line_search`, per seed.

    Attributes:
        theta: ``(S, P)`` the accepted candidates (a seed that accepted none: its old row).
        step_index: ``(S,)`` float64, the accepted trial counted from 1 (trial ``k`` applies
            ``step_fraction ** (k - 1)``), 0 when none was accepted (SafePO's ``Misc/AcceptanceStep``).
        step_fraction: ``(S,)`` float64, the fraction of the direction applied (0 when none).
    """

    theta: Tensor
    step_index: Tensor
    step_fraction: Tensor


@torch.no_grad()
def seed_line_search(theta_old: Tensor, direction: Tensor, accept: Callable[[Tensor, Tensor], Tensor], *,
                     max_trials: int = 15, step_fraction: float = 0.8) -> SeedLineSearch:
    """Backtracking for S seeds together: trial ``k`` tries :math:`\\theta_{\\text{old}} + f^{k-1} d_s`.

    Each trial calls ``accept(searching, candidates)`` with the indices ``(n,)`` of the seeds still
    searching and their candidates ``(n, P)``; it evaluates them (surrogates, KL, ... are the
    caller's business) and returns which passed, ``(n,)`` bool. A seed keeps its first accepted
    candidate and is not offered later trials; one that passes none of ``max_trials`` keeps its old
    row (no update), as in TRPO / CPO. The trials stop once every seed has accepted.

    Args:
        theta_old, direction: ``(S, P)`` rows before the step and full steps :math:`d_s`.
        accept: the acceptance test described above.

    Keyword Args:
        max_trials (int): candidates per seed (SafePO: 15; PCPO 200).
        step_fraction (float): shrink factor :math:`f \\in (0, 1)` (SafePO: 0.8).
    """
    if max_trials < 1:
        raise ValueError(f"max_trials must be >= 1, got {max_trials}.")
    if not 0.0 < step_fraction < 1.0:
        raise ValueError(f"step_fraction must be in (0, 1), got {step_fraction}.")
    final = theta_old.clone()
    step_index = torch.zeros(theta_old.shape[0], dtype=torch.float64, device=theta_old.device)
    fractions = torch.zeros_like(step_index)
    searching = torch.arange(theta_old.shape[0], device=theta_old.device)
    fraction = 1.0
    for trial in range(1, max_trials + 1):
        candidates = theta_old[searching] + fraction * direction[searching]
        ok = accept(searching, candidates)
        if bool(ok.any()):
            accepted = searching[ok]
            final[accepted] = candidates[ok]
            step_index[accepted] = float(trial)
            fractions[accepted] = fraction
            searching = searching[~ok]
            if searching.numel() == 0:
                break
        fraction *= step_fraction
    return SeedLineSearch(theta=final, step_index=step_index, step_fraction=fractions)


@dataclass(frozen=True)
class LineSearchResult:
    """Outcome of :func:`backtracking_line_search` (one seed of :class:`SeedLineSearch`).

    Attributes:
        step_index (int): the accepted trial counted from 1, or 0 when no trial was accepted.
        step_fraction (float): the fraction of the direction that was applied (0 when none).
    """

    step_index: int
    step_fraction: float

    @property
    def accepted(self) -> bool:
        return self.step_index > 0


@torch.no_grad()
def backtracking_line_search(params: Sequence[Tensor], theta_old: Tensor, direction: Tensor,
                             accept: Callable[[], bool], *, max_trials: int = 15,
                             step_fraction: float = 0.8) -> LineSearchResult:
    """:func:`seed_line_search` for one list of parameters, moved in place.

    Each trial writes the candidate into ``params`` and calls ``accept()``, which evaluates the
    policy as it now is. The first accepted candidate stays in ``params``; if none of the
    ``max_trials`` candidates is accepted, ``params`` are restored to ``theta_old`` (no update).

    Args:
        params (sequence of Tensor): the parameters to move (in place).
        theta_old (Tensor): their flat value before the step.
        direction (Tensor): the full step :math:`d` (flat).
        accept (callable): returns ``True`` to accept the parameters currently written.

    Keyword Args:
        max_trials (int), step_fraction (float): see :func:`seed_line_search`.
    """
    def accept_row(searching: Tensor, candidates: Tensor) -> Tensor:
        set_flat_params(params, candidates[0])
        return torch.tensor([bool(accept())], device=candidates.device)

    result = seed_line_search(theta_old.unsqueeze(0), direction.unsqueeze(0), accept_row, max_trials=max_trials,
                              step_fraction=step_fraction)
    set_flat_params(params, result.theta[0])
    return LineSearchResult(step_index=int(result.step_index[0]), step_fraction=float(result.step_fraction[0]))
