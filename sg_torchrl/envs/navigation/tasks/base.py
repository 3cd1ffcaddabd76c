"""The task interface: a level composes objects; the task class adds reward and events.

A :class:`Task` subclass holds what is common to every level of a task (reward, what happens when
the goal is reached, episode length, floor, lidar range); a level is one constructor call listing
its extents and objects, e.g. ``GoalTask(1, extents=1.5, objects=[Goal(keepout=0.305),
Hazards(8, keepout=0.18), Vases(1, constrained=False)])``. Register the level in
:data:`sg_torchrl.envs.navigation.levels.TASKS` and the registry picks it up for every robot.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

import numpy as np

from sg_torchrl.envs.navigation.objects.base import NavObject
from sg_torchrl.envs.navigation.world import world_order
from sg_torchrl.envs.rendering import GeomAlpha

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.env import NavigationEnv
    from sg_torchrl.envs.navigation.scenery import Scenery

__all__ = ["Task"]

ObjectT = TypeVar("ObjectT", bound=NavObject)


class Task(abc.ABC):
    """One navigation task at one level.

    Args:
        level: the level digit of the env id.
        extents: half-width of the square placement area, or ``(xmin, ymin, xmax, ymax)``.
        objects: the objects of this level (any order within a kind; see ``world_order``).
        agent_placements: rectangles for the agent's start (default: the extents).
        agent_keepout: overrides the robot's keep-out (Circle and Run use 0).
        scenery: static set dressing built into the world (floor look, fixed obstacles; see
            :mod:`~sg_torchrl.envs.navigation.scenery`); ``None``: the plain grey floor.
    """

    name: ClassVar[str]
    #: robots in the world (each an agent; more than one: a multi-agent task, see ``multi_goal``)
    num_agents: ClassVar[int] = 1
    #: build options of the robots this task uses, per robot name (e.g. ``{"Ant": {"foot_density": ...}}``)
    robot_options: ClassVar[dict[str, dict[str, Any]]] = {}
    max_episode_steps: ClassVar[int] = 1000
    floor_half_size: ClassVar[float] = 3.5
    lidar_max_dist: ClassVar[float | None] = 3.0
    lidar_bins: ClassVar[int] = 16
    #: rewards are clipped to [-clip, clip] (reference section 4; ``None``: no clip)
    reward_clip: ClassVar[float | None] = 10.0
    def __init__(
        self,
        level: int,
        *,
        extents: float | Sequence[float],
        objects: Sequence[NavObject],
        agent_placements: Sequence[Sequence[float]] | None = None,
        agent_keepout: float | None = None,
        scenery: Scenery | None = None,
    ) -> None:
        self.level = level
        self.scenery = scenery
        if np.ndim(extents) == 0:
            extents = (-float(extents), -float(extents), float(extents), float(extents))
        self.extents = tuple(float(e) for e in extents)
        self.objects = world_order(objects)
        names = [obj.name for obj in self.objects]
        if len(set(names)) != len(names):
            raise ValueError(f"{type(self).__name__}: object names must be unique, got {names}")
        self.agent_placements = None if agent_placements is None else np.asarray(agent_placements, float).reshape(-1, 4)
        self.agent_keepout = agent_keepout

    @property
    def key(self) -> tuple:
        """Identifies the world this task builds (with the robot: the compiled-model cache key)."""
        key = (self.name, self.level, self.floor_half_size, tuple(obj.spec_key() for obj in self.objects))
        return key if self.scenery is None else (*key, self.scenery.key)

    def find(self, kind: type[ObjectT]) -> ObjectT:
        """The object of class ``kind`` in this level."""
        for obj in self.objects:
            if isinstance(obj, kind):
                return obj
        raise LookupError(f"{type(self).__name__} level {self.level} has no {kind.__name__}")

    # ------------------------------------------------------------------ hooks
    def bind(self, env: NavigationEnv) -> None:
        """Allocate per-simulator state once the env's scene exists."""

    def reset(self, env: NavigationEnv, indices: np.ndarray) -> None:
        """Episode start of simulators ``indices`` (their layout is already in place)."""

    @abc.abstractmethod
    def reward(self, env: NavigationEnv) -> np.ndarray:
        """Reward of the step just simulated, ``(N,)`` (before clipping); ``(N, A)``, one per agent, when
        the task has several agents."""

    def reward_one(self, env: NavigationEnv) -> float:
        """:meth:`reward` of a one-simulator, one-robot env as a Python float (the one-simulator step's,
        :mod:`~sg_torchrl.envs.navigation.single`). Default: :meth:`reward`'s one value; a task may
        compute the same value on Python floats (:class:`~sg_torchrl.envs.navigation.tasks.goal.GoalTask`)."""
        return np.asarray(self.reward(env)).item(0)

    @property
    def cost_names(self) -> tuple[str, ...]:
        """Constraints of the task itself, beyond its objects' (e.g. robots touching each other). Default: none."""
        return ()

    def agent_costs(self, env: NavigationEnv, out: dict[str, np.ndarray]) -> None:
        """Write the raw cost of each of :attr:`cost_names` for every agent into ``out[name]`` ``(N, A)``."""

    def after_step(self, env: NavigationEnv) -> np.ndarray:
        """Events after reward and cost (goal reached, timers); returns which simulators terminate, ``(N,)`` bool."""
        return np.zeros(env.num_envs, dtype=bool)

    def after_step_one(self, env: NavigationEnv) -> bool:
        """:meth:`after_step` of a one-simulator, one-robot env: whether it terminates, as a bool (the
        one-simulator step's, :mod:`~sg_torchrl.envs.navigation.single`). Default: :meth:`after_step`'s one
        value; a task may answer its usual steps without arrays (:class:`~sg_torchrl.envs.navigation.tasks.goal.GoalTask`).
        A task that keeps :meth:`after_step`'s default (no events: Circle, Run) never terminates: False."""
        if type(self).after_step is Task.after_step:
            return False
        return bool(self.after_step(env)[0])

    def after_observe(self, env: NavigationEnv, observation: np.ndarray) -> None:
        """Adjust the assembled observation in place (e.g. Button blanks ``buttons_lidar`` while its timer runs)."""

    def geom_alpha(self, index: int) -> GeomAlpha | None:
        """Geoms simulator ``index`` draws with another alpha than the model's, and their alphas
        (``(geom_ids, alphas)``; the Fading tasks), or ``None`` (default: the model's colours). Rendering only."""
        return None

    def state_dict(self) -> dict:
        """Per-simulator task state (for checkpoints)."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass
