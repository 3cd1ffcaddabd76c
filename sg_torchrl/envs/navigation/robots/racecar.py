"""Racecar: a four-wheeled car with steered front wheels and a driven rear axle.

Facts from Safety-Gymnasium's Racecar (reference section 6 and its model file, which builds the
car from meshes): timestep 0.004 s with the RK4 integrator, 10 physics steps per env step;
world-wide defaults density 5, contact dimension 6, joint damping 0.001. The chassis (a body on a
free joint whose origin sits at axle height, 0.05 above the floor) carries:

* a chassis shell 0.405 long (x from -0.2 to 0.205), 0.2 wide and 0.06 high, and a front bumper
  (half-sizes 0.0165 x 0.0875 x 0.015, 0.23 ahead and 0.04 up), both weighing what density 5 gives
  (0.024 and 0.0009 kg);
* two welded differential blocks without geometry, on the centre line 0.16 behind and 0.16 ahead
  of the origin: 0.0637 kg ring plus 0.056 kg parts (two behind, four ahead), each part with
  principal inertia 0.04411 about the vertical and 0.02467 about the horizontal axes. These
  inertias are far larger than the masses suggest; they make the car slow to yaw and hard to tip,
  and they are kept because they shape the car's dynamics;
* a rear axle 0.16 behind the origin on one hinge about the body's y axis (both rear wheels turn
  together: the reference's differential joints are disabled), with two side gears of 0.39655 kg
  0.1052 to either side (principal inertia 0.02565 about x, 0.02508 about y, 0.04509 about z) and
  two wheels (radius 0.05, width 0.045, centres 0.1225 to either side);
* two steering knuckles 0.165 ahead of the origin, 0.1 to either side (0.1 kg, inertia 4e-6), each
  on a hinge about the vertical limited to +-0.785 rad, kept at the same angle by a joint equality;
  on each a free-spinning front wheel (0.34055 kg, inertia 0.00041226 about its axle and 0.00026046
  about the other two axes, radius 0.05 and width 0.045, its inner face at the knuckle). Both
  knuckles turn the same way: parallel steering, not true Ackermann geometry.

The whole car weighs 2.163 kg. Front wheels do not collide with the chassis (the reference excludes
that pair; the rear wheels are the chassis's children, which MuJoCo already excludes).

Action order follows Safety-Gymnasium (its actuators ``diff_ring`` then ``steering_hinge``):
``action[0]`` in [-20, 20] is the target angular velocity (rad/s) of the rear axle, a velocity servo
(kv 1, torque limited to +-1), so 20 approaches 1 m/s forward and -20 reverses; ``action[1]`` in
[-0.785, 0.785] is the target steering angle (rad) of the front wheels, a position servo on the
left knuckle (kp 1, torque limited to +-1): positive steers left (counter-clockwise seen from
above), so driving forward with positive steering turns the car counter-clockwise. Here (20, 0)
drives about 0.43 m in the first second and 1 m/s after that, as the reference model does.

Frame: the body's +x axis is the direction positive ``action[0]`` drives, and the reference model
uses the same frame, so lidar bin 0 and the compass look ahead and the sensors read the same axes.

Differences to the reference model, all without effect on sizes and none intended on dynamics:
primitive geoms replace its meshes (a box for the chassis shell, whose mesh is nearly that box,
cylinders for the wheels), its differential gears are lumped into the welded blocks and the axle
above (the same total mass and inertia about the same points), and the geometry-only parts (visual
meshes, a small collidable cylinder inside the chassis) are left out. Its ``subtreecom``,
``subtreelinvel`` and ``subtreeangmom`` sensors are not observed and not built. The ``vision``
camera is the reference's: 0.05 above the origin at x = 0.2, just behind the front bumper, level,
with a 45-degree view. The bumper, 13.5 mm ahead, is nearer than the near clipping plane of the
reference's extent at levels 1 and 2 and is not drawn, as there (at level 0 it is; see
:func:`~sg_torchrl.envs.navigation.world.world_extent`).

Observation (12 values, reference section 2): accelerometer, velocimeter, gyro, magnetometer on the
site 0.02 ahead of the origin. The car's hinges carry no sensors, so they add nothing:
RacecarGoal1 = 12 + 3 x 16 = 60 values.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.robots.base import FreeBodyRobot, add_fixed_sensors, add_vision_camera

__all__ = ["Racecar"]

_BOX, _CYLINDER, _SPHERE = mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_SPHERE
_HINGE = mujoco.mjtJoint.mjJNT_HINGE
_BODY_RGBA = [0.7412, 0.0431, 0.1843, 1.0]
_TRIM_RGBA = [0.0039, 0.1529, 0.3961, 1.0]
_TYRE_RGBA = [0.1, 0.1, 0.1, 1.0]

# A point part: (mass, position in the parent body's frame, principal inertia about x, y, z).
Part = tuple[float, Sequence[float], Sequence[float]]
_GEAR_INERTIA = (0.02467, 0.02467, 0.04411)  # every differential ring and small gear
_RING: Part = (0.0637, (0.0, 0.0, 0.0), _GEAR_INERTIA)
_GEAR: Part = (0.056, (0.0, 0.0, 0.0), _GEAR_INERTIA)
_REAR_DIFFERENTIAL: tuple[Part, ...] = (_RING, _GEAR, _GEAR)
_FRONT_DIFFERENTIAL: tuple[Part, ...] = (_RING, _GEAR, _GEAR, _GEAR, _GEAR)
_SIDE_GEAR_INERTIA = (0.0256521, 0.0250823, 0.0450921)
_REAR_AXLE: tuple[Part, ...] = ((0.39655, (0.0, 0.1052012, 0.0), _SIDE_GEAR_INERTIA),
                                (0.39655, (0.0, -0.1052012, 0.0), _SIDE_GEAR_INERTIA))
# The welded differential blocks: (body name, x of its centre, parts).
_DIFFERENTIALS = (("rear_differential", -0.16, _REAR_DIFFERENTIAL), ("front_differential", 0.16, _FRONT_DIFFERENTIAL))


def _set_inertial(body: mujoco.MjsBody, parts: Sequence[Part]) -> None:
    """Give ``body`` the combined mass and inertia of ``parts``, whose principal axes are the body's.

    Why: the reference model spreads these masses over several rigidly joined bodies; one body with
    their lumped inertia (parallel-axis theorem about the common centre of mass) moves the same way.
    """
    masses = np.array([mass for mass, _, _ in parts])
    positions = np.array([pos for _, pos, _ in parts], dtype=np.float64)
    centre = masses @ positions / masses.sum()
    inertia = np.zeros(3)
    for mass, pos, principal in parts:
        offset = np.asarray(pos) - centre
        if np.count_nonzero(offset) > 1:  # would add products of inertia: not a diagonal inertia any more
            raise ValueError(f"parts must be offset from their centre of mass along one axis, got {offset}")
        inertia += np.asarray(principal) + mass * (offset @ offset - offset**2)  # diagonal of m(|r|^2 I - r r^T)
    body.explicitinertial = True
    body.mass = float(masses.sum())
    body.ipos = centre.tolist()
    body.inertia = inertia.tolist()


class Racecar(FreeBodyRobot):
    """The Racecar robot (2 actuators: rear-axle velocity, front steering angle); see the module docstring."""

    name: ClassVar[str] = "Racecar"
    timestep: ClassVar[float] = 0.004
    height: ClassVar[float] = 0.05  # chassis origin above the floor: the axle height, wheels touch it
    wheel_radius: ClassVar[float] = 0.05
    wheel_width: ClassVar[float] = 0.045
    axle_x: ClassVar[tuple[float, float]] = (-0.16, 0.165)  # rear axle, front knuckles
    steering_limit: ClassVar[float] = 0.785  # rad, knuckle range and steering control range
    speed_limit: ClassVar[float] = 20.0  # rad/s, rear-axle velocity control range

    def build(self, spec: mujoco.MjSpec) -> None:
        spec.option.timestep = self.timestep
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_RK4
        spec.default.geom.condim = 6
        spec.default.geom.density = 5.0
        spec.default.joint.damping[0] = 0.001
        spec.default.site.size[0] = 0.032

        chassis = spec.worldbody.add_body(name=self.root_body, pos=[0.0, 0.0, self.height])
        # The reference's: level, looking along +x, just behind the front bumper (module docstring).
        add_vision_camera(chassis, [0.2, 0.0, 0.05], xyaxes=(0.0, -1.0, 0.0, 0.0, 0.0, 1.0), fovy=45.0)
        chassis.add_freejoint(name=self.root_body)  # free joints are undamped
        chassis.add_site(name=self.root_body, type=_SPHERE, pos=[0.02, 0.0, 0.0], rgba=[1.0, 0.0, 0.0, 0.1])
        chassis.add_geom(name=self.root_body, type=_BOX, pos=[0.0025, 0.0, 0.0], size=[0.2025, 0.1, 0.03],
                         rgba=_BODY_RGBA)
        chassis.add_geom(name="front_bumper", type=_BOX, pos=[0.23, 0.0, 0.04], size=[0.0165, 0.0875, 0.015],
                         rgba=_TRIM_RGBA)
        for name, x, parts in _DIFFERENTIALS:
            _set_inertial(chassis.add_body(name=name, pos=[x, 0.0, 0.0]), parts)  # welded: no joint
        rear_x, front_x = self.axle_x

        # Rear axle: positive velocity about +y rolls the car towards +x.
        axle = chassis.add_body(name="rear_axle", pos=[rear_x, 0.0, 0.0])
        axle.add_joint(name="rear_axle", type=_HINGE, axis=[0.0, 1.0, 0.0])
        _set_inertial(axle, _REAR_AXLE)
        inner, outer = 0.1, 0.1 + self.wheel_width
        for side, sign in (("left", 1.0), ("right", -1.0)):
            axle.add_geom(name=f"rear_{side}_wheel", type=_CYLINDER, size=[self.wheel_radius, 0.0, 0.0],
                          fromto=[0.0, inner * sign, 0.0, 0.0, outer * sign, 0.0], density=0.0, rgba=_TYRE_RGBA)

        # Front: a knuckle steering about the vertical, a free wheel spinning about the knuckle's y axis.
        # Joint ranges are read in the compiler's angle unit: degrees unless the spec says otherwise.
        limit = float(np.degrees(self.steering_limit)) if spec.compiler.degree else self.steering_limit
        for side, sign in (("left", 1.0), ("right", -1.0)):
            knuckle = chassis.add_body(name=f"{side}_steering", pos=[front_x, inner * sign, 0.0])
            knuckle.add_joint(name=f"{side}_steering", type=_HINGE, axis=[0.0, 0.0, 1.0], range=[-limit, limit],
                              limited=mujoco.mjtLimited.mjLIMITED_TRUE)
            _set_inertial(knuckle, ((0.1, (0.0, 0.0, 0.0), (4e-6, 4e-6, 4e-6)),))
            wheel = knuckle.add_body(name=f"front_{side}_wheel")
            wheel.add_joint(name=f"front_{side}_wheel", type=_HINGE, axis=[0.0, 1.0, 0.0])
            _set_inertial(wheel, ((0.34055, (0.0, 0.0225 * sign, 0.0), (0.00026046, 0.00041226, 0.00026046)),))
            wheel.add_geom(name=f"front_{side}_wheel", type=_CYLINDER, size=[self.wheel_radius, 0.0, 0.0],
                           fromto=[0.0, 0.0, 0.0, 0.0, self.wheel_width * sign, 0.0], density=0.0, rgba=_TYRE_RGBA)
            spec.add_exclude(bodyname1=self.root_body, bodyname2=f"front_{side}_wheel")
        # The right knuckle follows the left one (only the left is actuated): right = 0 + 1 * left.
        spec.add_equality(type=mujoco.mjtEq.mjEQ_JOINT, name1="right_steering", name2="left_steering",
                          data=[0.0, 1.0] + [0.0] * 10)

        drive = spec.add_actuator(name="drive", trntype=mujoco.mjtTrn.mjTRN_JOINT, target="rear_axle")
        drive.set_to_velocity(kv=1.0)
        drive.ctrlrange = [-self.speed_limit, self.speed_limit]
        steering = spec.add_actuator(name="steering", trntype=mujoco.mjtTrn.mjTRN_JOINT, target="left_steering")
        steering.set_to_position(kp=1.0)
        steering.ctrlrange = [-self.steering_limit, self.steering_limit]
        for actuator in (drive, steering):  # action order
            actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
            actuator.forcerange = [-1.0, 1.0]
            actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE

        add_fixed_sensors(spec, self.root_body)
