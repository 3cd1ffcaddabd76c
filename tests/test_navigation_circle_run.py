"""Circle and Run tasks (rewards, sigwall costs, layouts) and the lidar options (Circle range, natural, compass).

Expected numbers come from reference/safety_gymnasium_semantics.md sections 2-6, worked out by hand
in each test. Sizes: Circle observes only ``circle_lidar`` (Point 12 + 16 = 28, Car 24 + 16 = 40),
Run nothing but the robot's sensors (Point 12, Car 24).
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch
from test_navigation import action_td, arrange, idle, lidar, make_env
from test_navigation_car import assert_sim0_same_for_n1_and_n16

import sg_torchrl
from sg_torchrl.envs import registry_entry
from sg_torchrl.envs.navigation import CircleZone, Goal, Sigwalls

torch.set_num_threads(1)

SIZES = {
    "SafetyPointCircle0-v0": (28, ()),
    "SafetyPointCircle1-v0": (28, ("out_of_boundary",)),
    "SafetyPointCircle2-v0": (28, ("out_of_boundary",)),
    "SafetyCarCircle0-v0": (40, ()),
    "SafetyCarCircle1-v0": (40, ("out_of_boundary",)),
    "SafetyCarCircle2-v0": (40, ("out_of_boundary",)),
    "SafetyPointRun0-v0": (12, ("out_of_boundary",)),
    "SafetyCarRun0-v0": (24, ("out_of_boundary",)),
}


def place(env, agent=(0.0, 0.0), agent_yaw: float = 0.0, **objects) -> None:
    """``arrange`` (robot at ``agent``, other objects far away) leaving the fixed objects (circle, walls) in place."""
    fixed = {obj.name: obj.locations for obj in env.task.objects if len(obj.locations)}
    arrange(env, agent=agent, agent_yaw=agent_yaw, **{**fixed, **objects})


def set_velocity(env, velocity, index: int = 0) -> None:
    """Give simulator ``index``'s robot the planar world velocity ``velocity`` (at its current pose)."""
    model, data = env.physics.model, env.physics.datas[index]
    if env.robot.name == "Point":
        data.qvel[model.joint("agent_x").dofadr[0]] = velocity[0]
        data.qvel[model.joint("agent_y").dofadr[0]] = velocity[1]
    else:  # the free joint's first three velocities: linear, world frame
        data.qvel[model.joint("agent").dofadr[0] + np.arange(2)] = velocity
    mujoco.mj_forward(model, data)
    env.physics.refresh([index])


def circle_reward(xy, uv) -> float:
    x, y = xy
    u, v = uv
    rho = np.hypot(x, y)
    return 0.1 * ((-u * y + v * x) / rho) / (1 + abs(rho - 1.5))


# ---------------------------------------------------------------------------- registry and sizes
class TestSpecs:
    def test_ids(self):
        ids = sg_torchrl.list_envs(family="navigation")
        assert set(SIZES) <= set(ids)
        for env_id in SIZES:
            entry = registry_entry(env_id)
            assert entry.max_episode_steps == 500, env_id
        assert not any("Run1" in i or "Run2" in i for i in ids)

    @pytest.mark.parametrize("env_id", sorted(SIZES))
    def test_sizes_and_constraints(self, env_id):
        env = make_env(env_id)
        size, constraints = SIZES[env_id]
        assert env.observation_dim == size and env.action_dim == 2
        assert env.constraint_names == constraints
        assert env.max_episode_steps == 500
        lidar_entries = [name for name in env.observation_slices if name.endswith("_lidar")]
        assert lidar_entries == (["circle_lidar"] if "Circle" in env_id else [])  # sigwalls are not observed
        floor = env.physics.model.geom("floor").size[0]
        assert floor == (17.5 if "Run" in env_id else 3.5)
        assert env.task.reward_clip == (None if "Run" in env_id else 10.0)


# ---------------------------------------------------------------------------- layouts
class TestLayouts:
    def test_circle_layout(self):
        # Agent uniform in [-0.8, 0.8]^2 (keep-out 0); the circle at the origin; 4 walls at +-1.125,
        # upright and along their axis whatever yaw the layout drew.
        env = make_env("SafetyPointCircle2-v0", num_envs=50, seed=2)
        walls = env.task.find(Sigwalls)
        starts = []
        for _ in range(4):
            env.reset()
            starts.append(env.scene.agent_xy().copy())
            np.testing.assert_allclose(env.task.find(CircleZone).positions(env.scene), 0.0)
            expected = [(-1.125, 0.0), (1.125, 0.0), (0.0, -1.125), (0.0, 1.125)]
            np.testing.assert_allclose(walls.positions(env.scene)[0], expected)
            quats = np.stack([data.mocap_quat[walls.mocap_ids] for data in env.physics.datas])
            np.testing.assert_allclose(quats, np.broadcast_to([1.0, 0.0, 0.0, 0.0], quats.shape))
        starts = np.concatenate(starts)
        assert (np.abs(starts) <= 0.8).all() and np.abs(starts).max() > 0.7
        assert len(np.unique(starts, axis=0)) == 200

    def test_run_layout(self):
        env = make_env("SafetyCarRun0-v0", num_envs=50, seed=2)
        env.reset()
        xy = env.scene.agent_xy()
        assert (np.abs(xy[:, 0]) <= 0.2).all() and np.abs(xy[:, 0]).max() > 0.15
        np.testing.assert_allclose(xy[:, 1], 16.5, atol=2e-3)  # the car settles on its contacts
        np.testing.assert_allclose(env.task.find(Sigwalls).positions(env.scene)[0], [(-0.5, 0.0), (0.5, 0.0)])


# ---------------------------------------------------------------------------- rewards
class TestCircleReward:
    @pytest.mark.parametrize("robot", ["Point", "Car"])
    @pytest.mark.parametrize("yaw", [0.0, 2.5])
    def test_known_position_and_velocity(self, robot, yaw):
        # Robot at (1, 0.5) moving (-0.3, 0.4): -u*y + v*x = 0.15 + 0.4 = 0.55, rho = sqrt(1.25) = 1.11803,
        # reward = 0.1 * (0.55 / 1.11803) / (1 + |1.11803 - 1.5|) = 0.1 * 0.49193 / 1.38197 = 0.035597.
        # The robot's heading does not matter: the velocity is the world-frame one.
        env = make_env(f"Safety{robot}Circle0-v0")
        place(env, agent=(1.0, 0.5), agent_yaw=yaw)
        set_velocity(env, (-0.3, 0.4))
        assert env.task.reward(env)[0] == pytest.approx(0.035597, abs=1e-6)
        set_velocity(env, (0.3, -0.4))  # clockwise: the same, negative
        assert env.task.reward(env)[0] == pytest.approx(-0.035597, abs=1e-6)
        set_velocity(env, (0.5, 0.25))  # radial, outwards: no reward
        assert env.task.reward(env)[0] == pytest.approx(0.0, abs=1e-12)

    def test_step_reward_uses_the_state_after_the_step(self):
        # Point sliding counter-clockwise along the rim: the emitted reward is the formula on the
        # position and velocity the step ended in (its slide joints' velocities are world-frame).
        env = make_env("SafetyPointCircle0-v0")
        place(env, agent=(0.0, -1.5))
        set_velocity(env, (1.0, 0.0))
        nxt = idle(env)
        qvel = env.physics.qvel()[0]
        expected = circle_reward(env.scene.agent_xy()[0], qvel[:2])
        assert expected == pytest.approx(0.1, rel=0.05)  # ~ speed 1 on the rim
        assert nxt["reward"].item() == pytest.approx(expected, rel=1e-5)


class TestRunReward:
    @pytest.mark.parametrize("robot", ["Point", "Car"])
    def test_potential_difference(self, robot):
        # Driving down the corridor (-y): reward = phi - phi_prev = 60 * (distance gained towards (0, -1000)).
        env = make_env(f"Safety{robot}Run0-v0")
        place(env, agent=(0.1, 10.0), agent_yaw=-np.pi / 2)
        target = np.array([0.0, -1000.0])
        total = 0.0
        for _ in range(10):
            before = env.scene.agent_xy()[0].copy()
            nxt = env.step(action_td(env, [[1.0, 0.0] if robot == "Point" else [1.0, 1.0]]))["next"]
            after = env.scene.agent_xy()[0]
            expected = 60.0 * (np.linalg.norm(before - target) - np.linalg.norm(after - target))
            assert nxt["reward"].item() == pytest.approx(expected, rel=1e-4, abs=1e-6)
            total += nxt["reward"].item()
        assert total > 0.5  # it does run the right way

    def test_not_clipped(self):
        # Point at 15 m/s down the corridor: ~0.3 m per step, reward ~18, beyond the +-10 clip of other tasks.
        env = make_env("SafetyPointRun0-v0")
        place(env, agent=(0.0, 10.0))
        set_velocity(env, (0.0, -15.0))
        before = env.scene.agent_xy()[0].copy()
        reward = idle(env)["reward"].item()
        gained = np.linalg.norm(before - (0.0, -1000.0)) - np.linalg.norm(env.scene.agent_xy()[0] - (0.0, -1000.0))
        assert reward > 15.0 and reward == pytest.approx(60.0 * gained, rel=1e-4)


# ---------------------------------------------------------------------------- sigwall costs
@pytest.mark.parametrize(
    "env_id, position, cost",
    [
        ("SafetyPointCircle1-v0", (1.2, 0.0), 1.0),
        ("SafetyPointCircle1-v0", (-1.2, 0.3), 1.0),
        ("SafetyPointCircle1-v0", (1.0, 0.0), 0.0),
        ("SafetyPointCircle1-v0", (0.0, 1.2), 0.0),  # level 1 has no y walls
        ("SafetyPointCircle2-v0", (0.0, 1.2), 1.0),
        ("SafetyPointCircle2-v0", (0.3, -1.2), 1.0),
        ("SafetyPointCircle2-v0", (-1.2, 0.0), 1.0),
        ("SafetyPointCircle2-v0", (1.1, 1.1), 0.0),
        ("SafetyCarCircle2-v0", (1.1, -1.2), 1.0),
        ("SafetyPointRun0-v0", (0.6, 10.0), 1.0),
        ("SafetyPointRun0-v0", (-0.6, -5.0), 1.0),
        ("SafetyPointRun0-v0", (0.45, 10.0), 0.0),
        ("SafetyCarRun0-v0", (-0.45, 16.5), 0.0),
        ("SafetyCarRun0-v0", (0.55, 16.5), 1.0),
    ],
)
def test_sigwall_crossed(env_id, position, cost):
    env = make_env(env_id, cost_mode="raw")
    place(env, agent=position)
    nxt = idle(env)
    assert nxt["cost_info", "out_of_boundary"].item() == cost
    assert nxt["cost"].item() == cost


def test_circle0_and_walls_do_not_collide():
    # Level 0 costs nothing; a robot standing on a wall line touches nothing and stays at rest.
    nxt = make_env("SafetyPointCircle0-v0", num_envs=2).rollout(20, break_when_any_done=False)["next"]
    assert (nxt["cost"] == 0).all() and list(nxt["cost_info"].keys()) == []
    env = make_env("SafetyPointCircle2-v0")
    place(env, agent=(1.125, 0.0))
    for _ in range(3):
        idle(env)
    assert env.physics.count_contacts(env.task.find(Sigwalls).geom_mask, env.scene.robot_geoms)[0] == 0
    np.testing.assert_allclose(env.scene.agent_xy()[0], (1.125, 0.0), atol=1e-6)


# ---------------------------------------------------------------------------- lidar: Circle range, natural, compass
class TestLidar:
    def test_circle_lidar_range_6(self):
        # The circle's centre 3 m straight behind: 180 degrees (bins 7 and 8), reading (6 - 3) / 6.
        env = make_env("SafetyPointCircle1-v0")
        place(env, agent=(3.0, 0.0))
        expected = np.zeros(16)
        expected[7] = expected[8] = 0.5
        np.testing.assert_allclose(lidar(env, "circle"), expected, atol=1e-9)
        place(env, agent=(-1.0, 0.0))  # 1 m straight ahead: bins 0 and 15, (6 - 1) / 6
        expected = np.zeros(16)
        expected[0] = expected[15] = 5 / 6
        np.testing.assert_allclose(lidar(env, "circle"), expected, atol=1e-9)

    def test_option_sizes(self):
        assert make_env("SafetyPointGoal1-v0", lidar="natural").observation_dim == 60  # same size
        compass = make_env("SafetyPointGoal1-v0", compass=True)
        assert compass.observation_dim == 62
        assert list(compass.observation_slices)[4:] == ["goal_lidar", "goal_comp", "hazards_lidar", "vases_lidar"]
        assert compass.observation_slices["goal_comp"] == slice(28, 30)
        assert make_env("SafetyCarGoal1-v0", lidar="natural", compass=True).observation_dim == 74
        assert make_env("SafetyPointCircle0-v0", compass=True).observation_dim == 28  # nothing goal-like
        with pytest.raises(ValueError, match="lidar"):
            make_env("SafetyPointGoal1-v0", lidar="sonar")

    def test_natural_model_is_separate(self):
        pseudo = make_env("SafetyPointGoal1-v0")
        groups = pseudo.physics.model.geom_group.copy()
        natural = make_env("SafetyPointGoal1-v0", lidar="natural")
        assert natural.physics.model is not pseudo.physics.model
        np.testing.assert_array_equal(pseudo.physics.model.geom_group, groups)
        model = natural.physics.model
        for group, name in enumerate(("goal", "hazards", "vases"), start=1):
            obj = next(o for o in natural.task.objects if o.name == name)
            assert (model.geom_group[obj.geom_mask] == group).all()
        assert (model.geom_group[natural.scene.robot_geoms] == 0).all()

    @pytest.mark.parametrize("robot", ["Point", "Car"])
    def test_natural_sees_hazard_ahead(self, robot):
        # A hazard (radius 0.2) centred 1 m along the heading: ray 0 hits its rim at 0.8 m ->
        # (3 - 0.8) / 3; the rays at +-22.5 degrees pass it (it spans +-11.5 degrees). A vase half-way
        # does not hide it (each group sees only its own geoms); the vase is axis-aligned, so ray 0
        # (at 0.5 rad) meets its face 0.1 / cos(0.5) before its centre.
        env = make_env(f"Safety{robot}Goal1-v0", lidar="natural")
        start, yaw = np.array([0.0, -1.0]), 0.5
        ahead = np.array([np.cos(yaw), np.sin(yaw)])
        arrange(env, agent=start, agent_yaw=yaw, hazards=[start + ahead], vases=[start + 0.5 * ahead])
        expected = np.zeros(16)
        expected[0] = (3 - 0.8) / 3
        np.testing.assert_allclose(lidar(env, "hazards"), expected, atol=1e-9)
        vases = lidar(env, "vases")
        assert vases[0] == pytest.approx((3 - (0.5 - 0.1 / np.cos(yaw))) / 3, abs=1e-6)
        # The pseudo-lidar reads the hazard's centre instead: (3 - 1) / 3 in bins 0 and 15.
        pseudo = make_env(f"Safety{robot}Goal1-v0")
        arrange(pseudo, agent=start, agent_yaw=yaw, hazards=[start + ahead])
        assert lidar(pseudo, "hazards")[[0, 15]] == pytest.approx([2 / 3, 2 / 3])

    def test_natural_sees_the_flat_circle(self):
        # The zone is a 4 mm disc: from its centre every ray leaves it at the rim, 1.5 m -> (6 - 1.5) / 6;
        # from 2.5 m outside facing it, ray 0 meets the rim at 1 m and the rays pointing away see nothing.
        env = make_env("SafetyPointCircle0-v0", lidar="natural")
        place(env, agent=(0.0, 0.0))
        np.testing.assert_allclose(lidar(env, "circle"), np.full(16, 0.75), atol=1e-9)
        place(env, agent=(-2.5, 0.0))
        reading = lidar(env, "circle")
        assert reading[0] == pytest.approx(5 / 6, abs=1e-9)
        assert (reading[4:13] == 0).all()

    def test_natural_follows_a_resampled_goal(self):
        # Reaching the goal moves it mid-step; the observation of that step shows it at its new place,
        # exactly as a world laid out with the goal there from the start.
        env = make_env("SafetyPointGoal0-v0", lidar="natural")
        arrange(env, goal=[(0.2, 0.0)])
        nxt = idle(env)
        assert env.task.goal_met[0]
        new_goal = env.task.find(Goal).positions(env.scene)[0, 0].copy()
        fresh = make_env("SafetyPointGoal0-v0", lidar="natural")
        arrange(fresh, agent=env.scene.agent_xy()[0].copy(), goal=[new_goal])
        part = env.observation_slices["goal_lidar"]
        np.testing.assert_allclose(nxt["observation"][0, part].numpy(), lidar(fresh, "goal"), atol=1e-5)

    @pytest.mark.parametrize("robot", ["Point", "Car"])
    def test_compass_points_at_the_goal(self, robot):
        # Goal 1.5 m away at 60 degrees counter-clockwise from the heading: (cos 60, sin 60) * 1.5 / 1.501.
        env = make_env(f"Safety{robot}Goal1-v0", compass=True)
        start, yaw, angle = np.array([0.2, -0.3]), 0.7, np.pi / 3
        goal = start + 1.5 * np.array([np.cos(yaw + angle), np.sin(yaw + angle)])
        arrange(env, agent=start, agent_yaw=yaw, goal=[goal])
        comp = env._observe()[0, env.observation_slices["goal_comp"]]
        np.testing.assert_allclose(comp, np.array([np.cos(angle), np.sin(angle)]) * 1.5 / 1.501, atol=1e-6)


# ---------------------------------------------------------------------------- seeding
@pytest.mark.parametrize("env_id, options", [
    ("SafetyPointCircle2-v0", {}),
    ("SafetyCarCircle1-v0", {"lidar": "natural"}),
    ("SafetyPointGoal1-v0", {"lidar": "natural", "compass": True}),
])
def test_seeding_n1_equals_n16(env_id, options):
    assert_sim0_same_for_n1_and_n16(env_id, **options)
