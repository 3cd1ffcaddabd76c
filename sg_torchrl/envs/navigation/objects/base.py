"""Task objects: small classes that own their placement, geometry, lidar group and cost.

An object describes ``num`` identical instances (``hazard0``, ``hazard1``, ...). It owns:

* **placement**: ``size``, ``keepout`` (placement radius), optional ``placements`` (rectangles
  ``(xmin, ymin, xmax, ymax)``; default: the task's extents) or fixed ``locations``; the layout
  sampler (:mod:`~sg_torchrl.envs.navigation.layout`) reads them;
* **geometry**: :meth:`NavObject.add_to` adds its bodies to the world's ``MjSpec``;
* **state**: :meth:`NavObject.place` writes a sampled layout into the reset rows (mocap
  positions or free-joint ``qpos``), :meth:`NavObject.positions` reads current positions;
* **observation**: ``lidar=True`` adds a 16-bin ``<name>_lidar`` group over :meth:`positions`;
* **cost**: :attr:`NavObject.cost_names` and :meth:`NavObject.costs`, raw values vectorised over
  the batch (``constrained=False`` keeps the object in the world but costs nothing); with several
  robots, :meth:`NavObject.agent_costs` says what each robot pays.

Two bases cover the usual cases: :class:`StaticObject` (mocap bodies: never moved by physics,
repositioned by writing ``mocap_pos``: goal, hazards, pillars, buttons) and :class:`FreeObject`
(free-joint bodies pushed around by the robot: vases, the push box). Objects driven along a
trajectory (gremlins) are mocap bodies with ``kind = "mover"``; they would add a per-sub-step
hook. Adding an object is subclassing one of these with ``add_geoms`` (and ``costs`` if it is a
constraint), then listing it in a task level.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from typing import TYPE_CHECKING, ClassVar, Literal

import mujoco
import numpy as np

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.robots.base import Robot
    from sg_torchrl.envs.navigation.world import ResetBuffers, Scene

__all__ = ["FreeObject", "NamedCost", "NavObject", "StaticObject", "yaw_quat"]

Kind = Literal["static", "free", "mover"]
_KIND_RANK = {"static": 0, "free": 1, "mover": 2}


def yaw_quat(yaw: np.ndarray) -> np.ndarray:
    """Quaternions (w, x, y, z) of rotations by ``yaw`` about +z, ``(..., 4)``."""
    half = 0.5 * np.asarray(yaw, dtype=np.float64)
    quat = np.zeros((*half.shape, 4))
    quat[..., 0] = np.cos(half)
    quat[..., 3] = np.sin(half)
    return quat


class NavObject(abc.ABC):
    """One kind of task object with ``num`` instances (see the module docstring).

    Args:
        num: number of instances.
        size: characteristic size (radius, or half-size of a box).
        keepout: placement radius: instances are placed at least ``keepout + other keepout`` from
            every other placed item.
        placements: rectangles to draw positions from (default: the task's extents).
        locations: fixed positions for the first ``len(locations)`` instances.
        lidar: observed through a ``<name>_lidar`` group.
        constrained: contributes its cost entries.
    """

    #: group name: lidar entry ``<name>_lidar`` and prefix of its cost entries
    name: ClassVar[str]
    #: body names are ``<prefix><i>`` (``None``: the single instance is called ``name``)
    prefix: ClassVar[str | None] = None
    kind: ClassVar[Kind] = "static"
    #: counted as occupied space when a goal is re-sampled mid-episode (gremlins are not)
    in_goal_layout: ClassVar[bool] = True
    #: a goal-like target: with ``compass=True`` the env adds a ``<name>_comp`` entry pointing at instance 0
    compass_target: ClassVar[bool] = False

    def __init__(
        self,
        num: int = 1,
        *,
        size: float,
        keepout: float,
        placements: Sequence[Sequence[float]] | None = None,
        locations: Sequence[Sequence[float]] = (),
        lidar: bool = True,
        constrained: bool = False,
    ) -> None:
        if num < 1:
            raise ValueError(f"{type(self).__name__}: num must be >= 1, got {num}")
        if len(locations) > num:
            raise ValueError(f"{type(self).__name__}: {len(locations)} locations for {num} instances")
        self.num = int(num)
        self.size = float(size)
        self.keepout = float(keepout)
        self.placements = None if placements is None else np.asarray(placements, dtype=np.float64).reshape(-1, 4)
        self.locations = np.asarray(locations, dtype=np.float64).reshape(-1, 2)
        self.lidar = lidar
        self.constrained = constrained
        self.body_ids = np.zeros(0, dtype=np.int64)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(num={self.num}, size={self.size}, keepout={self.keepout}, "
                f"constrained={self.constrained})")

    @property
    def kind_rank(self) -> int:
        return _KIND_RANK[self.kind]

    def spec_key(self) -> tuple:
        """What :meth:`add_to` depends on: part of the compiled-model cache key. Subclasses whose
        geometry depends on more than class, count and size extend it."""
        return (type(self).__qualname__, self.num, self.size)

    def for_robot(self, robot: Robot) -> None:
        """Adapt to the robot before the world is built (the push box is smaller for the Car). Default: nothing."""

    def body_name(self, i: int) -> str:
        if self.prefix is None:
            if self.num != 1:
                raise ValueError(f"{type(self).__name__} has {self.num} instances but no body prefix")
            return self.name
        return f"{self.prefix}{i}"

    # ------------------------------------------------------------------ world
    @abc.abstractmethod
    def add_to(self, spec: mujoco.MjSpec) -> None:
        """Add the ``num`` instance bodies (named :meth:`body_name`) to the world."""

    def bind(self, scene: Scene) -> None:
        """Resolve ids in the compiled model and allocate per-simulator state."""
        model = scene.model
        self.body_ids = np.array([model.body(self.body_name(i)).id for i in range(self.num)], dtype=np.int64)
        self.geom_mask = np.isin(model.geom_bodyid, self.body_ids)

    # ------------------------------------------------------------------ layout
    @abc.abstractmethod
    def place(self, scene: Scene, indices: np.ndarray, rows: ResetBuffers, xy: np.ndarray, yaw: np.ndarray) -> None:
        """Write a sampled layout into reset rows: ``xy`` ``(n, num, 2)``, ``yaw`` ``(n, num)`` for sims ``indices``."""

    @abc.abstractmethod
    def positions(self, scene: Scene) -> np.ndarray:
        """Current planar positions of the instances, ``(N, num, 2)``."""

    # ------------------------------------------------------------------ cost
    @property
    def cost_names(self) -> tuple[str, ...]:
        """Names of this object's ``cost_info`` entries (empty when unconstrained)."""
        return ()

    def costs(self, scene: Scene) -> dict[str, np.ndarray]:
        """Raw cost of each entry of :attr:`cost_names` for the current state, each ``(N,)``."""
        return {}

    def agent_costs(self, views: Sequence[Scene], out: dict[str, np.ndarray]) -> None:
        """Write every robot's raw cost entries for the current state: ``out[name][:, a]`` ``(N, A)``
        is what robot ``a`` pays (``views[a]``: the scene seen from it, :meth:`Scene.for_robot`).

        Default: each robot pays :meth:`costs` computed from its own point of view (its distance to
        a hazard, its contacts with a vase, ...). With one robot this is exactly :meth:`costs`.
        """
        for agent, view in enumerate(views):
            for name, value in self.costs(view).items():
                out[name][:, agent] = value

    def agent_costs_one(self, scene: Scene, out: dict[str, np.ndarray]) -> None:
        """:meth:`agent_costs` of one simulator and one robot (``scene``), into ``out[name][0, 0]``: the
        one-simulator step's (:mod:`~sg_torchrl.envs.navigation.single`). Default: :meth:`agent_costs`
        itself; an object may compute the same values on Python floats (:class:`Hazards`)."""
        self.agent_costs(scene.views, out)

    # ------------------------------------------------------------------ snapshots
    def state_dict(self) -> dict:
        """Per-simulator state kept outside ``MjData`` (for checkpoints)."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


class NamedCost(abc.ABC):
    """Mixin for a :class:`NavObject` whose one cost entry is named after it (``"hazards"``, ``"pillars"``,
    ...) and exists only when constrained. Subclasses give its value: :meth:`cost` over the batch and
    :meth:`cost_one`, the same value for one simulator on Python floats (the one-simulator step's form)."""

    name: str
    constrained: bool

    @property
    def cost_names(self) -> tuple[str, ...]:
        return (self.name,) if self.constrained else ()

    def costs(self, scene: Scene) -> dict[str, np.ndarray]:
        return {self.name: self.cost(scene)} if self.constrained else {}

    def agent_costs_one(self, scene: Scene, out: dict[str, np.ndarray]) -> None:
        if self.constrained:
            out[self.name][0, 0] = self.cost_one(scene)

    @abc.abstractmethod
    def cost(self, scene: Scene) -> np.ndarray:
        """The raw cost of the current state, ``(N,)``."""

    @abc.abstractmethod
    def cost_one(self, scene: Scene) -> float:
        """:meth:`cost` of simulator 0 (of a one-simulator scene), bit for bit."""


class StaticObject(NavObject):
    """Instances are mocap bodies: fixed during physics, moved by writing their mocap position.

    Subclasses implement :meth:`add_geoms` (geoms relative to the body) and set :attr:`height`
    (z of the body). Collision is up to the geoms (``contype``/``conaffinity``): goal and hazards
    never collide, pillars and buttons do.
    """

    kind: ClassVar[Kind] = "static"
    height: float = 0.0

    def add_to(self, spec: mujoco.MjSpec) -> None:
        for i in range(self.num):
            body = spec.worldbody.add_body(name=self.body_name(i), mocap=True, pos=[0.0, 0.0, self.height])
            self.add_geoms(body, i)

    @abc.abstractmethod
    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        """Add the geoms of instance ``i`` to its body."""

    def bind(self, scene: Scene) -> None:
        super().bind(scene)
        self.mocap_ids = scene.model.body_mocapid[self.body_ids].astype(np.int64)
        self._xy = np.zeros((scene.num_envs, self.num, 2))

    def place(self, scene: Scene, indices: np.ndarray, rows: ResetBuffers, xy: np.ndarray, yaw: np.ndarray) -> None:
        rows.mocap_pos[:, self.mocap_ids, :2] = xy
        rows.mocap_pos[:, self.mocap_ids, 2] = self.height
        rows.mocap_quat[:, self.mocap_ids] = yaw_quat(yaw)
        self._xy[indices] = xy

    def positions(self, scene: Scene) -> np.ndarray:
        return self._xy

    def state_dict(self) -> dict:
        return {"xy": self._xy.copy()}

    def load_state_dict(self, state: dict) -> None:
        self._xy[:] = state["xy"]

    def move(self, scene: Scene, index: int, instance: int, xy: np.ndarray) -> None:
        """Move instance ``instance`` of simulator ``index`` to ``xy`` mid-episode."""
        self._xy[index, instance] = xy
        scene.physics.set_mocap_pos(index, int(self.mocap_ids[instance]), np.array([xy[0], xy[1], self.height]))


class FreeObject(NavObject):
    """Instances are free-joint bodies resting on the floor; physics moves them.

    Subclasses implement :meth:`add_geoms` and set :attr:`height` (z of the body at rest).
    """

    kind: ClassVar[Kind] = "free"
    height: float = 0.0

    def add_to(self, spec: mujoco.MjSpec) -> None:
        for i in range(self.num):
            body = spec.worldbody.add_body(name=self.body_name(i), pos=[0.0, 0.0, self.height])
            body.add_freejoint(name=self.body_name(i))
            self.add_geoms(body, i)

    @abc.abstractmethod
    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        """Add the geoms of instance ``i`` to its body."""

    def bind(self, scene: Scene) -> None:
        super().bind(scene)
        model = scene.model
        joints = [model.body_jntadr[body] for body in self.body_ids]
        self.qpos_adr = np.array([model.jnt_qposadr[j] for j in joints], dtype=np.int64)
        self.dof_adr = np.array([model.jnt_dofadr[j] for j in joints], dtype=np.int64)
        # The rows of the bodies in the state cache: a slice when they follow each other (positions() is
        # then a view of the cache, as a static object's are of its own array, instead of an indexed copy).
        ids = self.body_ids
        contiguous = len(ids) and (np.diff(ids) == 1).all()
        self._body_rows = slice(int(ids[0]), int(ids[-1]) + 1) if contiguous else ids
        # qpos columns of (x, y, z, qw, qx, qy, qz) and qvel columns of the linear velocity, per instance
        self._qpos_cols = self.qpos_adr[:, None] + np.arange(7)
        self._linvel_cols = self.dof_adr[:, None] + np.arange(3)

    def place(self, scene: Scene, indices: np.ndarray, rows: ResetBuffers, xy: np.ndarray, yaw: np.ndarray) -> None:
        pose = np.empty((len(indices), self.num, 7))
        pose[..., :2] = xy
        pose[..., 2] = self.height
        pose[..., 3:] = yaw_quat(yaw)
        rows.qpos[:, self._qpos_cols] = pose

    def positions(self, scene: Scene) -> np.ndarray:
        """Current planar positions, ``(N, num, 2)``: a view of the state cache when the bodies follow each
        other (it follows the next step: copy it to keep it), else a new array."""
        return scene.body_xpos(self._body_rows)[..., :2]

    def speeds(self, scene: Scene) -> np.ndarray:
        """Linear speed of each instance, ``(N, num)`` (free-joint linear velocity at the body origin)."""
        velocity = scene.qvel()[:, self._linvel_cols]
        return np.sqrt(np.einsum("nki,nki->nk", velocity, velocity))
