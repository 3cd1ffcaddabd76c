"""Push: push a box onto the goal; a new goal appears whenever the box reaches it (reference sections 2-6).

Reward per step: ``(dA_prev - dA) * 1.0 * [dA_prev > null_dist * box size] + (dB_prev - dB) * 1.0
+ 1.0 * [dB <= 0.3]`` with ``dA`` the distance robot to box and ``dB`` box to goal, both between
full 3-D body positions (unlike Goal's planar distance); ``null_dist`` is 0, so the first term
is always on. When the box reaches the goal, the goal is re-sampled exactly as in Goal (keep-out
rule against everything where it is now; the episode terminates if no position is found) and
``dB_prev`` restarts from the new distance. Episodes last 1000 steps.

Levels: 0 the goal (radius 0.3, keep-out 0.4) and the box in +-1; 1 in +-1.5 adds 2 hazards of
radius 0.3 (keep-out 0.4) and one unconstrained pillar; 2 in +-2 has 4 hazards and 4 constrained
pillars. Observation: sensors, then ``goal_lidar`` (, ``hazards_lidar``, ``pillars_lidar``),
``push_box_lidar``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np

from sg_torchrl.envs.navigation.objects import PushBox
from sg_torchrl.envs.navigation.tasks.goal import GoalTask

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.env import NavigationEnv

__all__ = ["PushTask"]


class PushTask(GoalTask):
    """Push the box onto goals one after another (see the module docstring).

    A :class:`GoalTask` in which what must reach the goal is the box: :meth:`distance` is the
    box-goal distance (its progress weighted by the goal's ``reward_distance``), plus a term for
    the robot closing in on the box (weighted by the box's ``reward_box_dist``).
    """

    name: ClassVar[str] = "Push"

    def bind(self, env: NavigationEnv) -> None:
        super().bind(env)
        self.box = self.find(PushBox)
        self._last_box_distance = np.zeros(env.num_envs)

    def box_pos(self, env: NavigationEnv) -> np.ndarray:
        """Position of the box's body, ``(N, 3)``."""
        return env.scene.body_xpos(self.box.body_ids)[:, 0]

    def distance(self, env: NavigationEnv) -> np.ndarray:
        """3-D distance box to goal centre, ``(N,)``."""
        goal = np.empty((env.num_envs, 3))
        goal[:, :2] = self.goal.positions(env.scene)[:, 0]
        goal[:, 2] = self.goal.height
        return np.linalg.norm(self.box_pos(env) - goal, axis=1)

    def box_distance(self, env: NavigationEnv) -> np.ndarray:
        """3-D distance robot to box, ``(N,)``."""
        return np.linalg.norm(self.box_pos(env) - env.scene.agent_pos(), axis=1)

    def reset(self, env: NavigationEnv, indices: np.ndarray) -> None:
        super().reset(env, indices)
        self._last_box_distance[indices] = self.box_distance(env)[indices]

    def reward(self, env: NavigationEnv) -> np.ndarray:
        box_distance = self.box_distance(env)
        gate = self._last_box_distance > self.box.null_dist * self.box.size
        approach = (self._last_box_distance - box_distance) * self.box.reward_box_dist * gate
        self._last_box_distance[:] = box_distance
        return approach + super().reward(env)

    def state_dict(self) -> dict:
        return {**super().state_dict(), "last_box_distance": self._last_box_distance.copy()}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self._last_box_distance[:] = state["last_box_distance"]
