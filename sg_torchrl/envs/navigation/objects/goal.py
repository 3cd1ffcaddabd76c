"""The goal: a translucent cylinder the robot drives into. Never collides, costs nothing."""

from __future__ import annotations

from typing import ClassVar

import mujoco

from sg_torchrl.envs.navigation.objects.base import StaticObject

__all__ = ["Goal"]


class Goal(StaticObject):
    """Goal area of radius ``size`` (default 0.3, reached when the robot is within it), keep-out 0.4.

    Reward terms (the task reads them): ``reward_distance`` times the distance gained towards
    the goal, plus ``reward_goal`` on a step that ends inside it.
    """

    name: ClassVar[str] = "goal"
    compass_target: ClassVar[bool] = True

    def __init__(self, *, size: float = 0.3, keepout: float = 0.4, reward_distance: float = 1.0,
                 reward_goal: float = 1.0, **options) -> None:
        super().__init__(1, size=size, keepout=keepout, **options)
        self.reward_distance = reward_distance
        self.reward_goal = reward_goal
        self.height = self.size / 2 + 0.01  # the cylinder stands on the floor

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        body.add_geom(name=self.body_name(i), type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[self.size, self.size / 2, 0.0],
                      contype=0, conaffinity=0, group=0, rgba=[0.0, 1.0, 0.0, 0.25])
