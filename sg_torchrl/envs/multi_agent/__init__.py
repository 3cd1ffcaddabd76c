"""Safe multi-agent tasks: MaMuJoCo-partitioned velocity robots (Safety-Gymnasium's ``make_ma``).

* :mod:`.partitions`: MaMuJoCo's body graphs, partitions and Safety-Gymnasium's thresholds, as data;
* :mod:`.layout`: those resolved into the index tables the env gathers with;
* :mod:`.env`: :class:`MultiAgentVelocityEnv`, TorchRL's multi-agent layout over a batched robot.

The PettingZoo façade is :mod:`sg_torchrl.pettingzoo`.
"""

from sg_torchrl.envs.multi_agent.env import GROUP, MultiAgentVelocityEnv
from sg_torchrl.envs.multi_agent.layout import AgentLayout, agent_layout
from sg_torchrl.envs.multi_agent.partitions import SCENARIOS, Node, Scenario

__all__ = ["GROUP", "MultiAgentVelocityEnv", "AgentLayout", "agent_layout", "SCENARIOS", "Node", "Scenario"]
