"""Safety-Gymnasium's vector envs (``safety_gymnasium.vector``): batched 6-tuple steps, same-step autoreset.

>>> envs = safety_gymnasium.vector.make("SafetyPointGoal1-v0", num_envs=4, asynchronous=False)
>>> obs, infos = envs.reset(seed=0)
>>> obs, rewards, costs, terminateds, truncateds, infos = envs.step(envs.action_space.sample())

:class:`SafetySyncVectorEnv` steps the envs in this process, :class:`SafetyAsyncVectorEnv` in worker
processes (with an explicit start method, see :mod:`.async_vector_env`). Both reset an env within
the step that ends its episode and report that step's reward, cost and flags with the finished
episode's ``final_observation`` / ``final_info`` (:class:`~.vector_env.SafeVectorEnv`), keeping
the cost of the final step. For many simulators in one process, ``sg_torchrl.make(env_id,
num_envs=N)`` (one batched TorchRL env) is much faster than either.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from gymnasium.vector import VectorEnv

from sg_torchrl.safety_gymnasium.vector.async_vector_env import SafetyAsyncVectorEnv
from sg_torchrl.safety_gymnasium.vector.sync_vector_env import SafetySyncVectorEnv

__all__ = ["SafetyAsyncVectorEnv", "SafetySyncVectorEnv", "VectorEnv", "make"]


def make(env_id: str, num_envs: int = 1, asynchronous: bool = True,
         wrappers: Callable | Iterable[Callable] | None = None, disable_env_checker: bool | None = None,
         **kwargs: Any) -> SafetySyncVectorEnv | SafetyAsyncVectorEnv:
    """A vector env of ``num_envs`` copies of ``safety_gymnasium.make(env_id, **kwargs)``.

    Args:
        env_id: an id of ``safety_gymnasium.make``.
        num_envs: number of envs.
        asynchronous: :class:`SafetyAsyncVectorEnv` (worker processes) or :class:`SafetySyncVectorEnv`.
        wrappers: a wrapper (callable taking and returning an env) or a list of them, applied to each env.
        disable_env_checker: whether to leave out the passive checker (it runs on the first env only).
        **kwargs: ``safety_gymnasium.make``'s keyword arguments (``max_episode_steps``, render options, ...).

    Raises:
        ValueError: ``num_envs`` is not a positive integer.
        TypeError: a wrapper is not callable.
    """
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
    if wrappers is None:
        wrapper_list: list[Callable] = []
    elif callable(wrappers):
        wrapper_list = [wrappers]
    else:
        wrapper_list = list(wrappers)
    for wrapper in wrapper_list:
        if not callable(wrapper):
            raise TypeError(f"wrapper {wrapper!r} is not callable")

    def env_fn(index: int) -> Callable:
        def build():
            from sg_torchrl.safety_gymnasium.registration import make as safety_make

            env = safety_make(env_id, disable_env_checker=True if index > 0 else disable_env_checker, **kwargs)
            for wrapper in wrapper_list:
                env = wrapper(env)
            return env

        return build

    env_fns = [env_fn(index) for index in range(num_envs)]
    return SafetyAsyncVectorEnv(env_fns) if asynchronous else SafetySyncVectorEnv(env_fns)
