"""The one-simulator path (issue 19) gives the batched path's data, bit for bit.

At ``num_envs=1`` the env takes shortcuts that the batch does not: the physics' state cache is a view
of the one ``MjData`` (no copies), the velocity tasks compute reward, cost and ``step_info`` on Python
floats, ``SafeEnv`` screens for faults with one sum instead of per-simulator masks, and the gymnasium
façade steps through :meth:`SafeEnv.step_one`. Each shortcut must leave every emitted value as it
was. Checked here over whole episodes with resets, out-of-bound actions included:

* the gymnasium façade, the TorchRL env at ``num_envs=1`` and simulator 0 of a batched env with the
  same seed (a seed gives simulator 0 the same trajectory whatever ``N`` is) emit the same
  observations, rewards, costs, per-constraint costs, flags and velocity info terms;
* a simulator that diverges, or whose reward would be emitted non-finite, is still isolated at
  ``num_envs=1`` (the fault screen lets it through to the exact test).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import sg_torchrl
import sg_torchrl.gym as sg_gym

VELOCITY_IDS = ["SafetyHalfCheetahVelocity-v1", "SafetyHopperVelocity-v1", "SafetySwimmerVelocity-v0",
                "SafetyWalker2dVelocity-v1", "SafetyAntVelocity-v1", "SafetyHumanoidVelocity-v1"]
NAVIGATION_IDS = ["SafetyPointGoal1-v0", "SafetyCarButton1-v0", "SafetyRacecarPush1-v0", "SafetyPointGoal0-v0"]
STEPS = 60
EPISODE = 25  # short episodes, so that resets happen inside the trajectory


def _actions(low: np.ndarray, high: np.ndarray, seed: int) -> np.ndarray:
    """``(STEPS, act_dim)`` float32 actions, some beyond the bounds (clipping is exercised)."""
    return np.random.default_rng(seed).uniform(1.3 * low, 1.3 * high, size=(STEPS, len(low))).astype(np.float32)


def _facade_trajectory(env_id: str, seed: int, actions: np.ndarray) -> list[tuple]:
    env = sg_gym.make(env_id, max_episode_steps=EPISODE)
    obs, _ = env.reset(seed=seed)
    records = [("reset", obs)]
    for action in actions:
        obs, reward, cost, terminated, truncated, info = env.step(action)
        records.append((obs, reward, cost, terminated, truncated, info))
        if terminated or truncated:
            obs, _ = env.reset()
            records.append(("reset", obs))
    env.close()
    return records


def _torchrl_trajectory(env_id: str, seed: int, actions: np.ndarray, num_envs: int) -> list[tuple]:
    """Simulator 0's records in the façade's layout, from a TorchRL env of ``num_envs`` simulators."""
    env = sg_torchrl.make(env_id, num_envs=num_envs, seed=seed, max_episode_steps=EPISODE)
    names = list(env.observation_spec["cost_info"].keys())
    td = env.reset()
    records = [("reset", td["observation"][0].numpy().astype(np.float64))]
    # The other simulators take simulator 0's action rolled: their own trajectories, same steps.
    for action in actions:
        batch = np.stack([np.roll(action, i) for i in range(num_envs)])
        td.set("action", torch.from_numpy(batch))
        out, td = env.step_and_maybe_reset(td)
        nxt = out["next"]
        info = env.step_info(0) if hasattr(env, "step_info") else {}
        info.update({f"cost_{name}": float(nxt["cost_info", name][0, 0]) for name in names})
        info["cost_sum"] = float(nxt["cost"][0, 0])
        terminated, truncated = bool(nxt["terminated"][0, 0]), bool(nxt["truncated"][0, 0])
        records.append((nxt["observation"][0].numpy().astype(np.float64), float(nxt["reward"][0, 0]),
                        float(nxt["cost"][0, 0]), terminated, truncated, info))
        if terminated or truncated:
            records.append(("reset", td["observation"][0].numpy().astype(np.float64)))
    env.close()
    return records


def _assert_same(first: list[tuple], second: list[tuple]) -> None:
    assert len(first) == len(second)
    for step, (a, b) in enumerate(zip(first, second)):
        assert len(a) == len(b), step
        for x, y in zip(a, b):
            if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
                assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), step  # bit for bit
            else:
                assert type(x) is type(y) and x == y, step


@pytest.mark.parametrize("env_id", VELOCITY_IDS + NAVIGATION_IDS)
def test_facade_torchrl_and_batched_simulator_agree(env_id):
    seed = 5
    probe = sg_gym.make(env_id)
    actions = _actions(probe.action_space.low, probe.action_space.high, seed)
    probe.close()
    facade = _facade_trajectory(env_id, seed, actions)
    assert any(isinstance(record[0], str) for record in facade[1:]), "the trajectory should cross an episode end"
    _assert_same(facade, _torchrl_trajectory(env_id, seed, actions, num_envs=1))
    _assert_same(facade, _torchrl_trajectory(env_id, seed, actions, num_envs=3))


@pytest.mark.parametrize("env_id", VELOCITY_IDS)
def test_step_info_of_one_simulator_is_its_row_of_the_batch(env_id):
    env = sg_torchrl.make(env_id, num_envs=3, seed=1)
    td = env.reset()
    for action in _actions(env.action_spec.space.low[0].numpy(), env.action_spec.space.high[0].numpy(), 1)[:5]:
        td.set("action", torch.from_numpy(np.stack([action] * 3)))
        _, td = env.step_and_maybe_reset(td)
        rows = env.step_info()
        for index in range(3):
            one = env.step_info(index)
            assert list(one) == list(rows) and all(type(value) is float for value in one.values())
            assert one == {key: float(values[index]) for key, values in rows.items()}


def test_one_simulator_state_cache_follows_the_simulator():
    """At num_envs=1 the cache is the MjData itself: direct writes show at once, and a refresh is harmless."""
    env = sg_torchrl.make("SafetyHalfCheetahVelocity-v1", num_envs=1, seed=0)
    env.reset()
    physics = env.physics
    physics.datas[0].qpos[0] = 1.25
    assert physics.qpos()[0, 0] == 1.25
    physics.refresh()
    assert physics.qpos()[0, 0] == 1.25 and not physics.unstable.any()


@pytest.mark.parametrize("corruption", ["state", "reward"])
def test_one_simulator_faults_are_still_isolated(corruption):
    env = sg_gym.make("SafetyHalfCheetahVelocity-v1")
    env.reset(seed=0)
    action = np.zeros(env.action_space.shape, dtype=np.float32)
    core = env.torchrl_env
    if corruption == "state":
        core.physics.datas[0].qvel[:] = np.nan
    else:
        # A finite action whose control cost overflows: the raw step would emit reward -inf.
        core.step_one = lambda a, step_one=core.step_one: step_one(np.full_like(a, 1e20))
    obs, reward, cost, terminated, truncated, _ = env.step(action)
    assert truncated and not terminated and reward == 0.0 and cost == 0.0
    assert np.isfinite(obs).all() and core.physics_errors == 1
