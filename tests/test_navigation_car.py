"""The Car robot: sizes and observation layout, driving and turning, contacts, stability, seeding.

Expected sizes come from reference/safety_gymnasium_semantics.md section 2: the Car's robot part is
the 12 fixed sensor values, then the rear ball joint's angular velocity (3) and its quaternion as a
3x3 rotation matrix (9) = 24 (its wheel hinges have no sensors), so CarGoal0 = 24 + 16 = 40,
CarGoal1/2 = 24 + 3 x 16 = 72, CarCircle0-2 = 24 + 16 (circle_lidar) = 40 and CarRun0 = 24.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_navigation import action_td, arrange, idle, make_env

import sg_torchrl
from sg_torchrl.envs import registry_entry
from sg_torchrl.envs.navigation import Car, Vases

torch.set_num_threads(1)

CAR_SIZES = {
    "SafetyCarGoal0-v0": 40,
    "SafetyCarGoal1-v0": 72,
    "SafetyCarGoal2-v0": 72,
    "SafetyCarCircle0-v0": 40,
    "SafetyCarCircle1-v0": 40,
    "SafetyCarCircle2-v0": 40,
    "SafetyCarRun0-v0": 24,
}


def drive(env, action, steps: int) -> None:
    for _ in range(steps):
        env.step(action_td(env, [action]))


def heading(env) -> float:
    mat = env.scene.agent_mat()[0]
    return float(np.arctan2(mat[1, 0], mat[0, 0]))


# ---------------------------------------------------------------------------- registry and sizes
class TestCarSpecs:
    def test_registered_for_every_task(self):
        car_ids = sg_torchrl.list_envs(family="navigation", robot="Car")
        point_ids = sg_torchrl.list_envs(family="navigation", robot="Point")
        assert car_ids == [i.replace("Point", "Car") for i in point_ids]  # one Car id per Point id
        assert set(CAR_SIZES) <= set(car_ids)
        entry = registry_entry("SafetyCarGoal1-v0")
        assert (entry.robot, entry.task, entry.level, entry.max_episode_steps) == ("Car", "Goal", 1, 1000)

    @pytest.mark.parametrize("env_id", sorted(CAR_SIZES))
    def test_sizes_and_physics_options(self, env_id):
        env = make_env(env_id)
        assert env.observation_dim == CAR_SIZES[env_id]
        assert env.action_spec.shape == (1, 2)
        assert env.action_spec.space.low.tolist() == [[-1.0, -1.0]]
        assert env.action_spec.space.high.tolist() == [[1.0, 1.0]]
        assert env.physics.timestep == 0.004 and env.frame_skip == 10

    def test_observation_layout(self):
        env = make_env("SafetyCarGoal1-v0")
        starts = {name: (part.start, part.stop) for name, part in env.observation_slices.items()}
        assert starts == {
            "accelerometer": (0, 3), "velocimeter": (3, 6), "gyro": (6, 9), "magnetometer": (9, 12),
            "ballangvel_rear": (12, 15), "ballquat_rear": (15, 24),
            "goal_lidar": (24, 40), "hazards_lidar": (40, 56), "vases_lidar": (56, 72),
        }

    def test_model(self):
        env = make_env("SafetyCarGoal0-v0")
        model = env.physics.model
        # Free chassis (7) + two wheel hinges (2) + the caster's ball joint (4).
        assert model.nq == 7 + 2 + 4 and model.nu == 2
        assert [model.actuator(i).name for i in range(2)] == ["right", "left"]
        assert model.actuator_forcerange.tolist() == [[-0.02, 0.02], [-0.02, 0.02]]
        # The robot's geoms are its whole tree: chassis box, 4 bumper parts, 2 wheels, the caster.
        assert env.scene.robot_geoms.sum() == 8
        assert model.body_subtreemass[env.scene.agent_body] == pytest.approx(0.0304, abs=1e-3)

    def test_sensors_at_rest(self):
        # After settling at rest facing +y: no motion, the caster upright (identity rotation matrix),
        # gravity's reaction on the accelerometer, the field (0, -0.5, 0) along body +x.
        env = make_env("SafetyCarGoal0-v0")
        arrange(env, agent_yaw=np.pi / 2)
        for _ in range(10):  # soft contacts: the car settles within 0.4 s
            obs = idle(env)["observation"][0].numpy()
        np.testing.assert_allclose(obs[0:3], [0.0, 0.0, 9.81], atol=0.05)
        np.testing.assert_allclose(obs[3:9], 0.0, atol=1e-3)
        np.testing.assert_allclose(obs[9:12], [-0.5, 0.0, 0.0], atol=1e-3)
        np.testing.assert_allclose(obs[12:15], 0.0, atol=1e-3)
        np.testing.assert_allclose(obs[15:24], np.eye(3).ravel(), atol=1e-3)


# ---------------------------------------------------------------------------- driving
class TestCarDrives:
    @pytest.mark.parametrize("yaw", [0.0, 2.0])
    def test_forward_and_backward(self, yaw):
        # (1, 1) for 1 s drives about 0.75 m along the heading; (-1, -1) comes back.
        env = make_env("SafetyCarGoal0-v0")
        arrange(env, agent_yaw=yaw)
        ahead = np.array([np.cos(yaw), np.sin(yaw)])
        drive(env, [1.0, 1.0], 25)
        moved = env.scene.agent_xy()[0].copy()
        assert moved @ ahead > 0.5
        assert abs(np.cross(ahead, moved)) < 0.1 * (moved @ ahead)  # nearly straight
        assert abs(np.angle(np.exp(1j * (heading(env) - yaw)))) < 0.2
        velocimeter = env._observe()[0, 3:6]
        assert velocimeter[0] > 0.5 and abs(velocimeter[1]) < 0.1  # body +x is forward
        drive(env, [-1.0, -1.0], 50)
        assert env.scene.agent_xy()[0] @ ahead < moved @ ahead - 0.5

    @pytest.mark.parametrize("action, sign", [([1.0, -1.0], 1.0), ([-1.0, 1.0], -1.0)])
    def test_turns_on_the_spot(self, action, sign):
        # Opposite wheels turn the car about its axle: (1, -1) counter-clockwise, (-1, 1) clockwise.
        env = make_env("SafetyCarGoal0-v0")
        arrange(env)
        drive(env, action, 10)
        assert sign * env._observe()[0, 8] > 1.0  # gyro z
        drive(env, action, 15)
        assert sign * heading(env) > np.pi / 3  # about 75 degrees in 1 s
        assert np.linalg.norm(env.scene.agent_xy()[0]) < 0.2

    def test_vase_contact_counts_the_wheels(self):
        # A vase (half-size 0.1) touching the left wheel's outer face (y = 0.155, axle at x = -0.1).
        env = make_env("SafetyCarGoal2-v0", cost_mode="raw")
        arrange(env, vases=[(-0.1, 0.254)])
        nxt = idle(env)
        assert nxt["cost_info", "vases_contact"].item() >= 1
        assert env.task.find(Vases).speeds(env.scene)[0, 0] > 1e-4


# ---------------------------------------------------------------------------- robustness and seeding
@pytest.mark.timeout(60)
def test_random_actions_stay_stable():
    # 4 simulators x 2,500 uniform random steps (10,000 env steps, resets every 500): every value
    # finite, no simulator diverged, and the car stays upright on its wheels throughout.
    env = make_env("SafetyCarGoal1-v0", num_envs=4, seed=11, max_episode_steps=500, cost_mode="raw")
    td = env.reset()
    actions = 2 * torch.rand((2500, 4, 2), generator=torch.Generator().manual_seed(3)) - 1
    lowest_up, heights = 1.0, []
    for action in actions:
        stepped, td = env.step_and_maybe_reset(td.set("action", action))
        nxt = stepped["next"]
        assert torch.isfinite(nxt["observation"]).all() and torch.isfinite(nxt["reward"]).all()
        lowest_up = min(lowest_up, float(env.scene.agent_mat()[:, 2, 2].min()))
        heights.append(env.scene.agent_pos()[:, 2].copy())
    heights = np.concatenate(heights)
    assert env.physics_errors == 0
    assert lowest_up > 0.9  # never tilted by more than ~25 degrees
    assert heights.min() > 0.09 and heights.max() < 0.13


def assert_sim0_same_for_n1_and_n16(env_id: str, steps: int = 25, **options) -> None:
    """Simulator 0 replays bit for bit with 1 or 16 simulators (same seed and actions, auto-resets every 10 steps)."""
    outs = []
    for num_envs in (1, 16):
        env = make_env(env_id, num_envs=num_envs, seed=7, max_episode_steps=10, **options)
        # The same actions both times (one seed), as many columns as the robot has actuators.
        actions = 2 * torch.rand((steps, 16, env.action_dim), generator=torch.Generator().manual_seed(0)) - 1
        td, trace = env.reset(), []
        for t in range(steps):
            stepped, td = env.step_and_maybe_reset(td.set("action", actions[t, :num_envs]))
            trace.append(stepped[0].clone())
        outs.append(trace)
    for t, (a, b) in enumerate(zip(*outs)):
        for key in ("observation", ("next", "observation"), ("next", "reward"), ("next", "cost"), ("next", "done")):
            torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=f"{key} at step {t}")
    assert outs[0][9]["next", "truncated"].item()


def test_seeding_n1_equals_n16():
    assert_sim0_same_for_n1_and_n16("SafetyCarGoal1-v0")


def test_car_class_is_exported():
    assert sg_torchrl.envs.navigation.ROBOTS["Car"] is Car
