"""Navigation task classes: what each task adds to its objects (reward, events, episode length).

Their levels, and the table the registry reads (``TASKS``, ``MULTI_AGENT_TASKS``, ``make_task``), are in
:mod:`sg_torchrl.envs.navigation.levels`; a task declared as data is a
:class:`~sg_torchrl.envs.navigation.compose.TaskSpec`.
"""

from __future__ import annotations

from sg_torchrl.envs.navigation.tasks.base import Task
from sg_torchrl.envs.navigation.tasks.button import ButtonTask
from sg_torchrl.envs.navigation.tasks.circle import CircleTask
from sg_torchrl.envs.navigation.tasks.fading import FadingEasyTask, FadingHardTask, FadingTask
from sg_torchrl.envs.navigation.tasks.goal import GoalTask
from sg_torchrl.envs.navigation.tasks.multi_goal import MultiGoalTask
from sg_torchrl.envs.navigation.tasks.push import PushTask
from sg_torchrl.envs.navigation.tasks.race import RaceTask
from sg_torchrl.envs.navigation.tasks.run import RunTask

__all__ = ["ButtonTask", "CircleTask", "FadingEasyTask", "FadingHardTask", "FadingTask", "GoalTask", "MultiGoalTask",
           "PushTask", "RaceTask", "RunTask", "Task"]
