"""Ant: a small four-legged walker (a sphere torso with four two-joint legs), the one robot that can fall.

Facts from Safety-Gymnasium's Ant (reference sections 2, 5 and 6, its model file and agent class):
timestep 0.01 s with the RK4 integrator, 10 physics steps per env step (0.1 s). World-wide defaults:
contact dimension 6, density 5, joints armature 1, damping 1 and limited; the free root joint has no
armature and no damping. The torso is a sphere of radius 0.0625 whose centre starts 0.18 above the
floor; the sensor site sits 0.02 below the centre. Four legs leave the torso along the diagonals
``d = (+1, +1), (-1, +1), (-1, -1), (+1, -1)`` (legs 1 to 4, counter-clockwise): a fixed capsule from
the centre to ``0.05 d``, then the thigh (hinge ``hip_k`` about +z, range +-0.70 rad, capsule to a
further ``0.05 d``), then the foot (hinge ``ankle_k`` about a horizontal axis across the leg, capsule
of length ``0.1 d``); every capsule has radius 0.02. Ankle ``k`` turns about ``s_k (z x d)`` with
``s = (+1, -1, -1, +1)`` and its range is ``s_k [0.52, 1.74]`` rad, so on every leg the allowed angles
bend the foot downwards (``s_k pi / 2`` points it straight down). Eight torque motors, gear 150,
controls in [-1, 1] (no torque limit). The whole ant weighs 0.0142 kg; with armature 1 on every leg
joint its legs are driven like heavy rotors. Stepped side by side with the reference's model file
under the same random controls, this model's state agreed to within 1e-9 over 40 env steps (the
motion is chaotic after that).

Action order follows Safety-Gymnasium: ``hip_1, ankle_1, hip_2, ankle_2, hip_3, ankle_3, hip_4,
ankle_4``. A positive hip control swings its leg counter-clockwise seen from above; a control of sign
``s_k`` on ankle ``k`` pushes its foot down (lifting the torso), the opposite sign lifts the foot.

Start pose: torso at 0.18 (the reference's model height), level, turned by the layout's yaw; hips at 0
and ankles at ``s_k pi / 2`` (feet pointing down), the reference's rest pose. The reference adds
uniform noise in [-0.1, 0.1] to each of the eight leg angles at every reset, and so does
:meth:`Ant.randomize_pose` (from each simulator's generator, after its layout is drawn); a layout
given explicitly (``NavigationEnv.set_layout``) starts from the exact rest pose.

Termination (reference section 5): the ant is dead, and its episode terminates, once the torso centre
is at 0.08 or lower (:meth:`Ant.is_alive`). Standing it is at about 0.16 (0.09 with its feet fully
raised), so in practice this means it has turned over (on its back the torso rests at 0.0625).

Frame: the same body frame as the reference's model. The ant has no built-in front (its legs are four
times symmetric); +x, the diagonal between legs 1 and 4, is its forward axis here, where lidar bin 0
looks, as in the reference. The ``vision`` camera is the reference's too: level, 0.05 above and
0.05 along +y from the torso centre, looking along +y (to the left of lidar bin 0), 45-degree view.

Observation (40 values, reference section 2): accelerometer, velocimeter, gyro, magnetometer on the
torso site (12); the eight leg-joint velocities ``hip_1_vel, ankle_1_vel, ..., ankle_4_vel`` (8);
``agent_pos``, the height of the torso site above the floor (1); ``agent_qvel`` (3); then the eight
leg-joint angles ``hip_1, ankle_1, ..., ankle_4`` as (sin, cos) pairs (16). AntGoal1 = 40 + 3 x 16 = 88.
Note on ``agent_qvel``: reference/safety_gymnasium_semantics.md calls it the free joint's linear
velocity, but Safety-Gymnasium's model file defines it as a frame angular-velocity sensor on the torso
site, i.e. the torso's angular velocity in world axes (the gyro reads the same vector in body axes).
This model reproduces the model file, since the values, not the name, are what a policy sees.

Multi-agent variant: Safety-Gymnasium's multi-agent navigation tasks (MultiGoal) load their own
``ant.xml``, identical but for a density of 50000 on the four foot capsules (about 10.6 kg per foot
against 0.01 kg for the rest of the ant). ``Ant(foot_density=50000.0)`` builds that variant; the
task asks for it (``Task.robot_options``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, ClassVar

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.robots.base import (
    FreeBodyRobot,
    FIXED_SENSORS,
    SensorTerm,
    add_fixed_sensors,
    add_vision_camera,
)

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.world import Scene

__all__ = ["Ant"]

_SPHERE, _CAPSULE = mujoco.mjtGeom.mjGEOM_SPHERE, mujoco.mjtGeom.mjGEOM_CAPSULE
_HINGE = mujoco.mjtJoint.mjJNT_HINGE
_LIMITED = mujoco.mjtLimited.mjLIMITED_TRUE
_TAN = [0.8, 0.6, 0.4, 1.0]  # the reference's default geom colour (set per geom: not a world default)
_FOOT_RGBA = [0.8, 0.5, 0.3, 1.0]
_FRONT_RGBA = [0.0039, 0.1529, 0.3961, 1.0]  # legs 1 and 2 (the reference's "front" pair)
_BACK_RGBA = [0.7412, 0.0431, 0.1843, 1.0]  # legs 3 and 4

#: leg directions d_k (unnormalised diagonals), legs 1..4 counter-clockwise from +x+y
_LEG_DIRECTIONS = ((1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0))
#: s_k: the sign that bends each ankle downwards (axis s_k (z x d_k), range s_k [0.52, 1.74])
_ANKLE_SIGNS = (1.0, -1.0, -1.0, 1.0)
_LEGS = (1, 2, 3, 4)
#: actuated joints in action order (reference actuator order)
_JOINTS = tuple(f"{part}_{k}" for k in _LEGS for part in ("hip", "ankle"))


class Ant(FreeBodyRobot):
    """The Ant robot (8 actuators: hip and ankle torque of each leg); see the module docstring."""

    name: ClassVar[str] = "Ant"
    timestep: ClassVar[float] = 0.01
    height: ClassVar[float] = 0.18  # torso centre above the floor at the start (reference model)
    site_offset: ClassVar[float] = -0.02  # sensor site below the torso centre
    torso_radius: ClassVar[float] = 0.0625
    limb_radius: ClassVar[float] = 0.02
    hip_range: ClassVar[float] = 0.70
    ankle_range: ClassVar[tuple[float, float]] = (0.52, 1.74)  # magnitude; signed by s_k per leg
    gear: ClassVar[float] = 150.0
    #: the torso centre's height at or below which the ant is dead (reference section 5)
    death_height: ClassVar[float] = 0.08
    reset_noise: ClassVar[float] = 0.1  # uniform spawn noise of each leg angle (rad), reference agent class
    observation_terms: ClassVar[tuple[SensorTerm, ...]] = (
        *(SensorTerm(name) for name in FIXED_SENSORS),
        *(SensorTerm(f"{joint}_vel") for joint in _JOINTS),
        SensorTerm("agent_pos", "z"),
        SensorTerm("agent_qvel"),
        *(SensorTerm(joint, "sincos") for joint in _JOINTS),
    )

    def __init__(self, prefix: str = "", *, foot_density: float | None = None) -> None:
        """``foot_density``: density of the four foot capsules (default: the world default, 5). The
        multi-agent tasks' Ant has 50000 (Safety-Gymnasium's multi-agent ``ant.xml``)."""
        super().__init__(prefix)
        self.foot_density = foot_density

    def spec_key(self) -> tuple:
        return super().spec_key() if self.foot_density is None else (*super().spec_key(), self.foot_density)

    def build(self, spec: mujoco.MjSpec) -> None:
        spec.option.timestep = self.timestep
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_RK4
        spec.compiler.degree = False  # joint ranges below are in radians (the reference compiles in radians)
        spec.default.geom.condim = 6
        spec.default.geom.density = 5.0
        spec.default.joint.armature = 1.0
        spec.default.joint.damping[0] = 1.0
        spec.default.joint.limited = _LIMITED
        spec.default.site.size[0] = 0.032

        torso = spec.worldbody.add_body(name=self.root_body, pos=[0.0, 0.0, self.height])
        # The reference's: level, looking along the body's +y axis (module docstring).
        add_vision_camera(torso, [0.0, 0.05, 0.05], xyaxes=(1.0, 0.0, 0.0, 0.0, 0.0, 1.0), fovy=45.0)
        free = torso.add_freejoint(name=self.root_body)
        free.armature, free.damping[0] = 0.0, 0.0  # the leg joints' defaults do not apply to the root
        free.limited = mujoco.mjtLimited.mjLIMITED_FALSE
        torso.add_site(name=self.root_body, type=_SPHERE, pos=[0.0, 0.0, self.site_offset], rgba=[1.0, 0.0, 0.0, 0.1])
        torso.add_geom(name="torso", type=_SPHERE, size=[self.torso_radius, 0.0, 0.0], rgba=_TAN)
        for k, (dx, dy), sign in zip(_LEGS, _LEG_DIRECTIONS, _ANKLE_SIGNS):
            self._add_leg(torso, k, dx, dy, sign)

        for joint in _JOINTS:  # action order
            motor = spec.add_actuator(name=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT, target=joint)
            motor.set_to_motor()
            motor.gear = [self.gear, 0.0, 0.0, 0.0, 0.0, 0.0]
            motor.ctrlrange = [-1.0, 1.0]
            motor.ctrllimited = _LIMITED

        add_fixed_sensors(spec, self.root_body)
        sensor, joint_obj, site_obj = mujoco.mjtSensor, mujoco.mjtObj.mjOBJ_JOINT, mujoco.mjtObj.mjOBJ_SITE
        for joint in _JOINTS:
            spec.add_sensor(name=f"{joint}_vel", type=sensor.mjSENS_JOINTVEL, objtype=joint_obj, objname=joint)
        # The reference's free-joint entries: height of the torso site, angular velocity in world axes.
        spec.add_sensor(name="agent_pos", type=sensor.mjSENS_FRAMEPOS, objtype=site_obj, objname=self.root_body)
        spec.add_sensor(name="agent_qvel", type=sensor.mjSENS_FRAMEANGVEL, objtype=site_obj, objname=self.root_body)
        for joint in _JOINTS:
            spec.add_sensor(name=joint, type=sensor.mjSENS_JOINTPOS, objtype=joint_obj, objname=joint)

    def _add_leg(self, torso: mujoco.MjsBody, k: int, dx: float, dy: float, sign: float) -> None:
        """Leg ``k`` along the diagonal ``(dx, dy)``: fixed stub, thigh on ``hip_k``, foot on ``ankle_k``.

        The stub is welded to the torso (the reference puts it in a joint-less child body, which
        MuJoCo treats the same way); thigh and foot each get their own body and hinge.
        """
        r, rgba = self.limb_radius, (_FRONT_RGBA if k in (1, 2) else _BACK_RGBA)
        step = [0.05 * dx, 0.05 * dy, 0.0]
        torso.add_geom(name=f"stub_{k}", type=_CAPSULE, size=[r, 0.0, 0.0], fromto=[0.0, 0.0, 0.0, *step], rgba=rgba)
        thigh = torso.add_body(name=f"thigh_{k}", pos=step)
        thigh.add_joint(name=f"hip_{k}", type=_HINGE, axis=[0.0, 0.0, 1.0], range=[-self.hip_range, self.hip_range])
        thigh.add_geom(name=f"thigh_{k}", type=_CAPSULE, size=[r, 0.0, 0.0], fromto=[0.0, 0.0, 0.0, *step], rgba=rgba)
        foot = thigh.add_body(name=f"foot_{k}", pos=step)
        low, high = self.ankle_range
        foot.add_joint(name=f"ankle_{k}", type=_HINGE, axis=[-sign * dy, sign * dx, 0.0],  # s_k (z x d_k)
                       range=sorted([sign * low, sign * high]))
        density = {} if self.foot_density is None else {"density": self.foot_density}
        foot.add_geom(name=f"foot_{k}", type=_CAPSULE, size=[r, 0.0, 0.0],
                      fromto=[0.0, 0.0, 0.0, 0.1 * dx, 0.1 * dy, 0.0],
                      rgba=_FOOT_RGBA if k in (1, 4) else _TAN, **density)

    def bind(self, model: mujoco.MjModel) -> None:
        super().bind(model)
        self._qpos_legs = np.array([int(model.joint(self.qualified(joint)).qposadr[0]) for joint in _JOINTS])
        rest = np.zeros(len(_JOINTS))
        rest[1::2] = np.array(_ANKLE_SIGNS) * np.pi / 2  # ankles: feet straight down
        self._rest_angles = rest

    def set_pose(self, model: mujoco.MjModel, qpos: np.ndarray, xy: np.ndarray, yaw: np.ndarray) -> None:
        super().set_pose(model, qpos, xy, yaw)
        qpos[:, self._qpos_legs] = self._rest_angles

    def randomize_pose(self, qpos: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        """The reference's spawn noise: each of the eight leg angles moves by a uniform draw in
        [-0.1, 0.1] rad around the rest pose, from the simulator's own generator."""
        for row, rng in zip(qpos, rngs):
            row[self._qpos_legs] += rng.uniform(-self.reset_noise, self.reset_noise, size=len(self._qpos_legs))

    def is_alive(self, scene: Scene) -> np.ndarray:
        """Alive while the torso centre is above :attr:`death_height` (0.08), ``(N,)`` bool."""
        return scene.agent_pos()[:, 2] > self.death_height
