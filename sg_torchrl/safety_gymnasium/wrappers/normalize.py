"""Running normalisation of observations, rewards and costs, for single and vector envs.

The behaviour of gymnasium 0.28's ``NormalizeObservation`` / ``NormalizeReward`` (which the
original subclassed) for 6-tuple steps, written for current gymnasium, whose wrappers of those names
changed: each wrapper works on one env or on a vector env of this package (``is_vector_env``).

* :class:`SafeNormalizeObservation`: every observation of ``reset`` and ``step`` updates running
  statistics and is returned as ``(obs - mean) / sqrt(var + epsilon)``. A ``final_observation`` in
  the info (autoreset) is normalised with the current statistics (without updating them); the raw
  one is kept as ``info["original_final_observation"]``.
* :class:`SafeNormalizeReward` / :class:`SafeNormalizeCost`: the reward (cost) is divided by the
  running standard deviation of its discounted return (``gamma``), which restarts after a terminated
  step.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium.wrappers.utils import RunningMeanStd

from sg_torchrl.safety_gymnasium.wrappers.base import SafeWrapper

__all__ = ["SafeNormalizeCost", "SafeNormalizeObservation", "SafeNormalizeReward"]


def _num_envs(env: gymnasium.Env) -> tuple[bool, int]:
    vector = bool(getattr(env, "is_vector_env", False))
    return vector, int(getattr(env, "num_envs", 1)) if vector else 1


class SafeNormalizeObservation(SafeWrapper):
    """Normalise observations with running statistics (module docstring); ``obs_rms`` holds them."""

    def __init__(self, env: gymnasium.Env, epsilon: float = 1e-8) -> None:
        super().__init__(env, epsilon=epsilon)
        self.is_vector_env, self.num_envs = _num_envs(env)
        space = env.single_observation_space if self.is_vector_env else env.observation_space
        if not isinstance(space, gymnasium.spaces.Box):
            raise TypeError(f"SafeNormalizeObservation needs a Box observation space, got {space}")
        self.obs_rms = RunningMeanStd(shape=space.shape)
        self.epsilon = epsilon

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        """Update the statistics with the batch ``obs`` and return it normalised."""
        self.obs_rms.update(obs)
        return self._scaled(obs)

    def _scaled(self, obs: np.ndarray) -> np.ndarray:
        return (obs - self.obs_rms.mean) / np.sqrt(self.obs_rms.var + self.epsilon)

    def _batch(self, obs: np.ndarray) -> np.ndarray:
        return self.normalize(obs) if self.is_vector_env else self.normalize(np.asarray([obs]))[0]

    def step(self, action: Any) -> tuple:
        obs, reward, cost, terminated, truncated, info = self.env.step(action)
        obs = self._batch(obs)
        if "final_observation" in info:
            final = info["final_observation"]
            info["original_final_observation"] = final
            if self.is_vector_env:
                mask = np.asarray(info.get("_final_observation", [o is not None for o in final]), dtype=bool)
                normalised = np.array(final, dtype=object)
                for index in np.flatnonzero(mask):
                    normalised[index] = self._scaled(np.asarray(final[index]))
                info["final_observation"] = normalised
            else:
                info["final_observation"] = self._scaled(np.asarray(final))
        return obs, reward, cost, terminated, truncated, info

    def reset(self, **kwargs: Any) -> tuple:
        obs, info = self.env.reset(**kwargs)
        return self._batch(obs), info


class _ReturnNormalizer(SafeWrapper):
    """Divides one output of ``step`` (index :attr:`_position`) by the std of its discounted return."""

    _position: int

    def __init__(self, env: gymnasium.Env, gamma: float = 0.99, epsilon: float = 1e-8) -> None:
        super().__init__(env, gamma=gamma, epsilon=epsilon)
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        self.is_vector_env, self.num_envs = _num_envs(env)
        self.return_rms = RunningMeanStd(shape=())
        self.returns = np.zeros(self.num_envs)
        self.gamma = gamma
        self.epsilon = epsilon

    def normalize(self, values: np.ndarray) -> np.ndarray:
        """``values`` divided by the running std of the returns (updated with the current returns)."""
        self.return_rms.update(self.returns)
        return values / np.sqrt(self.return_rms.var + self.epsilon)

    def step(self, action: Any) -> tuple:
        result = list(self.env.step(action))
        values = np.asarray(result[self._position], dtype=np.float64)
        if not self.is_vector_env:
            values = values.reshape(1)
        self.returns = self.returns * self.gamma * (1 - np.asarray(result[3], dtype=np.float64)) + values
        values = self.normalize(values)
        result[self._position] = values if self.is_vector_env else values[0]
        return tuple(result)


class SafeNormalizeReward(_ReturnNormalizer):
    """Scale rewards by the running std of the discounted reward return (module docstring)."""

    _position = 1


class SafeNormalizeCost(_ReturnNormalizer):
    """Scale costs by the running std of the discounted cost return (module docstring)."""

    _position = 2
