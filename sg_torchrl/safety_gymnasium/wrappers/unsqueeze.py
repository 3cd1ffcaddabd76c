"""``SafeUnsqueeze``: a batch dimension of one on every output, for training code written for vector envs."""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np

from sg_torchrl.safety_gymnasium.wrappers.base import SafeWrapper

__all__ = ["SafeUnsqueeze"]


def _unsqueeze_arrays(info: dict) -> dict:
    for key, value in info.items():
        if isinstance(value, np.ndarray):
            info[key] = np.expand_dims(value, axis=0)
    return info


class SafeUnsqueeze(SafeWrapper):
    """Give one env's outputs a leading dimension of 1: the observation ``(1, ...)``, the reward,
    cost and flags ``(1,)`` arrays, and every numpy array in the info (e.g. ``final_observation``).
    The spaces are unchanged.

    Raises:
        ValueError: ``env`` is a vector env (it has a batch dimension already).
    """

    def __init__(self, env: gymnasium.Env) -> None:
        super().__init__(env)
        if getattr(env, "is_vector_env", False):
            raise ValueError("SafeUnsqueeze is for a single env; a vector env already has a batch dimension")
        self.is_vector_env = False

    def step(self, action: Any) -> tuple:
        obs, reward, cost, terminated, truncated, info = self.env.step(action)
        obs, reward, cost, terminated, truncated = (
            np.expand_dims(value, axis=0) for value in (obs, reward, cost, terminated, truncated))
        return obs, reward, cost, terminated, truncated, _unsqueeze_arrays(info)

    def reset(self, **kwargs: Any) -> tuple:
        obs, info = self.env.reset(**kwargs)
        return np.expand_dims(obs, axis=0), _unsqueeze_arrays(info)
