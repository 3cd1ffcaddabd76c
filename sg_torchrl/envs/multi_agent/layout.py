"""Index tables that turn one batched single-robot simulation into per-agent tensors.

A :class:`~.partitions.Scenario` names joints, bodies and fields; :func:`agent_layout` resolves
them once against the compiled MuJoCo model into two integer tables, so that the env's hot path
is two numpy gathers for the whole batch and every agent (no per-agent Python loop):

* **observations**: the env keeps one *source* row per simulator: the robot's v4 observation (the
  global ``state``), then, only where needed, the raw joint velocities (Walker2d agents observe
  unclipped velocities, its v4 observation clips them), then one constant 0. Every value an agent
  observes is a column of that row, so ``source[:, observation_index]`` is the ``(N, A, D)`` group
  observation; the padding slots of smaller agents point at the 0 column.
* **actions**: ``action_slot[u]`` is the position of actuator ``u`` in the flattened ``(A, Da)``
  group action, so ``group_action.reshape(N, -1)[:, action_slot]`` is the robot's ``(N, nu)``
  control. Building it checks that every actuator belongs to exactly one agent.

The observation order is MaMuJoCo's (Peng et al., 2021; gymnasium-robotics ``obsk.build_obs``):
graph distance 0, 1, ... ``obsk``; within one distance the nodes sorted by label; per node the
distance's fields in order (a body's ``cinert``/``cvel``/``cfrc_ext`` only the first time the agent
meets it); then the scenario's global entries.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from sg_torchrl.envs.multi_agent.partitions import Field, Node, Scenario
from sg_torchrl.envs.velocity.robots import LocomotionRobot

__all__ = ["AgentLayout", "agent_layout", "neighbourhoods"]

_BODY_WIDTH = {"cinert": 10, "cvel": 6, "cfrc_ext": 6}


@dataclass(frozen=True)
class AgentLayout:
    """The resolved partition of one (scenario, configuration, obsk).

    Attributes:
        observation_sizes: true observation length of each agent.
        action_sizes: number of actuators of each agent.
        observation_index: ``(A, max observation size)`` columns of the source row; padding slots
            hold its last column, the constant 0.
        observation_mask: ``(A, max observation size)`` bool, ``True`` on real entries.
        action_actuators: ``(A, max action size)`` actuator driven by each action slot, ``-1`` on
            padding slots.
        action_slot: ``(nu,)`` position of each actuator in the flattened group action.
        state_dim: length of the v4 observation (the global ``state``), the first source columns.
        raw_qvel: the source row appends the raw ``qvel`` after the state.
        source_dim: length of the source row (state, raw qvel if any, the 0 column).
        observed: per agent, the ``(field, index)`` terms of its observation in order, for
            documentation and tests (``index`` is a joint address or ``(body, element)``).
    """

    observation_sizes: tuple[int, ...]
    action_sizes: tuple[int, ...]
    observation_index: np.ndarray
    observation_mask: np.ndarray
    action_actuators: np.ndarray
    action_slot: np.ndarray
    state_dim: int
    raw_qvel: bool
    source_dim: int
    observed: tuple[tuple[tuple[Field, object], ...], ...]

    @property
    def num_agents(self) -> int:
        return len(self.observation_sizes)


def neighbourhoods(scenario: Scenario, agent: tuple[Node, ...], obsk: int) -> list[list[Node]]:
    """The agent's nodes at graph distance 0, 1, ..., ``obsk``, each list sorted by label."""
    edges = [set(edge) for edge in scenario.edges]
    seen = {node.label for node in agent}
    frontier = set(seen)
    rings = [sorted(seen)]
    for _ in range(obsk):
        adjacent = {label for edge in edges if edge & frontier for label in edge}
        frontier = adjacent - seen
        seen |= frontier
        rings.append(sorted(frontier))
    return [[scenario.node(label) for label in ring] for ring in rings]


def _agent_terms(scenario: Scenario, agent: tuple[Node, ...], obsk: int, model: mujoco.MjModel) -> list:
    """The ``(field, index)`` terms of one agent's observation, in MaMuJoCo's order."""
    qpos_of = {model.joint(j).name: int(model.jnt_qposadr[j]) for j in range(model.njnt)}
    dof_of = {model.joint(j).name: int(model.jnt_dofadr[j]) for j in range(model.njnt)}
    terms: list[tuple[Field, object]] = []
    bodies_seen: dict[str, set[str]] = {name: set() for name in _BODY_WIDTH}
    for distance, ring in enumerate(neighbourhoods(scenario, agent, obsk)):
        fields = scenario.local_fields[min(distance, len(scenario.local_fields) - 1)]
        for node in ring:
            for name in fields:
                if name == "qpos":
                    terms.append(("qpos", qpos_of[node.joint]))
                elif name == "qvel":
                    terms.extend(("qvel", dof_of[joint]) for joint in node.velocity_joints)
                elif name == "qfrc_actuator":
                    terms.append(("qfrc_actuator", dof_of[node.joint]))
                else:  # a body field
                    for body in node.bodies:
                        if body not in bodies_seen[name]:
                            bodies_seen[name].add(body)
                            body_id = model.body(body).id
                            terms.extend((name, (body_id, e)) for e in range(_BODY_WIDTH[name]))
    for name, indices in scenario.globals:
        terms.extend((name, index) for index in indices)
    return terms


class _SourceColumns:
    """Where each ``(field, index)`` term sits in the source row (see the module docstring)."""

    def __init__(self, robot: LocomotionRobot, scenario: Scenario, model: mujoco.MjModel) -> None:
        data = mujoco.MjData(model)
        self.qpos_skip = robot.qpos_skip
        self.state_dim = model.nq - robot.qpos_skip + model.nv
        self.offsets: dict[str, int] = {"qvel": model.nq - robot.qpos_skip}
        for name in robot.extra_observations:  # the v4 observation appends these flattened, in order
            self.offsets[name] = self.state_dim
            self.state_dim += getattr(data, name).size
        # The v4 observation clips velocities for some robots; agents that observe raw ones read an appended copy.
        self.raw_qvel = robot.qvel_clip is not None and not scenario.clipped_qvel
        if self.raw_qvel:
            self.offsets["qvel"] = self.state_dim
        self.source_dim = self.state_dim + (model.nv if self.raw_qvel else 0) + 1
        self.robot = robot.name

    def __call__(self, name: Field, index) -> int:
        if name == "qpos":
            if index < self.qpos_skip:
                raise ValueError(f"{self.robot}: qpos[{index}] is not part of the v4 observation")
            return index - self.qpos_skip
        if name not in self.offsets:
            raise ValueError(f"{self.robot}: the v4 observation holds no {name!r}")
        if name in _BODY_WIDTH:
            body, element = index
            return self.offsets[name] + body * _BODY_WIDTH[name] + element
        return self.offsets[name] + index


def agent_layout(
    scenario: Scenario, conf: str, robot: LocomotionRobot, model: mujoco.MjModel, obsk: int = 1
) -> AgentLayout:
    """Resolve ``scenario``'s partition ``conf`` against ``model`` (the robot's compiled v4 model).

    Raises ``ValueError`` if an actuator is driven by no agent or by several.
    """
    if obsk < 0:
        raise ValueError(f"obsk must be >= 0, got {obsk}")
    agents = scenario.agents(conf)
    columns = _SourceColumns(robot, scenario, model)
    observed = [_agent_terms(scenario, agent, obsk, model) for agent in agents]
    observation_sizes = tuple(len(terms) for terms in observed)
    width = max(observation_sizes)
    observation_index = np.full((len(agents), width), columns.source_dim - 1, dtype=np.int64)
    for row, terms in zip(observation_index, observed):
        row[: len(terms)] = [columns(name, index) for name, index in terms]
    observation_mask = np.arange(width)[None, :] < np.asarray(observation_sizes)[:, None]

    actuator_of = {model.joint(int(model.actuator_trnid[u, 0])).name: u for u in range(model.nu)}
    action_sizes = tuple(len(agent) for agent in agents)
    action_actuators = np.full((len(agents), max(action_sizes)), -1, dtype=np.int64)
    for row, agent in zip(action_actuators, agents):
        row[: len(agent)] = [actuator_of[node.actuator] for node in agent]
    owners = np.bincount(action_actuators[action_actuators >= 0], minlength=model.nu)
    if not (owners == 1).all():
        raise ValueError(
            f"{scenario.robot} {conf}: every actuator must belong to exactly one agent; "
            f"owners per actuator: {owners.tolist()}"
        )
    flat = action_actuators.reshape(-1)
    action_slot = np.empty(model.nu, dtype=np.int64)
    action_slot[flat[flat >= 0]] = np.flatnonzero(flat >= 0)
    return AgentLayout(
        observation_sizes=observation_sizes,
        action_sizes=action_sizes,
        observation_index=observation_index,
        observation_mask=observation_mask,
        action_actuators=action_actuators,
        action_slot=action_slot,
        state_dim=columns.state_dim,
        raw_qvel=columns.raw_qvel,
        source_dim=columns.source_dim,
        observed=tuple(tuple(terms) for terms in observed),
    )
