"""Pillars: tall immovable cylinders the robot must not bump into."""

from __future__ import annotations

from typing import ClassVar

import mujoco

from sg_torchrl.envs.navigation.objects.base import StaticObject
from sg_torchrl.envs.navigation.objects.contacts import ContactCost

__all__ = ["Pillars"]


class Pillars(ContactCost, StaticObject):
    """``num`` cylinders of radius ``size`` (0.2) and half-height ``half_height`` (0.5), keep-out 0.3.

    They stand on the floor and collide with the robot (and push box). Cost ``"pillars"`` when
    constrained (reference section 3; Push level 2 only, the level-1 pillar is free): the number
    of robot-pillar contacts.
    """

    name: ClassVar[str] = "pillars"
    prefix: ClassVar[str] = "pillar"
    rgba: ClassVar[tuple[float, float, float, float]] = (0.5, 0.5, 1.0, 1.0)

    def __init__(self, num: int = 1, *, size: float = 0.2, half_height: float = 0.5, keepout: float = 0.3,
                 constrained: bool = True, **options) -> None:
        super().__init__(num, size=size, keepout=keepout, constrained=constrained, **options)
        self.half_height = float(half_height)
        self.height = self.half_height

    def spec_key(self) -> tuple:
        return (*super().spec_key(), self.half_height)

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        body.add_geom(name=self.body_name(i), type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                      size=[self.size, self.half_height, 0.0], group=0, rgba=list(self.rgba))
