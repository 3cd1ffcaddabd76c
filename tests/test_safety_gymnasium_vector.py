"""sg_torchrl.safety_gymnasium.vector: SafetySyncVectorEnv and SafetyAsyncVectorEnv with same-step
autoreset (the cost of an episode's final step kept), gymnasium 0.28's info layout, seeding, the
0.28 API, and the async env's explicit start method (a script without a main guard runs)."""

from __future__ import annotations

import multiprocessing as mp
import os
import subprocess
import sys
import textwrap

import gymnasium
import numpy as np
import pytest

import sg_torchrl.safety_gymnasium as safety_gymnasium
from sg_torchrl.safety_gymnasium.vector import SafetyAsyncVectorEnv, SafetySyncVectorEnv
from sg_torchrl.safety_gymnasium.vector.async_vector_env import WorkerError
from sg_torchrl.safety_gymnasium.vector.utils import tile_images
from sg_torchrl.safety_gymnasium.wrappers import SafeNormalizeCost, SafeNormalizeObservation

VEL_ID = "SafetyHalfCheetahVelocity-v1"
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LENGTH = 3


def make_vector(asynchronous: bool, num_envs: int = 2, **kwargs):
    kwargs = {"max_episode_steps": LENGTH, "velocity_threshold": -1e9, **kwargs}
    return safety_gymnasium.vector.make(VEL_ID, num_envs=num_envs, asynchronous=asynchronous, **kwargs)


def actions_for(steps: int, num_envs: int = 2) -> np.ndarray:
    return np.random.default_rng(0).uniform(-1, 1, (steps, num_envs, 6)).astype(np.float32)


@pytest.fixture(scope="module")
def single_env_runs():
    """What env ``i`` of a vector env seeded 10 must reproduce: a single env seeded 10 + i."""
    runs = []
    for index in range(2):
        env = safety_gymnasium.make(VEL_ID, max_episode_steps=LENGTH, velocity_threshold=-1e9)
        first, _ = env.reset(seed=10 + index)
        steps = []
        for action in actions_for(LENGTH)[:, index]:
            steps.append(env.step(action))
        runs.append((first, steps))
        env.close()
    return runs


@pytest.mark.parametrize("asynchronous", [False, True])
def test_steps_equal_single_envs_and_autoreset_keeps_the_final_cost(asynchronous, single_env_runs):
    envs = make_vector(asynchronous)
    assert isinstance(envs, SafetyAsyncVectorEnv if asynchronous else SafetySyncVectorEnv)
    assert isinstance(envs, gymnasium.vector.VectorEnv) and isinstance(envs, gymnasium.Env) and envs.is_vector_env
    assert envs.single_observation_space.shape == (17,) and envs.observation_space.shape == (2, 17)
    assert envs.single_action_space.shape == (6,) and envs.action_space.shape == (2, 6)
    obs, infos = envs.reset(seed=10)
    np.testing.assert_array_equal(obs, np.stack([run[0] for run in single_env_runs]))
    for t, action in enumerate(actions_for(LENGTH)):
        obs, rewards, costs, terminateds, truncateds, infos = envs.step(action)
        assert rewards.dtype == costs.dtype == np.float64 and truncateds.dtype == np.bool_
        expected = [run[1][t] for run in single_env_runs]
        np.testing.assert_array_equal(rewards, [step[1] for step in expected])
        np.testing.assert_array_equal(costs, [step[2] for step in expected])
        assert costs.tolist() == [1.0, 1.0]  # the final step's cost too
        if t < LENGTH - 1:
            np.testing.assert_array_equal(obs, np.stack([step[0] for step in expected]))
            assert "final_observation" not in infos
            np.testing.assert_array_equal(infos["cost_sum"], [1.0, 1.0])
            assert infos["_cost_sum"].all()
        else:  # both episodes end here: reset within the step
            assert truncateds.all() and infos["_final_observation"].all()
            assert infos["final_observation"].dtype == object and infos["final_info"].dtype == object
            for index, step in enumerate(expected):
                np.testing.assert_array_equal(infos["final_observation"][index], step[0])
                assert infos["final_info"][index] == step[5]
            assert not np.array_equal(obs[0], expected[0][0])
    envs.close()
    envs.close()  # twice is fine
    with pytest.raises(gymnasium.error.ClosedEnvironmentError):
        envs.step(actions_for(1)[0])


def test_final_observation_is_none_for_envs_still_running():
    envs = SafetySyncVectorEnv([
        lambda: safety_gymnasium.make(VEL_ID, max_episode_steps=1),
        lambda: safety_gymnasium.make(VEL_ID, max_episode_steps=5),
    ])
    envs.reset(seed=0)
    obs, rewards, costs, terminateds, truncateds, infos = envs.step(envs.action_space.sample())
    assert truncateds.tolist() == [True, False]
    assert infos["_final_observation"].tolist() == [True, False]
    assert infos["final_observation"][1] is None and infos["final_observation"][0].shape == (17,)
    # OmniSafe's and SafePO's way of reading it
    rows = np.array([array if array is not None else np.zeros(obs.shape[-1]) for array in infos["final_observation"]])
    assert rows.shape == (2, 17)
    assert infos["cost_velocity"].dtype == np.float64 and infos["_cost_velocity"].tolist() == [False, True]
    envs.close()


def test_0_28_api_attributes_and_render():
    envs = make_vector(False, render_mode="rgb_array", width=16, height=8)
    envs.reset_async(seed=0)
    obs, _ = envs.reset_wait()
    envs.step_async(envs.action_space.sample())
    assert len(envs.step_wait()) == 6
    with pytest.raises(gymnasium.error.NoAsyncCallError):
        envs.step_wait()
    assert envs.get_attr("env_id") == (VEL_ID, VEL_ID)
    assert [spec.max_episode_steps for spec in envs.call("spec")] == [LENGTH, LENGTH]
    envs.set_attr("marker", [1, 2])
    assert envs.get_attr("marker") == (1, 2)
    image = envs.render()
    assert image.shape == (8, 32, 3) and image.dtype == np.uint8
    envs.close()
    assert tile_images([np.ones((2, 2, 3))] * 3).shape == (4, 4, 3)


def test_async_env_calls_errors_and_explicit_context():
    envs = make_vector(True)
    assert envs.context == ("fork" if sys.platform.startswith("linux") else "spawn")
    assert mp.get_start_method(allow_none=True) in (None, "spawn")  # importing TorchRL may set spawn globally
    envs.reset(seed=0)
    assert envs.get_attr("env_id") == (VEL_ID, VEL_ID)
    envs.set_attr("marker", 7)
    assert envs.call("__getattribute__", "marker") == (7, 7)
    with pytest.raises(WorkerError, match="shape"):
        envs.step([np.zeros(5), np.zeros(5)])
    envs.close()
    with pytest.raises(WorkerError, match="not registered"):
        SafetyAsyncVectorEnv([lambda: safety_gymnasium.make("SafetyNoSuchTask-v0")])


def test_normalizers_on_a_vector_env():
    envs = SafeNormalizeCost(SafeNormalizeObservation(make_vector(False)))
    obs, _ = envs.reset(seed=0)
    assert obs.shape == (2, 17)
    for _ in range(LENGTH):
        obs, rewards, costs, terminateds, truncateds, infos = envs.step(envs.action_space.sample())
    assert costs.shape == (2,) and envs.returns.shape == (2,)
    observation_wrapper = envs.env
    raw = infos["original_final_observation"]
    for index in range(2):
        expected = (raw[index] - observation_wrapper.obs_rms.mean) / np.sqrt(observation_wrapper.obs_rms.var + 1e-8)
        np.testing.assert_allclose(infos["final_observation"][index], expected)
    envs.close()


def test_async_env_in_a_script_without_main_guard(tmp_path):
    # Importing sg_torchrl (TorchRL) sets the global start method to spawn, under which a worker
    # re-runs an unguarded script; the async env's own context keeps such scripts working.
    script = tmp_path / "unguarded.py"
    script.write_text(textwrap.dedent(f"""
        import multiprocessing as mp
        import safety_gymnasium
        envs = safety_gymnasium.vector.make("{VEL_ID}", num_envs=2, max_episode_steps=2)
        envs.reset(seed=0)
        for _ in range(2):
            out = envs.step(envs.action_space.sample())
        envs.close()
        print("unguarded ok", mp.get_start_method(allow_none=True), out[4].tolist())
    """))
    env = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}
    result = subprocess.run([sys.executable, "-m", "sg_torchrl.safety_gymnasium", str(script)],
                            capture_output=True, text=True, timeout=240, env=env, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.count("unguarded ok") == 1 and "[True, True]" in result.stdout


def test_async_env_with_spawn_carries_lambdas():
    # Under spawn the env functions travel to fresh interpreters: lambdas and closures go by cloudpickle.
    length = 2
    envs = SafetyAsyncVectorEnv([lambda: safety_gymnasium.make(VEL_ID, max_episode_steps=length)] * 2,
                                context="spawn")
    assert envs.context == "spawn"
    envs.reset(seed=0)
    for _ in range(length):
        truncateds = envs.step(envs.action_space.sample())[4]
    assert truncateds.tolist() == [True, True]
    envs.close()


def test_omnisafe_adapter_pattern():
    # OmniSafe 0.5's SafetyGymnasiumEnv: vector.make(env_id=..., num_envs=...) (asynchronous by default),
    # single_* spaces, torch actions, final_observation rows or None.
    import torch

    envs = safety_gymnasium.vector.make(env_id=VEL_ID, num_envs=2, max_episode_steps=2)
    assert isinstance(envs.single_action_space, gymnasium.spaces.Box)
    assert isinstance(envs.single_observation_space, gymnasium.spaces.Box)
    obs, info = envs.reset(seed=0)
    for _ in range(2):
        action = torch.as_tensor(envs.action_space.sample())
        obs, reward, cost, terminated, truncated, info = envs.step(action)
        obs, reward, cost, terminated, truncated = (
            torch.as_tensor(x, dtype=torch.float32) for x in (obs, reward, cost, terminated, truncated))
    final = torch.as_tensor(np.array([array if array is not None else np.zeros(obs.shape[-1])
                                      for array in info["final_observation"]]), dtype=torch.float32)
    assert final.shape == (2, 17) and truncated.tolist() == [1.0, 1.0]
    envs.close()
