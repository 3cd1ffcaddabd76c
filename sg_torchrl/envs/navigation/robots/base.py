"""The robot interface of the navigation engine.

A robot contributes to the world: the physics options and world-wide defaults it was tuned
with (Safety-Gymnasium takes them from the robot's model file, so they also apply to the task
objects), its body tree rooted at :attr:`Robot.root_body`, its actuators (one per action
dimension, in action order) and its sensors. At run time it writes its start pose into ``qpos``
and turns sensor readings into the leading part of the observation.

Observation order (reference section 2): the fixed sensors (accelerometer, velocimeter, gyro,
magnetometer, then robot extras such as Doggo's touch sensors), hinge-joint velocities,
ball-joint angular velocities, free-joint height, free-joint linear velocity, hinge-joint angles
as (sin, cos), ball-joint quaternions as 3x3 rotation matrices. Only the robot's own joints with
a sensor count: the planar root joints of Point and Car have none, so they add nothing. A robot
declares this list as :attr:`Robot.observation_terms`, one :class:`SensorTerm` per sensor.

Adding a robot: subclass :class:`Robot`, implement :meth:`build` and :meth:`set_pose`, declare
``observation_terms`` (and ``is_alive`` if it can fall over, as the Ant does), then add the class
to :data:`sg_torchrl.envs.navigation.robots.ROBOTS`.

Several robots in one world (the multi-agent tasks): each robot instance has a name ``prefix``
(``""`` for the one robot of a single-agent world). :meth:`build` always uses the plain names
(``"agent"``, ``"accelerometer"``, ...); the world builder then prefixes every element the robot
added and every reference between them (:func:`~sg_torchrl.envs.navigation.world.build_spec`), and
the robot looks its elements up in the compiled model through :meth:`Robot.qualified`.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, Literal

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.objects.base import yaw_quat

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.world import Scene

__all__ = ["FreeBodyRobot", "Robot", "SensorTerm", "FIXED_SENSORS", "add_fixed_sensors", "add_vision_camera"]

FIXED_SENSORS = ("accelerometer", "velocimeter", "gyro", "magnetometer")
_FIXED_SENSOR_TYPES = {
    "accelerometer": mujoco.mjtSensor.mjSENS_ACCELEROMETER,
    "velocimeter": mujoco.mjtSensor.mjSENS_VELOCIMETER,
    "gyro": mujoco.mjtSensor.mjSENS_GYRO,
    "magnetometer": mujoco.mjtSensor.mjSENS_MAGNETOMETER,
}


def add_fixed_sensors(spec: mujoco.MjSpec, site: str) -> None:
    """Add the four fixed sensors (:data:`FIXED_SENSORS`, named as such) on ``site``, in observation order."""
    for sensor in FIXED_SENSORS:
        spec.add_sensor(name=sensor, type=_FIXED_SENSOR_TYPES[sensor], objtype=mujoco.mjtObj.mjOBJ_SITE, objname=site)


#: the ``vision`` camera's image axes of Point, Car and Doggo: looking along the body's +x axis, tilted
#: down by 22 degrees (Safety-Gymnasium's ``xyaxes="0 -1 0 .4 0 1"``)
TILTED_FORWARD = (0.0, -1.0, 0.0, 0.4, 0.0, 1.0)


def add_vision_camera(body: mujoco.MjsBody, pos: list[float], *, xyaxes: tuple[float, ...] = TILTED_FORWARD,
                      fovy: float = 90.0) -> None:
    """Add the ``vision`` camera (the Vision ids' pixel observations) at ``pos`` on ``body``.

    ``xyaxes`` (the image's x and y axes in the body frame) and ``fovy`` (vertical field of view,
    degrees) are each robot's in Safety-Gymnasium 1.0.0, measured there relative to the robot's root
    body (its compiled models' ``cam_pos`` / ``cam_quat`` / ``cam_fovy``; 45 where its model gives none),
    so that the same id shows the same view.
    """
    camera = body.add_camera(name="vision", pos=pos, fovy=fovy)
    camera.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
    camera.alt.xyaxes = list(xyaxes)

# How a sensor reading becomes observation values.
Transform = Literal["raw", "sincos", "rotmat", "z"]
_WIDTH = {"sincos": 2, "rotmat": 9, "z": 1}


@dataclass(frozen=True)
class SensorTerm:
    """One observed sensor.

    Args:
        sensor: the MuJoCo sensor name (also the observation entry's name).
        transform: ``"raw"`` (the reading as is), ``"sincos"`` (a hinge angle as (sin, cos)),
            ``"rotmat"`` (a quaternion as a row-major 3x3 rotation matrix) or ``"z"`` (the last
            component of a 3-vector: the free-joint height).
    """

    sensor: str
    transform: Transform = "raw"


class Robot(abc.ABC):
    """A navigation robot (see the module docstring). Instances are bound to one compiled model."""

    name: ClassVar[str]
    #: the body at the root of the robot's tree; its frame is the agent frame of lidar and reward
    root_body: ClassVar[str] = "agent"
    #: placement keep-out radius of the agent (reference section 6)
    keepout: ClassVar[float] = 0.4
    #: physics steps per env step (reference section 6: 10 for every robot)
    frame_skip: ClassVar[int] = 10
    observation_terms: ClassVar[tuple[SensorTerm, ...]] = tuple(SensorTerm(name) for name in FIXED_SENSORS)

    def __init__(self, prefix: str = "") -> None:
        #: prepended to the name of every element of this robot in the world (see the module docstring)
        self.prefix = prefix
        self._columns: list[tuple[SensorTerm, int, int]] = []  # (term, sensordata address, width)
        #: ids of this robot's actuators in the compiled model, in action order (set by :meth:`bind`)
        self.actuator_ids = np.zeros(0, dtype=np.int64)

    def qualified(self, name: str) -> str:
        """The world's name of this robot's element ``name`` (as :meth:`build` called it)."""
        return self.prefix + name

    def spec_key(self) -> tuple:
        """What :meth:`build` depends on: part of the compiled-model cache key. Robots with build
        options extend it."""
        return (self.name,)

    # ------------------------------------------------------------------ model
    @abc.abstractmethod
    def build(self, spec: mujoco.MjSpec) -> None:
        """Set options and world-wide defaults, add the robot's bodies, actuators and sensors."""

    # ------------------------------------------------------------------ binding
    def bind(self, model: mujoco.MjModel) -> None:
        """Resolve sensor addresses and actuators (and anything else :meth:`set_pose` needs) in ``model``."""
        self._columns = []
        for term in self.observation_terms:
            sensor = model.sensor(self.qualified(term.sensor))
            self._columns.append((term, int(sensor.adr[0]), int(sensor.dim[0])))
        self._observe_plan = _observe_plan(self._columns)
        self.actuator_ids = np.array(
            [u for u in range(model.nu) if model.actuator(u).name.startswith(self.prefix)], dtype=np.int64)

    @property
    def action_size(self) -> int:
        """Number of actuators (action values) of this robot; known once bound."""
        return len(self.actuator_ids)

    @property
    def observation_size(self) -> int:
        return sum(_WIDTH.get(term.transform, width) for term, _, width in self._columns)

    def observation_names(self) -> list[tuple[str, int]]:
        """``(name, width)`` of each observation entry, in order."""
        return [(term.sensor, _WIDTH.get(term.transform, width)) for term, _, width in self._columns]

    # ------------------------------------------------------------------ run time
    @abc.abstractmethod
    def set_pose(self, model: mujoco.MjModel, qpos: np.ndarray, xy: np.ndarray, yaw: np.ndarray) -> None:
        """Write start poses into ``qpos`` rows ``(n, nq)``: root at ``xy`` ``(n, 2)``, heading ``yaw`` ``(n,)``."""

    def randomize_pose(self, qpos: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        """Perturb start poses written by :meth:`set_pose` (rows of ``qpos``, one generator per row).

        Called on every sampled reset, not for layouts given explicitly. Default: no noise (the
        reference's Point, Car, Racecar and Doggo start exactly at rest; the Ant overrides this).
        """

    def observe(self, sensordata: np.ndarray, out: np.ndarray) -> None:
        """Fill ``out`` (``(N, observation_size)``) from ``sensordata`` (``(N, nsensordata)``)."""
        for transform, source, column in self._observe_plan:
            reading = sensordata[:, source]
            if transform == "raw":
                out[:, column] = reading
            elif transform == "z":
                out[:, column] = reading[:, -1]
            elif transform == "sincos":
                out[:, column] = np.sin(reading[:, 0])
                out[:, column + 1] = np.cos(reading[:, 0])
            else:  # rotmat
                _quat_to_mat(reading, out[:, column])

    def is_alive(self, scene: Scene) -> np.ndarray:
        """Which simulators' robots are still alive, ``(N,)`` bool (reference section 5). Default: always
        (a robot that keeps this default is not asked: :attr:`can_die`)."""
        return np.ones(scene.num_envs, dtype=bool)

    @property
    def can_die(self) -> bool:
        """Whether :meth:`is_alive` may say False (a subclass overrides it); the env skips asking otherwise."""
        return type(self).is_alive is not Robot.is_alive


class FreeBodyRobot(Robot):
    """A robot whose root body hangs on a free joint (Car, Racecar, Doggo, Ant): its start pose puts
    the root at ``(x, y, height)``, level and turned by ``yaw`` about the vertical; every other joint
    keeps the model's rest angle (``qpos0``) unless a subclass writes it after ``super().set_pose``."""

    #: height of the root body above the floor at the start
    height: ClassVar[float]

    def bind(self, model: mujoco.MjModel) -> None:
        super().bind(model)
        root = model.joint(self.qualified(self.root_body))
        self._qpos_root = int(root.qposadr[0])  # x, y, z, qw, qx, qy, qz

    def set_pose(self, model: mujoco.MjModel, qpos: np.ndarray, xy: np.ndarray, yaw: np.ndarray) -> None:
        root = self._qpos_root
        qpos[:, root : root + 2] = xy
        qpos[:, root + 2] = self.height
        qpos[:, root + 3 : root + 7] = yaw_quat(yaw)


def _observe_plan(columns: list[tuple[SensorTerm, int, int]]) -> list[tuple[str, slice, int | slice]]:
    """:meth:`Robot.observe`'s steps: ``(transform, sensordata columns, observation column(s))``.

    Raw terms that follow each other in ``sensordata`` as in the observation are one copy (the same
    values; a Point's sensors are then a couple of copies instead of one per sensor).
    """
    plan: list[tuple[str, slice, int | slice]] = []
    column = 0
    for term, address, width in columns:
        source = slice(address, address + width)
        size = _WIDTH.get(term.transform, width)
        if term.transform == "raw":
            if plan and plan[-1][0] == "raw" and plan[-1][1].stop == address and plan[-1][2].stop == column:
                _, previous, target = plan.pop()
                plan.append(("raw", slice(previous.start, source.stop), slice(target.start, column + size)))
            else:
                plan.append(("raw", source, slice(column, column + size)))
        elif term.transform == "rotmat":
            plan.append(("rotmat", source, slice(column, column + size)))
        else:  # z, sincos: single columns
            plan.append((term.transform, source, column))
        column += size
    return plan


def _quat_to_mat(quat: np.ndarray, out: np.ndarray) -> None:
    """Unit quaternions ``(N, 4)`` (w, x, y, z) to row-major rotation matrices written to ``out`` ``(N, 9)``."""
    w, x, y, z = quat.T
    out[:, 0] = 1 - 2 * (y * y + z * z)
    out[:, 1] = 2 * (x * y - w * z)
    out[:, 2] = 2 * (x * z + w * y)
    out[:, 3] = 2 * (x * y + w * z)
    out[:, 4] = 1 - 2 * (x * x + z * z)
    out[:, 5] = 2 * (y * z - w * x)
    out[:, 6] = 2 * (x * z - w * y)
    out[:, 7] = 2 * (y * z + w * x)
    out[:, 8] = 1 - 2 * (x * x + y * y)
