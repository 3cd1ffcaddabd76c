"""What the sync and async vector envs share: spaces, batching, the 6-tuple ``step`` and 0.28's API."""

from __future__ import annotations

from copy import deepcopy
from typing import Any

import gymnasium
import numpy as np
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array

from sg_torchrl.safety_gymnasium.vector.utils import add_info, tile_images

__all__ = ["SafeVectorEnv"]


class SafeVectorEnv(gymnasium.vector.VectorEnv, gymnasium.Env):
    """Base of :class:`~.SafetySyncVectorEnv` and :class:`~.SafetyAsyncVectorEnv`.

    Both a gymnasium ``VectorEnv`` (``num_envs``, ``single_observation_space``,
    ``single_action_space``, batched ``observation_space`` / ``action_space``) and a ``gymnasium.Env``
    with ``is_vector_env = True``, as vector envs were in gymnasium 0.28: Safety-Gymnasium's wrappers
    (``SafeNormalizeObservation``, ...) and its users' own ``gymnasium.Wrapper`` subclasses wrap them.

    ``step(actions)`` returns ``(obs, rewards, costs, terminateds, truncateds, infos)``: batched
    observations, ``float64`` rewards and costs, ``bool`` flags, and the infos batched as gymnasium
    0.28 did (:func:`~.utils.add_info`). An env whose episode ends is reset within the step: its row
    holds the new episode's first observation, while its reward, cost and flags are those of the
    finished step, and ``infos["final_observation"][i]`` / ``infos["final_info"][i]`` its last
    observation and info. ``reset(seed=s)`` seeds env ``i`` with ``s + i`` (or takes one seed per env).
    Subclasses implement :meth:`_reset_envs`, :meth:`_step_envs`, :meth:`_images`, :meth:`call`,
    :meth:`set_attr` and :meth:`_close_envs`.
    """

    is_vector_env = True

    def _setup(self, num_envs: int, single_observation_space: gymnasium.Space, single_action_space: gymnasium.Space,
               metadata: dict, render_mode: str | None, spec: Any, copy: bool) -> None:
        self.num_envs = num_envs
        self.single_observation_space = single_observation_space
        self.single_action_space = single_action_space
        self.observation_space = batch_space(single_observation_space, num_envs)
        self.action_space = batch_space(single_action_space, num_envs)
        self.metadata = dict(metadata or {})
        self.render_mode = render_mode
        self.spec = spec
        self.copy = copy
        self.closed = False
        self._observations = create_empty_array(single_observation_space, n=num_envs, fn=np.zeros)
        self._actions = None

    # ------------------------------------------------------------------ what subclasses provide
    def _reset_envs(self, seeds: list[int | None], options: dict | None) -> list[tuple[Any, dict]]:
        raise NotImplementedError

    def _step_envs(self, actions: list[Any]) -> list[tuple]:
        raise NotImplementedError

    def _images(self) -> list[Any]:
        raise NotImplementedError

    def _close_envs(self) -> None:
        raise NotImplementedError

    def _set_attrs(self, name: str, values: list[Any]) -> None:
        """Set attribute ``name`` of env ``i`` to ``values[i]`` (one value per env, checked by :meth:`set_attr`)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | list[int | None] | None = None, options: dict | None = None) -> tuple:
        """Reset every env: ``(obs, infos)``; ``seed``: an int (env ``i`` gets ``seed + i``) or one per env."""
        self._check_open()
        if seed is None or isinstance(seed, (int, np.integer)):
            seeds = [None if seed is None else int(seed) + index for index in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"{len(seeds)} seeds for {self.num_envs} envs")
        results = self._reset_envs(seeds, options)
        infos: dict[str, Any] = {}
        for index, (_, info) in enumerate(results):
            add_info(infos, info, index, self.num_envs)
        return self._batch([obs for obs, _ in results]), infos

    def step(self, actions: Any) -> tuple:
        """Step every env (same-step autoreset): ``(obs, rewards, costs, terminateds, truncateds, infos)``."""
        self._check_open()
        per_env = list(gymnasium.vector.utils.iterate(self.action_space, actions))
        if len(per_env) != self.num_envs:
            raise ValueError(f"actions hold {len(per_env)} envs' actions, expected {self.num_envs}")
        results = self._step_envs(per_env)
        infos: dict[str, Any] = {}
        for index, result in enumerate(results):
            add_info(infos, result[5], index, self.num_envs)
        rewards = np.array([result[1] for result in results], dtype=np.float64)
        costs = np.array([result[2] for result in results], dtype=np.float64)
        terminateds = np.array([result[3] for result in results], dtype=np.bool_)
        truncateds = np.array([result[4] for result in results], dtype=np.bool_)
        return self._batch([result[0] for result in results]), rewards, costs, terminateds, truncateds, infos

    def render(self) -> np.ndarray | None:
        """The envs' frames tiled into one image (:func:`~.utils.tile_images`), or ``None`` without frames."""
        self._check_open()
        images = self._images()
        if any(image is None for image in images):
            return None
        return tile_images(images)

    def get_images(self) -> list[Any]:
        """Each env's ``render()``."""
        self._check_open()
        return self._images()

    def get_attr(self, name: str) -> tuple:
        """Attribute ``name`` of every env (``call`` of a non-callable attribute)."""
        return self.call(name)

    def set_attr(self, name: str, values: Any) -> None:
        """Set attribute ``name`` of every env: ``values`` is one value per env, or one for all."""
        self._check_open()
        if not isinstance(values, (list, tuple)):
            values = [values] * self.num_envs
        if len(values) != self.num_envs:
            raise ValueError(f"{len(values)} values for {self.num_envs} envs")
        self._set_attrs(name, list(values))

    def close(self, **kwargs: Any) -> None:
        """Close every env; calling it twice is allowed."""
        if not self.closed:
            self.closed = True
            self._close_envs()

    # ------------------------------------------------------------------ gymnasium 0.28's async API
    def reset_async(self, seed: int | list[int | None] | None = None, options: dict | None = None) -> None:
        """Start a reset; :meth:`reset_wait` returns its result (both run in ``reset_wait`` here)."""
        self._pending_reset = (seed, options)

    def reset_wait(self, timeout: float | None = None) -> tuple:
        """The result of the reset started by :meth:`reset_async`."""
        if getattr(self, "_pending_reset", None) is None:
            raise gymnasium.error.NoAsyncCallError("reset_wait() without a prior reset_async()", "reset")
        (seed, options), self._pending_reset = self._pending_reset, None
        return self.reset(seed=seed, options=options)

    def step_async(self, actions: Any) -> None:
        """Start a step; :meth:`step_wait` returns its result."""
        self._actions = actions

    def step_wait(self, timeout: float | None = None) -> tuple:
        """The result of the step started by :meth:`step_async`."""
        if self._actions is None:
            raise gymnasium.error.NoAsyncCallError("step_wait() without a prior step_async()", "step")
        actions, self._actions = self._actions, None
        return self.step(actions)

    # ------------------------------------------------------------------ internals
    def _batch(self, observations: list[Any]) -> Any:
        self._observations = concatenate(self.single_observation_space, observations, self._observations)
        return deepcopy(self._observations) if self.copy else self._observations

    def _check_open(self) -> None:
        if self.closed:
            raise gymnasium.error.ClosedEnvironmentError(f"{type(self).__name__} is closed")

    def __repr__(self) -> str:
        env_id = getattr(self.spec, "id", None)
        return f"{type(self).__name__}({env_id or '?'}, num_envs={self.num_envs})"
