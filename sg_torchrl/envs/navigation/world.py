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

Several robots (multi-agent tasks): :func:`build_spec` adds them one after the other, each under its
name prefix (:attr:`Robot.prefix <sg_torchrl.envs.navigation.robots.base.Robot>`, e.g.
``"agent_1/"``), and :class:`Scene` keeps one agent-relative view per robot
(:meth:`Scene.for_robot`), so objects compute each robot's cost with the code they use for one.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from sg_torchrl.envs.backends import SimulatorOptions, make_physics

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.objects.base import NavObject
    from sg_torchrl.envs.navigation.robots.base import Robot
    from sg_torchrl.envs.navigation.scenery import Scenery

__all__ = ["FIXED_CAMERAS", "FLOOR_CHECKER", "FLOOR_CHECKER_PERIOD", "REFERENCE_EXTENTS", "ResetBuffers", "Scene",
           "add_look", "add_track_camera", "agent_prefix", "build_spec", "compiled_model", "prefix_robot",
           "world_extent", "world_order"]

_MODELS: dict[Hashable, mujoco.MjModel] = {}


def world_order(objects: Sequence[NavObject]) -> list[NavObject]:
    """Objects in world order: by :attr:`NavObject.kind` rank, then as listed (stable)."""
    return sorted(objects, key=lambda obj: obj.kind_rank)


def agent_prefix(index: int, count: int) -> str:
    """Name prefix of robot ``index`` of ``count`` in one world: none for a single robot (the names of
    the single-agent worlds), ``"agent_<index>/"`` for several."""
    return "" if count == 1 else f"agent_{index}/"


def build_spec(
    robot: Robot | Sequence[Robot], objects: Sequence[NavObject], floor_half_size: float,
    scenery: Scenery | None = None, extent: float | None = None,
) -> mujoco.MjSpec:
    """The world as an ``MjSpec``: robot options and defaults, the robot(s), the floor, the fixed
    ``scenery`` (:mod:`.scenery`: Race's village, Building's construction site, FormulaOne's track), then
    the objects.

    ``robot`` is one robot or a sequence of them (several robots share one world: their options and
    defaults must agree, as they do for robots of one class); each robot's elements are renamed
    with its prefix (:func:`prefix_robot`). ``extent``: the model's ``stat.extent`` in metres
    (:func:`world_extent`; ``None``: MuJoCo's, computed at compile time).
    """
    robots = list(robot) if isinstance(robot, Sequence) else [robot]
    spec = mujoco.MjSpec()
    spec.modelname = f"{robots[0].name.lower()}_navigation"
    if extent is not None:
        spec.stat.extent = extent
    for each in robots:  # first: their defaults are the world's (the reference reads them from the robot file)
        counts = _ElementCounts.of(spec)
        each.build(spec)
        add_track_camera(spec.body(each.root_body))
        if each.prefix:
            prefix_robot(spec, each, counts)
    for name, pos in FIXED_CAMERAS.items():
        camera = spec.worldbody.add_camera(name=name, pos=list(pos))
        camera.alt.type = mujoco.mjtOrientation.mjORIENTATION_ZAXIS
        camera.alt.zaxis = [0.0, -1.0, 1.0]  # looking at the arena's centre, 45 degrees down
    add_look(spec, floor_half_size)
    if scenery is not None:
        scenery.build(spec)
    for obj in world_order(objects):
        obj.add_to(spec)
    return spec


#: Safety-Gymnasium's floor texture ("matplane"): a 2 x 2 checker of these two sand colours
FLOOR_CHECKER = ((0.859, 0.843, 0.765), (0.949, 0.914, 0.855))
#: metres per repeat of the checker (two squares): Safety-Gymnasium repeats it 10 times across its 7 m floor
FLOOR_CHECKER_PERIOD = 0.7
#: pixels a side of the skybox's faces and the share of them that are stars
_SKY_SIZE, _STARS = 512, 0.004


def add_look(spec: mujoco.MjSpec, floor_half_size: float) -> None:
    """Add what the world looks like: the floor, its light and the sky, as Safety-Gymnasium's worlds.

    Why: pixel observations (the Vision ids) are only comparable with the original's if the robot's
    camera sees the same world. Measured on safety-gymnasium 1.0.0 (its ``world.py`` and compiled
    models): the floor is a plane with a checkered texture (:data:`FLOOR_CHECKER`, squares of 0.35 m)
    in a slightly specular (0.1), shiny (0.1) and reflective (0.1) material; one directional light
    straight down (diffuse 1, no specular, no shadows) plus MuJoCo's default headlight; the sky is a
    star field (a skybox of black with sparse white stars; here MuJoCo's built-in random marks, not
    the original's star photographs). Scenery (:mod:`.scenery`) may restyle the floor afterwards.
    """
    repeat = 2.0 * floor_half_size / FLOOR_CHECKER_PERIOD
    spec.add_texture(name="floor_checker", type=mujoco.mjtTexture.mjTEXTURE_2D,
                     builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER, width=100, height=100,
                     rgb1=list(FLOOR_CHECKER[0]), rgb2=list(FLOOR_CHECKER[1]))
    material = spec.add_material(name="floor_checker", texrepeat=[repeat, repeat], specular=0.1, shininess=0.1,
                                 reflectance=0.1)
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "floor_checker"
    spec.add_texture(name="sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX, builtin=mujoco.mjtBuiltin.mjBUILTIN_FLAT,
                     width=_SKY_SIZE, height=_SKY_SIZE, rgb1=[0.0, 0.0, 0.0], rgb2=[0.0, 0.0, 0.0],
                     mark=mujoco.mjtMark.mjMARK_RANDOM, random=_STARS, markrgb=[1.0, 1.0, 1.0])
    spec.worldbody.add_light(name="sun", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, pos=[0.0, 0.0, 0.5],
                             dir=[0.0, 0.0, -1.0], castshadow=False, diffuse=[1.0, 1.0, 1.0],
                             specular=[0.0, 0.0, 0.0])
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, condim=6, material="floor_checker",
                            size=[floor_half_size, floor_half_size, 0.1], rgba=[1.0, 1.0, 1.0, 1.0])


#: Safety-Gymnasium's model extent (``stat.extent``, metres) per (task, level): the mean over 4-6 layouts
#: measured on 1.0.0 (Point; Car's agree within 3%). Circle 1-2 and Run are fixed by their boundary walls.
#: The Fading tasks are Goal levels (FadingEasy1 measured 2.91). See :func:`world_extent`.
REFERENCE_EXTENTS = {
    **{(task, level): extent for task in ("Goal", "FadingEasy", "FadingHard")
       for level, extent in enumerate((1.30, 2.88, 3.91))},
    ("Button", 0): 1.80, ("Button", 1): 2.90, ("Button", 2): 3.88,
    ("Push", 0): 1.86, ("Push", 1): 3.08, ("Push", 2): 4.11,
    ("Circle", 0): 3.00, ("Circle", 1): 9.28, ("Circle", 2): 9.28,
    ("Run", 0): 36.0,
}


def world_extent(task_name: str, level: int, placement_half_width: float) -> float:
    """The ``stat.extent`` to compile a task's world with: Safety-Gymnasium's (:data:`REFERENCE_EXTENTS`).

    Why: MuJoCo puts the cameras' clipping planes at 1% and 50 times the extent (and the free camera at
    a distance in proportion). Safety-Gymnasium recompiles every layout, so its extent is the spread of
    that layout's bodies: about 2.9 m at Goal level 1, 9.3 m for Circle (its boundary walls), 36 m for
    Run. Ours is compiled once, before any layout is placed (0.85 m for PointGoal1), which would put
    the near plane at 8 mm: the Racecar's ``vision`` camera, 13.5 mm behind its front bumper, would
    see the bumper fill its view where the original's clips it, and at Circle (near plane 9 cm) the
    original's Point camera does not see its own body. Tasks the table lacks (the original has no
    such task, or cannot build it) get twice their placement half-width, which is within 5% of the
    table for every Goal, Button and Push level above 0.
    """
    extent = REFERENCE_EXTENTS.get((task_name, level))
    return extent if extent is not None else 2.0 * placement_half_width


#: Safety-Gymnasium's fixed world cameras (its ``world.py``): name -> position, each looking towards +y, 45 degrees down
FIXED_CAMERAS = {"fixednear": (0.0, -2.0, 2.0), "fixedfar": (0.0, -5.0, 5.0)}
#: Safety-Gymnasium's ``track`` camera in the world frame: 2 m in +y and 2 m above the robot, looking back
#: towards -y 45 degrees down; image x axis along -x, y axis up the slope
_TRACK_OFFSET = np.array([0.0, 2.0, 2.0])
_TRACK_AXES = np.array([[-1.0, 0.0, 0.0], [0.0, -math.sqrt(0.5), math.sqrt(0.5)]])


def add_track_camera(root: mujoco.MjsBody) -> None:
    """Add Safety-Gymnasium's ``track`` camera to a robot's ``root`` body.

    Why this pose: the original builds it from the layout's robot yaw so that, once the robot's body is
    rotated by that yaw, the camera always sits at the same world offset (:data:`_TRACK_OFFSET`,
    measured on safety-gymnasium 1.0.0 for every robot and seed). A MuJoCo ``track`` camera keeps the
    world offset and orientation it has at ``qpos0`` while following the body, so the offset is
    written here in the root body's frame at ``qpos0`` (its spec orientation).
    """
    rotation = np.zeros(9)
    mujoco.mju_quat2Mat(rotation, np.asarray(root.quat, dtype=np.float64))
    to_local = rotation.reshape(3, 3).T
    camera = root.add_camera(name="track", pos=list(to_local @ _TRACK_OFFSET))
    camera.mode = mujoco.mjtCamLight.mjCAMLIGHT_TRACK
    camera.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
    camera.alt.xyaxes = list((_TRACK_AXES @ to_local.T).reshape(-1))


@dataclass(frozen=True)
class _ElementCounts:
    """How many sensors, actuators, equalities and excludes a spec held before a robot was built into it."""

    sensors: int
    actuators: int
    equalities: int
    excludes: int
    tendons: int

    @classmethod
    def of(cls, spec: mujoco.MjSpec) -> _ElementCounts:
        return cls(len(spec.sensors), len(spec.actuators), len(spec.equalities), len(spec.excludes),
                   len(spec.tendons))


_TREE_ELEMENTS = (mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_JOINT, mujoco.mjtObj.mjOBJ_GEOM,
                  mujoco.mjtObj.mjOBJ_SITE, mujoco.mjtObj.mjOBJ_CAMERA, mujoco.mjtObj.mjOBJ_LIGHT)


def prefix_robot(spec: mujoco.MjSpec, robot: Robot, before: _ElementCounts) -> None:
    """Prepend ``robot.prefix`` to the names of everything ``robot.build`` just added to ``spec``.

    The robot's elements are its body tree (rooted at ``robot.root_body``: bodies, joints, geoms,
    sites, cameras, lights) and the sensors, actuators, equality constraints and contact excludes
    added after ``before`` was counted. ``MjSpec`` resolves references by name at compile time and
    does not follow renames, so every reference those elements hold (an actuator's target, a
    sensor's object, the bodies of an exclude, ...) is prefixed too: a robot only refers to its
    own elements. Tendons are not supported (no robot has one).
    """
    prefix = robot.prefix
    if len(spec.tendons) != before.tendons:
        raise NotImplementedError(f"{robot.name}: robots with tendons cannot be prefixed")

    def rename(element, *fields: str) -> None:
        for name in ("name", *fields):
            value = getattr(element, name)
            if value:
                setattr(element, name, prefix + value)

    root = spec.body(robot.root_body)
    for element in [root, *(e for kind in _TREE_ELEMENTS for e in root.find_all(kind))]:
        rename(element)
    for sensor in spec.sensors[before.sensors:]:
        rename(sensor, "objname", "refname")
    for actuator in spec.actuators[before.actuators:]:
        rename(actuator, "target", "refsite", "slidersite")
    for equality in spec.equalities[before.equalities:]:
        rename(equality, "name1", "name2")
    for exclude in spec.excludes[before.excludes:]:
        rename(exclude, "bodyname1", "bodyname2")


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
        robot: the (bound) robot of this world, or its robots in agent order.
        physics_threads: threads stepping the simulators (:class:`~sg_torchrl.envs.physics.MujocoBatch`).

    Agent-relative views (:meth:`agent_pos`, :meth:`planar_distance`, :attr:`robot_geoms`,
    :meth:`robot_contacts`, ...) refer to one robot: the first. :meth:`for_robot` gives the same
    simulators seen from another robot; :attr:`views` lists one scene per robot.
    """

    def __init__(self, model: mujoco.MjModel, num_envs: int, robot: Robot | Sequence[Robot], *,
                 physics_threads: int = 1) -> None:
        self.model = model
        self.num_envs = num_envs
        self.robots: list[Robot] = list(robot) if isinstance(robot, Sequence) else [robot]
        self.physics = make_physics(model, num_envs, SimulatorOptions(physics_threads=physics_threads),
                                    fields=("xpos", "xmat", "sensordata"), forward_after_step=True)
        mocap_bodies = np.flatnonzero(model.body_mocapid >= 0)
        order = model.body_mocapid[mocap_bodies]
        self._mocap_pos = np.empty((model.nmocap, 3))
        self._mocap_quat = np.empty((model.nmocap, 4))
        self._mocap_pos[order] = model.body_pos[mocap_bodies]
        self._mocap_quat[order] = model.body_quat[mocap_bodies]
        self._xpos = self.physics.field("xpos")
        self._xmat = self.physics.field("xmat").reshape(num_envs, model.nbody, 3, 3)
        self._sensordata = self.physics.field("sensordata")
        self._attach(self.robots[0])
        views = [self]
        for other in self.robots[1:]:
            view = copy.copy(self)  # shares the simulators and state caches; agent-relative fields are replaced
            view._attach(other)
            views.append(view)
        #: one scene per robot, in agent order (the first robot's is this scene; :meth:`for_robot`)
        self.views: list[Scene] = views
        for view in views[1:]:
            view.views = views

    def _attach(self, robot: Robot) -> None:
        """Make ``robot`` the one the agent-relative views refer to."""
        model = self.model
        self.robot = robot
        self.agent_body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, robot.qualified(robot.root_body))
        #: which geoms belong to the robot (its whole body tree), ``(ngeom,)`` bool
        self.robot_geoms = model.body_rootid[model.geom_bodyid] == self.agent_body
        self._robot_contacts = np.zeros((self.num_envs, model.ngeom))  # see robot_contacts
        self._contacts_version = -1
        self._robot_geom_list = self.robot_geoms.tolist()  # see robot_contacts_one
        self._contacts_one: dict[int, float] = {}
        self._contacts_one_version = -1
        # The robot's rows of the state cache, taken once: the cache is filled in place, so these views
        # follow every step (a step reads them several times; each fresh view costs an indexing).
        self._agent_pos = self._xpos[:, self.agent_body]
        self._agent_xy = self._xpos[:, self.agent_body, :2]
        self._agent_mat = self._xmat[:, self.agent_body]

    def for_robot(self, index: int) -> Scene:
        """These simulators seen from robot ``index`` (0: this scene): its agent-relative views refer
        to that robot; everything else is shared."""
        return self.views[index]

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
        """Position of the robot's root body, ``(N, 3)`` (a view of the state cache: do not write)."""
        return self._agent_pos

    def agent_xy(self) -> np.ndarray:
        """Planar position of the robot's root body, ``(N, 2)`` (a view of the state cache: do not write)."""
        return self._agent_xy

    def agent_mat(self) -> np.ndarray:
        """Rotation matrix (body to world) of the robot's root body, ``(N, 3, 3)`` (a view: do not write)."""
        return self._agent_mat

    def body_xpos(self, bodies: np.ndarray | slice) -> np.ndarray:
        """Positions of ``bodies`` (ids: a new array; a slice of ids: a view of the state cache, do not
        write), ``(N, len(bodies), 3)``."""
        return self._xpos[:, bodies]

    def sensordata(self) -> np.ndarray:
        """Sensor readings, ``(N, nsensordata)`` (the state cache: do not write)."""
        return self._sensordata

    def qvel(self) -> np.ndarray:
        return self.physics.qvel()

    def planar_distance(self, xy: np.ndarray) -> np.ndarray:
        """Planar distance from the robot's root to points ``xy`` (``(N, K, 2)``), ``(N, K)``.

        ``sqrt(dx * dx + dy * dy)``: the products and the sum ``np.einsum`` would take, in its order
        (same values bit for bit), without its call overhead; one simulator reads the robot's position
        as two Python floats (a one-simulator step is mostly per-operation overhead).
        """
        if self.num_envs == 1:
            x, y = self._agent_xy[0].tolist()
        else:
            x, y = self._agent_xy[:, 0, None], self._agent_xy[:, 1, None]
        dx = xy[..., 0] - x
        dy = xy[..., 1] - y
        return np.sqrt(dx * dx + dy * dy)

    def planar_distances_one(self, xy: np.ndarray) -> list[float]:
        """:meth:`planar_distance` of simulator 0 as Python floats, ``[d_k]`` for ``xy[0]`` (``(1, K, 2)``).

        Why two forms: a one-simulator step (:mod:`~sg_torchrl.envs.navigation.single`) computes a
        goal distance or a hazard depth on floats, without the five array operations. The values are
        the same: the same float64 differences, products and sum, and ``math.sqrt`` and ``np.sqrt`` are
        both IEEE's correctly rounded square root (tested against :meth:`planar_distance`).
        """
        x, y = self._agent_xy[0].tolist()
        distances = []
        for px, py in xy[0].tolist():
            dx, dy = px - x, py - y
            distances.append(math.sqrt(dx * dx + dy * dy))
        return distances

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

    def robot_contacts_one(self) -> dict[int, float]:
        """:meth:`robot_contacts` of simulator 0 as ``{geom: count}`` over the geoms touching the robot
        (absent: 0.0), cached until the physics state changes: the one-simulator step's form
        (:mod:`~sg_torchrl.envs.navigation.single`), which the goal button, the buttons' cost and the
        contact costs share within a step. The same whole-number counts
        (:meth:`MujocoBatch.contact_counts_one <sg_torchrl.envs.physics.MujocoBatch.contact_counts_one>`)."""
        version = self.physics.version
        if self._contacts_one_version != version:
            self._contacts_one = self.physics.contact_counts_one(self._robot_geom_list)
            self._contacts_one_version = version
        return self._contacts_one
