"""The one-simulator forms of the Button levels' step (for single-env speed) equal their array forms bit for bit.

The gymnasium façade's navigation step (:mod:`sg_torchrl.envs.navigation.single`) reads contacts, the
goal button, the buttons' and gremlins' costs and the resampling timer on Python values; the batched
step reads them from ``(N, ...)`` arrays. These tests drive the robot into buttons and gremlins and
compare both forms on every step, with the timer running and stopped.
"""

from __future__ import annotations

import numpy as np
import pytest

import sg_torchrl
from sg_torchrl.envs import contacts as contacts_module
from sg_torchrl.envs.navigation.objects import Buttons, Gremlins


def _contact_states(env_id: str, seed: int, steps: int = 150):
    """An env of one simulator, then yields after each of ``steps`` steps; the robot starts next to a button
    or a gremlin (alternating episodes of 30 steps) and drives forward with some turning, so it touches them."""
    env = sg_torchrl.make(env_id, num_envs=1, seed=seed)
    env.reset()
    rng = np.random.default_rng(seed)
    buttons, gremlins = env.task.find(Buttons), env.task.find(Gremlins)
    action = np.zeros((1, env.action_dim), dtype=np.float32)
    for step in range(steps):
        if step % 30 == 0:
            xy = env.layout[0].copy()
            target = buttons if (step // 30) % 2 == 0 else gremlins
            part = env.layout_sampler.slice_of(target)
            start = xy[part.start + int(rng.integers(target.num))]
            if target is gremlins:  # a gremlin starts its circle at its centre + (0, travel)
                start = start + (0.0, gremlins.travel)
            xy[0] = start - (0.25, 0.0)  # just behind it, facing +x
            env.set_layout([0], xy[None])
        action[0] = rng.uniform(-1.0, 1.0, env.action_dim)
        action[0, 0] = 1.0  # forward
        env.physics.step(action, env.frame_skip)  # the physics only: the layout stays where it was put
        yield env


def _expected_counts(scene) -> dict[int, float]:
    row = scene.robot_contacts()[0]
    return {int(geom): float(row[geom]) for geom in np.flatnonzero(row)}


@pytest.mark.parametrize("env_id", ["SafetyPointButton1-v0", "SafetyCarButton2-v0"])
def test_contact_counts_one_equal_the_array_form(env_id, monkeypatch):
    """Scene.robot_contacts_one gives robot_contacts' row (few-contacts loop and, forced, the array path)."""
    touched = 0
    for env in _contact_states(env_id, seed=1):
        scene = env.scene
        floor = scene.model.geom("floor").id
        counts = scene.robot_contacts_one()
        assert counts == _expected_counts(scene)
        assert all(type(value) is float for value in counts.values())
        touched += any(geom != floor for geom in counts)  # a contact besides the floor
        with monkeypatch.context() as patch:  # the (N, ngeom) bincount path, whatever the number of contacts
            patch.setattr(contacts_module, "_FEW_CONTACTS", 0)
            assert env.physics.contact_counts(scene.robot_geoms)[0].tobytes() == scene.robot_contacts()[0].tobytes()
    assert touched > 20


@pytest.mark.parametrize("env_id", ["SafetyPointButton1-v0", "SafetyPointButton2-v0", "SafetyCarButton1-v0"])
def test_button_and_gremlin_float_forms_equal_the_array_forms(env_id):
    """Buttons.touches_one / goal_pressed_one / agent_costs_one, Gremlins.agent_costs_one and Buttons.tick_one
    give the array forms' values, with the resampling timer running and stopped."""
    pressed = wrong = gremlin_hits = 0
    for step, env in enumerate(_contact_states(env_id, seed=2, steps=240)):
        scene, buttons, gremlins = env.scene, env.task.find(Buttons), env.task.find(Gremlins)
        buttons.timer[0] = (0, 0, 3)[step % 3]
        buttons.goal_button[0] = step % buttons.num
        assert buttons.touches_one(scene) == buttons.touches(scene)[0].tolist()
        assert buttons.goal_pressed_one(scene) is bool(buttons.goal_pressed(scene)[0])
        for obj in (buttons, gremlins):
            out = {name: np.full((1, 1), 7.0) for name in obj.cost_names}
            obj.agent_costs_one(scene, out)
            expected = obj.costs(scene)
            for name in obj.cost_names:
                assert out[name].tobytes() == expected[name].reshape(1, 1).tobytes()
        pressed += buttons.goal_pressed_one(scene)
        wrong += float(buttons.costs(scene)["buttons"][0]) > 0
        gremlin_hits += float(gremlins.costs(scene)["gremlins"][0]) > 0
        timer = buttons.timer.copy()
        buttons.tick_one()
        np.maximum(timer - 1, 0, out=timer)
        assert buttons.timer.tobytes() == timer.tobytes()
    assert pressed and wrong and gremlin_hits


def test_tick_one_equals_tick_for_any_timer():
    env = sg_torchrl.make("SafetyPointButton1-v0", num_envs=1, seed=0)
    buttons = env.task.find(Buttons)
    for value in (-3, -1, 0, 1, 2, 10):
        buttons.timer[0] = value
        buttons.tick_one()
        one = buttons.timer.copy()
        buttons.timer[0] = value
        buttons.tick()
        assert one.tobytes() == buttons.timer.tobytes()



@pytest.mark.parametrize("num_envs", [1, 3])
def test_gremlin_trajectory_equals_the_stacked_form(num_envs):
    """Gremlins.trajectory (a reused buffer, the circle's displacements remembered per times) gives the
    centres plus Gremlins.offset's displacements bit for bit, when times repeat (a new episode), when the
    centres move in between (a reset), and once its memory of times has started over."""
    env = sg_torchrl.make("SafetyPointButton2-v0", num_envs=num_envs, seed=0)
    gremlins = env.task.find(Gremlins)
    gremlins.circle_memory = 5  # an instance override: the memory starts over within the test
    rng = np.random.default_rng(0)
    offsets = np.arange(env.frame_skip) * env.physics.timestep
    clocks = [rng.uniform(0, 20, num_envs) for _ in range(8)]
    for trial in range(40):
        if trial % 9 == 0:
            gremlins.centres[:] = rng.uniform(-1.5, 1.5, gremlins.centres.shape)
        times = clocks[int(rng.integers(len(clocks)))][:, None] + offsets
        expected = np.empty((*times.shape, gremlins.num, 3))
        expected[..., :2] = gremlins.centres[:, None] + gremlins.offset(times)[:, :, None]
        expected[..., 2] = gremlins.height
        assert gremlins.trajectory(times).tobytes() == expected.tobytes(), trial
    assert len(gremlins._circles) <= 5


@pytest.mark.parametrize("env_id", ["SafetyPointButton1-v0", "SafetyCarGoal1-v0", "SafetyDoggoGoal1-v0"])
def test_float_clip_equals_the_array_clip(env_id):
    """SingleNavigationStep._clip writes np.minimum(np.maximum(action, low), high) into the control bit for bit:
    random float32 and float64 actions within, beyond and exactly at the bounds, signed zeros and NaN."""
    env = sg_torchrl.make(env_id, num_envs=1, seed=0)
    single = env._single
    assert single is not None and single._bounds is not None
    low, high = env._clip_low, env._clip_high
    rng = np.random.default_rng(7)
    specials = np.array([0.0, -0.0, np.nan, np.inf, -np.inf])
    for trial in range(500):
        action = rng.uniform(1.5 * low, 1.5 * high).astype(np.float32 if trial % 2 else np.float64)
        picks = rng.random(action.shape) < 0.3
        action[picks] = rng.choice(np.concatenate([specials, low.reshape(-1), high.reshape(-1)]), size=picks.sum())
        if trial % 3 == 0:
            action = action.reshape(-1)  # (act_dim,) as well as (1, act_dim)
        assert single._clip(action)
        expected = np.minimum(np.maximum(action, low), high)
        assert single._ctrl.tobytes() == expected.astype(np.float64).reshape(1, -1).tobytes(), trial
    assert not single._clip(np.zeros(env.action_dim + 1, dtype=np.float32))  # the array form raises on that


def test_one_simulator_instability_flags_follow_the_counters():
    """MujocoBatch._check_one (Python copies of the count and flag) flags exactly the steps on which MuJoCo reset
    the simulator, including a second divergence right after the first with no env reset between (MuJoCo's
    reset leaves its counter at 1 both times, so the counters are cleared once reported), around env resets,
    for plain and driven (gremlins) physics."""
    from sg_torchrl.envs.physics import _UNSTABLE

    for env_id in ("SafetyPointGoal1-v0", "SafetyPointButton1-v0"):
        env = sg_torchrl.make(env_id, num_envs=1, seed=0)
        env.reset()
        physics = env.physics
        action = np.zeros((1, env.action_dim))
        for step in range(14):
            if step in (2, 3, 9):
                physics.datas[0].qvel[:] = np.nan  # MuJoCo resets it within the next step (BADQVEL)
            flags = physics.step(action, env.frame_skip)
            assert flags is physics.unstable and bool(flags[0]) == (step in (2, 3, 9)), step
            assert int(physics._warnings[0, _UNSTABLE].sum()) == 0 == int(physics._unstable_counts[0])
            if step in (5, 11):
                env.reset()
                assert not physics.unstable[0]


def test_batched_instability_flags_repeat_divergences_of_one_simulator():
    """At N=3, a simulator that diverges on consecutive steps is flagged each time and the others never are."""
    env = sg_torchrl.make("SafetyPointGoal1-v0", num_envs=3, seed=0)
    env.reset()
    physics = env.physics
    action = np.zeros((3, env.action_dim))
    for step in range(6):
        if step in (1, 2, 4):
            physics.datas[1].qvel[:] = np.nan
        flags = physics.step(action, env.frame_skip)
        assert flags.tolist() == [False, step in (1, 2, 4), False], step
