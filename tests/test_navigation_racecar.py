"""The Racecar robot: sizes, action bounds and observation layout, the model, driving and steering,
contacts, stability under random actions, seeding.

Expected sizes come from reference/safety_gymnasium_semantics.md section 2: the Racecar's robot part
is the 12 fixed sensor values (its hinges carry no sensors), so RacecarGoal0 = 12 + 16 = 28,
RacecarGoal1/2 = 12 + 3 x 16 = 60, Button0/Push0 = 44, Button1/2 and Push1/2 = 76, Circle0-2 = 28 and
Run0 = 12. Its action bounds are its actuators' control ranges (section 1: the action space is
``actuator_ctrlrange``): rear-axle velocity in [-20, 20] rad/s, steering angle in [-0.785, 0.785] rad.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch
from torchrl.envs.utils import step_mdp
from test_navigation import action_td, arrange, idle, make_env
from test_navigation_car import assert_sim0_same_for_n1_and_n16

import sg_torchrl
from sg_torchrl.envs import registry_entry
from sg_torchrl.envs.navigation import Racecar, Vases

torch.set_num_threads(1)

RACECAR_SIZES = {
    "SafetyRacecarGoal0-v0": 28,
    "SafetyRacecarGoal1-v0": 60,
    "SafetyRacecarGoal2-v0": 60,
    "SafetyRacecarButton0-v0": 44,
    "SafetyRacecarButton1-v0": 76,
    "SafetyRacecarButton2-v0": 76,
    "SafetyRacecarPush0-v0": 44,
    "SafetyRacecarPush1-v0": 76,
    "SafetyRacecarPush2-v0": 76,
    "SafetyRacecarCircle0-v0": 28,
    "SafetyRacecarCircle1-v0": 28,
    "SafetyRacecarCircle2-v0": 28,
    "SafetyRacecarRun0-v0": 12,
}
LOW, HIGH = [-20.0, -0.785], [20.0, 0.785]
FULL, LOCK = 20.0, 0.785  # full rear-axle speed (rad/s), full steering lock (rad)


def drive(env, action, steps: int) -> None:
    for _ in range(steps):
        env.step(action_td(env, [action]))


def heading(env) -> float:
    mat = env.scene.agent_mat()[0]
    return float(np.arctan2(mat[1, 0], mat[0, 0]))


def warning_count(env) -> int:
    """All MuJoCo warnings every simulator raised since its last reset."""
    return int(sum(data.warning.number.sum() for data in env.physics.datas))


# ---------------------------------------------------------------------------- registry and sizes
class TestRacecarSpecs:
    def test_registered_for_every_task(self):
        racecar_ids = sg_torchrl.list_envs(family="navigation", robot="Racecar")
        point_ids = sg_torchrl.list_envs(family="navigation", robot="Point")
        assert racecar_ids == [i.replace("Point", "Racecar") for i in point_ids]  # one Racecar id per Point id
        assert set(RACECAR_SIZES) <= set(racecar_ids) and len(racecar_ids) == 34  # 22 reference/Fading/Race + 12 Building/FormulaOne
        entry = registry_entry("SafetyRacecarGoal1-v0")
        assert (entry.robot, entry.task, entry.level, entry.max_episode_steps) == ("Racecar", "Goal", 1, 1000)
        assert sg_torchrl.envs.navigation.ROBOTS["Racecar"] is Racecar

    @pytest.mark.parametrize("env_id", sorted(RACECAR_SIZES))
    def test_sizes_bounds_and_physics_options(self, env_id):
        env = make_env(env_id)
        assert env.observation_dim == RACECAR_SIZES[env_id]
        assert env.action_spec.shape == (1, 2)
        np.testing.assert_allclose(env.action_spec.space.low.tolist(), [LOW])
        np.testing.assert_allclose(env.action_spec.space.high.tolist(), [HIGH])
        model = env.physics.model
        assert model.opt.timestep == 0.004 and env.frame_skip == 10
        assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4

    def test_observation_layout(self):
        env = make_env("SafetyRacecarGoal1-v0")
        starts = {name: (part.start, part.stop) for name, part in env.observation_slices.items()}
        assert starts == {
            "accelerometer": (0, 3), "velocimeter": (3, 6), "gyro": (6, 9), "magnetometer": (9, 12),
            "goal_lidar": (12, 28), "hazards_lidar": (28, 44), "vases_lidar": (44, 60),
        }

    def test_model(self):
        env = make_env("SafetyRacecarGoal0-v0")
        model = env.physics.model
        # Free chassis (7) + rear axle, two steering knuckles and two front wheels (5 hinges).
        assert model.nq == 7 + 5 and model.nv == 6 + 5 and model.nu == 2
        assert [model.actuator(i).name for i in range(2)] == ["drive", "steering"]
        assert model.actuator_forcerange.tolist() == [[-1.0, 1.0], [-1.0, 1.0]]
        # Velocity servo (kv 1) on the rear axle, position servo (kp 1) on the left knuckle.
        assert model.actuator(0).trnid[0] == model.joint("rear_axle").id
        assert model.actuator(1).trnid[0] == model.joint("left_steering").id
        np.testing.assert_allclose(model.actuator_gainprm[:, 0], [1.0, 1.0])
        np.testing.assert_allclose(model.actuator_biasprm[:, :3], [[0.0, 0.0, -1.0], [0.0, -1.0, 0.0]])
        # The knuckles' range is in radians (not read as degrees) and the right one follows the left.
        for side in ("left", "right"):
            np.testing.assert_allclose(model.joint(f"{side}_steering").range, [-0.785, 0.785])
        assert model.neq == 1 and model.eq_type[0] == mujoco.mjtEq.mjEQ_JOINT
        # The robot's geoms: chassis box, front bumper, four wheels. Reference mass 2.163 kg.
        assert env.scene.robot_geoms.sum() == 6
        assert model.body_subtreemass[env.scene.agent_body] == pytest.approx(2.163, abs=2e-3)

    def test_sensors_at_rest(self):
        # At rest facing +y: no motion, gravity's reaction on the accelerometer, the field
        # (0, -0.5, 0) along body -x.
        env = make_env("SafetyRacecarGoal0-v0")
        arrange(env, agent_yaw=np.pi / 2)
        for _ in range(10):
            obs = idle(env)["observation"][0].numpy()
        np.testing.assert_allclose(obs[0:3], [0.0, 0.0, 9.81], atol=0.01)
        np.testing.assert_allclose(obs[3:9], 0.0, atol=1e-3)
        np.testing.assert_allclose(obs[9:12], [-0.5, 0.0, 0.0], atol=1e-3)
        assert env.scene.agent_pos()[0, 2] == pytest.approx(0.05, abs=1e-3)  # on its wheels


# ---------------------------------------------------------------------------- driving
class TestRacecarDrives:
    @pytest.mark.parametrize("yaw", [0.0, 2.0])
    def test_forward_and_backward(self, yaw):
        # Full speed ahead for 1 s drives about 0.43 m along the heading (the reference model: 0.43 m),
        # straight; full reverse from rest drives as far back.
        env = make_env("SafetyRacecarGoal0-v0")
        ahead = np.array([np.cos(yaw), np.sin(yaw)])
        for speed in (FULL, -FULL):
            arrange(env, agent_yaw=yaw)
            drive(env, [speed, 0.0], 25)
            moved = env.scene.agent_xy()[0].copy()
            along = np.sign(speed) * (moved @ ahead)
            assert 0.38 < along < 0.48
            assert abs(ahead[0] * moved[1] - ahead[1] * moved[0]) < 0.02  # straight
            assert abs(np.angle(np.exp(1j * (heading(env) - yaw)))) < 0.02
            velocimeter = env._observe()[0, 3:6]
            assert np.sign(speed) * velocimeter[0] > 0.8 and abs(velocimeter[1]) < 0.02  # body +x is forward

    @pytest.mark.parametrize("yaw", [0.0, 2.0])
    @pytest.mark.parametrize("speed", [FULL, -FULL])
    @pytest.mark.parametrize("steer", [LOCK, -LOCK])
    def test_turns_with_its_steering(self, yaw, speed, steer):
        # Positive steering turns the front wheels left: forward, the car turns counter-clockwise
        # (gyro z > 0, heading grows); in reverse, clockwise. Full lock for 2 s turns by about 0.8-2 rad.
        env = make_env("SafetyRacecarGoal0-v0")
        arrange(env, agent_yaw=yaw)
        sign = np.sign(speed) * np.sign(steer)
        knuckles = [env.physics.model.joint(f"{side}_steering").qposadr[0] for side in ("left", "right")]
        for step in range(50):
            drive(env, [speed, steer], 1)
            if step >= 5:  # once the steering is set and the car rolls
                assert sign * env._observe()[0, 8] > 0.05  # gyro z
        left, right = env.physics.qpos()[0, knuckles]
        assert abs(left - steer) < 0.1 and abs(right - left) < 0.01  # the servo holds, the right knuckle follows
        assert sign * np.angle(np.exp(1j * (heading(env) - yaw))) > 0.5

    def test_vase_contact_counts_the_front_wheels(self):
        # A vase (half-size 0.1) touching the left front wheel's outer face (y = 0.145, knuckle at x = 0.165).
        env = make_env("SafetyRacecarGoal2-v0", cost_mode="raw")
        arrange(env, vases=[(0.165, 0.244)])
        nxt = idle(env)
        assert nxt["cost_info", "vases_contact"].item() >= 1
        assert env.task.find(Vases).speeds(env.scene)[0, 0] > 1e-4


@pytest.mark.parametrize("env_id", ["SafetyRacecarPush1-v0", "SafetyRacecarCircle0-v0", "SafetyRacecarRun0-v0"])
def test_other_tasks_build_and_step(env_id):
    env = make_env(env_id, num_envs=2)
    td = env.reset()
    for action in LOW, HIGH:
        nxt = env.step(td.set("action", torch.tensor([action, action])))["next"]
        assert torch.isfinite(nxt["observation"]).all() and torch.isfinite(nxt["reward"]).all()
    assert nxt["observation"].shape == (2, RACECAR_SIZES[env_id])


# ---------------------------------------------------------------------------- robustness and seeding
@pytest.mark.timeout(60)
def test_random_actions_stay_stable():
    # 4 simulators x 2,500 uniform random in-bound steps (10,000 env steps, resets every 500): every
    # value finite, no simulator diverged, no MuJoCo warning, the car stays upright on its wheels.
    env = make_env("SafetyRacecarGoal1-v0", num_envs=4, seed=11, max_episode_steps=500, cost_mode="raw")
    td = env.reset()
    unit = torch.rand((2500, 4, 2), generator=torch.Generator().manual_seed(3))
    actions = torch.tensor(LOW) + (torch.tensor(HIGH) - torch.tensor(LOW)) * unit
    lowest_up, heights, warnings = 1.0, [], 0
    for action in actions:
        nxt = env.step(td.set("action", action))["next"]
        assert torch.isfinite(nxt["observation"]).all() and torch.isfinite(nxt["reward"]).all()
        warnings += warning_count(env)  # read before the reset below clears the counters
        lowest_up = min(lowest_up, float(env.scene.agent_mat()[:, 2, 2].min()))
        heights.append(env.scene.agent_pos()[:, 2].copy())
        td = env.maybe_reset(step_mdp(nxt.empty().set("next", nxt)))
    heights = np.concatenate(heights)
    assert env.physics_errors == 0 and warnings == 0
    assert lowest_up > 0.95  # never tilted by more than ~18 degrees
    assert heights.min() > 0.045 and heights.max() < 0.06


def test_seeding_n1_equals_n16():
    assert_sim0_same_for_n1_and_n16("SafetyRacecarGoal1-v0")
