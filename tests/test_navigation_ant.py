"""The Ant robot: sizes, model facts, observation layout and sources, the death rule, walking, stability, seeding.

Expected sizes come from reference/safety_gymnasium_semantics.md section 2: the Ant's robot part is
the 12 fixed sensor values, 8 hinge velocities, the torso height (1), ``agent_qvel`` (3) and 8 hinge
angles as (sin, cos) = 40, so AntGoal0 = 40 + 16 = 56, AntGoal1/2 = 40 + 3 x 16 = 88, AntButton0 and
AntPush0 = 72, AntButton1/2 and AntPush1/2 = 104, AntCircle0-2 = 56 and AntRun0 = 40. The death rule
(section 5): the episode terminates once the torso centre is at 0.08 or lower.
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
from sg_torchrl.envs.navigation import Ant

torch.set_num_threads(1)

ANT_SIZES = {
    "SafetyAntGoal0-v0": 56,
    "SafetyAntGoal1-v0": 88,
    "SafetyAntGoal2-v0": 88,
    "SafetyAntButton0-v0": 72,
    "SafetyAntButton1-v0": 104,
    "SafetyAntButton2-v0": 104,
    "SafetyAntPush0-v0": 72,
    "SafetyAntPush1-v0": 104,
    "SafetyAntPush2-v0": 104,
    "SafetyAntCircle0-v0": 56,
    "SafetyAntCircle1-v0": 56,
    "SafetyAntCircle2-v0": 56,
    "SafetyAntRun0-v0": 40,
}
JOINTS = [f"{part}_{k}" for k in range(1, 5) for part in ("hip", "ankle")]  # action order
ANKLE_SIGNS = np.array([1.0, -1.0, -1.0, 1.0])  # the sign that bends each ankle downwards
REST = np.zeros(8)
REST[1::2] = ANKLE_SIGNS * np.pi / 2
GRAVITY_DROP = 0.5 * 9.81 * 0.1**2  # free fall from rest during one env step (0.1 s), exact under RK4
UPSIDE_DOWN = [0.0, 1.0, 0.0, 0.0]  # half a turn about x: the torso sphere is the lowest part


def gait(t: int, period: int = 7, lag: float = 1.25 * np.pi, hip: float = 0.6, ankle: float = 0.2) -> np.ndarray:
    """An open-loop trot, action ``(8,)`` at env step ``t`` (torques, not targets).

    Diagonal legs (1 and 3, 2 and 4) move in phase, the pairs half a period (``period`` env steps)
    apart. Each ankle pushes its foot down and lifts it sinusoidally; each hip swings its leg along
    +x (forward for legs 3 and 4 is a counter-clockwise turn, for legs 1 and 2 clockwise) ``lag``
    radians after its ankle. Hand-tuned on a small grid (period, lag, amplitudes).
    """
    phase = 2 * np.pi * t / period + np.array([0.0, np.pi, 0.0, np.pi])
    forward = np.array([-1.0, -1.0, 1.0, 1.0])
    action = np.empty(8)
    action[0::2] = -forward * hip * np.sin(phase + lag)
    action[1::2] = ANKLE_SIGNS * ankle * np.sin(phase)
    return action


def place(env, index: int, z: float, quat=(1.0, 0.0, 0.0, 0.0), xy=(0.0, 0.0), qvel=None, legs=REST) -> None:
    """Put simulator ``index``'s ant at height ``z`` (torso centre) in orientation ``quat``, at rest
    unless ``qvel`` is given; other objects stay where they are."""
    physics, robot = env.physics, env.robot
    data = physics.datas[index]
    qpos, velocity = data.qpos.copy(), np.zeros_like(data.qvel) if qvel is None else np.asarray(qvel, float)
    root = robot._qpos_root
    qpos[root : root + 7] = [*xy, z, *quat]
    qpos[robot._qpos_legs] = legs
    physics.reset([index], qpos[None], velocity[None], data.mocap_pos.copy()[None], data.mocap_quat.copy()[None])


# ---------------------------------------------------------------------------- registry and sizes
class TestAntSpecs:
    def test_registered_for_every_task(self):
        ant_ids = sg_torchrl.list_envs(family="navigation", robot="Ant")
        point_ids = sg_torchrl.list_envs(family="navigation", robot="Point")
        assert ant_ids == [i.replace("Point", "Ant") for i in point_ids]  # one Ant id per Point id
        assert set(ANT_SIZES) <= set(ant_ids) and len(ant_ids) == 22
        entry = registry_entry("SafetyAntGoal1-v0")
        assert (entry.robot, entry.task, entry.level, entry.max_episode_steps) == ("Ant", "Goal", 1, 1000)
        # The velocity family's Ant is a different env under the same robot name; the family tells them apart.
        assert sg_torchrl.list_envs(family="velocity", robot="Ant") == ["SafetyAntVelocity-v0", "SafetyAntVelocity-v1"]
        multi_agent = ["Safety2x4AntVelocity-v0", "Safety4x2AntVelocity-v0"]  # MaMuJoCo partitions of the velocity Ant
        multi_goal = [f"SafetyAntMultiGoal{level}-v0" for level in range(3)]  # two Ants in one navigation world
        vision = [i.replace("-v0", "Vision-v0") for i in ant_ids]  # the same tasks seen through the robot's camera
        assert sg_torchrl.list_envs(robot="Ant") == sorted(
            [*ant_ids, *vision, "SafetyAntVelocity-v0", "SafetyAntVelocity-v1", *multi_agent, *multi_goal])

    @pytest.mark.parametrize("env_id", sorted(ANT_SIZES))
    def test_sizes_and_physics_options(self, env_id):
        env = make_env(env_id)
        assert env.observation_dim == ANT_SIZES[env_id]
        assert env.action_spec.shape == (1, 8)
        assert env.action_spec.space.low.tolist() == [[-1.0] * 8]
        assert env.action_spec.space.high.tolist() == [[1.0] * 8]
        assert env.physics.timestep == 0.01 and env.frame_skip == 10
        assert env.physics.model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4

    def test_observation_layout(self):
        env = make_env("SafetyAntGoal1-v0")
        widths = [(name, part.stop - part.start) for name, part in env.observation_slices.items()]
        assert widths == [
            ("accelerometer", 3), ("velocimeter", 3), ("gyro", 3), ("magnetometer", 3),
            *((f"{joint}_vel", 1) for joint in JOINTS),
            ("agent_pos", 1), ("agent_qvel", 3),
            *((joint, 2) for joint in JOINTS),
            ("goal_lidar", 16), ("hazards_lidar", 16), ("vases_lidar", 16),
        ]
        assert env.observation_slices["agent_pos"] == slice(20, 21)
        assert env.observation_slices["hip_1"] == slice(24, 26)

    def test_model(self):
        env = make_env("SafetyAntGoal0-v0")
        model = env.physics.model
        assert model.nq == 7 + 8 and model.nv == 6 + 8 and model.nu == 8
        assert [model.actuator(i).name for i in range(8)] == JOINTS
        assert [model.joint(model.actuator(i).trnid[0]).name for i in range(8)] == JOINTS
        assert model.actuator_gear[:, 0].tolist() == [150.0] * 8
        assert not model.actuator_forcelimited.any()
        ranges = np.array([model.joint(joint).range for joint in JOINTS])
        np.testing.assert_allclose(ranges[0::2], [[-0.7, 0.7]] * 4)
        np.testing.assert_allclose(ranges[1::2], [[0.52, 1.74], [-1.74, -0.52], [-1.74, -0.52], [0.52, 1.74]])
        legs = [int(model.joint(joint).dofadr[0]) for joint in JOINTS]
        assert model.dof_armature[legs].tolist() == [1.0] * 8 and model.dof_damping[legs].tolist() == [1.0] * 8
        assert model.dof_armature[:6].tolist() == [0.0] * 6 and model.dof_damping[:6].tolist() == [0.0] * 6
        # Torso sphere, 4 stubs, 4 thighs, 4 feet; density 5 gives the reference's 0.0142 kg.
        assert env.scene.robot_geoms.sum() == 13
        assert model.body_subtreemass[env.scene.agent_body] == pytest.approx(0.014233, abs=1e-5)

    def test_start_pose(self):
        env = make_env("SafetyAntGoal0-v0")
        arrange(env, agent=(0.5, -0.25), agent_yaw=2.0)
        qpos = env.physics.datas[0].qpos
        np.testing.assert_allclose(qpos[:3], [0.5, -0.25, 0.18])
        np.testing.assert_allclose(qpos[3:7], [np.cos(1.0), 0.0, 0.0, np.sin(1.0)])
        np.testing.assert_allclose(qpos[7:15], REST)

    def test_sampled_resets_add_the_reference_spawn_noise(self):
        # Sampled resets move each leg angle by U(-0.1, 0.1) around the rest pose (reference agent
        # class), drawn from each simulator's own generator; explicit layouts start exactly at rest.
        env = make_env("SafetyAntGoal0-v0", num_envs=64, seed=3)
        env.reset()
        offsets = np.stack([data.qpos[7:15] for data in env.physics.datas]) - REST
        assert np.abs(offsets).max() <= 0.1 and np.abs(offsets).max() > 0.09
        assert np.abs(offsets).min() > 0.0 and abs(offsets.mean()) < 0.02
        assert len(np.unique(offsets[:, 0])) == 64


# ---------------------------------------------------------------------------- observation sources
class TestAntObservation:
    def test_entries_read_the_joints(self):
        # A tilted, spinning torso with the legs at arbitrary in-range angles and speeds.
        env = make_env("SafetyAntGoal0-v0")
        env.reset()
        quat = np.array([0.9, 0.2, -0.3, 0.25])
        quat /= np.linalg.norm(quat)
        legs = np.array([0.3, 1.0, -0.5, -1.2, 0.1, -0.8, -0.6, 1.5])
        qvel = np.r_[0.4, -0.2, 0.3, 1.5, -2.0, 0.7, np.linspace(-1.0, 1.0, 8)]
        place(env, 0, 1.0, quat, qvel=qvel, legs=legs)  # high above the floor: no contacts
        obs, parts = env._observe()[0], env.observation_slices
        rotation = np.empty(9)
        mujoco.mju_quat2Mat(rotation, quat)
        rotation = rotation.reshape(3, 3)
        site = np.array([0.0, 0.0, 1.0]) + rotation @ [0.0, 0.0, -0.02]
        assert obs[parts["agent_pos"]] == pytest.approx([site[2]], abs=1e-12)  # height of the torso site
        # agent_qvel: the torso's angular velocity in world axes (free-joint qvel[3:6] is in body axes);
        # the gyro reads the same vector in body axes.
        np.testing.assert_allclose(obs[parts["agent_qvel"]], rotation @ qvel[3:6], atol=1e-12)
        np.testing.assert_allclose(obs[parts["gyro"]], qvel[3:6], atol=1e-12)
        for i, joint in enumerate(JOINTS):
            assert obs[parts[f"{joint}_vel"]] == pytest.approx([qvel[6 + i]], abs=1e-12)
            np.testing.assert_allclose(obs[parts[joint]], [np.sin(legs[i]), np.cos(legs[i])], atol=1e-12)

    def test_sensors_at_rest(self):
        # Standing at rest facing +y: no motion, feet straight down, gravity's reaction on the
        # accelerometer, the field (0, -0.5, 0) along body +x, the torso site about 0.14 high.
        env = make_env("SafetyAntGoal0-v0")
        arrange(env, agent_yaw=np.pi / 2)
        for _ in range(10):
            nxt = idle(env)
        obs, parts = nxt["observation"][0].double().numpy(), env.observation_slices
        assert not nxt["terminated"].item()
        np.testing.assert_allclose(obs[0:3], [0.0, 0.0, 9.81], atol=0.05)
        np.testing.assert_allclose(obs[3:9], 0.0, atol=1e-3)
        np.testing.assert_allclose(obs[9:12], [-0.5, 0.0, 0.0], atol=1e-3)
        np.testing.assert_allclose(obs[12:20], 0.0, atol=1e-3)
        assert obs[parts["agent_pos"]] == pytest.approx([0.141], abs=0.005)
        np.testing.assert_allclose(obs[parts["agent_qvel"]], 0.0, atol=1e-3)
        angles = obs[24:40].reshape(8, 2)
        np.testing.assert_allclose(angles, np.c_[np.sin(REST), np.cos(REST)], atol=1e-3)


# ---------------------------------------------------------------------------- the death rule
class TestAntDeath:
    def test_terminates_at_or_below_008(self):
        # Upside-down ants falling freely (the torso sphere is their lowest part, clear of the floor):
        # after one env step the torso centre is exactly 0.001 below / at +0.001 above the threshold.
        env = make_env("SafetyAntGoal0-v0", num_envs=3)
        env.reset()
        for index, z_after in ((0, 0.079), (1, 0.081)):
            place(env, index, z_after + GRAVITY_DROP, UPSIDE_DOWN, xy=(index, 0.0))
        place(env, 2, 0.18, xy=(2.0, 0.0))  # standing
        nxt = idle(env)
        np.testing.assert_allclose(env.scene.agent_pos()[:2, 2], [0.079, 0.081], atol=1e-9)
        assert nxt["terminated"][:, 0].tolist() == [True, False, False]
        assert nxt["done"][:, 0].tolist() == [True, False, False]
        assert not nxt["truncated"].any()
        np.testing.assert_array_equal(env.robot.is_alive(env.scene), [False, True, True])

    def test_threshold_is_inclusive(self):
        env = make_env("SafetyAntGoal0-v0", num_envs=2)
        env.reset()
        place(env, 0, 0.08, UPSIDE_DOWN)
        place(env, 1, 0.08 + 1e-9, UPSIDE_DOWN)
        assert env.robot.is_alive(env.scene).tolist() == [False, True]

    def test_dead_simulator_auto_resets_alone(self):
        env = make_env("SafetyAntGoal0-v0", num_envs=3)
        td = env.reset()
        place(env, 0, 0.075 + GRAVITY_DROP, UPSIDE_DOWN)  # dies on the next step
        for index in (1, 2):
            place(env, index, 0.18, xy=(index, 1.0))
        stepped, td = env.step_and_maybe_reset(td.set("action", torch.zeros(3, 8)))
        assert stepped["next", "terminated"][:, 0].tolist() == [True, False, False]
        positions = env.scene.agent_pos().copy()
        np.testing.assert_allclose(positions[0, 2], 0.18)  # reset: standing again at the start height
        np.testing.assert_allclose(positions[1:, :2], [[1.0, 1.0], [2.0, 1.0]], atol=0.01)  # not reset
        torch.testing.assert_close(td["observation"][1:], stepped["next", "observation"][1:])
        assert not td["done"].any()
        stepped, td = env.step_and_maybe_reset(td.set("action", torch.zeros(3, 8)))
        assert not stepped["next", "done"].any()


# ---------------------------------------------------------------------------- walking
@pytest.mark.parametrize("yaw", [0.0, 2.0])
def test_walks_forward_with_a_trot(yaw):
    # Measured: 1.01 m along the heading after 30 env steps (3 s), drifting 0.42 m to the left
    # (it turns left by about 0.1 rad), the same whatever the yaw (the gait is the same in the
    # ant's frame); it never falls.
    env = make_env("SafetyAntGoal0-v0")
    arrange(env, agent_yaw=yaw)
    ahead = np.array([np.cos(yaw), np.sin(yaw)])
    for t in range(30):
        nxt = env.step(action_td(env, [gait(t)]))["next"]
        assert not nxt["terminated"].item()
    moved = env.scene.agent_xy()[0].copy()
    assert moved @ ahead > 0.6
    assert abs(ahead[0] * moved[1] - ahead[1] * moved[0]) < 0.6


# ---------------------------------------------------------------------------- robustness and seeding
@pytest.mark.timeout(90)
def test_random_actions_stay_stable():
    # 4 simulators x 2,500 uniform random steps (10,000 env steps): every value finite, no simulator
    # diverged, no MuJoCo warning. Random torques flip the ant now and then: each death
    # auto-resets that simulator only (it stands at the start height again).
    env = make_env("SafetyAntGoal1-v0", num_envs=4, seed=11, max_episode_steps=500, cost_mode="raw")
    td = env.reset()
    actions = 2 * torch.rand((2500, 4, 8), generator=torch.Generator().manual_seed(3)) - 1
    deaths = warnings = 0
    for action in actions:
        stepped = env.step(td.set("action", action))
        nxt = stepped["next"]
        # Before the reset: resetting a simulator clears its warning counters.
        warnings += sum(int(w.number) for data in env.physics.datas for w in data.warning)
        assert torch.isfinite(nxt["observation"]).all() and torch.isfinite(nxt["reward"]).all()
        td = env.maybe_reset(step_mdp(stepped))
        dead = nxt["terminated"][:, 0].numpy()
        if dead.any():
            deaths += int(dead.sum())
            np.testing.assert_allclose(env.scene.agent_pos()[dead, 2], 0.18)
    assert env.physics_errors == 0
    assert warnings == 0
    assert deaths > 0  # the death path ran (287 deaths with these seeds)


def test_seeding_n1_equals_n16():
    assert_sim0_same_for_n1_and_n16("SafetyAntGoal1-v0")


def test_ant_class_is_exported():
    assert sg_torchrl.envs.navigation.ROBOTS["Ant"] is Ant
