"""The two-hand tasks as a constrained Markov game: one agent per Shadow Hand.

Safety-Gymnasium's paper (section 4.4) trains its dexterous-hand tasks with single- and multi-agent
algorithms alike (MACPO, MAPPO-L); the multi-agent form splits the same world by hand.
:class:`MultiAgentShadowHandEnv` is :class:`~sg_torchrl.envs.hands.env.ShadowHandEnv` (physics, reward,
termination, seeding, partial resets: all inherited) in TorchRL's multi-agent layout
(:mod:`sg_torchrl.envs.agent_group`):

* agents ``agent_0`` (the throwing ``right/`` hand) and ``agent_1`` (the catching ``left/`` hand);
* ``("agents", "action")`` ``(N, 2, Da)``: each agent drives its own hand's actuators (Da = 20, or 26
  with actuated bases);
* ``("agents", "observation")`` ``(N, 2, D)``: the agent's own hand block of the single-agent
  observation (187, or 199) followed by the shared ball and goal block (24): D = 211 (223);
* ``"state"``: the full single-agent observation (398 or 422), for centralised critics;
* ``("agents", "reward")``: the team reward, equal for both agents;
* ``("agents", "cost")`` and ``("agents", "cost_info", name)``: each agent pays for its own hand's
  forefinger; the root ``cost`` is 1 when either did (indicator mode).
"""

from __future__ import annotations

import numpy as np

from sg_torchrl.envs.hands.env import OBJECT_OBSERVATION_DIM, ShadowHandEnv
from sg_torchrl.envs.agent_group import JointVectorAgentsMixin

__all__ = ["MultiAgentShadowHandEnv"]


class MultiAgentShadowHandEnv(JointVectorAgentsMixin, ShadowHandEnv):
    """:class:`ShadowHandEnv` with one agent per hand (same arguments; see the module docstring)."""

    @property
    def num_agents(self) -> int:
        return len(self.layout.hands)

    @property
    def action_sizes(self) -> tuple[int, ...]:
        return tuple(len(hand.actuators) for hand in self.layout.hands)

    @property
    def _action_slot(self) -> np.ndarray:
        # The single-agent action is the hands' actuators in hand order: exactly the flattened (A, Da) group action.
        return np.arange(sum(self.action_sizes))

    def _make_specs(self, observation_dim: int) -> None:
        per_hand, agents = self.hand_observation_dim, self.num_agents
        shared = np.arange(agents * per_hand, observation_dim)
        assert len(shared) == OBJECT_OBSERVATION_DIM
        agent_index = np.stack([np.concatenate((np.arange(a * per_hand, (a + 1) * per_hand), shared))
                                for a in range(agents)])
        actions = self.action_sizes[0]
        self._make_joint_view_specs(agent_index, observation_dim, self._action_low.reshape(agents, actions),
                                    self._action_high.reshape(agents, actions))

    def _compute_cost(self) -> dict[str, np.ndarray]:
        """Each agent's raw cost per constraint: its own hand's violations, ``(N, A)`` each."""
        qpos = self.physics.qpos()
        return {c.name: c.per_hand(qpos, self._last_action) for c in self.constraints}
