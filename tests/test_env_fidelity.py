"""Fidelity to Safety-Gymnasium 1.0.0 where a first comparison found us apart (issue 19).

* Button tasks: the original's reset draws the goal button, which starts the 10-step resampling
  timer, and then zeroes the timer (``ButtonLevel0.specific_reset``), so the buttons are observed in
  the first observation and a wrong press costs from the first step. Checked for every robot and
  level.
* Velocity (``test_velocity_*`` below): unit torso quaternions after the reset noise, and
  gymnasium's per-robot ``info`` terms.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDict

import sg_torchrl

torch.set_num_threads(1)

NAV_ROBOTS = ("Point", "Car", "Racecar", "Doggo", "Ant")


def zero_step(env) -> TensorDict:
    """One step of every simulator with a zero action; returns ``td["next"]``."""
    action = torch.zeros((*env.batch_size, *env.action_spec.shape[len(env.batch_size):]))
    return env.step(TensorDict({"action": action}, batch_size=env.batch_size))["next"]


# ---------------------------------------------------------------------------- Button timer at reset
@pytest.mark.parametrize("robot", NAV_ROBOTS)
@pytest.mark.parametrize("level", (0, 1, 2))
def test_button_first_observation_sees_the_buttons(robot, level):
    env = sg_torchrl.make(f"Safety{robot}Button{level}-v0", num_envs=4, seed=level)
    try:
        part = env.observation_slices["buttons_lidar"]
        for _ in range(3):
            obs = env.reset()["observation"].numpy()
            assert (env.task.buttons.timer == 0).all()
            distance = env.scene.planar_distance(env.task.buttons.positions(env.scene))  # (N, 4)
            in_range = (distance < env.task.lidar_max_dist - 0.05).any(axis=1)
            assert in_range.any()
            assert (obs[in_range, part] > 0).any(axis=1).all()
    finally:
        env.close()


def arrange_wrong_press(env) -> None:
    """Lay out simulator 0 with the robot at the origin sitting on button 0 (the others parked 3 m away),
    redrawn until button 0 is not the goal: every robot then rests on a wrong button within a few steps."""
    sampler, buttons = env.layout_sampler, env.task.buttons
    xy, yaw = np.zeros((sampler.size, 2)), np.zeros(sampler.size)
    xy[1:, 0] = np.linspace(-3.2, 3.2, sampler.size - 1)
    xy[1:, 1] = 3.2
    xy[sampler.slice_of(buttons).start] = 0.0
    for _ in range(50):  # each set_layout draws the goal button again
        env.set_layout([0], xy[None], yaw[None])
        if buttons.goal_button[0] != 0:
            return
    raise AssertionError("button 0 was always the goal")


@pytest.mark.parametrize("robot", NAV_ROBOTS)
@pytest.mark.parametrize("level", (1, 2))
def test_button_wrong_press_costs_from_the_first_steps(robot, level):
    # Before the fix the timer started at 10, so no wrong press cost anything in the first 10 steps.
    env = sg_torchrl.make(f"Safety{robot}Button{level}-v0", num_envs=1, seed=7, cost_mode="raw")
    try:
        env.reset()
        arrange_wrong_press(env)
        assert env.task.buttons.timer[0] == 0
        costs, touches = [], []
        for _ in range(5):
            nxt = zero_step(env)
            touches.append(env.task.buttons.touches(env.scene)[0, 0])
            costs.append(nxt["cost_info", "buttons"].item())
            assert nxt["cost"].item() == costs[-1]  # buttons are the only cost touched here
        assert max(touches) >= 1
        np.testing.assert_array_equal(costs, touches)
    finally:
        env.close()


def test_button_timer_still_restarts_after_a_goal():
    env = sg_torchrl.make("SafetyPointButton1-v0", num_envs=1, seed=3)
    try:
        env.reset()
        task = env.task
        task.next_goal(env, 0)  # what reaching the goal does
        assert task.buttons.timer[0] == task.buttons.resampling_delay == 10
        obs = env._observe()
        assert (obs[0, env.observation_slices["buttons_lidar"]] == 0).all()
    finally:
        env.close()


# ---------------------------------------------------------------------------- velocity: unit quaternion after reset
# Safety-Gymnasium 1.0.0 ran on MuJoCo 2.3.3, whose mj_forward normalised qpos quaternions in place: the reset
# noise lands on the torso quaternion, and the first observation holds it scaled to unit length.
QUATERNION_IDS = ("SafetyAntVelocity-v0", "SafetyAntVelocity-v1", "SafetyHumanoidVelocity-v0",
                  "SafetyHumanoidVelocity-v1", "Safety2x4AntVelocity-v0", "Safety4x2AntVelocity-v0",
                  "Safety9|8HumanoidVelocity-v0")


@pytest.mark.parametrize("env_id", QUATERNION_IDS)
def test_velocity_first_quaternion_is_unit(env_id):
    env = sg_torchrl.make(env_id, num_envs=16, seed=11)
    try:
        key = "state" if "state" in env.reset().keys() else "observation"
        for _ in range(8):  # 128 draws of the reset noise
            td = env.reset()
            quat = td[key][:, 1:5].double()  # after the torso height: qpos[3:7]
            np.testing.assert_allclose(quat.norm(dim=1).numpy(), 1.0, atol=1e-6)  # float32 observation
            qpos = env.physics.qpos()[:, 3:7]
            np.testing.assert_allclose(np.linalg.norm(qpos, axis=1), 1.0, atol=1e-12)
            np.testing.assert_allclose(quat.numpy(), qpos, atol=1e-6)
            assert (np.abs(qpos - (1.0, 0.0, 0.0, 0.0)) > 1e-4).any(axis=1).all()  # the noise is still there
    finally:
        env.close()


def test_velocity_quaternion_is_the_normalised_noisy_one():
    # Same generator draws as the env, by hand: gymnasium v4's qpos noise, then q / |q| (only the quaternion moves).
    from sg_torchrl.envs.velocity.env import normalize_quaternions, quaternion_addresses

    env = sg_torchrl.make("SafetyAntVelocity-v1", num_envs=1, seed=5)
    try:
        env.reset()
        scale = env.robot.reset_noise_scale
        rng = np.random.default_rng()
        rng.bit_generator.state = env._rngs[0].bit_generator.state
        noisy = env.physics.model.qpos0 + rng.uniform(-scale, scale, size=env.physics.model.nq)
        env.reset()
        expected = noisy.copy()[None]
        normalize_quaternions(expected, quaternion_addresses(env.physics.model))
        assert quaternion_addresses(env.physics.model).tolist() == [3]
        np.testing.assert_allclose(env.physics.qpos()[0], expected[0], rtol=0, atol=1e-15)
        np.testing.assert_allclose(expected[0, 3:7], noisy[3:7] / np.linalg.norm(noisy[3:7]), atol=1e-15)
        np.testing.assert_array_equal(np.delete(expected[0], range(3, 7)), np.delete(noisy, range(3, 7)))
    finally:
        env.close()


def test_normalize_quaternions_degenerate_is_identity():
    from sg_torchrl.envs.velocity.env import normalize_quaternions

    qpos = np.array([[9.0, 0.0, 0.0, 0.0, 0.0, 7.0], [9.0, 0.0, 3.0, 0.0, 4.0, 7.0]])
    normalize_quaternions(qpos, np.array([1]))
    np.testing.assert_allclose(qpos, [[9.0, 1.0, 0.0, 0.0, 0.0, 7.0], [9.0, 0.0, 0.6, 0.0, 0.8, 7.0]])
