"""The goal: a translucent cylinder the robot drives into. Never collides, costs nothing.

Multi-agent tasks give every robot its own goal: :class:`AgentGoal` subclasses name the goal and the
agent it belongs to (Safety-Gymnasium's MultiGoal: ``goal_red`` for agent 0, ``goal_blue`` for agent 1).
"""

from __future__ import annotations

from typing import ClassVar

import mujoco

from sg_torchrl.envs.navigation.objects.base import StaticObject

__all__ = ["AgentGoal", "Goal", "GoalBlue", "GoalRed"]


class Goal(StaticObject):
    """Goal area of radius ``size`` (default 0.3, reached when the robot is within it), keep-out 0.4.

    Reward terms (the task reads them): ``reward_distance`` times the distance gained towards
    the goal, plus ``reward_goal`` on a step that ends inside it.
    """

    name: ClassVar[str] = "goal"
    compass_target: ClassVar[bool] = True
    rgba: ClassVar[tuple[float, float, float, float]] = (0.0, 1.0, 0.0, 0.25)

    def __init__(self, *, size: float = 0.3, keepout: float = 0.4, reward_distance: float = 1.0,
                 reward_goal: float = 1.0, **options) -> None:
        super().__init__(1, size=size, keepout=keepout, **options)
        self.reward_distance = reward_distance
        self.reward_goal = reward_goal
        self.height = self.size / 2 + 0.01  # the cylinder stands on the floor

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        body.add_geom(name=self.body_name(i), type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[self.size, self.size / 2, 0.0],
                      contype=0, conaffinity=0, group=0, rgba=list(self.rgba))


class AgentGoal(Goal):
    """The goal of one agent (robot) in a multi-agent task: only that robot is rewarded for reaching it."""

    #: index of the agent this goal belongs to
    agent: ClassVar[int]


class GoalRed(AgentGoal):
    """Agent 0's goal (Safety-Gymnasium's ``goal_red``)."""

    name: ClassVar[str] = "goal_red"
    agent: ClassVar[int] = 0
    rgba: ClassVar[tuple[float, float, float, float]] = (0.7412, 0.0431, 0.1843, 0.25)


class GoalBlue(AgentGoal):
    """Agent 1's goal (Safety-Gymnasium's ``goal_blue``)."""

    name: ClassVar[str] = "goal_blue"
    agent: ClassVar[int] = 1
    rgba: ClassVar[tuple[float, float, float, float]] = (0.0039, 0.1529, 0.3961, 0.25)
