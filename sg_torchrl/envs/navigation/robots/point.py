"""Point: a sphere with a heading marker that moves in the plane.

Facts from Safety-Gymnasium's Point (reference section 4 and its model file): timestep 0.002 s;
the body (a sphere of radius 0.1 with a 0.05 half-size box 0.1 ahead marking the heading, density
1) slides in x and y (damping 0.01) and turns about z (damping 0.005); action[0] is a force along
the body's forward (+x) axis (motor on the body site, gear 0.3), action[1] a yaw-velocity
actuator on the turning joint (gear 0.3, kv 1); both take controls in [-1, 1] and saturate at
0.05 before the gear. World-wide defaults: contact dimension 6, density 1, joint damping 0.001.
Sensors: accelerometer, velocimeter, gyro, magnetometer on the body site (12 values). The three
root joints carry no sensors, so the robot part of the observation is exactly those 12 values.
"""

from __future__ import annotations

from typing import ClassVar

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.robots.base import Robot, add_fixed_sensors, add_vision_camera

__all__ = ["Point"]


class Point(Robot):
    """The Point robot (2 actuators: forward force, yaw velocity)."""

    name: ClassVar[str] = "Point"
    timestep: ClassVar[float] = 0.002
    height: ClassVar[float] = 0.1  # root body height: the sphere rests on the floor

    def build(self, spec: mujoco.MjSpec) -> None:
        spec.option.timestep = self.timestep
        spec.default.geom.condim = 6
        spec.default.geom.density = 1.0
        spec.default.joint.damping[0] = 0.001
        spec.default.site.size[0] = 0.032

        body = spec.worldbody.add_body(name=self.root_body, pos=[0.0, 0.0, self.height])
        add_vision_camera(body, [0.0, 0.0, 0.15])
        slide, hinge = mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE
        body.add_joint(name="agent_x", type=slide, axis=[1.0, 0.0, 0.0], damping=[0.01, 0.0, 0.0])
        body.add_joint(name="agent_y", type=slide, axis=[0.0, 1.0, 0.0], damping=[0.01, 0.0, 0.0])
        body.add_joint(name="agent_yaw", type=hinge, axis=[0.0, 0.0, 1.0], damping=[0.005, 0.0, 0.0])
        body.add_geom(name="agent", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.1, 0.0, 0.0],
                      friction=[1.0, 0.01, 0.01], rgba=[0.74, 0.04, 0.18, 1.0])
        body.add_geom(name="agent_heading", type=mujoco.mjtGeom.mjGEOM_BOX, pos=[0.1, 0.0, 0.0],
                      size=[0.05, 0.05, 0.05], rgba=[0.0, 0.15, 0.4, 1.0])
        body.add_site(name=self.root_body, type=mujoco.mjtGeom.mjGEOM_SPHERE, rgba=[1.0, 0.0, 0.0, 0.1])

        forward = spec.add_actuator(name="forward", trntype=mujoco.mjtTrn.mjTRN_SITE, target=self.root_body)
        forward.set_to_motor()
        forward.gear = [0.3, 0.0, 0.0, 0.0, 0.0, 0.0]
        turn = spec.add_actuator(name="turn", trntype=mujoco.mjtTrn.mjTRN_JOINT, target="agent_yaw")
        turn.set_to_velocity(kv=1.0)
        turn.gear = [0.3, 0.0, 0.0, 0.0, 0.0, 0.0]
        for actuator in (forward, turn):
            actuator.ctrlrange = [-1.0, 1.0]
            actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
            actuator.forcerange = [-0.05, 0.05]
            actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE

        add_fixed_sensors(spec, self.root_body)

    def bind(self, model: mujoco.MjModel) -> None:
        super().bind(model)
        self._qpos_x = int(model.joint(self.qualified("agent_x")).qposadr[0])
        self._qpos_y = int(model.joint(self.qualified("agent_y")).qposadr[0])
        self._qpos_yaw = int(model.joint(self.qualified("agent_yaw")).qposadr[0])

    def set_pose(self, model: mujoco.MjModel, qpos: np.ndarray, xy: np.ndarray, yaw: np.ndarray) -> None:
        qpos[:, self._qpos_x] = xy[:, 0]
        qpos[:, self._qpos_y] = xy[:, 1]
        qpos[:, self._qpos_yaw] = yaw
