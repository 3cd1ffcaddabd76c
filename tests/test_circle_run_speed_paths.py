"""The one-simulator forms of the Circle and Run levels' step equal their array forms bit for bit.

The gymnasium façade's navigation step (:mod:`sg_torchrl.envs.navigation.single`) computes the Circle
reward (``CircleTask.reward_one``), the Run reward (``RunTask.reward_one``) and the sigwalls' cost
(``Sigwalls.agent_costs_one``) on Python floats; the batched step computes them on ``(N, ...)`` arrays.
These tests write random and edge-case states into the one simulator's state cache (the robot's position,
orientation and velocimeter) and compare both forms on each.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import sg_torchrl
from sg_torchrl.envs.navigation.objects import Sigwalls

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")  # NaN and inf edge cases, on purpose

EDGES = [0.0, -0.0, 1e-13, -1e-13, 1.125, -1.125, 0.5, -0.5, 1.5, -1.5, 1e300, -1e300, math.inf, -math.inf, math.nan]


def _same(a: float, b: float) -> bool:
    """Equal bit for bit (NaN equals NaN; +0.0 and -0.0 differ)."""
    return type(a) is float and (math.isnan(a) and math.isnan(b) or (a == b and math.copysign(1.0, a) == math.copysign(1.0, b)))


def _env(env_id: str):
    env = sg_torchrl.make(env_id, num_envs=1, seed=3)
    env.reset()
    return env


def _positions(rng: np.random.Generator, count: int):
    """Random planar positions at several scales, then every pair of edge values."""
    for _ in range(count):
        yield rng.standard_normal(2) * 10.0 ** rng.integers(-4, 3, 2)
    for x in EDGES:
        for y in EDGES:
            yield np.array([x, y])


@pytest.mark.parametrize("env_id", ["SafetyPointCircle1-v0", "SafetyPointCircle2-v0", "SafetyCarCircle1-v0"])
def test_circle_reward_one_equals_the_array_form(env_id):
    env = _env(env_id)
    task, scene = env.task, env.scene
    velocimeter = scene.sensordata()[0, task._velocimeter]
    rng = np.random.default_rng(0)
    checked = 0
    for xy in _positions(rng, 3000):
        scene.agent_xy()[0] = xy
        scene.agent_mat()[0] = rng.standard_normal((3, 3)) * 10.0 ** rng.integers(-3, 3, (3, 3))
        velocimeter[:] = rng.standard_normal(3) * 10.0 ** rng.integers(-3, 3, 3)
        if rng.random() < 0.05:
            velocimeter[int(rng.integers(3))] = rng.choice([0.0, -0.0, math.inf, math.nan])
        expected = float(task.reward(env)[0])
        got = task.reward_one(env)
        assert _same(got, expected), (xy, got, expected)
        checked += 1
    # the velocity's buffer of the float form leaves the array form's operands alone
    assert np.array_equal(task.agent_velocity(env), task.agent_velocity(env), equal_nan=True)
    assert checked > 3000
    env.close()


def test_run_reward_one_equals_the_array_form():
    env = _env("SafetyPointRun0-v0")
    task, scene = env.task, env.scene
    rng = np.random.default_rng(1)
    for xy in _positions(rng, 3000):
        last = float(rng.choice([0.0, -0.0, -60_000.0, float(rng.standard_normal()) * 1e5, math.nan, -math.inf]))
        scene.agent_xy()[0] = xy
        task._last_potential[0] = last
        got = task.reward_one(env)
        after_one = task._last_potential.copy()
        task._last_potential[0] = last
        expected = float(task.reward(env)[0])
        assert _same(got, expected), (xy, last, got, expected)
        assert np.array_equal(after_one, task._last_potential, equal_nan=True)
    env.close()


@pytest.mark.parametrize("env_id", ["SafetyPointCircle1-v0", "SafetyPointCircle2-v0", "SafetyPointRun0-v0"])
def test_sigwalls_cost_one_equals_the_array_form(env_id):
    env = _env(env_id)
    scene = env.scene
    walls = env.task.find(Sigwalls)
    out = {"out_of_boundary": np.full((1, 1), -1.0)}
    rng = np.random.default_rng(2)
    seen = set()
    for xy in _positions(rng, 2000):
        scene.agent_xy()[0] = xy * walls.bound  # around the walls
        walls.agent_costs_one(scene, out)
        expected = walls.costs(scene)["out_of_boundary"][0]
        assert _same(out["out_of_boundary"].item(0), float(expected))
        seen.add(float(expected))
    assert seen == {0.0, 1.0}
    env.close()


def test_facade_takes_the_one_simulator_step():
    """The façade's step on Circle and Run runs the one-simulator path, whose hooks are these forms."""
    import sg_torchrl.gym as sgym

    for env_id in ("SafetyPointCircle2-v0", "SafetyPointRun0-v0"):
        env = sgym.make(env_id)
        env.reset(seed=0)
        assert env.unwrapped.torchrl_env._single is not None
        env.close()


@pytest.mark.parametrize("env_id", ["SafetyPointCircle1-v0", "SafetyPointRun0-v0", "SafetyPointGoal1-v0"])
def test_after_step_one_equals_the_array_form(env_id):
    """Task.after_step_one answers False without arrays for tasks without events, as after_step's zeros say."""
    env = _env(env_id)
    for _ in range(20):
        env.physics.step(np.zeros((1, env.action_dim)), env.frame_skip)
        assert env.task.after_step_one(env) is bool(env.task.after_step(env)[0])
    env.close()
