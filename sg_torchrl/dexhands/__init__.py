"""Safe dexterous-hand tasks on MuJoCo (Safety-Gymnasium paper, section 4.4, "Safe Isaac Gym").

``ShadowHandOverSafeJoint-v0`` and ``ShadowHandOverSafeFinger-v0``: two Shadow Hands pass a ball
under a forefinger constraint. Model derived from gymnasium-robotics' Shadow Hand assets
(Apache-2.0, (C) Vikash Kumar, CSE, UW): see ``NOTICE`` and ``LICENSE-gymnasium-robotics-assets.md``.
"""

from sg_torchrl.dexhands.constraints import PAPER_JOINTS, SAFETY_VARIANTS, JointRangeConstraint
from sg_torchrl.dexhands.env import ShadowHandOverEnv
from sg_torchrl.dexhands.scene import build_scene

__all__ = ["PAPER_JOINTS", "SAFETY_VARIANTS", "JointRangeConstraint", "ShadowHandOverEnv", "build_scene"]
