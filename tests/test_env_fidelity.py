"""Fidelity to Safety-Gymnasium 1.0.0 where a first comparison found us apart.

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


# ---------------------------------------------------------------------------- velocity: gymnasium's info terms
# Keys and order probed from safety-gymnasium 1.0.0 (its velocity envs' step builds gymnasium v4's info).
_PLANAR = ["x_position", "y_position", "distance_from_origin", "x_velocity", "y_velocity", "forward_reward"]
INFO_KEYS = {
    "HalfCheetah": ["x_position", "x_velocity", "reward_run", "reward_ctrl"],
    "Hopper": ["x_position", "x_velocity"],
    "Walker2d": ["x_position", "x_velocity"],
    "Swimmer": ["reward_fwd", "reward_ctrl", *_PLANAR],
    "Ant": ["reward_forward", "reward_ctrl", "reward_survive", *_PLANAR],
    "Humanoid": ["reward_linvel", "reward_quadctrl", "reward_alive", *_PLANAR],
}
FORWARD = {"HalfCheetah": "reward_run", "Swimmer": "reward_fwd", "Ant": "reward_forward", "Humanoid": "reward_linvel"}
CTRL = {"HalfCheetah": "reward_ctrl", "Swimmer": "reward_ctrl", "Ant": "reward_ctrl", "Humanoid": "reward_quadctrl"}
HEALTHY = {"Ant": "reward_survive", "Humanoid": "reward_alive"}


@pytest.mark.parametrize("robot", sorted(INFO_KEYS))
def test_velocity_info_terms_match_gymnasium_v4(robot):
    import gymnasium

    reference = gymnasium.make(f"{robot}-v4").unwrapped
    reference.reset(seed=3)
    env = sg_torchrl.make(f"Safety{robot}Velocity-v1", num_envs=1, seed=0)
    try:
        assert list(env.info_keys) == INFO_KEYS[robot]
        env.reset()
        env.physics.reset([0], reference.data.qpos.copy()[None], reference.data.qvel.copy()[None])
        generator = torch.Generator().manual_seed(4)
        high = env.action_spec.space.high
        for t in range(15):
            action = (2 * torch.rand(high.shape, generator=generator) - 1) * high  # float32-representable
            _, ref_reward, ref_terminated, _, ref_info = reference.step(action[0].double().numpy())
            nxt = env.step(TensorDict({"action": action}, batch_size=env.batch_size))["next"]
            info = env.step_info(0)
            assert list(info) == INFO_KEYS[robot] and all(type(v) is float for v in info.values())
            for key in INFO_KEYS[robot]:
                np.testing.assert_allclose(info[key], ref_info[key], rtol=1e-5, atol=1e-7, err_msg=f"{key}, step {t}")
            # The terms are the reward's own: forward + healthy + ctrl (+ nothing else), and the cost's velocity.
            if robot in FORWARD:
                total = info[FORWARD[robot]] + info.get(HEALTHY.get(robot), 0.0) + info[CTRL[robot]]
                assert nxt["reward"].item() == pytest.approx(total, rel=1e-6, abs=1e-6)
            speed = np.hypot(info["x_velocity"], info["y_velocity"]) if "y_velocity" in info else info["x_velocity"]
            if robot == "Swimmer":  # v1 prices the x velocity
                speed = info["x_velocity"]
            assert speed == pytest.approx(env.last_velocity[0], rel=1e-12)
            if ref_terminated:
                break
        assert t >= 5
    finally:
        reference.close()
        env.close()


def test_velocity_step_info_batched_and_untouched_by_reset():
    env = sg_torchrl.make("SafetyAntVelocity-v0", num_envs=3, seed=1)
    try:
        env.reset()
        assert all((value == 0).all() for key, value in env.step_info().items() if key != "reward_survive")
        env.rollout(4)
        batched = env.step_info()
        assert list(batched) == INFO_KEYS["Ant"] and all(v.shape == (3,) and v.dtype == np.float64 for v in batched.values())
        for i in range(3):
            assert env.step_info(i) == {key: float(value[i]) for key, value in batched.items()}
        np.testing.assert_array_equal(batched["reward_survive"], 1.0)
        np.testing.assert_allclose(batched["distance_from_origin"], np.hypot(batched["x_position"], batched["y_position"]))
        np.testing.assert_array_equal(batched["forward_reward"], batched["reward_forward"])
        batched["x_velocity"][:] = 99.0  # fresh arrays: the env's buffers are untouched
        assert env.step_info(0)["x_velocity"] != 99.0
        env.reset()
        assert env.step_info(1) == {key: float(value[1]) for key, value in env.step_info().items()}
    finally:
        env.close()


@pytest.mark.parametrize("env_id", ["Safety2x4AntVelocity-v0", "Safety2x3HalfCheetahVelocity-v0"])
def test_multi_agent_velocity_step_info(env_id):
    env = sg_torchrl.make(env_id, num_envs=2, seed=0)
    try:
        env.rollout(3)
        info = env.step_info(0)
        robot = env.robot.name
        assert list(info) == INFO_KEYS[robot]
        assert info["x_velocity"] == env._velocity[0, 0]
    finally:
        env.close()
