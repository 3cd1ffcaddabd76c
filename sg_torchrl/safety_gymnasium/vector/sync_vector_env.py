"""``SafetySyncVectorEnv``: several 6-tuple envs stepped one after another in this process."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import gymnasium

from sg_torchrl.safety_gymnasium.vector.utils import autoreset_step, set_wrapper_attr, wrapper_attr
from sg_torchrl.safety_gymnasium.vector.vector_env import SafeVectorEnv

__all__ = ["SafetySyncVectorEnv"]


class SafetySyncVectorEnv(SafeVectorEnv):
    """Vector env of the envs ``env_fns`` build, stepped serially (the API of :class:`SafeVectorEnv`).

    Args:
        env_fns: callables that each build one env with Safety-Gymnasium's 6-tuple ``step``.
        observation_space / action_space: one env's spaces (default: the first env's).
        copy: return a copy of the batched observations (else a buffer the next step overwrites).

    Raises:
        ValueError: no env functions, or envs whose spaces differ from the given ones.
    """

    def __init__(self, env_fns: Iterable[Callable[[], gymnasium.Env]], observation_space: gymnasium.Space | None = None,
                 action_space: gymnasium.Space | None = None, copy: bool = True) -> None:
        self.env_fns = list(env_fns)
        if not self.env_fns:
            raise ValueError("SafetySyncVectorEnv needs at least one env function")
        self.envs = [env_fn() for env_fn in self.env_fns]
        first = self.envs[0]
        observation_space = observation_space or first.observation_space
        action_space = action_space or first.action_space
        for index, env in enumerate(self.envs):
            if env.observation_space != observation_space or env.action_space != action_space:
                raise ValueError(f"env {index}'s spaces differ from the vector env's: "
                                 f"{env.observation_space} / {env.action_space}")
        self._setup(len(self.envs), observation_space, action_space, first.metadata,
                    getattr(first, "render_mode", None), getattr(first, "spec", None), copy)

    def _reset_envs(self, seeds: list[int | None], options: dict | None) -> list[tuple[Any, dict]]:
        kwargs = {} if options is None else {"options": options}
        return [env.reset(seed=seed, **kwargs) for env, seed in zip(self.envs, seeds)]

    def _step_envs(self, actions: list[Any]) -> list[tuple]:
        return [autoreset_step(env, action) for env, action in zip(self.envs, actions)]

    def _images(self) -> list[Any]:
        return [env.render() for env in self.envs]

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple:
        """Call method ``name`` of every env (or read attribute ``name``; through wrappers, as
        gymnasium 0.28's wrappers forwarded attributes): a tuple of the results."""
        self._check_open()
        results = []
        for env in self.envs:
            attribute = wrapper_attr(env, name)
            results.append(attribute(*args, **kwargs) if callable(attribute) else attribute)
        return tuple(results)

    def _set_attrs(self, name: str, values: list[Any]) -> None:
        for env, value in zip(self.envs, values):
            set_wrapper_attr(env, name, value)

    def _close_envs(self) -> None:
        for env in self.envs:
            env.close()
