"""Velocity-constrained locomotion tasks (Safety-Gymnasium paper, section 4.2)."""

from sg_torchrl.envs.velocity.env import VelocityEnv
from sg_torchrl.envs.velocity.robots import ROBOTS, HealthCheck, LocomotionRobot

__all__ = ["VelocityEnv", "ROBOTS", "HealthCheck", "LocomotionRobot"]
