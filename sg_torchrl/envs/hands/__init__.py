"""Safe dexterous-hand tasks on MuJoCo (Safety-Gymnasium paper, section 4.4, "Safe Isaac Gym").

``ShadowHandOver{SafeJoint,SafeFinger}-v0`` and ``ShadowHandCatchOver2Underarm{SafeJoint,SafeFinger}-v0``:
two Shadow Hands pass a ball under a forefinger constraint; ``MultiAgent`` + each id: one agent per hand. Model derived from gymnasium-robotics' Shadow Hand assets
(Apache-2.0, (C) Vikash Kumar, CSE, UW): see ``NOTICE`` and ``LICENSE-gymnasium-robotics-assets.md``.
"""

from sg_torchrl.envs.hands.constraints import PAPER_JOINTS, SAFETY_VARIANTS, JointRangeConstraint
from sg_torchrl.envs.hands.env import ShadowHandEnv
from sg_torchrl.envs.hands.multi_agent import MultiAgentShadowHandEnv
from sg_torchrl.envs.hands.scene import build_scene
from sg_torchrl.envs.hands.tasks import TASKS, HandTask

__all__ = ["PAPER_JOINTS", "SAFETY_VARIANTS", "JointRangeConstraint", "MultiAgentShadowHandEnv", "ShadowHandEnv", "TASKS", "HandTask", "build_scene"]
