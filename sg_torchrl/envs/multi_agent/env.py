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

TensorDict layout: TorchRL's multi-agent layout (:mod:`.group`), agents ``agent_0 .. agent_{A-1}``
in MaMuJoCo's order. Here:

* ``("agents", "observation")`` ``(N, A, D)``: agent ``a``'s MaMuJoCo observation (``obsk=1``),
  padded with zeros to the largest agent's (``("agents", "observation_mask")`` marks the real entries);
* ``("agents", "action")`` ``(N, A, Da)``: agent ``a`` drives its MaMuJoCo actuators;
* ``("agents", "reward")``: the team reward, equal for every agent;
* ``("agents", "cost")``: each agent's cost (the velocity indicator, equal for every agent);
* ``("agents", "done" | "terminated" | "truncated")``: the robot's episode flags;
* ``"state"`` ``(N, S)``: the robot's v4 observation (MaMuJoCo's ``state()``);
* ``"cost"`` and ``("cost_info", "velocity")`` ``(N, 1)``: the team's cost.

Heterogeneous partitions (Humanoid 9|8: 248 and 176 values, 9 and 8 actuators; HalfCheetah 6x1:
9 or 8 values) are padded as above; :attr:`~MultiAgentVelocityEnv.observation_sizes` and
:attr:`~MultiAgentVelocityEnv.action_sizes` give the true sizes.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from sg_torchrl.envs.backends import Backend
from sg_torchrl.envs.base import CostMode
from sg_torchrl.envs.agent_group import GROUP, AgentGroupMixin, agent_column, root_column
from sg_torchrl.envs.multi_agent.layout import AgentLayout, agent_layout
from sg_torchrl.envs.multi_agent.partitions import Scenario, scenario_of
from sg_torchrl.envs.velocity.env import VelocityEnv
from sg_torchrl.envs.velocity.robots import ROBOTS, load_model

__all__ = ["GROUP", "MultiAgentVelocityEnv"]


class MultiAgentVelocityEnv(AgentGroupMixin, VelocityEnv):
    """A MaMuJoCo-partitioned v4 robot with Safety-Gymnasium's multi-agent velocity cost, batched.

    Args:
        scenario: the robot, a key of :data:`~sg_torchrl.envs.multi_agent.partitions.SCENARIOS`
            (``"Ant"``, ``"HalfCheetah"``, ``"Hopper"``, ``"Humanoid"``, ``"Swimmer"``, ``"Walker2d"``).
        agent_conf: MaMuJoCo's partition, e.g. ``"2x4"`` (valid ones per robot in the scenario).
        agent_obsk: graph distance of the joints an agent observes (MaMuJoCo's ``agent_obsk``; the
            reference and its sizes use 1).
        velocity_threshold: override the configuration's threshold (reference section 9).
        physics_threads, backend, warp_device, warp_options: how the simulators run, the fields of
            :class:`~sg_torchrl.envs.options.SimulatorOptions` (handed to :class:`~sg_torchrl.envs.velocity.VelocityEnv`).
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
        seed: int | list[int] | None = None,
        cost_mode: CostMode = "indicator",
        max_episode_steps: int = 1000,
        velocity_threshold: float | None = None,
        physics_threads: int = 1,
        backend: Backend = "cpu",
        warp_device: str | None = None,
        warp_options: dict[str, Any] | None = None,
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
            physics_threads=physics_threads,
            backend=backend,
            warp_device=warp_device,
            warp_options=warp_options,
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

    @property
    def _action_slot(self) -> np.ndarray:
        return self.layout.action_slot

    def _make_specs(self, observation_dim: int) -> None:
        layout = self.layout
        # Per action slot, its actuator's control range; padding slots the robot's widest range.
        slots = layout.action_actuators
        self._make_group_specs(
            observation_width=layout.observation_index.shape[1],
            state_dim=layout.state_dim,
            action_low=np.where(slots >= 0, self._action_low[slots], self._action_low.min()),
            action_high=np.where(slots >= 0, self._action_high[slots], self._action_high.max()),
            constraint_names=self.constraint_names,
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

    # ------------------------------------------------------------------ output
    def _output_arrays(self, observation, reward, costs, terminated, truncated) -> dict:
        """The step's (or, with ``reward=None``, the reset's) output as a nested dict of fresh numpy
        arrays with the emitted shapes and dtypes: the body of :meth:`_pack` without TensorDicts.
        The PettingZoo façade reads it directly."""
        cost, cost_info = self._aggregate_cost(costs)
        n, agents = self.num_envs, self.num_agents

        def root(values: np.ndarray, dtype: type) -> np.ndarray:
            return root_column(values, n, dtype)

        def per_agent(values: np.ndarray, dtype: type) -> np.ndarray:  # one value shared by every agent
            return agent_column(values, n, agents, dtype)

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
