"""``SafePassiveEnvChecker``: gymnasium's passive checker, knowing Safety-Gymnasium's 6-tuple step."""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import logger
from gymnasium.utils.passive_env_checker import check_obs
from gymnasium.wrappers import PassiveEnvChecker

from sg_torchrl.safety_gymnasium.wrappers.base import ForwardingWrapper

__all__ = ["SafePassiveEnvChecker", "env_step_passive_checker"]


class SafePassiveEnvChecker(ForwardingWrapper, PassiveEnvChecker):
    """Check the spaces at construction, the first ``reset`` and ``render`` (gymnasium's checks) and
    the first ``step`` as a 6-tuple (:func:`env_step_passive_checker`): warnings for doubtful values,
    errors for a malformed result. Later calls pass through unchecked."""

    def step(self, action: Any) -> tuple:
        if not self.checked_step:
            self.checked_step = True
            return env_step_passive_checker(self.env, action)
        return self.env.step(action)


def _check_scalar(name: str, value: Any) -> None:
    if not (np.issubdtype(type(value), np.integer) or np.issubdtype(type(value), np.floating)):
        logger.warn(f"the {name} returned by step() should be a float, int, np.integer or np.floating, "
                    f"got {type(value)}")
    elif not np.isfinite(value):
        logger.warn(f"the {name} returned by step() is {value}")


def env_step_passive_checker(env: Any, action: Any) -> tuple:
    """Step ``env`` once and check the result as Safety-Gymnasium's 6-tuple; return it unchanged.

    Raises:
        TypeError: the result is not a tuple, or its info is not a dict.
        ValueError: the tuple does not have 6 elements.
    """
    result = env.step(action)
    if not isinstance(result, tuple):
        raise TypeError(f"step() must return a tuple, got {type(result)}")
    if len(result) != 6:
        raise ValueError(f"step() must return the 6 elements (obs, reward, cost, terminated, truncated, info), "
                         f"got {len(result)}")
    obs, reward, cost, terminated, truncated, info = result
    for name, flag in (("terminated", terminated), ("truncated", truncated)):
        if not isinstance(flag, (bool, np.bool_)):
            logger.warn(f"`{name}` returned by step() should be a bool, got {type(flag)}")
    check_obs(obs, env.observation_space, "step")
    _check_scalar("reward", reward)
    _check_scalar("cost", cost)
    if not isinstance(info, dict):
        raise TypeError(f"the info returned by step() must be a dict, got {type(info)}")
    return result
