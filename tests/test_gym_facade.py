"""The gymnasium façade (``sg_torchrl.gym``): Safety-Gymnasium's step API over the TorchRL envs.

Every registered id is checked for the 6-tuple contract, seeding, error handling, gymnasium's
registry and ``check_env`` on the 5-tuple twin, and — the property that makes the façade a safe
migration path — that it reproduces the TorchRL env's trajectory exactly for the same seed and
actions.
"""

from __future__ import annotations

import os
import warnings

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from tensordict import TensorDict

import sg_torchrl
import sg_torchrl.gym as sg_gym
from sg_torchrl.envs import registry as sg_registry
from sg_torchrl.render_modes import HumanRenderingUnavailable

torch.set_num_threads(1)

# Multi-agent ids have their own façade (sg_torchrl.pettingzoo, tests/test_multi_agent_envs.py); the Vision ids'
# Dict observations (images) are tested in tests/test_vision.py.
ENV_IDS = [env_id for env_id in sg_torchrl.list_envs()
           if not sg_registry.registry_entry(env_id).multi_agent and sg_registry.registry_entry(env_id).family != "vision"]
STEPS = 6


# ---------------------------------------------------------------------------- helpers
def sample_actions(env: gymnasium.Env, steps: int, seed: int, scale: float = 1.0) -> np.ndarray:
    """``(steps, act_dim)`` float32 actions uniform in ``scale`` times the action bounds."""
    low, high = env.action_space.low.astype(np.float64), env.action_space.high.astype(np.float64)
    mid, half = (high + low) / 2, (high - low) / 2 * scale
    rng = np.random.default_rng(seed)
    return (mid + half * rng.uniform(-1, 1, size=(steps, *low.shape))).astype(np.float32)


def mid_action(env: gymnasium.Env) -> np.ndarray:
    return ((env.action_space.low + env.action_space.high) / 2).astype(np.float32)


def expected_info_keys(env: sg_gym.SafetyGymnasiumEnv) -> set[str]:
    names = env.torchrl_env.observation_spec["cost_info"].keys()
    terms = set(getattr(env.torchrl_env, "info_keys", ()))  # velocity ids: gymnasium's terms (x_velocity, ...)
    return {f"cost_{name}" for name in names} | {"cost_sum"} | terms


def quiet_check_env(env: gymnasium.Env) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unbounded observation space, wrapped env: advice only
        check_env(env, skip_render_check=True)


# ---------------------------------------------------------------------------- 6-tuple contract
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_step_returns_safety_gymnasium_six_tuple(env_id):
    env = sg_gym.make(env_id)
    assert isinstance(env, gymnasium.Env) and isinstance(env, sg_gym.SafetyGymnasiumEnv)
    assert isinstance(env.observation_space, gymnasium.spaces.Box)
    assert env.observation_space.dtype == np.float64
    assert isinstance(env.action_space, gymnasium.spaces.Box)
    spec = env.torchrl_env.action_spec.space
    np.testing.assert_array_equal(env.action_space.low, spec.low[0].numpy())
    np.testing.assert_array_equal(env.action_space.high, spec.high[0].numpy())
    assert env.max_episode_steps == sg_torchrl.envs.registry_entry(env_id).max_episode_steps

    obs, info = env.reset(seed=0)
    assert info == {}
    assert isinstance(obs, np.ndarray) and obs.dtype == np.float64 and obs in env.observation_space
    for action in sample_actions(env, STEPS, seed=1):
        result = env.step(action)
        assert isinstance(result, tuple) and len(result) == 6
        obs, reward, cost, terminated, truncated, info = result
        assert isinstance(obs, np.ndarray) and obs.dtype == np.float64
        assert obs.shape == env.observation_space.shape and np.isfinite(obs).all()
        assert type(reward) is float and type(cost) is float
        assert type(terminated) is bool and type(truncated) is bool
        assert set(info) == expected_info_keys(env)
        assert all(type(value) is float for value in info.values())
        assert info["cost_sum"] == cost and cost in (0.0, 1.0)  # indicator costs by default
        if terminated or truncated:
            break
    env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_reset_seed_determinism_and_stream(env_id):
    first, second = sg_gym.make(env_id), sg_gym.make(env_id)
    obs_a, _ = first.reset(seed=7)
    obs_b, _ = second.reset(seed=7)
    np.testing.assert_array_equal(obs_a, obs_b)  # same seed, separate instances
    actions = sample_actions(first, 3, seed=2)
    steps_a = [first.step(a) for a in actions]
    np.testing.assert_array_equal(first.reset(seed=7)[0], obs_a)  # re-seeding restarts the stream
    steps_b = [first.step(a) for a in actions]
    for step_a, step_b in zip(steps_a, steps_b):
        np.testing.assert_array_equal(step_a[0], step_b[0])
        assert step_a[1:] == step_b[1:]
    # No seed: the random stream continues, so the next episode starts elsewhere, and identically
    # in two instances seeded alike.
    first.reset(seed=7)
    second.reset(seed=7)
    next_a, _ = first.reset()
    next_b, _ = second.reset(seed=None)
    assert not np.array_equal(next_a, obs_a)
    np.testing.assert_array_equal(next_a, next_b)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_trajectory_equals_torchrl_env(env_id):
    """Same seed and actions (some out of bounds, so clipping is exercised) give identical data on
    both façade paths (numpy fast path and public TorchRL step) and the TorchRL env itself."""
    length = 5
    raw = sg_torchrl.make(env_id, num_envs=1, seed=11, max_episode_steps=length)
    fast = sg_gym.make(env_id, max_episode_steps=length)
    slow = sg_gym.make(env_id, max_episode_steps=length)
    slow._fast = False
    if sg_torchrl.envs.registry_entry(env_id).family == "velocity":
        assert fast._fast  # SafeEnv's own _step: the numpy path is the one under test
    actions = sample_actions(fast, length, seed=3, scale=1.5)

    td = raw.reset()
    for facade in (fast, slow):
        obs, _ = facade.reset(seed=11)
        np.testing.assert_array_equal(obs, td["observation"][0].numpy().astype(np.float64))
    names = list(raw.observation_spec["cost_info"].keys())
    for k, action in enumerate(actions):
        nxt = raw.step(TensorDict({"action": torch.from_numpy(action)[None]}, batch_size=[1]))["next"]
        expected_info = raw.step_info(0) if hasattr(raw, "step_info") else {}  # velocity: gymnasium's terms
        expected_info.update({f"cost_{name}": float(nxt["cost_info", name][0, 0]) for name in names})
        expected_info["cost_sum"] = float(nxt["cost"][0, 0])
        for facade in (fast, slow):
            obs, reward, cost, terminated, truncated, info = facade.step(action)
            np.testing.assert_array_equal(obs, nxt["observation"][0].numpy().astype(np.float64))
            assert reward == float(nxt["reward"][0, 0])
            assert cost == float(nxt["cost"][0, 0])
            assert terminated == bool(nxt["terminated"][0, 0])
            assert truncated == bool(nxt["truncated"][0, 0])
            assert info == expected_info
        if bool(nxt["done"][0, 0]):
            break
    assert k == length - 1 and truncated or terminated  # the episode ended on the time limit or earlier


# ---------------------------------------------------------------------------- errors
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_errors_bad_action_and_step_after_done(env_id):
    env = sg_gym.make(env_id, max_episode_steps=3)
    action = mid_action(env)
    with pytest.raises(sg_gym.EpisodeEndedError, match="reset"):
        env.step(action)  # before the first reset
    env.reset(seed=0)
    for bad in (np.zeros(action.size + 1, np.float32), action[None], np.float32(0.0)):
        with pytest.raises(ValueError, match="shape"):
            env.step(bad)
    nan = action.copy()
    nan[0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        env.step(nan)
    for step in range(3):  # rejected actions did not advance the episode
        *_, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break
    assert truncated or terminated
    assert step == 2 or terminated
    with pytest.raises(sg_gym.EpisodeEndedError) as caught:
        env.step(action)
    # Safety-Gymnasium asserts here; gymnasium code expects ResetNeeded: both catch it.
    assert isinstance(caught.value, AssertionError) and isinstance(caught.value, gymnasium.error.ResetNeeded)
    env.reset()
    env.step(action)  # a reset starts a new episode


def test_render_mode_num_envs_reset_options_and_close():
    env_id = ENV_IDS[0]
    # Every gymnasium render mode is tested in tests/test_safety_gymnasium_api.py; "human" needs a
    # display and pygame and says so at construction (these machines are headless).
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        with pytest.raises(HumanRenderingUnavailable, match="no display.*rgb_array"):
            sg_gym.make(env_id, render_mode="human")
        with pytest.raises(HumanRenderingUnavailable, match="no display"):
            gymnasium.make(env_id, render_mode="human")
    with pytest.raises(ValueError, match="render_mode"):
        sg_gym.make(env_id, render_mode="rgb")
    with pytest.raises(TypeError, match="num_envs"):
        sg_gym.make(env_id, num_envs=4)
    env = sg_gym.make(env_id)
    assert env.render_mode is None
    env.reset(options={})
    env.reset(options={"layout": 1})  # accepted and ignored, as by Safety-Gymnasium's envs
    with pytest.raises(TypeError, match="options"):
        env.reset(options=1)
    env.close()
    env.close()  # twice is fine
    with pytest.raises(gymnasium.error.ClosedEnvironmentError):
        env.step(mid_action(env))
    with pytest.raises(gymnasium.error.ClosedEnvironmentError):
        env.reset()


# ---------------------------------------------------------------------------- 5-tuple twins, registry
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_twin_passes_check_env_and_carries_cost_in_info(env_id):
    twin_id = sg_gym.gymnasium_twin_id(env_id)
    assert twin_id.endswith(f"Gymnasium-v{env_id.rpartition('-v')[2]}")
    twin = sg_gym.make(twin_id)
    assert isinstance(twin, sg_gym.GymnasiumEnv)
    quiet_check_env(twin)
    quiet_check_env(gymnasium.make(twin_id))

    six = sg_gym.make(env_id)
    twin.reset(seed=4)
    six.reset(seed=4)
    for action in sample_actions(six, 3, seed=5):
        obs5, reward5, terminated5, truncated5, info5 = twin.step(action)
        obs6, reward6, cost6, terminated6, truncated6, info6 = six.step(action)
        np.testing.assert_array_equal(obs5, obs6)
        assert (reward5, terminated5, truncated5) == (reward6, terminated6, truncated6)
        assert info5 == {**info6, "cost": cost6}
        if terminated6 or truncated6:
            break


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_gymnasium_make_after_import(env_id):
    plain = gymnasium.make(env_id)
    assert type(plain) is sg_gym.SafetyGymnasiumEnv and plain.unwrapped is plain  # no 5-tuple wrappers
    plain.reset(seed=0)
    assert len(plain.step(mid_action(plain))) == 6
    assert plain.max_episode_steps == sg_torchrl.envs.registry_entry(env_id).max_episode_steps

    twin_id = sg_gym.gymnasium_twin_id(env_id)
    twin = gymnasium.make(twin_id)
    assert isinstance(twin.unwrapped, sg_gym.GymnasiumEnv)
    assert twin.spec.max_episode_steps == sg_torchrl.envs.registry_entry(env_id).max_episode_steps
    assert twin.unwrapped.max_episode_steps is None  # gymnasium's TimeLimit is the only limit
    short = gymnasium.make(twin_id, max_episode_steps=3)
    short.reset(seed=0)
    for _ in range(3):
        *_, terminated, truncated, info = short.step(mid_action(short))
        assert "cost" in info
        if terminated:
            break
    assert truncated or terminated


def test_register_envs_is_idempotent_and_covers_every_id():
    assert sg_gym.register_envs() == []  # already done at import
    for env_id in ENV_IDS:
        for gym_id in (env_id, sg_gym.gymnasium_twin_id(env_id)):
            assert gymnasium.registry[gym_id].entry_point == "sg_torchrl.gym:make"
    plain = gymnasium.registry[ENV_IDS[0]]
    assert plain.disable_env_checker and not plain.order_enforce and plain.max_episode_steps is None


def test_ids_added_later_are_registered():
    entry = sg_torchrl.envs.registry_entry("SafetySwimmerVelocity-v1")
    env_id = "SafetyFacadeTestVelocity-v7"
    sg_registry.register(
        sg_registry.EnvEntry(env_id=env_id, constructor=entry.constructor, family="test", robot="Swimmer",
                             task="Velocity", max_episode_steps=20, kwargs=dict(entry.kwargs))
    )
    twin_id = sg_gym.gymnasium_twin_id(env_id)
    try:
        assert sorted(sg_gym.register_envs()) == sorted([env_id, twin_id])
        assert sg_gym.register_envs() == []
        env = gymnasium.make(env_id)
        env.reset(seed=0)
        assert env.max_episode_steps == 20
        assert gymnasium.make(twin_id).spec.max_episode_steps == 20
    finally:
        sg_registry._REGISTRY.pop(env_id, None)
        gymnasium.registry.pop(env_id, None)
        gymnasium.registry.pop(twin_id, None)


def test_spec_recreates_the_env_and_twins_vectorise():
    env = sg_gym.make(ENV_IDS[0], max_episode_steps=7, cost_mode="raw")
    again = gymnasium.make(env.spec)
    assert type(again) is type(env) and again.max_episode_steps == 7
    assert again.torchrl_env.cost_mode == "raw"

    vec = gymnasium.make_vec(sg_gym.gymnasium_twin_id(ENV_IDS[0]), num_envs=2, vectorization_mode="sync")
    obs, _ = vec.reset(seed=0)
    assert obs.shape == (2, *env.observation_space.shape)
    _, reward, terminated, truncated, info = vec.step(np.stack([mid_action(env)] * 2))
    assert reward.shape == (2,) and info["cost"].shape == (2,)
    vec.close()
