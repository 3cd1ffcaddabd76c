"""PettingZoo façade: Safety-Gymnasium's multi-agent API (``make_ma``) on top of the TorchRL envs.

This is the migration path for code written against ``safety_gymnasium.make_ma(scenario, conf)``:

>>> import sg_torchrl.pettingzoo
>>> env = sg_torchrl.pettingzoo.make("Safety2x4AntVelocity-v0")
>>> observations, infos = env.reset(seed=0)
>>> actions = {agent: env.action_space(agent).sample() for agent in env.agents}
>>> observations, rewards, costs, terminations, truncations, infos = env.step(actions)
>>> env.state().shape
(27,)

API
---
* :func:`make` ``(env_id, *, cost_in_info=False, render_mode=None, **options)`` builds one
  simulator of the multi-agent sg_torchrl env ``env_id`` (``sg_torchrl.make(env_id, num_envs=1,
  **options)``) and wraps it in a :class:`pettingzoo.ParallelEnv`.
* :class:`SafeParallelEnv` (the default): ``step(actions)`` returns Safety-Gymnasium's **6-tuple**
  ``(observations, rewards, costs, terminations, truncations, infos)``, each a dict keyed by agent
  (``"agent_0"``, ...). Observations are ``float64`` arrays of each agent's true (unpadded) size,
  rewards and costs python floats (each agent's ``("agents", "reward")`` and ``("agents", "cost")``:
  for the velocity ids the team reward and the velocity indicator, equal for all agents; for the
  MultiGoal ids each agent's own), the flags python bools, and ``infos[agent]`` holds ``cost_<name>``
  per constraint (the agent's own where the env reports per-agent entries, else the team's) plus
  ``cost_sum``, after gymnasium's terms where the env has them (velocity ids: ``x_velocity``, ...,
  the same for every agent as in MaMuJoCo). ``reset(seed=None, options=None)`` returns
  ``(observations, infos)`` with empty infos; ``options`` are accepted and ignored (as MaMuJoCo's v4
  robots do). ``state()`` is the
  global state (the env's ``"state"``: the robot's v4 observation, or the MultiGoal joint observation;
  ``float64``), ``state_space`` its box.
* Rendering: gymnasium's render modes and options, as in :mod:`sg_torchrl.gym`
  (:mod:`sg_torchrl.render_modes`). ``copy.deepcopy(env)`` copies the simulator's state, as there.
* :class:`CostInInfoParallelEnv` (``make(env_id, cost_in_info=True)``): the standard PettingZoo
  **5-tuple** ``(observations, rewards, terminations, truncations, infos)`` with each agent's cost in
  ``infos[agent]["cost"]``. This is the variant that passes ``pettingzoo.test.parallel_api_test``,
  which unpacks exactly five values from ``step`` and so cannot accept the 6-tuple.
* Episodes: when the episode ends (terminated or truncated) every agent is done at once and
  ``agents`` becomes empty, as in MaMuJoCo and Safety-Gymnasium's multi-agent navigation. ``step``
  before ``reset`` or after the end raises :class:`sg_torchrl.gym.EpisodeEndedError`; an action dict
  that misses a live agent, names an unknown one, has the wrong shape or is not finite raises
  ``ValueError``. Actions outside the bounds are clipped.
* Seeding and values as in :mod:`sg_torchrl.gym`: ``reset(seed=s)`` re-seeds the simulator, ``reset()``
  continues its random stream; the values are exactly the TorchRL env's (actions cast to ``float32``).

Speed
-----
For the envs built on :class:`~sg_torchrl.envs.multi_agent.AgentGroupMixin` (every registered
multi-agent env) the step runs the env's public numpy interface (``robot_control``,
:meth:`~sg_torchrl.envs.base.SafeEnv.step_arrays`, ``output_arrays``: the mixin's TorchRL step
without building TensorDicts), as the gymnasium façade does; other multi-agent envs (or subclasses
that override ``_step`` without marking it, :mod:`sg_torchrl.envs.step_hooks`) go through the public TorchRL ``step``. Both give identical data.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pettingzoo
import torch
from gymnasium import spaces
from tensordict import TensorDict

from sg_torchrl.envs.multi_agent import GROUP as _GROUP
from sg_torchrl.envs.registry import registry_entry
from sg_torchrl.envs.registry import make as make_torchrl_env
from sg_torchrl.facade import SimulatorFacade
from sg_torchrl.render_modes import RENDER_MODES, FrameSource, available_render_modes, split_render_options

__all__ = ["CostInInfoParallelEnv", "SafeParallelEnv", "make"]


def make(env_id: str, *, cost_in_info: bool = False, render_mode: str | None = None, **options: Any) -> SafeParallelEnv:
    """Build a PettingZoo ``ParallelEnv`` for one simulator of the multi-agent sg_torchrl env ``env_id``.

    Args:
        env_id: a multi-agent id, e.g. ``"Safety2x4AntVelocity-v0"`` or ``"SafetyPointMultiGoal1-v0"``
            (``sg_torchrl.list_envs(family="multi_agent_velocity")``, ``family="multi_agent_navigation"``).
        cost_in_info: ``False``: Safety-Gymnasium's 6-tuple step (:class:`SafeParallelEnv`);
            ``True``: PettingZoo's 5-tuple with ``infos[agent]["cost"]`` (:class:`CostInInfoParallelEnv`).
        render_mode: ``None`` or one of :data:`~sg_torchrl.render_modes.RENDER_MODES` (then ``width``,
            ``height``, ``camera`` / ``camera_name`` / ``camera_id`` options too).
        **options: sg_torchrl options, e.g. ``max_episode_steps=500``, ``cost_mode="raw"``, ``seed=0``.
    """
    cls = CostInInfoParallelEnv if cost_in_info else SafeParallelEnv
    return cls(env_id, render_mode=render_mode, **options)


class SafeParallelEnv(SimulatorFacade, pettingzoo.ParallelEnv):
    """One multi-agent sg_torchrl simulator behind Safety-Gymnasium's ``make_ma`` API (6-tuple step).

    Args:
        env_id: a multi-agent id of :func:`sg_torchrl.list_envs`.
        render_mode: ``None`` or one of :data:`~sg_torchrl.render_modes.RENDER_MODES`.
        **options: sg_torchrl options and render options (see :func:`make`).

    The wrapped TorchRL env is :attr:`torchrl_env` (``batch_size=[1]``).
    """

    metadata = {"render_modes": list(RENDER_MODES), "name": "sg_torchrl", "is_parallelizable": True}

    def __init__(self, env_id: str, render_mode: str | None = None, **options: Any) -> None:
        if not registry_entry(env_id).multi_agent:
            raise ValueError(f"{env_id!r} is a single-agent env: use sg_torchrl.gym.make({env_id!r})")
        if "num_envs" in options:
            raise TypeError("the PettingZoo façade steps one simulator; use sg_torchrl.make(env_id, num_envs=N)")
        self._options = dict(options)  # what a deepcopy rebuilds the env from
        self.metadata = {**self.metadata, "render_modes": available_render_modes()}  # no "human" when headless
        render_options = split_render_options(options)
        env = make_torchrl_env(env_id, num_envs=1, **options)
        self._env = env
        self.env_id = env_id
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "name": env_id}
        self._frames = FrameSource(env, render_mode, render_options) if render_mode is not None else None
        self.possible_agents = list(env.agent_names)
        self.agents: list[str] = []
        self._sizes = dict(zip(self.possible_agents, env.observation_sizes))
        self._action_sizes = dict(zip(self.possible_agents, env.action_sizes))
        self.observation_spaces = {
            agent: spaces.Box(-np.inf, np.inf, shape=(size,), dtype=np.float64) for agent, size in self._sizes.items()
        }
        bounds = env.full_action_spec[_GROUP, "action"].space
        low, high = bounds.low[0].numpy(), bounds.high[0].numpy()
        self.action_spaces = {
            agent: spaces.Box(low[i, :size], high[i, :size], dtype=np.float32)
            for i, (agent, size) in enumerate(self._action_sizes.items())
        }
        self.state_space = spaces.Box(-np.inf, np.inf, shape=(env.state_dim,), dtype=np.float64)
        self._action_buffer = np.zeros(tuple(env.full_action_spec[_GROUP, "action"].shape), dtype=np.float32)
        self._constraints = tuple(env.observation_spec["cost_info"].keys())
        self._state = np.zeros(env.state_dim)
        # Numpy fast path only where the env's _step is marked as its agent-group numpy interface's (module docstring).
        self._fast = getattr(env, "numpy_step_interface", None) == "agent_group"
        self._closed = False

    # ------------------------------------------------------------------ properties
    def observation_space(self, agent: str) -> spaces.Box:
        """Agent ``agent``'s observation box (its true size); the same object on every call."""
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        """Agent ``agent``'s action box (its actuators' control ranges); the same object on every call."""
        return self.action_spaces[agent]

    # ------------------------------------------------------------------ PettingZoo API
    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        """Start an episode; ``seed`` re-seeds the simulator, ``None`` continues its random stream.
        ``options`` (a dict or ``None``) is accepted and ignored."""
        self._check_reset_options(options)
        if seed is not None:
            self._env.set_seed(int(seed), static_seed=True)
        arrays = self._env.reset().numpy()
        self.agents = list(self.possible_agents)
        if self._frames is not None:
            self._frames.after_reset()
        return self._observations(arrays), {agent: {} for agent in self.agents}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict, dict]:
        """Advance one step: ``(observations, rewards, costs, terminations, truncations, infos)``."""
        return self._transition(actions)

    def state(self) -> np.ndarray:
        """The global state after the last ``reset``/``step`` (the env's ``"state"``)."""
        return self._state.copy()

    def close(self) -> None:
        """Release the simulator; calling it twice is allowed."""
        if not self._closed:
            self.agents = []
            self._release()

    def __deepcopy__(self, memo: dict) -> SafeParallelEnv:
        """A new env with the same id and options whose simulator continues exactly from this one's
        (:meth:`~sg_torchrl.envs.base.SafeEnv.sim_state` loaded into the copy)."""
        clone = self._clone(memo)
        clone.agents = list(self.agents)
        clone._state = self._state.copy()
        return clone

    # ------------------------------------------------------------------ internals
    def _observations(self, arrays: dict) -> dict[str, np.ndarray]:
        """Per-agent ``float64`` observations (true sizes) from the env's output (as nested numpy
        dicts, see :meth:`~sg_torchrl.envs.base.SafeEnv.output_arrays`); records the state."""
        group = arrays[_GROUP]["observation"][0].astype(np.float64)
        self._state = arrays["state"][0].astype(np.float64)
        return {agent: group[i, : self._sizes[agent]] for i, agent in enumerate(self.possible_agents)}

    def _group_action(self, actions: dict[str, Any]) -> np.ndarray:
        """The ``(1, A, Da)`` float32 group action the TorchRL env receives (padding slots 0)."""
        if not isinstance(actions, dict):
            raise ValueError(f"{self.env_id}: actions must be a dict keyed by agent, got {type(actions).__name__}")
        unknown = set(actions) - set(self.possible_agents)
        missing = set(self.agents) - set(actions)
        if unknown or missing:
            raise ValueError(
                f"{self.env_id}: actions must hold one entry per live agent {self.agents}; "
                f"unknown {sorted(unknown)}, missing {sorted(missing)}"
            )
        buffer = self._action_buffer
        buffer[:] = 0.0
        for i, agent in enumerate(self.possible_agents):
            array = np.asarray(actions[agent], dtype=np.float32)
            expected = self.action_spaces[agent].shape
            if array.shape != expected:
                raise ValueError(f"{self.env_id}: action of {agent} has shape {array.shape}, expected {expected}")
            if not np.isfinite(array).all():
                raise ValueError(f"{self.env_id}: action of {agent} is not finite: {array}")
            buffer[0, i, : expected[0]] = array
        return buffer.copy()

    def _transition(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict, dict]:
        if not self.agents:
            self._raise_episode_ended()
        env, action = self._env, self._group_action(actions)
        if self._fast:
            out = env.output_arrays(*env.step_arrays(env.robot_control(action)))
        else:
            td = TensorDict({(_GROUP, "action"): torch.from_numpy(action).to(env.device)}, batch_size=env.batch_size)
            out = env.step(td).get("next").cpu().numpy()
        observations = self._observations(out)
        group = out[_GROUP]
        reward = group["reward"][0, :, 0].tolist()
        cost = group["cost"][0, :, 0].tolist()
        terminated = group["terminated"][0, :, 0].tolist()
        truncated = group["truncated"][0, :, 0].tolist()
        agents = self.possible_agents
        agent_info = group.get("cost_info")  # per-agent entries where the env has them, else the team's
        cost_info = [
            {f"cost_{name}": float(agent_info[name][0, i, 0] if agent_info else out["cost_info"][name][0, 0])
             for name in self._constraints}
            for i in range(len(agents))
        ]
        rewards = dict(zip(agents, reward))
        costs = dict(zip(agents, cost))
        terminations = dict(zip(agents, map(bool, terminated)))
        truncations = dict(zip(agents, map(bool, truncated)))
        terms = env.step_info(0) if hasattr(env, "step_info") else {}  # gymnasium's terms, as MaMuJoCo's info
        infos = {agent: {**terms, **info, "cost_sum": costs[agent]} for agent, info in zip(agents, cost_info)}
        if any(terminated) or any(truncated):
            self.agents = []
        if self._frames is not None:
            self._frames.after_step()
        return observations, rewards, costs, terminations, truncations, infos


class CostInInfoParallelEnv(SafeParallelEnv):
    """:class:`SafeParallelEnv` with PettingZoo's 5-tuple step; each agent's cost is ``infos[agent]["cost"]``.

    For code (and tests such as ``pettingzoo.test.parallel_api_test``) that expects a plain
    :class:`pettingzoo.ParallelEnv`.
    """

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Advance one step: ``(observations, rewards, terminations, truncations, infos)``, costs in ``infos``."""
        observations, rewards, costs, terminations, truncations, infos = self._transition(actions)
        for agent, cost in costs.items():
            infos[agent]["cost"] = cost
        return observations, rewards, terminations, truncations, infos
