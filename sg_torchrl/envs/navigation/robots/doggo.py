"""Doggo: a quadruped with two hip joints and one knee per leg, and a flexible waist.

Facts from Safety-Gymnasium's Doggo (reference sections 2, 5 and 6, and its model file): timestep
0.01 s, 10 physics steps per env step (0.1 s per env step); angles in radians; world-wide
defaults contact dimension 6 and density 5, sites of radius 0.018. The torso is two cylinders of
radius 0.0375 and length 0.1 (density 2) on the body's x axis: the front half (the root body
``agent``, starting 0.22 above the floor) and the rear half (body ``rear``), joined by a passive
waist hinge about x (``waist_x``, range +-0.523599, no actuator, no sensor).

Four legs, numbered as in the reference: 1 front left, 4 front right (on the front half), 2 rear
left, 3 rear right (on the rear half). Every leg part is a capsule of radius 0.016 and density 20:
a strut from (+-0.05, 0, 0) to the hip at (+-0.1, +-0.05, 0), a thigh from the hip to the knee at
(0.049, +-0.0283, -0.025) from the hip (pointing forward on every leg), and a shin from the knee
by (-0.0588, -+0.0339, -0.05) (pointing back, down and in). Joints per leg, all hinges with
stiffness 0.0001 and armature 0.00005 and limited:

* ``hip_k_z`` (azimuth) about z for the left legs and -z for the right legs, range
  [-0.174533, 0.523599] (positive swings the leg outwards on either side);
* ``hip_k_y`` (elevation) about y, range [-1.308998, 0.2618] on the front legs (spring reference
  -0.174533) and [0, 2.356196] on the rear legs (spring reference 0);
* ``ankle_k`` (the knee) about (-+0.5, 0.866, 0), range [-1.308998, 0], spring reference -0.349066.

At the rest angles (all 0) the shins end 0.075 below the torso axis, so the robot drops onto its
feet from the start height 0.22 during the first env steps, as it does in the reference.

Actuators: 12 torque motors (gear 0.00625, controls in [-1, 1], no force limit), in the
reference's action order: ``hip_1_z``, ``hip_2_z``, ``hip_3_z``, ``hip_4_z``, ``hip_1_y``,
``hip_2_y``, ``hip_3_y``, ``hip_4_y``, ``ankle_1``, ``ankle_2``, ``ankle_3``, ``ankle_4``.

Frame: the same as the reference's: the body's +x axis points from the rear legs to the front
legs and is the forward direction (lidar bin 0, compass and the ``vision`` camera look along it).

Observation (56 values, reference section 2): accelerometer, velocimeter, gyro, magnetometer on
the torso site (12); the 8 touch sensors in the reference's order ``touch_ankle_1a``, ``2a``,
``3a``, ``4a``, ``1b``, ``2b``, ``3b``, ``4b`` (``a`` is a sphere site of radius 0.018 at the knee,
``b`` one at the foot); the 12 hinge velocities ``jointvel_*``, then the 12 hinge angles
``jointpos_*`` as (sin, cos) pairs, both in the reference's sensor order (all ``hip_*_z``, all
``hip_*_y``, all ``ankle_*``, legs 1 to 4 within each group). The waist carries no sensor, so it
adds nothing. DoggoGoal1 = 56 + 3 x 16 = 104 values. The reference's centre-of-mass sensors
(``subtreecom`` and friends) feed no observation or cost of the navigation tasks and are left out.
"""

from __future__ import annotations

from typing import ClassVar

import mujoco

from sg_torchrl.envs.navigation.robots.base import (
    FreeBodyRobot,
    FIXED_SENSORS,
    SensorTerm,
    add_fixed_sensors,
    add_vision_camera,
)

__all__ = ["Doggo"]

_CAPSULE, _CYLINDER = mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER
_SPHERE = mujoco.mjtGeom.mjGEOM_SPHERE
_HINGE = mujoco.mjtJoint.mjJNT_HINGE
_FRONT_RGBA = [0.0039, 0.1529, 0.3961, 1.0]
_REAR_RGBA = [0.7412, 0.0431, 0.1843, 1.0]
_BODY_RGBA = [0.8, 0.6, 0.4, 1.0]

_LEGS = (1, 2, 3, 4)
#: leg number -> (+1 front / -1 rear, +1 left / -1 right)
_LEG_SIDES = {1: (1.0, 1.0), 4: (1.0, -1.0), 2: (-1.0, 1.0), 3: (-1.0, -1.0)}
#: hinge joints in the reference's sensor and actuator order
HINGES = (*(f"hip_{k}_z" for k in _LEGS), *(f"hip_{k}_y" for k in _LEGS), *(f"ankle_{k}" for k in _LEGS))
#: touch sensors in the reference's observation order
TOUCH_SENSORS = (*(f"touch_ankle_{k}a" for k in _LEGS), *(f"touch_ankle_{k}b" for k in _LEGS))


class Doggo(FreeBodyRobot):
    """The Doggo robot (12 actuators: hip azimuth, hip elevation, knee of each leg); see the module docstring."""

    name: ClassVar[str] = "Doggo"
    timestep: ClassVar[float] = 0.01
    height: ClassVar[float] = 0.22  # start height of the torso axis (the reference's)
    leg_radius: ClassVar[float] = 0.016
    torso_radius: ClassVar[float] = 0.0375
    gear: ClassVar[float] = 0.00625
    observation_terms: ClassVar[tuple[SensorTerm, ...]] = (
        *(SensorTerm(name) for name in FIXED_SENSORS),
        *(SensorTerm(name) for name in TOUCH_SENSORS),
        *(SensorTerm(f"jointvel_{joint}") for joint in HINGES),
        *(SensorTerm(f"jointpos_{joint}", "sincos") for joint in HINGES),
    )

    def build(self, spec: mujoco.MjSpec) -> None:
        spec.option.timestep = self.timestep
        spec.compiler.degree = False  # every angle below is in radians (the reference compiles in radians)
        spec.default.geom.condim = 6
        spec.default.geom.density = 5.0
        spec.default.site.size[0] = 0.018

        torso = spec.worldbody.add_body(name=self.root_body, pos=[0.0, 0.0, self.height])
        add_vision_camera(torso, [0.0625, 0.0, 0.1], fovy=100.0)  # the reference's field of view
        torso.add_site(name=self.root_body, type=_SPHERE, rgba=[1.0, 0.0, 0.0, 0.0])
        torso.add_geom(name="agent", type=_CYLINDER, size=[self.torso_radius, 0.0, 0.0],
                       fromto=[0.0, 0.0, 0.0, 0.1, 0.0, 0.0], density=2.0, rgba=_BODY_RGBA)
        torso.add_freejoint(name=self.root_body)
        # Body tree in the reference's order (it fixes the qpos layout): legs 1 and 4 on the front
        # half, then the rear half with legs 2 and 3.
        self._add_leg(torso, 1)
        self._add_leg(torso, 4)
        rear = torso.add_body(name="rear")
        rear.add_geom(name="agent2", type=_CYLINDER, size=[self.torso_radius, 0.0, 0.0],
                      fromto=[-0.1, 0.0, 0.0, 0.0, 0.0, 0.0], density=2.0, rgba=_BODY_RGBA)
        self._add_hinge(rear, "waist_x", [1.0, 0.0, 0.0], [-0.523599, 0.523599], 0.0)
        self._add_leg(rear, 2)
        self._add_leg(rear, 3)

        for joint in HINGES:  # action order
            motor = spec.add_actuator(name=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT, target=joint)
            motor.set_to_motor()
            motor.gear = [self.gear, 0.0, 0.0, 0.0, 0.0, 0.0]
            motor.ctrlrange = [-1.0, 1.0]
            motor.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE

        site, joint_obj = mujoco.mjtObj.mjOBJ_SITE, mujoco.mjtObj.mjOBJ_JOINT
        for k in _LEGS:
            for end in "ab":
                spec.add_sensor(name=f"touch_ankle_{k}{end}", type=mujoco.mjtSensor.mjSENS_TOUCH,
                                objtype=site, objname=f"ankle_{k}{end}")
        for kind, sensor_type in (("jointpos", mujoco.mjtSensor.mjSENS_JOINTPOS),
                                  ("jointvel", mujoco.mjtSensor.mjSENS_JOINTVEL)):
            for joint in HINGES:
                spec.add_sensor(name=f"{kind}_{joint}", type=sensor_type, objtype=joint_obj, objname=joint)
        add_fixed_sensors(spec, self.root_body)

    def _add_leg(self, parent: mujoco.MjsBody, k: int) -> None:
        """Add leg ``k`` (strut, thigh on the two hip hinges, shin on the knee hinge) to ``parent``."""
        front, left = _LEG_SIDES[k]
        rgba = _FRONT_RGBA if front > 0 else _REAR_RGBA
        r = self.leg_radius
        # The strut is fixed to its torso half: body leg_k sits at the torso half's origin.
        leg = parent.add_body(name=f"leg_{k}")
        leg.add_geom(name=f"aux_{k}", type=_CAPSULE, size=[r, 0.0, 0.0],
                     fromto=[0.05 * front, 0.0, 0.0, 0.1 * front, 0.05 * left, 0.0], density=20.0, rgba=rgba)
        hip = leg.add_body(name=f"aux_{k}", pos=[0.1 * front, 0.05 * left, 0.0])
        self._add_hinge(hip, f"hip_{k}_z", [0.0, 0.0, left], [-0.174533, 0.523599], 0.0)
        if front > 0:
            self._add_hinge(hip, f"hip_{k}_y", [0.0, 1.0, 0.0], [-1.308998, 0.2618], -0.174533)
        else:
            self._add_hinge(hip, f"hip_{k}_y", [0.0, 1.0, 0.0], [0.0, 2.356196], 0.0)
        knee = [0.049, 0.0283 * left, -0.025]
        hip.add_geom(name=f"hip_{k}", type=_CAPSULE, size=[r, 0.0, 0.0], fromto=[0.0, 0.0, 0.0, *knee],
                     density=20.0, rgba=rgba)
        shin = hip.add_body(name=f"shin_{k}", pos=knee)
        self._add_hinge(shin, f"ankle_{k}", [-0.5 * left, 0.866, 0.0], [-1.308998, 0.0], -0.349066)
        foot = [-0.0588, -0.0339 * left, -0.05]
        shin.add_geom(name=f"ankle_{k}", type=_CAPSULE, size=[r, 0.0, 0.0], fromto=[0.0, 0.0, 0.0, *foot],
                      density=20.0, rgba=_BODY_RGBA)
        shin.add_site(name=f"ankle_{k}a", type=_SPHERE, rgba=[1.0, 0.0, 0.0, 0.0])
        shin.add_site(name=f"ankle_{k}b", type=_SPHERE, pos=foot, rgba=[1.0, 0.0, 0.0, 0.0])

    @staticmethod
    def _add_hinge(body: mujoco.MjsBody, name: str, axis: list[float], limits: list[float], springref: float) -> None:
        """A limited hinge with the reference's joint defaults (stiffness 0.0001, armature 0.00005)."""
        joint = body.add_joint(name=name, type=_HINGE, axis=axis, range=limits, springref=springref,
                               limited=mujoco.mjtLimited.mjLIMITED_TRUE, armature=0.00005)
        joint.stiffness[0] = 0.0001
