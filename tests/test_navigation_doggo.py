"""The Doggo robot: sizes and observation layout, model facts, touch sensors, walking, stability, seeding.

Expected sizes come from reference/safety_gymnasium_semantics.md section 2: the Doggo's robot part is
the 12 fixed sensor values, 8 touch sensors, 12 hinge velocities and 12 hinge angles as (sin, cos)
= 56, so DoggoGoal0 = 56 + 16 = 72, DoggoGoal1/2 = 56 + 3 x 16 = 104, DoggoCircle0-2 = 72 and
DoggoRun0 = 56 (tests/test_registry.py checks every Doggo id against the reference table).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torchrl.envs.utils import step_mdp
from test_navigation import action_td, arrange, idle, make_env
from test_navigation_car import assert_sim0_same_for_n1_and_n16

import sg_torchrl
from sg_torchrl.envs import registry_entry
from sg_torchrl.envs.navigation import Doggo

torch.set_num_threads(1)

DOGGO_SIZES = {
    "SafetyDoggoGoal0-v0": 72,
    "SafetyDoggoGoal1-v0": 104,
    "SafetyDoggoCircle0-v0": 72,
    "SafetyDoggoRun0-v0": 56,
}
HINGES = [f"hip_{k}_z" for k in range(1, 5)] + [f"hip_{k}_y" for k in range(1, 5)] + [f"ankle_{k}" for k in range(1, 5)]
TOUCH = slice(12, 20)  # touch_ankle_1a .. 4a, then 1b .. 4b
FEET = slice(16, 20)  # the foot ends (b) of legs 1 to 4


def trot(t: int, period: int = 10, lag: float = np.pi / 4) -> np.ndarray:
    """An open-loop trot, action ``(12,)`` at env step ``t``: diagonal legs (1 and 3, 2 and 4) in phase,
    the pairs half a period apart; every hip swings its leg with the full control range (azimuth and
    elevation together) and every knee follows its hip ``lag`` radians later."""
    phase = 2 * np.pi * t / period + np.array([0.0, np.pi, 0.0, np.pi])  # legs 1, 2, 3, 4
    return np.concatenate([np.sin(phase), np.sin(phase), np.sin(phase + lag)])


def warning_count(env) -> int:
    """All MuJoCo warnings every simulator raised since its last reset."""
    return int(sum(data.warning.number.sum() for data in env.physics.datas))


# ---------------------------------------------------------------------------- registry and sizes
class TestDoggoSpecs:
    def test_registered_for_every_task(self):
        doggo_ids = sg_torchrl.list_envs(family="navigation", robot="Doggo")
        point_ids = sg_torchrl.list_envs(family="navigation", robot="Point")
        assert doggo_ids == [i.replace("Point", "Doggo") for i in point_ids]  # one Doggo id per Point id
        assert len(doggo_ids) == 34 and set(DOGGO_SIZES) <= set(doggo_ids)  # 22 reference/Fading/Race + 12 Building/FormulaOne
        entry = registry_entry("SafetyDoggoGoal1-v0")
        assert (entry.robot, entry.task, entry.level, entry.max_episode_steps) == ("Doggo", "Goal", 1, 1000)
        assert sg_torchrl.envs.navigation.ROBOTS["Doggo"] is Doggo

    @pytest.mark.parametrize("env_id", sorted(DOGGO_SIZES))
    def test_sizes_and_physics_options(self, env_id):
        env = make_env(env_id)
        assert env.observation_dim == DOGGO_SIZES[env_id]
        assert env.action_spec.shape == (1, 12)
        assert env.action_spec.space.low.tolist() == [[-1.0] * 12]
        assert env.action_spec.space.high.tolist() == [[1.0] * 12]
        assert env.physics.timestep == 0.01 and env.frame_skip == 10

    def test_observation_layout(self):
        env = make_env("SafetyDoggoGoal1-v0")
        names = [(name, part.start, part.stop) for name, part in env.observation_slices.items()]
        expected = ["accelerometer", "velocimeter", "gyro", "magnetometer"]
        expected += [f"touch_ankle_{k}{end}" for end in "ab" for k in range(1, 5)]
        expected += [f"jointvel_{joint}" for joint in HINGES] + [f"jointpos_{joint}" for joint in HINGES]
        expected += ["goal_lidar", "hazards_lidar", "vases_lidar"]
        assert [name for name, _, _ in names] == expected
        widths = [3] * 4 + [1] * 8 + [1] * 12 + [2] * 12 + [16] * 3
        assert [stop - start for _, start, stop in names] == widths
        assert names[-3][1] == 56

    def test_model(self):
        env = make_env("SafetyDoggoGoal0-v0")
        model = env.physics.model
        # Free torso (7) + 12 leg hinges + the passive waist hinge.
        assert model.nq == 7 + 13 and model.nu == 12
        assert [model.actuator(i).name for i in range(12)] == HINGES  # reference action order
        np.testing.assert_allclose(model.actuator_gear[:, 0], 0.00625)
        assert not model.actuator_forcelimited.any()
        assert [model.joint(model.actuator_trnid[i, 0]).name for i in range(12)] == HINGES
        joints = ("hip_1_z", "hip_1_y", "hip_2_y", "ankle_3", "waist_x")
        ranges = {name: model.joint(name).range.tolist() for name in joints}
        assert ranges == {"hip_1_z": [-0.174533, 0.523599], "hip_1_y": [-1.308998, 0.2618],
                          "hip_2_y": [0.0, 2.356196], "ankle_3": [-1.308998, 0.0], "waist_x": [-0.523599, 0.523599]}
        # The robot's geoms: 2 torso cylinders and 3 capsules per leg. Mass from the reference model.
        assert env.scene.robot_geoms.sum() == 14
        assert model.body_subtreemass[env.scene.agent_body] == pytest.approx(0.01984, abs=1e-4)
        assert model.camera("vision").fovy[0] == 100.0

    def test_start_pose(self):
        env = make_env("SafetyDoggoGoal0-v0")
        arrange(env, agent=(0.5, -0.25), agent_yaw=1.0)
        qpos = env.physics.qpos()[0]
        np.testing.assert_allclose(qpos[:3], [0.5, -0.25, 0.22])
        np.testing.assert_allclose(qpos[3:7], [np.cos(0.5), 0.0, 0.0, np.sin(0.5)])
        np.testing.assert_array_equal(qpos[7:], 0.0)  # the legs at their rest angles


# ---------------------------------------------------------------------------- sensors and walking
class TestDoggoBody:
    def test_touch_sensors_on_the_floor_and_in_the_air(self):
        # Dropped from 0.22 with zero action it settles on its four feet within 1 s.
        env = make_env("SafetyDoggoGoal0-v0")
        arrange(env, agent_yaw=0.7)
        for _ in range(10):
            obs = idle(env)["observation"][0].numpy()
        assert (obs[FEET] > 0).all()
        assert (obs[TOUCH] >= 0).all()
        np.testing.assert_allclose(obs[20:32], 0.0, atol=0.05)  # at rest: no hinge moves
        # Lifted 1 m up: nothing touches; one env step (0.1 s) later it is still falling freely.
        qpos = env.physics.qpos()[:1].copy()
        qpos[0, 2] = 1.0
        env.physics.reset([0], qpos, np.zeros((1, env.physics.model.nv)))
        assert (env._observe()[0, TOUCH] == 0).all()
        assert (idle(env)["observation"][0, TOUCH] == 0).all()
        assert env.scene.agent_pos()[0, 2] > 0.9

    def test_hinge_observations(self):
        # The angle pairs are (sin, cos) of the hinge angles; the velocities are the hinge speeds.
        env = make_env("SafetyDoggoGoal0-v0")
        arrange(env)
        for t in range(5):
            obs = env.step(action_td(env, [trot(t)]))["next", "observation"][0].numpy()
        model, qpos, qvel = env.physics.model, env.physics.qpos()[0], env.physics.qvel()[0]
        angles = np.array([qpos[model.joint(name).qposadr[0]] for name in HINGES])
        speeds = np.array([qvel[model.joint(name).dofadr[0]] for name in HINGES])
        np.testing.assert_allclose(obs[20:32], speeds, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(obs[32:56].reshape(12, 2), np.stack([np.sin(angles), np.cos(angles)], 1), atol=1e-6)

    def test_trot_walks_forward(self):
        # 10 s of the open-loop trot from 4 headings: about 1.05-1.1 m along the start heading was
        # measured (0.3-1.2 m over nearby gait parameters); sideways drift is small.
        env = make_env("SafetyDoggoGoal0-v0", num_envs=4)
        env.reset()
        yaws = np.array([0.0, 1.5, 3.0, 4.5])
        xy = np.zeros((4, env.layout_sampler.size, 2))
        xy[:, 1:] = 3.0  # the goal out of the way
        yaw = np.zeros(xy.shape[:2])
        yaw[:, 0] = yaws
        env.set_layout(np.arange(4), xy, yaw)
        for t in range(100):
            env.step(action_td(env, np.tile(trot(t), (4, 1))))
        ahead = np.stack([np.cos(yaws), np.sin(yaws)], 1)
        moved = env.scene.agent_xy()
        along = (moved * ahead).sum(1)
        sideways = moved[:, 1] * ahead[:, 0] - moved[:, 0] * ahead[:, 1]
        assert (along > 0.5).all(), along
        assert (np.abs(sideways) < 0.5 * along).all(), sideways
        assert env.physics_errors == 0


# ---------------------------------------------------------------------------- robustness and seeding
@pytest.mark.timeout(60)
def test_random_actions_stay_stable():
    # 4 simulators x 2,500 uniform random steps (10,000 env steps, resets every 500): every value
    # finite, no simulator diverged, no MuJoCo warning, the torso stays between floor and start height.
    env = make_env("SafetyDoggoGoal1-v0", num_envs=4, seed=11, max_episode_steps=500, cost_mode="raw")
    td = env.reset()
    actions = 2 * torch.rand((2500, 4, 12), generator=torch.Generator().manual_seed(3)) - 1
    heights, warnings = [], 0
    for action in actions:
        stepped = env.step(td.set("action", action))
        nxt = stepped["next"]
        assert torch.isfinite(nxt["observation"]).all() and torch.isfinite(nxt["reward"]).all()
        warnings += warning_count(env)  # read before the reset below clears the counters
        heights.append(env.scene.agent_pos()[:, 2].copy())
        td = env.maybe_reset(step_mdp(stepped))
    heights = np.concatenate(heights)
    assert env.physics_errors == 0 and warnings == 0
    assert heights.min() > 0.02 and heights.max() < 0.22, (heights.min(), heights.max())
    assert nxt["truncated"].all() and not nxt["terminated"].any()  # Doggo never dies


def test_seeding_n1_equals_n16():
    assert_sim0_same_for_n1_and_n16("SafetyDoggoGoal1-v0")
