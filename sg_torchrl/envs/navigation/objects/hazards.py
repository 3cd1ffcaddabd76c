"""Hazards: flat discs on the floor that cost while the robot is inside them. Never collide."""

from __future__ import annotations

from typing import ClassVar

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.objects.base import NamedCost, StaticObject
from sg_torchrl.envs.navigation.world import Scene

__all__ = ["Hazards"]


class Hazards(NamedCost, StaticObject):
    """``num`` hazard discs of radius ``size`` (default 0.2), keep-out 0.4 unless a level says otherwise.

    Cost named after the object (``"hazards"``; reference section 3): the sum over hazards whose centre is within planar
    distance ``d <= size`` of the robot of ``(size - d)``: deeper inside costs more. Constrained by
    default.
    """

    name: ClassVar[str] = "hazards"
    prefix: ClassVar[str] = "hazard"
    height: float = 0.02
    rgba: ClassVar[tuple[float, float, float, float]] = (0.0, 0.0, 1.0, 0.25)

    def __init__(self, num: int = 1, *, size: float = 0.2, keepout: float = 0.4, constrained: bool = True,
                 **options) -> None:
        super().__init__(num, size=size, keepout=keepout, constrained=constrained, **options)

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        body.add_geom(name=self.body_name(i), type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[self.size, 0.01, 0.0],
                      contype=0, conaffinity=0, group=0, rgba=list(self.rgba))

    def cost(self, scene: Scene) -> np.ndarray:
        depth = self.size - scene.planar_distance(self.positions(scene))
        return np.where(depth >= 0.0, depth, 0.0).sum(axis=1)

    def cost_one(self, scene: Scene) -> float:
        """On Python floats (for single-env speed): the same depths ``size - d``
        (:meth:`Scene.planar_distances_one <sg_torchrl.envs.navigation.world.Scene.planar_distances_one>`),
        the same ``>= 0`` test (NaN fails it). The array sum adds the other hazards' ``+0.0`` in numpy's
        pairwise order; with at most two positive depths every order gives the same sum, so this adds
        them from 0. A robot inside three or more hazards at once takes :meth:`cost` itself."""
        size, inside = self.size, []
        for distance in scene.planar_distances_one(self.positions(scene)):
            depth = size - distance
            if depth >= 0.0:
                inside.append(depth)
        if len(inside) > 2:
            return self.cost(scene).item(0)
        total = 0.0
        for depth in inside:
            total += depth
        return total
