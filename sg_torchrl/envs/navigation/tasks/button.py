"""Button: press the goal button among four; a new goal button is drawn each time (reference sections 2-6).

Reward per step: ``(d_prev - d) * 1.0`` with ``d`` the planar distance from the robot to the goal
button (the goal marker sits on it), plus ``1.0`` when any robot geom touches the goal button.
Then the goal button is drawn again uniformly among the four (it may repeat), the marker moves
onto it and a 10-step timer restarts. While the timer is non-zero the ``buttons_lidar`` entry
reads all zeros and wrong buttons cost nothing. The timer counts down once per step, after reward
and cost. A reset draws a goal button too but leaves the timer at 0, as the original does (its
``reset`` draws the goal, which starts the timer, then ``specific_reset`` zeroes it): the buttons
are seen in the first observation and a wrong press costs from the first step. Episodes last
1000 steps and never terminate early.

Levels: 0 the four buttons (unconstrained) and the marker in +-1; 1 in +-1.5 adds 4 hazards and
4 gremlins and constrains the buttons; 2 in +-1.8 has 8 hazards and 6 gremlins. Observation:
sensors, then ``buttons_lidar``, ``goal_lidar`` (, ``hazards_lidar``, ``gremlins_lidar``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np

from sg_torchrl.envs.navigation.objects import Buttons
from sg_torchrl.envs.navigation.tasks.goal import GoalTask

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.env import NavigationEnv

__all__ = ["ButtonTask"]


class ButtonTask(GoalTask):
    """Press goal buttons one after another (see the module docstring).

    A :class:`GoalTask` whose goal is the marker on the goal button: reached by touching that
    button, and followed by drawing a new goal button instead of moving the goal.
    """

    name: ClassVar[str] = "Button"

    def bind(self, env: NavigationEnv) -> None:
        super().bind(env)
        self.buttons = self.find(Buttons)
        self._buttons_lidar = env.observation_slices.get(f"{self.buttons.name}_lidar")

    def reset(self, env: NavigationEnv, indices: np.ndarray) -> None:
        for index in indices:
            self._press(env, int(index))
        self.buttons.timer[indices] = 0  # no resampling delay at the start of an episode
        super().reset(env, indices)

    def reached(self, env: NavigationEnv, distance: np.ndarray) -> np.ndarray:
        return self.buttons.goal_pressed(env.scene)

    def reached_one(self, env: NavigationEnv, distance: float) -> bool:
        """:meth:`reached` of one simulator: the goal button's count among the step's shared contacts
        (:meth:`Buttons.goal_pressed_one <sg_torchrl.envs.navigation.objects.buttons.Buttons.goal_pressed_one>`)."""
        if type(self).reached is not ButtonTask.reached:
            return super().reached_one(env, distance)
        return self.buttons.goal_pressed_one(env.scene)

    def next_goal(self, env: NavigationEnv, index: int) -> bool:
        self._press(env, index)
        return True

    def _press(self, env: NavigationEnv, index: int) -> None:
        """Draw simulator ``index``'s goal button, restart its timer, move the marker onto the button."""
        xy = self.buttons.choose_goal(env.scene, index, env.rng(index))
        self.goal.move(env.scene, index, 0, xy)

    def after_step(self, env: NavigationEnv) -> np.ndarray:
        self.buttons.tick()  # after reward and cost, before a pressed goal restarts the timer
        return super().after_step(env)

    def after_step_one(self, env: NavigationEnv) -> bool:
        """:meth:`after_step` of one simulator: the timer's tick on a Python int, then the goal events
        (:meth:`GoalTask.after_step_one`); a subclass with its own :meth:`after_step` takes that one."""
        if type(self).after_step is not ButtonTask.after_step:
            return bool(self.after_step(env)[0])
        self.buttons.tick_one()
        return self._goal_events_one(env)

    def after_observe(self, env: NavigationEnv, observation: np.ndarray) -> None:
        timer = self.buttons.timer
        if self._buttons_lidar is not None and np.count_nonzero(timer):  # no timer running: the masked write is a no-op
            observation[timer > 0, self._buttons_lidar] = 0.0
