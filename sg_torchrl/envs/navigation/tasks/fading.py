"""FadingEasy / FadingHard: Goal tasks whose goal (and at level 2 more) fades from view (reference section 6).

A Fading level is the Goal level of the same digit (extents, objects, reward, costs, 1000 steps,
:data:`~sg_torchrl.envs.navigation.levels.GOAL_SPECS`, built with this task class) plus a
:class:`~sg_torchrl.envs.navigation.fading.Fader`: the goal's render alpha falls linearly to 0
over 150 steps (FadingEasy) or 75 (FadingHard) and comes back whenever a new goal is drawn or an
episode starts. Level 2 also fades the hazards (and, in FadingHard, the vases); each group shows
itself again on any step it costs something (the robot inside a hazard, touching or moving a vase).

Fading only changes what is drawn: with the same seed and actions a Fading id's vector observations,
rewards and costs are the Goal id's. Its point is the ``...Vision-v0`` twins, where the policy sees
pixels and has to remember where the goal was.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np

from sg_torchrl.envs.navigation.fading import Fader
from sg_torchrl.envs.navigation.tasks.goal import GoalTask
from sg_torchrl.envs.rendering import GeomAlpha

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.env import NavigationEnv

__all__ = ["FadingEasyTask", "FadingHardTask", "FadingTask"]


class FadingTask(GoalTask):
    """A Goal task whose objects named in ``faded`` fade over :attr:`fading_steps` steps (module docstring).

    Args:
        level, extents, objects, ...: as :class:`GoalTask`.
        faded: names of the objects that fade (default: the goal).
    """

    #: steps from full alpha to invisible
    fading_steps: ClassVar[int]

    def __init__(self, level: int, *, faded: tuple[str, ...] = ("goal",), **options) -> None:
        super().__init__(level, **options)
        by_name = {obj.name: obj for obj in self.objects}
        unknown = [name for name in faded if name not in by_name]
        if unknown:
            raise ValueError(f"{type(self).__name__} level {level}: cannot fade {unknown}; objects: {sorted(by_name)}")
        self.fader = Fader([by_name[name] for name in faded], self.fading_steps)

    def bind(self, env: NavigationEnv) -> None:
        super().bind(env)
        self.fader.bind(env.scene)

    def reset(self, env: NavigationEnv, indices: np.ndarray) -> None:
        super().reset(env, indices)
        self.fader.reset(indices)

    def after_step(self, env: NavigationEnv) -> np.ndarray:
        terminated = super().after_step(env)  # reached goals moved (or their episodes end)
        self.fader.step(env.step_costs)
        self.fader.restore(np.flatnonzero(self.goal_met & ~terminated), self.goal)  # a new goal, fully visible
        return terminated

    def geom_alpha(self, index: int) -> GeomAlpha:
        return self.fader.geom_alpha(index)

    def state_dict(self) -> dict:
        return {**super().state_dict(), "fader": self.fader.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.fader.load_state_dict(state["fader"])


class FadingEasyTask(FadingTask):
    """The goal fades over 150 steps; level 2 also the hazards."""

    name: ClassVar[str] = "FadingEasy"
    fading_steps: ClassVar[int] = 150


class FadingHardTask(FadingTask):
    """The goal fades over 75 steps; level 2 also the hazards and the vases."""

    name: ClassVar[str] = "FadingHard"
    fading_steps: ClassVar[int] = 75
