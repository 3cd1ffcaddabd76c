"""The two-hand scene of the Shadow-Hand tasks, composed with ``mujoco.MjSpec``.

The Safety-Gymnasium paper's dexterous-hand tasks (section 4.4, "Safe Isaac Gym") put two Shadow
Hands opposite each other, palms up, and pass a ball between them. Isaac Gym ships a left/right
pair; MuJoCo here uses the one right hand of gymnasium-robotics (OpenAI's Shadow Hand model:
24 joints, 20 position actuators, the distal joints coupled to the middle ones by tendons).

Model derived from gymnasium-robotics' Shadow Hand assets (Apache-2.0, (C) Vikash Kumar, CSE, UW;
see ``NOTICE`` and ``LICENSE-gymnasium-robotics-assets.md`` in this package).

Composition (nothing is copied to disk): the hand MJCF is loaded twice from the installed
gymnasium-robotics package and attached to one world spec under the prefixes ``right/`` and
``left/``. The second copy is the first turned by pi about the vertical axis and moved across a
gap, so the palms face up and the fingers point at each other (the layout of Isaac Gym's
ShadowHandOver: wrists 1 m apart along y). Both copies are right hands: the model has no left hand
(see ``reference/stack_notes.md``), which the docs of the env say. Added to each hand: fingertip
frame sensors (position, orientation, linear and angular velocity) and force/torque sensors at
the five tip sites, which the paper's observation reads. Added to the world: a free-joint ball and
a mocap goal marker (no collision). The model is compiled once per :class:`SceneConfig` and shared
by every simulator.

Actuated bases (ShadowHandCatchOver2Underarm, :data:`BASE_JOINTS`): each hand's mount gets three
slide and three hinge joints, each driven by a position servo (Isaac Gym moves the hand roots with
forces; here the servos' ranges, gains and damping are this project's choice, see
:data:`BASE_RANGES`), 6 actuators per hand after its 20 finger actuators.
"""

from __future__ import annotations

import importlib.util
import os
from dataclasses import dataclass
from functools import lru_cache

import mujoco
import numpy as np

__all__ = ["BASE_JOINTS", "HAND_PREFIXES", "FINGERTIPS", "HandLayout", "SceneConfig", "SceneLayout", "build_scene",
           "hand_assets_dir"]

#: Prefixes of the two hands: ``right/`` throws (holds the ball at reset), ``left/`` catches.
HAND_PREFIXES = ("right/", "left/")
#: Fingertip sites of the gymnasium-robotics model, in the order the observation lists them.
FINGERTIPS = ("ff", "mf", "rf", "lf", "th")

_HAND_MOUNT = "robot0:hand mount"
#: Wrist mount height and the distance between the two mounts (Isaac Gym's ShadowHandOver: 1 m).
MOUNT_HEIGHT = 0.5
MOUNT_GAP = 1.0
#: Joints added to a hand's mount when its base is actuated: translations along, then rotations about, x, y, z
#: (the mount's frame). Unprefixed names, as :class:`HandLayout` lists them.
BASE_JOINTS = ("ARTx", "ARTy", "ARTz", "ARRx", "ARRy", "ARRz")
#: ``(range, kp, damping)`` of the base servos: slides (m, N/m, N s/m) and hinges (rad, N m/rad, N m s/rad).
BASE_RANGES = {"slide": (0.1, 4000.0, 400.0), "hinge": (0.5, 1000.0, 100.0)}
BALL_RADIUS = 0.035
BALL_MASS = 0.05


def hand_assets_dir() -> str:
    """The gymnasium-robotics assets folder (``.../envs/assets``); a clear error if it is missing.

    The package is located, not imported: importing it registers all of its environments and prints
    a notice about its Adroit tasks, neither of which the Shadow-Hand tasks need.
    """
    spec = importlib.util.find_spec("gymnasium_robotics")
    if spec is None or not spec.submodule_search_locations:
        raise ImportError(
            "the Shadow-Hand tasks (sg_torchrl.envs.hands) load the Shadow Hand model of gymnasium-robotics; "
            "install it with `pip install gymnasium-robotics==1.4.2` (a dependency of sg_torchrl)"
        )
    root = os.path.join(next(iter(spec.submodule_search_locations)), "envs", "assets")
    if not os.path.isfile(os.path.join(root, "hand", "robot.xml")):
        raise FileNotFoundError(f"gymnasium-robotics is installed but its Shadow Hand model is missing under {root}/hand")
    return root


@dataclass(frozen=True)
class SceneConfig:
    """Where the two hands stand and whether their bases move.

    ``mounts``: per hand ``(x, y, z, yaw)`` of its wrist mount (yaw about the vertical, radians; at
    yaw 0 the palm faces up and the fingers point along -y). ``actuated_base``: add :data:`BASE_JOINTS`.
    """

    mounts: tuple[tuple[float, float, float, float], tuple[float, float, float, float]]
    actuated_base: bool = False


#: ShadowHandOver: fixed hands, fingers towards each other, wrists :data:`MOUNT_GAP` apart.
HAND_OVER_SCENE = SceneConfig(mounts=((0.0, 0.0, MOUNT_HEIGHT, 0.0), (0.0, -MOUNT_GAP, MOUNT_HEIGHT, np.pi)))


def _add_base_joints(spec: mujoco.MjSpec) -> None:
    """Make the mount of ``spec``'s hand movable: :data:`BASE_JOINTS`, each with a position servo."""
    mount = spec.body(_HAND_MOUNT)
    axes = np.eye(3)
    for index, name in enumerate(BASE_JOINTS):
        kind = "slide" if index < 3 else "hinge"
        limit, kp, damping = BASE_RANGES[kind]
        joint_type = mujoco.mjtJoint.mjJNT_SLIDE if kind == "slide" else mujoco.mjtJoint.mjJNT_HINGE
        mount.add_joint(name=f"robot0:{name}", type=joint_type, axis=axes[index % 3], range=[-limit, limit],
                        damping=damping, armature=0.01)
        actuator = spec.add_actuator(name=f"robot0:A_{name}", target=f"robot0:{name}",
                                     trntype=mujoco.mjtTrn.mjTRN_JOINT, ctrlrange=[-limit, limit])
        actuator.set_to_position(kp=kp)


def _hand_spec(actuated_base: bool) -> mujoco.MjSpec:
    """One gymnasium-robotics Shadow Hand (right), its mount at the origin, as an ``MjSpec``."""
    root = hand_assets_dir()
    hand = os.path.join(root, "hand")
    xml = (
        f'<mujoco><compiler angle="radian" meshdir="{root}/stls/hand" texturedir="{root}/textures"/>'
        f'<include file="{hand}/shared.xml"/><asset><include file="{hand}/shared_asset.xml"/></asset>'
        f'<worldbody><include file="{hand}/robot.xml"/></worldbody></mujoco>'
    )
    spec = mujoco.MjSpec.from_string(xml)
    mount = spec.body(_HAND_MOUNT)
    mount.pos = [0.0, 0.0, 0.0]  # the frame it is attached to places it
    for tip in FINGERTIPS:
        site = f"robot0:S_{tip}tip"
        for kind, suffix in ((mujoco.mjtSensor.mjSENS_FRAMEPOS, "pos"), (mujoco.mjtSensor.mjSENS_FRAMEQUAT, "quat"),
                             (mujoco.mjtSensor.mjSENS_FRAMELINVEL, "linvel"), (mujoco.mjtSensor.mjSENS_FRAMEANGVEL, "angvel"),
                             (mujoco.mjtSensor.mjSENS_FORCE, "force"), (mujoco.mjtSensor.mjSENS_TORQUE, "torque")):
            spec.add_sensor(name=f"{tip}tip_{suffix}", type=kind, objtype=mujoco.mjtObj.mjOBJ_SITE, objname=site)
    if actuated_base:
        _add_base_joints(spec)
    return spec


@dataclass(frozen=True)
class HandLayout:
    """Where one hand's quantities live in the compiled model.

    ``qpos``/``qvel``: addresses of its 24 joints (model order); ``joint_names``: their unprefixed
    names (``"FFJ3"``, ...); ``joint_low``/``joint_high``: their ranges; ``actuators``: its 20
    actuator ids; ``sensors``: ``{name: slice of sensordata}`` for the fingertip sensors.
    """

    prefix: str
    joint_names: tuple[str, ...]
    qpos: np.ndarray
    qvel: np.ndarray
    joint_low: np.ndarray
    joint_high: np.ndarray
    base_qpos: np.ndarray
    actuators: np.ndarray
    actuator_names: tuple[str, ...]
    ctrl_low: np.ndarray
    ctrl_high: np.ndarray
    sensors: dict[str, slice]

    def qpos_index(self, joint: str) -> int:
        """The ``qpos`` address of the unprefixed joint name ``joint`` (e.g. ``"FFJ3"``)."""
        if joint not in self.joint_names:
            raise KeyError(f"{self.prefix!r} hand has no joint {joint!r}; it has {list(self.joint_names)}")
        return int(self.qpos[self.joint_names.index(joint)])

    def actuator_index(self, joint: str) -> int:
        """Position in this hand's action block of the actuator driving ``joint`` (``"A_" + joint``)."""
        name = f"A_{joint}"
        if name not in self.actuator_names:
            raise KeyError(f"no actuator drives joint {joint!r}; actuated joints: {[a[2:] for a in self.actuator_names]}")
        return self.actuator_names.index(name)


@dataclass(frozen=True)
class SceneLayout:
    """The compiled two-hand model's addresses: the hands, the ball's free joint, the goal mocap body."""

    hands: tuple[HandLayout, HandLayout]
    ball_qpos: int
    ball_qvel: int
    ball_sensors: dict[str, slice]
    goal_mocap: int


def _hand_layout(model: mujoco.MjModel, prefix: str) -> HandLayout:
    full = f"{prefix}robot0:"
    names = {j: model.joint(j).name for j in range(model.njnt)}
    base = {f"{full}{name}" for name in BASE_JOINTS}
    joints = [j for j, name in names.items() if name.startswith(full) and name not in base]
    base_joints = [model.joint(name).id for name in (f"{full}{b}" for b in BASE_JOINTS) if name in names.values()]
    actuators = [a for a in range(model.nu) if model.actuator(a).name.startswith(full)]
    sensors = {}
    for s in range(model.nsensor):
        name = model.sensor(s).name
        if name.startswith(prefix):
            start = int(model.sensor_adr[s])
            sensors[name[len(prefix):]] = slice(start, start + int(model.sensor_dim[s]))
    return HandLayout(
        prefix=prefix,
        joint_names=tuple(model.joint(j).name[len(full):] for j in joints),
        qpos=model.jnt_qposadr[joints].copy(),
        qvel=model.jnt_dofadr[joints].copy(),
        joint_low=model.jnt_range[joints, 0].copy(),
        joint_high=model.jnt_range[joints, 1].copy(),
        base_qpos=model.jnt_qposadr[base_joints].astype(np.int64),
        actuators=np.asarray(actuators),
        actuator_names=tuple(model.actuator(a).name[len(full):] for a in actuators),
        ctrl_low=model.actuator_ctrlrange[actuators, 0].copy(),
        ctrl_high=model.actuator_ctrlrange[actuators, 1].copy(),
        sensors=sensors,
    )


def build_scene(config: SceneConfig = HAND_OVER_SCENE) -> tuple[mujoco.MjModel, SceneLayout]:
    """Compile the two-hand scene of ``config`` (once per process) and return it with its :class:`SceneLayout`.

    The returned model is shared: callers must not modify it.
    """
    return _compile(config)  # one cache key per config, however the argument was passed


@lru_cache(maxsize=None)
def _compile(config: SceneConfig) -> tuple[mujoco.MjModel, SceneLayout]:
    world = mujoco.MjSpec()
    world.option.timestep = 0.002  # the hand model's own timestep
    world.option.iterations = 20
    world.compiler.degree = False
    for prefix, (x, y, z, yaw) in zip(HAND_PREFIXES, config.mounts):
        hand = _hand_spec(config.actuated_base)
        for attr in ("nuser_jnt", "nuser_site", "nuser_tendon", "nuser_actuator", "nuser_sensor"):
            setattr(world, attr, getattr(hand, attr))  # keep the hand's user data without attach warnings
        hand.njmax = hand.nconmax = -1
        frame = world.worldbody.add_frame(pos=[x, y, z], quat=[np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
        world.attach(hand, frame=frame, prefix=prefix)
    world.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[2.0, 2.0, 0.1], pos=[0, -MOUNT_GAP / 2, 0])
    world.worldbody.add_light(pos=[0, -MOUNT_GAP / 2, 3.0], dir=[0, 0, -1], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
    ball = world.worldbody.add_body(name="ball", pos=[0.0, -0.3, MOUNT_HEIGHT + 0.1])
    ball.add_freejoint(name="ball")
    ball.add_geom(name="ball", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[BALL_RADIUS, 0, 0], mass=BALL_MASS,
                  condim=4, rgba=[0.9, 0.4, 0.1, 1.0])
    ball.add_site(name="ball")
    goal = world.worldbody.add_body(name="goal", mocap=True, pos=[0.0, -0.7, MOUNT_HEIGHT + 0.1])
    goal.add_geom(name="goal", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[BALL_RADIUS, 0, 0], contype=0,
                  conaffinity=0, group=2, rgba=[0.1, 0.9, 0.2, 0.4])
    for kind, suffix in ((mujoco.mjtSensor.mjSENS_FRAMELINVEL, "linvel"), (mujoco.mjtSensor.mjSENS_FRAMEANGVEL, "angvel")):
        world.add_sensor(name=f"ball_{suffix}", type=kind, objtype=mujoco.mjtObj.mjOBJ_SITE, objname="ball")
    model = world.compile()
    ball_joint = model.joint("ball").id
    ball_sensors = {}
    for suffix in ("linvel", "angvel"):
        sensor = model.sensor(f"ball_{suffix}")
        ball_sensors[suffix] = slice(int(sensor.adr[0]), int(sensor.adr[0]) + 3)
    layout = SceneLayout(
        hands=tuple(_hand_layout(model, prefix) for prefix in HAND_PREFIXES),  # type: ignore[arg-type]
        ball_qpos=int(model.jnt_qposadr[ball_joint]),
        ball_qvel=int(model.jnt_dofadr[ball_joint]),
        ball_sensors=ball_sensors,
        goal_mocap=int(model.body_mocapid[model.body("goal").id]),
    )
    return model, layout
