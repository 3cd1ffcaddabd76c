"""The one-simulator path gives the batched path's data, bit for bit.

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
NAVIGATION_IDS = ["SafetyPointGoal1-v0", "SafetyCarButton1-v0", "SafetyRacecarPush1-v0", "SafetyPointGoal0-v0",
                  "SafetyPointGoal2-v0", "SafetyPointButton1-v0"]
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


# ------------------------------------------------------------------ navigation's one-simulator step
def test_navigation_one_simulator_step_applies_where_it_should():
    """The façade's navigation envs take SingleNavigationStep; batched, multi-robot and pixel envs do not."""
    assert sg_torchrl.make("SafetyPointGoal1-v0", num_envs=1)._single is not None
    assert sg_torchrl.make("SafetyPointButton1-v0", num_envs=1)._single is not None
    assert sg_torchrl.make("SafetyPointGoal1-v0", num_envs=2)._single is None
    assert sg_torchrl.make("SafetyPointGoal1-v0", num_envs=1, obs_mode="vector+rgb", image_size=16)._single is None


@pytest.mark.parametrize("env_id", ["SafetyPointGoal2-v0", "SafetyPointButton1-v0"])
def test_navigation_float_costs_and_distances_equal_the_array_forms(env_id):
    """Scene.planar_distances_one and Hazards.agent_costs_one (Python floats) give planar_distance's and
    Hazards.costs' values bit for bit, with the robot inside 0 to 4 hazards at once (3+ take the array form)."""
    from sg_torchrl.envs.navigation.objects import Hazards

    env = sg_torchrl.make(env_id, num_envs=1, seed=3)
    env.reset()
    hazards, sampler, scene = env.task.find(Hazards), env.layout_sampler, env.scene
    part = sampler.slice_of(hazards)
    rng = np.random.default_rng(0)
    buffers = {name: np.zeros((1, 1)) for name in hazards.cost_names}
    for trial in range(200):
        xy = rng.uniform(-1.5, 1.5, size=(1, sampler.size, 2))
        robot = xy[0, 0]
        inside = trial % 5  # hazards whose centre is within reach of the robot
        xy[0, part.start : part.start + inside] = robot + rng.uniform(-0.15, 0.15, size=(inside, 2))
        env.set_layout([0], xy, rng.uniform(-np.pi, np.pi, size=(1, sampler.size)))
        positions = hazards.positions(scene)
        assert np.array(scene.planar_distances_one(positions)).tobytes() == scene.planar_distance(positions)[0].tobytes()
        hazards.agent_costs_one(scene, buffers)
        assert buffers["hazards"].tobytes() == hazards.costs(scene)["hazards"].reshape(1, 1).tobytes()


def test_navigation_one_simulator_faults_are_still_isolated():
    env = sg_gym.make("SafetyPointGoal1-v0")
    env.reset(seed=0)
    core = env.torchrl_env
    core.physics.datas[0].qvel[:] = np.nan
    obs, reward, cost, terminated, truncated, _ = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
    assert truncated and not terminated and reward == 0.0 and cost == 0.0
    assert np.isfinite(obs).all() and core.physics_errors == 1


@pytest.mark.parametrize("env_id", ["SafetyPointGoal1-v0", "SafetyPointButton1-v0"])
def test_navigation_goal_reached_on_one_simulator(env_id):
    """Steps that reach the goal (the robot starts on it, or drives into the goal button): the façade's
    one-simulator step and the TorchRL step at N=1 emit the same values."""
    facade = sg_gym.make(env_id)
    facade.reset(seed=2)
    batched = sg_torchrl.make(env_id, num_envs=1, seed=2)
    td = batched.reset()
    for env in (facade.torchrl_env, batched):
        xy = env.layout[0].copy()
        if env_id.endswith("Goal1-v0"):
            xy[env.layout_sampler.slice_of(env.task.goal)] = xy[0]
        else:  # the robot just behind the goal button, facing it
            xy[0] = env.task.goal.positions(env.scene)[0, 0] - (0.3, 0.0)
        env.set_layout([0], xy[None])
    actions = np.tile(np.array([1.0, 0.0], dtype=np.float32), (40, 1))
    facade_records = [facade.step(action)[:5] for action in actions]
    records = []
    for action in actions:
        nxt = batched.step(td.set("action", torch.from_numpy(action[None])))["next"]
        records.append((nxt["observation"][0].numpy().astype(np.float64), float(nxt["reward"][0, 0]),
                        float(nxt["cost"][0, 0]), bool(nxt["terminated"][0, 0]), bool(nxt["truncated"][0, 0])))
    assert any(record[1] > 0.5 for record in records), "a goal should be reached"
    _assert_same([tuple(record) for record in facade_records], records)


def _reference_lidar(pos, mat, groups, num_bins, max_dist, alias):
    """The pseudo-lidar in its textbook form: einsum frame change, one target and one bin at a time."""
    out = np.zeros((pos.shape[0], len(groups), num_bins))
    for g, targets in enumerate(groups):
        offset = np.concatenate([targets - pos[:, None, :2], np.broadcast_to(-pos[:, None, 2:3], targets.shape[:2] + (1,))],
                                axis=-1)
        ego = np.einsum("nki,nij->nkj", offset, mat[:, :, :2])
        distance = np.hypot(ego[..., 0], ego[..., 1])
        position = (np.arctan2(ego[..., 1], ego[..., 0]) % (2 * np.pi)) * (num_bins / (2 * np.pi))
        reading = np.exp(-distance) if max_dist is None else np.maximum(0.0, max_dist - distance) / max_dist
        for n in range(pos.shape[0]):
            for k in range(targets.shape[1]):
                row = np.zeros(num_bins)
                b = min(int(position[n, k]), num_bins - 1)
                if alias:
                    fraction = min(max(position[n, k] - b, 0.0), 1.0)
                    row[(b + 1) % num_bins] = fraction * reading[n, k]
                    row[(b - 1) % num_bins] = (1.0 - fraction) * reading[n, k]
                row[b] = reading[n, k]
                out[n, g] = np.maximum(out[n, g], row)
    return out


def test_pseudo_lidars_equal_the_textbook_form():
    """The pseudo-lidar's rewritten arithmetic (frame change without einsum, every group's and bin's writes
    in one pass) gives the textbook form's readings bit for bit, blocks and separate outputs."""
    from sg_torchrl.envs.navigation.lidar import pseudo_lidars

    rng = np.random.default_rng(4)
    for trial in range(300):
        n, num_bins = int(rng.integers(1, 4)), int(rng.choice([16, 16, 8, 3, 2]))
        alias, max_dist = bool(trial % 2), (None if trial % 5 == 0 else 3.0)
        pos = np.concatenate([rng.uniform(-2, 2, (n, 2)), rng.uniform(0, 0.3, (n, 1))], axis=1)
        mat = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]
        groups = [rng.uniform(-3, 3, size=(n, int(size), 2)) for size in rng.integers(0, 5, size=3)]
        expected = _reference_lidar(pos, mat, groups, num_bins, max_dist, alias)
        block = np.full((n, len(groups), num_bins), 7.0)
        pseudo_lidars(pos, mat, groups, block, num_bins=num_bins, max_dist=max_dist, alias=alias)
        outs = [np.full((n, num_bins), 7.0) for _ in groups]
        pseudo_lidars(pos, mat, groups, outs, num_bins=num_bins, max_dist=max_dist, alias=alias)
        assert block.tobytes() == expected.tobytes(), trial
        assert np.stack(outs, axis=1).tobytes() == expected.tobytes(), trial


def test_pseudo_lidars_one_equals_the_array_form():
    """pseudo_lidars_one (Python floats) writes pseudo_lidars' readings bit for bit: random poses (tilted
    too), groups of 0-5 targets near and beyond max_dist, targets straight ahead (angles at 0 and a hair
    below 2 pi), 3-16 bins; it declines (False, output untouched) where it does not apply."""
    from sg_torchrl.envs.navigation.lidar import pseudo_lidars, pseudo_lidars_one

    rng = np.random.default_rng(5)
    for trial in range(2000):
        num_bins = int(rng.choice([16, 16, 8, 5, 3]))
        max_dist = float(rng.choice([3.0, 3.0, 1.0, 0.7]))
        pos = np.concatenate([rng.uniform(-2, 2, (1, 2)), rng.uniform(0, 0.3, (1, 1))], axis=1)
        mat = np.eye(3)[None] if trial % 7 == 0 else np.linalg.qr(rng.normal(size=(1, 3, 3)))[0]
        groups = [rng.uniform(-4, 4, size=(1, int(size), 2)) for size in rng.integers(0, 6, size=int(rng.integers(1, 5)))]
        if trial % 7 == 0 and groups[0].shape[1]:  # straight ahead of an upright robot: angle 0 or -0 ... 2 pi
            groups[0][0, 0] = pos[0, :2] + (rng.uniform(0.1, 1.0), float(rng.choice([0.0, -0.0, -1e-17, 1e-17])))
        expected = np.full((1, len(groups), num_bins), 7.0)
        pseudo_lidars(pos, mat, groups, expected, num_bins=num_bins, max_dist=max_dist)
        row = np.full(len(groups) * num_bins, 7.0)
        assert pseudo_lidars_one(pos, mat, groups, row, num_bins=num_bins, max_dist=max_dist)
        assert row.tobytes() == expected.reshape(-1).tobytes(), trial
    pos, mat = np.zeros((1, 3)), np.eye(3)[None]
    row = np.full(16, 7.0)
    for groups, options in (([np.full((1, 1, 2), np.nan)], {}), ([np.full((1, 2, 2), np.inf)], {}),
                            ([np.ones((1, 1, 2))], {"max_dist": None}), ([np.ones((1, 1, 2))], {"num_bins": 2})):
        assert not pseudo_lidars_one(pos, mat, groups, row, **options)
        assert (row == 7.0).all()


def test_float_remainder_equals_numpys():
    """pseudo_lidars_one reduces angles with Python's float ``%`` where the array form calls ``np.remainder``:
    the same values on arctan2's outputs, signed zeros, +-pi and the tiniest negatives included."""
    from sg_torchrl.envs.navigation.lidar import TWO_PI

    rng = np.random.default_rng(6)
    edges = [0.0, -0.0, np.pi, -np.pi, 5e-324, -5e-324, 1e-300, -1e-300, -1e-17, np.nextafter(-np.pi, 0.0),
             np.nextafter(np.pi, 0.0), np.nextafter(0.0, -1.0)]
    angles = np.concatenate([np.arctan2(rng.normal(size=200_000), rng.normal(size=200_000)),
                             np.arctan2(rng.normal(size=1000) * 1e-12, -1.0), edges])
    expected = np.remainder(angles, TWO_PI)
    assert np.array([angle % TWO_PI for angle in angles.tolist()]).tobytes() == expected.tobytes()
