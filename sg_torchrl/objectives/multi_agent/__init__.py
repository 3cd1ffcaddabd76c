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
* the rounds, ``update(batch, mean_episode_cost) -> dict[str, float]``: :class:`MAPPOUpdate`
  (Yu et al. 2022), :class:`HAPPOUpdate` (Kuba et al. 2022), :class:`MAPPOLagUpdate`
  (:class:`MultiAgentPPOUpdate`) and
  :class:`MACPOUpdate` (Gu et al. 2023; :class:`MACPORule` is CPO's proposal with MACPO's step-size
  policy, :class:`MACPOStep` on one actor, :class:`StackedMACPOStep` on the round's rows), all
  :class:`SeedBatchedRound` s: S seeds' rounds in one update call per stage (``for_seeds``), each seed with
  its own random agent order. Their minibatch epochs are the package's one update loop,
  :func:`~sg_torchrl.objectives.run_passes`.
"""

from sg_torchrl.objectives.multi_agent.advantages import (
    AGENT_VIEW_KEYS,
    agent_view,
    make_multi_agent_cost_gae,
    make_multi_agent_gae,
)
from sg_torchrl.objectives.multi_agent.loss import AgentPPOLoss
from sg_torchrl.objectives.multi_agent.macpo import MACPORule, MACPOStep, MACPOUpdate, StackedMACPOStep
from sg_torchrl.objectives.multi_agent.multiplier import MAPPOLagMultiplier
from sg_torchrl.objectives.multi_agent.objective import AgentObjective
from sg_torchrl.objectives.multi_agent.seed_round import SeedBatchedRound
from sg_torchrl.objectives.multi_agent.updates import HAPPOUpdate, MAPPOLagUpdate, MAPPOUpdate, MultiAgentPPOUpdate

__all__ = [
    "AGENT_VIEW_KEYS",
    "AgentObjective",
    "AgentPPOLoss",
    "HAPPOUpdate",
    "MACPORule",
    "MACPOStep",
    "MACPOUpdate",
    "MAPPOLagMultiplier",
    "MAPPOLagUpdate",
    "MAPPOUpdate",
    "MultiAgentPPOUpdate",
    "SeedBatchedRound",
    "StackedMACPOStep",
    "agent_view",
    "make_multi_agent_cost_gae",
    "make_multi_agent_gae",
]
