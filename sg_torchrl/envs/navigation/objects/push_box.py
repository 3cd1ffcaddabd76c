"""The push box: a light box the robot pushes onto the goal (Push task). Costs nothing."""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import mujoco

from sg_torchrl.envs.navigation.objects.base import FreeObject

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.robots.base import Robot

__all__ = ["PushBox"]

_POINT_BOX = {"size": 0.2, "keepout": 0.2, "density": 0.001}


class PushBox(FreeObject):
    """The box: half-size 0.2, keep-out 0.2, density 0.001 for the Point (reference section 6).

    Size, keep-out and density depend on the robot (:attr:`robot_variants`: the Car pushes a
    0.125 box, keep-out 0.125, density 0.0005); values passed explicitly win over the robot's.
    As in the reference model, four corner posts (half-size ``size / 2`` in x and y, full height)
    centred on the box's vertical edges stick out of it (the box reaches ``1.5 * size`` at its corners).

    Reward terms (the task reads them): ``reward_box_dist`` times the distance the robot gained
    on the box, counted only while it was farther than ``null_dist * size`` (0: always).
    """

    name: ClassVar[str] = "push_box"
    #: per-robot size, keep-out and density (robots not listed get the Point's)
    robot_variants: ClassVar[dict[str, dict[str, float]]] = {"Car": {"size": 0.125, "keepout": 0.125, "density": 0.0005}}
    rgba: ClassVar[tuple[float, float, float, float]] = (1.0, 1.0, 0.0, 1.0)
    sink: ClassVar[float] = 9e-6  # soft contacts let the resting box settle this far into the floor

    def __init__(self, *, size: float | None = None, keepout: float | None = None, density: float | None = None,
                 reward_box_dist: float = 1.0, null_dist: float = 0.0, **options) -> None:
        self._explicit = {key: value for key, value in (("size", size), ("keepout", keepout), ("density", density))
                          if value is not None}
        settings = {**_POINT_BOX, **self._explicit}
        super().__init__(1, size=settings["size"], keepout=settings["keepout"], **options)
        self.density = float(settings["density"])
        self.reward_box_dist = reward_box_dist
        self.null_dist = null_dist
        self.height = self.size - self.sink

    def for_robot(self, robot: Robot) -> None:
        settings = {**_POINT_BOX, **self.robot_variants.get(robot.name, {}), **self._explicit}
        self.size, self.keepout, self.density = (float(settings[key]) for key in ("size", "keepout", "density"))
        self.height = self.size - self.sink

    def spec_key(self) -> tuple:
        return (*super().spec_key(), self.density)

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        box, post, rgba = mujoco.mjtGeom.mjGEOM_BOX, self.size / 2, list(self.rgba)
        body.add_geom(name=self.name, type=box, size=[self.size] * 3, density=self.density, group=0, rgba=rgba)
        for k, (sx, sy) in enumerate(((1, 1), (-1, 1), (1, -1), (-1, -1))):
            body.add_geom(name=f"{self.name}_post{k}", type=box, size=[post, post, self.size],
                          pos=[sx * self.size, sy * self.size, 0.0], density=self.density, group=0, rgba=rgba)
