"""PPO-Lag with a pessimistic cost clip: a first-order algorithm added as one Surrogate and one loss.

PPO-Lag clips the ratio of the *combined* advantage :math:`(A_r - \\lambda A_c) / (1 + \\lambda)`, so
where the cost advantage is negative the clip can be optimistic about the cost. Here the two terms
are clipped apart: the reward term as PPO clips it (:math:`\\min`), the cost term pessimistically
(:math:`\\max`, the cost surrogate of P3O, Zhang et al. 2022, "Penalized Proximal Policy Optimization
for Safe Reinforcement Learning"):

.. math::

    L = \\frac{-\\min(r A_r,\\ \\mathrm{clip}(r) A_r) + \\lambda \\max(r A_c,\\ \\mathrm{clip}(r) A_c)}{1 + \\lambda}

This module is the whole algorithm: :class:`PessimisticCostSurrogate` is its math, written once for
any leading seed dimensions; :class:`PessimisticPPOLagLoss` is the TorchRL ``LossModule`` that returns
it (and hands it to the seed-batched engine through the inherited ``seed_batched_objective``); the
``ppo_lag_pessimistic`` row of :mod:`sg_torchrl.algorithms.manifest` makes ``sg-train --algo
ppo_lag_pessimistic`` train it. The README's "Add an algorithm" walks through it.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from sg_torchrl.objectives.ppo_lag import PPOLagLoss
from sg_torchrl.objectives.surrogates import ClipSurrogate, over_samples

__all__ = ["PessimisticCostSurrogate", "PessimisticPPOLagLoss"]


@dataclass(frozen=True)
class PessimisticCostSurrogate(ClipSurrogate):
    """PPO's clip on the reward term, a pessimistic (max) clip on the cost term, normalised by :math:`1 + \\lambda`."""

    advantage = "reward"  # receive A_r itself; A_c comes as cost_advantage

    def loss(self, log_weight, advantage, *, cost_advantage=None, kl=None, lam=None, log_is_weight=None,
             seed_dims=0):
        ratio = self.log_ratio(log_weight, log_is_weight).exp()
        clipped = log_weight.clamp(*self.bounds).exp()
        lam = over_samples(lam, log_weight)
        reward_term = torch.minimum(ratio * advantage, clipped * advantage)
        cost_term = torch.maximum(ratio * cost_advantage, clipped * cost_advantage)
        return (-reward_term + lam * cost_term) / (1 + lam)


class PessimisticPPOLagLoss(PPOLagLoss):
    """PPO-Lag whose cost term is clipped apart and pessimistically (:class:`PessimisticCostSurrogate`)."""

    @property
    def surrogate(self) -> PessimisticCostSurrogate:
        return PessimisticCostSurrogate(float(self.clip_epsilon))
