"""Second-order machinery shared by the trust-region policy steps (NPG, TRPO, CPO, PCPO, MACPO).

The natural policy gradient (Kakade 2002, "A Natural Policy Gradient"), TRPO (Schulman et al. 2015,
"Trust Region Policy Optimization", https://arxiv.org/abs/1502.05477), CPO (Achiam et al. 2017,
"Constrained Policy Optimization", https://arxiv.org/abs/1705.10528) and PCPO (Yang et al. 2020,
"Projection-Based Constrained Policy Optimization", https://arxiv.org/abs/2010.03152) all solve a
quadratic model of the policy update in the metric of the Fisher information matrix :math:`H`,
the Hessian of the mean KL divergence between the old and the new policy. They need the same few
tools, collected here as small functions over a *flat* parameter vector so that each one can be
tested on its own:

* :func:`flat_params`, :func:`set_flat_params`, :func:`flat_grad`: views of a list of parameters
  as one vector;
* :class:`FisherVectorProduct`: :math:`v \\mapsto (H + \\beta I) v` by double back-propagation
  through the KL (never forming :math:`H`), built once per update and reused for every vector;
* :func:`conjugate_gradient`: :math:`H^{-1} g` from Hessian-vector products only;
* :func:`linearise`: :math:`x = H^{-1} g`, :math:`p = H^{-1} b` and the scalars :math:`q, r, s` every
  step is built from;
* :func:`natural_step_size`: the step length :math:`\\sqrt{2\\delta / x^\\top H x}` that puts the
  quadratic KL model on the trust-region boundary;
* :func:`backtracking_line_search`: shrinks a step by :math:`0.8^k` until a caller-supplied
  acceptance test passes, restoring the parameters when none does.

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
    "backtracking_line_search",
    "conjugate_gradient",
    "flat_grad",
    "flat_params",
    "linearise",
    "natural_step_size",
    "set_flat_params",
]

MatrixVectorProduct = Callable[[Tensor], Tensor]


# ----------------------------------------------------------------------------- flat views
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


def flat_grad(
    output: Tensor,
    params: Sequence[Tensor],
    *,
    retain_graph: bool | None = None,
    create_graph: bool = False,
) -> Tensor:
    """Gradient of the scalar ``output`` with respect to ``params``, as one vector.

    Parameters that ``output`` does not depend on get zero gradients (rather than ``None``), so the
    vector always lines up with :func:`flat_params`. Does not touch ``.grad``.

    Args:
        output (Tensor): a scalar.
        params (sequence of Tensor): the leaves to differentiate with respect to.

    Keyword Args:
        retain_graph (bool, optional): keep the graph for further differentiation (default: the
            value of ``create_graph``).
        create_graph (bool): build the graph of the gradient itself (for Hessian-vector products).
    """
    if output.numel() != 1:
        raise ValueError(f"flat_grad needs a scalar output, got shape {tuple(output.shape)}.")
    grads = torch.autograd.grad(
        output.reshape(()),
        tuple(params),
        retain_graph=retain_graph,
        create_graph=create_graph,
        allow_unused=True,
        materialize_grads=True,
    )
    return torch.cat([g.reshape(-1) for g in grads])


# ----------------------------------------------------------------------------- Fisher product
class FisherVectorProduct:
    """The damped Fisher-vector product :math:`v \\mapsto (\\nabla^2_\\theta \\overline{\\mathrm{KL}} + \\beta I)\\, v`.

    ``kl`` must be the mean divergence :math:`\\overline{\\mathrm{KL}}(\\pi_{\\text{fixed}} \\,\\|\\,
    \\pi_\\theta)` over the batch, evaluated at the current parameters with the first argument
    detached (so its value and gradient are zero and its Hessian is the Fisher information matrix
    of the policy, Schulman et al. 2015, appendix C). The gradient of the KL is built once, with its
    own graph; each call then costs one more backward pass (Pearlmutter's double-backprop trick):
    :math:`Hv = \\nabla_\\theta (\\nabla_\\theta \\overline{\\mathrm{KL}} \\cdot v)`. Damping
    :math:`\\beta` (SafePO: 0.1) keeps the system well conditioned for conjugate gradient.

    The graph of ``kl`` is retained for as long as the object lives: build one per update.

    Args:
        kl (Tensor): scalar mean KL with a graph to ``params``.
        params (sequence of Tensor): the policy parameters (their order defines the flat layout).
        damping (float): :math:`\\beta \\ge 0`. Defaults to ``0.1``.
    """

    def __init__(self, kl: Tensor, params: Sequence[Tensor], damping: float = 0.1) -> None:
        if damping < 0:
            raise ValueError(f"damping must be >= 0, got {damping}.")
        self.params = tuple(params)
        self.damping = float(damping)
        self._kl_grad = flat_grad(kl, self.params, create_graph=True)

    def __call__(self, v: Tensor) -> Tensor:
        v = v.detach().to(self._kl_grad.dtype)
        directional = torch.dot(self._kl_grad, v)
        if directional.requires_grad:
            hv = flat_grad(directional, self.params, retain_graph=True)
        else:  # the KL is (locally) linear in the parameters: zero curvature
            hv = torch.zeros_like(v)
        return hv + self.damping * v


# ----------------------------------------------------------------------------- CG and step size
def conjugate_gradient(
    Avp: MatrixVectorProduct,
    b: Tensor,
    iters: int = 15,
    residual_tol: float = 1e-10,
    eps: float = 1e-6,
) -> Tensor:
    """Approximately solves :math:`A x = b` for symmetric positive-definite :math:`A` given only ``Avp``.

    Plain conjugate gradient from :math:`x_0 = 0` (Hestenes and Stiefel 1952), stopped after
    ``iters`` iterations or once :math:`\\|r\\| <` ``residual_tol``. As in SafePO, ``eps`` is added to
    the two denominators (:math:`p^\\top A p` and :math:`r^\\top r`) as a guard against division by
    zero; it slightly perturbs the last iterations when the residual is tiny.

    Args:
        Avp (callable): :math:`v \\mapsto A v`, e.g. a :class:`FisherVectorProduct`.
        b (Tensor): right-hand side (a vector).
        iters (int): maximum number of iterations (SafePO / the paper: 15).
        residual_tol (float): stop once the residual norm is below this. Defaults to ``1e-10``.
        eps (float): denominator guard. Defaults to ``1e-6``.

    Returns:
        The approximate solution :math:`x`, same shape and dtype as ``b``.
    """
    if iters < 1:
        raise ValueError(f"iters must be >= 1, got {iters}.")
    x = torch.zeros_like(b)
    r = b.clone()  # residual b - A x0 with x0 = 0
    p = r.clone()
    rdotr = torch.dot(r, r)
    for _ in range(iters):
        z = Avp(p)
        alpha = rdotr / (torch.dot(p, z) + eps)
        x = x + alpha * p
        r = r - alpha * z
        new_rdotr = torch.dot(r, r)
        if float(new_rdotr.sqrt()) < residual_tol:
            break
        p = r + (new_rdotr / (rdotr + eps)) * p
        rdotr = new_rdotr
    return x


def natural_step_size(xHx: Tensor | float, delta: float) -> float:
    """:math:`\\alpha = \\sqrt{2\\delta / (x^\\top H x + 10^{-8})}`.

    The step :math:`\\alpha x` with :math:`x = H^{-1} g` maximises the linear model
    :math:`g^\\top d` on the boundary of the quadratic trust region
    :math:`\\tfrac12 d^\\top H d \\le \\delta` (Schulman et al. 2015, appendix C).
    """
    return math.sqrt(2.0 * delta / (float(xHx) + 1e-8))


# ----------------------------------------------------------------------------- linearised problem


@dataclass(frozen=True)
class Linearisation:
    """The quantities every step is built from (notation of Achiam et al. 2017, section 6.1).

    Attributes:
        g: reward-surrogate gradient; x: :math:`H^{-1} g` (conjugate gradient); hx: :math:`Hx`;
        q: :math:`x^\\top H x \\approx g^\\top H^{-1} g`.
        b: cost-surrogate gradient; p: :math:`H^{-1} b`; r: :math:`g^\\top p`;
        s: :math:`b^\\top p` (``None`` when no cost gradient was given).
    """

    g: Tensor
    x: Tensor
    hx: Tensor
    q: float
    b: Tensor | None = None
    p: Tensor | None = None
    r: float | None = None
    s: float | None = None


def linearise(
    hvp: MatrixVectorProduct | Tensor,
    g: Tensor,
    b: Tensor | None = None,
    *,
    cg_iters: int = 15,
    residual_tol: float = 1e-10,
    eps: float = 1e-6,
) -> Linearisation:
    """Solves :math:`Hx = g` (and :math:`Hp = b`) by conjugate gradient and forms :math:`q, r, s`.

    Args:
        hvp (callable or Tensor): :math:`v \\mapsto Hv` (e.g. a
            :class:`FisherVectorProduct`) or the matrix itself.
        g (Tensor): reward gradient (flat).
        b (Tensor, optional): cost gradient (flat).

    Keyword Args:
        cg_iters, residual_tol, eps: see :func:`conjugate_gradient`.
    """
    apply = (lambda v: hvp @ v) if isinstance(hvp, Tensor) else hvp
    solve = lambda rhs: conjugate_gradient(apply, rhs, cg_iters, residual_tol, eps)  # noqa: E731
    x = solve(g)
    hx = apply(x)
    lin = Linearisation(g=g, x=x, hx=hx, q=float(torch.dot(x, hx)))
    if b is None:
        return lin
    p = solve(b)
    r, s = float(torch.dot(g, p)), float(torch.dot(b, p))
    return Linearisation(g=g, x=x, hx=hx, q=lin.q, b=b, p=p, r=r, s=s)


# ----------------------------------------------------------------------------- line search
@dataclass(frozen=True)
class LineSearchResult:
    """Outcome of :func:`backtracking_line_search`.

    Attributes:
        step_index (int): the accepted trial counted from 1 (trial ``k`` applies the fraction
            ``step_fraction ** (k - 1)``), or 0 when no trial was accepted; SafePO logs it as
            ``Misc/AcceptanceStep``.
        step_fraction (float): the fraction of the direction that was applied (0 when none).
    """

    step_index: int
    step_fraction: float

    @property
    def accepted(self) -> bool:
        return self.step_index > 0


@torch.no_grad()
def backtracking_line_search(
    params: Sequence[Tensor],
    theta_old: Tensor,
    direction: Tensor,
    accept: Callable[[], bool],
    *,
    max_trials: int = 15,
    step_fraction: float = 0.8,
) -> LineSearchResult:
    """Tries :math:`\\theta_{\\text{old}} + f^k d` for :math:`k = 0, 1, \\dots` until ``accept()`` holds.

    Each trial writes the candidate into ``params`` and calls ``accept()``, which evaluates the
    policy as it now is (surrogate improvement, KL, cost, ... are the caller's business). The first
    accepted candidate stays in ``params``; if none of the ``max_trials`` candidates is accepted,
    ``params`` are restored to ``theta_old`` (no update), as in TRPO / CPO.

    Args:
        params (sequence of Tensor): the parameters to move (in place).
        theta_old (Tensor): their flat value before the step.
        direction (Tensor): the full step :math:`d` (flat).
        accept (callable): returns ``True`` to accept the parameters currently written.

    Keyword Args:
        max_trials (int): number of candidates (SafePO: 15; PCPO 200).
        step_fraction (float): shrink factor :math:`f \\in (0, 1)` (SafePO: 0.8).

    Returns:
        A :class:`LineSearchResult`.
    """
    if max_trials < 1:
        raise ValueError(f"max_trials must be >= 1, got {max_trials}.")
    if not 0.0 < step_fraction < 1.0:
        raise ValueError(f"step_fraction must be in (0, 1), got {step_fraction}.")
    fraction = 1.0
    for trial in range(1, max_trials + 1):
        set_flat_params(params, theta_old + fraction * direction)
        if accept():
            return LineSearchResult(step_index=trial, step_fraction=fraction)
        fraction *= step_fraction
    set_flat_params(params, theta_old)
    return LineSearchResult(step_index=0, step_fraction=0.0)
