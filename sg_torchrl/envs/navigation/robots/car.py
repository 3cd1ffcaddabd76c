"""Car: a two-wheeled differential-drive car with a passive ball caster.

Facts from Safety-Gymnasium's Car (reference sections 2 and 6, and its model file): timestep
0.004 s, 10 physics steps per env step; world-wide defaults density 5, contact dimension 6, joint
damping 0.001. A free-floating chassis box (half-sizes 0.1 x 0.1 x 0.05, body 0.1 above the floor)
with bumpers; two wheels (cylinders of radius 0.05 and width 0.05 on hinge joints) on one axle 0.1
behind the centre, 0.13 to either side; a sphere of radius 0.05 on a ball joint 0.1 ahead of the
centre (Safety-Gymnasium calls it ``rear``, and so do the sensor names). Two torque motors (gear
1) drive the wheels, controls in [-1, 1], torque limited to +-0.02. The whole car weighs 0.03 kg.

Action order follows Safety-Gymnasium: ``action[0]`` drives the right wheel, ``action[1]`` the
left wheel (its motors are named ``left`` and ``right`` by their position in its model frame).
So ``(1, 1)`` drives forward (0.76 m/s and 0.74 m after one second), ``(-1, -1)`` backward, ``(1, -1)``
turns counter-clockwise on the spot and ``(-1, 1)`` clockwise.

Frame: the body's +x axis is the direction ``(1, 1)`` drives, as for Point, so lidar bin 0 and the
compass look ahead. Safety-Gymnasium's Car model is the same car turned by 90 degrees: it drives
along its body's -y axis, so there lidar bin 0 points to the car's left and the accelerometer,
velocimeter and gyro read the same vectors in axes turned by 90 degrees. Sizes, masses, contacts
and dynamics are unchanged.

Observation (24 values, reference section 2): accelerometer, velocimeter, gyro, magnetometer on
the chassis site (12), then the caster's ball-joint angular velocity ``ballangvel_rear`` (3), then
its orientation ``ballquat_rear`` as a row-major 3x3 rotation matrix (9). The wheel hinges carry no
sensors in the reference model (its wheel ``jointvel`` sensors are commented out), so they add
nothing: CarGoal1 = 24 + 3 x 16 = 72 values.
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

__all__ = ["Car"]

_BOX, _CYLINDER, _SPHERE = mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_SPHERE
_BODY_RGBA = [0.7412, 0.0431, 0.1843, 1.0]
_TRIM_RGBA = [0.0039, 0.1529, 0.3961, 1.0]


class Car(FreeBodyRobot):
    """The Car robot (2 actuators: right and left wheel torque); see the module docstring."""

    name: ClassVar[str] = "Car"
    timestep: ClassVar[float] = 0.004
    height: ClassVar[float] = 0.1  # chassis centre above the floor: wheels and caster touch it
    wheel_radius: ClassVar[float] = 0.05
    observation_terms: ClassVar[tuple[SensorTerm, ...]] = (
        *(SensorTerm(name) for name in FIXED_SENSORS),
        SensorTerm("ballangvel_rear"),
        SensorTerm("ballquat_rear", "rotmat"),
    )

    def build(self, spec: mujoco.MjSpec) -> None:
        spec.option.timestep = self.timestep
        spec.default.geom.condim = 6
        spec.default.geom.density = 5.0
        spec.default.joint.damping[0] = 0.001
        spec.default.site.size[0] = 0.032

        chassis = spec.worldbody.add_body(name=self.root_body, pos=[0.0, 0.0, self.height])
        add_vision_camera(chassis, [-0.1, 0.0, 0.2], fovy=45.0)  # the reference's pose in this frame, its default fovy
        chassis.add_freejoint(name=self.root_body)  # free joints are undamped
        chassis.add_site(name=self.root_body, type=_SPHERE, rgba=[1.0, 0.0, 0.0, 0.1])
        chassis.add_geom(name="agent", type=_BOX, size=[0.1, 0.1, 0.05], rgba=_BODY_RGBA)
        for name, pos, size in (
            ("back_bumper", [-0.15, 0.0, 0.0], [0.01, 0.1, 0.05]),
            ("back_connector", [-0.125, 0.0, 0.0], [0.025, 0.01, 0.03]),
            ("front_bumper", [0.165, 0.0, 0.0], [0.01, 0.05, 0.05]),
            ("front_connector", [0.13, 0.0, 0.04], [0.03, 0.05, 0.01]),
        ):
            chassis.add_geom(name=name, type=_BOX, pos=pos, size=size, rgba=_TRIM_RGBA)

        # Wheels: hinge about the body's y axis, so a positive torque rolls the car towards +x.
        # Each cylinder spans 0.005..0.055 outwards from its body, which sits 0.1 to the side.
        for name, side in (("right", -1.0), ("left", 1.0)):
            wheel = chassis.add_body(name=name, pos=[-0.1, 0.1 * side, -0.05])
            wheel.add_joint(name=name, type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0.0, 1.0, 0.0])
            wheel.add_geom(name=name, type=_CYLINDER, size=[self.wheel_radius, 0.0, 0.0],
                           fromto=[0.0, 0.005 * side, 0.0, 0.0, 0.055 * side, 0.0], rgba=_BODY_RGBA)
        caster = chassis.add_body(name="rear", pos=[0.1, 0.0, -0.05])
        caster.add_joint(name="rear", type=mujoco.mjtJoint.mjJNT_BALL)
        caster.add_geom(name="rear", type=_SPHERE, size=[self.wheel_radius, 0.0, 0.0], rgba=_BODY_RGBA)

        for name in ("right", "left"):  # action order
            motor = spec.add_actuator(name=name, trntype=mujoco.mjtTrn.mjTRN_JOINT, target=name)
            motor.set_to_motor()
            motor.gear = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]
            motor.ctrlrange = [-1.0, 1.0]
            motor.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
            motor.forcerange = [-0.02, 0.02]
            motor.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE

        add_fixed_sensors(spec, self.root_body)
        joint = mujoco.mjtObj.mjOBJ_JOINT
        spec.add_sensor(name="ballangvel_rear", type=mujoco.mjtSensor.mjSENS_BALLANGVEL, objtype=joint, objname="rear")
        spec.add_sensor(name="ballquat_rear", type=mujoco.mjtSensor.mjSENS_BALLQUAT, objtype=joint, objname="rear")
