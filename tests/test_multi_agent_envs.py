"""Multi-agent velocity envs: MaMuJoCo parity, partitions, cost semantics, SafeEnv behaviour, PettingZoo façade.

The MaMuJoCo oracle is gymnasium-robotics 1.4.2 (the ``test`` extra), built with the options that
give the observation layout Safety-Gymnasium 1.0.0 ran on (gymnasium-robotics 1.2 on gymnasium's v4
robots, see :mod:`sg_torchrl.envs.multi_agent.partitions`): it is stepped next to our env from the
same physics state with the same actions, so partitions, per-agent observations, the state, the
reward and the velocity cost are checked against MaMuJoCo itself.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs.utils import check_env_specs

import sg_torchrl
import sg_torchrl.gym as sg_gym
import sg_torchrl.pettingzoo as sg_pz
from sg_torchrl.envs.multi_agent import SCENARIOS, MultiAgentVelocityEnv, Scenario, agent_layout
from sg_torchrl.envs.velocity.robots import ROBOTS, load_model
from test_registry import MULTI_AGENT_SIZES

torch.set_num_threads(1)

IDS = sg_torchrl.list_envs(family="multi_agent_velocity")


# ---------------------------------------------------------------------------- helpers
def make_env(env_id: str = "Safety2x4AntVelocity-v0", num_envs: int = 1, seed: int = 0, **options):
    return sg_torchrl.make(env_id, num_envs=num_envs, seed=seed, **options)


def group_action(env, action) -> TensorDict:
    """An input TensorDict holding the group action (array-like ``(N, A, Da)``)."""
    return TensorDict({("agents", "action"): torch.as_tensor(np.asarray(action), dtype=torch.float32)},
                      batch_size=env.batch_size)


def action_bounds(env) -> tuple[torch.Tensor, torch.Tensor]:
    """``(low, high)`` of the group action, ``(N, A, Da)`` each."""
    box = env.full_action_spec["agents", "action"].space
    return box.low, box.high


def random_actions(env, steps: int, seed: int) -> torch.Tensor:
    """``(steps, N, A, Da)`` actions uniform in the action bounds."""
    generator = torch.Generator().manual_seed(seed)
    low, high = action_bounds(env)
    return low + (high - low) * torch.rand((steps, *low.shape), generator=generator)


def place(env, index: int, qpos: np.ndarray | None = None, qvel: np.ndarray | None = None) -> None:
    """Put simulator ``index`` in the given joint state (defaults: the rest pose, at rest)."""
    model = env.physics.model
    qpos = model.qpos0 if qpos is None else qpos
    qvel = np.zeros(model.nv) if qvel is None else qvel
    env.physics.reset([index], qpos[None], qvel[None])


def mamujoco(scenario: str, conf: str):
    """gymnasium-robotics 1.4.2's MaMuJoCo with the options of Safety-Gymnasium 1.0.0's layout (1.2, v4 robots)."""
    gymnasium = pytest.importorskip("gymnasium")
    pytest.importorskip("gymnasium_robotics")
    from gymnasium_robotics.envs.multiagent_mujoco.mujoco_multi import MultiAgentMujocoEnv
    from gymnasium_robotics.envs.multiagent_mujoco.obsk import Node as MaNode
    from gymnasium_robotics.envs.multiagent_mujoco.obsk import get_parts_and_edges

    parts, edges, global_nodes = get_parts_and_edges(scenario, conf)
    local_categories = global_categories = None
    if scenario == "Ant":  # 1.2 on Ant-v4: no contact forces in the local observations
        local_categories = [["qpos", "qvel"], ["qpos"]]
    if scenario == "Humanoid":  # 1.2: the torso also reports qfrc_actuator[:6], all fields are global categories
        global_nodes = [MaNode("root", None, None, None, extra_obs={
            "qpos": lambda data: data.qpos[2:7], "qvel": lambda data: data.qvel[:6],
            "qfrc_actuator": lambda data: data.qfrc_actuator[:6]})]
        global_categories = ("qpos", "qvel", "cinert", "cvel", "qfrc_actuator", "cfrc_ext")
    if scenario == "Walker2d":  # 1.2's global nodes [root_x, root_x, root_z]
        global_nodes = [global_nodes[0], global_nodes[0], global_nodes[1]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # v4 deprecation notices
        robot = gymnasium.make(f"{scenario}-v4")
    return MultiAgentMujocoEnv(
        scenario, conf, agent_obsk=1,
        agent_factorization={"partition": parts, "edges": edges, "globals": global_nodes},
        local_categories=local_categories, global_categories=global_categories, gym_env=robot,
    )


# ---------------------------------------------------------------------------- specs and sizes
@pytest.mark.parametrize("env_id", IDS)
class TestSpecs:
    def test_check_env_specs(self, env_id):
        env = make_env(env_id, num_envs=3)
        check_env_specs(env, seed=0)
        assert isinstance(env, MultiAgentVelocityEnv)

    def test_layout(self, env_id):
        env = make_env(env_id, num_envs=2)
        agents, state_dim, threshold = MULTI_AGENT_SIZES[env_id]
        count, width, act_width = len(agents), max(o for o, _ in agents), max(a for _, a in agents)
        assert list(zip(env.observation_sizes, env.action_sizes)) == agents
        assert (env.state_dim, env.velocity_threshold, env.num_agents) == (state_dim, threshold, count)
        assert env.group_map == {"agents": [f"agent_{i}" for i in range(count)]}
        assert env.reward_key == ("agents", "reward") and env.action_key == ("agents", "action")
        assert set(env.done_keys) == {"done", "terminated", "truncated", ("agents", "done"),
                                      ("agents", "terminated"), ("agents", "truncated")}
        td = env.reset()
        td = env.step(td.set(("agents", "action"), random_actions(env, 1, seed=0)[0]))
        nxt = td["next"]
        assert nxt["agents"].batch_size == (2, count)
        expected = {("agents", "observation"): ((2, count, width), torch.float32),
                    ("agents", "observation_mask"): ((2, count, width), torch.bool),
                    ("agents", "reward"): ((2, count, 1), torch.float32),
                    ("agents", "cost"): ((2, count, 1), torch.float32),
                    ("agents", "done"): ((2, count, 1), torch.bool),
                    "state": ((2, state_dim), torch.float32), "cost": ((2, 1), torch.float32)}
        for key, (shape, dtype) in expected.items():
            assert (nxt[key].shape, nxt[key].dtype) == (shape, dtype), key
        assert td["agents", "action"].shape == (2, count, act_width)
        # Padding: the mask marks the true sizes, padded entries are 0.
        sizes = torch.tensor(env.observation_sizes)
        torch.testing.assert_close(nxt["agents", "observation_mask"][0].sum(-1), sizes)
        assert (nxt["agents", "observation"][~nxt["agents", "observation_mask"]] == 0).all()


def test_heterogeneous_padding():
    env = make_env("Safety9|8HumanoidVelocity-v0", num_envs=1)
    assert env.observation_sizes == (248, 176) and env.action_sizes == (9, 8)
    mask = env.layout.observation_mask
    assert mask[0].all() and mask[1, :176].all() and not mask[1, 176:].any()
    assert env.layout.action_actuators[1, 8] == -1  # agent_1's ninth action slot drives nothing
    # The padding slot's bounds are a real control range (a squashing policy needs low < high).
    low, high = action_bounds(env)
    assert (low[0, 1, 8].item(), high[0, 1, 8].item()) == pytest.approx((-0.4, 0.4))


# ---------------------------------------------------------------------------- partitions
@pytest.mark.parametrize("env_id", IDS)
class TestPartition:
    def test_every_actuator_belongs_to_exactly_one_agent(self, env_id):
        layout = make_env(env_id).layout
        actuators = layout.action_actuators[layout.action_actuators >= 0]
        nu = make_env(env_id).physics.model.nu
        assert sorted(actuators.tolist()) == list(range(nu))
        assert [int((row >= 0).sum()) for row in layout.action_actuators] == list(layout.action_sizes)

    def test_matches_mamujoco_partition(self, env_id):
        env = make_env(env_id)
        reference = mamujoco(env.scenario.robot, env.agent_conf)
        assert reference.possible_agents == env.agent_names
        for agent, row in zip(reference.agent_action_partitions, env.layout.action_actuators):
            assert [node.act_ids for node in agent] == row[row >= 0].tolist()
        # Both map a group action to the same robot control.
        actions = random_actions(env, 1, seed=4)[0]
        local = {name: actions[0, i, :size].double().numpy()
                 for i, (name, size) in enumerate(zip(env.agent_names, env.action_sizes))}
        expected = reference.map_local_actions_to_global_action(local)[None]
        np.testing.assert_array_equal(env.robot_control(actions), expected)
        reference.close()


def test_partition_must_cover_each_actuator_once():
    cheetah = SCENARIOS["HalfCheetah"]
    model, robot = load_model(ROBOTS["HalfCheetah"].xml_file), ROBOTS["HalfCheetah"]
    twice = Scenario(robot="HalfCheetah", nodes=cheetah.nodes, edges=cheetah.edges, globals=cheetah.globals,
                     partitions={"bad": (("bthigh", "bshin"), ("bshin", "bfoot", "fthigh", "fshin", "ffoot"))},
                     thresholds={"bad": 1.0})
    with pytest.raises(ValueError, match="exactly one agent"):
        agent_layout(twice, "bad", robot, model)
    missing = Scenario(robot="HalfCheetah", nodes=cheetah.nodes, edges=cheetah.edges, globals=cheetah.globals,
                       partitions={"bad": (("bthigh",), ("bshin",))}, thresholds={"bad": 1.0})
    with pytest.raises(ValueError, match="exactly one agent"):
        agent_layout(missing, "bad", robot, model)
    with pytest.raises(ValueError, match="unknown node labels"):
        Scenario(robot="HalfCheetah", nodes=cheetah.nodes, edges=(("nope", "bshin"),), globals=(),
                 partitions={}, thresholds={})
    with pytest.raises(ValueError, match="configurations"):
        MultiAgentVelocityEnv("Ant", "8x1")


# ---------------------------------------------------------------------------- MaMuJoCo oracle
@pytest.mark.parametrize("env_id", IDS)
def test_observations_match_mamujoco(env_id):
    """Per-agent observations, state, reward, termination and cost equal MaMuJoCo's, step by step."""
    env = make_env(env_id)
    reference = mamujoco(env.scenario.robot, env.agent_conf)
    first, _ = reference.reset(seed=3)
    env.reset()
    data = reference.single_agent_env.unwrapped.data
    place(env, 0, data.qpos.copy(), data.qvel.copy())
    actions = random_actions(env, 30, seed=1)
    for t in range(30):
        local = {name: actions[t, 0, i, :size].double().numpy()
                 for i, (name, size) in enumerate(zip(env.agent_names, env.action_sizes))}
        observations, rewards, terminations, _, infos = reference.step(local)
        nxt = env.step(group_action(env, actions[t]))["next"]
        for i, name in enumerate(env.agent_names):
            ours = nxt["agents", "observation"][0, i, : env.observation_sizes[i]].numpy()
            assert ours.shape == observations[name].shape
            np.testing.assert_allclose(ours, observations[name], rtol=1e-5, atol=1e-5, err_msg=f"{name}, step {t}")
        np.testing.assert_allclose(nxt["state"][0].numpy(), reference.state(), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(nxt["agents", "reward"][0, :, 0].numpy(), rewards["agent_0"], rtol=1e-5, atol=1e-5)
        assert nxt["terminated"].item() == terminations["agent_0"]
        # Safety-Gymnasium's make_ma: hypot of the info velocities (a missing y reads 0), Swimmer x only.
        info = infos["agent_0"]
        speed = np.hypot(info["x_velocity"], info.get("y_velocity", 0.0))
        if env.scenario.robot == "Swimmer":
            speed = info["x_velocity"]
        np.testing.assert_allclose(env.last_velocity[0], speed, rtol=1e-6, atol=1e-8)
        assert (nxt["agents", "cost"] == float(speed > env.velocity_threshold)).all()
        if terminations["agent_0"]:
            break
    reference.close()
    assert t >= 9, f"only {t + 1} steps compared"


# ---------------------------------------------------------------------------- cost semantics
class TestCost:
    @staticmethod
    def step_from(env_id: str, qvel_entries: dict[int, float]):
        """One zero-action step from the rest pose with the given root velocities: (measured velocity, next td)."""
        env = make_env(env_id)
        env.reset()
        qvel = np.zeros(env.physics.model.nv)
        for index, value in qvel_entries.items():
            qvel[index] = value
        place(env, 0, qvel=qvel)
        nxt = env.step(group_action(env, np.zeros(action_bounds(env)[0].shape)))["next"]
        return env, float(env.last_velocity[0]), nxt

    @pytest.mark.parametrize("env_id", IDS)
    @pytest.mark.parametrize("factor", [3.0, 0.3, -3.0])
    def test_every_agent_pays_exactly_when_too_fast(self, env_id, factor):
        threshold = MULTI_AGENT_SIZES[env_id][2]
        env, speed, nxt = self.step_from(env_id, {0: factor * threshold})  # qvel[0]: the root's x velocity
        expected = float(speed > threshold)
        assert nxt["agents", "cost"].flatten().tolist() == [expected] * env.num_agents
        assert nxt["cost"].item() == nxt["cost_info", "velocity"].item() == expected
        swimmer = env.scenario.robot == "Swimmer"
        if factor == 3.0:
            assert expected == 1.0
        elif factor == 0.3:
            assert expected == 0.0
        else:  # running backwards: the speed counts (|vx|, planar speed), except the Swimmer's signed x velocity
            assert expected == (0.0 if swimmer else 1.0)

    @pytest.mark.parametrize("env_id", ["Safety2x4AntVelocity-v0", "Safety9|8HumanoidVelocity-v0"])
    def test_sideways_motion_costs(self, env_id):
        threshold = MULTI_AGENT_SIZES[env_id][2]
        env, speed, nxt = self.step_from(env_id, {1: 3 * threshold})  # free joint: qvel[1] is the y velocity
        assert speed > threshold and (nxt["agents", "cost"] == 1.0).all()


# ---------------------------------------------------------------------------- SafeEnv behaviour
def run_sim0(env, actions: torch.Tensor, steps: int) -> list[TensorDict]:
    """Step with ``step_and_maybe_reset``; per step, simulator 0's transition and next root td."""
    out = []
    td = env.reset()
    for t in range(steps):
        td.set(("agents", "action"), actions[t, : env.num_envs])
        stepped, td = env.step_and_maybe_reset(td)
        out.append(TensorDict({"step": stepped[0].clone(), "root": td[0].clone()}))
    return out


@pytest.mark.parametrize("env_id", ["Safety2x3HalfCheetahVelocity-v0", "Safety3x1HopperVelocity-v0"])
def test_simulator_zero_independent_of_batch_size(env_id):
    steps = 12  # with 5-step episodes: two auto-resets of simulator 0
    small = make_env(env_id, num_envs=1, seed=11, max_episode_steps=5)
    large = make_env(env_id, num_envs=16, seed=11, max_episode_steps=5)
    actions = random_actions(large, steps, seed=3)
    a, b = run_sim0(small, actions, steps), run_sim0(large, actions, steps)
    for t, (x, y) in enumerate(zip(a, b)):
        assert set(x.keys(True, True)) == set(y.keys(True, True))
        for key in x.keys(True, True):
            torch.testing.assert_close(x[key], y[key], rtol=0, atol=0, msg=f"{key} differs at step {t}")
    assert a[4]["step", "next", "truncated"].item() and a[4]["step", "next", "agents", "truncated"].all()


class TestPartialReset:
    @pytest.mark.parametrize("mask_key", ["_reset", ("agents", "_reset")])
    def test_only_masked_simulators_reset(self, mask_key):
        env = make_env("Safety2x4AntVelocity-v0", num_envs=4, seed=2)
        td = env.reset()
        for action in random_actions(env, 3, seed=0):
            td = env.step(td.set(("agents", "action"), action))["next"].clone()
        qpos_before = env.physics.qpos().copy()
        mask = torch.tensor([True, False, True, False])
        flags = mask[:, None] if mask_key == "_reset" else mask[:, None, None].expand(4, 2, 1).clone()
        out = env.reset(td.clone().set(mask_key, flags))
        keep = (~mask).numpy()
        np.testing.assert_array_equal(env.physics.qpos()[keep], qpos_before[keep])
        assert not np.allclose(env.physics.qpos()[mask.numpy()], qpos_before[mask.numpy()])
        for key in (("agents", "observation"), "state"):
            torch.testing.assert_close(out[key][~mask], td[key][~mask], rtol=0, atol=0)
        assert env._elapsed.tolist() == [0, 3, 0, 3]
        assert not out["done"].any() and not out["agents", "done"].any()
        assert "_reset" not in out.keys() and ("agents", "_reset") not in out.keys(True)
        assert out["agents"].batch_size == (4, 2)

    def test_terminated_robot_resets_in_step_and_maybe_reset(self):
        env = make_env("Safety2x3Walker2dVelocity-v0", num_envs=3, seed=0)
        td = env.reset()
        place(env, 1, qpos=env.physics.model.qpos0 + np.r_[0.0, -0.9, np.zeros(7)])  # torso on the ground
        stepped, td = env.step_and_maybe_reset(td.set(("agents", "action"), torch.zeros(3, 2, 3)))
        assert stepped["next", "terminated"].squeeze(-1).tolist() == [False, True, False]
        assert stepped["next", "agents", "terminated"][1].all()
        assert env._elapsed.tolist() == [1, 0, 1] and not td["agents", "done"].any()


class TestBadInput:
    def test_wrong_action_shape(self):
        env = make_env(num_envs=2)
        env.reset()
        with pytest.raises(ValueError, match=r"expected \(2, 2, 4\)"):
            env.step(group_action(env, np.zeros((2, 8))))

    def test_nan_action_names_simulator_and_agent(self):
        env = make_env("Safety4x2AntVelocity-v0", num_envs=3)
        env.reset()
        action = np.zeros((3, 4, 2))
        action[1, 2, 0] = np.nan
        with pytest.raises(ValueError, match=r"\(1, 'agent_2'\)"):
            env.step(group_action(env, action))

    def test_padding_slots_are_ignored(self):
        env, twin = make_env("Safety9|8HumanoidVelocity-v0", seed=1), make_env("Safety9|8HumanoidVelocity-v0", seed=1)
        env.reset(), twin.reset()
        action = random_actions(env, 1, seed=0)[0]
        padded = action.clone()
        padded[0, 1, 8] = float("nan")  # agent_1 has 8 actuators: slot 8 is padding
        out, ref = env.step(group_action(env, padded))["next"], twin.step(group_action(twin, action))["next"]
        for key in (("agents", "observation"), ("agents", "reward"), "state"):
            torch.testing.assert_close(out[key], ref[key], rtol=0, atol=0)


def test_diverged_simulator_is_truncated_and_reset():
    env, twin = make_env(num_envs=3, seed=4), make_env(num_envs=3, seed=4)
    actions = random_actions(env, 5, seed=2)
    td, td_twin = env.reset(), twin.reset()
    for t in range(5):
        if t == 2:
            env.physics.datas[1].qvel[:] = np.nan
        out = env.step(td.set(("agents", "action"), actions[t]))["next"]
        ref = twin.step(td_twin.set(("agents", "action"), actions[t]))["next"]
        if t == 2:
            assert out["truncated"].squeeze(-1).tolist() == [False, True, False]
            assert out["agents", "truncated"][1].all() and (out["agents", "reward"][1] == 0).all()
            assert (out["agents", "observation"][1] == 0).all() and (out["state"][1] == 0).all()
        for key in (("agents", "observation"), ("agents", "reward"), ("agents", "cost"), "state"):
            assert torch.isfinite(out[key]).all(), key
            torch.testing.assert_close(out[key][[0, 2]], ref[key][[0, 2]], rtol=0, atol=0)
        td, td_twin = out.clone(), ref.clone()
    assert env.physics_errors == 1 and env._elapsed.tolist() == [5, 2, 5]


def test_collector_batches_the_group_layout():
    env = make_env("Safety6x1HalfCheetahVelocity-v0", num_envs=4, max_episode_steps=10)
    collector = Collector(env, policy=None, frames_per_batch=4 * 15, total_frames=4 * 15,
                          auto_register_policy_transforms=False)
    batch = next(iter(collector))
    collector.shutdown()
    assert batch.batch_size == (4, 15) and batch["next", "agents"].batch_size == (4, 15, 6)
    assert batch["next", "done"][:, 9].all() and batch["next", "agents", "done"][:, 9].all()


# ---------------------------------------------------------------------------- PettingZoo façade
@pytest.mark.parametrize("env_id", IDS)
def test_pettingzoo_parallel_api(env_id):
    from pettingzoo.test import parallel_api_test

    env = sg_pz.make(env_id, cost_in_info=True, max_episode_steps=15)
    parallel_api_test(env, num_cycles=20)  # runs two episodes; the 15-step limit ends them
    env.close()


class TestPettingZooFacade:
    env_id = "Safety9|8HumanoidVelocity-v0"  # heterogeneous: true sizes 248 / 176, 9 / 8

    def test_six_tuple(self):
        env = sg_pz.make(self.env_id)
        assert env.possible_agents == ["agent_0", "agent_1"] and env.agents == []
        assert [env.observation_space(a).shape for a in env.possible_agents] == [(248,), (176,)]
        assert [env.action_space(a).shape for a in env.possible_agents] == [(9,), (8,)]
        assert env.observation_space("agent_0") is env.observation_space("agent_0")
        observations, infos = env.reset(seed=0)
        assert infos == {"agent_0": {}, "agent_1": {}} and env.agents == env.possible_agents
        assert env.state().shape == env.state_space.shape == (376,)
        result = env.step({a: env.action_space(a).sample() for a in env.agents})
        assert isinstance(result, tuple) and len(result) == 6
        observations, rewards, costs, terminations, truncations, infos = result
        for agent, space in env.observation_spaces.items():
            assert observations[agent].dtype == np.float64 and observations[agent] in space
        assert rewards["agent_0"] == rewards["agent_1"] and type(rewards["agent_0"]) is float
        assert costs["agent_0"] == costs["agent_1"] and costs["agent_0"] in (0.0, 1.0)
        assert all(type(flag) is bool for flag in (*terminations.values(), *truncations.values()))
        terms = env.torchrl_env.step_info(0)  # gymnasium's terms (x_velocity, ...), the same for every agent
        assert infos["agent_0"] == {**terms, "cost_velocity": costs["agent_0"], "cost_sum": costs["agent_0"]}
        assert list(infos["agent_1"])[: len(terms)] == list(env.torchrl_env.info_keys)

    def test_six_tuple_does_not_fit_pettingzoo_api_test(self):
        # PettingZoo's test unpacks exactly five values from step: Safety-Gymnasium's 6-tuple cannot pass it,
        # which is why make(..., cost_in_info=True) exists (tested above on every id).
        from pettingzoo.test import parallel_api_test

        with pytest.raises(ValueError, match="too many values to unpack"):
            parallel_api_test(sg_pz.make(self.env_id), num_cycles=3)

    def test_same_trajectory_as_torchrl_env(self):
        facade = sg_pz.make("Safety2x4AntVelocity-v0", seed=5)
        env = make_env("Safety2x4AntVelocity-v0", seed=5)
        observations, _ = facade.reset()
        td = env.reset()
        actions = random_actions(env, 8, seed=6)
        for t in range(8):
            np.testing.assert_array_equal(observations["agent_1"], td["agents", "observation"][0, 1].double().numpy())
            np.testing.assert_array_equal(facade.state(), td["state"][0].double().numpy())
            local = {a: actions[t, 0, i].numpy() for i, a in enumerate(facade.possible_agents)}
            observations, rewards, costs, *_ = facade.step(local)
            td = env.step(td.set(("agents", "action"), actions[t]))["next"]
            assert rewards["agent_0"] == td["agents", "reward"][0, 0].item()
            assert costs["agent_1"] == td["agents", "cost"][0, 1].item()

    def test_numpy_fast_path_equals_torchrl_step(self):
        fast = sg_pz.make("Safety6x1HalfCheetahVelocity-v0", seed=2, max_episode_steps=4)
        slow = sg_pz.make("Safety6x1HalfCheetahVelocity-v0", seed=2, max_episode_steps=4)
        slow._fast = False  # the path of multi-agent envs other than MultiAgentVelocityEnv
        results = [fast.reset(), slow.reset()]
        rng = np.random.default_rng(0)
        for _ in range(6):
            actions = {a: rng.uniform(-1, 1, size=1).astype(np.float32) for a in fast.possible_agents}
            results = [env.step(actions) if env.agents else env.reset() for env in (fast, slow)]
            for x, y in zip(*results):
                assert x.keys() == y.keys()
                for agent in x:
                    np.testing.assert_equal(x[agent], y[agent])
            np.testing.assert_array_equal(fast.state(), slow.state())
        assert fast.agents == [] or fast.agents == fast.possible_agents

    def test_reset_seed_repeats_episode(self):
        env = sg_pz.make("Safety2x3HalfCheetahVelocity-v0")
        first, _ = env.reset(seed=7)
        action = {a: env.action_space(a).sample() for a in env.agents}
        after = env.step(action)[0]
        again, _ = env.reset(seed=7)
        np.testing.assert_array_equal(first["agent_0"], again["agent_0"])
        np.testing.assert_array_equal(after["agent_1"], env.step(action)[0]["agent_1"])
        other, _ = env.reset(seed=8)
        assert not np.array_equal(first["agent_0"], other["agent_0"])

    def test_errors(self):
        env = sg_pz.make("Safety2x3HalfCheetahVelocity-v0", max_episode_steps=1)
        zero = {"agent_0": np.zeros(3), "agent_1": np.zeros(3)}
        with pytest.raises(sg_gym.EpisodeEndedError):
            env.step(zero)
        env.reset(seed=0)
        with pytest.raises(ValueError, match="missing"):
            env.step({"agent_0": np.zeros(3)})
        with pytest.raises(ValueError, match="shape"):
            env.step({"agent_0": np.zeros(3), "agent_1": np.zeros(2)})
        with pytest.raises(ValueError, match="not finite"):
            env.step({"agent_0": np.zeros(3), "agent_1": np.full(3, np.nan)})
        *_, truncations, _ = env.step(zero)
        assert all(truncations.values()) and env.agents == []
        with pytest.raises(sg_gym.EpisodeEndedError):
            env.step(zero)
        with pytest.raises(ValueError, match="single-agent"):
            sg_pz.make("SafetyAntVelocity-v1")
        with pytest.raises(ValueError, match="pettingzoo"):
            sg_gym.make("Safety2x4AntVelocity-v0")

    def test_cost_in_info(self):
        env = sg_pz.make("Safety2x1SwimmerVelocity-v0", cost_in_info=True, velocity_threshold=-1.0)
        env.reset(seed=0)
        result = env.step({a: env.action_space(a).sample() for a in env.agents})
        assert len(result) == 5
        assert all(info["cost"] == 1.0 for info in result[4].values())  # threshold -1: every step costs
