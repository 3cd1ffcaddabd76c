"""Multi-agent navigation (Safety-Gymnasium's MultiGoal): two robots in one world, each with its own goal and costs.

Checks the six ids' specs and sizes, that each agent's reward follows its own goal and each agent's costs
are its own (scripted layouts), that a reached goal moves that agent's goal only, per-agent lidar frames,
seeding across batch sizes, keep-outs for both robots, long random runs, the Ant's death rule, resets
without recompiling, the joint single-agent view of the same world, and the PettingZoo façade.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

import sg_torchrl
import sg_torchrl.pettingzoo as sg_pz
from layout_checks import assert_layouts_respect_keepouts
from sg_torchrl.envs.multi_agent import MultiAgentNavigationEnv
from sg_torchrl.envs.navigation import Hazards, NavigationEnv, Vases
from test_registry import MULTI_GOAL_SIZES

torch.set_num_threads(1)

IDS = sg_torchrl.list_envs(family="multi_agent_navigation")


# ---------------------------------------------------------------------------- helpers
def make_env(env_id: str = "SafetyPointMultiGoal1-v0", num_envs: int = 1, seed: int = 0, **options):
    env = sg_torchrl.make(env_id, num_envs=num_envs, seed=seed, **options)
    env.reset()
    return env


def scripted_layout(env, agents, goals=(), items=None):
    """Put simulator 0 in a layout: ``agents`` ``[(x, y, yaw), ...]``, ``goals`` ``[(x, y), ...]`` (red, blue),
    ``items`` ``{layout item: (x, y)}``; every other item parked on two far rows."""
    sampler = env.layout_sampler
    xy = np.stack([(-3.0 + 0.5 * (k // 2), 3.2 if k % 2 else -3.2) for k in range(sampler.size)])
    yaw = np.zeros(sampler.size)
    for item, (x, y, heading) in enumerate(agents):
        xy[item], yaw[item] = (x, y), heading
    for goal, where in zip(env.task.goals, goals):
        xy[sampler.slice_of(goal).start] = where
    for item, where in (items or {}).items():
        xy[item] = where
    env.set_layout([0], xy[None], yaw[None])


def step(env, action) -> TensorDict:
    """One step with the group action ``(N, A, Da)``; returns the ``"next"`` TensorDict."""
    td = TensorDict({("agents", "action"): torch.as_tensor(np.asarray(action), dtype=torch.float32)},
                    batch_size=env.batch_size)
    return env.step(td)["next"]


def item_of(env, obj, instance: int = 0) -> int:
    return env.layout_sampler.slice_of(obj).start + instance


# ---------------------------------------------------------------------------- specs and sizes
def test_six_ids():
    assert IDS == sorted(MULTI_GOAL_SIZES)


@pytest.mark.parametrize("env_id", IDS)
def test_specs_and_sizes(env_id):
    env = make_env(env_id, num_envs=3)
    check_env_specs(env, seed=0)
    agents, state = MULTI_GOAL_SIZES[env_id]
    assert env.agent_names == ["agent_0", "agent_1"] and env.group_map == {"agents": ["agent_0", "agent_1"]}
    assert list(zip(env.observation_sizes, env.action_sizes)) == agents and env.state_dim == state
    assert env.observation_spec["agents", "observation"].shape == (3, 2, agents[0][0])
    assert env.full_action_spec["agents", "action"].shape == (3, 2, agents[0][1])
    assert env.reward_key == ("agents", "reward") and env.action_key == ("agents", "action")
    level = int(env_id[-4])
    expected = {0: (), 1: ("hazards", "contact_other"),
                2: ("hazards", "vases_contact", "vases_velocity", "contact_other")}[level]
    assert env.constraint_names == expected
    assert set(env.observation_spec["agents", "cost_info"].keys()) == set(expected)
    # Both robots in the world, under their prefixes; their actuators split between the agents.
    model = env.physics.model
    assert model.body("agent_0/agent").id > 0 and model.body("agent_1/agent").id > 0
    assert sorted(np.concatenate([robot.actuator_ids for robot in env.robots]).tolist()) == list(range(model.nu))


def test_own_view_is_each_robots_part_of_the_joint_vector():
    env = make_env("SafetyPointMultiGoal1-v0", num_envs=2, agent_view="own")
    assert env.observation_sizes == (76, 76) and env.state_dim == 152  # 12 sensors + 4 lidars, both robots 152
    nxt = step(env, np.zeros((2, 2, 2)))
    state, observation = nxt["state"].numpy(), nxt["agents", "observation"].numpy()
    own = [np.r_[0:12, 24:88], np.r_[12:24, 88:152]]  # sensors 0, sensors 1, lidars of robot 0, lidars of robot 1
    for agent, columns in enumerate(own):
        np.testing.assert_array_equal(observation[:, agent], state[:, columns])
    slices = env.observation_slices
    assert slices["agent_1/accelerometer"] == slice(12, 15) and slices["agent_0/goal_red_lidar"] == slice(24, 40)
    assert slices["agent_1/vases_lidar"] == slice(136, 152)
    with pytest.raises(ValueError, match="agent_view"):
        MultiAgentNavigationEnv("Point", "MultiGoal", 1, agent_view="mine")


def test_lidar_is_seen_from_each_robots_frame():
    env = make_env("SafetyPointMultiGoal0-v0")
    # Robot 0 at the origin facing +x, robot 1 at (0, 1) facing +y; goal_blue at (0, 2), goal_red at (2, 0).
    scripted_layout(env, [(0.0, 0.0, 0.0), (0.0, 1.0, np.pi / 2)], goals=[(2.0, 0.0), (0.0, 2.0)])
    obs, slices = env._observe()[0], env.observation_slices
    ahead_of_1 = obs[slices["agent_1/goal_blue_lidar"]]  # 1 m straight ahead of robot 1: bin 0 (or 15)
    assert ahead_of_1.max() == pytest.approx(2 / 3) and ahead_of_1.argmax() in (0, 15)
    left_of_0 = obs[slices["agent_0/goal_blue_lidar"]]  # 2 m to the left of robot 0: bin 4 (or 3)
    assert left_of_0.max() == pytest.approx(1 / 3) and left_of_0.argmax() in (3, 4)
    ahead_of_0 = obs[slices["agent_0/goal_red_lidar"]]  # 2 m ahead of robot 0
    assert ahead_of_0.max() == pytest.approx(1 / 3) and ahead_of_0.argmax() in (0, 15)
    right_of_1 = obs[slices["agent_1/goal_red_lidar"]]  # (2, -1) from robot 1: to its right, sqrt(5) m away
    assert right_of_1.max() == pytest.approx((3 - np.sqrt(5)) / 3) and 9 <= right_of_1.argmax() <= 13


# ---------------------------------------------------------------------------- rewards
@pytest.mark.parametrize("mover", [0, 1])
def test_each_agents_reward_follows_its_own_goal(mover):
    env = make_env("SafetyPointMultiGoal0-v0")
    # Each robot 1.6 m behind its goal, facing it; only `mover` drives forward.
    scripted_layout(env, [(-0.8, -0.5, 0.0), (-0.8, 0.5, 0.0)], goals=[(0.8, -0.5), (0.8, 0.5)])
    action = np.zeros((1, 2, 2))
    action[0, mover, 0] = 1.0
    rewards = np.stack([step(env, action)["agents", "reward"][0, :, 0].numpy() for _ in range(15)])
    still = 1 - mover
    assert (rewards[:, mover] > 0).all()
    np.testing.assert_allclose(rewards[:, still], 0.0, atol=1e-9)
    # The mover's rewards telescope to its progress towards its own goal.
    distance = env.task.distance(env)[0]
    assert distance[still] == pytest.approx(1.6)
    assert rewards[:, mover].sum() == pytest.approx(1.6 - distance[mover], abs=1e-5)


def test_reached_goal_moves_that_agents_goal_only():
    env = make_env("SafetyPointMultiGoal1-v0")
    red, blue = env.task.goals
    scripted_layout(env, [(0.0, 0.0, 0.0), (-1.0, 1.0, 0.0)], goals=[(0.0, 0.0), (1.0, 1.0)])
    blue_before = blue.positions(env.scene)[0, 0].copy()
    lidar = env.observation_slices["agent_0/goal_red_lidar"]
    nxt = step(env, np.zeros((1, 2, 2)))
    assert env.task.goal_met[0].tolist() == [True, False]
    reward = nxt["agents", "reward"][0, :, 0]
    assert reward[0].item() == pytest.approx(1.0, abs=1e-3) and abs(reward[1].item()) < 1e-9
    assert not nxt["done"].any()  # the episode goes on
    red_now = red.positions(env.scene)[0, 0]
    assert np.linalg.norm(red_now) > 0.7  # moved away from robot 0
    np.testing.assert_array_equal(blue.positions(env.scene)[0, 0], blue_before)
    # The new goal keeps out of both robots and the other goal; the observation already shows it.
    robots = np.stack([view.agent_xy()[0] for view in env.scene.views])
    assert (np.linalg.norm(robots - red_now, axis=1) >= 0.4 + 0.305).all()
    assert np.linalg.norm(red_now - blue_before) >= 2 * 0.305
    assert nxt["agents", "observation"][0, 0, lidar].max().item() < 0.99
    # Progress restarts from the new goal: no second bonus.
    assert abs(step(env, np.zeros((1, 2, 2)))["agents", "reward"][0, 0].item()) < 1e-3


# ---------------------------------------------------------------------------- costs
@pytest.mark.parametrize("cost_mode", ["indicator", "raw"])
def test_only_the_agent_in_a_hazard_pays(cost_mode):
    env = make_env("SafetyPointMultiGoal1-v0", cost_mode=cost_mode)
    hazard = item_of(env, env.task.find(Hazards))  # hazard0
    scripted_layout(env, [(-0.5, -0.5, 0.0), (0.5, 0.5, 0.0)], goals=[(-1.0, 1.0), (1.0, -1.0)],
                    items={hazard: (0.5, 0.5)})
    nxt = step(env, np.zeros((1, 2, 2)))
    depth = 0.2 if cost_mode == "raw" else 1.0  # the hazard's radius minus the distance (0) to its centre
    np.testing.assert_allclose(nxt["agents", "cost_info", "hazards"][0, :, 0].numpy(), [0.0, depth], atol=1e-6)
    np.testing.assert_allclose(nxt["agents", "cost"][0, :, 0].numpy(), [0.0, depth], atol=1e-6)
    assert nxt["agents", "cost_info", "contact_other"].sum() == 0
    assert nxt["cost"].item() == pytest.approx(depth, abs=1e-6)  # the team: robot 1 paid


def test_touching_robots_both_pay_contact_other():
    env = make_env("SafetyPointMultiGoal1-v0")
    scripted_layout(env, [(0.0, 0.0, 0.0), (0.19, 0.0, np.pi)], goals=[(-1.0, 1.0), (1.0, -1.0)])
    nxt = step(env, np.zeros((1, 2, 2)))
    assert nxt["agents", "cost_info", "contact_other"][0, :, 0].tolist() == [1.0, 1.0]
    assert nxt["agents", "cost"][0, :, 0].tolist() == [1.0, 1.0]
    assert nxt["agents", "cost_info", "hazards"].sum() == 0
    assert make_env("SafetyPointMultiGoal0-v0").constraint_names == ()  # level 0: no constraint at all


def test_vase_costs_go_to_the_robot_that_pushed_it():
    env = make_env("SafetyPointMultiGoal2-v0", cost_mode="raw")
    vases = env.task.find(Vases)
    scripted_layout(env, [(-0.3, 0.0, 0.0), (0.0, 1.5, 0.0)], goals=[(-1.5, -1.5), (1.5, -1.5)],
                    items={item_of(env, vases): (0.0, 0.0)})
    action = np.zeros((1, 2, 2))
    action[0, 0, 0] = 1.0  # robot 0 drives into vase0
    costs = [step(env, action)["agents", "cost_info"] for _ in range(40)]
    contact = np.stack([c["vases_contact"][0, :, 0].numpy() for c in costs])
    velocity = np.stack([c["vases_velocity"][0, :, 0].numpy() for c in costs])
    assert contact[:, 0].max() >= 1 and velocity[:, 0].max() > 0
    assert contact[:, 1].max() == 0 and velocity[:, 1].max() == 0
    assert vases.last_toucher[0].tolist() == [0] + [-1] * 9
    env.reset()
    assert (vases.last_toucher == -1).all()  # a new episode: nobody touched anything yet


# ---------------------------------------------------------------------------- layouts, seeding, resets
@pytest.mark.parametrize("env_id, extents", [("SafetyPointMultiGoal2-v0", 2.0), ("SafetyAntMultiGoal1-v0", 1.5)])
def test_layouts_respect_keepouts_for_both_robots(env_id, extents):
    env = make_env(env_id, num_envs=16)
    sampler = env.layout_sampler
    assert sampler.num_agents == 2 and sampler.keepouts[:2].tolist() == [0.4, 0.4]
    layouts = assert_layouts_respect_keepouts(env, resets=8, extents=extents)
    assert np.linalg.norm(layouts[:, 0] - layouts[:, 1], axis=-1).min() >= 0.8
    np.testing.assert_allclose(env.scene.for_robot(1).agent_xy(), env.layout[:, 1], atol=1e-9)


def test_seeding_is_independent_of_batch_size():
    single, batch = make_env("SafetyAntMultiGoal2-v0", 1, seed=7), make_env("SafetyAntMultiGoal2-v0", 16, seed=7)
    np.testing.assert_array_equal(single.layout[0], batch.layout[0])
    np.testing.assert_array_equal(single.physics.qpos()[0], batch.physics.qpos()[0])  # the Ants' spawn noise too
    generator = torch.Generator().manual_seed(0)
    for _ in range(5):
        action = 2 * torch.rand((16, 2, 8), generator=generator) - 1
        one, many = step(single, action[:1]), step(batch, action)
        for key in ("state", ("agents", "reward"), ("agents", "cost"), ("agents", "observation")):
            torch.testing.assert_close(one[key][0], many[key][0], rtol=0, atol=0)
    assert not np.array_equal(batch.layout[1], batch.layout[0])


def test_reset_never_recompiles(monkeypatch):
    env = make_env("SafetyPointMultiGoal2-v0", num_envs=2)

    def no_build(*args, **kwargs):
        raise AssertionError("the world was rebuilt")

    monkeypatch.setattr("sg_torchrl.envs.navigation.env.build_spec", no_build)
    model, layout = env.physics.model, env.layout.copy()
    for _ in range(3):
        env.reset()
    assert env.physics.model is model and not np.array_equal(env.layout, layout)
    assert make_env("SafetyPointMultiGoal2-v0").physics.model is model  # the same id reuses the compiled world


# ---------------------------------------------------------------------------- dynamics
def test_ant_death_ends_the_episode_of_both_agents():
    env = make_env("SafetyAntMultiGoal0-v0")
    scripted_layout(env, [(-0.8, 0.0, 0.0), (0.8, 0.0, 0.0)], goals=[(-0.8, 0.8), (0.8, -0.8)])
    nxt = step(env, np.zeros((1, 2, 8)))
    assert not nxt["done"].any() and not nxt["agents", "terminated"].any()  # both standing
    # Turn robot 1 on its back (torso centre at 0.065 < 0.08: dead, as Safety-Gymnasium's is_alive says).
    qpos, root = env.physics.qpos()[:1].copy(), env.robots[1]._qpos_root
    qpos[0, root + 2], qpos[0, root + 3 : root + 7] = 0.065, (0.0, 1.0, 0.0, 0.0)
    env.physics.reset([0], qpos, np.zeros((1, env.physics.model.nv)), env.physics.gather("mocap_pos")[:1])
    nxt = step(env, np.zeros((1, 2, 8)))
    assert env.scene.for_robot(0).agent_pos()[0, 2] > 0.08 >= env.scene.for_robot(1).agent_pos()[0, 2]
    assert nxt["terminated"].item() and nxt["agents", "terminated"][0, :, 0].tolist() == [True, True]
    assert not nxt["truncated"].any()


def test_random_actions_stay_finite():
    """2,000 steps of random actions: Point level 2 through TorchRL's rollout (autoresets included), the
    Ant level 1 through the numpy step with the same partial resets."""
    env = make_env("SafetyPointMultiGoal2-v0", num_envs=1, max_episode_steps=500)
    rollout = env.rollout(2000, break_when_any_done=False)
    for key in ("state", ("agents", "reward"), ("agents", "cost"), ("agents", "observation")):
        assert torch.isfinite(rollout["next", key]).all(), key
    assert rollout["next", "truncated"].sum() == 4 and env.physics_errors == 0

    ant = make_env("SafetyAntMultiGoal1-v0", num_envs=1, max_episode_steps=1000)
    rng = np.random.default_rng(0)
    done_steps = 0
    for _ in range(2000):
        observation, reward, costs, terminated, truncated = ant._transition_arrays(rng.uniform(-1, 1, (1, 16)))
        assert np.isfinite(observation).all() and np.isfinite(reward).all()
        assert all(np.isfinite(value).all() for value in costs.values())
        if terminated[0] or truncated[0]:
            done_steps += 1
            ant._reset_sims(np.array([0]))
            ant._elapsed[0] = 0
    assert done_steps >= 2 and ant.physics_errors == 0


# ---------------------------------------------------------------------------- other interfaces
def test_single_agent_view_is_the_joint_control_of_the_same_world():
    """NavigationEnv on a multi-agent task: observation = the state, action = both robots', reward = the sum."""
    joint = NavigationEnv("Point", "MultiGoal", 1, num_envs=2, seed=3)
    group = MultiAgentNavigationEnv("Point", "MultiGoal", 1, num_envs=2, seed=3)
    torch.testing.assert_close(joint.reset()["observation"], group.reset()["state"])
    generator = torch.Generator().manual_seed(1)
    for _ in range(10):
        action = 2 * torch.rand((2, 2, 2), generator=generator) - 1
        one = joint.step(TensorDict({"action": action.reshape(2, 4)}, batch_size=[2]))["next"]
        two = step(group, action)
        torch.testing.assert_close(one["observation"], two["state"])
        torch.testing.assert_close(one["reward"], two["agents", "reward"].sum(dim=1))


def test_pettingzoo_facade():
    from pettingzoo.test import parallel_api_test

    parallel_api_test(sg_pz.make("SafetyPointMultiGoal1-v0", cost_in_info=True), num_cycles=30)
    facade = sg_pz.make("SafetyPointMultiGoal1-v0")
    env = make_env("SafetyPointMultiGoal1-v0", seed=5)
    observations, _ = facade.reset(seed=5)
    assert facade.possible_agents == ["agent_0", "agent_1"] and facade.state().shape == (152,)
    assert facade.observation_space("agent_1").shape == (152,) and facade.action_space("agent_0").shape == (2,)
    rng = np.random.default_rng(0)
    for _ in range(20):
        action = rng.uniform(-1, 1, (1, 2, 2)).astype(np.float32)
        observations, rewards, costs, _, _, infos = facade.step({"agent_0": action[0, 0], "agent_1": action[0, 1]})
        nxt = step(env, action)
        for i, agent in enumerate(facade.possible_agents):
            np.testing.assert_array_equal(observations[agent], nxt["agents", "observation"][0, i].numpy())
            assert rewards[agent] == nxt["agents", "reward"][0, i].item()
            assert costs[agent] == infos[agent]["cost_sum"] == nxt["agents", "cost"][0, i].item()
            assert infos[agent]["cost_hazards"] == nxt["agents", "cost_info", "hazards"][0, i].item()
