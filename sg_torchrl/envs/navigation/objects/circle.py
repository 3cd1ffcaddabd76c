"""The Circle zone: a flat disc marking the circle the robot should run along. Never collides, costs nothing."""

from __future__ import annotations

from typing import ClassVar

import mujoco

from sg_torchrl.envs.navigation.objects.base import StaticObject

__all__ = ["CircleZone"]


class CircleZone(StaticObject):
    """A disc of radius ``size`` (default 1.5) fixed at ``center`` (default the origin), keep-out 0.

    Observed through ``circle_lidar`` (the Circle task reads it with lidar range 6). Reward term
    (the task reads it): ``reward_factor`` (0.1) times the robot's speed around the centre,
    damped by how far the robot is from the rim (reference section 4).
    """

    name: ClassVar[str] = "circle"
    in_goal_layout: ClassVar[bool] = False  # a floor marking, not an obstacle
    height: float = 0.002

    def __init__(self, *, size: float = 1.5, center: tuple[float, float] = (0.0, 0.0), reward_factor: float = 0.1,
                 **options) -> None:
        super().__init__(1, size=size, keepout=0.0, locations=[center], **options)
        self.reward_factor = reward_factor

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        body.add_geom(name=self.body_name(i), type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[self.size, self.height, 0.0],
                      contype=0, conaffinity=0, group=0, rgba=[0.0, 1.0, 0.0, 0.1])
