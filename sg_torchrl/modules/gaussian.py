"""The diagonal Gaussian policy's log-density and entropy, written once for the networks and the objectives.

The seed-stacked actor (:class:`~sg_torchrl.modules.stacked.StackedActorCritic`) samples and scores
actions with it, and the seed-batched surrogates and trust-region steps
(:mod:`sg_torchrl.objectives.surrogates`, :mod:`sg_torchrl.objectives.stacked_trust_region`) score
them with it, so a stacked network and its losses agree to the last bit.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["gaussian_entropy", "gaussian_log_prob"]

_LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))
_HALF_LOG_2PI_E = 0.5 * math.log(2.0 * math.pi * math.e)


def gaussian_log_prob(action: Tensor, loc: Tensor, scale: Tensor) -> Tensor:
    """Log-density of a diagonal Gaussian, summed over the last (action) dimension.

    The same expression as ``torch.distributions.Normal.log_prob`` summed by ``Independent`` (the
    actor's ``IndependentNormal``), so values agree with the LossModule's to the last bit where the
    inputs do; ``scale`` may broadcast (e.g. ``(S, 1, A)`` against ``(S, B, A)``).
    """
    var = scale**2
    return (-((action - loc) ** 2) / (2 * var) - scale.log() - _LOG_SQRT_2PI).sum(-1)


def gaussian_entropy(scale: Tensor, mask: Tensor) -> Tensor:
    """Entropy of a diagonal Gaussian over the action slots where ``mask`` is true, summed over the last dimension.

    ``mask`` broadcasts against ``scale`` (padded action slots of a smaller agent count nothing).
    """
    return torch.where(mask, _HALF_LOG_2PI_E + scale.log(), 0.0).sum(-1)
