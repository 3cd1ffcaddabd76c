"""Velocity-constrained locomotion: ``Safety{Robot}Velocity-v{0,1}``.

The robot is rewarded for running forward exactly as in gymnasium's v4 MuJoCo env and pays a
cost of 1 on every step whose measured velocity exceeds a threshold (Safety-Gymnasium paper,
section 4.2, "Safe Velocity"): the agent must learn to run fast, but not too fast. ``N``
simulators share one compiled model; observation, reward, termination and reset noise match
gymnasium's v4 env for the same state (checked against gymnasium in the tests), so results
compare with the paper's.
"""

from __future__ import annotations

import math

from typing import Any

import mujoco
import numpy as np
import torch

from sg_torchrl.envs.backends import Backend, SimulatorOptions, make_physics
from sg_torchrl.envs.base import FLOAT32_MAX, CostMode, check_num_envs
from sg_torchrl.envs.mujoco_env import MujocoSafeEnv
from sg_torchrl.envs.rendering import LOCOMOTION_CAMERA, RenderMixin
from sg_torchrl.envs.step_hooks import step_hook
from sg_torchrl.envs.velocity.robots import (ROBOTS, LocomotionRobot, load_model, normalize_quaternions,
                                             quaternion_addresses)

__all__ = ["INFO_TERMS", "VelocityEnv", "normalize_quaternions", "quaternion_addresses"]

#: What each ``info`` key of the velocity tasks holds (one name per quantity, several keys per
#: quantity because gymnasium's v4 robots name their reward terms differently).
INFO_TERMS: dict[str, str] = {
    "x_position": "position x after the step (what the velocity differentiates)",
    "y_position": "position y after the step",
    "distance_from_origin": "planar norm of the position after the step",
    "x_velocity": "x velocity over the step",
    "y_velocity": "y velocity over the step",
    "forward_reward": "forward reward term (weight times x velocity)",
    "reward_run": "forward reward term (HalfCheetah)",
    "reward_fwd": "forward reward term (Swimmer)",
    "reward_forward": "forward reward term (Ant)",
    "reward_linvel": "forward reward term (Humanoid)",
    "reward_ctrl": "minus the control penalty",
    "reward_quadctrl": "minus the control penalty (Humanoid)",
    "reward_survive": "healthy reward (Ant)",
    "reward_alive": "healthy reward (Humanoid)",
}
_FORWARD = ("forward_reward", "reward_run", "reward_fwd", "reward_forward", "reward_linvel")


class VelocityEnv(RenderMixin, MujocoSafeEnv):
    """A gymnasium-v4 locomotion robot with Safety-Gymnasium's velocity cost, batched.

    Args:
        robot: a key of :data:`~sg_torchrl.envs.velocity.robots.ROBOTS` (``"HalfCheetah"``, ...).
        version: env version; selects the cost threshold (and, for the Swimmer, whether the
            cost uses planar speed (v0) or x velocity (v1)).
        velocity_threshold: override the version's threshold.
        planar_cost: override the version's velocity measure: ``True`` prices the planar speed
            ``hypot(vx, vy)`` (``|vx|`` for robots that move along x only), ``False`` the signed x
            velocity. The multi-agent velocity tasks use it (:mod:`sg_torchrl.envs.multi_agent`).
        physics_threads, backend, warp_device, warp_options: how the simulators run, the fields of
            :class:`~sg_torchrl.envs.options.SimulatorOptions` (:attr:`simulator_options`).
        num_envs, device, seed, cost_mode, max_episode_steps: see :class:`SafeEnv`.

    The single constraint is ``("cost_info", "velocity")``. Diagnostics of the last step:
    :attr:`last_velocity` (the measured speed, ``(N,)``; overwritten in place by every step, copy it
    to keep it), and :meth:`step_info`, the terms Safety-Gymnasium's ``info`` holds for this robot
    (:attr:`info_keys`; ``x_velocity``, ``reward_ctrl``, ...), from the very numbers the reward and
    cost were computed from.
    """

    def __init__(
        self,
        robot: str,
        version: int = 1,
        *,
        num_envs: int = 1,
        device: torch.device | str = "cpu",
        seed: int | list[int] | None = None,
        cost_mode: CostMode = "indicator",
        max_episode_steps: int = 1000,
        velocity_threshold: float | None = None,
        planar_cost: bool | None = None,
        physics_threads: int = 1,
        backend: Backend = "cpu",
        warp_device: str | None = None,
        warp_options: dict[str, Any] | None = None,
    ) -> None:
        check_num_envs(num_envs)  # before MujocoBatch, for this message
        #: how the simulators run (built from the four simulator keywords)
        self.simulator_options = SimulatorOptions(physics_threads, backend, warp_device, warp_options)
        if robot not in ROBOTS:
            raise ValueError(f"unknown velocity robot {robot!r}; choose from {sorted(ROBOTS)}")
        spec: LocomotionRobot = ROBOTS[robot]
        if version not in spec.thresholds:
            raise ValueError(f"{robot} velocity task has versions {sorted(spec.thresholds)}, got {version}")
        self.robot = spec
        self.version = version
        self.velocity_threshold = float(spec.thresholds[version] if velocity_threshold is None else velocity_threshold)
        if not np.isfinite(self.velocity_threshold):  # NaN compares false with every speed: the cost never fires
            raise ValueError(f"velocity_threshold must be a finite number, got {velocity_threshold!r}")
        position_field = {"qpos": (), "torso": ("xpos",), "mass_center": ("xipos",)}[spec.position_source]
        self.physics = make_physics(load_model(spec.xml_file), num_envs, self.simulator_options,
                                    post_constraint="cfrc_ext" in spec.extra_observations,
                                    fields=position_field + spec.extra_observations)
        model = self.physics.model
        self._init_qpos = model.qpos0.copy()
        self._quaternions = quaternion_addresses(model)
        self._init_qvel = np.zeros(model.nv)
        self._dt = model.opt.timestep * spec.frame_skip
        # Constants of the hot path as one-element arrays: a ufunc with a Python-scalar operand costs more.
        self._dt_array = np.array([self._dt])
        self._ctrl_cost_weight = np.array([spec.ctrl_cost_weight])
        self._planar_cost = version in spec.planar_cost_versions if planar_cost is None else bool(planar_cost)
        self._torso_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "torso")
        self._body_mass = model.body_mass[:, None] / model.body_mass.sum()
        self._position_before = np.zeros((num_envs, 2 if spec.planar else 1))
        self._position_after = np.zeros_like(self._position_before)
        self._penalty_ctrl = np.zeros(num_envs)  # the last step's control penalty (step_info)
        self.last_velocity = np.zeros(num_envs)
        self._velocity = np.zeros((num_envs, 2))
        self._velocity_measured = self._velocity[:, : self._position_before.shape[1]]  # views of the buffers
        self._velocity_x = self._velocity[:, 0]
        self._action_squared = np.zeros((num_envs, model.nu))
        self._never_terminated = np.zeros(num_envs, dtype=bool)  # robots without a health check
        self._never_terminated.flags.writeable = False
        # Hot-path buffers are filled in place: assigning an attribute of an EnvBase (an nn.Module)
        # costs microseconds, and SafeEnv copies what it emits.
        self._observation = np.zeros((num_envs, self._observation_size(model)))
        self._parts = self._observation_parts()  # views of it
        low, high = self.physics.ctrl_range
        super().__init__(
            num_envs=num_envs,
            observation_dim=self._observation.shape[1],
            action_low=low,
            action_high=high,
            constraint_names=("velocity",),
            max_episode_steps=max_episode_steps,
            frame_skip=spec.frame_skip,
            cost_mode=cost_mode,
            device=device,
            seed=seed,
        )
        self._single = self._single_plan()

    default_camera = LOCOMOTION_CAMERA  # render(): follows the torso (sg_torchrl.envs.rendering)

    def _render_body(self) -> int:
        return self._torso_id

    # ------------------------------------------------------------------ layout
    def _observation_size(self, model: mujoco.MjModel) -> int:
        extra = sum(self.physics.field(name)[0].size for name in self.robot.extra_observations)
        return model.nq - self.robot.qpos_skip + model.nv + extra

    # ------------------------------------------------------------------ hooks
    def _reset_sims(self, indices: np.ndarray) -> None:
        restored = self.__dict__.get("_restored_position")
        if restored is not None:  # a reset simulator starts from its new state's position
            restored[0][indices] = False
        spec, scale = self.robot, self.robot.reset_noise_scale
        qpos = np.empty((len(indices), self.physics.model.nq))
        qvel = np.empty((len(indices), self.physics.model.nv))
        for row, index in enumerate(indices):
            rng = self._rngs[index]
            # Same draw order and distributions as gymnasium's v4 ``reset_model``.
            qpos[row] = self._init_qpos + rng.uniform(-scale, scale, size=qpos.shape[1])
            if spec.qvel_noise == "normal":
                qvel[row] = self._init_qvel + scale * rng.standard_normal(qvel.shape[1])
            else:
                qvel[row] = self._init_qvel + rng.uniform(-scale, scale, size=qvel.shape[1])
        normalize_quaternions(qpos, self._quaternions)
        self.physics.reset(indices, qpos, qvel)

    @step_hook
    def _position(self) -> np.ndarray:
        """The position whose finite difference is the robot's velocity, ``(N, 1 or 2)``."""
        width = 2 if self.robot.planar else 1
        source = self.robot.position_source
        if source == "qpos":
            return self.physics.qpos()[:, :width]
        if source == "torso":
            return self.physics.field("xpos")[:, self._torso_id, :width]
        return (self.physics.field("xipos") * self._body_mass).sum(axis=1)[:, :width]

    def _before_step(self) -> None:
        self._position_before[:] = self._position()
        restored = self.__dict__.get("_restored_position")
        if restored is not None:  # the first step after load_sim_state (see there)
            rows, position = restored
            self._position_before[rows] = position[rows]
            self.__dict__["_restored_position"] = None

    # ------------------------------------------------------------------ snapshots
    def sim_state(self) -> dict:
        """:meth:`SafeEnv.sim_state` and the position the next step's velocity starts from.

        For the Ant (torso ``xpos``) and the Humanoid (``xipos``) that position is a quantity MuJoCo
        derives from ``qpos`` at the start of its last substep, one substep behind the state; loading
        the state recomputes it from the current ``qpos``, so without it a copy's first reward
        (``x_velocity``, ``y_velocity``) would differ from the original's.
        """
        return {**super().sim_state(), "position": self._position().copy()}

    def load_sim_state(self, state: dict) -> None:
        """Restore :meth:`sim_state` output (the next step starts from the saved position)."""
        super().load_sim_state(state)
        # Joint qpos positions are state, restored exactly (and step_one's own path reads them
        # directly); snapshots taken before the position was saved lack it.
        if "position" in state and self.robot.position_source != "qpos":
            # Set in __dict__: an EnvBase (nn.Module) attribute assignment costs microseconds.
            self.__dict__["_restored_position"] = (np.ones(self.num_envs, dtype=bool), np.array(state["position"]))

    def _advance(self, action: np.ndarray) -> None:
        self.physics.step(action, self.frame_skip)
        self._position_after[:] = self._position()
        velocity = np.subtract(self._position_after, self._position_before, out=self._velocity_measured)
        np.divide(velocity, self._dt_array, out=velocity)

    def _observation_parts(self) -> tuple[np.ndarray, np.ndarray, list[tuple[str, np.ndarray]]]:
        """Views of the observation buffer, taken once: where qpos, qvel and each extra field go."""
        model, robot, obs = self.physics.model, self.robot, self._observation
        width = model.nq - robot.qpos_skip
        end = width + model.nv
        extras = []
        for name in robot.extra_observations:
            size = self.physics.field(name)[0].size
            extras.append((name, obs[:, end : end + size]))
            end += size
        return obs[:, :width], obs[:, width : width + model.nv], extras

    def _observe(self) -> np.ndarray:
        # One reused buffer, filled from the physics state cache; SafeEnv copies it when emitting.
        physics, robot = self.physics, self.robot
        qpos_part, qvel_part, extras = self._parts
        np.copyto(qpos_part, physics.qpos()[:, robot.qpos_skip:])
        if robot.qvel_clip is None:
            np.copyto(qvel_part, physics.qvel())
        else:
            np.clip(physics.qvel(), -robot.qvel_clip, robot.qvel_clip, out=qvel_part)
        for name, part in extras:
            np.copyto(part, physics.field(name).reshape(self.num_envs, -1))
        return self._observation


    def _compute_reward(self, action: np.ndarray) -> np.ndarray:
        # gymnasium v4 penalises the action as given (MuJoCo clamps it only inside the physics).
        # Buffers filled in place, the same operations as w * square(action).sum(axis=1).
        spec, penalty = self.robot, self._penalty_ctrl
        np.add.reduce(np.square(action, out=self._action_squared), axis=1, out=penalty)
        np.multiply(self._ctrl_cost_weight, penalty, out=penalty)
        if self.num_envs == 1:  # the same float64 operations on Python floats: cheaper than three on arrays
            reward = spec.forward_reward_weight * self._velocity_x.item() + spec.healthy_reward - penalty.item()
            return np.array((reward,))
        return spec.forward_reward_weight * self._velocity_x + spec.healthy_reward - penalty

    def _compute_cost(self) -> dict[str, np.ndarray]:
        if self._planar_cost:
            np.hypot(self._velocity[:, 0], self._velocity[:, 1], out=self.last_velocity)
        else:
            self.last_velocity[:] = self._velocity_x
        if self.num_envs == 1:  # one comparison of Python floats
            return {"velocity": np.array((1.0 if self.last_velocity.item() > self.velocity_threshold else 0.0,))}
        return {"velocity": (self.last_velocity > self.velocity_threshold).astype(np.float64)}

    def _compute_terminated(self) -> np.ndarray:
        health = self.robot.health
        if health is None:
            return self._never_terminated  # read-only: emitted flags are copies
        return ~health(self.physics.qpos(), self.physics.qvel())

    # ------------------------------------------------------------------ one simulator (gymnasium façade)

    def _single_plan(self) -> tuple | None:
        """What :meth:`step_one`'s own path reads, taken once (views of the buffers and of the one
        ``MjData``), or ``None`` where it does not apply: more than one simulator, a backend without the
        aliased single step, a position other than joint ``qpos`` (Ant, Humanoid) or extra observation
        fields, or step hooks that a subclass redefines (:mod:`sg_torchrl.envs.step_hooks`)."""
        physics, robot = self.physics, self.robot
        if (self.num_envs != 1 or not physics.supports_aliased_single_step
                or robot.position_source != "qpos" or robot.extra_observations
                or type(self).hooks_overridden_since(VelocityEnv)):
            return None
        qpos_part, qvel_part, _ = self._parts
        qvel_clip = None
        if robot.qvel_clip is not None:
            qvel_clip = (np.full_like(qvel_part, -robot.qvel_clip), np.full_like(qvel_part, robot.qvel_clip))
        ctrl = physics.datas[0].ctrl
        return (
            physics, physics.qpos()[0], physics.qvel()[0], ctrl[None], np.zeros((1, ctrl.size)),
            qpos_part, physics.qpos()[:, robot.qpos_skip:], qvel_part, physics.qvel(), qvel_clip,
        )

    def step_one(self, action: np.ndarray) -> tuple[np.ndarray, float, float, bool, bool, dict[str, float]]:
        """:meth:`SafeEnv.step_one <sg_torchrl.envs.base.SafeEnv.step_one>` with the velocity task's
        arithmetic on Python floats where it is elementwise.

        Why: a gymnasium step of a small robot (HalfCheetah, Hopper, Swimmer, Walker2d) spent as long
        in a dozen operations on one-element arrays as in the physics. This path does the
        same float64 operations in the same order as :meth:`_transition_arrays` and the hooks it
        calls (the positions' finite difference, the reward terms, the threshold comparison, the
        health rule: :meth:`HealthCheck.healthy_one`), keeps numpy for the control penalty's sum (its
        summation order is numpy's), fills the same buffers (:attr:`last_velocity`, :meth:`step_info`'s
        terms, the observation, the step counter) and sends a faulty step (an unstable simulator, a
        non-finite observation or outcome) through the same screen and isolation. Only robots whose
        position is joint ``qpos`` take this path; the outputs, :meth:`step_info` and the buffers
        equal :meth:`SafeEnv.step_one <sg_torchrl.envs.base.SafeEnv.step_one>`'s bit for bit.
        """
        plan = self._single
        if plan is None:
            return super().step_one(action)
        physics, qpos, qvel, ctrl, clipped, qpos_part, qpos_source, qvel_part, qvel_source, qvel_clip = plan
        if physics.drives_mocap:
            return super().step_one(action)
        if not (type(action) is np.ndarray and action.dtype == np.float32 and action.shape == clipped.shape):
            action = np.asarray(action, dtype=np.float64).reshape(1, -1)
        # else the façade's float32 action, read through float64 loops below (widening is exact)
        robot = self.robot
        planar = robot.planar
        x_before = qpos.item(0)
        y_before = qpos.item(1) if planar else 0.0
        position_before = self._position_before
        position_before[0, 0] = x_before
        if planar:
            position_before[0, 1] = y_before
        np.maximum(action, self._clip_low, out=clipped)  # np.clip's value, written into MjData's ctrl
        np.minimum(clipped, self._clip_high, out=ctrl)
        unstable = physics.advance_one(self.frame_skip)
        dt = self._dt
        x_after = qpos.item(0)
        x_velocity = (x_after - x_before) / dt
        velocity = self._velocity
        position_after = self._position_after
        position_after[0, 0] = x_after
        velocity[0, 0] = x_velocity
        if planar:
            y_after = qpos.item(1)
            position_after[0, 1] = y_after
            velocity[0, 1] = (y_after - y_before) / dt
        # _observe
        np.copyto(qpos_part, qpos_source)
        if qvel_clip is None:
            np.copyto(qvel_part, qvel_source)
        else:
            np.maximum(qvel_source, qvel_clip[0], out=qvel_part)  # np.clip's value
            np.minimum(qvel_part, qvel_clip[1], out=qvel_part)
        observation = self._observation
        # _compute_reward
        penalty = self._penalty_ctrl
        np.add.reduce(np.square(action, out=self._action_squared, dtype=np.float64), axis=1, out=penalty)
        penalty[0] = control = robot.ctrl_cost_weight * penalty.item()  # the float64 product np.multiply takes
        reward = robot.forward_reward_weight * x_velocity + robot.healthy_reward - control
        # _compute_cost
        if self._planar_cost:
            np.hypot(self._velocity[:, 0], self._velocity[:, 1], out=self.last_velocity)
            speed = self.last_velocity.item()
        else:
            self.last_velocity[0] = speed = x_velocity
        cost = 1.0 if speed > self.velocity_threshold else 0.0
        # _compute_terminated
        health = robot.health
        terminated = False if health is None else not health.healthy_one(qpos, qvel)
        elapsed = self._elapsed
        steps = elapsed.item() + 1
        elapsed[0] = steps
        truncated = steps >= self.max_episode_steps
        # _fault_free's screen: a finite sum proves every entry finite (an overflow only takes the exact path)
        if not unstable and math.isfinite(sum(observation[0].tolist())) and abs(reward) + abs(cost) <= FLOAT32_MAX:
            return (
                observation[0].astype(np.float32).astype(np.float64),
                float(np.float32(reward)),
                cost,  # 0.0 or 1.0: its float32 value, its own indicator and the total of one constraint
                terminated,
                truncated,
                {"velocity": cost},
            )
        # A faulty step: SafeEnv's own screen and isolation, on the arrays its hooks would have returned.
        rewards, costs = np.array((reward,)), {"velocity": np.array((cost,))}
        terminated_flags, truncated_flags = np.array((terminated,)), np.array((truncated,))
        diverged = self._diverged(observation) | self._nonfinite_outcome(rewards, costs)
        if diverged.any():
            return self._single_outputs(
                *self._isolate(diverged, observation, rewards, costs, terminated_flags, truncated_flags))
        return self._single_outputs(observation, rewards, costs, terminated_flags, truncated_flags)

    # ------------------------------------------------------------------ info
    @property
    def info_keys(self) -> tuple[str, ...]:
        """The keys of :meth:`step_info`: Safety-Gymnasium 1.0.0's ``info`` keys for this robot, in its order."""
        return self.robot.info_keys

    def step_info(self, index: int | None = None) -> dict[str, np.ndarray] | dict[str, float]:
        """Gymnasium's ``info`` terms of the last step (:attr:`info_keys`; meanings in :data:`INFO_TERMS`).

        Why: training scripts written for Safety-Gymnasium log them (``x_velocity``, ``reward_ctrl``,
        ...); the gymnasium façade adds them to its ``info``. They are derived from the buffers the
        last step's reward and cost were computed from, so ``reward`` equals the sum of the reward
        terms (forward + healthy + ctrl) and the cost is ``speed > threshold`` of these velocities.

        Args:
            index: one simulator: a dict of Python floats, as one gymnasium env's ``info``.
                ``None``: every simulator, a dict of fresh ``(N,)`` float64 arrays.

        Before the first step the measured terms are zeros; a reset does not change them (gymnasium's
        ``reset`` returns an empty ``info``).
        """
        if index is not None:
            return self._step_info_of(index)
        spec, rows = self.robot, slice(None)
        position, velocity = self._position_after[rows], self._velocity[rows]
        values: dict[str, Any] = {}
        for key in spec.info_keys:
            if key in _FORWARD:
                value = spec.forward_reward_weight * velocity[..., 0]
            elif key in ("reward_ctrl", "reward_quadctrl"):
                value = -self._penalty_ctrl[rows]
            elif key in ("reward_survive", "reward_alive"):
                value = np.full_like(self._penalty_ctrl[rows], spec.healthy_reward)
            elif key == "distance_from_origin":
                value = np.linalg.norm(position, axis=-1)
            else:  # x_position, y_position, x_velocity, y_velocity
                source = position if key.endswith("position") else velocity
                value = source[..., 0 if key.startswith("x") else 1]
            values[key] = float(value) if index is not None else np.array(value, dtype=np.float64)
        return values

    def _step_info_of(self, index: int) -> dict[str, float]:
        """:meth:`step_info` of one simulator: the same values as a row of the batched terms, read as Python
        floats (each term is one float64 product, copy or negation, so the arithmetic is the same; the
        distance is ``np.linalg.norm``'s own ``sqrt(x * x + y * y)`` for a row of two). The gymnasium
        façade calls it every step, so the keys come from a plan made once (:meth:`_info_plan`)."""
        plan = self.__dict__.get("_info_plan_cache")
        if plan is None:
            plan = self._info_plan()
        position = self._position_after[index]
        if len(position) == 2:
            x_position, y_position = position.tolist()
        else:
            x_position, y_position = position.item(0), 0.0
        x_velocity, y_velocity = self._velocity[index].tolist()
        distance = 0.0  # computed only where a key asks for it
        if plan[1]:
            distance = (math.sqrt(x_position * x_position + y_position * y_position) if len(position) == 2
                        else float(np.linalg.norm(position, axis=-1)))
        values = (
            self.robot.forward_reward_weight * x_velocity,  # 0: the forward reward
            -self._penalty_ctrl.item(index),  # 1: the control penalty
            float(self.robot.healthy_reward),  # 2
            distance,  # 3
            x_position, y_position, x_velocity, y_velocity,  # 4-7
        )
        return {key: values[code] for key, code in plan[0]}

    def _info_plan(self) -> tuple[tuple[tuple[str, int], ...], bool]:
        """``((key, term), ...)`` in :attr:`info_keys`' order (``term`` indexes :meth:`_step_info_of`'s
        values) and whether a key asks for the distance from the origin."""
        codes = []
        for key in self.robot.info_keys:
            if key in _FORWARD:
                code = 0
            elif key in ("reward_ctrl", "reward_quadctrl"):
                code = 1
            elif key in ("reward_survive", "reward_alive"):
                code = 2
            elif key == "distance_from_origin":
                code = 3
            else:
                code = {"x_position": 4, "y_position": 5, "x_velocity": 6, "y_velocity": 7}[key]
            codes.append((key, code))
        plan = (tuple(codes), any(code == 3 for _, code in codes))
        self.__dict__["_info_plan_cache"] = plan  # not through nn.Module.__setattr__
        return plan
