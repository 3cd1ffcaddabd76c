"""Multi-agent navigation: ``Safety{Point,Ant}MultiGoal{0,1,2}-v0`` in TorchRL's multi-agent layout.

Safety-Gymnasium's safe multi-agent navigation tasks: two robots of one kind share a navigation
world, each an agent with its own goal, its own reward and its own costs
(:mod:`sg_torchrl.envs.navigation.tasks.multi_goal` has the task's facts).
:class:`MultiAgentNavigationEnv` is the navigation engine's
:class:`~sg_torchrl.envs.navigation.NavigationEnv` built for such a task (one compiled world with
both robots, layouts with every keep-out, per-robot lidar, per-agent reward and costs, seeding,
partial resets, divergence isolation: all inherited) behind TorchRL's multi-agent interface
(:class:`~sg_torchrl.envs.agent_group.AgentGroupMixin`).

TensorDict layout (:mod:`.group`; ``A = 2`` agents, ``agent_i`` drives robot ``i``):

* ``("agents", "observation")`` ``(N, A, D)``: with ``agent_view="joint"`` (default) every agent
  observes Safety-Gymnasium's one observation vector, which it hands to each agent: robot 0's sensors,
  robot 1's sensors, then robot 0's lidars (``goal_red``, ``goal_blue``, then the level's objects,
  each seen from robot 0), then robot 1's (seen from robot 1); :attr:`observation_slices` names
  every part (``"agent_1/hazards_lidar"``, ...). ``D`` is the reference's size: Point 88 / 152 / 152,
  Ant 144 / 208 / 208 at levels 0 / 1 / 2. With ``agent_view="own"`` agent ``i`` observes only its
  own part, robot ``i``'s sensors then its lidars (Point 44 / 76 / 76, Ant 72 / 104 / 104): the
  single-agent observation of its robot with one more goal lidar. ``("agents", "observation_mask")``
  is all ``True`` (both agents have the same size).
* ``("agents", "action")`` ``(N, A, Da)``: robot ``i``'s actuators (Point 2, Ant 8), clipped to their
  control range.
* ``("agents", "reward")`` ``(N, A, 1)``: **each agent's own reward** (progress towards its own goal,
  +1 on reaching it); not shared.
* ``("agents", "cost")`` ``(N, A, 1)``: **each agent's own cost**: the indicator of the sum of its own
  raw costs (``cost_mode="raw"``: the sum); ``("agents", "cost_info", name)`` ``(N, A, 1)`` per
  constraint (``hazards``, ``vases_contact``, ``vases_velocity``, ``contact_other``).
* ``("agents", "done" | "terminated" | "truncated")``: shared: the agents live one episode (a failed goal
  re-sampling or a dead Ant ends it for both).
* ``"state"`` ``(N, S)``: the joint observation vector above (``S`` = the joint ``D``); it holds
  every agent's own part.
* ``"cost"`` and ``("cost_info", name)`` ``(N, 1)``: the team: per constraint the agents' raw costs
  summed, then the indicator, i.e. 1 when some agent paid (``cost_mode="raw"``: the sums).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch

from sg_torchrl.envs.base import CostMode
from sg_torchrl.envs.agent_group import JointVectorAgentsMixin
from sg_torchrl.envs.navigation.env import NavigationEnv
from sg_torchrl.envs.navigation.lidar import LidarMode
from sg_torchrl.envs.navigation.tasks import Task

__all__ = ["AgentView", "MultiAgentNavigationEnv"]

#: What each agent observes: the joint observation vector (the reference's) or its own robot's part.
AgentView = Literal["joint", "own"]


class MultiAgentNavigationEnv(JointVectorAgentsMixin, NavigationEnv):
    """A multi-agent navigation task (several robots, one world) in TorchRL's multi-agent layout, batched.

    Args:
        robot: the robot of every agent, a key of :data:`~sg_torchrl.envs.navigation.robots.ROBOTS`.
        task: a multi-agent task of :data:`~sg_torchrl.envs.navigation.levels.MULTI_AGENT_TASKS`
            (``"MultiGoal"``) or a fresh task instance.
        level: the task level (0, 1, 2).
        agent_view: ``"joint"`` (default, the reference's: every agent observes the joint vector) or
            ``"own"`` (each agent its own robot's sensors and lidars); see the module docstring.
        num_envs, device, seed, cost_mode, max_episode_steps, lidar, compass, physics_threads: see
            :class:`~sg_torchrl.envs.navigation.NavigationEnv`.

    See the module docstring for the TensorDict layout.
    """

    def __init__(
        self,
        robot: str = "Point",
        task: str | Task = "MultiGoal",
        level: int = 1,
        *,
        agent_view: AgentView = "joint",
        num_envs: int = 1,
        device: torch.device | str = "cpu",
        seed: int | list[int] | None = None,
        cost_mode: CostMode = "indicator",
        max_episode_steps: int | None = None,
        lidar: LidarMode = "pseudo",
        compass: bool = False,
        physics_threads: int = 1,
    ) -> None:
        if agent_view not in ("joint", "own"):
            raise ValueError(f"agent_view must be 'joint' or 'own', got {agent_view!r}")
        self.agent_view: AgentView = agent_view
        super().__init__(robot, task, level, num_envs=num_envs, device=device, seed=seed, cost_mode=cost_mode,
                         max_episode_steps=max_episode_steps, lidar=lidar, compass=compass,
                         physics_threads=physics_threads)

    # ------------------------------------------------------------------ layout
    @property
    def num_agents(self) -> int:
        return len(self.robots)

    @property
    def action_sizes(self) -> tuple[int, ...]:
        """Number of actuators per agent: its robot's."""
        return tuple(robot.action_size for robot in self.robots)

    @property
    def _action_slot(self) -> np.ndarray:
        return self._slots

    def _agent_columns(self) -> np.ndarray:
        """``(A, D)`` the columns of the joint vector each agent observes (see ``agent_view``)."""
        joint = self._observation.shape[1]
        if self.agent_view == "joint":
            return np.tile(np.arange(joint), (self.num_agents, 1))
        own = []
        for sensors, lidars, compasses in zip(self._robot_columns, self._lidar_groups, self._compass_groups):
            parts = sorted([sensors, *(part for _, part in lidars), *(part for _, part in compasses)],
                           key=lambda part: part.start)
            own.append(np.concatenate([np.arange(part.start, part.stop) for part in parts]))
        return np.stack(own)

    def _make_specs(self, observation_dim: int) -> None:
        # Called by the base constructor once the observation layout is known: resolve the agents' columns here.
        # The robots are of one kind: agent a's slot k drives the k-th actuator of robot a.
        actuators = np.stack([robot.actuator_ids for robot in self.robots])  # (A, Da)
        self._slots = np.empty(self.physics.model.nu, dtype=np.int64)
        self._slots[actuators.reshape(-1)] = np.arange(actuators.size)
        self._make_joint_view_specs(self._agent_columns(), observation_dim, self._action_low[actuators],
                                    self._action_high[actuators])

    # ------------------------------------------------------------------ hooks
    def _compute_reward(self, action: np.ndarray) -> np.ndarray:
        """Each agent's own (clipped) reward, ``(N, A)``."""
        return self._agent_reward

    def _compute_cost(self) -> dict[str, np.ndarray]:
        """Each agent's own raw cost per constraint, ``(N, A)`` each."""
        return self._agent_costs
