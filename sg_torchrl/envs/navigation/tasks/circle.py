"""Circle: run around a circle of radius 1.5, inside boundary walls (reference sections 4, 6).

Reward per step (clipped to +-10): ``0.1 * ((-u * y + v * x) / rho) / (1 + |rho - 1.5|)``, with
``(x, y)`` the robot's position relative to the circle's centre (the origin), ``rho`` its norm and
``(u, v)`` the robot's linear velocity in the world frame: the counter-clockwise speed around the
centre, damped by the distance from the rim. No goal events, no termination; 500 steps. Only the
circle is observed, through ``circle_lidar`` with lidar range 6; the walls are not.

Levels: the robot starts in ``[-0.8, 0.8]^2`` (keep-out 0) with the circle alone (0), between two
walls at ``x = +-1.125`` (1), or inside four walls at ``x, y = +-1.125`` (2); crossing a wall costs.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from sg_torchrl.envs.navigation.objects import CircleZone, NavObject
from sg_torchrl.envs.navigation.tasks.base import Task

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.env import NavigationEnv

__all__ = ["CircleTask"]

try:  # what np.einsum(..., optimize=False) returns, called without its Python wrapper (a microsecond a step)
    from numpy._core.multiarray import c_einsum as _einsum
except ImportError:  # another numpy layout: the public function, the same kernel
    _einsum = np.einsum


class CircleTask(Task):
    """Circle around the :class:`CircleZone` (see the module docstring)."""

    name: ClassVar[str] = "Circle"
    max_episode_steps: ClassVar[int] = 500
    lidar_max_dist: ClassVar[float | None] = 6.0

    def __init__(
        self,
        level: int,
        *,
        objects: Sequence[NavObject],
        extents: float | Sequence[float] = 2.0,  # unused: the circle and the walls stand at fixed places
        agent_placements: Sequence[Sequence[float]] | None = ((-0.8, -0.8, 0.8, 0.8),),
        agent_keepout: float | None = 0.0,
    ) -> None:
        super().__init__(level, extents=extents, objects=objects, agent_placements=agent_placements,
                         agent_keepout=agent_keepout)

    def bind(self, env: NavigationEnv) -> None:
        self.zone = self.find(CircleZone)
        velocimeter = env.scene.model.sensor("velocimeter")
        self._velocimeter = slice(int(velocimeter.adr[0]), int(velocimeter.adr[0]) + 3)
        # The operands of agent_velocity taken once: the state cache is filled in place, so these views
        # follow every step (each fresh view costs an indexing).
        self._rotation = env.scene.agent_mat()[:, :2]
        self._local = env.scene.sensordata()[:, self._velocimeter]
        self._velocity_one = np.empty((1, 2))
        # reward_one's float form applies unless a subclass changes what it computes
        self._reward_floats = (type(self).reward is CircleTask.reward
                               and type(self).agent_velocity is CircleTask.agent_velocity)

    def agent_velocity(self, env: NavigationEnv) -> np.ndarray:
        """Linear velocity of the robot's root in the world frame, ``(N, 2)`` (its velocimeter, rotated)."""
        return _einsum("nij,nj->ni", self._rotation, self._local)

    def reward(self, env: NavigationEnv) -> np.ndarray:
        x, y = (env.scene.agent_xy() - self.zone.positions(env.scene)[:, 0]).T
        u, v = self.agent_velocity(env).T
        rho = np.maximum(np.hypot(x, y), 1e-12)  # at the very centre the tangential speed is 0 / 0: read 0
        return self.zone.reward_factor * ((-u * y + v * x) / rho) / (1.0 + np.abs(rho - self.zone.size))

    def reward_one(self, env: NavigationEnv) -> float:
        """:meth:`reward` of one simulator on Python floats (the one-simulator step's): the same
        differences, products, quotients and sums in the same order. The rotation of the velocity stays
        ``np.einsum``'s kernel (its sum of three products is a vector reduction, not a left-to-right sum,
        and its order may depend on the CPU numpy dispatches to) and the norm ``np.hypot``'s (libm's, which
        :func:`math.hypot` is not), each on the same operands; ``np.maximum``'s floor keeps NaN, as the
        comparison below does."""
        if not self._reward_floats:
            return super().reward_one(env)
        velocity = self._velocity_one
        _einsum("nij,nj->ni", self._rotation, self._local, out=velocity)
        u, v = velocity[0].tolist()
        ax, ay = env.scene.agent_xy()[0].tolist()
        cx, cy = self.zone.positions(env.scene)[0, 0].tolist()
        x, y = ax - cx, ay - cy
        rho = float(np.hypot(x, y))
        if rho < 1e-12:
            rho = 1e-12
        return self.zone.reward_factor * ((-u * y + v * x) / rho) / (1.0 + abs(rho - self.zone.size))
