"""Cameras of the MuJoCo envs: what a frame is looked at from, chosen by name.

:func:`resolve_camera` turns what a user passes as ``camera`` to
:meth:`~sg_torchrl.envs.rendering.RenderMixin.render` (or ``render_depth``) into the
``mujoco.MjvCamera`` MuJoCo renders from. Accepted, in this order:

* ``None`` / ``"follow"``: the env's default :class:`FollowCamera` (its look-at point is the robot's
  root body in every frame);
* ``"chase"``: :data:`CHASE_CAMERA`, behind the robot and turning with its heading;
* ``"world"`` / ``"human"`` / ``-1``: MuJoCo's default free camera over the whole world. ``"human"``
  because that is what Safety-Gymnasium's ``camera_name="human"`` gives in its array modes (no model
  camera has that name, so it falls back to the free camera; its human window moves it by keyboard);
* a camera of the model, by name or id. The names are Safety-Gymnasium's: every navigation world
  has ``"fixednear"`` and ``"fixedfar"`` (fixed, above the arena's -y edge, looking at its centre
  from 45 degrees) and its robot carries ``"vision"`` (egocentric) and ``"track"`` (2 m behind, in
  +y, and 2 m above the robot, looking down at 45 degrees; it moves with the robot but does not
  turn); the velocity robots carry gymnasium's ``"track"`` (from the side, following the torso);
  multi-agent navigation worlds prefix the robots' cameras (``"agent_0/vision"``);
* a :class:`FollowCamera` of your own, or a ``mujoco.MjvCamera`` (used as is).

An unknown name raises ``ValueError`` listing every valid name of that env (:func:`camera_names`),
so a typo fails at once rather than rendering from somewhere else (Safety-Gymnasium silently falls
back to the free camera).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

__all__ = ["CHASE_CAMERA", "FREE_CAMERA_NAMES", "FollowCamera", "LOCOMOTION_CAMERA", "NAVIGATION_CAMERA",
           "camera_names", "resolve_camera"]

#: names of MuJoCo's default free camera over the whole world
FREE_CAMERA_NAMES = ("world", "human")


@dataclass(frozen=True)
class FollowCamera:
    """A free camera whose look-at point is the robot's root body in every frame.

    Args:
        distance: from the look-at point, metres.
        elevation: degrees above the horizon of the viewing direction (negative: looking down).
        azimuth: degrees of the viewing direction in the plane (0: along +x, 90: along +y, which
            shows +x to the right); relative to the robot's heading when ``heading`` is true.
        heading: turn with the robot's yaw (a chase camera).
        offset: added to the look-at point (world frame).
    """

    distance: float = 4.0
    elevation: float = -60.0
    azimuth: float = 90.0
    heading: bool = False
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def place(self, camera: mujoco.MjvCamera, position: np.ndarray, rotation: np.ndarray) -> mujoco.MjvCamera:
        """Point ``camera`` at a body at ``position`` (3,) with orientation ``rotation`` (3, 3)."""
        camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        camera.lookat[:] = np.asarray(position) + np.asarray(self.offset)
        camera.distance = self.distance
        camera.elevation = self.elevation
        azimuth = self.azimuth
        if self.heading:
            azimuth += math.degrees(math.atan2(rotation[1, 0], rotation[0, 0]))
        camera.azimuth = azimuth
        return camera


#: the navigation default: from above at 60 degrees, a few metres of the arena around the robot
NAVIGATION_CAMERA = FollowCamera(distance=4.5, elevation=-60.0, azimuth=90.0)
#: the locomotion default: from the side, slightly above (gymnasium's MuJoCo envs look alike)
LOCOMOTION_CAMERA = FollowCamera(distance=4.0, elevation=-20.0, azimuth=90.0)
#: behind the robot, turning with it
CHASE_CAMERA = FollowCamera(distance=2.5, elevation=-25.0, azimuth=0.0, heading=True)


def camera_names(model: mujoco.MjModel) -> tuple[str, ...]:
    """Every name :func:`resolve_camera` accepts for ``model``: ours, then the model's named cameras."""
    named = tuple(model.camera(i).name for i in range(model.ncam) if model.camera(i).name)
    return ("follow", "chase", *FREE_CAMERA_NAMES, *named)


def resolve_camera(model: mujoco.MjModel, data: mujoco.MjData, camera: Any, *, default: FollowCamera,
                   body: int) -> mujoco.MjvCamera:
    """The ``MjvCamera`` that ``camera`` (module docstring) names for a frame of ``data``.

    ``default`` is what ``None`` / ``"follow"`` mean; ``body`` is the body follow cameras look at.
    """
    if isinstance(camera, mujoco.MjvCamera):
        return camera
    if camera is None or camera == "follow":
        camera = default
    elif camera == "chase":
        camera = CHASE_CAMERA
    elif isinstance(camera, str) and camera in FREE_CAMERA_NAMES:
        camera = -1
    result = mujoco.MjvCamera()
    if isinstance(camera, FollowCamera):
        return camera.place(result, data.xpos[body], data.xmat[body].reshape(3, 3))
    camera_id = camera
    if isinstance(camera, str):
        camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if camera_id < 0:
            raise ValueError(f"unknown camera {camera!r}: this env's cameras are {list(camera_names(model))} "
                             "(or pass a camera id, a FollowCamera or an MjvCamera)")
    if isinstance(camera_id, bool) or not isinstance(camera_id, (int, np.integer)) or not -1 <= camera_id < model.ncam:
        raise ValueError(f"camera must be a name, a FollowCamera, an MjvCamera or an id in [-1, {model.ncam}), "
                         f"got {camera!r}; names: {list(camera_names(model))}")
    if camera_id == -1:
        mujoco.mjv_defaultFreeCamera(model, result)
    else:
        result.type = mujoco.mjtCamera.mjCAMERA_FIXED
        result.fixedcamid = int(camera_id)
    return result
