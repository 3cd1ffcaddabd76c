"""``ShadowHand{Over,CatchOver2Underarm}{SafeJoint,SafeFinger}-v0``: pass a ball between two Shadow Hands, safely.

Safety-Gymnasium paper, section 4.4 ("Safe Isaac Gym"): the Isaac Gym tasks ShadowHandOver and
ShadowHandCatchOver2Underarm (:mod:`sg_torchrl.envs.hands.tasks`), with a constraint on the
forefinger (:mod:`sg_torchrl.envs.hands.constraints`), rebuilt on MuJoCo with ``N`` simulators
sharing one compiled two-hand model per task (:mod:`sg_torchrl.envs.hands.scene`). Model
derived from gymnasium-robotics' Shadow Hand assets (Apache-2.0, (C) Vikash Kumar, CSE, UW; see
``NOTICE`` in this package).

The task. The ball starts resting on the ``right/`` hand's palm; the goal, a pose above the
``left/`` hand's palm, has a random orientation drawn at every reset. Reward, as the paper's:

    r = exp(-0.2 (alpha d_t + d_r)),  d_t = |p_ball - p_goal|,  d_r = 2 asin(min(|vec(q_ball conj(q_goal))|, 1))

with ``alpha = distance_scale`` (Isaac Gym's ``distRewardScale``, 20). An episode terminates when
the ball falls below the task's ``fall_height`` (0.2 m, 0.3 m under the palms as in Isaac Gym) and
is truncated after 75 steps (Isaac Gym's ``episodeLength``); one step is 8 physics steps of 2 ms
(62.5 Hz, Isaac Gym's is 60 Hz).

Action (40 for HandOver, 52 for CatchOver2Underarm): each hand's (``right/`` first) 20 finger and
wrist position actuators, then, with an actuated base, its 6 base servos; in [-1, 1], mapped
linearly onto each actuator's control range (for the fingers, its joint's range).

Observation (HandOver: 398, the paper's size and order; per hand 187. CatchOver2Underarm: 422, the
paper's size; per hand 199, the 6 base joint positions (translation m, rotation rad, relative to the
mount's rest pose) between the fingertip forces and the last action, which then has 26 entries):

====================================== ==== ==================================================
entry                                  size notes
====================================== ==== ==================================================
joint positions                        24   scaled to [-1, 1] over each joint's range
joint velocities                       24   x 0.2 (Isaac Gym's ``vel_obs_scale``)
joint forces                           24   actuator force on each joint (``qfrc_actuator``) x 10;
                                            the tendon-coupled distal joints read 0
fingertip pose and velocities          65   5 tips x (position 3, quaternion 4, linear 3, angular 3)
fingertip force and torque             30   5 tips x (force 3, torque 3) x 10, tip sensors
(base pose, CatchOver2Underarm only)   6
last action                            20 (26)
(the same for the ``left/`` hand)      187 (199)
ball pose                              7    position, quaternion (w, x, y, z)
ball linear velocity                   3
ball angular velocity                  3    x 0.2
goal pose                              7
rotation difference                    4    q_ball * conj(q_goal)
====================================== ==== ==================================================

Both hands are gymnasium-robotics' right hand (the model has no left hand), so the catching hand
is a mirror-less copy turned by pi; Isaac Gym's has a true left hand. Force observations are
MuJoCo's (soft contacts), not PhysX's, so their scale differs from the paper's.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from sg_torchrl.envs.hands.constraints import SAFETY_VARIANTS, CostSource, JointRangeConstraint
from sg_torchrl.envs.hands.rotations import quat_conjugate, quat_multiply, random_quaternion, rotation_distance
from sg_torchrl.envs.hands.scene import FINGERTIPS, HandLayout, build_scene
from sg_torchrl.envs.hands.tasks import TASKS
from sg_torchrl.envs.backends import Backend, SimulatorOptions, make_physics
from sg_torchrl.envs.base import CostMode, check_num_envs
from sg_torchrl.envs.mujoco_env import MujocoSafeEnv
from sg_torchrl.envs.rendering import FollowCamera, RenderMixin

__all__ = ["ShadowHandEnv"]

VELOCITY_SCALE = 0.2  # Isaac Gym's vel_obs_scale
FORCE_SCALE = 10.0  # Isaac Gym's force_torque_obs_scale
JOINT_NOISE = 0.2  # Isaac Gym's resetDofPosRandomInterval: fraction of the way to a random point of the range
BALL_POSITION_NOISE = 0.01  # Isaac Gym's resetPositionNoise (m)
FRAME_SKIP = 8
#: The observation's tail after the hands' blocks: ball pose 7, velocities 3 + 3, goal pose 7, rotation difference 4.
OBJECT_OBSERVATION_DIM = 24


class ShadowHandEnv(RenderMixin, MujocoSafeEnv):
    """Two Shadow Hands pass a ball from one to the other under a forefinger constraint.

    Args:
        task: a key of :data:`~sg_torchrl.envs.hands.tasks.TASKS` (``"HandOver"``, ``"CatchOver2Underarm"``).
        safety: ``"SafeJoint"`` or ``"SafeFinger"`` (:data:`~sg_torchrl.envs.hands.constraints.SAFETY_VARIANTS`).
        cost_source: ``"joints"`` (default: measured joint angles) or ``"actions"`` (the original
            code's normalised actions); see :mod:`sg_torchrl.envs.hands.constraints`.
        distance_scale: ``alpha`` of the reward.
        fall_height: the episode terminates when the ball's centre is below this height (m);
            default: the task's.
        physics_threads, backend, warp_device, warp_options: how the simulators run, the fields of
            :class:`~sg_torchrl.envs.options.SimulatorOptions` (:attr:`simulator_options`). The two-hand
            scene is heavy enough for 2 threads to pay on 2 cores (``benchmarks/threaded_stepping.py``);
            ``backend="warp"`` steps thousands of envs on a GPU (``benchmarks/warp_throughput.py``).
        num_envs, device, seed, cost_mode, max_episode_steps: see :class:`SafeEnv`.

    ``cost_info`` entries: ``forefinger_abduction`` (both variants) and ``forefinger_flexion``
    (SafeFinger); each counts the joints of both hands outside their safe ranges.

    ``render(index)`` (:class:`~sg_torchrl.envs.rendering.RenderMixin`) looks at both hands from the
    side, slightly above, centred between the two mounts; ``record_video`` works as for every env.
    """

    def __init__(
        self,
        task: str = "HandOver",
        safety: str = "SafeJoint",
        *,
        num_envs: int = 1,
        device: torch.device | str = "cpu",
        seed: int | list[int] | None = None,
        cost_mode: CostMode = "indicator",
        cost_source: CostSource = "joints",
        max_episode_steps: int = 75,
        distance_scale: float = 20.0,
        fall_height: float | None = None,
        physics_threads: int = 1,
        backend: Backend = "cpu",
        warp_device: str | None = None,
        warp_options: dict[str, Any] | None = None,
    ) -> None:
        check_num_envs(num_envs)  # before MujocoBatch, for this message
        #: how the simulators run (built from the four simulator keywords)
        self.simulator_options = SimulatorOptions(physics_threads, backend, warp_device, warp_options)
        if safety not in SAFETY_VARIANTS:
            raise ValueError(f"unknown safety variant {safety!r}; choose from {sorted(SAFETY_VARIANTS)}")
        if task not in TASKS:
            raise ValueError(f"unknown two-hand task {task!r}; choose from {sorted(TASKS)}")
        self.task = TASKS[task]
        model, layout = build_scene(self.task.scene)
        self.safety = safety
        self.layout = layout
        self.distance_scale = float(distance_scale)
        self.fall_height = float(self.task.fall_height if fall_height is None else fall_height)
        self.physics = make_physics(model, num_envs, self.simulator_options, fields=("sensordata", "qfrc_actuator"),
                                    forward_after_step=True)
        hands = layout.hands
        self.constraints = [JointRangeConstraint(name, ranges, hands, cost_source)
                            for name, ranges in SAFETY_VARIANTS[safety].items()]
        self.cost_source = cost_source
        self._actuators = np.concatenate([hand.actuators for hand in hands])
        ctrl_low = np.concatenate([hand.ctrl_low for hand in hands])
        ctrl_high = np.concatenate([hand.ctrl_high for hand in hands])
        self._ctrl_center, self._ctrl_half = (ctrl_high + ctrl_low) / 2, (ctrl_high - ctrl_low) / 2
        self._tip_state = [self._tip_columns(hand, ("pos", "quat", "linvel", "angvel")) for hand in hands]
        self._tip_force = [self._tip_columns(hand, ("force", "torque")) for hand in hands]
        num_actions = len(self._actuators)
        self._last_action = np.zeros((num_envs, num_actions))
        self._goal_pos = np.tile(self.task.goal_position, (num_envs, 1))
        self._goal_quat = np.tile([1.0, 0.0, 0.0, 0.0], (num_envs, 1))
        self._ctrl = np.zeros((num_envs, model.nu))
        per_hand = (3 * len(hands[0].qpos) + sum(len(c) for c in (self._tip_state[0], self._tip_force[0]))
                    + len(hands[0].base_qpos) + num_actions // 2)
        self.hand_observation_dim = per_hand
        # render(): a fixed side view of both hands, centred between the mounts (world body, offset)
        between = np.mean([mount[:3] for mount in self.task.scene.mounts], axis=0)
        self.default_camera = FollowCamera(distance=1.1, elevation=-40.0, azimuth=0.0,
                                           offset=(float(between[0]), float(between[1]), float(between[2]) + 0.1))
        self._observation = np.zeros((num_envs, len(hands) * per_hand + OBJECT_OBSERVATION_DIM))
        super().__init__(
            num_envs=num_envs,
            observation_dim=self._observation.shape[1],
            action_low=-np.ones(num_actions),
            action_high=np.ones(num_actions),
            constraint_names=tuple(c.name for c in self.constraints),
            max_episode_steps=max_episode_steps,
            frame_skip=FRAME_SKIP,
            cost_mode=cost_mode,
            device=device,
            seed=seed,
        )

    @staticmethod
    def _tip_columns(hand: HandLayout, kinds: tuple[str, ...]) -> np.ndarray:
        """``sensordata`` columns of ``hand``'s fingertip sensors of ``kinds``, tip by tip."""
        return np.concatenate([np.arange(hand.sensors[f"{tip}tip_{kind}"].start, hand.sensors[f"{tip}tip_{kind}"].stop)
                               for tip in FINGERTIPS for kind in kinds])

    def _render_body(self) -> int:
        return 0  # the world: the camera stays put between the hands

    # ------------------------------------------------------------------ state access
    def ball_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The ball's position ``(N, 3)`` and quaternion ``(N, 4)`` (views of the state cache)."""
        start = self.layout.ball_qpos
        qpos = self.physics.qpos()
        return qpos[:, start:start + 3], qpos[:, start + 3:start + 7]

    def goal_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The goal's position ``(N, 3)`` and quaternion ``(N, 4)`` (the env's arrays; do not write)."""
        return self._goal_pos, self._goal_quat

    # ------------------------------------------------------------------ hooks
    def _reset_sims(self, indices: np.ndarray) -> None:
        model = self.physics.model
        qpos = np.tile(model.qpos0, (len(indices), 1))
        qvel = np.zeros((len(indices), model.nv))
        mocap_pos = np.empty((len(indices), model.nmocap, 3))
        mocap_quat = np.empty((len(indices), model.nmocap, 4))
        start = self.layout.ball_qpos
        for row, index in enumerate(indices):
            rng = self._rngs[index]
            for hand in self.layout.hands:
                default = np.clip(model.qpos0[hand.qpos], hand.joint_low, hand.joint_high)
                target = rng.uniform(hand.joint_low, hand.joint_high)
                qpos[row, hand.qpos] = default + JOINT_NOISE * (target - default)
            qpos[row, start:start + 3] = self.task.ball_start + rng.uniform(-BALL_POSITION_NOISE, BALL_POSITION_NOISE, 3)
            qpos[row, start + 3:start + 7] = (1.0, 0.0, 0.0, 0.0)
            self._goal_quat[index] = random_quaternion(rng)
            self._goal_pos[index] = self.task.goal_position
            mocap_pos[row, self.layout.goal_mocap] = self.task.goal_position
            mocap_quat[row, self.layout.goal_mocap] = self._goal_quat[index]
        self._last_action[indices] = 0.0
        self.physics.reset(indices, qpos, qvel, mocap_pos, mocap_quat)

    def _advance(self, action: np.ndarray) -> None:
        self._last_action[:] = action
        self._ctrl[:, self._actuators] = self._ctrl_center + self._ctrl_half * action
        self.physics.step(self._ctrl, self.frame_skip)

    def _observe(self) -> np.ndarray:
        obs, qpos, qvel = self._observation, self.physics.qpos(), self.physics.qvel()
        sensors, forces = self.physics.field("sensordata"), self.physics.field("qfrc_actuator")
        end, actions_per_hand = 0, self._last_action.shape[1] // len(self.layout.hands)

        def put(values: np.ndarray) -> None:
            nonlocal end
            obs[:, end:end + values.shape[1]] = values
            end += values.shape[1]

        for h, hand in enumerate(self.layout.hands):
            put(2.0 * (qpos[:, hand.qpos] - hand.joint_low) / (hand.joint_high - hand.joint_low) - 1.0)
            put(VELOCITY_SCALE * qvel[:, hand.qvel])
            put(FORCE_SCALE * forces[:, hand.qvel])
            put(sensors[:, self._tip_state[h]])
            put(FORCE_SCALE * sensors[:, self._tip_force[h]])
            put(qpos[:, hand.base_qpos])
            put(self._last_action[:, h * actions_per_hand:(h + 1) * actions_per_hand])
        ball_pos, ball_quat = self.ball_pose()
        put(ball_pos)
        put(ball_quat)
        put(sensors[:, self.layout.ball_sensors["linvel"]])
        put(VELOCITY_SCALE * sensors[:, self.layout.ball_sensors["angvel"]])
        put(self._goal_pos)
        put(self._goal_quat)
        put(quat_multiply(ball_quat, quat_conjugate(self._goal_quat)))
        assert end == obs.shape[1], (end, obs.shape)
        return obs

    def reward_at(self, ball_pos: np.ndarray, ball_quat: np.ndarray, goal_pos: np.ndarray, goal_quat: np.ndarray) -> np.ndarray:
        """The paper's reward ``exp(-0.2 (alpha d_t + d_r))`` for given ball and goal poses, ``(...)``."""
        distance = np.linalg.norm(ball_pos - goal_pos, axis=-1)
        return np.exp(-0.2 * (self.distance_scale * distance + rotation_distance(ball_quat, goal_quat)))

    def _compute_reward(self, action: np.ndarray) -> np.ndarray:
        return self.reward_at(*self.ball_pose(), self._goal_pos, self._goal_quat)

    def _compute_cost(self) -> dict[str, np.ndarray]:
        qpos = self.physics.qpos()
        return {c.name: c(qpos, self._last_action) for c in self.constraints}

    def _compute_terminated(self) -> np.ndarray:
        return self.ball_pose()[0][:, 2] < self.fall_height

    # ------------------------------------------------------------------ snapshots
    def _physics_state(self) -> dict:
        return {"physics": self.physics.get_state(), "goal_pos": self._goal_pos.copy(),
                "goal_quat": self._goal_quat.copy(), "last_action": self._last_action.copy()}

    def _load_physics_state(self, state: dict) -> None:
        self._goal_pos[:] = state["goal_pos"]
        self._goal_quat[:] = state["goal_quat"]
        self._last_action[:] = state["last_action"]
        self.physics.set_state(state["physics"])  # the goal's mocap pose is part of the physics state
