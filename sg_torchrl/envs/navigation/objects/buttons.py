"""Buttons, one of which is the goal, and the goal marker that sits on it (Button task).

:class:`Buttons` owns which button is the goal in each simulator and the resampling timer, since
its cost depends on both; the task decides when a new goal button is drawn (reference section 4).
:class:`GoalMarker` is the ``goal`` of a Button level: an almost invisible disc, twice a button's
radius, placed with the layout like any goal and then moved onto the goal button. Its lidar group
``goal_lidar`` therefore points at the goal button.
"""

from __future__ import annotations

from typing import ClassVar

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.objects.base import NamedCost, StaticObject
from sg_torchrl.envs.navigation.objects.goal import Goal
from sg_torchrl.envs.navigation.world import Scene

__all__ = ["Buttons", "GoalMarker"]


class Buttons(NamedCost, StaticObject):
    """``num`` immovable spheres of radius ``size`` (default 4, 0.1) resting on the floor, keep-out 0.2.

    Per simulator, :attr:`goal_button` is the button to press and :attr:`timer` counts the steps
    left in the resampling delay (``resampling_delay``, 10 steps) after a new goal button was
    drawn; :meth:`choose_goal` draws one, :meth:`tick` counts down.

    Cost named after the object (``"buttons"``) when constrained (reference section 3; levels 1 and 2): the number of
    contacts between the robot and any button other than the goal button, counted only while the
    timer is 0.
    """

    name: ClassVar[str] = "buttons"
    prefix: ClassVar[str] = "button"
    rgba: ClassVar[tuple[float, float, float, float]] = (1.0, 0.5, 0.0, 1.0)

    def __init__(self, num: int = 4, *, size: float = 0.1, keepout: float = 0.2, constrained: bool = True,
                 resampling_delay: int = 10, **options) -> None:
        super().__init__(num, size=size, keepout=keepout, constrained=constrained, **options)
        self.resampling_delay = int(resampling_delay)
        self.height = self.size

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        body.add_geom(name=self.body_name(i), type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[self.size, 0.0, 0.0],
                      group=0, rgba=list(self.rgba))

    def bind(self, scene: Scene) -> None:
        super().bind(scene)
        self.geom_ids = scene.model.body_geomadr[self.body_ids].astype(np.int64)  # one geom per button
        self._geom_list = self.geom_ids.tolist()  # for the one-simulator forms (touches_one, ...)
        self._rows = np.arange(scene.num_envs)
        #: ``(N,)`` index of the goal button of each simulator
        self.goal_button = np.zeros(scene.num_envs, dtype=np.int64)
        #: ``(N,)`` steps left before the buttons are observed (and cost) again
        self.timer = np.zeros(scene.num_envs, dtype=np.int64)

    # ------------------------------------------------------------------ goal button and timer
    def choose_goal(self, scene: Scene, index: int, rng: np.random.Generator) -> np.ndarray:
        """Draw simulator ``index``'s goal button uniformly (it may repeat), restart its timer; returns its ``xy``."""
        self.goal_button[index] = rng.integers(self.num)
        self.timer[index] = self.resampling_delay
        return self.positions(scene)[index, self.goal_button[index]]

    def tick(self) -> None:
        """One step of the resampling timer (it stops at 0)."""
        np.maximum(self.timer - 1, 0, out=self.timer)

    def tick_one(self) -> None:
        """:meth:`tick` of one simulator on a Python int: the same ``max(timer - 1, 0)``, written only
        when the timer runs (at 0 the array form writes 0 again)."""
        timer = self.timer.item(0)
        if timer:
            self.timer[0] = max(timer - 1, 0)

    # ------------------------------------------------------------------ contacts and cost
    def touches(self, scene: Scene) -> np.ndarray:
        """Robot contacts with each button, ``(N, num)``."""
        return scene.robot_contacts()[:, self.geom_ids]

    def goal_pressed(self, scene: Scene) -> np.ndarray:
        """Whether a robot geom touches the goal button, ``(N,)`` bool."""
        return self.touches(scene)[self._rows, self.goal_button] > 0

    def touches_one(self, scene: Scene) -> list[float]:
        """:meth:`touches` of one simulator as Python floats, one per button: the same whole-number counts,
        read from the step's shared :meth:`Scene.robot_contacts_one
        <sg_torchrl.envs.navigation.world.Scene.robot_contacts_one>` (the goal test and the cost of a
        one-simulator step both read it; the contacts are counted once per step)."""
        counts = scene.robot_contacts_one()
        return [counts.get(geom, 0.0) for geom in self._geom_list]

    def goal_pressed_one(self, scene: Scene) -> bool:
        """:meth:`goal_pressed` of one simulator, as a bool (from :meth:`touches_one`'s counts)."""
        return scene.robot_contacts_one().get(self._geom_list[self.goal_button.item(0)], 0.0) > 0

    def cost(self, scene: Scene) -> np.ndarray:
        touches = self.touches(scene)
        # Every contact with a button (one geom each) minus those with the goal button; the counts are
        # whole numbers, so summing the touches equals summing the buttons' geom columns in model order.
        wrong = touches.sum(axis=1) - touches[self._rows, self.goal_button]
        return np.where(self.timer == 0, wrong, 0.0)

    def cost_one(self, scene: Scene) -> float:
        """On Python floats (:meth:`touches_one`): the same whole-number sum (exact in any order) minus the
        goal button's count, 0.0 while the timer runs."""
        wrong = 0.0
        if not self.timer.item(0):
            touches = self.touches_one(scene)
            for count in touches:
                wrong += count
            wrong -= touches[self.goal_button.item(0)]
        return wrong

    # ------------------------------------------------------------------ snapshots
    def state_dict(self) -> dict:
        return {**super().state_dict(), "goal_button": self.goal_button.copy(), "timer": self.timer.copy()}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.goal_button[:] = state["goal_button"]
        self.timer[:] = state["timer"]


class GoalMarker(Goal):
    """The goal of a Button level (radius 0.2 = twice a button's, keep-out 0.4): nearly invisible, never
    collides; the task moves it onto the goal button, so the shaping reward and ``goal_lidar`` follow
    that button."""

    def __init__(self, *, size: float = 0.2, keepout: float = 0.4, **options) -> None:
        super().__init__(size=size, keepout=keepout, **options)

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        body.add_geom(name=self.body_name(i), type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[self.size, self.size / 2, 0.0],
                      contype=0, conaffinity=0, group=0, rgba=[0.0, 1.0, 0.0, 0.1])
