"""``SafeTimeLimit``: gymnasium's ``TimeLimit`` for 6-tuple steps."""

from __future__ import annotations

from typing import Any

from gymnasium.error import ResetNeeded
from gymnasium.wrappers import TimeLimit

from sg_torchrl.safety_gymnasium.wrappers.base import ForwardingWrapper

__all__ = ["SafeTimeLimit"]


class SafeTimeLimit(ForwardingWrapper, TimeLimit):
    """Truncate the episode after ``max_episode_steps`` steps (``truncated=True`` on that step).

    A subclass of gymnasium's ``TimeLimit``, so ``env.spec.max_episode_steps`` reports the limit
    (OmniSafe and other clients read it) and ``isinstance(env, TimeLimit)`` holds; only ``step``
    changes, to pass the ``cost`` through.
    """

    def step(self, action: Any) -> tuple:
        """``(obs, reward, cost, terminated, truncated, info)`` with ``truncated`` set at the limit."""
        if self._elapsed_steps is None:
            raise ResetNeeded("SafeTimeLimit: call reset() before step()")
        obs, reward, cost, terminated, truncated, info = self.env.step(action)
        self._elapsed_steps += 1
        if self._elapsed_steps >= self._max_episode_steps:
            truncated = True
        return obs, reward, cost, terminated, truncated, info

