"""Sigwalls: boundary lines the robot must not cross. They do not collide; crossing one costs."""

from __future__ import annotations

from typing import ClassVar

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.objects.base import StaticObject
from sg_torchrl.envs.navigation.world import ResetBuffers, Scene

__all__ = ["Sigwalls"]


class Sigwalls(StaticObject):
    """2 walls at ``x = +-bound``, or 4 walls adding ``y = +-bound``, each ``2 * length`` long.

    Cost ``"out_of_boundary"`` (reference section 3; Safety-Gymnasium's ``cost_out_of_boundary``):
    1 while the robot's root is beyond a wall, i.e. ``|x| > bound`` (or ``|y| > bound`` with 4
    walls), else 0. The walls are thin translucent boxes that nothing collides with, and they are not
    observed. They stand at fixed positions (keep-out 0) and keep their orientation whatever yaw
    the layout draws. Circle levels 1 and 2 use ``bound=1.125`` (2 and 4 walls), Run ``bound=0.5``
    with ``length=17.5``.
    """

    name: ClassVar[str] = "sigwalls"
    prefix: ClassVar[str] = "sigwall"
    in_goal_layout: ClassVar[bool] = False  # lines, not obstacles: a re-sampled goal may sit on one
    height: float = 0.25  # half the wall height: the walls stand on the floor
    thickness: ClassVar[float] = 0.01  # half-thickness

    def __init__(self, num: int = 2, *, bound: float = 1.125, length: float = 3.5, constrained: bool = True) -> None:
        if num not in (2, 4):
            raise ValueError(f"Sigwalls: num must be 2 (x = +-bound) or 4 (x and y = +-bound), got {num}")
        locations = [(-bound, 0.0), (bound, 0.0), (0.0, -bound), (0.0, bound)][:num]
        super().__init__(num, size=length, keepout=0.0, locations=locations, lidar=False, constrained=constrained)
        self.bound = float(bound)

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        half = [self.thickness, self.size, self.height] if i < 2 else [self.size, self.thickness, self.height]
        body.add_geom(name=self.body_name(i), type=mujoco.mjtGeom.mjGEOM_BOX, size=half, contype=0, conaffinity=0,
                      group=0, rgba=[1.0, 0.65, 0.0, 0.3])

    def place(self, scene: Scene, indices: np.ndarray, rows: ResetBuffers, xy: np.ndarray, yaw: np.ndarray) -> None:
        super().place(scene, indices, rows, xy, np.zeros_like(yaw))  # walls keep their axis

    @property
    def cost_names(self) -> tuple[str, ...]:
        return ("out_of_boundary",) if self.constrained else ()

    def costs(self, scene: Scene) -> dict[str, np.ndarray]:
        if not self.constrained:
            return {}
        outside = np.abs(scene.agent_xy()[:, : self.num // 2]) > self.bound  # x only, or x and y
        return {"out_of_boundary": outside.any(axis=1).astype(np.float64)}

    def agent_costs_one(self, scene: Scene, out: dict[str, np.ndarray]) -> None:
        """:meth:`costs` of one simulator and one robot on Python floats (the one-simulator step's): the
        same ``|coordinate| > bound`` comparisons (NaN fails them, as in the array form), their ``any``
        read as ``1.0`` or ``0.0``."""
        if not self.constrained:
            return
        x, y = scene.agent_xy()[0].tolist()
        bound = self.bound
        outside = abs(x) > bound or (self.num == 4 and abs(y) > bound)
        out["out_of_boundary"][0, 0] = 1.0 if outside else 0.0
