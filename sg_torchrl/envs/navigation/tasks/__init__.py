"""Navigation tasks and their levels.

``TASKS[task][level]`` builds a fresh :class:`Task` (with fresh objects) for one env; the registry
registers ``Safety{Robot}{Task}{Level}-v0`` for every task level and every robot.
"""

from __future__ import annotations

from collections.abc import Callable

from sg_torchrl.envs.navigation.tasks.base import Task
from sg_torchrl.envs.navigation.tasks.button import BUTTON_LEVELS, ButtonTask
from sg_torchrl.envs.navigation.tasks.circle import CIRCLE_LEVELS, CircleTask
from sg_torchrl.envs.navigation.tasks.goal import GOAL_LEVELS, GoalTask
from sg_torchrl.envs.navigation.tasks.push import PUSH_LEVELS, PushTask
from sg_torchrl.envs.navigation.tasks.run import RUN_LEVELS, RunTask

TASKS: dict[str, dict[int, Callable[[], Task]]] = {
    "Goal": GOAL_LEVELS,
    "Button": BUTTON_LEVELS,
    "Push": PUSH_LEVELS,
    "Circle": CIRCLE_LEVELS,
    "Run": RUN_LEVELS,
}


def make_task(name: str, level: int) -> Task:
    """A fresh ``name`` task at ``level``."""
    if name not in TASKS:
        raise ValueError(f"unknown navigation task {name!r}; choose from {sorted(TASKS)}")
    if level not in TASKS[name]:
        raise ValueError(f"{name} has levels {sorted(TASKS[name])}, got {level}")
    return TASKS[name][level]()


__all__ = ["ButtonTask", "CircleTask", "GoalTask", "PushTask", "RunTask", "TASKS", "Task", "make_task"]
