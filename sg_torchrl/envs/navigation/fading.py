"""Fading: objects whose render alpha falls linearly, per simulator, until something restores it.

Safety-Gymnasium's Fading tasks (reference section 6) fade the goal (and at level 2 the hazards,
and in FadingHard the vases too) so that a pixel policy has to remember where it saw them. A
:class:`Fader` holds that state for ``N`` simulators and a few object groups: the number of steps
since each group was last shown at full alpha (``age``, ``(N, G)`` integers). A group drawn with
model alpha ``a0`` shows ``a0 * max(0, 1 - age / steps)``: after ``steps`` steps it is invisible
(the reference subtracts ``a0 / steps`` each step, clamped at 0: the same schedule, without the
rounding drift of repeated subtraction).

When ``age`` restarts at 0: at an episode reset (:meth:`Fader.reset`, partial resets too), when the
task restores a group (:meth:`Fader.restore`: a new goal is drawn), and while a group is costing
something (:meth:`Fader.step` with the step's raw costs: a level-2 hazard shows itself while the
robot is inside it; the reference does this at level 2, the only level where something costly fades).

Fading changes only what is drawn: nothing here touches the physics, the layout or the observation
vector. The renderer reads :meth:`Fader.geom_alpha` for one simulator just before drawing it
(:mod:`sg_torchrl.envs.rendering`, "Per-simulator transparency"): the shared model keeps its colours.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from sg_torchrl.envs.rendering import GeomAlpha

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.objects.base import NavObject
    from sg_torchrl.envs.navigation.world import Scene

__all__ = ["Fader"]


class Fader:
    """Per-simulator linear fading of the geoms of some objects (see the module docstring).

    Args:
        objects: the object groups that fade (each with all its instances).
        steps: steps from full alpha to invisible (FadingEasy 150, FadingHard 75).
    """

    def __init__(self, objects: Sequence[NavObject], steps: int) -> None:
        if not isinstance(steps, (int, np.integer)) or steps < 1:
            raise ValueError(f"Fader: steps must be a positive integer, got {steps!r}")
        if not objects:
            raise ValueError("Fader: nothing to fade")
        self.objects = list(objects)
        self.steps = int(steps)
        self.age = np.zeros((0, len(self.objects)), dtype=np.int64)

    def bind(self, scene: Scene) -> None:
        """Resolve the objects' geoms in the compiled model (after the objects are bound) and allocate ``age``."""
        ids, groups = [], []
        for group, obj in enumerate(self.objects):
            geoms = np.flatnonzero(obj.geom_mask)
            ids.append(geoms)
            groups.append(np.full(len(geoms), group))
        #: the fading geoms, their group (index into :attr:`objects`) and their model alpha
        self.geom_ids = np.concatenate(ids)
        self.geom_group = np.concatenate(groups)
        self.base_alpha = scene.model.geom_rgba[self.geom_ids, 3].copy()
        #: ``(N, G)`` steps since each group of each simulator was last shown at full alpha
        self.age = np.zeros((scene.num_envs, len(self.objects)), dtype=np.int64)

    def group(self, obj: NavObject) -> int:
        """Index of ``obj`` among the fading groups (``ValueError`` if it does not fade)."""
        for index, each in enumerate(self.objects):
            if each is obj:
                return index
        raise ValueError(f"{obj!r} does not fade")

    def reset(self, indices: np.ndarray) -> None:
        """Episode start of simulators ``indices``: every group at full alpha."""
        self.age[indices] = 0

    def restore(self, indices: np.ndarray, obj: NavObject) -> None:
        """Show ``obj`` at full alpha again in simulators ``indices`` (it fades again from the next step)."""
        self.age[indices, self.group(obj)] = 0

    def step(self, costs: Mapping[str, np.ndarray]) -> None:
        """One env step: every group fades by one step, then a group that cost something this step
        (its entries of ``costs``, raw values ``(N,)`` or ``(N, A)``) is shown at full alpha."""
        self.age += 1
        for group, obj in enumerate(self.objects):
            paid = np.zeros(self.age.shape[0], dtype=bool)
            for name in obj.cost_names:
                value = np.asarray(costs[name])
                paid |= (value.reshape(len(paid), -1) > 0).any(axis=1)
            self.age[paid, group] = 0

    def alpha(self, index: int) -> np.ndarray:
        """The alpha of every fading geom of simulator ``index``, ``(K,)`` in :attr:`geom_ids` order."""
        visible = np.clip(1.0 - self.age[index, self.geom_group] / self.steps, 0.0, 1.0)
        return self.base_alpha * visible

    def geom_alpha(self, index: int) -> GeomAlpha:
        """``(geom_ids, alphas)`` simulator ``index`` draws with (what the renderer takes)."""
        return self.geom_ids, self.alpha(index)

    def state_dict(self) -> dict:
        return {"age": self.age.copy()}

    def load_state_dict(self, state: dict) -> None:
        self.age[:] = state["age"]
