"""Safe multi-agent tasks: MaMuJoCo-partitioned velocity robots (Safety-Gymnasium's ``make_ma``) and
multi-agent navigation (two robots in one navigation world, MultiGoal).

* :mod:`sg_torchrl.envs.agent_group`: :class:`AgentGroupMixin`, TorchRL's multi-agent layout over a batched
  SafeEnv, once (a core module: the two-hand envs use it too);
* :mod:`.partitions`: MaMuJoCo's body graphs, partitions and Safety-Gymnasium's thresholds, as data;
* :mod:`.layout`: those resolved into the index tables the env gathers with;
* :mod:`.env`: :class:`MultiAgentVelocityEnv`, the layout over a batched partitioned robot;
* :mod:`.navigation`: :class:`MultiAgentNavigationEnv`, the layout over a batched multi-robot world.

The PettingZoo façade is :mod:`sg_torchrl.pettingzoo`.
"""

from sg_torchrl.envs.multi_agent.env import MultiAgentVelocityEnv
from sg_torchrl.envs.agent_group import GROUP, AgentGroupMixin
from sg_torchrl.envs.multi_agent.layout import AgentLayout, agent_layout
from sg_torchrl.envs.multi_agent.navigation import AgentView, MultiAgentNavigationEnv
from sg_torchrl.envs.multi_agent.partitions import SCENARIOS, Node, Scenario

__all__ = ["GROUP", "AgentGroupMixin", "AgentView", "MultiAgentNavigationEnv", "MultiAgentVelocityEnv", "AgentLayout",
           "agent_layout", "SCENARIOS", "Node", "Scenario"]
