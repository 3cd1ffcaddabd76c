"""Safety-Gymnasium's wrappers (``safety_gymnasium.wrappers``) for 6-tuple steps on current gymnasium.

======================================  ==========================================================
:class:`SafeAutoResetWrapper`           reset within the step that ends an episode; the finished
                                        episode's ``final_observation`` / ``final_info``
:class:`SafeTimeLimit`                  truncate after ``max_episode_steps`` (``spec`` reports it)
:class:`SafePassiveEnvChecker`          gymnasium's passive checks, for the 6-tuple step
:class:`SafetyGymnasium2Gymnasium`      6-tuple -> gymnasium 5-tuple, cost in ``info["cost"]``
:class:`Gymnasium2SafetyGymnasium`      gymnasium 5-tuple with ``info["cost"]`` -> 6-tuple
:func:`with_gymnasium_wrappers`         apply gymnasium's own wrappers to a 6-tuple env
:class:`SafeNormalizeObservation`       running observation normalisation (single or vector env)
:class:`SafeNormalizeReward` / ``Cost`` reward / cost scaled by the std of its discounted return
:class:`SafeUnsqueeze`                  a leading batch dimension of 1 on every output
:class:`SafeRescaleAction`              actions in ``[min_action, max_action]`` mapped to the bounds
======================================  ==========================================================

Like gymnasium 0.28's wrappers (and unlike 1.x's), each forwards the read of a public attribute it
does not have to the env inside (``env.obs_rms`` through ``SafeUnsqueeze``), and records its
arguments, so ``gymnasium.make(env.spec)`` can rebuild it (:mod:`.base`).
"""

from __future__ import annotations

from typing import Callable

import gymnasium

from sg_torchrl.safety_gymnasium.wrappers.autoreset import SafeAutoResetWrapper
from sg_torchrl.safety_gymnasium.wrappers.env_checker import SafePassiveEnvChecker
from sg_torchrl.safety_gymnasium.wrappers.gymnasium_conversion import (
    Gymnasium2SafetyGymnasium,
    SafetyGymnasium2Gymnasium,
)
from sg_torchrl.safety_gymnasium.wrappers.normalize import (
    SafeNormalizeCost,
    SafeNormalizeObservation,
    SafeNormalizeReward,
)
from sg_torchrl.safety_gymnasium.wrappers.rescale_action import SafeRescaleAction
from sg_torchrl.safety_gymnasium.wrappers.time_limit import SafeTimeLimit
from sg_torchrl.safety_gymnasium.wrappers.unsqueeze import SafeUnsqueeze

__all__ = [
    "Gymnasium2SafetyGymnasium",
    "SafeAutoResetWrapper",
    "SafeNormalizeCost",
    "SafeNormalizeObservation",
    "SafeNormalizeReward",
    "SafePassiveEnvChecker",
    "SafeRescaleAction",
    "SafeTimeLimit",
    "SafeUnsqueeze",
    "SafetyGymnasium2Gymnasium",
    "with_gymnasium_wrappers",
]


def with_gymnasium_wrappers(env: gymnasium.Env, *wrappers: Callable[[gymnasium.Env], gymnasium.Env]) -> gymnasium.Env:
    """Apply gymnasium wrappers (classes or ``functools.partial`` of them) to a 6-tuple env.

    The env is converted to gymnasium's 5-tuple (:class:`SafetyGymnasium2Gymnasium`), wrapped with
    each of ``wrappers`` in order, and converted back (:class:`Gymnasium2SafetyGymnasium`), the cost
    travelling in ``info["cost"]`` in between.

    Raises:
        TypeError: a wrapper is not callable.
    """
    for wrapper in (SafetyGymnasium2Gymnasium, *wrappers, Gymnasium2SafetyGymnasium):
        if not callable(wrapper):
            raise TypeError(f"wrapper {wrapper!r} is not callable (pass wrapper classes or functools.partial)")
        env = wrapper(env)
    return env
