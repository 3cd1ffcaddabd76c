"""MultiGoal: two robots share one world, each with its own goal and its own costs.

Safety-Gymnasium's safe multi-agent navigation task (``SafetyPointMultiGoal{0,1,2}-v0``,
``SafetyAntMultiGoal{0,1,2}-v0``; its ``tasks/safe_multi_agent/tasks/multi_goal``). Facts:

* **layout**: agent 0, agent 1 (keep-out 0.4 each), ``goal_red`` (agent 0's goal), ``goal_blue``
  (agent 1's), both of radius 0.3 and keep-out 0.305, then the level's objects. Level 0: the goals
  alone in +-1; level 1: + 8 hazards (keep-out 0.18) and one unconstrained vase in +-1.5; level 2:
  10 hazards and 10 constrained vases in +-2.
* **reward of agent i**, from its own goal only: ``(d_prev - d) * 1.0 + 1.0 * [d <= 0.3]``, ``d`` the
  planar distance from robot i to its goal. When a robot reaches its goal, that goal alone moves
  (layout keep-out rule against both robots, the other goal and the objects at their current
  positions) and the episode goes on; if no position is found, the episode ends (for both agents).
* **costs of agent i**: its own (``hazards``: its depth inside each hazard; ``vases_contact``: its
  contacts with vases; ``vases_velocity``: the speed of the vases it touched last, see
  :class:`~sg_torchrl.envs.navigation.objects.Vases`) and, from level 1, ``contact_other``: 1.0
  while any of its geoms touches the other robot (then both robots pay it).
* **termination**: shared: a failed goal re-sampling, or either robot dead (an Ant's torso at 0.08 or
  lower) ends the episode of both agents. 1000 steps.
* **robots**: the single-agent Point; the Ant with feet of density 50000 (the multi-agent model
  file's, :class:`~sg_torchrl.envs.navigation.robots.Ant`).

Differences: the reference draws a candidate for both goals whenever one is reached and then moves
only the reached one (its candidate for the other goal is wasted); here only the reached goal draws.
The reference's reward clip is a no-op (the clipped value is never stored); here rewards are
clipped to +-10 as in every navigation task, which a reward of 1 + a step's progress never reaches.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from sg_torchrl.envs.navigation.objects import AgentGoal, GoalBlue, GoalRed, Hazards, NavObject, Vases
from sg_torchrl.envs.navigation.tasks.base import Task

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.env import NavigationEnv

__all__ = ["MULTI_GOAL_LEVELS", "MultiGoalTask"]


class MultiGoalTask(Task):
    """Each of two robots drives to its own goals (see the module docstring).

    Args:
        level, extents, objects: see :class:`Task`; ``objects`` holds one
            :class:`~sg_torchrl.envs.navigation.objects.AgentGoal` per agent.
        contact_other_cost: cost each robot pays while the robots touch (0: no such constraint).

    Attributes (per simulator, updated every step):
        goal_met: ``(N, 2)`` bool, agent ``a`` reached its goal on the last step.
    """

    name: ClassVar[str] = "MultiGoal"
    num_agents: ClassVar[int] = 2
    robot_options: ClassVar[dict[str, dict[str, Any]]] = {"Ant": {"foot_density": 50000.0}}

    def __init__(self, level: int, *, extents: float | Sequence[float], objects: Sequence[NavObject],
                 contact_other_cost: float = 0.0) -> None:
        super().__init__(level, extents=extents, objects=objects)
        goals = sorted((obj for obj in self.objects if isinstance(obj, AgentGoal)), key=lambda goal: goal.agent)
        if [goal.agent for goal in goals] != list(range(self.num_agents)):
            raise ValueError(f"{type(self).__name__}: needs one AgentGoal per agent, got {goals}")
        self.goals: list[AgentGoal] = goals
        self.contact_other_cost = float(contact_other_cost)
        self._sizes = np.array([goal.size for goal in goals])
        self._reward_distance = np.array([goal.reward_distance for goal in goals])
        self._reward_goal = np.array([goal.reward_goal for goal in goals])

    @property
    def key(self) -> tuple:
        return (*super().key, self.contact_other_cost)

    @property
    def cost_names(self) -> tuple[str, ...]:
        return ("contact_other",) if self.contact_other_cost else ()

    # ------------------------------------------------------------------ hooks
    def bind(self, env: NavigationEnv) -> None:
        shape = (env.num_envs, self.num_agents)
        self._last_distance = np.zeros(shape)
        self.goal_met = np.zeros(shape, dtype=bool)
        views = env.scene.views
        # Per agent, the geoms of every other robot (what its contact_other cost watches).
        self._other_robots = [
            np.logical_or.reduce([other.robot_geoms for other in views if other is not view]) for view in views
        ]

    def distance(self, env: NavigationEnv) -> np.ndarray:
        """Planar distance from each robot to its own goal, ``(N, A)``."""
        scene = env.scene
        return np.stack([scene.for_robot(goal.agent).planar_distance(goal.positions(scene))[:, 0]
                         for goal in self.goals], axis=1)

    def reset(self, env: NavigationEnv, indices: np.ndarray) -> None:
        self._last_distance[indices] = self.distance(env)[indices]
        self.goal_met[indices] = False

    def reward(self, env: NavigationEnv) -> np.ndarray:
        distance = self.distance(env)
        np.less_equal(distance, self._sizes, out=self.goal_met)
        reward = (self._last_distance - distance) * self._reward_distance + self._reward_goal * self.goal_met
        self._last_distance[:] = distance
        return reward

    def after_step(self, env: NavigationEnv) -> np.ndarray:
        """Move every reached goal (that agent's only); a simulator where that fails terminates."""
        terminated = np.zeros(env.num_envs, dtype=bool)
        for index, agent in np.argwhere(self.goal_met):
            if env.resample(self.goals[agent], index):
                self._last_distance[index, agent] = self.distance(env)[index, agent]
            else:
                terminated[index] = True
        return terminated

    def agent_costs(self, env: NavigationEnv, out: dict[str, np.ndarray]) -> None:
        if not self.contact_other_cost:
            return
        for agent, (view, others) in enumerate(zip(env.scene.views, self._other_robots)):
            touching = view.robot_contacts()[:, others].sum(axis=1) > 0
            out["contact_other"][:, agent] = self.contact_other_cost * touching

    def state_dict(self) -> dict:
        return {"last_distance": self._last_distance.copy(), "goal_met": self.goal_met.copy()}

    def load_state_dict(self, state: dict) -> None:
        self._last_distance[:] = state["last_distance"]
        self.goal_met[:] = state["goal_met"]


def _goals() -> list[NavObject]:
    return [GoalRed(keepout=0.305), GoalBlue(keepout=0.305)]


# Safety-Gymnasium's multi_goal_level{0,1,2}: extents, counts, keep-outs and the robot-robot contact cost.
MULTI_GOAL_LEVELS = {
    0: lambda: MultiGoalTask(0, extents=1.0, objects=_goals()),
    1: lambda: MultiGoalTask(1, extents=1.5, objects=[*_goals(), Hazards(8, keepout=0.18), Vases(1, constrained=False)],
                             contact_other_cost=1.0),
    2: lambda: MultiGoalTask(2, extents=2.0, objects=[*_goals(), Hazards(10, keepout=0.18), Vases(10)],
                             contact_other_cost=1.0),
}
