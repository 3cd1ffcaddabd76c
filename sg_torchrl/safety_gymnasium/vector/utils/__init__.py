"""Helpers of the vector envs: gymnasium 0.28's info batching and the same-step autoreset."""

from __future__ import annotations

from typing import Any

import numpy as np

from sg_torchrl.safety_gymnasium.vector.utils.tile_images import tile_images

__all__ = ["add_info", "autoreset_step", "set_wrapper_attr", "tile_images", "wrapper_attr"]


def add_info(infos: dict[str, Any], info: dict[str, Any], env_index: int, num_envs: int) -> dict[str, Any]:
    """Merge env ``env_index``'s ``info`` into the batched ``infos`` (in place; returned).

    The layout is gymnasium 0.28's, which Safety-Gymnasium's users read: each key holds an array
    over the envs (python and numpy numbers in an array of their type, anything else, arrays and
    dicts included, in an object array with ``None`` for envs without the key) and ``"_<key>"`` a
    bool mask of the envs that set it. So ``infos["final_observation"][i]`` is env ``i``'s final
    observation or ``None``, and ``infos["_final_observation"]`` says which envs finished.
    """
    for key, value in info.items():
        if key not in infos:
            kind = type(value)
            if kind in (int, float, bool) or issubclass(kind, np.number):
                infos[key] = np.zeros(num_envs, dtype=kind)
            else:
                infos[key] = np.full(num_envs, None, dtype=object)
            infos[f"_{key}"] = np.zeros(num_envs, dtype=bool)
        infos[key][env_index] = value
        infos[f"_{key}"][env_index] = True
    return infos


def autoreset_step(env: Any, action: Any) -> tuple:
    """Step ``env``; if the episode ends, reset it within the step (Safety-Gymnasium's vector envs).

    Returns the finished step's reward, **cost** and flags with the new episode's first observation
    and the reset's info, to which ``final_observation`` and ``final_info`` (the finished step's
    observation and info) are added.
    """
    obs, reward, cost, terminated, truncated, info = env.step(action)
    if terminated or truncated:
        final_obs, final_info = obs, info
        obs, info = env.reset()
        info = dict(info)
        info["final_observation"] = final_obs
        info["final_info"] = final_info
    return obs, reward, cost, terminated, truncated, info


def wrapper_attr(env: Any, name: str) -> Any:
    """Attribute ``name`` of ``env`` or of the first env inside its wrappers that has it.

    Gymnasium 0.28's wrappers forwarded unknown attributes to the env inside; gymnasium 1.x's do not
    (``get_wrapper_attr`` does): the vector envs' ``call`` / ``get_attr`` read through it.
    """
    getter = getattr(env, "get_wrapper_attr", None)
    return getter(name) if getter is not None else getattr(env, name)


def set_wrapper_attr(env: Any, name: str, value: Any) -> None:
    """Set attribute ``name`` where :func:`wrapper_attr` finds it (else on ``env`` itself)."""
    setter = getattr(env, "set_wrapper_attr", None)
    if setter is not None:
        setter(name, value)
    else:
        setattr(env, name, value)
