"""Closed-form KL divergence between diagonal Gaussian policies.

SafePO's first-order loop (PPO, PPO-Lag, CPPO-PID, FOCOPS, CUP) stops the epoch's passes early
once :math:`\\mathrm{KL}(\\pi_{\\text{old}} \\,\\|\\, \\pi_\\theta)` on the whole batch exceeds
``target_kl`` (0.02 in the Safety-Gymnasium paper); the second-order methods use the same
divergence as their trust region. Policies are diagonal Gaussians, so the KL has a closed form.
"""
from __future__ import annotations

from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import distributions as D, Tensor

__all__ = ["diagonal_gaussian_params", "gaussian_kl", "kl_to_stored_gaussian"]


def gaussian_kl(loc_old: Tensor, scale_old: Tensor, loc_new: Tensor, scale_new: Tensor) -> Tensor:
    """:math:`\\mathrm{KL}(\\mathcal N(\\mu_o, \\sigma_o) \\,\\|\\, \\mathcal N(\\mu_n, \\sigma_n))` summed over the action dim.

    Per action dimension,

    .. math::

        \\log\\frac{\\sigma_n}{\\sigma_o} + \\frac{\\sigma_o^2 + (\\mu_o - \\mu_n)^2}{2\\sigma_n^2} - \\frac12 ,

    summed over the last (action) dimension, which is the KL of the two independent
    (diagonal) Gaussians. Average the result over samples for SafePO's early-stop statistic.

    Args:
        loc_old (Tensor): mean of the old policy, shape ``[*B, A]``.
        scale_old (Tensor): standard deviation of the old policy (> 0), broadcastable to ``loc_old``.
        loc_new (Tensor): mean of the new policy.
        scale_new (Tensor): standard deviation of the new policy (> 0).

    Returns:
        The per-sample KL, shape ``[*B]``; differentiable in all arguments.
    """
    var_ratio = (scale_old / scale_new).pow(2)
    mean_term = ((loc_old - loc_new) / scale_new).pow(2)
    return 0.5 * (var_ratio + mean_term - 1.0 - var_ratio.log()).sum(-1)


def diagonal_gaussian_params(dist: D.Distribution, needed_by: str) -> tuple[Tensor, Tensor]:
    """``(loc, scale)`` of a diagonal Gaussian: a ``Normal``, or an ``Independent`` ``Normal`` over one (action)
    dimension such as ``IndependentNormal``.

    Raises:
        TypeError: for any other distribution, naming ``needed_by`` (what needs the Gaussian).
    """
    base = dist.base_dist if isinstance(dist, D.Independent) else dist
    if not isinstance(base, D.Normal) or (isinstance(dist, D.Independent) and dist.reinterpreted_batch_ndims != 1):
        raise TypeError(f"{needed_by} needs a diagonal-Gaussian policy (Normal / IndependentNormal over the action "
                        f"dimension); the actor's distribution is {type(dist).__name__}.")
    return base.loc, base.scale


def kl_to_stored_gaussian(
    dist: D.Distribution, tensordict: TensorDictBase, loc_key: NestedKey, scale_key: NestedKey
) -> Tensor:
    """Per-sample :math:`\\mathrm{KL}(\\pi_\\theta \\,\\|\\, \\mathcal N(\\mu, \\sigma))`, shape ``[*B, 1]``.

    ``dist`` is the current (diagonal Gaussian) policy; :math:`\\mu, \\sigma` are read from
    ``tensordict`` under ``loc_key`` / ``scale_key``. The KL is summed over the action dimension and
    is differentiable in the current policy only.

    Raises:
        TypeError: if ``dist`` is not a diagonal Gaussian (:func:`diagonal_gaussian_params`).
        KeyError: if a stored parameter is missing.
    """
    loc_now, scale_now = diagonal_gaussian_params(dist, "The closed-form KL to a stored policy")
    stored = []
    for key in (loc_key, scale_key):
        value = tensordict.get(key, None)
        if value is None:
            raise KeyError(
                f"{key!r} (a stored policy parameter) is missing from the input; write it into the "
                f"batch first, or remap the key with loss.set_keys(...)."
            )
        stored.append(value)
    loc, scale = stored
    return gaussian_kl(loc_now, scale_now, loc, scale).unsqueeze(-1)
