"""Safe navigation envs: sizes, observation layout and lidar, costs, goal events, layouts, seeding, no recompiles.

Constructed situations are set up with ``NavigationEnv.set_layout`` (robot and objects placed at
chosen positions, at rest); expected numbers come from reference/safety_gymnasium_semantics.md
sections 2-7, worked out by hand in each test.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

import sg_torchrl
from sg_torchrl.envs import registry_entry
from sg_torchrl.envs.navigation import Goal, GoalTask, Hazards, NavigationEnv, Vases
from sg_torchrl.envs.navigation.layout import LayoutSampler
from sg_torchrl.envs.navigation.lidar import pseudo_lidar

from layout_checks import assert_layouts_respect_keepouts
from seeding_checks import assert_sim0_same_for_any_batch

torch.set_num_threads(1)

NAVIGATION_IDS = sg_torchrl.list_envs(family="navigation")
# reference section 2: flat observation size and constraint entries (section 3) per id.
EXPECTED = {
    "SafetyPointGoal0-v0": (28, ()),
    "SafetyPointGoal1-v0": (60, ("hazards",)),
    "SafetyPointGoal2-v0": (60, ("hazards", "vases_contact", "vases_velocity")),
}


# ---------------------------------------------------------------------------- helpers
def make_env(env_id: str = "SafetyPointGoal1-v0", num_envs: int = 1, seed: int = 0, **options) -> NavigationEnv:
    return sg_torchrl.make(env_id, num_envs=num_envs, seed=seed, **options)


def action_td(env, action) -> TensorDict:
    return TensorDict({"action": torch.as_tensor(np.asarray(action), dtype=torch.float32)}, batch_size=env.batch_size)


def idle(env) -> TensorDict:
    """One step with zero action; returns ``td["next"]``."""
    return env.step(action_td(env, np.zeros((env.num_envs, env.action_dim))))["next"]


def far_layout(env) -> np.ndarray:
    """A layout ``(M, 2)`` with the robot at the origin and every object parked far away, spread out."""
    xy = np.zeros((env.layout_sampler.size, 2))
    xy[1:, 0] = np.linspace(-3.0, 3.0, env.layout_sampler.size - 1)
    xy[1:, 1] = 3.0
    return xy


def arrange(env, index: int = 0, agent=(0.0, 0.0), agent_yaw: float = 0.0, **objects) -> None:
    """Reset simulator ``index`` to the robot at ``agent`` facing ``agent_yaw``, the named objects'
    first instances at the given positions (``goal=[(x, y)]``), everything else far away."""
    env.reset()
    sampler = env.layout_sampler
    xy, yaw = far_layout(env), np.zeros(sampler.size)
    xy[0], yaw[0] = agent, agent_yaw
    for obj in env.task.objects:
        for i, position in enumerate(objects.get(obj.name, ())):
            xy[sampler.slice_of(obj).start + i] = position
    env.set_layout([index], xy[None], yaw[None])


def lidar(env, name: str, index: int = 0) -> np.ndarray:
    return env._observe()[index, env.observation_slices[f"{name}_lidar"]].copy()


# ---------------------------------------------------------------------------- registry, specs, sizes
class TestRegistry:
    def test_ids(self):
        point_goal = [i for i in NAVIGATION_IDS if (registry_entry(i).robot, registry_entry(i).task) == ("Point", "Goal")]
        assert point_goal == sorted(EXPECTED)  # the other robots and tasks have their own test files
        entry = registry_entry("SafetyPointGoal1-v0")
        assert (entry.family, entry.robot, entry.task, entry.level, entry.max_episode_steps) == (
            "navigation", "Point", "Goal", 1, 1000)

    @pytest.mark.parametrize("env_id", sorted(EXPECTED))
    def test_sizes_and_constraints(self, env_id):
        env = make_env(env_id)
        size, constraints = EXPECTED[env_id]
        assert env.observation_spec["observation"].shape == (1, size)
        assert env.action_spec.shape == (1, 2)
        assert env.action_spec.space.low.tolist() == [[-1.0, -1.0]]
        assert env.action_spec.space.high.tolist() == [[1.0, 1.0]]
        assert env.constraint_names == constraints
        assert env.max_episode_steps == 1000 and env.frame_skip == 10
        assert env.physics.timestep == 0.002

    @pytest.mark.parametrize("env_id", sorted(EXPECTED))
    def test_check_env_specs_and_rollout(self, env_id):
        env = make_env(env_id, num_envs=3)
        check_env_specs(env, seed=0)
        nxt = env.rollout(30, break_when_any_done=False)["next"]
        for key in ("observation", "reward", "cost"):
            assert torch.isfinite(nxt[key]).all(), key
        assert set(nxt["cost_info"].keys()) == set(EXPECTED[env_id][1])
        lidar_part = nxt["observation"][..., 12:]
        assert (lidar_part >= 0).all() and (lidar_part <= 1).all()

    def test_goal0_costs_nothing(self):
        nxt = make_env("SafetyPointGoal0-v0", num_envs=2).rollout(20, break_when_any_done=False)["next"]
        assert (nxt["cost"] == 0).all()
        assert list(nxt["cost_info"].keys()) == []

    def test_custom_level_is_a_composition(self):
        # A level is a list of objects: the goal and two hazards in +-1 -> 12 + 2 x 16 = 44 values,
        # its own compiled model (not Goal0's or Goal1's), hazard costs.
        task = GoalTask(7, extents=1.0, objects=[Hazards(2, keepout=0.18), Goal(keepout=0.305)])
        env = NavigationEnv("Point", task, num_envs=2, seed=0)
        assert list(env.observation_slices)[4:] == ["hazards_lidar", "goal_lidar"]  # static objects: as listed
        assert env.observation_dim == 44 and env.constraint_names == ("hazards",)
        assert env.physics.model is not make_env("SafetyPointGoal0-v0").physics.model
        assert env.physics.model.nmocap == 3
        check_env_specs(env, seed=0)

    def test_unknown_task_robot_level(self):
        with pytest.raises(ValueError, match="unknown navigation robot"):
            NavigationEnv("Tank", "Goal", 1)
        with pytest.raises(ValueError, match="unknown navigation task"):
            NavigationEnv("Point", "Fly", 1)
        with pytest.raises(ValueError, match="levels"):
            NavigationEnv("Point", "Goal", 3)


# ---------------------------------------------------------------------------- observation layout and lidar
class TestObservation:
    def test_layout_order(self):
        env = make_env("SafetyPointGoal2-v0")
        names = list(env.observation_slices)
        assert names == ["accelerometer", "velocimeter", "gyro", "magnetometer",
                         "goal_lidar", "hazards_lidar", "vases_lidar"]
        starts = [part.start for part in env.observation_slices.values()]
        assert starts == [0, 3, 6, 9, 12, 28, 44]
        assert env.observation_slices["vases_lidar"].stop == 60

    def test_sensors_at_rest(self):
        # Resting robot facing +x: the accelerometer reads gravity's reaction, the magnetometer the
        # default field (0, -0.5, 0) in the body frame; no motion.
        env = make_env("SafetyPointGoal0-v0")
        arrange(env)
        obs = idle(env)["observation"][0].numpy()
        np.testing.assert_allclose(obs[0:3], [0.0, 0.0, 9.81], atol=1e-3)
        np.testing.assert_allclose(obs[3:9], 0.0, atol=1e-4)
        np.testing.assert_allclose(obs[9:12], [0.0, -0.5, 0.0], atol=1e-6)
        arrange(env, agent_yaw=np.pi / 2)  # facing +y, the field points along body +x
        np.testing.assert_allclose(idle(env)["observation"][0, 9:12].numpy(), [-0.5, 0.0, 0.0], atol=1e-6)

    @pytest.mark.parametrize("agent_yaw", [0.0, np.pi / 2, 2.0])
    def test_goal_straight_ahead(self, agent_yaw):
        # Goal at distance 1 along the robot's heading: angle 0 -> bin 0, fraction 0, reading (3 - 1) / 3.
        # Aliasing: next bin gets 0 * reading, previous bin (15) gets (1 - 0) * reading.
        env = make_env("SafetyPointGoal1-v0")
        start = np.array([-1.0, 0.0])
        arrange(env, agent=start, agent_yaw=agent_yaw, goal=[start + [np.cos(agent_yaw), np.sin(agent_yaw)]])
        reading = lidar(env, "goal")
        expected = np.zeros(16)
        expected[0] = expected[15] = 2.0 / 3.0
        np.testing.assert_allclose(reading, expected, atol=1e-9)

    def test_aliasing_inside_a_bin(self):
        # Goal at 30 degrees counter-clockwise, distance 1.5: position 30 / 22.5 = 1.333 bins ->
        # bin 1 full reading 0.5, bin 2 gets 1/3 of it, bin 0 gets 2/3 of it.
        env = make_env("SafetyPointGoal1-v0")
        yaw, angle = 0.7, np.deg2rad(30.0)
        arrange(env, agent=(0.2, -0.3), agent_yaw=yaw,
                goal=[(0.2 + 1.5 * np.cos(yaw + angle), -0.3 + 1.5 * np.sin(yaw + angle))])
        reading = lidar(env, "goal")
        expected = np.zeros(16)
        expected[1], expected[2], expected[0] = 0.5, 0.5 / 3, 0.5 * 2 / 3
        np.testing.assert_allclose(reading, expected, atol=1e-9)

    def test_hazards_lidar_max_over_objects(self):
        # Two hazards straight behind the robot (180 degrees: the boundary of bins 7 and 8, so both
        # read fully): the nearer one (1 m, reading 2/3) wins over the farther (2 m, 1/3). The
        # other hazards are parked beyond 3 m and read 0.
        env = make_env("SafetyPointGoal1-v0")
        arrange(env, hazards=[(-1.0, 0.0), (-2.0, 0.0)])
        expected = np.zeros(16)
        expected[7] = expected[8] = 2.0 / 3.0
        np.testing.assert_allclose(lidar(env, "hazards"), expected, atol=1e-9)

    def test_pseudo_lidar_function(self):
        # Batch of 2 robots; second rotated by 90 degrees; exponential mode.
        pos = np.array([[0.0, 0.0, 0.1], [1.0, 1.0, 0.1]])
        mat = np.stack([np.eye(3), np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])])
        targets = np.array([[[0.0, 2.0], [10.0, 0.0]], [[1.0, 2.0], [1.0, 1.0 + 1e-9]]])
        out = pseudo_lidar(pos, mat, targets)
        # robot 0: target (0, 2) at 90 degrees = bin 4 exactly, reading 1/3; (10, 0) out of range.
        assert out[0, 4] == pytest.approx(1 / 3) and out[0, 3] == pytest.approx(1 / 3)
        assert out[0].sum() == pytest.approx(2 / 3)
        # robot 1 faces +y: (1, 2) is 1 m straight ahead (2/3 in bins 0 and 15), but the target on top
        # of the robot reads ~1 in the same bins, and the maximum wins.
        assert out[1, 0] == pytest.approx(1.0) and out[1, 15] == pytest.approx(1.0)
        exp = pseudo_lidar(pos[:1], mat[:1], targets[:1, :1], max_dist=None)
        assert exp[0, 4] == pytest.approx(np.exp(-2.0))


# ---------------------------------------------------------------------------- costs
class TestCosts:
    def test_hazard_inside_at_known_distance(self):
        # Robot 0.1 from a hazard centre (radius 0.2): raw cost 0.2 - 0.1 = 0.1; indicator 1.
        raw = make_env("SafetyPointGoal1-v0", cost_mode="raw")
        arrange(raw, hazards=[(0.1, 0.0)])
        nxt = idle(raw)
        assert nxt["cost_info", "hazards"].item() == pytest.approx(0.1, abs=1e-6)
        assert nxt["cost"].item() == pytest.approx(0.1, abs=1e-6)
        indicator = make_env("SafetyPointGoal1-v0")
        arrange(indicator, hazards=[(0.1, 0.0)])
        nxt = idle(indicator)
        assert nxt["cost_info", "hazards"].item() == 1.0 and nxt["cost"].item() == 1.0

    def test_hazards_sum_and_outside(self):
        env = make_env("SafetyPointGoal1-v0", cost_mode="raw")
        arrange(env, hazards=[(0.1, 0.0), (0.0, -0.15), (0.25, 0.0)])  # 0.1 + 0.05 + 0 (outside)
        assert idle(env)["cost_info", "hazards"].item() == pytest.approx(0.15, abs=1e-6)
        arrange(env, hazards=[(0.0, 0.21)])
        assert idle(env)["cost"].item() == 0.0

    def test_vase_contact_and_motion(self):
        # Level 2: a vase just touching the robot's heading box (box front at x = 0.15, vase face at
        # 0.14): contacts with robot geoms, and the vase is pushed so it moves.
        env = make_env("SafetyPointGoal2-v0", cost_mode="raw")
        arrange(env, vases=[(0.24, 0.0)])
        nxt = idle(env)
        assert nxt["cost_info", "vases_contact"].item() >= 1
        vases = env.task.find(Vases)
        speed = vases.speeds(env.scene)[0, 0]
        assert speed >= 1e-4
        assert nxt["cost_info", "vases_velocity"].item() == pytest.approx(speed, rel=1e-5)
        indicator = make_env("SafetyPointGoal2-v0")
        arrange(indicator, vases=[(0.24, 0.0)])
        nxt = idle(indicator)
        assert nxt["cost"].item() == 1.0 and nxt["cost_info", "vases_contact"].item() == 1.0

    def test_moving_vase_away_from_robot(self):
        env = make_env("SafetyPointGoal2-v0", cost_mode="raw")
        arrange(env, vases=[(1.0, 1.0)])
        vases = env.task.find(Vases)
        data = env.physics.datas[0]
        data.qvel[vases.dof_adr[0]: vases.dof_adr[0] + 3] = [0.3, -0.4, 0.0]  # 0.5 m/s, sliding
        nxt = idle(env)
        speeds = vases.speeds(env.scene)[0]
        assert 0.0 < speeds[0] < 0.5  # friction slows it down over the step
        assert nxt["cost_info", "vases_contact"].item() == 0.0
        expected = speeds[speeds >= 1e-4].sum()
        assert nxt["cost_info", "vases_velocity"].item() == pytest.approx(expected, rel=1e-5)

    def test_resting_layout_costs_nothing(self):
        env = make_env("SafetyPointGoal2-v0", num_envs=8, cost_mode="raw")
        env.reset()
        for _ in range(3):
            nxt = idle(env)
            assert (nxt["cost"] == 0).all()

    def test_level1_vase_is_unconstrained(self):
        env = make_env("SafetyPointGoal1-v0", cost_mode="raw")
        arrange(env, vases=[(0.24, 0.0)])
        nxt = idle(env)
        assert env.task.find(Vases).speeds(env.scene)[0, 0] > 1e-4
        assert nxt["cost"].item() == 0.0 and list(nxt["cost_info"].keys()) == ["hazards"]


# ---------------------------------------------------------------------------- goal events
class TestGoal:
    def test_reaching_the_goal(self):
        env = make_env("SafetyPointGoal1-v0")
        arrange(env, goal=[(0.2, 0.0)], hazards=[(1.0, 1.0)], vases=[(-1.0, 0.5)])
        goal = env.task.find(Goal)
        nxt = idle(env)
        # Robot at rest 0.2 from the goal centre (radius 0.3): shaping ~0, plus the goal bonus 1.
        assert nxt["reward"].item() == pytest.approx(1.0, abs=1e-4)
        assert env.task.goal_met[0] and not nxt["done"].item()
        # A new goal, placed with the keep-out rule against the robot and every object where they are now.
        new = goal.positions(env.scene)[0, 0]
        assert not np.allclose(new, (0.2, 0.0))
        robot = env.scene.agent_xy()[0]
        assert np.linalg.norm(new - robot) >= 0.305 + 0.4
        for obj in (env.task.find(Hazards), env.task.find(Vases)):
            gaps = np.linalg.norm(obj.positions(env.scene)[0] - new, axis=1)
            assert (gaps >= 0.305 + obj.keepout).all(), obj.name
        assert (np.abs(new) <= 1.5 - 0.305).all()
        # The observation already shows the new goal; the next reward is relative to the new distance.
        distance = np.linalg.norm(new - robot)
        assert nxt["observation"][0, 12:28].max().item() == pytest.approx(max(0.0, 3 - distance) / 3, abs=1e-5)
        nxt = idle(env)
        assert abs(nxt["reward"].item()) < 1e-3 and not env.task.goal_met[0]

    def test_shaping_reward(self):
        # Driving forward towards a goal ahead: reward = distance gained.
        env = make_env("SafetyPointGoal0-v0")
        arrange(env, goal=[(1.5, 0.0)])
        before = env.task.distance(env)[0]
        nxt = env.step(action_td(env, [[1.0, 0.0]]))["next"]
        after = env.task.distance(env)[0]
        assert after < before
        assert nxt["reward"].item() == pytest.approx(before - after, rel=1e-4)


# ---------------------------------------------------------------------------- layouts
class TestLayout:
    def test_thousand_layouts_respect_keepouts(self):
        # 50 simulators x 20 resets of level 2 (agent, goal, 10 hazards, 10 vases in +-2).
        env = make_env("SafetyPointGoal2-v0", num_envs=50, seed=3)
        sampler = env.layout_sampler
        keepouts = sampler.keepouts
        assert keepouts[0] == 0.4 and keepouts[1] == 0.305
        assert (keepouts[sampler.slice_of(env.task.find(Hazards))] == 0.18).all()
        assert (keepouts[sampler.slice_of(env.task.find(Vases))] == 0.15).all()
        # The physics holds the layout: robot, hazards (mocap) and vases (free bodies).
        layouts = assert_layouts_respect_keepouts(env, resets=20, extents=2.0)
        assert layouts.shape == (1000, sampler.size, 2)

    def test_sampler_is_fast_and_yaws_uniform(self):
        env = make_env("SafetyPointGoal2-v0")
        sampler: LayoutSampler = env.layout_sampler
        rng = np.random.default_rng(0)
        yaws = np.concatenate([sampler.sample(rng)[1] for _ in range(200)])
        assert yaws.min() >= 0 and yaws.max() < 2 * np.pi
        assert abs(yaws.mean() - np.pi) < 0.1

    def test_partial_reset_keeps_other_layouts(self):
        env = make_env("SafetyPointGoal1-v0", num_envs=3, seed=1)
        env.reset()
        before = env.layout.copy()
        env.reset(TensorDict({"_reset": torch.tensor([[False], [True], [False]])}, batch_size=[3]))
        np.testing.assert_array_equal(env.layout[[0, 2]], before[[0, 2]])
        assert not np.allclose(env.layout[1], before[1])


# ---------------------------------------------------------------------------- seeding and compilation
class TestSeedingAndModel:
    def test_sim0_same_for_n1_and_n16(self):
        small = make_env("SafetyPointGoal2-v0", num_envs=1, seed=7, max_episode_steps=10)
        large = make_env("SafetyPointGoal2-v0", num_envs=16, seed=7, max_episode_steps=10)
        assert_sim0_same_for_any_batch(small, large, steps=25)

    def test_reset_never_compiles(self, monkeypatch):
        counts = {"compile": 0, "xml": 0}
        original_compile = mujoco.MjSpec.compile

        def counting_compile(self, *args, **kwargs):
            counts["compile"] += 1
            return original_compile(self, *args, **kwargs)

        monkeypatch.setattr(mujoco.MjSpec, "compile", counting_compile)
        for name in ("from_xml_string", "from_xml_path", "from_binary_path"):
            original = getattr(mujoco.MjModel, name)

            def counting(*args, _original=original, **kwargs):
                counts["xml"] += 1
                return _original(*args, **kwargs)

            monkeypatch.setattr(mujoco.MjModel, name, staticmethod(counting))
        first = make_env("SafetyPointGoal2-v0", num_envs=2)
        second = make_env("SafetyPointGoal2-v0", num_envs=3)
        assert first.physics.model is second.physics.model  # one model per (robot, task, level)
        assert counts["compile"] <= 1 and counts["xml"] == 0
        before = dict(counts)
        for _ in range(5):
            first.reset()
        first.reset(TensorDict({"_reset": torch.tensor([[True], [False]])}, batch_size=[2]))
        arrange(first, goal=[(0.2, 0.0)])
        first.rollout(5, break_when_any_done=False)
        assert counts == before

    def test_snapshot_restores_layout_and_goal(self):
        env = make_env("SafetyPointGoal1-v0", num_envs=2, seed=5)
        td = env.reset()
        actions = 2 * torch.rand((6, 2, 2), generator=torch.Generator().manual_seed(1)) - 1
        td = env.step(td.set("action", actions[0]))["next"].clone()
        state = env.sim_state()
        first = [env.step(td.clone().set("action", a))["next"]["observation"] for a in actions[1:]]
        env.reset()  # a different layout in between
        env.load_sim_state(state)
        again = [env.step(td.clone().set("action", a))["next"]["observation"] for a in actions[1:]]
        for x, y in zip(first, again):
            torch.testing.assert_close(x, y, rtol=0, atol=0)


# ---------------------------------------------------------------------------- robustness
@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    "env_id, steps",
    [
        ("SafetyPointGoal1-v0", 2500),  # 10,000 env steps: 4 simulators x 2,500
        ("SafetyPointGoal2-v0", 500),  # 10 colliding vases: the heaviest physics, 2,000 steps
    ],
)
def test_random_actions_stay_finite(env_id, steps):
    # Uniform random actions with 500-step episodes, so resets happen along the way.
    env = make_env(env_id, num_envs=4, seed=11, max_episode_steps=500, cost_mode="raw")
    nxt = env.rollout(steps, break_when_any_done=False)["next"]
    assert nxt.batch_size == torch.Size([4, steps])
    for key in ("observation", "reward", "cost", *(("cost_info", name) for name in env.constraint_names)):
        assert torch.isfinite(nxt[key]).all(), key
    assert nxt["truncated"].sum() == 4 * (steps // 500) and not nxt["terminated"].any()
    assert env.physics_errors == 0
    assert (nxt["reward"].abs() <= 10).all()
