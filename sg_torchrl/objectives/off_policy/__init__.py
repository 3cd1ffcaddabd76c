"""Off-policy safe RL losses: SAC, TD3 and DDPG with a cost critic and a Lagrange or PID multiplier.

:class:`SACLagLoss`, :class:`TD3LagLoss`, :class:`DDPGLagLoss` subclass TorchRL's ``SACLoss``, ``TD3Loss``
and ``DDPGLoss``; their math is one :class:`OffPolicyObjective` (seed-batched, the engine's form).
"""

from sg_torchrl.objectives.off_policy.losses import DDPGLagLoss, SACLagLoss, TD3LagLoss
from sg_torchrl.objectives.off_policy.objective import COST_REDUCTIONS, OffPolicyObjective

__all__ = ["COST_REDUCTIONS", "DDPGLagLoss", "OffPolicyObjective", "SACLagLoss", "TD3LagLoss"]
