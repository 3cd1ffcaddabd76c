"""Safe multi-agent algorithms of the Safety-Gymnasium paper: MAPPO, HAPPO, MAPPO-Lag and MACPO.

Over TorchRL's multi-agent layout (group ``("agents", ...)`` with batch ``[*B, n_agents]``, a
global ``"state"`` for the centralised critics):

* the networks they train live in :mod:`sg_torchrl.modules.multi_agent`
  (:func:`~sg_torchrl.modules.make_multi_agent_networks` / :class:`~sg_torchrl.modules.MultiAgentNetworks`:
  one actor, one reward critic and one cost critic per agent, group-wise for collection and per agent
  for the updates);
* :func:`make_multi_agent_gae`, :func:`make_multi_agent_cost_gae`: per-agent reward and cost GAE
  (:func:`~sg_torchrl.objectives.make_gae` / :func:`~sg_torchrl.objectives.make_cost_gae` with TorchRL's
  :class:`~torchrl.objectives.value.MultiAgentGAE` over the group keys), standardised per agent;
* :class:`AgentObjective`: one agent's factor-weighted clipped PPO with reward and cost critics, written
  once for a leading seed dimension; :class:`AgentPPOLoss` is its TorchRL LossModule view (TorchRL's
  :class:`~torchrl.objectives.multiagent.MAPPOLoss` with sg_torchrl's :class:`~sg_torchrl.objectives.PPOLagLoss`),
  which hands the rounds the objective (:meth:`AgentPPOLoss.seed_batched_objective`);
  :class:`MAPPOLagMultiplier`: MAPPO-Lagrangian's per-agent multiplier (Gu et al. 2023);
* :class:`MACPORule`: CPO's proposal with MACPO's step-size policy, on one actor (:class:`MACPOStep`) or on
  stacked rows (:class:`StackedMACPOStep`).

The rounds that train these (``update(batch, mean_episode_cost) -> dict[str, float]``: ``MAPPOUpdate``
(Yu et al. 2022), ``HAPPOUpdate`` (Kuba et al. 2022), ``MAPPOLagUpdate`` and ``MACPOUpdate`` (Gu et al. 2023),
S seeds' rounds in one update call per stage) are training machinery:
:mod:`sg_torchrl.train.multi_agent_updates`.
"""

from sg_torchrl.objectives.multi_agent.advantages import (
    AGENT_VIEW_KEYS,
    agent_view,
    make_multi_agent_cost_gae,
    make_multi_agent_gae,
)
from sg_torchrl.objectives.multi_agent.loss import AgentPPOLoss
from sg_torchrl.objectives.multi_agent.macpo import MACPORule, MACPOStep, StackedMACPOStep
from sg_torchrl.objectives.multi_agent.multiplier import MAPPOLagMultiplier
from sg_torchrl.objectives.multi_agent.objective import AgentObjective

__all__ = [
    "AGENT_VIEW_KEYS",
    "AgentObjective",
    "AgentPPOLoss",
    "MACPORule",
    "MACPOStep",
    "MAPPOLagMultiplier",
    "StackedMACPOStep",
    "agent_view",
    "make_multi_agent_cost_gae",
    "make_multi_agent_gae",
]
