"""Converting between Safety-Gymnasium's 6-tuple steps and gymnasium's 5-tuple steps."""

from __future__ import annotations

from typing import Any

import gymnasium

from sg_torchrl.envs.info import numpy_scalar_info
from sg_torchrl.safety_gymnasium.wrappers.base import SafeWrapper

__all__ = ["Gymnasium2SafetyGymnasium", "SafetyGymnasium2Gymnasium", "make_gymnasium_environment"]


class SafetyGymnasium2Gymnasium(SafeWrapper):
    """A 6-tuple env seen as a gymnasium env: ``step`` returns ``(obs, reward, terminated, truncated,
    info)`` with the cost in ``info["cost"]`` (a warning if the info already held one), so gymnasium's
    own wrappers and vector envs can be used on it. The info's Python numbers become numpy scalars
    (:func:`sg_torchrl.envs.info.numpy_scalar_info`), which TorchRL's info readers accept."""

    def step(self, action: Any) -> tuple:
        obs, reward, cost, terminated, truncated, info = self.env.step(action)
        if "cost" in info:
            gymnasium.logger.warn("the info dict already holds a 'cost': SafetyGymnasium2Gymnasium overwrites it")
        info["cost"] = cost
        return obs, reward, terminated, truncated, numpy_scalar_info(info)


class Gymnasium2SafetyGymnasium(SafeWrapper):
    """A gymnasium env whose info carries ``"cost"`` seen as a Safety-Gymnasium env (6-tuple ``step``).

    Raises:
        ValueError: a step's info has no ``"cost"``.
    """

    def step(self, action: Any) -> tuple:
        obs, reward, terminated, truncated, info = self.env.step(action)
        if "cost" not in info:
            raise ValueError("the info dict has no 'cost', which Gymnasium2SafetyGymnasium needs "
                             f"(info keys: {sorted(info)})")
        return obs, reward, info["cost"], terminated, truncated, info


def make_gymnasium_environment(env_id: str, **kwargs: Any) -> gymnasium.Env:
    """``safety_gymnasium.make`` of the plain id behind a twin ``<Name>Gymnasium-v<k>``, as a gymnasium env.

    Raises:
        ValueError: ``env_id``'s name does not end in ``Gymnasium``.
    """
    from sg_torchrl.safety_gymnasium.registration import make

    name, dash, version = env_id.partition("-")
    if not name.endswith("Gymnasium"):
        raise ValueError(f"{env_id!r} is not a twin id '<Name>Gymnasium-v<k>'")
    return SafetyGymnasium2Gymnasium(make(f"{name[: -len('Gymnasium')]}{dash}{version}", **kwargs))
