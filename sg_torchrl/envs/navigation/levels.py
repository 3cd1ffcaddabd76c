"""The navigation tasks' levels: ``TASKS[task][level]`` builds a fresh :class:`~sg_torchrl.envs.navigation.tasks.Task`.

The registry registers ``Safety{Robot}{Task}{Level}-v0`` for every task level here and every robot;
``MULTI_AGENT_TASKS`` holds the tasks with several robots (MultiGoal), registered in the multi-agent
layout for the robots Safety-Gymnasium names them with (``sg_torchrl.envs.multi_agent``).

The Goal, Button, Push and Circle levels (reference section 6: extents, counts, sizes and keep-outs) are
:class:`~sg_torchrl.envs.navigation.compose.TaskSpec` values, the composition API users declare their own
tasks with; the Fading levels are the Goal specs built with the Fading task classes. The levels of the
scene tasks (Run, Race, the Building tasks, FormulaOne) and of MultiGoal are written with their task
classes: they need scenery, fixed tracks, per-agent goals or task options the specs do not cover.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from sg_torchrl.envs.navigation.compose import TaskSpec
from sg_torchrl.envs.navigation.tasks import FadingEasyTask, FadingHardTask, Task
from sg_torchrl.envs.navigation.tasks.building import (BUILDING_BUTTON_LEVELS, BUILDING_GOAL_LEVELS,
                                                       BUILDING_PUSH_LEVELS)
from sg_torchrl.envs.navigation.tasks.formula_one import FORMULA_ONE_LEVELS
from sg_torchrl.envs.navigation.tasks.multi_goal import MULTI_GOAL_LEVELS
from sg_torchrl.envs.navigation.tasks.race import RACE_LEVELS
from sg_torchrl.envs.navigation.tasks.run import RUN_LEVELS

__all__ = ["BUTTON_SPECS", "CIRCLE_SPECS", "GOAL_SPECS", "MULTI_AGENT_TASKS", "PUSH_SPECS", "TASKS", "make_task"]

_GOAL = {"keepout": 0.305}
GOAL_SPECS = {
    0: TaskSpec("Goal", level=0, extents=1.0, objects={"goal": _GOAL}),
    1: TaskSpec("Goal", level=1, extents=1.5, objects={
        "goal": _GOAL, "hazards": {"count": 8, "keepout": 0.18}, "vases": {"count": 1, "cost": False}}),
    2: TaskSpec("Goal", level=2, extents=2.0, objects={
        "goal": _GOAL, "hazards": {"count": 10, "keepout": 0.18}, "vases": {"count": 10}}),
}
BUTTON_SPECS = {
    0: TaskSpec("Button", objective="button", level=0, extents=1.0, objects={"buttons": {"count": 4, "cost": False}}),
    1: TaskSpec("Button", objective="button", level=1, extents=1.5, objects={
        "buttons": {"count": 4}, "goal": {}, "hazards": {"count": 4, "keepout": 0.18}, "gremlins": {"count": 4}}),
    2: TaskSpec("Button", objective="button", level=2, extents=1.8, objects={
        "buttons": {"count": 4}, "goal": {}, "hazards": {"count": 8, "keepout": 0.18}, "gremlins": {"count": 6}}),
}
PUSH_SPECS = {
    0: TaskSpec("Push", objective="push", level=0, extents=1.0),
    1: TaskSpec("Push", objective="push", level=1, extents=1.5, objects={
        "goal": {}, "hazards": {"count": 2, "size": 0.3, "keepout": 0.4}, "pillars": {"count": 1, "cost": False}}),
    2: TaskSpec("Push", objective="push", level=2, extents=2.0, objects={
        "goal": {}, "hazards": {"count": 4, "size": 0.3, "keepout": 0.4}, "pillars": {"count": 4}}),
}
CIRCLE_SPECS = {
    0: TaskSpec("Circle", objective="circle", level=0),
    1: TaskSpec("Circle", objective="circle", level=1, objects={"walls": {"count": 2, "bound": 1.125}}),
    2: TaskSpec("Circle", objective="circle", level=2, objects={"walls": {"count": 4, "bound": 1.125}}),
}
# What fades per level (reference: Safety-Gymnasium's fading levels).
_EASY_FADED = {0: ("goal",), 1: ("goal",), 2: ("goal", "hazards")}
_HARD_FADED = {0: ("goal",), 1: ("goal",), 2: ("goal", "hazards", "vases")}


def _fading(task_class: type[Task], faded: dict[int, tuple[str, ...]]) -> dict[int, Callable[[], Task]]:
    return {level: dataclasses.replace(GOAL_SPECS[level], name=task_class.name, task_class=task_class,
                                       task_options={"faded": names}).build for level, names in faded.items()}


def _built(specs: dict[int, TaskSpec]) -> dict[int, Callable[[], Task]]:
    return {level: spec.build for level, spec in specs.items()}


TASKS: dict[str, dict[int, Callable[[], Task]]] = {
    "Goal": _built(GOAL_SPECS),
    "Button": _built(BUTTON_SPECS),
    "Push": _built(PUSH_SPECS),
    "Circle": _built(CIRCLE_SPECS),
    "Run": RUN_LEVELS,
    "FadingEasy": _fading(FadingEasyTask, _EASY_FADED),
    "FadingHard": _fading(FadingHardTask, _HARD_FADED),
    "Race": RACE_LEVELS,
    # the paper's construction-site scenes (sg_torchrl.envs.navigation.tasks.building)
    "BuildingGoal": BUILDING_GOAL_LEVELS,
    "BuildingButton": BUILDING_BUTTON_LEVELS,
    "BuildingPush": BUILDING_PUSH_LEVELS,
    # the paper's race-track scene (sg_torchrl.envs.navigation.tasks.formula_one)
    "FormulaOne": FORMULA_ONE_LEVELS,
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
