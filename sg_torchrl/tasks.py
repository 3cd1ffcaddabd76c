"""Your own safe tasks, registered as env ids that ``sg_torchrl.make`` and ``sg-train`` build like built-in ones.

Two entry points (tutorial: ``docs/custom_tasks.md``):

* a **navigation task** declared as data, :class:`TaskSpec` (objective, placement extents, objects with
  counts, sizes, keep-outs and costs, reward weights, episode length), on one of the navigation robots:
  :func:`register_task`. The built-in Goal, Button, Push and Circle levels are specs of the same kind.
* **any env plus a cost function**: a gymnasium id (or a factory of gymnasium / TorchRL envs) and
  ``cost_fn(obs, action, next_obs, info)``: :func:`register_cost_env` (or :func:`make_cost_env` for one
  env without an id).

Registered ids live in this process; ``sg-train --task-module my_tasks`` imports a module that registers
them before the command line is checked. ``sg_torchrl.gym.make`` sees a new id after
:func:`sg_torchrl.gym_registration.register_envs` (gymnasium's registry is filled once, at import).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from sg_torchrl.envs.cost_env import CostFunction, CostTransform, make_cost_env
from sg_torchrl.envs.navigation.compose import OBJECTIVES, OBJECTS, REWARD_TERMS, TaskSpec, TaskSpecError, object_fields
from sg_torchrl.envs.navigation.layout import LayoutError, LayoutSampler
from sg_torchrl.envs.navigation.robots import ROBOTS
from sg_torchrl.envs.registry import EnvEntry, register, unregister

__all__ = ["CostTransform", "OBJECTIVES", "OBJECTS", "REWARD_TERMS", "ROBOTS", "TaskSpec", "TaskSpecError",
           "make_cost_env", "object_fields", "register_cost_env", "register_task", "unregister"]

_NAVIGATION = "sg_torchrl.envs.navigation.env:NavigationEnv"


def register_task(env_id: str, task: TaskSpec, robot: str = "Point") -> str:
    """Register ``env_id``: ``task`` with ``robot`` (``"Point"``, ``"Car"``, ``"Racecar"``, ``"Doggo"``, ``"Ant"``).

    The id then takes the navigation options (``cost_mode``, ``lidar``, ``obs_mode``, ...). Checked here:
    the robot's name, and that the task's objects and the robot fit in the placement area.

    Raises:
        TaskSpecError: an unknown robot or a task whose objects cannot fit (the message names them).
        ValueError: ``env_id`` is registered already (:func:`unregister` it first).
    """
    if not isinstance(task, TaskSpec):
        raise TypeError(f"register_task takes a TaskSpec, got {type(task).__name__}")
    if robot not in ROBOTS:
        raise TaskSpecError(f"task {task.name!r}: unknown robot {robot!r}; valid: {', '.join(map(repr, ROBOTS))}")
    built, robot_class = task.build(), ROBOTS[robot]
    for obj in built.objects:
        obj.for_robot(robot_class)
    keepout = robot_class.keepout if built.agent_keepout is None else built.agent_keepout
    try:
        LayoutSampler(built.extents, keepout, built.objects, built.agent_placements, label=f"task {task.name!r}")
    except (LayoutError, ValueError) as error:
        raise TaskSpecError(f"{error} (robot {robot})") from None
    register(EnvEntry(env_id=env_id, constructor=_NAVIGATION, family="navigation", robot=robot, task=task.name,
                      level=task.level, max_episode_steps=task.episode_length, kwargs={"robot": robot, "task": task}))
    return env_id


def register_cost_env(env_id: str, env: str | Callable[[], Any], cost_fn: CostFunction, *,
                      max_episode_steps: int | None = None, cost_name: str = "cost",
                      info_keys: Sequence[str] = ()) -> str:
    """Register ``env_id``: ``env`` (a gymnasium id or a factory) with the cost ``cost_fn`` (:func:`make_cost_env`).

    ``cost_fn`` must be picklable (a module-level function) for env copies and checkpoints to work.
    """
    probe = make_cost_env(env, cost_fn, max_episode_steps=max_episode_steps, cost_name=cost_name,
                          info_keys=info_keys)  # a bad id or a failing env: refused now, not at the first run
    probe.reset()
    steps = probe.max_episode_steps
    probe.close()
    register(EnvEntry(env_id=env_id, constructor=make_cost_env, family="custom", robot=str(env), task=cost_name,
                      max_episode_steps=steps, kwargs={"env": env, "cost_fn": cost_fn, "cost_name": cost_name,
                                                       "info_keys": tuple(info_keys)}))
    return env_id
