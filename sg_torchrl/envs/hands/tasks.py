"""The two-hand tasks of the Safety-Gymnasium paper (section 4.4): geometry and episode settings.

Each :class:`HandTask` is data for the one env class, :class:`~sg_torchrl.envs.hands.env.ShadowHandEnv`.

* ``HandOver`` (Isaac Gym's ShadowHandOver): fixed hands, palms up, fingers towards each other,
  wrists 1 m apart; the ball starts on the ``right/`` palm, the goal is above the ``left/`` palm.
  75 steps per episode, episode ends when the ball falls below 0.2 m (0.3 m under the palms).
* ``CatchOver2Underarm`` (Isaac Gym's ShadowHandCatchOver2Underarm): the same roles with each hand's
  base actuated (3 translations, 3 rotations: 26 actions per hand, 52 in all) and the wrists 0.8 m
  apart. The original's exact hand orientations (the throwing hand turned over, the catching hand
  underarm) are *not* reproduced: both palms face up here, so the task differs from the paper's in
  how the ball must be thrown; episode length and fall height are taken as HandOver's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sg_torchrl.envs.hands.scene import HAND_OVER_SCENE, MOUNT_HEIGHT, SceneConfig

__all__ = ["HandTask", "TASKS", "above_palm"]

#: The palm's centre lies this far from the wrist mount along the fingers, and the ball this high above the mount.
PALM_REACH = 0.36
BALL_LIFT = 0.07


def above_palm(mount: tuple[float, float, float, float]) -> np.ndarray:
    """The point just above the palm of a hand mounted at ``(x, y, z, yaw)`` (where a resting ball's centre is)."""
    x, y, z, yaw = mount
    return np.array([x + PALM_REACH * np.sin(yaw), y - PALM_REACH * np.cos(yaw), z + BALL_LIFT])


@dataclass(frozen=True)
class HandTask:
    """One two-hand task: its scene, where the ball starts, where the goal is, when an episode ends."""

    name: str
    scene: SceneConfig
    max_episode_steps: int
    fall_height: float

    @property
    def ball_start(self) -> np.ndarray:
        """The ball's resting position at reset (before noise): above the throwing (``right/``) palm."""
        return above_palm(self.scene.mounts[0])

    @property
    def goal_position(self) -> np.ndarray:
        """The goal position: above the catching (``left/``) palm."""
        return above_palm(self.scene.mounts[1])


TASKS: dict[str, HandTask] = {
    "HandOver": HandTask("HandOver", HAND_OVER_SCENE, max_episode_steps=75, fall_height=MOUNT_HEIGHT - 0.3),
    "CatchOver2Underarm": HandTask(
        "CatchOver2Underarm",
        SceneConfig(mounts=((0.0, 0.0, MOUNT_HEIGHT, 0.0), (0.0, -0.8, MOUNT_HEIGHT, np.pi)), actuated_base=True),
        max_episode_steps=75,
        fall_height=MOUNT_HEIGHT - 0.3,
    ),
}
