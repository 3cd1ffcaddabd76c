"""Multi-agent velocity tasks: ``Safety{conf}{Robot}Velocity-v0`` (Safety-Gymnasium's ``make_ma``).

The constrained Markov game of the Safety-Gymnasium paper's safe multi-agent velocity tasks (Ji et
al., 2023) on one robot: MaMuJoCo (Peng et al., 2021) splits the robot's actuators among agents,
every agent receives the shared team reward (the single-agent v4 reward) and pays its own cost,
which for the velocity task is the same 0/1 indicator for all agents: the robot moved faster than
the configuration's threshold (reference section 9). The speed is measured as ``make_ma`` does,
``hypot(vx, vy)`` of the robot's v4 velocity: ``|vx|`` for the robots that move along x only, so
running backwards fast costs too (unlike the single-agent v1 tasks), and the signed x velocity for
the Swimmer.

:class:`MultiAgentVelocityEnv` is the single-agent :class:`~sg_torchrl.envs.velocity.VelocityEnv`
of the same robot (physics, reward, termination, reset noise, seeding, partial resets, divergence
isolation: all inherited) with a different *interface*: the action comes in per agent and the
outputs go out in TorchRL's multi-agent layout. Per step this costs two numpy gathers over the
whole batch (:mod:`.layout`), not a Python loop over agents.

TensorDict layout (``N`` simulators, ``A`` agents, ``D`` / ``Da`` the largest agent's observation /
action size; agents are ``agent_0 .. agent_{A-1}`` in MaMuJoCo's order):

* ``("agents", "observation")`` ``(N, A, D)`` float32: agent ``a``'s MaMuJoCo observation
  (``obsk=1``) in ``[..., a, :observation_sizes[a]]``, zeros after it;
* ``("agents", "observation_mask")`` ``(N, A, D)`` bool: ``True`` on each agent's real entries;
* ``("agents", "action")`` ``(N, A, Da)`` float32, input: agent ``a`` drives its actuators with
  ``[..., a, :action_sizes[a]]``; padding slots are ignored;
* ``("agents", "reward")`` ``(N, A, 1)`` float32: the team reward, equal for every agent;
* ``("agents", "cost")`` ``(N, A, 1)`` float32: each agent's cost (the velocity indicator);
* ``("agents", "done" | "terminated" | "truncated")`` ``(N, A, 1)`` bool: the robot's episode flags;
* ``"state"`` ``(N, S)`` float32: the robot's v4 observation, for centralised critics (MaMuJoCo's
  ``state()``);
* ``"cost"`` and ``("cost_info", "velocity")`` ``(N, 1)`` float32: the team's cost, as in every
  SafeEnv, so single-agent tools (``EpisodeSum``, episode statistics) apply unchanged;
* ``"done" | "terminated" | "truncated"`` ``(N, 1)`` bool: the episode flags.

Specs: ``reward_key == ("agents", "reward")`` and ``action_key == ("agents", "action")`` (the only
reward and action keys); costs, observations and ``state`` are in the observation spec (see
:mod:`sg_torchrl.envs.base` for why costs are not reward keys). Padding action slots carry the
robot's widest control range in the action spec, so a squashing policy distribution stays well
defined on them; their values never reach the robot. Partial resets accept the root ``"_reset"``
or ``("agents", "_reset")`` (a simulator restarts if any of its agents asks).

Heterogeneous partitions (Humanoid 9|8: 248 and 176 values, 9 and 8 actuators; HalfCheetah 6x1:
9 or 8 values) are padded as above; :attr:`~MultiAgentVelocityEnv.observation_sizes` and
:attr:`~MultiAgentVelocityEnv.action_sizes` give the true sizes.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded

from sg_torchrl.envs.base import CostMode
from sg_torchrl.envs.multi_agent.layout import AgentLayout, agent_layout
from sg_torchrl.envs.multi_agent.partitions import Scenario, scenario_of
from sg_torchrl.envs.velocity.env import VelocityEnv
from sg_torchrl.envs.velocity.robots import ROBOTS, load_model

__all__ = ["GROUP", "MultiAgentVelocityEnv"]

#: Name of the agents' group sub-TensorDict (TorchRL's MARL convention).
GROUP = "agents"


class MultiAgentVelocityEnv(VelocityEnv):
    """A MaMuJoCo-partitioned v4 robot with Safety-Gymnasium's multi-agent velocity cost, batched.

    Args:
        scenario: the robot, a key of :data:`~sg_torchrl.envs.multi_agent.partitions.SCENARIOS`
            (``"Ant"``, ``"HalfCheetah"``, ``"Hopper"``, ``"Humanoid"``, ``"Swimmer"``, ``"Walker2d"``).
        agent_conf: MaMuJoCo's partition, e.g. ``"2x4"`` (valid ones per robot in the scenario).
        agent_obsk: graph distance of the joints an agent observes (MaMuJoCo's ``agent_obsk``; the
            reference and its sizes use 1).
        velocity_threshold: override the configuration's threshold (reference section 9).
        num_envs, device, seed, cost_mode, max_episode_steps: see :class:`~sg_torchrl.envs.base.SafeEnv`.

    See the module docstring for the TensorDict layout.
    """

    def __init__(
        self,
        scenario: str,
        agent_conf: str,
        *,
        agent_obsk: int = 1,
        num_envs: int = 1,
        device: torch.device | str = "cpu",
        seed: int | None = None,
        cost_mode: CostMode = "indicator",
        max_episode_steps: int = 1000,
        velocity_threshold: float | None = None,
    ) -> None:
        spec: Scenario = scenario_of(scenario)
        robot = ROBOTS[spec.robot]
        self.scenario = spec
        self.agent_conf = agent_conf
        # Resolved before the base class builds the specs, which need the agents' sizes.
        self.layout: AgentLayout = agent_layout(spec, agent_conf, robot, load_model(robot.xml_file), agent_obsk)
        threshold = spec.thresholds[agent_conf] if velocity_threshold is None else velocity_threshold
        super().__init__(
            spec.robot,
            version=0,
            num_envs=num_envs,
            device=device,
            seed=seed,
            cost_mode=cost_mode,
            max_episode_steps=max_episode_steps,
            velocity_threshold=threshold,
            planar_cost=spec.cost_velocity == "planar",
        )
        layout = self.layout
        # The source rows (see .layout): state, raw velocities if observed, a constant 0 column.
        self._source = np.zeros((num_envs, layout.source_dim))
        mask = layout.observation_mask
        self._observation_mask = np.broadcast_to(mask, (num_envs, *mask.shape)).copy()

    # ------------------------------------------------------------------ layout
    @property
    def num_agents(self) -> int:
        return self.layout.num_agents

    @property
    def agent_names(self) -> list[str]:
        """``["agent_0", ...]``: the agents in group order (MaMuJoCo's and PettingZoo's names)."""
        return [f"agent_{i}" for i in range(self.num_agents)]

    @property
    def group_map(self) -> dict[str, list[str]]:
        """TorchRL's group map: one group, :data:`GROUP`, holding every agent."""
        return {GROUP: self.agent_names}

    @property
    def observation_sizes(self) -> tuple[int, ...]:
        """True observation length per agent (agent ``a`` reads ``observation[..., a, :size]``)."""
        return self.layout.observation_sizes

    @property
    def action_sizes(self) -> tuple[int, ...]:
        """Number of actuators per agent (agent ``a`` writes ``action[..., a, :size]``)."""
        return self.layout.action_sizes

    @property
    def state_dim(self) -> int:
        return self.layout.state_dim

    @property
    def observation_dim(self) -> int:
        """Padded per-agent observation length ``D``."""
        return self.layout.observation_index.shape[1]

    def _make_specs(self, observation_dim: int) -> None:
        n, layout, device = self.num_envs, self.layout, self.device
        agents, width = layout.observation_index.shape
        group_shape = (n, agents)

        def flags(shape: tuple[int, ...]) -> dict:
            return {name: Categorical(n=2, shape=(*shape, 1), dtype=torch.bool, device=device)
                    for name in ("done", "terminated", "truncated")}

        scalar = dict(shape=(n, 1), dtype=torch.float32, device=device)
        self.observation_spec = Composite(
            state=Unbounded(shape=(n, layout.state_dim), dtype=torch.float32, device=device),
            cost=Unbounded(**scalar),
            cost_info=Composite(
                {name: Unbounded(**scalar) for name in self.constraint_names}, shape=(n,), device=device
            ),
            **{GROUP: Composite(
                observation=Unbounded(shape=(*group_shape, width), dtype=torch.float32, device=device),
                observation_mask=Categorical(n=2, shape=(*group_shape, width), dtype=torch.bool, device=device),
                cost=Unbounded(shape=(*group_shape, 1), dtype=torch.float32, device=device),
                shape=group_shape, device=device,
            )},
            shape=(n,), device=device,
        )
        # Per action slot, its actuator's control range; padding slots the robot's widest range.
        slots = layout.action_actuators
        low = np.where(slots >= 0, self._action_low[slots], self._action_low.min())
        high = np.where(slots >= 0, self._action_high[slots], self._action_high.max())
        self.full_action_spec = Composite(
            {GROUP: Composite(
                action=Bounded(
                    low=torch.as_tensor(low, dtype=torch.float32).expand(n, -1, -1).clone(),
                    high=torch.as_tensor(high, dtype=torch.float32).expand(n, -1, -1).clone(),
                    shape=(*group_shape, slots.shape[1]), dtype=torch.float32, device=device,
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

    # ------------------------------------------------------------------ hooks
    def _observe(self) -> np.ndarray:
        """The source rows: the v4 observation (``state``), raw velocities where agents need them, 0."""
        source, state = self._source, super()._observe()
        source[:, : state.shape[1]] = state
        if self.layout.raw_qvel:
            source[:, state.shape[1] : -1] = self.physics.qvel()
        return source

    def agent_observations(self, source: np.ndarray) -> np.ndarray:
        """``(N, A, D)`` group observation (padded with zeros) from source rows ``(N, source_dim)``."""
        return source[:, self.layout.observation_index]

    def robot_control(self, action: torch.Tensor | np.ndarray) -> np.ndarray:
        """The robot's ``(N, nu)`` float64 control for a group action ``(N, A, Da)``.

        MaMuJoCo's local-to-global action map, with the checks of :meth:`step` (shape; finite
        values, with the offending simulators and agents named). Padding slots are dropped before
        the checks: whatever they hold never reaches the robot. Clipping to the control range
        happens later, in the step, as in the single-agent env.
        """
        expected = (self.num_envs, self.num_agents, self.layout.action_actuators.shape[1])
        if tuple(action.shape) != expected:
            raise ValueError(
                f"{type(self).__name__}: {(GROUP, 'action')!r} has shape {tuple(action.shape)}, expected {expected} "
                f"(num_envs={self.num_envs}, {self.num_agents} agents with {list(self.action_sizes)} actuators, "
                "padded to the largest)"
            )
        array = action if isinstance(action, np.ndarray) else action.detach().cpu().numpy()
        control = array.reshape(self.num_envs, -1)[:, self.layout.action_slot].astype(np.float64)
        if not np.isfinite(control).all():
            sims, actuators = np.nonzero(~np.isfinite(control))
            agents = self.layout.action_slot[actuators] // expected[2]
            pairs = sorted({(int(s), f"agent_{a}") for s, a in zip(sims, agents)})
            raise ValueError(f"{type(self).__name__}: non-finite action (NaN or inf) for (simulator, agent) {pairs}")
        return control

    def _validated_action(self, action: torch.Tensor | None) -> np.ndarray:
        if action is None:
            raise KeyError(f"the input TensorDict has no {(GROUP, 'action')!r} entry")
        return self.robot_control(action)

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
        # The group's reset flags carry no extra information (one robot, one episode): fold them
        # into the root flag so that SafeEnv's merge sees the one mask it handles.
        if tensordict is not None:
            nested = tensordict.get((GROUP, "_reset"), None)
            if nested is not None:
                del tensordict[GROUP, "_reset"]
                if "_reset" not in tensordict.keys():
                    tensordict.set("_reset", self._any_agent(nested))
        return super()._reset_proc_data(tensordict, tensordict_reset)

    def _any_agent(self, flags: torch.Tensor) -> torch.Tensor:
        return flags.reshape(self.num_envs, -1).any(dim=-1, keepdim=True)

    # ------------------------------------------------------------------ output
    def _output_arrays(self, observation, reward, costs, terminated, truncated) -> dict:
        """The step's (or, with ``reward=None``, the reset's) output as a nested dict of fresh numpy
        arrays with the emitted shapes and dtypes: the body of :meth:`_pack` without TensorDicts.
        The PettingZoo façade reads it directly."""
        cost, cost_info = self._aggregate_cost(costs)
        n, agents = self.num_envs, self.num_agents

        def root(values: np.ndarray, dtype: type) -> np.ndarray:
            return np.array(values, dtype=dtype).reshape(n, 1)  # np.array copies

        def per_agent(values: np.ndarray, dtype: type) -> np.ndarray:
            return np.repeat(np.asarray(values, dtype=dtype).reshape(n, 1, 1), agents, axis=1)

        done = terminated | truncated
        group = {
            "observation": self.agent_observations(observation).astype(np.float32),
            "observation_mask": self._observation_mask.copy(),
            "cost": per_agent(cost, np.float32),
            "terminated": per_agent(terminated, np.bool_),
            "truncated": per_agent(truncated, np.bool_),
            "done": per_agent(done, np.bool_),
        }
        if reward is not None:
            group["reward"] = per_agent(reward, np.float32)
        return {
            "state": np.array(observation[:, : self.layout.state_dim], dtype=np.float32),
            "cost": root(cost, np.float32),
            "cost_info": {name: root(value, np.float32) for name, value in cost_info.items()},
            "terminated": root(terminated, np.bool_),
            "truncated": root(truncated, np.bool_),
            "done": root(done, np.bool_),
            GROUP: group,
        }

    def _pack(self, observation, reward, costs, terminated, truncated) -> TensorDictBase:
        """The output TensorDict in the layout of the module docstring (every tensor a fresh copy)."""
        arrays = self._output_arrays(observation, reward, costs, terminated, truncated)
        cpu = self._cpu
        group = {key: torch.from_numpy(value) for key, value in arrays.pop(GROUP).items()}
        source = {key: torch.from_numpy(value) for key, value in arrays.items() if key != "cost_info"}
        source["cost_info"] = {key: torch.from_numpy(value) for key, value in arrays["cost_info"].items()}
        # Built with the declared shapes, dtypes and device: TensorDict's per-entry checks are skipped.
        source[GROUP] = TensorDict._new_unsafe(group, batch_size=(self.num_envs, self.num_agents), device=cpu)
        out = TensorDict._new_unsafe(source, batch_size=self.batch_size, device=cpu)
        return out if self.device is None or self.device.type == "cpu" else out.to(self.device)
