"""Navigation tasks and their levels.

``TASKS[task][level]`` builds a fresh :class:`Task` (with fresh objects) for one env; the registry
registers ``Safety{Robot}{Task}{Level}-v0`` for every task level and every robot.
``MULTI_AGENT_TASKS`` holds the tasks with several robots (MultiGoal), registered in the multi-agent
layout for the robots Safety-Gymnasium names them with (``sg_torchrl.envs.multi_agent``).
"""

from __future__ import annotations

from collections.abc import Callable

from sg_torchrl.envs.navigation.tasks.base import Task
from sg_torchrl.envs.navigation.tasks.button import BUTTON_LEVELS, ButtonTask
from sg_torchrl.envs.navigation.tasks.circle import CIRCLE_LEVELS, CircleTask
from sg_torchrl.envs.navigation.tasks.fading import FADING_EASY_LEVELS, FADING_HARD_LEVELS, FadingEasyTask, FadingHardTask, FadingTask
from sg_torchrl.envs.navigation.tasks.goal import GOAL_LEVELS, GoalTask
from sg_torchrl.envs.navigation.tasks.multi_goal import MULTI_GOAL_LEVELS, MultiGoalTask
from sg_torchrl.envs.navigation.tasks.push import PUSH_LEVELS, PushTask
from sg_torchrl.envs.navigation.tasks.race import RACE_LEVELS, RaceTask
from sg_torchrl.envs.navigation.tasks.run import RUN_LEVELS, RunTask

TASKS: dict[str, dict[int, Callable[[], Task]]] = {
    "Goal": GOAL_LEVELS,
    "Button": BUTTON_LEVELS,
    "Push": PUSH_LEVELS,
    "Circle": CIRCLE_LEVELS,
    "Run": RUN_LEVELS,
    "FadingEasy": FADING_EASY_LEVELS,
    "FadingHard": FADING_HARD_LEVELS,
    "Race": RACE_LEVELS,
}

MULTI_AGENT_TASKS: dict[str, dict[int, Callable[[], Task]]] = {
    "MultiGoal": MULTI_GOAL_LEVELS,
}


def make_task(name: str, level: int) -> Task:
    """A fresh ``name`` task (single- or multi-agent) at ``level``."""
    levels = TASKS.get(name) or MULTI_AGENT_TASKS.get(name)
    if levels is None:
        raise ValueError(f"unknown navigation task {name!r}; choose from {sorted([*TASKS, *MULTI_AGENT_TASKS])}")
    if level not in levels:
        raise ValueError(f"{name} has levels {sorted(levels)}, got {level}")
    return levels[level]()


__all__ = ["ButtonTask", "CircleTask", "FadingEasyTask", "FadingHardTask", "FadingTask", "GoalTask", "MULTI_AGENT_TASKS", "MultiGoalTask", "PushTask", "RaceTask", "RunTask",
           "TASKS", "Task", "make_task"]
