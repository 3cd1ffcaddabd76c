"""Navigation tasks and their levels.

``TASKS[task][level]`` builds a fresh :class:`Task` (with fresh objects) for one env. Still to come:
Button (buttons, goal marker, gremlins, button timer), Push (push box, pillars), Circle (circle
zone, sigwalls, lidar range 6, 500 steps) and Run (long floor, sigwalls, no lidar, no clip).
"""

from __future__ import annotations

from collections.abc import Callable

from sg_torchrl.envs.navigation.tasks.base import Task
from sg_torchrl.envs.navigation.tasks.goal import GOAL_LEVELS, GoalTask

TASKS: dict[str, dict[int, Callable[[], Task]]] = {
    "Goal": GOAL_LEVELS,
}


def make_task(name: str, level: int) -> Task:
    """A fresh ``name`` task at ``level``."""
    if name not in TASKS:
        raise ValueError(f"unknown navigation task {name!r}; choose from {sorted(TASKS)}")
    if level not in TASKS[name]:
        raise ValueError(f"{name} has levels {sorted(TASKS[name])}, got {level}")
    return TASKS[name][level]()


__all__ = ["GoalTask", "TASKS", "Task", "make_task"]
