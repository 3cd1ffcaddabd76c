"""TorchRL's multi-agent layout for a batched :class:`~sg_torchrl.envs.base.SafeEnv`, written once.

Every multi-agent env of sg_torchrl is a ``SafeEnv`` (``N`` simulators, numpy hooks, per-simulator
seeding, partial resets, divergence isolation) whose *interface* is TorchRL's multi-agent layout.
:class:`AgentGroupMixin` is that interface: the specs, the group action turned into the robots'
controls, partial resets asked per agent, and packing the step's numpy arrays into TensorDicts.
The envs supply what differs: the per-agent arrays (:meth:`AgentGroupMixin._output_arrays`), the
sizes and the action slots. Users: :class:`~sg_torchrl.envs.multi_agent.MultiAgentVelocityEnv`
(MaMuJoCo partitions of one robot) and :class:`~sg_torchrl.envs.multi_agent.MultiAgentNavigationEnv`
(several robots in one navigation world) and :class:`~sg_torchrl.envs.hands.MultiAgentShadowHandEnv` (one agent
per hand), which is why it sits beside :mod:`~sg_torchrl.envs.base` rather than in one family's package.

TensorDict layout (``N`` simulators, ``A`` agents ``agent_0 .. agent_{A-1}``, ``D`` / ``Da`` the
largest agent's observation / action size):

* ``("agents", "observation")`` ``(N, A, D)`` float32, agent ``a``'s observation in
  ``[..., a, :observation_sizes[a]]``, zeros after it; ``("agents", "observation_mask")`` ``(N, A, D)``
  bool, ``True`` on the real entries;
* ``("agents", "action")`` ``(N, A, Da)`` float32, input: agent ``a`` drives its actuators with
  ``[..., a, :action_sizes[a]]``; padding slots are ignored (their spec bounds are the widest control
  range, so a squashing policy distribution stays well defined on them);
* ``("agents", "reward")`` and ``("agents", "cost")`` ``(N, A, 1)`` float32: each agent's reward and
  cost (the env says whether they are shared); an env may add per-agent ``("agents", "cost_info", name)``;
* ``("agents", "done" | "terminated" | "truncated")`` ``(N, A, 1)`` bool;
* ``"state"`` ``(N, S)`` float32: the global state for centralised critics;
* ``"cost"`` and ``("cost_info", name)`` ``(N, 1)`` float32: the team's cost, as in every SafeEnv, so
  single-agent tools (``EpisodeSum``, episode statistics) apply unchanged;
* ``"done" | "terminated" | "truncated"`` ``(N, 1)`` bool: the episode flags.

Specs: ``reward_key == ("agents", "reward")`` and ``action_key == ("agents", "action")``; costs,
observations and ``state`` are in the observation spec (see :mod:`sg_torchrl.envs.base` for why
costs are not reward keys). Partial resets accept the root ``"_reset"`` or ``("agents", "_reset")``
(a simulator restarts if any of its agents asks: its agents share one episode).
"""

from __future__ import annotations

import abc
from collections.abc import Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded

from sg_torchrl.envs.base import reject_complex_action
from sg_torchrl.envs.step_hooks import numpy_faced

__all__ = ["GROUP", "AgentGroupMixin", "JointVectorAgentsMixin", "agent_column", "root_column"]

#: Name of the agents' group sub-TensorDict (TorchRL's MARL convention).
GROUP = "agents"


def root_column(values: np.ndarray, num_envs: int, dtype: type) -> np.ndarray:
    """A fresh ``(N, 1)`` array of ``values`` (``(N,)``) in ``dtype``: a root entry of the output."""
    return np.array(values, dtype=dtype).reshape(num_envs, 1)  # np.array copies


def agent_column(values: np.ndarray, num_envs: int, num_agents: int, dtype: type) -> np.ndarray:
    """A fresh ``(N, A, 1)`` array in ``dtype``: per-agent ``values`` ``(N, A)``, or ``(N,)`` shared by every agent."""
    column = np.asarray(values, dtype=dtype).reshape(num_envs, -1, 1)
    return np.broadcast_to(column, (num_envs, num_agents, 1)).copy()


class AgentGroupMixin(abc.ABC):
    """TorchRL's multi-agent interface of a batched SafeEnv (see the module docstring).

    Put it before the env's SafeEnv base (``class MyEnv(AgentGroupMixin, SomeSafeEnv)``). The env
    provides :attr:`num_agents`, :attr:`action_sizes`, :attr:`_action_slot` and
    :meth:`_output_arrays`, and builds its specs with :meth:`_make_group_specs` from ``_make_specs``.
    """

    num_envs: int
    batch_size: torch.Size
    device: torch.device | None
    _cpu: torch.device

    # ------------------------------------------------------------------ what the env provides
    @property
    @abc.abstractmethod
    def num_agents(self) -> int:
        """Number of agents ``A``."""

    @property
    @abc.abstractmethod
    def action_sizes(self) -> tuple[int, ...]:
        """Number of actuators per agent (agent ``a`` writes ``action[..., a, :size]``)."""

    @property
    @abc.abstractmethod
    def _action_slot(self) -> np.ndarray:
        """``(nu,)`` position of each actuator of the simulated world in the flattened ``(A, Da)`` group action."""

    @abc.abstractmethod
    def _output_arrays(self, observation, reward, costs, terminated, truncated) -> dict:
        """The step's (or, with ``reward=None``, the reset's) output as a nested dict of fresh numpy arrays
        with the emitted shapes and dtypes (the layout of the module docstring, group under :data:`GROUP`)."""

    # ------------------------------------------------------------------ names
    @property
    def agent_names(self) -> list[str]:
        """``["agent_0", ...]``: the agents in group order (also their PettingZoo names)."""
        return [f"agent_{i}" for i in range(self.num_agents)]

    @property
    def group_map(self) -> dict[str, list[str]]:
        """TorchRL's group map: one group, :data:`GROUP`, holding every agent."""
        return {GROUP: self.agent_names}

    # ------------------------------------------------------------------ specs
    def _make_group_specs(
        self,
        *,
        observation_width: int,
        state_dim: int,
        action_low: np.ndarray,
        action_high: np.ndarray,
        constraint_names: Sequence[str],
        agent_constraints: Sequence[str] | None = None,
    ) -> None:
        """Build every spec of the layout.

        Args:
            observation_width: ``D``, the padded per-agent observation length.
            state_dim: ``S``, the length of ``"state"``.
            action_low / action_high: ``(A, Da)`` bounds of every group action slot.
            constraint_names: the root ``cost_info`` entries.
            agent_constraints: per-agent ``("agents", "cost_info", name)`` entries; ``None`` (default): no
                per-agent ``cost_info`` (the agents share one cost).
        """
        n, agents, device = self.num_envs, self.num_agents, self.device
        group_shape = (n, agents)

        def flags(shape: tuple[int, ...]) -> dict:
            return {name: Categorical(n=2, shape=(*shape, 1), dtype=torch.bool, device=device)
                    for name in ("done", "terminated", "truncated")}

        def values(shape: tuple[int, ...], names: Sequence[str]) -> Composite:
            scalar = dict(shape=(*shape, 1), dtype=torch.float32, device=device)
            return Composite({name: Unbounded(**scalar) for name in names}, shape=shape, device=device)

        group = dict(
            observation=Unbounded(shape=(*group_shape, observation_width), dtype=torch.float32, device=device),
            observation_mask=Categorical(n=2, shape=(*group_shape, observation_width), dtype=torch.bool, device=device),
            cost=Unbounded(shape=(*group_shape, 1), dtype=torch.float32, device=device),
        )
        if agent_constraints is not None:
            group["cost_info"] = values(group_shape, agent_constraints)
        self.observation_spec = Composite(
            state=Unbounded(shape=(n, state_dim), dtype=torch.float32, device=device),
            cost=Unbounded(shape=(n, 1), dtype=torch.float32, device=device),
            cost_info=values((n,), constraint_names),
            **{GROUP: Composite(**group, shape=group_shape, device=device)},
            shape=(n,), device=device,
        )
        width = action_low.shape[-1]
        self.full_action_spec = Composite(
            {GROUP: Composite(
                action=Bounded(
                    low=torch.as_tensor(action_low, dtype=torch.float32).expand(n, -1, -1).clone(),
                    high=torch.as_tensor(action_high, dtype=torch.float32).expand(n, -1, -1).clone(),
                    shape=(*group_shape, width), dtype=torch.float32, device=device,
                ),
                shape=group_shape, device=device,
            )},
            shape=(n,), device=device,
        )
        self.full_reward_spec = Composite(
            {GROUP: Composite(reward=Unbounded(shape=(*group_shape, 1), dtype=torch.float32, device=device),
                              shape=group_shape, device=device)},
            shape=(n,), device=device,
        )
        self.full_done_spec = Composite(
            **flags((n,)), **{GROUP: Composite(**flags(group_shape), shape=group_shape, device=device)},
            shape=(n,), device=device,
        )

    # ------------------------------------------------------------------ actions
    def robot_control(self, action: torch.Tensor | np.ndarray) -> np.ndarray:
        """The simulated world's ``(N, nu)`` float64 control for a group action ``(N, A, Da)``.

        Checks the shape and that the values are finite (naming the offending simulators and agents).
        Padding slots are dropped before the checks: whatever they hold never reaches a robot.
        Clipping to the control range happens later, in the step, as in the single-agent envs.
        """
        expected = (self.num_envs, self.num_agents, max(self.action_sizes))
        if tuple(action.shape) != expected:
            raise ValueError(
                f"{type(self).__name__}: {(GROUP, 'action')!r} has shape {tuple(action.shape)}, expected {expected} "
                f"(num_envs={self.num_envs}, {self.num_agents} agents with {list(self.action_sizes)} actuators, "
                "padded to the largest)"
            )
        array = action if isinstance(action, np.ndarray) else action.detach().cpu().numpy()
        slots = self._action_slot
        control = array.reshape(self.num_envs, -1)[:, slots].astype(np.float64)
        if not np.isfinite(control).all():
            sims, actuators = np.nonzero(~np.isfinite(control))
            agents = slots[actuators] // expected[2]
            pairs = sorted({(int(s), f"agent_{a}") for s, a in zip(sims, agents)})
            raise ValueError(f"{type(self).__name__}: non-finite action (NaN or inf) for (simulator, agent) {pairs}")
        return control

    def _validated_action(self, action: torch.Tensor | None) -> np.ndarray:
        if action is None:
            raise KeyError(f"the input TensorDict has no {(GROUP, 'action')!r} entry")
        reject_complex_action(self, action)
        return self.robot_control(action)

    # ------------------------------------------------------------------ TorchRL hooks
    @numpy_faced("agent_group")
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = self._validated_action(tensordict.get((GROUP, "action"), None))
        return self._pack(*self._transition_arrays(action))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        if tensordict is not None and "_reset" not in tensordict.keys():
            nested = tensordict.get((GROUP, "_reset"), None)
            if nested is not None:  # only the group asks: a simulator restarts if any of its agents does
                tensordict = TensorDict({"_reset": self._any_agent(nested)}, batch_size=self.batch_size)
        return super()._reset(tensordict, **kwargs)

    def _reset_proc_data(self, tensordict: TensorDictBase | None, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # The group's reset flags carry no extra information (the agents share one episode): fold
        # them into the root flag so that SafeEnv's merge sees the one mask it handles.
        if tensordict is not None:
            nested = tensordict.get((GROUP, "_reset"), None)
            if nested is not None:
                del tensordict[GROUP, "_reset"]
                if "_reset" not in tensordict.keys():
                    tensordict.set("_reset", self._any_agent(nested))
        return super()._reset_proc_data(tensordict, tensordict_reset)

    def _own_cost_arrays(self, agent_observation, observation_mask, state, reward, costs, terminated, truncated) -> dict:
        """:meth:`_output_arrays` for envs whose agents each pay their own cost (several robots or hands).

        ``agent_observation`` ``(N, A, D)``, ``observation_mask`` ``(N, A, D)``, ``state`` ``(N, S)``;
        ``reward`` ``(N, A)`` or ``(N,)`` (shared); ``costs``: raw per-constraint costs ``(N, A)`` (or ``(N,)``,
        shared). Each agent's ``cost``/``cost_info`` follow :attr:`cost_mode` on its own costs; the root
        ``cost``/``cost_info`` on the agents' sum (under ``"indicator"``: 1 when some agent paid).
        """
        n, agents = self.num_envs, self.num_agents
        per_agent = {name: np.broadcast_to(np.reshape(value, (n, -1)), (n, agents)) for name, value in costs.items()}
        agent_cost, agent_info = self._aggregate_cost(per_agent)
        team_cost, team_info = self._aggregate_cost({name: value.sum(axis=1) for name, value in per_agent.items()})
        done = terminated | truncated
        group = {
            "observation": np.asarray(agent_observation, dtype=np.float32),
            "observation_mask": observation_mask.copy(),
            "cost": agent_column(agent_cost, n, agents, np.float32),
            "cost_info": {name: agent_column(value, n, agents, np.float32) for name, value in agent_info.items()},
            "terminated": agent_column(terminated, n, agents, np.bool_),
            "truncated": agent_column(truncated, n, agents, np.bool_),
            "done": agent_column(done, n, agents, np.bool_),
        }
        if reward is not None:
            group["reward"] = agent_column(reward, n, agents, np.float32)
        return {
            "state": np.array(state, dtype=np.float32),
            "cost": root_column(team_cost, n, np.float32),
            "cost_info": {name: root_column(value, n, np.float32) for name, value in team_info.items()},
            "terminated": root_column(terminated, n, np.bool_),
            "truncated": root_column(truncated, n, np.bool_),
            "done": root_column(done, n, np.bool_),
            GROUP: group,
        }

    def _any_agent(self, flags: torch.Tensor) -> torch.Tensor:
        return flags.reshape(self.num_envs, -1).any(dim=-1, keepdim=True)

    def _pack(self, observation, reward, costs, terminated, truncated) -> TensorDictBase:
        """The output TensorDict in the layout of the module docstring (every tensor a fresh copy)."""
        arrays = self._output_arrays(observation, reward, costs, terminated, truncated)
        cpu, group_size = self._cpu, (self.num_envs, self.num_agents)

        def tensors(entries: dict, batch_size: tuple[int, ...]) -> TensorDict:
            # Built with the declared shapes, dtypes and device: TensorDict's per-entry checks are skipped.
            source = {}
            for key, value in entries.items():
                if isinstance(value, dict):
                    source[key] = tensors(value, group_size if key == GROUP else batch_size)
                else:
                    source[key] = torch.from_numpy(value)
            return TensorDict._new_unsafe(source, batch_size=batch_size, device=cpu)

        out = tensors(arrays, tuple(self.batch_size))
        return out if self.device is None or self.device.type == "cpu" else out.to(self.device)


class JointVectorAgentsMixin(AgentGroupMixin):
    """Agents that each observe fixed columns of the env's joint observation vector and pay their own costs.

    The multi-robot navigation tasks (MultiGoal) and the two-hand tasks split one world this way:
    the joint vector is the global ``"state"``, agent ``a`` observes ``state[:, agent_index[a]]`` (every
    agent the same width, so no padding), and each agent's ``cost`` follows its own per-agent costs
    (:meth:`_own_cost_arrays`). The env calls :meth:`_make_joint_view_specs` from its ``_make_specs``.
    """

    _agent_index: np.ndarray
    _observation: np.ndarray
    _action_low: np.ndarray
    _action_high: np.ndarray
    constraint_names: list[str]

    @property
    def observation_sizes(self) -> tuple[int, ...]:
        """Observation length per agent (all equal)."""
        return (self._agent_index.shape[1],) * self.num_agents

    @property
    def observation_dim(self) -> int:
        """Per-agent observation length ``D``."""
        return self._agent_index.shape[1]

    @property
    def state_dim(self) -> int:
        """Length ``S`` of ``"state"``, the joint observation vector."""
        return self._observation.shape[1]

    def _make_joint_view_specs(
        self, agent_index: np.ndarray, state_dim: int, action_low: np.ndarray, action_high: np.ndarray
    ) -> None:
        """Record each agent's ``(A, D)`` columns of the joint vector and build the group specs.

        ``action_low`` / ``action_high``: ``(A, Da)`` bounds of the group action slots.
        """
        self._agent_index = agent_index
        self._observation_mask = np.ones((self.num_envs, *agent_index.shape), dtype=bool)
        self._make_group_specs(
            observation_width=agent_index.shape[1],
            state_dim=state_dim,
            action_low=action_low,
            action_high=action_high,
            constraint_names=self.constraint_names,
            agent_constraints=self.constraint_names,
        )

    def _output_arrays(self, observation, reward, costs, terminated, truncated) -> dict:
        """The step's (or, with ``reward=None``, the reset's) output as a nested dict of fresh numpy arrays
        (the layout of the module docstring). The PettingZoo façade reads it directly."""
        return self._own_cost_arrays(observation[:, self._agent_index], self._observation_mask, observation,
                                     reward, costs, terminated, truncated)
