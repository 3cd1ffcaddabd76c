"""Navigation tasks declared as data: :class:`TaskSpec`, the composition API behind custom and built-in levels.

A task is an **objective** (what earns reward: reach goals, press the goal button, push a box onto
goals, circle a zone), a square (or rectangular) placement area, the **objects** placed in it with
their counts, sizes, keep-outs and whether they cost, the **reward** weights and the episode length::

    TaskSpec("SparseHazards", objective="goal", extents=2.0,
             objects={"goal": {"keepout": 0.305}, "hazards": {"count": 12, "size": 0.25}, "vases": {"cost": False}},
             reward={"distance": 1.0, "goal": 2.0}, max_episode_steps=500)

Objects (:data:`OBJECTS`; which ones an objective takes: :data:`OBJECTIVES`): ``goal``, ``hazards``,
``vases``, ``pillars``, ``gremlins``, ``walls`` (Circle's boundary walls), ``buttons`` (the Button
objective), ``push_box`` (Push), ``circle`` (Circle). Each object's fields are its class's constructor
keywords (``size``, ``keepout``, ``placements``, ``locations``, ``lidar``, ``density``, ...), with
``count`` for the number of instances and ``cost`` for whether it is a constraint. The objects an
objective needs (the goal, the buttons, the box, the zone) are added with their defaults when not listed.
Reward terms (:data:`REWARD_TERMS`) are the weights the objective's reward reads: ``distance`` and
``goal`` (progress towards, and reaching, the goal), ``box_distance`` (Push: the robot closing in on the
box), ``circle`` (Circle: the circling reward's factor).

Mistakes fail at construction with the bad name and the valid ones (an unknown objective, object,
field or reward term), or with the object that does not fit (more objects than the placement area can
hold, :class:`~sg_torchrl.envs.navigation.layout.LayoutSampler`). A spec is frozen, hashable by value
and picklable; :meth:`TaskSpec.build` makes the fresh :class:`~sg_torchrl.envs.navigation.tasks.Task`
each env needs (tasks hold per-simulator state). :class:`~sg_torchrl.envs.navigation.env.NavigationEnv`
takes a spec as its ``task``; :func:`sg_torchrl.tasks.register_task` registers an env id for it.

The built-in Goal, Button, Push and Circle levels (and the Fading levels, Goal's with another task
class) are specs of this kind (:mod:`sg_torchrl.envs.navigation.levels`), so a user's task and a built-in
one are built by the same code.
"""

from __future__ import annotations

import copy
import inspect
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from sg_torchrl.envs.navigation.objects import (Buttons, CircleZone, Goal, GoalMarker, Gremlins, Hazards,
                                                NavObject, Pillars, PushBox, Sigwalls, Vases)
from sg_torchrl.envs.navigation.tasks import ButtonTask, CircleTask, GoalTask, PushTask, Task

__all__ = ["OBJECTIVES", "OBJECTS", "REWARD_TERMS", "TaskSpec", "TaskSpecError"]

#: Objects any objective may place (name -> class).
_SHARED_OBJECTS: dict[str, type[NavObject]] = {
    "hazards": Hazards, "vases": Vases, "pillars": Pillars, "gremlins": Gremlins, "walls": Sigwalls,
}
#: Per objective: its task class, the objects it needs (added with defaults when not listed) and the ones
#: only it may place.
OBJECTIVES: dict[str, tuple[type[Task], tuple[str, ...], dict[str, type[NavObject]]]] = {
    "goal": (GoalTask, ("goal",), {"goal": Goal}),
    "button": (ButtonTask, ("buttons", "goal"), {"buttons": Buttons, "goal": GoalMarker}),
    "push": (PushTask, ("goal", "push_box"), {"goal": Goal, "push_box": PushBox}),
    "circle": (CircleTask, ("circle",), {"circle": CircleZone}),
}
#: Every object name (its class for the goal objective; Button's goal is the marker on the goal button).
OBJECTS: dict[str, type[NavObject]] = {**_SHARED_OBJECTS, **{name: cls for _, _, own in reversed(OBJECTIVES.values())
                                                             for name, cls in own.items()}}
#: Per objective, reward term -> (object, its constructor keyword).
REWARD_TERMS: dict[str, dict[str, tuple[str, str]]] = {
    "goal": {"distance": ("goal", "reward_distance"), "goal": ("goal", "reward_goal")},
    "button": {"distance": ("goal", "reward_distance"), "goal": ("goal", "reward_goal")},
    "push": {"distance": ("goal", "reward_distance"), "goal": ("goal", "reward_goal"),
             "box_distance": ("push_box", "reward_box_dist")},
    "circle": {"circle": ("circle", "reward_factor")},
}
#: The public names of the keywords every object spells differently in its constructor.
_RENAMED = {"count": "num", "cost": "constrained"}


class TaskSpecError(ValueError):
    """A :class:`TaskSpec` that cannot be built: the message names the task, the bad key and the valid ones."""


def _one_of(task: str, what: str, name: object, valid: Sequence[str]) -> TaskSpecError:
    return TaskSpecError(f"task {task!r}: unknown {what} {name!r}; valid: {', '.join(map(repr, valid))}")


def object_fields(cls: type[NavObject]) -> list[str]:
    """The fields a spec may give an object of class ``cls``: its constructor keywords (and, where it
    passes more on, :class:`NavObject`'s), ``num`` as ``count``, ``constrained`` as ``cost``, without the
    reward weights (given as reward terms)."""
    names: list[str] = []
    for klass in (cls, NavObject):
        parameters = inspect.signature(klass.__init__).parameters.values()
        names += [p.name for p in parameters if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
                  and p.name != "self" and p.name not in names]
        if not any(p.kind is p.VAR_KEYWORD for p in parameters):
            break
    if cls is not NavObject and "num" not in inspect.signature(cls.__init__).parameters:
        names.remove("num")  # a single object (the goal, the box, the zone)
    rewards = {keyword for terms in REWARD_TERMS.values() for _, keyword in terms.values()}
    public = {value: key for key, value in _RENAMED.items()}
    return [public.get(name, name) for name in names if name not in rewards]


@dataclass(frozen=True)
class TaskSpec:
    """A navigation task as data (module docstring).

    Args:
        name: the task's name (model cache key, error messages; with ``level``, what the built-in ids say).
        objects: object name -> its fields (``{"hazards": {"count": 8, "keepout": 0.18}}``; ``{}`` for the
            defaults). Valid names per objective: :data:`OBJECTIVES`; fields: :func:`object_fields`.
        objective: ``"goal"``, ``"button"``, ``"push"`` or ``"circle"``.
        extents: half-width of the square placement area, or ``(xmin, ymin, xmax, ymax)``; ``None``: the
            objective's (Circle places everything at fixed spots; the others need one).
        reward: reward term -> weight (:data:`REWARD_TERMS`); terms not given keep the objects' defaults.
        max_episode_steps: episode length (``None``: the objective's, 1000; Circle's 500).
        level: the level number (built-in tasks: the id's digit).
        agent_placements: rectangles for the robot's start (``None``: the objective's; the extents).
        agent_keepout: the robot's placement radius (``None``: the objective's; the robot's own).
        task_options: more keywords for the objective's task class (the Fading tasks' ``faded``).
        task_class: a subclass of the objective's task class to build instead (the Fading tasks).
    """

    name: str
    objects: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    objective: str = "goal"
    extents: float | tuple[float, float, float, float] | None = None
    reward: Mapping[str, float] = field(default_factory=dict)
    max_episode_steps: int | None = None
    level: int = 0
    agent_placements: tuple[tuple[float, float, float, float], ...] | None = None
    agent_keepout: float | None = None
    task_options: Mapping[str, Any] = field(default_factory=dict)
    task_class: type[Task] | None = None

    def __post_init__(self) -> None:
        name = self.name
        if not isinstance(name, str) or not name:
            raise TaskSpecError(f"a task's name must be a non-empty string, got {name!r}")
        if self.objective not in OBJECTIVES:
            raise _one_of(name, "objective", self.objective, list(OBJECTIVES))
        base, required, own = OBJECTIVES[self.objective]
        if self.task_class is not None and not (isinstance(self.task_class, type) and issubclass(self.task_class, base)):
            raise TaskSpecError(f"task {name!r}: task_class must be a subclass of {base.__name__}, got {self.task_class!r}")
        if not isinstance(self.objects, Mapping):
            raise TaskSpecError(f"task {name!r}: objects must map object names to their fields, got {self.objects!r}")
        valid = {**_SHARED_OBJECTS, **own}
        for kind, fields in self.objects.items():
            if kind not in valid:
                raise _one_of(name, f"object for objective {self.objective!r}", kind, list(valid))
            if not isinstance(fields, Mapping):
                raise TaskSpecError(f"task {name!r}: the fields of {kind!r} must be a mapping, got {fields!r}")
            allowed = object_fields(valid[kind])
            for key in fields:
                if key not in allowed:
                    raise _one_of(name, f"field of {kind!r}", key, allowed)
        terms = REWARD_TERMS[self.objective]
        for term in self.reward:
            if term not in terms:
                raise _one_of(name, f"reward term for objective {self.objective!r}", term, list(terms))
        steps = self.max_episode_steps
        if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
            raise TaskSpecError(f"task {name!r}: max_episode_steps must be a positive integer, got {steps!r}")
        if self.extents is None and self.objective != "circle":
            raise TaskSpecError(f"task {name!r}: objective {self.objective!r} needs extents (the placement area)")
        # Frozen copies: a user editing their dicts afterwards does not change a registered task.
        objects = {kind: dict(self.objects.get(kind, {})) for kind in (*required, *self.objects)}
        object.__setattr__(self, "objects", objects)
        object.__setattr__(self, "reward", {term: float(weight) for term, weight in self.reward.items()})
        object.__setattr__(self, "task_options", copy.deepcopy(dict(self.task_options)))
        if self.agent_placements is not None:
            object.__setattr__(self, "agent_placements", tuple(tuple(map(float, r)) for r in self.agent_placements))
        self.build()  # every value the objects and the task check themselves, now rather than at make

    def __hash__(self) -> int:
        return hash((self.name, self.objective, self.level, repr(self.objects), repr(self.reward)))

    @property
    def episode_length(self) -> int:
        """:attr:`max_episode_steps`, or the objective's when ``None``."""
        return self.max_episode_steps or (self.task_class or OBJECTIVES[self.objective][0]).max_episode_steps

    def build_objects(self) -> list[NavObject]:
        """Fresh objects of this task (the reward weights applied)."""
        _, _, own = OBJECTIVES[self.objective]
        classes = {**_SHARED_OBJECTS, **own}
        keywords = {kind: {_RENAMED.get(key, key): value for key, value in fields.items()}
                    for kind, fields in self.objects.items()}
        for term, weight in self.reward.items():
            kind, keyword = REWARD_TERMS[self.objective][term]
            keywords[kind][keyword] = weight
        objects = []
        for kind, kwargs in keywords.items():
            try:
                objects.append(classes[kind](**copy.deepcopy(kwargs)))
            except (TypeError, ValueError) as error:
                raise TaskSpecError(f"task {self.name!r}: object {kind!r}: {error}") from None
        return objects

    def build(self) -> Task:
        """A fresh task of this spec, for one env."""
        cls = self.task_class or OBJECTIVES[self.objective][0]
        options: dict[str, Any] = dict(copy.deepcopy(self.task_options))
        if self.extents is not None:
            options["extents"] = self.extents
        for key in ("agent_placements", "agent_keepout"):
            if getattr(self, key) is not None:
                options[key] = getattr(self, key)
        try:
            task = cls(self.level, objects=self.build_objects(), **options)
        except (TypeError, ValueError) as error:
            if isinstance(error, TaskSpecError):
                raise
            raise TaskSpecError(f"task {self.name!r}: {error}") from None
        if self.name != cls.name:  # a custom task: its own name (cache key, reference extents) and length
            task.name = self.name
        if self.max_episode_steps is not None:
            task.max_episode_steps = self.max_episode_steps
        return task
