"""``SafeAutoResetWrapper``: reset within the step that ends an episode (Safety-Gymnasium's autoreset)."""

from __future__ import annotations

from typing import Any

from sg_torchrl.safety_gymnasium.wrappers.base import SafeWrapper

__all__ = ["SafeAutoResetWrapper"]


class SafeAutoResetWrapper(SafeWrapper):
    """Reset the env inside the ``step`` that ends an episode (terminated or truncated).

    That step returns the **new** episode's first observation and the reset's info, together with
    the finished step's reward, **cost**, ``terminated`` and ``truncated``; the finished episode's last
    observation and info are ``info["final_observation"]`` and ``info["final_info"]``. This is
    gymnasium 0.28's ``AutoResetWrapper`` (same-step reset) for 6-tuple steps, the behaviour the
    original's users rely on; gymnasium 1.x's ``Autoreset`` resets on the *next* step instead.

    Raises:
        ValueError: the env's reset info already holds ``final_observation`` or ``final_info``.
    """

    def step(self, action: Any) -> tuple:
        """``(obs, reward, cost, terminated, truncated, info)``, reset within the step at an episode's end."""
        obs, reward, cost, terminated, truncated, info = self.env.step(action)
        if terminated or truncated:
            new_obs, new_info = self.env.reset()
            clashes = sorted({"final_observation", "final_info"} & set(new_info))
            if clashes:
                raise ValueError(f"the env's reset info holds {clashes}, which SafeAutoResetWrapper sets itself")
            new_info["final_observation"] = obs
            new_info["final_info"] = info
            obs, info = new_obs, new_info
        return obs, reward, cost, terminated, truncated, info
