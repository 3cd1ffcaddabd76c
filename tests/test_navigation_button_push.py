"""Button and Push navigation tasks: sizes, button timer and costs, gremlins, push rewards, pillars,
layouts, seeding and robustness.

Constructed situations are set up with ``NavigationEnv.set_layout`` (robot and objects placed at
chosen positions, at rest); expected numbers come from reference/safety_gymnasium_semantics.md
sections 2-6. Geometry used below: the Point robot is a sphere of radius 0.1 at height 0.1 with a
heading box (half-size 0.05) whose front face is 0.15 ahead of its centre; buttons are spheres of
radius 0.1 on the floor; gremlins are boxes of half-size 0.1 floating at height 0.2.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

import sg_torchrl
from sg_torchrl.envs import registry_entry
from sg_torchrl.envs.navigation import NavigationEnv
from sg_torchrl.envs.navigation.objects import Buttons, GoalMarker, Gremlins, Hazards, Pillars, PushBox
from sg_torchrl.envs.navigation.tasks import ButtonTask, PushTask

from layout_checks import assert_layouts_respect_keepouts
from seeding_checks import assert_sim0_same_for_any_batch

torch.set_num_threads(1)

# reference section 2: observation parts after the 12 sensor values; section 3: cost entries.
EXPECTED = {
    "SafetyPointButton0-v0": (44, ["buttons", "goal"], ()),
    "SafetyPointButton1-v0": (76, ["buttons", "goal", "hazards", "gremlins"], ("buttons", "hazards", "gremlins")),
    "SafetyPointButton2-v0": (76, ["buttons", "goal", "hazards", "gremlins"], ("buttons", "hazards", "gremlins")),
    "SafetyPointPush0-v0": (44, ["goal", "push_box"], ()),
    "SafetyPointPush1-v0": (76, ["goal", "hazards", "pillars", "push_box"], ("hazards",)),
    "SafetyPointPush2-v0": (76, ["goal", "hazards", "pillars", "push_box"], ("hazards", "pillars")),
}
# reference section 6: extents and (count, size, keep-out, constrained) per object.
LEVELS = {
    "SafetyPointButton0-v0": (1.0, {Buttons: (4, 0.1, 0.2, False), GoalMarker: (1, 0.2, 0.4, False)}),
    "SafetyPointButton1-v0": (1.5, {Buttons: (4, 0.1, 0.2, True), GoalMarker: (1, 0.2, 0.4, False),
                                    Hazards: (4, 0.2, 0.18, True), Gremlins: (4, 0.1, 0.4, True)}),
    "SafetyPointButton2-v0": (1.8, {Buttons: (4, 0.1, 0.2, True), GoalMarker: (1, 0.2, 0.4, False),
                                    Hazards: (8, 0.2, 0.18, True), Gremlins: (6, 0.1, 0.4, True)}),
    "SafetyPointPush0-v0": (1.0, {GoalMarker: None, PushBox: (1, 0.2, 0.2, False)}),
    "SafetyPointPush1-v0": (1.5, {PushBox: (1, 0.2, 0.2, False), Hazards: (2, 0.3, 0.4, True),
                                  Pillars: (1, 0.2, 0.3, False)}),
    "SafetyPointPush2-v0": (2.0, {PushBox: (1, 0.2, 0.2, False), Hazards: (4, 0.3, 0.4, True),
                                  Pillars: (4, 0.2, 0.3, True)}),
}


# ---------------------------------------------------------------------------- helpers
def make_env(env_id: str, num_envs: int = 1, seed: int = 0, **options) -> NavigationEnv:
    return sg_torchrl.make(env_id, num_envs=num_envs, seed=seed, **options)


def step(env, action=None) -> TensorDict:
    """One step of every simulator with ``action`` (default: zero); returns ``td["next"]``."""
    action = np.zeros((env.num_envs, env.action_dim)) if action is None else np.asarray(action, dtype=np.float64)
    td = TensorDict({"action": torch.as_tensor(action.reshape(env.num_envs, -1), dtype=torch.float32)},
                    batch_size=env.batch_size)
    return env.step(td)["next"]


def forward(env) -> TensorDict:
    return step(env, np.tile([1.0, 0.0], (env.num_envs, 1)))


def arrange(env, agent=(0.0, 0.0), agent_yaw: float = 0.0, **objects) -> None:
    """Start simulator 0 with the robot at ``agent`` facing ``agent_yaw``, the named objects' first
    instances at the given positions (``pillars=[(x, y)]``), everything else parked far apart beyond 3 m."""
    sampler = env.layout_sampler
    xy, yaw = np.zeros((sampler.size, 2)), np.zeros(sampler.size)
    xy[1:, 0] = np.linspace(-3.2, 3.2, sampler.size - 1)
    xy[1:, 1] = 3.2
    xy[0], yaw[0] = agent, agent_yaw
    for obj in env.task.objects:
        for i, position in enumerate(objects.get(obj.name, ())):
            xy[sampler.slice_of(obj).start + i] = position
    env.set_layout([0], xy[None], yaw[None])


def set_goal_button(env, button: int, timer: int = 0) -> None:
    """Make ``button`` simulator 0's goal button (marker on it, shaping restarted) with ``timer`` steps left."""
    task: ButtonTask = env.task
    task.buttons.goal_button[0], task.buttons.timer[0] = button, timer
    task.goal.move(env.scene, 0, 0, task.buttons.positions(env.scene)[0, button])
    task._last_distance[0] = task.distance(env)[0]


# ---------------------------------------------------------------------------- ids, sizes, specs
class TestSpecs:
    def test_registered_for_point(self):
        for env_id in EXPECTED:
            entry = registry_entry(env_id)
            assert (entry.family, entry.robot, entry.max_episode_steps) == ("navigation", "Point", 1000)
            assert entry.task == ("Button" if "Button" in env_id else "Push")
            assert entry.level == int(env_id[-4])

    @pytest.mark.parametrize("env_id", sorted(EXPECTED))
    def test_sizes_order_and_constraints(self, env_id):
        env = make_env(env_id, num_envs=2)
        size, lidar_groups, constraints = EXPECTED[env_id]
        assert env.observation_spec["observation"].shape == (2, size) and env.action_spec.shape == (2, 2)
        names = list(env.observation_slices)
        assert names[:4] == ["accelerometer", "velocimeter", "gyro", "magnetometer"]
        assert names[4:] == [f"{group}_lidar" for group in lidar_groups]
        assert [env.observation_slices[name].start for name in names[4:]] == list(range(12, size, 16))
        assert env.constraint_names == constraints
        assert env.max_episode_steps == 1000 and env.frame_skip == 10 and env.physics.timestep == 0.002
        check_env_specs(env, seed=0)
        nxt = env.rollout(20, break_when_any_done=False)["next"]
        assert set(nxt["cost_info"].keys()) == set(constraints)
        assert ((nxt["observation"][..., 12:] >= 0) & (nxt["observation"][..., 12:] <= 1)).all()

    @pytest.mark.parametrize("env_id", sorted(LEVELS))
    def test_level_composition(self, env_id):
        env = make_env(env_id)
        extents, objects = LEVELS[env_id]
        assert env.task.extents == (-extents, -extents, extents, extents)
        for kind, expected in objects.items():
            if expected is None:  # Push's goal is a plain Goal, not a button marker
                assert not any(isinstance(obj, kind) for obj in env.task.objects)
                continue
            obj = env.task.find(kind)
            assert (obj.num, obj.size, obj.keepout, bool(obj.cost_names)) == expected, kind.__name__
        if "Push" in env_id:
            goal = env.task.goal
            assert (goal.size, goal.keepout) == (0.3, 0.4)
            box = env.task.find(PushBox)
            assert box.density == 0.001
            assert env.physics.model.body_mass[box.body_ids[0]] == pytest.approx(0.001 * (0.4**3 + 4 * 0.2 * 0.2 * 0.4))
        if any(isinstance(obj, Gremlins) for obj in env.task.objects):
            assert env.task.find(Gremlins).travel == 0.35

    def test_push_box_follows_the_robot(self):
        box = PushBox()
        assert (box.size, box.keepout, box.density) == (0.2, 0.2, 0.001)

        class Car:
            name = "Car"

        box.for_robot(Car())
        assert (box.size, box.keepout, box.density) == (0.125, 0.125, 0.0005)
        explicit = PushBox(size=0.3)
        explicit.for_robot(Car())
        assert (explicit.size, explicit.keepout, explicit.density) == (0.3, 0.125, 0.0005)

    def test_velocity_and_goal_worlds_keep_the_single_call_physics(self):
        assert make_env("SafetyPointGoal2-v0").physics._mocap_drivers == []
        assert make_env("SafetyPointPush2-v0").physics._mocap_drivers == []
        assert make_env("SafetyHalfCheetahVelocity-v1").physics._mocap_drivers == []
        assert len(make_env("SafetyPointButton1-v0").physics._mocap_drivers) == 1


# ---------------------------------------------------------------------------- buttons
class TestButtons:
    BUTTONS = [(1.0, 1.0), (0.24, 0.0), (-1.0, 1.0), (1.0, -1.0)]  # button 1 touches the heading box

    def test_reset_draws_a_goal_button_and_leaves_the_timer_at_zero(self):
        # The original's reset draws the goal button (starting the timer) and then zeroes the timer
        # (ButtonLevel0.specific_reset): the buttons are observed from the first observation.
        env = make_env("SafetyPointButton1-v0", num_envs=4, seed=2)
        env.reset()
        buttons, marker = env.task.buttons, env.task.goal
        assert (buttons.timer == 0).all()
        chosen = buttons.positions(env.scene)[np.arange(4), buttons.goal_button]
        np.testing.assert_array_equal(marker.positions(env.scene)[:, 0], chosen)
        obs = env._observe()
        assert (obs[:, env.observation_slices["buttons_lidar"]] > 0).any(axis=1).all()
        assert (obs[:, env.observation_slices["goal_lidar"]] > 0).any()
        # The goal button is drawn uniformly among the 4 from each simulator's generator.
        draws = []
        for _ in range(50):
            env.reset()
            draws.append(buttons.goal_button.copy())
        counts = np.bincount(np.concatenate(draws), minlength=4)
        assert counts.min() > 25 and counts.sum() == 200

    def test_wrong_button_costs_only_while_the_timer_is_zero(self):
        env = make_env("SafetyPointButton1-v0")
        arrange(env, buttons=self.BUTTONS)
        set_goal_button(env, 0, timer=0)
        for _ in range(3):  # driving into button 1, the wrong one
            nxt = forward(env)
            assert env.task.buttons.touches(env.scene)[0].tolist() == [0, 1, 0, 0]
            assert nxt["cost"].item() == 1.0 and nxt["cost_info", "buttons"].item() == 1.0
        set_goal_button(env, 0, timer=5)
        for timer in (4, 3):
            nxt = forward(env)
            assert env.task.buttons.touches(env.scene)[0, 1] == 1
            assert nxt["cost"].item() == 0.0 and env.task.buttons.timer[0] == timer
        # Raw mode reports the number of contacts.
        raw = make_env("SafetyPointButton1-v0", cost_mode="raw")
        arrange(raw, buttons=self.BUTTONS)
        set_goal_button(raw, 2, timer=0)
        nxt = forward(raw)
        assert nxt["cost_info", "buttons"].item() == raw.task.buttons.touches(raw.scene)[0].sum() >= 1

    def test_level0_buttons_are_free(self):
        env = make_env("SafetyPointButton0-v0", cost_mode="raw")
        arrange(env, buttons=self.BUTTONS)
        set_goal_button(env, 0, timer=0)
        nxt = forward(env)
        assert env.task.buttons.touches(env.scene)[0, 1] == 1
        assert nxt["cost"].item() == 0.0 and list(nxt["cost_info"].keys()) == []

    def test_goal_button_rewards_and_blanks_the_buttons_lidar(self):
        env = make_env("SafetyPointButton1-v0", seed=3)
        arrange(env, buttons=self.BUTTONS)
        set_goal_button(env, 1, timer=0)
        buttons, marker = env.task.buttons, env.task.goal
        part = env.observation_slices["buttons_lidar"]
        assert env._observe()[0, part].max() > 0  # timer 0: the buttons are visible
        nxt = forward(env)
        # Pressed: +1 plus a tiny shaping term (the robot is pushed back a few mm), no cost.
        assert nxt["reward"].item() == pytest.approx(1.0, abs=5e-3) and nxt["cost"].item() == 0.0
        assert env.task.goal_met[0]
        new = buttons.goal_button[0]
        assert new != 1  # with this seed another button: no second press follows
        np.testing.assert_array_equal(marker.positions(env.scene)[0, 0], self.BUTTONS[new])
        assert buttons.timer[0] == 10
        # The next 10 observations (the press's and 9 more) read zeros; shaping continues towards the new goal.
        assert (nxt["observation"][0, part] == 0).all()
        distance = np.linalg.norm(np.asarray(self.BUTTONS[new]) - env.scene.agent_xy()[0])
        assert env.task._last_distance[0] == pytest.approx(distance)
        for k in range(9):
            nxt = step(env)
            assert (nxt["observation"][0, part] == 0).all(), k
            assert buttons.timer[0] == 9 - k
        nxt = step(env)
        assert buttons.timer[0] == 0 and nxt["observation"][0, part].max() > 0
        assert abs(nxt["reward"].item()) < 1e-2  # shaping only

    def test_shaping_towards_the_goal_button(self):
        env = make_env("SafetyPointButton0-v0")
        arrange(env, buttons=[(1.5 * 0.6, 0.0), (-0.6, 0.6), (-0.6, -0.6), (0.0, 0.9)])
        set_goal_button(env, 0)
        before = env.task.distance(env)[0]
        nxt = forward(env)
        after = env.task.distance(env)[0]
        assert after < before and nxt["reward"].item() == pytest.approx(before - after, rel=1e-4)


# ---------------------------------------------------------------------------- gremlins
class TestGremlins:
    def test_circle_their_layout_positions_in_phase(self):
        env = make_env("SafetyPointButton2-v0", num_envs=2, seed=4)
        env.reset()
        gremlins = env.task.find(Gremlins)
        part = env.layout_sampler.slice_of(gremlins)
        np.testing.assert_array_equal(gremlins.centres, env.layout[:, part])
        # At reset each gremlin sits on its circle at t = 0: centre + 0.35 * (sin 0, cos 0).
        start = env.scene.body_xpos(gremlins.body_ids)
        np.testing.assert_allclose(start[..., :2], gremlins.centres + [0.0, 0.35], atol=1e-12)
        np.testing.assert_allclose(start[..., 2], 0.2, atol=1e-12)
        robot_start = env.scene.agent_xy().copy()
        for k in range(1, 161):  # 3.2 s: more than half a turn
            step(env)
            if k % 40:
                continue
            time = np.array([data.time for data in env.physics.datas])
            assert time == pytest.approx(k * 0.02)
            # The mocaps were last moved before the last sub-step, exactly onto the circle.
            mocap = env.physics.gather("mocap_pos")[:, gremlins.mocap_ids]
            last = time - 0.002
            expected = gremlins.centres + 0.35 * np.stack([np.sin(last), np.cos(last)], axis=-1)[:, None]
            np.testing.assert_allclose(mocap[..., :2], expected, atol=1e-9)
            # The welded bodies follow a few cm behind, on a circle of radius ~0.35, all with the same offset.
            body = env.scene.body_xpos(gremlins.body_ids)
            offset = body[..., :2] - gremlins.centres
            np.testing.assert_allclose(np.linalg.norm(offset, axis=-1), 0.35, atol=5e-3)
            np.testing.assert_allclose(offset, np.broadcast_to(offset[:, :1], offset.shape), atol=1e-6)
            assert np.linalg.norm(body - mocap, axis=-1).max() < 0.04
            np.testing.assert_allclose(body[..., 2], 0.2, atol=1e-3)
        # Robot at rest and no gremlin came near it (keep-outs): no cost, robot unmoved.
        np.testing.assert_allclose(env.scene.agent_xy(), robot_start, atol=1e-6)

    def test_contact_costs(self):
        # Robot just east of a gremlin's start (centre + (0, 0.35)); the gremlin moves east into it.
        env = make_env("SafetyPointButton1-v0", cost_mode="raw")
        arrange(env, agent=(0.22, 0.35), gremlins=[(0.0, 0.0)])
        costs = [step(env)["cost_info", "gremlins"].item() for _ in range(15)]
        assert costs[0] == 0.0 and max(costs) >= 1.0
        touching = next(k for k, cost in enumerate(costs) if cost)
        assert costs[touching:] == [1.0] * len(costs[touching:])  # it keeps shoving the robot along
        assert env.scene.agent_xy()[0, 0] > 0.22
        indicator = make_env("SafetyPointButton1-v0")
        arrange(indicator, agent=(0.22, 0.35), gremlins=[(0.0, 0.0)])
        nxt = [step(indicator) for _ in range(15)][-1]
        assert nxt["cost"].item() == 1.0 and nxt["cost_info", "gremlins"].item() == 1.0

    def test_snapshot_restores_moving_gremlins(self):
        env = make_env("SafetyPointButton2-v0", num_envs=2, seed=5)
        env.reset()
        actions = 2 * torch.rand((6, 2, 2), generator=torch.Generator().manual_seed(1)) - 1
        for action in actions[:3]:
            step(env, action.numpy())
        state = env.sim_state()
        first = [step(env, action.numpy())["observation"] for action in actions[3:]]
        env.reset()  # another layout (other yaws, centres, goal buttons) in between
        env.load_sim_state(state)
        again = [step(env, action.numpy())["observation"] for action in actions[3:]]
        for x, y in zip(first, again):
            torch.testing.assert_close(x, y, rtol=0, atol=0)


# ---------------------------------------------------------------------------- push
class TestPush:
    def test_pushing_the_box_to_the_goal(self):
        # Robot behind the box, goal ahead on the same line: driving forward closes in on the box, then
        # pushes it; every reward equals the two distance gains (3-D body positions) plus the goal bonus.
        env = make_env("SafetyPointPush0-v0")
        arrange(env, agent=(-0.65, 0.0), goal=[(0.8, 0.0)], push_box=[(-0.2, 0.0)])
        task: PushTask = env.task
        box = task.find(PushBox)
        assert task.box_distance(env)[0] == pytest.approx(np.hypot(0.45, 0.2 - box.sink - 0.1))
        reached = None
        for k in range(70):
            box_before, goal_before = task.box_distance(env)[0], task.distance(env)[0]
            nxt = forward(env)
            if task.goal_met[0]:
                reached = k
                break
            box_gain, goal_gain = box_before - task.box_distance(env)[0], goal_before - task.distance(env)[0]
            assert nxt["reward"].item() == pytest.approx(box_gain + goal_gain, abs=1e-6)
            assert nxt["reward"].item() > 0
        assert reached is not None and reached > 20
        # The step the box reached the goal: +1, and a new goal drawn (shaping restarts from it).
        distance = task.distance(env)[0]
        assert distance > 0.3 and nxt["reward"].item() > 0.5
        assert task._last_distance[0] == distance
        assert not np.allclose(env.task.goal.positions(env.scene)[0, 0], (0.8, 0.0))

    def test_box_moving_away_from_goal_is_penalised(self):
        env = make_env("SafetyPointPush0-v0")
        arrange(env, agent=(-0.65, 0.0), goal=[(-0.8, 0.6)], push_box=[(-0.2, 0.0)])
        task = env.task
        total, gains = 0.0, 0.0
        for _ in range(40):
            before = task.distance(env)[0], task.box_distance(env)[0]
            total += forward(env)["reward"].item()
            gains += (before[0] - task.distance(env)[0]) + (before[1] - task.box_distance(env)[0])
        assert task.distance(env)[0] > 1.1  # the box moved away from the goal
        assert total == pytest.approx(gains, abs=1e-5)
        assert total < 0

    def test_pillar_contact_costs_at_level_2_only(self):
        for env_id, constrained in (("SafetyPointPush1-v0", False), ("SafetyPointPush2-v0", True)):
            env = make_env(env_id)
            arrange(env, pillars=[(0.36, 0.0)])  # pillar face 0.01 beyond the heading box: closed in 5 steps
            nxt = [forward(env) for _ in range(6)][-1]
            assert env.scene.robot_contacts()[0, env.task.find(Pillars).geom_mask].sum() >= 1
            assert nxt["cost"].item() == float(constrained), env_id
            assert ("pillars" in nxt["cost_info"].keys()) == constrained
        far = make_env("SafetyPointPush2-v0")
        arrange(far, pillars=[(0.6, 0.0)])
        assert forward(far)["cost"].item() == 0.0

    def test_push_hazards_have_radius_0_3(self):
        env = make_env("SafetyPointPush1-v0", cost_mode="raw")
        arrange(env, hazards=[(0.25, 0.0)])
        assert step(env)["cost_info", "hazards"].item() == pytest.approx(0.05, abs=1e-6)


# ---------------------------------------------------------------------------- layouts, seeding, robustness
@pytest.mark.parametrize("env_id", ["SafetyPointButton2-v0", "SafetyPointPush2-v0"])
def test_thousand_layouts_respect_keepouts(env_id):
    env = make_env(env_id, num_envs=50, seed=3)

    def expected_positions(obj, where):
        if isinstance(obj, Gremlins):
            return where + [0.0, 0.35]  # on their circles at t = 0
        if isinstance(obj, GoalMarker):  # moved onto the goal button
            buttons = env.task.buttons
            return buttons.positions(env.scene)[np.arange(50), buttons.goal_button][:, None]
        return where

    layouts = assert_layouts_respect_keepouts(
        env, resets=20, extents=env.task.extents[2], expected_positions=expected_positions
    )
    assert layouts.shape == (1000, env.layout_sampler.size, 2)


def test_resting_layouts_cost_nothing():
    for env_id in ("SafetyPointButton2-v0", "SafetyPointPush2-v0"):
        env = make_env(env_id, num_envs=16, seed=6, cost_mode="raw")
        env.reset()
        for _ in range(3):
            nxt = step(env)
            assert (nxt["cost"] == 0).all(), env_id


@pytest.mark.parametrize("env_id", ["SafetyPointButton2-v0", "SafetyPointPush2-v0"])
def test_sim0_same_for_n1_and_n16(env_id):
    small = make_env(env_id, num_envs=1, seed=7, max_episode_steps=10)
    large = make_env(env_id, num_envs=16, seed=7, max_episode_steps=10)
    assert_sim0_same_for_any_batch(small, large, steps=25)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("env_id", ["SafetyPointButton2-v0", "SafetyPointPush2-v0"])
def test_random_actions_stay_finite(env_id):
    # 4 simulators x 2,500 uniform random steps, 500-step episodes so resets happen along the way.
    env = make_env(env_id, num_envs=4, seed=11, max_episode_steps=500, cost_mode="raw")
    nxt = env.rollout(2500, break_when_any_done=False)["next"]
    assert nxt.batch_size == torch.Size([4, 2500])
    for key in ("observation", "reward", "cost", *(("cost_info", name) for name in env.constraint_names)):
        assert torch.isfinite(nxt[key]).all(), key
    assert nxt["truncated"].sum() == 4 * 5 and not nxt["terminated"].any()
    assert env.physics_errors == 0
    assert (nxt["reward"].abs() <= 10).all()
