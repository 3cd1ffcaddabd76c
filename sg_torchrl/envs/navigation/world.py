"""The world builder (``mujoco.MjSpec``) and :class:`Scene`, the runtime view of N simulators.

Building: :func:`build_spec` composes floor, robot and task objects as an ``MjSpec`` (no XML
templates); :func:`compiled_model` compiles it once per key and caches the ``MjModel`` for the life
of the process. The env's key is the robot, task and level plus what the objects' geometry depends
on (:meth:`NavObject.spec_key`), so one model exists per (robot, task, level) and a custom level
with different objects cannot pick up a stale model. Everything a layout decides (robot pose, goal,
hazards, vases, ...) is state in ``MjData`` (joint ``qpos``, mocap positions), so an episode reset
writes numbers and never recompiles, and every simulator of every env of that key shares one
model. (Safety-Gymnasium regenerates and recompiles its XML on every reset: about 1 s.)

Object order in the world, the layout and the observation: static objects (mocap bodies: goal,
hazards, pillars, buttons, ...), then free bodies (vases, the push box), then mocap-driven movers
(gremlins), each group in the order the task level lists them (reference section 2).
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from sg_torchrl.envs.physics import MujocoBatch

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.objects.base import NavObject
    from sg_torchrl.envs.navigation.robots.base import Robot

__all__ = ["ResetBuffers", "Scene", "build_spec", "compiled_model", "world_order"]

_MODELS: dict[Hashable, mujoco.MjModel] = {}


def world_order(objects: Sequence[NavObject]) -> list[NavObject]:
    """Objects in world order: by :attr:`NavObject.kind` rank, then as listed (stable)."""
    return sorted(objects, key=lambda obj: obj.kind_rank)


def build_spec(robot: Robot, objects: Sequence[NavObject], floor_half_size: float) -> mujoco.MjSpec:
    """The world as an ``MjSpec``: robot options and defaults, floor, robot, then the objects."""
    spec = mujoco.MjSpec()
    spec.modelname = f"{robot.name.lower()}_navigation"
    robot.build(spec)  # first: its defaults are the world's (the reference reads them from the robot file)
    spec.worldbody.add_light(name="sun", pos=[0.0, 0.0, 4.0], dir=[0.0, 0.0, -1.0], castshadow=False,
                             diffuse=[1.0, 1.0, 1.0], specular=[0.0, 0.0, 0.0])
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, condim=6,
                            size=[floor_half_size, floor_half_size, 0.1], rgba=[0.9, 0.9, 0.9, 1.0])
    for obj in world_order(objects):
        obj.add_to(spec)
    return spec


def compiled_model(key: Hashable, build: Callable[[], mujoco.MjSpec]) -> mujoco.MjModel:
    """The model compiled from ``build()`` for ``key``, compiled on first use and cached.

    The cached model is shared read-only by every env and simulator built for the same key.
    """
    model = _MODELS.get(key)
    if model is None:
        model = _MODELS[key] = build().compile()
    return model


@dataclass
class ResetBuffers:
    """Rows of simulator state being prepared for a reset (one row per reset simulator)."""

    qpos: np.ndarray  # (n, nq)
    qvel: np.ndarray  # (n, nv)
    mocap_pos: np.ndarray  # (n, nmocap, 3)
    mocap_quat: np.ndarray  # (n, nmocap, 4)


class Scene:
    """N simulators of one compiled world, with the vectorised views tasks and objects read.

    Args:
        model: the compiled world.
        num_envs: number of simulators.
        robot: the (bound) robot of this world.
    """

    def __init__(self, model: mujoco.MjModel, num_envs: int, robot: Robot) -> None:
        self.model = model
        self.num_envs = num_envs
        self.robot = robot
        self.physics = MujocoBatch(model, num_envs, fields=("xpos", "xmat", "sensordata"), forward_after_step=True)
        self.agent_body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, robot.root_body)
        #: which geoms belong to the robot (its whole body tree), ``(ngeom,)`` bool
        self.robot_geoms = model.body_rootid[model.geom_bodyid] == self.agent_body
        mocap_bodies = np.flatnonzero(model.body_mocapid >= 0)
        order = model.body_mocapid[mocap_bodies]
        self._mocap_pos = np.empty((model.nmocap, 3))
        self._mocap_quat = np.empty((model.nmocap, 4))
        self._mocap_pos[order] = model.body_pos[mocap_bodies]
        self._mocap_quat[order] = model.body_quat[mocap_bodies]
        self._xpos = self.physics.field("xpos")
        self._xmat = self.physics.field("xmat").reshape(num_envs, model.nbody, 3, 3)
        self._robot_contacts = np.zeros((num_envs, model.ngeom))  # see robot_contacts
        self._contacts_version = -1

    def reset_buffers(self, count: int) -> ResetBuffers:
        """Fresh state rows for ``count`` simulators: the model's rest state, mocaps where the model put them."""
        model = self.model
        return ResetBuffers(
            qpos=np.tile(model.qpos0, (count, 1)),
            qvel=np.zeros((count, model.nv)),
            mocap_pos=np.tile(self._mocap_pos, (count, 1, 1)),
            mocap_quat=np.tile(self._mocap_quat, (count, 1, 1)),
        )

    # ------------------------------------------------------------------ state views (updated in place)
    def agent_pos(self) -> np.ndarray:
        """Position of the robot's root body, ``(N, 3)``."""
        return self._xpos[:, self.agent_body]

    def agent_xy(self) -> np.ndarray:
        return self._xpos[:, self.agent_body, :2]

    def agent_mat(self) -> np.ndarray:
        """Rotation matrix (body to world) of the robot's root body, ``(N, 3, 3)``."""
        return self._xmat[:, self.agent_body]

    def body_xpos(self, bodies: np.ndarray) -> np.ndarray:
        """Positions of ``bodies`` (ids), ``(N, len(bodies), 3)`` (a new array)."""
        return self._xpos[:, bodies]

    def sensordata(self) -> np.ndarray:
        return self.physics.field("sensordata")

    def qvel(self) -> np.ndarray:
        return self.physics.qvel()

    def planar_distance(self, xy: np.ndarray) -> np.ndarray:
        """Planar distance from the robot's root to points ``xy`` (``(N, K, 2)``), ``(N, K)``."""
        delta = xy - self.agent_xy()[:, None, :]
        return np.sqrt(np.einsum("nki,nki->nk", delta, delta))

    def robot_contacts(self) -> np.ndarray:
        """Number of contacts between each geom and the robot, ``(N, ngeom)``, for the current state.

        Computed in one pass over the contacts and cached until the physics state changes, so every
        contact-cost object (buttons, gremlins, pillars, ...) and the task share it within a step.
        """
        version = self.physics.version
        if self._contacts_version != version:
            self._robot_contacts = self.physics.contact_counts(self.robot_geoms)
            self._contacts_version = version
        return self._robot_contacts
