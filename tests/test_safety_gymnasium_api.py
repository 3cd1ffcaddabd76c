"""sg_torchrl.safety_gymnasium as a drop-in for Safety-Gymnasium 1.0.0: the top level, make, make_ma,
render modes, deepcopy, reset options, the alias. Usage patterns are the original's and its clients'
(SafePO's make_sa_mujoco_env / ShareEnv, OmniSafe's SafetyGymnasiumEnv adapter)."""

from __future__ import annotations

import copy
import os
import subprocess
import sys
import textwrap

import gymnasium
import numpy as np
import pytest

import sg_torchrl.safety_gymnasium as safety_gymnasium
from sg_torchrl.render_modes import HumanRenderingUnavailable

NAV_ID = "SafetyPointGoal1-v0"
VEL_ID = "SafetyHalfCheetahVelocity-v1"
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def wrapper_chain(env) -> list[str]:
    names = []
    while hasattr(env, "env"):
        names.append(type(env).__name__)
        env = env.env
    return [*names, type(env).__name__]


# ---------------------------------------------------------------------------- top level
def test_top_level_names_of_the_original():
    for name in ("make", "make_ma", "register", "gymnasium_make", "gymnasium_register", "vector", "wrappers",
                 "__version__", "VERSION", "PREFIX", "ROBOT_NAMES", "robots", "goal_tasks", "button_tasks",
                 "push_tasks", "circle_tasks", "run_tasks", "race_tasks", "fading_tasks", "MAKE_VISION_ENVIRONMENTS",
                 "MAKE_DEBUG_ENVIRONMENTS"):
        assert hasattr(safety_gymnasium, name), name
    assert safety_gymnasium.__version__ == "1.0.0"
    assert safety_gymnasium.gymnasium_make is gymnasium.make
    assert set(safety_gymnasium.wrappers.__all__) == {
        "SafeAutoResetWrapper", "SafePassiveEnvChecker", "SafeTimeLimit", "SafetyGymnasium2Gymnasium",
        "Gymnasium2SafetyGymnasium", "with_gymnasium_wrappers", "SafeNormalizeObservation", "SafeNormalizeCost",
        "SafeNormalizeReward", "SafeUnsqueeze", "SafeRescaleAction"}
    assert set(safety_gymnasium.vector.__all__) == {"SafetyAsyncVectorEnv", "SafetySyncVectorEnv", "VectorEnv", "make"}
    assert {NAV_ID, VEL_ID, "SafetyPointGoal1Vision-v0", "Safety2x4AntVelocity-v0"} <= safety_gymnasium.safe_registry


# ---------------------------------------------------------------------------- make
def test_make_wraps_like_the_original_and_reports_the_episode_length():
    env = safety_gymnasium.make(NAV_ID)
    assert wrapper_chain(env) == ["SafeTimeLimit", "OrderEnforcing", "SafePassiveEnvChecker", "SafetyGymnasiumEnv"]
    assert env.spec.max_episode_steps == 1000 and env.spec.id == NAV_ID
    assert env.unwrapped.spec.max_episode_steps is None  # as the original's: the limit is the wrapper's
    assert env.observation_space.shape == (60,) and env.observation_space.dtype == np.float64
    assert env.action_space.shape == (2,)
    obs, info = env.reset(seed=0)
    assert obs.shape == (60,) and info == {}
    obs, reward, cost, terminated, truncated, info = env.step(env.action_space.sample())
    assert isinstance(reward, float) and isinstance(cost, float)
    assert isinstance(terminated, bool) and isinstance(truncated, bool)
    assert set(info) == {"cost_hazards", "cost_sum"}
    # OmniSafe's adapter: make(id=..., autoreset=True) and an integer spec.max_episode_steps.
    auto = safety_gymnasium.make(id=VEL_ID, autoreset=True)
    assert wrapper_chain(auto)[0] == "SafeAutoResetWrapper"
    assert isinstance(auto.spec.max_episode_steps, int) and auto.spec.max_episode_steps == 1000
    assert safety_gymnasium.make(id="SafetyPointCircle1-v0").spec.max_episode_steps == 500
    bare = safety_gymnasium.make(VEL_ID, disable_env_checker=True)
    assert wrapper_chain(bare) == ["SafeTimeLimit", "OrderEnforcing", "SafetyGymnasiumEnv"]
    for made in (env, auto, bare):
        made.close()


def test_make_max_episode_steps_and_autoreset_keep_the_final_step():
    env = safety_gymnasium.make(VEL_ID, max_episode_steps=3, autoreset=True, velocity_threshold=-1e9)
    assert env.spec.max_episode_steps == 3
    env.reset(seed=1)
    for step in range(1, 7):
        obs, reward, cost, terminated, truncated, info = env.step(env.action_space.sample())
        assert cost == 1.0  # every step costs with this threshold: the final one too
        if step % 3 == 0:
            assert truncated and set(info) == {"final_observation", "final_info"}
            assert info["final_observation"].shape == obs.shape and info["final_info"]["cost_sum"] == 1.0
        else:
            assert not truncated and "final_observation" not in info
    longer = safety_gymnasium.make(NAV_ID, max_episode_steps=1200)
    assert longer.spec.max_episode_steps == 1200 and longer.unwrapped.max_episode_steps == 1200
    env.close()
    longer.close()


def test_make_refuses_what_it_cannot_build():
    with pytest.raises(gymnasium.error.Error, match="not registered"):
        safety_gymnasium.make("SafetyPointGoal9-v0")
    with pytest.raises(TypeError, match="unexpected keyword argument 'frameskip'"):
        safety_gymnasium.make(NAV_ID, frameskip=2)
    with pytest.raises(ValueError, match="max_episode_steps"):
        safety_gymnasium.make(NAV_ID, max_episode_steps=0)
    with pytest.raises(ValueError, match="multi-agent"):
        safety_gymnasium.make("Safety2x3HalfCheetahVelocity-v0", autoreset=True)


def test_register_and_make_a_user_env():
    class Counter(gymnasium.Env):
        observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (1,), dtype=np.float64)
        action_space = gymnasium.spaces.Box(-1, 1, (1,), dtype=np.float32)

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            self.t = 0
            return np.zeros(1), {}

        def step(self, action):
            self.t += 1
            return np.full(1, float(self.t)), 1.0, 0.5, False, False, {}

    rebuilt = safety_gymnasium.make(safety_gymnasium.make("SafetyPointGoal0-v0").spec)  # make(EnvSpec)
    assert rebuilt.spec.max_episode_steps == 1000 and len(rebuilt.reset(seed=0)) == 2
    assert len(rebuilt.step(rebuilt.action_space.sample())) == 6
    safety_gymnasium.register(id="SgTorchrlCounter-v0", entry_point=Counter, max_episode_steps=2)
    env = safety_gymnasium.make("SgTorchrlCounter-v0", autoreset=True)
    env.reset(seed=0)
    env.step(np.zeros(1, dtype=np.float32))
    obs, reward, cost, terminated, truncated, info = env.step(np.zeros(1, dtype=np.float32))
    assert truncated and cost == 0.5 and info["final_observation"][0] == 2.0 and obs[0] == 0.0


def test_velocity_info_carries_gymnasiums_terms():
    env = safety_gymnasium.make(VEL_ID)
    env.reset(seed=0)
    info = env.step(env.action_space.sample())[5]
    assert list(info)[:4] == ["x_position", "x_velocity", "reward_run", "reward_ctrl"]  # the original's keys
    assert {"cost_velocity", "cost_sum"} <= set(info)
    ma = safety_gymnasium.make_ma("Ant", "2x4")
    ma.reset(seed=0)
    infos = ma.step({agent: ma.action_space(agent).sample() for agent in ma.agents})[5]
    assert infos["agent_0"]["x_velocity"] == infos["agent_1"]["x_velocity"]


def test_reset_accepts_options_and_seeds_reproduce():
    env = safety_gymnasium.make(NAV_ID)
    first, _ = env.reset(seed=5, options={"anything": 1})
    again, _ = env.reset(seed=5, options=None)
    np.testing.assert_array_equal(first, again)
    with pytest.raises(TypeError, match="options"):
        env.reset(options=3)
    env.close()


# ---------------------------------------------------------------------------- deepcopy
@pytest.mark.parametrize("env_id", [NAV_ID, VEL_ID, "SafetyPointButton1-v0"])
def test_deepcopy_copies_the_simulator(env_id):
    env = safety_gymnasium.make(env_id, autoreset=True)
    env.reset(seed=2)
    rng = np.random.default_rng(0)
    for _ in range(7):
        env.step(rng.uniform(-1, 1, env.action_space.shape))
    twin = copy.deepcopy(env)
    assert wrapper_chain(twin) == wrapper_chain(env)
    for _ in range(5):
        action = rng.uniform(-1, 1, env.action_space.shape)
        mine, theirs = env.step(action), twin.step(action)
        np.testing.assert_array_equal(mine[0], theirs[0])
        assert mine[1:5] == theirs[1:5] and mine[5] == theirs[5]
    # The copy is independent: stepping it does not move the original.
    before = copy.deepcopy(env)
    twin.step(rng.uniform(-1, 1, env.action_space.shape))
    action = rng.uniform(-1, 1, env.action_space.shape)
    np.testing.assert_array_equal(env.step(action)[0], before.step(action)[0])
    for made in (env, twin, before):
        made.close()


VELOCITY_IDS = [f"Safety{robot}Velocity-v1" for robot in ("Ant", "HalfCheetah", "Hopper", "Humanoid", "Swimmer",
                                                            "Walker2d")]


@pytest.mark.parametrize("env_id", VELOCITY_IDS)
def test_deepcopy_mid_episode_is_exact_on_every_velocity_id(env_id):
    # The Ant's and Humanoid's velocity differentiates a position MuJoCo derives one substep late:
    # the copy's first reward (x/y velocity) must still be the original's.
    env = safety_gymnasium.make(env_id)
    env.reset(seed=3)
    rng = np.random.default_rng(1)
    for _ in range(4):
        env.step(rng.uniform(-1, 1, env.action_space.shape))
    twin = copy.deepcopy(env)
    for _ in range(3):
        action = rng.uniform(-1, 1, env.action_space.shape)
        mine, theirs = env.step(action), twin.step(action)
        np.testing.assert_array_equal(mine[0], theirs[0])
        assert mine[1:5] == theirs[1:5] and mine[5] == theirs[5]
    env.close()
    twin.close()


def test_deepcopy_of_a_multi_agent_env():
    env = safety_gymnasium.make_ma("HalfCheetah", "2x3")
    env.reset(seed=0)
    actions = {agent: np.full(3, 0.3, dtype=np.float32) for agent in env.possible_agents}
    env.step(actions)
    twin = copy.deepcopy(env)
    mine, theirs = env.step(actions), twin.step(actions)
    for agent in env.possible_agents:
        np.testing.assert_array_equal(mine[0][agent], theirs[0][agent])
    assert mine[1] == theirs[1] and mine[2] == theirs[2]
    np.testing.assert_array_equal(env.state(), twin.state())


# ---------------------------------------------------------------------------- render modes and cameras
@pytest.mark.parametrize("env_id", [NAV_ID, VEL_ID])
def test_every_render_mode(env_id):
    for mode, shape, dtype in (("rgb_array", (24, 32, 3), np.uint8), ("depth_array", (24, 32), np.float32)):
        env = safety_gymnasium.make(env_id, render_mode=mode, width=32, height=24)
        env.reset(seed=0)
        frame = env.render()
        assert frame.shape == shape and frame.dtype == dtype
        if mode == "depth_array":  # gymnasium's depth buffer: 0 at the near plane, 1 at the far one
            assert 0.0 <= frame.min() and frame.max() <= 1.0 and frame.min() < frame.max()
        env.close()
    for mode, shape in (("rgb_array_list", (24, 32, 3)), ("depth_array_list", (24, 32))):
        env = safety_gymnasium.make(env_id, render_mode=mode, width=32, height=24)
        env.reset(seed=0)
        env.step(env.action_space.sample())
        frames = env.render()  # the reset's frame and the step's, as gymnasium's RenderCollection
        assert len(frames) == 2 and all(frame.shape == shape for frame in frames)
        env.step(env.action_space.sample())
        assert len(env.render()) == 1 and env.render() == []
        env.reset()
        env.step(env.action_space.sample())
        twin = copy.deepcopy(env)  # the collected frames travel with a copy
        assert len(twin.render()) == len(env.render()) == 2
        twin.close()
        env.close()
    declared = safety_gymnasium.make(env_id).metadata["render_modes"]
    assert set(declared) >= {"rgb_array", "depth_array", "rgb_array_list", "depth_array_list"}
    assert ("human" in declared) == bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def test_human_mode_names_the_reason_without_a_display(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if not sys.platform.startswith("linux"):
        pytest.skip("the display check is Linux's")
    with pytest.raises(HumanRenderingUnavailable, match="no display.*rgb_array"):
        safety_gymnasium.make(NAV_ID, render_mode="human")


def test_camera_name_and_id_choose_the_frame():
    frames = {}
    names = ["fixednear", "fixedfar", "track"]
    available = [name for name in names if name in safety_gymnasium.make(NAV_ID).unwrapped.torchrl_env.camera_names]
    for key, value in (("camera_name", None), ("camera_name", "vision"), ("camera_id", -1),
                       *(("camera_name", name) for name in available)):
        env = safety_gymnasium.make(NAV_ID, render_mode="rgb_array", width=32, height=32, **{key: value})
        env.reset(seed=0)
        frames[value] = env.render()
        env.close()
    np.testing.assert_array_equal(frames[None], frames["vision"])  # the original's default: the robot's camera
    assert not np.array_equal(frames["vision"], frames[-1])
    assert all(not np.array_equal(frames[name], frames["vision"]) for name in available)
    with pytest.raises(ValueError, match="unknown camera"):
        safety_gymnasium.make(NAV_ID, render_mode="rgb_array", camera_name="no_such_camera")
    with pytest.raises(TypeError, match="only one of"):
        safety_gymnasium.make(NAV_ID, render_mode="rgb_array", camera_name="vision", camera_id=0)


# ---------------------------------------------------------------------------- make_ma
PARTITIONS = {  # reference section 10: per-agent observation / action sizes and the state size
    ("Ant", "2x4"): ([21, 21], [4, 4], 27),
    ("Ant", "4x2"): ([18] * 4, [2] * 4, 27),
    ("HalfCheetah", "2x3"): ([12, 12], [3, 3], 17),
    ("HalfCheetah", "6x1"): ([9, 9, 8, 9, 9, 8], [1] * 6, 17),
    ("Hopper", "3x1"): ([8, 9, 8], [1] * 3, 11),
    ("Humanoid", "9|8"): ([248, 176], [9, 8], 376),
    ("Swimmer", "2x1"): ([6, 6], [1, 1], 8),
    ("Walker2d", "2x3"): ([11, 11], [3, 3], 17),
}


@pytest.mark.parametrize(("scenario", "conf"), list(PARTITIONS))
def test_make_ma_on_the_eight_partitions(scenario, conf):
    observation_sizes, action_sizes, state_size = PARTITIONS[scenario, conf]
    env = safety_gymnasium.make_ma(scenario, conf)
    assert env.possible_agents == [f"agent_{i}" for i in range(len(action_sizes))]
    assert [env.observation_space(agent).shape[0] for agent in env.possible_agents] == observation_sizes
    assert [env.action_spaces[agent].shape[0] for agent in env.possible_agents] == action_sizes
    assert [len(part) for part in env.agent_action_partitions] == action_sizes
    assert all(hasattr(node, "label") for part in env.agent_action_partitions for node in part)
    observations, infos = env.reset(seed=0)
    assert env.state().shape == (state_size,) and env.state().dtype == np.float64
    assert {agent: obs.shape[0] for agent, obs in observations.items()} == dict(zip(env.possible_agents,
                                                                                    observation_sizes))
    actions = {agent: env.action_space(agent).sample() for agent in env.agents}
    observations, rewards, costs, terminations, truncations, infos = env.step(actions)
    assert set(costs) == set(env.possible_agents) and len(set(costs.values())) == 1  # the team's indicator
    assert all(isinstance(flag, bool) for flag in (*terminations.values(), *truncations.values()))
    env.close()


def test_make_ma_subclass_like_safepo_share_env():
    class ShareEnv(safety_gymnasium.make_ma):  # SafePO subclasses SafeMAEnv and assigns these
        def __init__(self, scenario, agent_conf, **kwargs):
            super().__init__(scenario=scenario, agent_conf=agent_conf, **kwargs)
            self.num_agents = len(self.agent_action_partitions)
            self.n_actions = max(len(part) for part in self.agent_action_partitions)
            self.observation_spaces = {}

        def reset(self, seed=None):
            super().reset(seed=seed)
            return self.env.state()

    env = ShareEnv("Swimmer", "2x1")
    assert env.reset(seed=0).shape == (8,) and env.num_agents == 2 and env.n_actions == 1
    with pytest.raises(ValueError, match="agent_conf"):
        safety_gymnasium.make_ma("Ant", "3x3")
    with pytest.raises(NotImplementedError, match="partitions"):
        safety_gymnasium.make_ma("Ant", "2x4", agent_factorization={})


def test_multi_agent_ids_through_make():
    env = safety_gymnasium.make("SafetyPointMultiGoal1-v0")
    observations, _ = env.reset(seed=0)
    assert env.possible_agents == ["agent_0", "agent_1"] and set(observations) == set(env.possible_agents)
    result = env.step({agent: env.action_space(agent).sample() for agent in env.agents})
    assert len(result) == 6
    velocity = safety_gymnasium.make("Safety2x4AntVelocity-v0", max_episode_steps=2)
    velocity.reset(seed=0)
    actions = {agent: velocity.action_space(agent).sample() for agent in velocity.possible_agents}
    velocity.step(actions)
    assert all(velocity.step(actions)[4].values()) and velocity.agents == []


# ---------------------------------------------------------------------------- the alias
def _run(code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=240, env=env, cwd=ROOT)


def test_install_alias_makes_import_safety_gymnasium_resolve_here():
    result = _run("""
        import sg_torchrl.safety_gymnasium as sgs
        sgs.install_alias()
        import safety_gymnasium
        from safety_gymnasium.wrappers import SafeAutoResetWrapper, SafeRescaleAction, SafeUnsqueeze
        from safety_gymnasium.vector.async_vector_env import SafetyAsyncVectorEnv
        from safety_gymnasium.vector.utils.tile_images import tile_images
        from safety_gymnasium.tasks.safe_multi_agent.safe_mujoco_multi import SafeMAEnv
        from safety_gymnasium.utils.registration import make, safe_registry
        from safety_gymnasium.utils.passive_env_checker import env_step_passive_checker
        from safety_gymnasium.version import __version__
        assert safety_gymnasium is sgs and SafeMAEnv is sgs.make_ma and make is sgs.make
        assert safety_gymnasium.wrappers.autoreset.SafeAutoResetWrapper is SafeAutoResetWrapper
        env = safety_gymnasium.make("SafetyPointGoal0-v0")
        env = SafeUnsqueeze(SafeRescaleAction(SafeAutoResetWrapper(env), -1.0, 1.0))
        obs, _ = env.reset(seed=0)
        assert obs.shape == (1, 28)
        try:
            import safety_gymnasium.builder
        except ModuleNotFoundError as error:
            assert "drop-in" in str(error)
        else:
            raise AssertionError("the original's engine modules are not provided")
        print("alias ok", __version__)
    """)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "alias ok 1.0.0" in result.stdout


def test_module_runner_runs_an_unchanged_script(tmp_path):
    script = tmp_path / "original_script.py"
    script.write_text(textwrap.dedent("""
        import sys
        import safety_gymnasium

        env = safety_gymnasium.make("SafetyPointGoal0-v0", max_episode_steps=3, autoreset=True)
        obs, info = env.reset(seed=0)
        for _ in range(3):
            obs, reward, cost, terminated, truncated, info = env.step(env.action_space.sample())
        assert truncated and "final_observation" in info
        print("script ok", sys.argv[1:])
    """))
    env = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}
    result = subprocess.run([sys.executable, "-m", "sg_torchrl.safety_gymnasium", str(script), "--seed", "1"],
                            capture_output=True, text=True, timeout=240, env=env, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "script ok ['--seed', '1']" in result.stdout


def test_alias_refuses_when_the_original_is_already_imported(monkeypatch):
    from sg_torchrl.safety_gymnasium import alias

    impostor = type(sys)("safety_gymnasium")
    monkeypatch.setitem(sys.modules, "safety_gymnasium", impostor)
    with pytest.raises(ImportError, match="already imported"):
        alias.install_alias()
    assert not alias.is_alias_installed()
