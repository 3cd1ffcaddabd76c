"""``SafeRescaleAction``: actions given in ``[min_action, max_action]``, mapped affinely to the env's bounds."""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np

from sg_torchrl.safety_gymnasium.wrappers.base import ForwardingWrapper

__all__ = ["SafeRescaleAction"]


class SafeRescaleAction(ForwardingWrapper, gymnasium.ActionWrapper, gymnasium.utils.RecordConstructorArgs):
    """Take actions in ``[min_action, max_action]`` (scalars or arrays of the action's shape) and map
    them affinely onto the env's ``Box`` action bounds.

    Unlike the original, which left ``action_space`` as the env's, the wrapper's ``action_space`` is
    the box it accepts (as gymnasium's ``RescaleAction``), so ``env.action_space.sample()`` gives
    actions it maps correctly.

    Raises:
        TypeError: the env's action space is not a ``Box``.
        ValueError: the bounds do not broadcast to the action's shape, or ``min_action >= max_action``
            somewhere.
    """

    def __init__(self, env: gymnasium.Env, min_action: float | int | np.ndarray,
                 max_action: float | int | np.ndarray) -> None:
        gymnasium.utils.RecordConstructorArgs.__init__(self, min_action=min_action, max_action=max_action)
        gymnasium.ActionWrapper.__init__(self, env)
        space = env.action_space
        if not isinstance(space, gymnasium.spaces.Box):
            raise TypeError(f"SafeRescaleAction needs a Box action space, got {space}")
        try:
            self.min_action = np.zeros(space.shape, dtype=space.dtype) + min_action
            self.max_action = np.zeros(space.shape, dtype=space.dtype) + max_action
        except ValueError as error:
            raise ValueError(f"min_action / max_action do not fit the action shape {space.shape}: {error}") from None
        if self.min_action.shape != space.shape or self.max_action.shape != space.shape:
            raise ValueError(f"min_action / max_action must broadcast to the action shape {space.shape}")
        if not np.all(self.min_action < self.max_action):
            raise ValueError(f"min_action must be below max_action everywhere, got {min_action} and {max_action}")
        self.action_space = gymnasium.spaces.Box(self.min_action, self.max_action, dtype=space.dtype)

    def action(self, action: Any) -> np.ndarray:
        """The env's action for ``action`` given in ``[min_action, max_action]``."""
        low, high = self.env.action_space.low, self.env.action_space.high
        return low + (high - low) * ((np.asarray(action) - self.min_action) / (self.max_action - self.min_action))
