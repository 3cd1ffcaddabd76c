"""The six locomotion robots of the velocity-constrained tasks, as data.

Safety-Gymnasium's velocity tasks (paper section 4.2) subclass gymnasium's **v4** MuJoCo envs:
reward, observation and reset are gymnasium's, and a cost of 1 is paid whenever the robot moves
faster than a threshold. Each robot here is one :class:`LocomotionRobot` record holding exactly
those facts (the numbers are gymnasium v4's defaults and Safety-Gymnasium's thresholds, see
``reference/safety_gymnasium_semantics.md`` sections 8 and 10); :class:`~.env.VelocityEnv`
interprets the record. Adding a robot is adding a record, not a class.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Literal

import gymnasium.envs.mujoco
import mujoco
import numpy as np

__all__ = ["HealthCheck", "LocomotionRobot", "ROBOTS", "load_model", "normalize_quaternions", "quaternion_addresses"]

ASSETS = Path(gymnasium.envs.mujoco.__file__).parent / "assets"


@dataclass(frozen=True)
class HealthCheck:
    """Gymnasium's ``is_healthy`` rule: the episode terminates when it fails.

    Args:
        z_index: qpos index of the torso height.
        z_range: allowed torso height.
        angle_index / angle_range: optional torso pitch bound (Hopper, Walker2d).
        state_range: optional bound on ``concat(qpos, qvel)[2:]`` (Hopper).
        inclusive: bounds are ``<=`` (Ant) rather than strict ``<`` (the others).
    """

    z_index: int
    z_range: tuple[float, float]
    angle_index: int | None = None
    angle_range: tuple[float, float] | None = None
    state_range: tuple[float, float] | None = None
    inclusive: bool = False

    def __call__(self, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        """Healthy flags, ``(N,)``; non-finite states are never healthy."""
        within = _within_inclusive if self.inclusive else _within_strict
        healthy = np.isfinite(qpos).all(axis=1) & np.isfinite(qvel).all(axis=1)
        healthy &= within(qpos[:, self.z_index], self.z_range)
        if self.angle_index is not None:
            healthy &= within(qpos[:, self.angle_index], self.angle_range)
        if self.state_range is not None:
            state = np.concatenate([qpos, qvel], axis=1)[:, 2:]
            healthy &= within(state, self.state_range).all(axis=1)
        return healthy

    def healthy_one(self, qpos: np.ndarray, qvel: np.ndarray) -> bool:
        """:meth:`__call__` of one simulator, ``qpos`` ``(nq,)`` and ``qvel`` ``(nv,)``: the same comparisons
        on Python floats (float64 both ways; NaN and inf are ruled out first, as there).

        Why: on one simulator the five ``(1,)``-array operations of the batched rule cost several
        microseconds, a sizeable share of a small robot's step."""
        q, v = qpos.tolist(), qvel.tolist()
        isfinite = math.isfinite
        if not (all(map(isfinite, q)) and all(map(isfinite, v))):
            return False
        low, high = self.z_range
        z = q[self.z_index]
        if not (low <= z <= high if self.inclusive else low < z < high):
            return False
        if self.angle_index is not None:
            low, high = self.angle_range
            angle = q[self.angle_index]
            if not (low <= angle <= high if self.inclusive else low < angle < high):
                return False
        if self.state_range is not None:
            state = (q + v)[2:]  # every entry finite here: within the range iff its extremes are
            low, high = self.state_range
            if state and not (low <= min(state) and max(state) <= high if self.inclusive
                              else low < min(state) and max(state) < high):
                return False
        return True


def _within_strict(x: np.ndarray, bounds: tuple[float, float]) -> np.ndarray:
    return (bounds[0] < x) & (x < bounds[1])


def _within_inclusive(x: np.ndarray, bounds: tuple[float, float]) -> np.ndarray:
    return (bounds[0] <= x) & (x <= bounds[1])


@dataclass(frozen=True)
class LocomotionRobot:
    """Everything that distinguishes one velocity-task robot from another.

    Args:
        name: robot name as it appears in the env id (``HalfCheetah``).
        xml_file: gymnasium asset file.
        frame_skip: physics steps per env step.
        qpos_skip: leading qpos entries excluded from the observation (world x, and y for
            robots that move in the plane).
        qvel_clip: observations clip qvel to ``[-clip, clip]`` (Hopper, Walker2d).
        forward_reward_weight / ctrl_cost_weight / healthy_reward: gymnasium v4 reward terms.
        reset_noise_scale: half-width of the uniform qpos reset noise.
        qvel_noise: ``"uniform"`` (same half-width) or ``"normal"`` (scale times N(0, 1)).
        position_source: what the forward velocity differentiates: joint ``"qpos"`` (x, y), the
            ``"torso"`` body position, or the ``"mass_center"`` (gymnasium v4 per robot).
        planar: the position is 2-D (x, y) rather than x only.
        health: termination rule, or ``None`` for robots that never terminate.
        extra_observations: ``MjData`` arrays appended to the observation (Humanoid v4).
        thresholds: Safety-Gymnasium's cost threshold per env version.
        planar_cost_versions: versions whose cost uses the planar speed instead of the signed
            x velocity (Ant, Humanoid; Swimmer only in v0).
        info_keys: the ``info`` keys Safety-Gymnasium 1.0.0 returns after a step, in its order
            (gymnasium v4's, per robot; their meaning is :data:`~sg_torchrl.envs.velocity.env.INFO_TERMS`).
    """

    name: str
    xml_file: str
    frame_skip: int
    qpos_skip: int
    forward_reward_weight: float
    ctrl_cost_weight: float
    reset_noise_scale: float
    thresholds: dict[int, float]
    qvel_clip: float | None = None
    healthy_reward: float = 0.0
    qvel_noise: Literal["uniform", "normal"] = "uniform"
    position_source: Literal["qpos", "torso", "mass_center"] = "qpos"
    planar: bool = False
    health: HealthCheck | None = None
    extra_observations: tuple[str, ...] = ()
    planar_cost_versions: frozenset[int] = field(default_factory=frozenset)
    info_keys: tuple[str, ...] = ("x_position", "x_velocity")


# The position terms that Safety-Gymnasium's planar robots (Swimmer, Ant, Humanoid) add to ``info``.
_PLANAR_INFO = ("x_position", "y_position", "distance_from_origin", "x_velocity", "y_velocity", "forward_reward")

ROBOTS: dict[str, LocomotionRobot] = {
    robot.name: robot
    for robot in (
        LocomotionRobot(
            name="HalfCheetah", xml_file="half_cheetah.xml", frame_skip=5, qpos_skip=1,
            forward_reward_weight=1.0, ctrl_cost_weight=0.1, reset_noise_scale=0.1, qvel_noise="normal",
            thresholds={0: 2.8795, 1: 3.2096},
            info_keys=("x_position", "x_velocity", "reward_run", "reward_ctrl"),
        ),
        LocomotionRobot(
            name="Hopper", xml_file="hopper.xml", frame_skip=4, qpos_skip=1, qvel_clip=10.0,
            forward_reward_weight=1.0, ctrl_cost_weight=1e-3, healthy_reward=1.0, reset_noise_scale=5e-3,
            health=HealthCheck(z_index=1, z_range=(0.7, float("inf")), angle_index=2, angle_range=(-0.2, 0.2),
                               state_range=(-100.0, 100.0)),
            thresholds={0: 0.37315, 1: 0.7402},
        ),
        LocomotionRobot(
            name="Walker2d", xml_file="walker2d.xml", frame_skip=4, qpos_skip=1, qvel_clip=10.0,
            forward_reward_weight=1.0, ctrl_cost_weight=1e-3, healthy_reward=1.0, reset_noise_scale=5e-3,
            health=HealthCheck(z_index=1, z_range=(0.8, 2.0), angle_index=2, angle_range=(-1.0, 1.0)),
            thresholds={0: 1.7075, 1: 2.3415},
        ),
        LocomotionRobot(
            name="Swimmer", xml_file="swimmer.xml", frame_skip=4, qpos_skip=2, planar=True,
            forward_reward_weight=1.0, ctrl_cost_weight=1e-4, reset_noise_scale=0.1,
            thresholds={0: 0.04845, 1: 0.2282}, planar_cost_versions=frozenset({0}),
            info_keys=("reward_fwd", "reward_ctrl", *_PLANAR_INFO),
        ),
        LocomotionRobot(
            name="Ant", xml_file="ant.xml", frame_skip=5, qpos_skip=2, planar=True, position_source="torso",
            forward_reward_weight=1.0, ctrl_cost_weight=0.5, healthy_reward=1.0, reset_noise_scale=0.1,
            qvel_noise="normal", health=HealthCheck(z_index=2, z_range=(0.2, 1.0), inclusive=True),
            thresholds={0: 2.5745, 1: 2.6222}, planar_cost_versions=frozenset({0, 1}),
            info_keys=("reward_forward", "reward_ctrl", "reward_survive", *_PLANAR_INFO),
        ),
        LocomotionRobot(
            name="Humanoid", xml_file="humanoid.xml", frame_skip=5, qpos_skip=2, planar=True,
            position_source="mass_center", forward_reward_weight=1.25, ctrl_cost_weight=0.1, healthy_reward=5.0,
            reset_noise_scale=1e-2, health=HealthCheck(z_index=2, z_range=(1.0, 2.0)),
            extra_observations=("cinert", "cvel", "qfrc_actuator", "cfrc_ext"),
            thresholds={0: 2.3475, 1: 1.4149}, planar_cost_versions=frozenset({0, 1}),
            info_keys=("reward_linvel", "reward_quadctrl", "reward_alive", *_PLANAR_INFO),
        ),
    )
}

_TOTAL_MASS = re.compile(r'\s+settotalmass="([0-9.eE+-]+)"')


@lru_cache(maxsize=None)
def load_model(xml_file: str) -> mujoco.MjModel:
    """Compile a gymnasium asset once per process.

    ``settotalmass`` is deprecated in MuJoCo 4 and makes the compiler print a warning on every
    load, so the attribute is stripped and the same rescaling is applied with
    ``mj_setTotalmass`` + ``mj_setConst``: the compiled model is identical to what the attribute would give.
    The cached model is shared read-only by every env and simulator.
    """
    xml = (ASSETS / xml_file).read_text()
    total_mass = _TOTAL_MASS.search(xml)
    model = mujoco.MjModel.from_xml_string(_TOTAL_MASS.sub("", xml))
    if total_mass is not None:
        mujoco.mj_setTotalmass(model, float(total_mass.group(1)))
        mujoco.mj_setConst(model, mujoco.MjData(model))  # refresh constants derived from masses
    return model


def quaternion_addresses(model: mujoco.MjModel) -> np.ndarray:
    """Where each free or ball joint's quaternion starts in ``qpos``, ``(K,)`` (empty for planar robots)."""
    free, ball = int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL)
    kinds = model.jnt_type.astype(int)
    starts = [int(model.jnt_qposadr[j]) + (3 if kinds[j] == free else 0)
              for j in range(model.njnt) if kinds[j] in (free, ball)]
    return np.asarray(starts, dtype=np.int64)


def normalize_quaternions(qpos: np.ndarray, starts: np.ndarray) -> None:
    """Scale the quaternions of ``qpos`` (``(N, nq)``, in place) starting at ``starts`` to unit length.

    Why: gymnasium's v4 ``reset_model`` adds uniform noise to every ``qpos`` entry, the torso
    quaternion included, and MuJoCo 2.3.3 (what Safety-Gymnasium 1.0.0 runs on) normalised
    quaternions inside ``qpos`` during ``mj_forward``, so the original's first observation holds a
    unit quaternion ``q / |q|`` (checked against safety-gymnasium 1.0.0: norm 1 to 1e-16 over 200
    seeds, the other coordinates untouched). Current MuJoCo normalises only a copy, so we do it
    here. A quaternion of (near) zero length becomes the identity, as MuJoCo's ``mju_normalize4``.
    """
    for start in starts:
        quat = qpos[:, start : start + 4]
        norm = np.linalg.norm(quat, axis=1, keepdims=True)
        tiny = norm[:, 0] < 1e-15
        quat /= np.where(norm < 1e-15, 1.0, norm)
        quat[tiny] = (1.0, 0.0, 0.0, 0.0)
