"""Goal: drive to a goal area; a new goal appears whenever it is reached (reference sections 4, 6).

Reward per step: ``(d_prev - d) * 1.0 + 1.0 * [d <= 0.3]``, ``d`` the planar distance from the
robot to the goal centre. Reaching the goal does not end the episode: the goal is re-sampled with
the layout keep-out rule against the current positions of the robot and all objects, and
``d_prev`` restarts from the distance to the new goal. If no position is found (10000 tries) the
episode terminates. Episodes last 1000 steps.

Levels (:mod:`sg_torchrl.envs.navigation.levels`): 0 the goal alone in +-1; 1 adds 8 hazards and one
unconstrained vase in +-1.5; 2 has 10 hazards and 10 constrained vases in +-2.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np

from sg_torchrl.envs.navigation.objects import Goal
from sg_torchrl.envs.navigation.tasks.base import Task

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.env import NavigationEnv

__all__ = ["GoalTask"]


class GoalTask(Task):
    """Reach goals one after another (see the module docstring).

    Attributes (per simulator, updated every step):
        goal_met: ``(N,)`` bool, the goal was reached on the last step (Safety-Gymnasium's
            ``info["goal_met"]``).
    """

    name: ClassVar[str] = "Goal"

    def bind(self, env: NavigationEnv) -> None:
        self.goal = self.find(Goal)
        self._last_distance = np.zeros(env.num_envs)
        self.goal_met = np.zeros(env.num_envs, dtype=bool)

    def distance(self, env: NavigationEnv) -> np.ndarray:
        """Planar distance robot to goal centre, ``(N,)``."""
        return env.scene.planar_distance(self.goal.positions(env.scene))[:, 0]

    def reset(self, env: NavigationEnv, indices: np.ndarray) -> None:
        self._last_distance[indices] = self.distance(env)[indices]
        self.goal_met[indices] = False

    def reward(self, env: NavigationEnv) -> np.ndarray:
        distance = self.distance(env)
        self.goal_met[:] = self.reached(env, distance)
        reward = self._shaped(self._last_distance, distance, self.goal_met)
        self._last_distance[:] = distance
        return reward

    def reward_one(self, env: NavigationEnv) -> float:
        """:meth:`reward` of one simulator on Python floats (for single-env speed): the distance from
        :meth:`Scene.planar_distances_one <sg_torchrl.envs.navigation.world.Scene.planar_distances_one>`
        (the same value), :meth:`reached` given that float (a task may ignore it and answer from its own
        state: a one-element array reads as its bool), the same :meth:`_shaped` arithmetic. A subclass
        with its own :meth:`reward` or :meth:`distance` (Push) takes :meth:`Task.reward_one`'s."""
        if type(self).reward is not GoalTask.reward or type(self).distance is not GoalTask.distance:
            return super().reward_one(env)
        distance = env.scene.planar_distances_one(self.goal.positions(env.scene))[0]
        met = self.reached_one(env, distance)
        self.goal_met[0] = met
        reward = self._shaped(self._last_distance.item(0), distance, met)
        self._last_distance[0] = distance
        return reward

    def _shaped(self, last_distance, distance, met):
        """The reward: distance gained times ``reward_distance``, plus ``reward_goal`` when the goal is met.
        On ``(N,)`` arrays (``met`` bool) or one simulator's Python floats (``met`` a bool): ``reward_goal
        * met`` is ``reward_goal * 1.0`` or ``reward_goal * 0.0`` either way, so the values are the same."""
        return (last_distance - distance) * self.goal.reward_distance + self.goal.reward_goal * met

    def after_step(self, env: NavigationEnv) -> np.ndarray:
        terminated = np.zeros(env.num_envs, dtype=bool)
        if not np.count_nonzero(self.goal_met):  # most steps: nothing to move (count_nonzero: cheaper than .any())
            return terminated
        for index in np.flatnonzero(self.goal_met):
            if self.next_goal(env, index):
                self._last_distance[index] = self.distance(env)[index]
            else:
                terminated[index] = True
        return terminated

    def after_step_one(self, env: NavigationEnv) -> bool:
        """:meth:`after_step` of one simulator (:meth:`Task.after_step_one`): on most steps no goal was met
        and nothing happens, read from one flag; a met goal goes through :meth:`after_step` itself. A
        subclass with its own :meth:`after_step` takes :meth:`Task.after_step_one`'s."""
        if type(self).after_step is not GoalTask.after_step:
            return super().after_step_one(env)
        return self._goal_events_one(env)

    def _goal_events_one(self, env: NavigationEnv) -> bool:
        """:meth:`GoalTask.after_step` of one simulator, as a bool; no arrays unless its goal was met."""
        return bool(GoalTask.after_step(self, env)[0]) if self.goal_met.item(0) else False

    def reached(self, env: NavigationEnv, distance: np.ndarray) -> np.ndarray:
        """Which simulators reached the goal this step, ``(N,)`` bool (given one simulator's distance as a
        Python float, :meth:`reward_one`: a bool or a one-element array). Here: within the goal's radius."""
        return distance <= self.goal.size

    def reached_one(self, env: NavigationEnv, distance: float) -> bool:
        """:meth:`reached` of one simulator given its distance as a Python float (:meth:`reward_one`), as a
        bool. Default: :meth:`reached`'s answer; a task may read it from its own state (Button)."""
        return bool(self.reached(env, distance))

    def next_goal(self, env: NavigationEnv, index: int) -> bool:
        """Set up simulator ``index``'s next goal after reaching one; False ends its episode. Here: re-sample
        the goal position with the layout keep-out rule."""
        return env.resample(self.goal, index)

    def state_dict(self) -> dict:
        return {"last_distance": self._last_distance.copy(), "goal_met": self.goal_met.copy()}

    def load_state_dict(self, state: dict) -> None:
        self._last_distance[:] = state["last_distance"]
        self.goal_met[:] = state["goal_met"]
