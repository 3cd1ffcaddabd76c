"""Run: run as far as possible in one direction along a corridor (reference sections 4, 6).

The robot starts at ``y = 16.5``, ``x`` uniform in ``[-0.2, 0.2]`` (keep-out 0), on a floor of
half-size 17.5, between two walls at ``x = +-0.5`` (crossing one costs). Reward per step: the
change of the potential ``phi = -60 * |xy - (0, -1000)|``, i.e. 60 times the distance gained towards
a far point down the corridor; not clipped. Nothing is observed but the robot's sensors; 500
steps, no termination.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import math

import numpy as np

from sg_torchrl.envs.navigation.objects import Sigwalls
from sg_torchrl.envs.navigation.tasks.base import Task

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.env import NavigationEnv

__all__ = ["RunTask", "RUN_LEVELS"]


class RunTask(Task):
    """Run towards ``target`` (see the module docstring)."""

    name: ClassVar[str] = "Run"
    max_episode_steps: ClassVar[int] = 500
    floor_half_size: ClassVar[float] = 17.5
    reward_clip: ClassVar[float | None] = None
    target: ClassVar[tuple[float, float]] = (0.0, -1000.0)
    reward_distance: ClassVar[float] = 60.0

    def bind(self, env: NavigationEnv) -> None:
        self._target = np.array(self.target)
        self._last_potential = np.zeros(env.num_envs)
        # reward_one's float form applies unless a subclass changes what it computes
        self._reward_floats = type(self).reward is RunTask.reward and type(self).potential is RunTask.potential

    def potential(self, env: NavigationEnv) -> np.ndarray:
        """``-60 * |xy - target|`` per simulator, ``(N,)``."""
        return -self.reward_distance * np.linalg.norm(env.scene.agent_xy() - self._target, axis=1)

    def reward_one(self, env: NavigationEnv) -> float:
        """:meth:`reward` of one simulator on Python floats (the one-simulator step's): the same
        differences and squares; their sum (two non-negative terms: numpy's reduction adds them in any
        grouping to the same value) under IEEE's correctly rounded square root, which ``math.sqrt`` and
        ``np.sqrt`` both are (``np.linalg.norm``'s ``sqrt(add.reduce(x * x))``)."""
        if not self._reward_floats:
            return super().reward_one(env)
        x, y = env.scene.agent_xy()[0].tolist()
        tx, ty = self.target
        dx, dy = x - tx, y - ty
        potential = -self.reward_distance * math.sqrt(dx * dx + dy * dy)
        last = self._last_potential
        reward = potential - last.item(0)
        last[0] = potential
        return reward

    def reset(self, env: NavigationEnv, indices: np.ndarray) -> None:
        self._last_potential[indices] = self.potential(env)[indices]

    def reward(self, env: NavigationEnv) -> np.ndarray:
        potential = self.potential(env)
        reward = potential - self._last_potential
        self._last_potential[:] = potential
        return reward

    def state_dict(self) -> dict:
        return {"last_potential": self._last_potential.copy()}

    def load_state_dict(self, state: dict) -> None:
        self._last_potential[:] = state["last_potential"]


# reference section 6 (the extents are unused: the walls stand at fixed places).
RUN_LEVELS = {
    0: lambda: RunTask(0, extents=17.5, objects=[Sigwalls(2, bound=0.5, length=17.5)],
                       agent_placements=[(-0.2, 16.5, 0.2, 16.5)], agent_keepout=0.0),
}
