"""Vases: light boxes that must not be touched or set in motion."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.objects.base import FreeObject
from sg_torchrl.envs.navigation.world import ResetBuffers, Scene

__all__ = ["Vases"]


class Vases(FreeObject):
    """``num`` free boxes of half-size ``size`` (default 0.1, density 0.001), keep-out 0.15.

    Costs when constrained (reference section 3; Goal level 2), each per step:

    * ``"<name>_contact"`` (``"vases_contact"``): the number of MuJoCo contacts between a vase geom and a robot geom;
    * ``"<name>_velocity"`` (``"vases_velocity"``): the sum of the linear speeds of the vases moving at least
      ``velocity_threshold`` (1e-4 m/s).

    Safety-Gymnasium also defines a displacement cost with coefficient 0, so it never appears.

    Several robots (Safety-Gymnasium's multi-agent tasks, :meth:`agent_costs`): each robot pays
    for its own contacts, and the speed of a moving vase is charged to the robot that touched it
    last in the episode (:attr:`last_toucher`; robots are visited in agent order, each marking the
    vases it touches now before its speed cost is summed, as the reference does). A vase nobody
    has touched costs nobody.
    """

    name: ClassVar[str] = "vases"
    prefix: ClassVar[str] = "vase"
    sink: ClassVar[float] = 4e-5  # soft contacts let a resting vase settle this far into the floor
    velocity_threshold: ClassVar[float] = 1e-4
    rgba: ClassVar[tuple[float, float, float, float]] = (0.0, 1.0, 1.0, 1.0)

    def __init__(self, num: int = 1, *, size: float = 0.1, keepout: float = 0.15, density: float = 0.001,
                 constrained: bool = True, **options) -> None:
        super().__init__(num, size=size, keepout=keepout, constrained=constrained, **options)
        self.density = density
        self.height = self.size - self.sink

    def spec_key(self) -> tuple:
        return (*super().spec_key(), self.density)

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        body.add_geom(name=self.body_name(i), type=mujoco.mjtGeom.mjGEOM_BOX, size=[self.size] * 3,
                      density=self.density, group=0, rgba=list(self.rgba))

    def bind(self, scene: Scene) -> None:
        super().bind(scene)
        self._geom_ids = np.flatnonzero(self.geom_mask)  # one box per vase: in instance order
        #: ``(N, num)`` the robot that touched each vase last this episode (-1: none); several robots only
        self.last_toucher = np.full((scene.num_envs, self.num), -1, dtype=np.int64)

    def place(self, scene: Scene, indices: np.ndarray, rows: ResetBuffers, xy: np.ndarray, yaw: np.ndarray) -> None:
        super().place(scene, indices, rows, xy, yaw)
        self.last_toucher[indices] = -1

    def state_dict(self) -> dict:
        return {"last_toucher": self.last_toucher.copy()}

    def load_state_dict(self, state: dict) -> None:
        self.last_toucher[:] = state.get("last_toucher", -1)  # snapshots from before multi-agent tasks: none

    @property
    def cost_names(self) -> tuple[str, ...]:
        return (f"{self.name}_contact", f"{self.name}_velocity") if self.constrained else ()

    def costs(self, scene: Scene) -> dict[str, np.ndarray]:
        if not self.constrained:
            return {}
        speeds = self.speeds(scene)
        return {
            f"{self.name}_contact": scene.physics.count_contacts(self.geom_mask, scene.robot_geoms),
            f"{self.name}_velocity": np.where(speeds >= self.velocity_threshold, speeds, 0.0).sum(axis=1),
        }

    def agent_costs(self, views: Sequence[Scene], out: dict[str, np.ndarray]) -> None:
        if len(views) == 1 or not self.constrained:
            super().agent_costs(views, out)
            return
        speeds = self.speeds(views[0])
        moving = np.where(speeds >= self.velocity_threshold, speeds, 0.0)
        for agent, view in enumerate(views):
            touching = view.robot_contacts()[:, self._geom_ids]  # (N, num) contacts of each vase with this robot
            out[f"{self.name}_contact"][:, agent] = touching.sum(axis=1)
            self.last_toucher[touching > 0] = agent
            out[f"{self.name}_velocity"][:, agent] = np.where(self.last_toucher == agent, moving, 0.0).sum(axis=1)
