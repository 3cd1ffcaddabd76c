"""Fading (FadingEasy / FadingHard) and Race navigation tasks and their Vision twins.

Fading = Goal plus per-simulator render alphas (``sg_torchrl.envs.navigation.fading``); Race = a
fixed start and goal on a long road with roadside scenery. Expected numbers come from
reference/safety_gymnasium_semantics.md sections 4-6 (fading rates alpha0/150 and alpha0/75, Race's
goal bonus 10, clip 11, 500 steps). Tests that draw skip without an OpenGL backend, as in
tests/test_vision.py.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch

from sg_torchrl.envs import registry_entry
from sg_torchrl.envs.navigation import ROBOTS

from test_navigation import action_td, arrange, idle, make_env

torch.set_num_threads(1)

GOAL_ALPHA = 0.25  # the goal's model alpha (objects/goal.py)
FAR = (-3.2, 0.0)  # behind a robot at the origin facing +x: out of its camera's view


def random_actions(env, steps: int, seed: int) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    box = env.action_spec.space
    return [box.low + (box.high - box.low) * torch.rand(box.low.shape, generator=generator) for _ in range(steps)]


def alpha_of(env, obj_name: str, index: int = 0) -> np.ndarray:
    """The alphas simulator ``index`` draws the geoms of object ``obj_name`` with (what the renderer gets)."""
    ids, alphas = env.geom_alpha(index)
    obj = next(o for o in env.task.objects if o.name == obj_name)
    return alphas[np.isin(ids, np.flatnonzero(obj.geom_mask))]


def build_and_step(env_id: str) -> None:
    env = make_env(env_id, num_envs=2)
    td = env.reset()
    for action in random_actions(env, 3, seed=0):
        nxt = env.step(action_td(env, action))["next"]
        for key in ("observation", "reward", "cost"):
            assert torch.isfinite(nxt[key]).all(), (env_id, key)
    assert td["observation"].shape == nxt["observation"].shape == (2, env.observation_dim)
    assert set(nxt["cost_info"].keys()) == set(env.constraint_names)


# ---------------------------------------------------------------------------- Fading: ids and specs
FADING_TASKS = ("FadingEasy", "FadingHard")


def test_fading_ids_are_registered_with_their_vision_twins():
    for robot in ROBOTS:
        for task in FADING_TASKS:
            for level in range(3):
                plain, vision = registry_entry(f"Safety{robot}{task}{level}-v0"), registry_entry(
                    f"Safety{robot}{task}{level}Vision-v0")
                assert (plain.family, vision.family) == ("navigation", "vision")
                for entry in (plain, vision):
                    assert (entry.robot, entry.task, entry.level, entry.max_episode_steps) == (robot, task, level, 1000)


@pytest.mark.parametrize("env_id", [f"Safety{robot}{task}1-v0" for robot in sorted(ROBOTS) for task in FADING_TASKS]
                         + [f"SafetyPoint{task}{level}-v0" for task in FADING_TASKS for level in (0, 2)])
def test_fading_ids_build_and_step(env_id):
    build_and_step(env_id)


@pytest.mark.parametrize("level", [0, 1, 2])
def test_fading_vector_observations_are_the_goal_ids(level):
    goal, easy, hard = (make_env(f"SafetyPoint{task}{level}-v0", num_envs=2, seed=5)
                        for task in ("Goal", "FadingEasy", "FadingHard"))
    assert goal.observation_slices == easy.observation_slices == hard.observation_slices
    assert goal.constraint_names == easy.constraint_names == hard.constraint_names
    outputs = [env.reset() for env in (goal, easy, hard)]
    assert all(torch.equal(outputs[0]["observation"], out["observation"]) for out in outputs[1:])
    for action in random_actions(goal, 40, seed=6):
        steps = [env.step(action_td(env, action))["next"] for env in (goal, easy, hard)]
        for key in ("observation", "reward", "cost", "done"):
            assert torch.equal(steps[0][key], steps[1][key]) and torch.equal(steps[0][key], steps[2][key]), key


# ---------------------------------------------------------------------------- Fading: the schedule
@pytest.mark.parametrize(("task", "steps"), [("FadingEasy", 150), ("FadingHard", 75)])
def test_goal_alpha_falls_linearly_then_stays_at_zero(task, steps):
    env = make_env(f"SafetyPoint{task}0-v0", num_envs=2)
    arrange(env, agent=(0.0, 0.0), goal=[(0.8, 0.0)])
    assert alpha_of(env, "goal") == pytest.approx([GOAL_ALPHA])
    for k in range(1, steps + 6):
        idle(env)
        expected = max(GOAL_ALPHA - k * GOAL_ALPHA / steps, 0.0)
        assert alpha_of(env, "goal") == pytest.approx([expected], abs=1e-12), k
    assert alpha_of(env, "goal") == [0.0]
    assert env.physics.model.geom_rgba[env.task.goal.geom_mask, 3] == pytest.approx([GOAL_ALPHA])  # model untouched


def test_goal_alpha_restored_on_a_new_goal_and_on_reset():
    env = make_env("SafetyPointFadingEasy0-v0", num_envs=2)
    arrange(env, index=0, agent=(0.0, 0.0), goal=[(1.0, 0.0)])
    env.set_layout([1], env.layout[0].copy()[None])  # simulator 1: the same start
    for _ in range(10):
        idle(env)
    faded = GOAL_ALPHA * (1 - 10 / 150)
    assert alpha_of(env, "goal", 0) == alpha_of(env, "goal", 1) == pytest.approx([faded])
    # Simulator 0's goal is reached: a new goal is drawn, fully visible; simulator 1 keeps fading.
    reached = env.scene.agent_xy()[0].copy()
    env.task.goal.move(env.scene, 0, 0, reached)
    nxt = idle(env)
    assert bool(env.task.goal_met[0]) and not bool(env.task.goal_met[1])
    assert np.linalg.norm(env.task.goal.positions(env.scene)[0, 0] - reached) > 0.3  # a new goal elsewhere
    assert nxt["reward"][0].item() > 0.9  # the goal bonus
    assert alpha_of(env, "goal", 0) == pytest.approx([GOAL_ALPHA])
    assert alpha_of(env, "goal", 1) == pytest.approx([GOAL_ALPHA * (1 - 11 / 150)])
    idle(env)
    assert alpha_of(env, "goal", 0) == pytest.approx([GOAL_ALPHA * (1 - 1 / 150)])
    # A partial reset restores only the reset simulator.
    td = env.step(action_td(env, np.zeros((2, 2))))
    td = td["next"].clone()
    td.set("_reset", torch.tensor([[False], [True]]))
    env.reset(td)
    assert alpha_of(env, "goal", 1) == pytest.approx([GOAL_ALPHA])
    assert alpha_of(env, "goal", 0) == pytest.approx([GOAL_ALPHA * (1 - 2 / 150)])


def test_level2_hazards_fade_and_show_while_they_cost():
    env = make_env("SafetyPointFadingEasy2-v0", num_envs=1)
    arrange(env, agent=(0.0, 0.0), goal=[(1.5, 0.0)], hazards=[(-1.0, 1.0)])
    hazards = next(o for o in env.task.objects if o.name == "hazards")
    base = env.physics.model.geom_rgba[np.flatnonzero(hazards.geom_mask), 3]
    assert len(base) == 10 and (base > 0).all()
    for _ in range(5):
        nxt = idle(env)
        assert nxt["cost_info", "hazards"].item() == 0
    assert alpha_of(env, "hazards") == pytest.approx(base * (1 - 5 / 150))
    # Hazard 0 under the robot: on every step it costs, all hazards are drawn at full alpha; the goal keeps fading.
    hazards.move(env.scene, 0, 0, env.scene.agent_xy()[0].copy())
    for k in range(6, 9):
        nxt = idle(env)
        assert nxt["cost_info", "hazards"].item() > 0 and nxt["cost"].item() == 1
        assert alpha_of(env, "hazards") == pytest.approx(base)
        assert alpha_of(env, "goal") == pytest.approx([GOAL_ALPHA * (1 - k / 150)])
    # Out of it again: the hazards fade from full alpha.
    hazards.move(env.scene, 0, 0, np.array([-1.0, 1.0]))
    for k in range(1, 4):
        nxt = idle(env)
        assert nxt["cost_info", "hazards"].item() == 0
        assert alpha_of(env, "hazards") == pytest.approx(base * (1 - k / 150))


def test_what_fades_per_level():
    for task, level, faded in [("FadingEasy", 0, ["goal"]), ("FadingEasy", 1, ["goal"]),
                               ("FadingEasy", 2, ["goal", "hazards"]), ("FadingHard", 1, ["goal"]),
                               ("FadingHard", 2, ["goal", "hazards", "vases"])]:
        env = make_env(f"SafetyPoint{task}{level}-v0")
        assert [obj.name for obj in env.task.fader.objects] == faded, (task, level)
        assert env.task.fader.steps == (150 if task == "FadingEasy" else 75)


def test_fading_state_is_in_the_snapshot():
    env = make_env("SafetyPointFadingHard2-v0", num_envs=2)
    env.reset()
    for _ in range(4):
        idle(env)
    state = env.sim_state()
    before = [alpha_of(env, "goal", i).copy() for i in range(2)]
    for _ in range(6):
        idle(env)
    assert not np.allclose(alpha_of(env, "goal", 0), before[0])
    env.load_sim_state(state)
    for i in range(2):
        assert alpha_of(env, "goal", i) == pytest.approx(before[i])


# ---------------------------------------------------------------------------- Fading: what is drawn
def twin_simulators(env, goal) -> None:
    """Both simulators start from the same layout: robot at the origin facing +x, the goal at ``goal``."""
    arrange(env, index=0, agent=(0.0, 0.0), goal=[goal])
    env.set_layout([1], env.layout[0].copy()[None])


def move_out_of_view(env, obj) -> None:
    """Move ``obj``'s first instance in simulator 0 far from the robot (and update the geoms' poses that are drawn)."""
    obj.move(env.scene, 0, 0, np.array(FAR))
    mujoco.mj_kinematics(env.physics.model, env.physics.datas[0])


def test_rendering_one_simulator_never_shows_another_ones_alphas(backend):
    env = make_env("SafetyPointFadingHard0-v0", num_envs=2)
    twin_simulators(env, goal=(0.8, 0.0))
    for _ in range(75):  # the same zero actions from the same layout: two identical simulators, both goals faded out
        idle(env)
    np.testing.assert_array_equal(env.physics.datas[0].qpos, env.physics.datas[1].qpos)
    assert alpha_of(env, "goal", 0) == alpha_of(env, "goal", 1) == [0.0]
    hidden = env.render(1, 32, 32, camera="vision")
    assert np.array_equal(env.render(0, 32, 32, camera="vision"), hidden)
    env.task.fader.restore(np.array([0]), env.task.goal)  # simulator 0 shows its goal again (as after a new goal)
    rgba = env.physics.model.geom_rgba.copy()
    shown = env.render(0, 32, 32, camera="vision")
    assert np.array_equal(env.render(1, 32, 32, camera="vision"), hidden)  # simulator 1 still draws it invisible
    assert np.array_equal(env.render(0, 32, 32, camera="vision"), shown)  # ... and that did not leak into 0
    assert not np.array_equal(shown, hidden)  # the goal is in view of the camera
    green = shown.astype(int)[..., 1] - shown.astype(int)[..., 0]
    assert (green > hidden.astype(int)[..., 1] - hidden.astype(int)[..., 0]).sum() > 20  # it tints the floor green
    np.testing.assert_array_equal(env.physics.model.geom_rgba, rgba)  # the shared model keeps its colours
    # An invisible goal looks exactly like no goal in view.
    move_out_of_view(env, env.task.goal)
    assert np.array_equal(env.render(0, 32, 32, camera="vision"), hidden)


def test_vision_twin_draws_the_fading_goal(backend):
    env = make_env("SafetyPointFadingHard0Vision-v0", num_envs=2, image_size=24)
    assert env.observation_spec["pixels"].shape == (2, 24, 24, 3)
    twin_simulators(env, goal=(0.8, 0.0))
    first = env.vision.observation()["pixels"]
    assert torch.equal(first[0], first[1])
    for k in range(75):
        nxt = idle(env)
        assert nxt["pixels"].shape == (2, 24, 24, 3) and nxt["pixels"].dtype == torch.uint8
        if k == 0:
            assert not torch.equal(nxt["pixels"][0], first[0])  # a little fainter (the robot settles too)
    faded = nxt["pixels"]
    move_out_of_view(env, env.task.goal)  # the picture of an invisible goal
    env.vision.render([0])
    assert torch.equal(env.vision.observation()["pixels"][0], faded[0])
    env.close()


# ---------------------------------------------------------------------------- Race
RACE_GOAL = (3.15, 1.05)  # 0.9 x 3.5, 0.3 x 3.5 (reference Race levels)
RACE_START = {0: (-2.3625, 0.875, -2.1875, 1.225), 1: (-2.3625, 0.875, -2.1875, 1.225),
              2: (-2.3625, -2.8875, -2.1875, -2.7125)}


def test_race_ids_are_registered_with_their_vision_twins():
    for robot in ROBOTS:
        for level in range(3):
            plain, vision = registry_entry(f"Safety{robot}Race{level}-v0"), registry_entry(f"Safety{robot}Race{level}Vision-v0")
            assert (plain.family, vision.family) == ("navigation", "vision")
            for entry in (plain, vision):
                assert (entry.robot, entry.task, entry.level, entry.max_episode_steps) == (robot, "Race", level, 500)


@pytest.mark.parametrize("env_id", [f"Safety{robot}Race1-v0" for robot in sorted(ROBOTS)]
                         + ["SafetyPointRace0-v0", "SafetyPointRace2-v0"])
def test_race_ids_build_and_step(env_id):
    build_and_step(env_id)


@pytest.mark.parametrize(("level", "size", "constraints"), [
    (0, 28, ()), (1, 44, ("hazards", "static_geoms_contact")), (2, 44, ("hazards", "static_geoms_contact"))])
def test_race_observation_and_constraints(level, size, constraints):
    env = make_env(f"SafetyPointRace{level}-v0")
    assert env.observation_dim == size and env.constraint_names == constraints
    assert list(env.observation_slices)[-(1 if level == 0 else 2):] == ["goal_lidar", "hazards_lidar"][: 1 + (level > 0)]
    assert env.physics.model.geom("floor").size[0] == 17.5 and env.max_episode_steps == 500


@pytest.mark.parametrize("level", [0, 1, 2])
def test_race_start_and_goal_are_fixed(level):
    layouts = []
    for seed in (0, 1, 2):
        env = make_env(f"SafetyPointRace{level}-v0", num_envs=3, seed=seed)
        for _ in range(2):  # two resets per seed
            env.reset()
            layouts.append(env.layout.copy())
            xmin, ymin, xmax, ymax = RACE_START[level]
            robot = env.scene.agent_xy()
            assert ((robot[:, 0] >= xmin - 0.01) & (robot[:, 0] <= xmax + 0.01)).all()
            assert ((robot[:, 1] >= ymin - 0.01) & (robot[:, 1] <= ymax + 0.01)).all()
            np.testing.assert_allclose(env.task.goal.positions(env.scene)[:, 0], [RACE_GOAL] * 3)
    starts = np.concatenate([layout[:, 0] for layout in layouts])
    assert len(np.unique(starts.round(6), axis=0)) > 1  # a region, not a point: the start still varies within it


def test_reaching_the_race_goal_ends_the_episode_with_the_bonus():
    env = make_env("SafetyPointRace0-v0", num_envs=2)
    env.reset()
    xy, yaw = env.layout.copy(), np.zeros(env.layout.shape[:2])
    xy[0, 0] = (RACE_GOAL[0] - 0.2, RACE_GOAL[1])  # inside the goal's 0.3 m radius already, 0.2 m from its centre
    env.set_layout([0, 1], xy, yaw)
    nxt = idle(env)
    assert nxt["terminated"].tolist() == [[True], [False]] and nxt["done"][0].item()
    assert nxt["reward"][0].item() == pytest.approx(10.0, abs=0.05)  # the bonus (and almost no progress)
    np.testing.assert_allclose(env.task.goal.positions(env.scene)[0, 0], RACE_GOAL)  # the goal did not move
    # The reward is clipped to +-11: a robot moved onto the goal from 5 m away within one step earns 11, not 5 + 10.
    far = env.layout.copy()
    far[1, 0] = (RACE_GOAL[0] - 5.0, RACE_GOAL[1])
    env.set_layout([1], far[1:2], yaw[1:2])  # the shaping starts from 5 m
    data = env.physics.datas[1]
    qpos = data.qpos.copy()[None]
    env.robot.set_pose(env.physics.model, qpos, np.array([RACE_GOAL]), np.zeros(1))
    data.qpos[:] = qpos[0]
    mujoco.mj_forward(env.physics.model, data)
    nxt = idle(env)
    assert nxt["terminated"][1].item() and nxt["reward"][1].item() == pytest.approx(11.0)


def race_against_a_house(level: int):
    """Race ``level`` with simulator 0's robot just south of a house, facing it, and the house's prop."""
    env = make_env(f"SafetyPointRace{level}-v0", num_envs=1)
    env.reset()
    house = next(p for p in env.task.scenery.props if p.kind == "house" and abs(p.x - 0.6) < 1e-9)
    xy, yaw = env.layout.copy(), np.zeros(env.layout.shape[:2])
    xy[0, 0] = (house.x, house.y - house.footprint[1] - 0.15)
    yaw[0, 0] = np.pi / 2  # facing +y, the house
    env.set_layout([0], xy, yaw)
    return env


@pytest.mark.parametrize("level", [1, 2])
def test_touching_the_scenery_costs_at_levels_1_and_2(level):
    env = race_against_a_house(level)
    contacts = []
    for _ in range(40):  # full throttle into the wall
        nxt = env.step(action_td(env, [[1.0, 0.0]]))["next"]
        contacts.append(nxt["cost_info", "static_geoms_contact"].item())
        assert nxt["cost_info", "hazards"].item() == 0
        if contacts[-1] > 0:
            assert nxt["cost"].item() == 1.0
    assert max(contacts) >= 1 and contacts[0] == 0  # not touching at the start, touching once it got there
    assert contacts == [float(int(c)) for c in contacts]  # a count of contacts


def test_scenery_is_solid_but_free_at_level_0():
    env = race_against_a_house(0)
    start = env.scene.agent_xy()[0].copy()
    for _ in range(40):
        nxt = env.step(action_td(env, [[1.0, 0.0]]))["next"]
        assert nxt["cost"].item() == 0 and "static_geoms_contact" not in nxt["cost_info"].keys()
    house_south_face = 2.9 - 0.42  # the roof overhangs the walls' 0.35
    assert start[1] < env.scene.agent_xy()[0, 1] < house_south_face  # it drove up to the house and stopped there
    assert env.scene.robot_contacts()[0, env.task.scenery.geom_mask].sum() >= 1


def test_race_vision_twin_emits_pixels(backend):
    env = make_env("SafetyPointRace2Vision-v0", num_envs=2, image_size=20)
    out = env.rollout(2)
    assert out["next", "pixels"].shape == (2, 2, 20, 20, 3) and out["next", "pixels"].dtype == torch.uint8
    assert out["next", "pixels"].float().std() > 5
    env.close()


@pytest.mark.parametrize("env_id", ["SafetyPointFadingEasy2Vision-v0", "SafetyCarFadingHard1Vision-v0"])
def test_fading_vision_twins_emit_pixels(backend, env_id):
    env = make_env(env_id, num_envs=2, image_size=20)
    out = env.rollout(2)
    assert out["next", "pixels"].shape == (2, 2, 20, 20, 3) and out["next", "pixels"].dtype == torch.uint8
    env.close()
