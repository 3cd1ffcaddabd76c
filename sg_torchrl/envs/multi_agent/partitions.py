"""MaMuJoCo's agent partitions of the velocity robots, as data.

Multi-Agent MuJoCo (MaMuJoCo; Peng et al., "FACMAC: Factored Multi-Agent Centralised Policy
Gradients", NeurIPS 2021) splits one robot among several agents: each agent drives a fixed set of
joints and observes them, the joints one edge away in the robot's body graph (``obsk=1``) and a
few global quantities of the torso. Safety-Gymnasium's multi-agent velocity tasks
(``safety_gymnasium.make_ma``; Ji et al., 2023) run gymnasium-robotics' MaMuJoCo on gymnasium's
**v4** robots and add the velocity cost.

Each robot is one :class:`Scenario` record holding MaMuJoCo's facts: the graph nodes (joint,
actuator, velocity and body entries), the hyper-edges, the global observation, the partitions per
configuration and Safety-Gymnasium's cost threshold per configuration
(``reference/safety_gymnasium_semantics.md`` sections 9 and 10). :mod:`.layout` turns a record
into index tables; nothing here runs MaMuJoCo.

Where the facts come from: the node graphs and partitions are those of gymnasium-robotics'
``multiagent_mujoco/obsk.py`` (1.4.2, unchanged since 1.2). The **observation** layout is the one
of gymnasium-robotics 1.2.x, which Safety-Gymnasium 1.0.0 ran on (the v4 envs) and whose sizes the
paper's results were produced with. It differs from 1.4.2 (v5 envs) in four ways, kept here so
that sizes and results compare with the reference:

* the underlying robots are gymnasium's v4 envs: the global ``state`` is the v4 observation (Ant
  27 without contact forces, Humanoid 376 with the world body's terms) and Ant agents do not
  observe contact forces (MaMuJoCo 1.2: "Ant-v4 has disabled cfrc_ext");
* Humanoid agents also observe the torso's actuator forces ``qfrc_actuator[:6]`` (globals);
* Walker2d's global nodes are ``[root_x, root_x, root_z]`` in 1.2 (``root_y``, the torso pitch, is
  missing and the x velocity appears twice), giving the reference's 11 values per agent, not 12;
* (as in 1.4.2) Humanoid's node ``abdomen_y`` observes the position and velocity of the *joint*
  ``abdomen_z`` and vice versa, while their actuators are the ones named after the node.

The oracle tests build gymnasium-robotics 1.4.2's MaMuJoCo with the options that restore this
layout and compare every agent's observation with ours.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

__all__ = ["Field", "Node", "Scenario", "SCENARIOS", "scenario_of"]

#: ``MjData`` arrays an observation reads. ``qpos``/``qvel``/``qfrc_actuator`` are indexed by joint,
#: ``cinert``/``cvel``/``cfrc_ext`` by body (10, 6 and 6 values per body).
Field = Literal["qpos", "qvel", "qfrc_actuator", "cinert", "cvel", "cfrc_ext"]


@dataclass(frozen=True)
class Node:
    """One node of MaMuJoCo's body graph: a joint with its actuator.

    Args:
        label: MaMuJoCo's node name. Within one graph distance an agent lists its nodes sorted by
            label, so the label fixes the observation order.
        joint: MuJoCo joint whose ``qpos``/``qvel``/``qfrc_actuator`` entries the node contributes.
        actuator: MuJoCo joint driven by the node's actuator (defaults to ``joint``).
        qvel: joints whose velocities the node contributes instead of its own (Swimmer).
        bodies: bodies whose ``cinert``/``cvel``/``cfrc_ext`` the node contributes (Humanoid), each
            body at most once per agent and field.
    """

    label: str
    joint: str
    actuator: str = ""
    qvel: tuple[str, ...] = ()
    bodies: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.actuator:
            object.__setattr__(self, "actuator", self.joint)

    @property
    def velocity_joints(self) -> tuple[str, ...]:
        return self.qvel or (self.joint,)


@dataclass(frozen=True)
class Scenario:
    """One robot's MaMuJoCo graph and Safety-Gymnasium's multi-agent velocity task on it.

    Args:
        robot: key of :data:`sg_torchrl.envs.velocity.ROBOTS` (the gymnasium v4 robot).
        nodes: the graph nodes (every actuated joint).
        edges: hyper-edges as tuples of node labels: nodes sharing an edge are one step apart.
        globals: what every agent observes after its local part, in order: ``(field, indices)``
            pairs of ``MjData`` entries (``qpos[2:7]`` of a free joint is ``("qpos", (2, ..., 6))``).
        partitions: per configuration (``"2x4"``), each agent's nodes in the order of its action.
        thresholds: Safety-Gymnasium's velocity cost threshold per configuration.
        local_fields: fields observed of the nodes at graph distance 0, 1, ... (the last entry
            repeats for larger distances).
        clipped_qvel: local and global velocities are clipped to the v4 observation's range
            (Hopper); otherwise they are the raw ``qvel`` even where the v4 observation clips (Walker2d).
        cost_velocity: ``"planar"``: the cost measures ``hypot(vx, vy)`` (``|vx|`` for robots moving
            along x only, as Safety-Gymnasium reads a missing ``y_velocity`` as 0); ``"x"``: the
            signed x velocity (Swimmer).
    """

    robot: str
    nodes: tuple[Node, ...]
    edges: tuple[tuple[str, ...], ...]
    globals: tuple[tuple[Field, tuple[int, ...]], ...]
    partitions: dict[str, tuple[tuple[str, ...], ...]]
    thresholds: dict[str, float]
    local_fields: tuple[tuple[Field, ...], ...] = (("qpos", "qvel"), ("qpos",))
    clipped_qvel: bool = False
    cost_velocity: Literal["planar", "x"] = "planar"
    _by_label: dict[str, Node] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        by_label = {node.label: node for node in self.nodes}
        if len(by_label) != len(self.nodes):
            raise ValueError(f"{self.robot}: duplicate node labels")
        for group in (*self.edges, *(agent for agents in self.partitions.values() for agent in agents)):
            unknown = set(group) - set(by_label)
            if unknown:
                raise ValueError(f"{self.robot}: unknown node labels {sorted(unknown)}")
        if set(self.partitions) != set(self.thresholds):
            raise ValueError(f"{self.robot}: every configuration needs a cost threshold")
        object.__setattr__(self, "_by_label", by_label)

    def node(self, label: str) -> Node:
        return self._by_label[label]

    def agents(self, conf: str) -> tuple[tuple[Node, ...], ...]:
        """Each agent's nodes, in action order, for configuration ``conf``."""
        if conf not in self.partitions:
            raise ValueError(f"{self.robot} has configurations {sorted(self.partitions)}, got {conf!r}")
        return tuple(tuple(self._by_label[label] for label in agent) for agent in self.partitions[conf])


def _joints(*names: str) -> tuple[Node, ...]:
    """Nodes whose label, joint and actuator share one name."""
    return tuple(Node(name, name) for name in names)


def _range(start: int, stop: int) -> tuple[int, ...]:
    return tuple(range(start, stop))


_HUMANOID_FIELDS: tuple[Field, ...] = ("qpos", "qvel", "cinert", "cvel", "qfrc_actuator", "cfrc_ext")
_RIGHT_ARM = ("torso", "right_upper_arm", "right_lower_arm")
_LEFT_ARM = ("torso", "left_upper_arm", "left_lower_arm")
_ABDOMEN = ("torso", "lwaist", "pelvis")

SCENARIOS: dict[str, Scenario] = {
    scenario.robot: scenario
    for scenario in (
        Scenario(
            robot="HalfCheetah",
            nodes=_joints("bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot"),
            edges=(("bfoot", "bshin"), ("bshin", "bthigh"), ("bthigh", "fthigh"), ("fthigh", "fshin"),
                   ("fshin", "ffoot")),
            # root_x's position is not observed; root_z, root_y positions; all three root velocities.
            globals=(("qpos", (1, 2)), ("qvel", (0, 1, 2))),
            partitions={
                "2x3": (("bthigh", "bshin", "bfoot"), ("fthigh", "fshin", "ffoot")),
                "6x1": (("bthigh",), ("bshin",), ("bfoot",), ("fthigh",), ("fshin",), ("ffoot",)),
            },
            thresholds={"2x3": 3.227, "6x1": 2.932},
        ),
        Scenario(
            robot="Ant",
            nodes=(
                Node("hip1", "hip_1"), Node("ankle1", "ankle_1"),  # front left leg
                Node("hip2", "hip_2"), Node("ankle2", "ankle_2"),  # front right leg
                Node("hip3", "hip_3"), Node("ankle3", "ankle_3"),  # back left leg
                Node("hip4", "hip_4"), Node("ankle4", "ankle_4"),  # back right leg
            ),
            edges=(("ankle4", "hip4"), ("ankle1", "hip1"), ("ankle2", "hip2"), ("ankle3", "hip3"),
                   ("hip4", "hip1", "hip2", "hip3")),
            # The torso's free joint: height and orientation qpos[2:7], linear and angular qvel[0:6].
            globals=(("qpos", _range(2, 7)), ("qvel", _range(0, 6))),
            partitions={
                "2x4": (("hip1", "ankle1", "hip2", "ankle2"), ("hip3", "ankle3", "hip4", "ankle4")),
                "4x2": (("hip1", "ankle1"), ("hip2", "ankle2"), ("hip3", "ankle3"), ("hip4", "ankle4")),
            },
            thresholds={"2x4": 2.522, "4x2": 2.418},
        ),
        Scenario(
            robot="Hopper",
            nodes=_joints("thigh_joint", "leg_joint", "foot_joint"),
            edges=(("foot_joint", "leg_joint"), ("leg_joint", "thigh_joint")),
            globals=(("qpos", (1, 2)), ("qvel", (0, 1, 2))),
            partitions={"3x1": (("thigh_joint",), ("leg_joint",), ("foot_joint",))},
            thresholds={"3x1": 0.9613},
            clipped_qvel=True,  # MaMuJoCo clips every Hopper velocity to [-10, 10], as the v4 observation does
        ),
        Scenario(
            robot="Humanoid",
            nodes=(
                # MaMuJoCo's abdomen_y / abdomen_z nodes read each other's joint (module docstring).
                Node("abdomen_y", "abdomen_z", actuator="abdomen_y", bodies=_ABDOMEN),
                Node("abdomen_z", "abdomen_y", actuator="abdomen_z", bodies=_ABDOMEN),
                Node("abdomen_x", "abdomen_x", bodies=("pelvis", "right_thigh", "left_thigh")),
                *(Node(f"right_hip_{a}", f"right_hip_{a}", bodies=("right_thigh", "right_shin")) for a in "xzy"),
                Node("right_knee", "right_knee", bodies=("right_shin", "right_foot")),
                *(Node(f"left_hip_{a}", f"left_hip_{a}", bodies=("left_thigh", "left_shin")) for a in "xzy"),
                Node("left_knee", "left_knee", bodies=("left_shin", "left_foot")),
                Node("right_shoulder1", "right_shoulder1", bodies=_RIGHT_ARM),
                Node("right_shoulder2", "right_shoulder2", bodies=_RIGHT_ARM),
                Node("right_elbow", "right_elbow", bodies=("right_lower_arm",)),
                Node("left_shoulder1", "left_shoulder1", bodies=_LEFT_ARM),
                Node("left_shoulder2", "left_shoulder2", bodies=_LEFT_ARM),
                Node("left_elbow", "left_elbow", bodies=("left_lower_arm",)),
            ),
            edges=(
                ("abdomen_x", "abdomen_y", "abdomen_z"),
                ("right_hip_x", "right_hip_y", "right_hip_z"),
                ("left_hip_x", "left_hip_y", "left_hip_z"),
                ("left_elbow", "left_shoulder1", "left_shoulder2"),
                ("right_elbow", "right_shoulder1", "right_shoulder2"),
                ("left_knee", "left_hip_x", "left_hip_y", "left_hip_z"),
                ("right_knee", "right_hip_x", "right_hip_y", "right_hip_z"),
                ("left_shoulder1", "left_shoulder2", "abdomen_x", "abdomen_y", "abdomen_z"),
                ("right_shoulder1", "right_shoulder2", "abdomen_x", "abdomen_y", "abdomen_z"),
                ("abdomen_x", "abdomen_y", "abdomen_z", "left_hip_x", "left_hip_y", "left_hip_z"),
                ("abdomen_x", "abdomen_y", "abdomen_z", "right_hip_x", "right_hip_y", "right_hip_z"),
            ),
            # The torso: qpos[2:7], qvel[0:6] and (gymnasium-robotics 1.2) qfrc_actuator[0:6].
            globals=(("qpos", _range(2, 7)), ("qvel", _range(0, 6)), ("qfrc_actuator", _range(0, 6))),
            partitions={
                "9|8": (
                    ("abdomen_x", "abdomen_y", "abdomen_z", "right_shoulder1", "right_shoulder2", "right_elbow",
                     "left_shoulder1", "left_shoulder2", "left_elbow"),  # upper body
                    ("right_hip_x", "right_hip_y", "right_hip_z", "right_knee", "left_hip_x", "left_hip_y",
                     "left_hip_z", "left_knee"),  # lower body
                ),
            },
            thresholds={"9|8": 0.58},
            local_fields=(_HUMANOID_FIELDS, ("qpos",)),
        ),
        Scenario(
            robot="Swimmer",
            nodes=(
                # Each rotor also reports one of the body's planar velocities (x for rot2, y for rot3).
                Node("rot2", "motor1_rot", qvel=("slider1", "motor1_rot")),
                Node("rot3", "motor2_rot", qvel=("slider2", "motor2_rot")),
            ),
            edges=(("rot2", "rot3"),),
            globals=(("qpos", (2,)), ("qvel", (2,))),  # the front body's rotation free_body_rot
            partitions={"2x1": (("rot2",), ("rot3",))},
            thresholds={"2x1": 0.04891},
            cost_velocity="x",
        ),
        Scenario(
            robot="Walker2d",
            nodes=_joints("thigh_joint", "leg_joint", "foot_joint", "thigh_left_joint", "leg_left_joint",
                          "foot_left_joint"),
            edges=(("foot_joint", "leg_joint"), ("leg_joint", "thigh_joint"), ("foot_left_joint", "leg_left_joint"),
                   ("leg_left_joint", "thigh_left_joint"), ("thigh_joint", "thigh_left_joint")),
            # gymnasium-robotics 1.2's globals [root_x, root_x, root_z]: z position; x, x, z velocities.
            globals=(("qpos", (1,)), ("qvel", (0, 0, 1))),
            partitions={
                "2x3": (("foot_joint", "leg_joint", "thigh_joint"),
                        ("foot_left_joint", "leg_left_joint", "thigh_left_joint")),
            },
            thresholds={"2x3": 1.641},
        ),
    )
}


def scenario_of(robot: str) -> Scenario:
    """The :class:`Scenario` of ``robot``, with an error listing the valid ones."""
    try:
        return SCENARIOS[robot]
    except KeyError:
        raise ValueError(f"no multi-agent scenario for {robot!r}; choose from {sorted(SCENARIOS)}") from None
