"""Safe-RL objectives: Lagrange multipliers, cost value estimation and Lagrangian PPO losses.

* :class:`Multiplier`, :class:`LagrangeMultiplier`, :class:`PIDLagrangeMultiplier`: the
  multiplier update rules (Adam projected ascent, Ray et al. 2019; PID, Stooke et al. 2020).
* :func:`make_gae`, :func:`make_cost_gae`, :func:`normalize_advantages`: reward and cost GAE side by
  side and SafePO's batch normalisation.
* :class:`PPOLagLoss`: PPO-Lag; CPPO-PID is ``PPOLagLoss(..., multiplier=PIDLagrangeMultiplier())``.
* :func:`gaussian_kl`: closed-form KL between diagonal Gaussian policies (KL early stop).
"""
from sg_torchrl.objectives.kl import gaussian_kl
from sg_torchrl.objectives.multipliers import (
    LagrangeMultiplier,
    Multiplier,
    NoMultiplier,
    PIDLagrangeMultiplier,
)
from sg_torchrl.objectives.ppo_lag import PPOLagLoss
from sg_torchrl.objectives.value import make_cost_gae, make_gae, normalize_advantages

__all__ = [
    "LagrangeMultiplier",
    "Multiplier",
    "NoMultiplier",
    "PIDLagrangeMultiplier",
    "PPOLagLoss",
    "gaussian_kl",
    "make_cost_gae",
    "make_gae",
    "normalize_advantages",
]
