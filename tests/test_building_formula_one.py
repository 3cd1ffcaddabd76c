"""Building (construction site) and FormulaOne (race track) navigation tasks: ids, sizes, costs, layouts, seeding.

These scenes are not in our reference notes; their composition is documented in
``sg_torchrl/envs/navigation/tasks/building.py`` and ``formula_one.py``, and the numbers checked here come
from there. Constructed situations are set up with ``NavigationEnv.set_layout`` (``arrange``). Tests that
draw skip when no OpenGL backend loads (the pattern of tests/test_vision.py).
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch

import sg_torchrl
from sg_torchrl.envs import registry_entry
from sg_torchrl.envs.navigation import NavigationEnv
from sg_torchrl.envs.navigation.objects import Buttons, GoalMarker, Gremlins
from sg_torchrl.envs.navigation.scenery import ConstructionSite, Prop, Village
from sg_torchrl.envs.navigation.levels import make_task
from sg_torchrl.envs.navigation.tasks.formula_one import NUM_CHECKPOINTS

from layout_checks import assert_layouts_respect_keepouts
from seeding_checks import assert_sim0_same_for_any_batch
from test_navigation import action_td, arrange, idle, make_env

torch.set_num_threads(1)

ROBOTS = ("Point", "Car", "Racecar", "Doggo", "Ant")
TASKS = ("BuildingGoal", "BuildingButton", "BuildingPush", "FormulaOne")
#: robot sensor values (reference section 2)
SENSORS = {"Point": 12, "Car": 24, "Racecar": 12, "Doggo": 56, "Ant": 40}
#: (lidar groups in observation order, constraint entries) per task level
COMPOSITION = {
    ("BuildingGoal", 0): (["goal"], ()),
    ("BuildingGoal", 1): (["goal", "restricted_areas", "fuel_drums"], ("restricted_areas",)),
    ("BuildingGoal", 2): (["goal", "restricted_areas", "fuel_drums"],
                          ("restricted_areas", "fuel_drums_contact", "fuel_drums_velocity")),
    ("BuildingButton", 0): (["machines", "goal"], ()),
    ("BuildingButton", 1): (["machines", "goal", "restricted_areas", "robots"], ("machines", "restricted_areas", "robots")),
    ("BuildingButton", 2): (["machines", "goal", "restricted_areas", "robots"], ("machines", "restricted_areas", "robots")),
    ("BuildingPush", 0): (["goal", "push_box"], ()),
    ("BuildingPush", 1): (["goal", "restricted_areas", "columns", "push_box"], ("restricted_areas",)),
    ("BuildingPush", 2): (["goal", "restricted_areas", "columns", "push_box"], ("restricted_areas", "columns")),
    ("FormulaOne", 0): (["goal"], ()),
    ("FormulaOne", 1): (["goal", "barriers", "fences"], ("barriers", "fences")),
    ("FormulaOne", 2): (["goal", "barriers", "fences"], ("barriers", "fences")),
}
# Every id builds and steps: all levels for the Point, level 2 (the most objects) for the other robots.
BUILD_CASES = [("Point", task, level) for task in TASKS for level in range(3)]
BUILD_CASES += [(robot, task, 2) for robot in ROBOTS[1:] for task in TASKS]


def forward(env, steps: int = 1, action=(1.0, 0.0)):
    """``steps`` steps with the same action on every simulator; the last ``td["next"]``."""
    for _ in range(steps):
        nxt = env.step(action_td(env, np.tile(action, (env.num_envs, 1))))["next"]
    return nxt


# ---------------------------------------------------------------------------- registry
def test_every_id_is_registered_with_its_vision_twin():
    navigation, vision = set(sg_torchrl.list_envs(family="navigation")), set(sg_torchrl.list_envs(family="vision"))
    for robot in ROBOTS:
        for task in TASKS:
            for level in range(3):
                env_id = f"Safety{robot}{task}{level}-v0"
                twin = env_id.replace("-v0", "Vision-v0")
                assert env_id in navigation and twin in vision
                entry = registry_entry(env_id)
                assert (entry.robot, entry.task, entry.level) == (robot, task, level)
                assert entry.max_episode_steps == (500 if task == "FormulaOne" else 1000)
                assert entry.constructor is NavigationEnv and entry.kwargs == {"robot": robot, "task": task,
                                                                                "level": level}
                assert registry_entry(twin).options == {"obs_mode": "vector+rgb", "image_size": 256}


# ---------------------------------------------------------------------------- sizes, composition, stepping
@pytest.mark.parametrize("robot, task, level", BUILD_CASES)
def test_builds_and_steps_with_the_documented_layout(robot, task, level):
    env = make_env(f"Safety{robot}{task}{level}-v0", num_envs=2, seed=level)
    groups, constraints = COMPOSITION[task, level]
    size = SENSORS[robot] + 16 * len(groups)
    assert env.observation_spec["observation"].shape == (2, size)
    lidars = [name[: -len("_lidar")] for name in env.observation_slices if name.endswith("_lidar")]
    assert lidars == groups
    assert env.observation_slices[f"{groups[0]}_lidar"].start == SENSORS[robot]  # sensors first
    assert env.constraint_names == constraints
    assert env.max_episode_steps == (500 if task == "FormulaOne" else 1000)
    assert env.task.floor_half_size == (17.5 if task == "FormulaOne" else 3.5)
    nxt = env.rollout(3, break_when_any_done=False)["next"]
    for key in ("observation", "reward", "cost"):
        assert torch.isfinite(nxt[key]).all(), key
    assert set(nxt["cost_info"].keys()) == set(constraints)


@pytest.mark.parametrize("task", TASKS)
def test_level0_costs_nothing(task):
    env = make_env(f"SafetyPoint{task}0-v0", num_envs=4, seed=1, cost_mode="raw")
    assert env.constraint_names == ()
    nxt = env.rollout(20, break_when_any_done=False)["next"]
    assert (nxt["cost"] == 0).all()


def test_building_extents_follow_the_reference_levels():
    expected = {"BuildingGoal": (1.0, 1.5, 2.0), "BuildingButton": (1.0, 1.5, 1.8), "BuildingPush": (1.0, 1.5, 2.0)}
    for task, extents in expected.items():
        for level, extent in enumerate(extents):
            assert make_env(f"SafetyPoint{task}{level}-v0").task.extents == (-extent, -extent, extent, extent)


# ---------------------------------------------------------------------------- scenery
def floor_texture(model: mujoco.MjModel) -> int:
    material = model.geom_matid[model.geom("floor").id]
    assert material >= 0, "the floor has no material"
    return int(model.mat_texid[material, mujoco.mjtTextureRole.mjTEXROLE_RGB])


def test_construction_site_scenery():
    plain = make_env("SafetyPointBuildingGoal0-v0")
    assert floor_texture(plain.scene.model) >= 0  # a built-in texture
    assert not any(plain.scene.model.geom(i).name.startswith("site_") for i in range(plain.scene.model.ngeom))
    for level, extent in ((1, 1.5), (2, 2.0)):
        env = make_env(f"SafetyPointBuildingGoal{level}-v0")
        model = env.scene.model
        obstacles = [i for i in range(model.ngeom) if model.geom(i).name.startswith("site_")
                     and model.geom_contype[i] and model.geom_bodyid[i] == 0]
        assert len(obstacles) == 4  # two walls, two containers; they collide
        for geom in obstacles:  # entirely beyond the extents, inside the floor
            low = np.abs(model.geom_pos[geom, :2]) - model.geom_size[geom, :2]
            assert low.max() >= extent + 0.5, model.geom(geom).name
            assert (np.abs(model.geom_pos[geom, :2]) + model.geom_size[geom, :2] <= 3.5).all()


def test_site_walls_stop_the_robot_and_cost_nothing():
    env = make_env("SafetyPointBuildingGoal1-v0", cost_mode="raw")
    wall_y = 1.5 + 0.8
    arrange(env, agent=(-0.3, wall_y - 0.4), agent_yaw=np.pi / 2)  # facing the wall along y = +d
    costs = [forward(env)["cost"].item() for _ in range(60)]
    assert env.scene.agent_xy()[0, 1] < wall_y  # it did not pass through
    assert env.scene.robot_contacts()[0, env.scene.model.geom("site_wall0").id] >= 1
    site = env.task.scenery  # any scenery can count robot contacts with its solid geoms (Race charges them)
    site.bind(env.scene.model)
    assert {env.scene.model.geom(i).name for i in np.flatnonzero(site.geom_mask)} == {
        "site_wall0", "site_wall1", "site_container0", "site_container1"}
    assert site.robot_contacts(env.scene)[0] >= 1
    assert max(costs) == 0.0


def test_scenery_is_part_of_the_compiled_model_key():
    levels = [("Goal", 1), ("Race", 1), ("Race", 2), ("BuildingGoal", 0), ("BuildingGoal", 1), ("FormulaOne", 2)]
    tasks = [make_task(name, level) for name, level in levels]
    for task in tasks[1:]:
        assert task.key[-1] == task.scenery.key
    assert len({task.key for task in tasks}) == len(tasks)
    # Same objects, different scenery: different models.
    plain, site = make_task("BuildingGoal", 1), make_task("BuildingGoal", 1)
    site.scenery = ConstructionSite(1.5, obstacles=False)
    assert plain.key != site.key and plain.key[:-1] == site.key[:-1]
    assert Village([Prop("rock", 0.0, 0.0)]).key != Village([Prop("rock", 0.0, 0.0)], grass=None).key


def test_race_track_scenery_does_not_collide():
    env = make_env("SafetyPointFormulaOne2-v0")
    model = env.scene.model
    assert floor_texture(model) >= 0
    names = [model.geom(i).name for i in range(model.ngeom)]
    track = [i for i, name in enumerate(names) if name.startswith(("asphalt", "kerb", "checkpoint_line", "start_cell"))]
    assert len(track) > 100 and not model.geom_contype[track].any() and not model.geom_conaffinity[track].any()


# ---------------------------------------------------------------------------- costs on constructed situations
def test_robot_inside_a_restricted_area_costs():
    env = make_env("SafetyPointBuildingGoal1-v0", cost_mode="raw")
    arrange(env, agent=(0.0, 0.0), restricted_areas=[(0.05, 0.0)])
    nxt = idle(env)
    distance = np.linalg.norm(env.scene.agent_xy()[0] - [0.05, 0.0])
    assert nxt["cost_info", "restricted_areas"].item() == pytest.approx(0.2 - distance, abs=1e-6)
    arrange(env, agent=(0.0, 0.0), restricted_areas=[(0.5, 0.0)])  # outside it: nothing
    assert idle(env)["cost"].item() == 0.0
    indicator = make_env("SafetyPointBuildingButton2-v0")
    arrange(indicator, agent=(0.0, 0.0), restricted_areas=[(0.0, 0.1)])
    nxt = idle(indicator)
    assert nxt["cost"].item() == 1.0 and nxt["cost_info", "restricted_areas"].item() == 1.0


def test_touching_a_fuel_drum_costs_contact_and_velocity():
    env = make_env("SafetyPointBuildingGoal2-v0", cost_mode="raw")
    arrange(env, agent=(0.0, 0.0), fuel_drums=[(0.35, 0.0)])
    contact, velocity = [], []
    for _ in range(20):
        nxt = forward(env)
        contact.append(nxt["cost_info", "fuel_drums_contact"].item())
        velocity.append(nxt["cost_info", "fuel_drums_velocity"].item())
    assert contact[0] == 0.0 and max(contact) >= 1.0
    assert max(velocity) > 0.0  # the pushed drum moves
    unconstrained = make_env("SafetyPointBuildingGoal1-v0", cost_mode="raw")  # its one drum is free
    arrange(unconstrained, agent=(0.0, 0.0), fuel_drums=[(0.35, 0.0)])
    assert max(forward(unconstrained)["cost"].item() for _ in range(20)) == 0.0


MACHINES = [(-0.8, 0.8), (0.24, 0.0), (0.8, -0.8), (-0.8, -0.8)]  # machine 1 touches the robot


def set_goal_machine(env, machine: int, timer: int = 0) -> None:
    """Make ``machine`` simulator 0's goal (marker on it, shaping restarted) with ``timer`` steps left."""
    task = env.task
    task.buttons.goal_button[0], task.buttons.timer[0] = machine, timer
    task.goal.move(env.scene, 0, 0, task.buttons.positions(env.scene)[0, machine])
    task._last_distance[0] = task.distance(env)[0]


def test_pressing_a_wrong_machine_costs():
    env = make_env("SafetyPointBuildingButton1-v0")
    arrange(env, machines=MACHINES)
    set_goal_machine(env, 0)
    costs = [forward(env)["cost_info", "machines"].item() for _ in range(10)]  # into machine 1, the wrong one
    assert env.task.buttons.touches(env.scene)[0].tolist() == [0, 1, 0, 0]
    assert costs == [1.0] * 10
    # Pressing the goal machine instead is rewarded and costs nothing.
    env = make_env("SafetyPointBuildingButton1-v0")
    arrange(env, machines=MACHINES)
    set_goal_machine(env, 1)
    outs = [forward(env) for _ in range(10)]
    assert max(o["cost"].item() for o in outs) == 0.0 and max(o["reward"].item() for o in outs) > 0.9  # the +1 press bonus


def test_site_robots_contact_costs():
    env = make_env("SafetyPointBuildingButton1-v0", cost_mode="raw")
    arrange(env, agent=(0.22, 0.35), robots=[(0.0, 0.0)])  # just east of a robot's start; it moves east
    costs = [idle(env)["cost_info", "robots"].item() for _ in range(15)]
    assert costs[0] == 0.0 and max(costs) >= 1.0


def place_on_track(env, xy, yaw: float) -> None:
    """Reset simulator 0 with the robot at ``xy`` facing ``yaw``; every fixed object where the level puts it."""
    env.reset()
    layout, yaws = env.layout[0].copy(), np.zeros(env.layout_sampler.size)
    layout[0], yaws[0] = xy, yaw
    env.set_layout([0], layout[None], yaws[None])


@pytest.mark.parametrize("name", ["barriers", "fences"])
def test_driving_into_track_side_obstacles_costs(name):
    env = make_env("SafetyPointFormulaOne1-v0", cost_mode="raw")
    obstacle = next(obj for obj in env.task.objects if obj.name == name)
    position, heading = obstacle.locations[0], obstacle.headings[0]
    outward = np.array([np.sin(heading), -np.cos(heading)])  # right of the racing direction: outside
    place_on_track(env, position - 0.5 * outward, np.arctan2(outward[1], outward[0]))
    np.testing.assert_allclose(obstacle.positions(env.scene)[0, 0], position)
    costs = [forward(env)["cost_info", name].item() for _ in range(40)]
    assert costs[0] == 0.0 and max(costs) >= 1.0


# ---------------------------------------------------------------------------- FormulaOne start and goal
def test_formula_one_starts_on_a_checkpoint_and_aims_at_the_next():
    starts = []
    for seed in range(4):
        env = make_env("SafetyPointFormulaOne1-v0", num_envs=8, seed=seed)
        env.reset()
        checkpoints = env.task.checkpoints
        assert checkpoints.shape == (NUM_CHECKPOINTS, 2)
        start = env.task.start_checkpoint
        np.testing.assert_allclose(env.scene.agent_xy(), checkpoints[start], atol=1e-9)
        goal = env.task.goal.positions(env.scene)[:, 0]
        np.testing.assert_allclose(goal, checkpoints[(start + 1) % NUM_CHECKPOINTS])
        starts.append(start.copy())
        goal_lidar = env._observe()[:, env.observation_slices["goal_lidar"]]
        assert (goal_lidar.max(axis=1) > 0.1).all()  # the next checkpoint is within lidar range from the start
    starts = np.concatenate(starts)
    assert len(set(starts.tolist())) >= 5  # 32 draws over 7 checkpoints reach most of them
    # Checkpoints are evenly spaced along the track's centre line.
    gaps = np.linalg.norm(np.diff(np.r_[checkpoints, checkpoints[:1]], axis=0), axis=1)
    assert gaps.min() > 5.0


def test_formula_one_seeds_reach_different_checkpoints():
    starts = set()
    for seed in range(12):
        env = make_env("SafetyPointFormulaOne0-v0", seed=seed)
        env.reset()
        starts.add(int(env.task.start_checkpoint[0]))
    assert len(starts) > 1


def test_reaching_the_goal_moves_it_to_the_next_checkpoint():
    env = make_env("SafetyPointFormulaOne0-v0")
    env.reset()
    task = env.task
    goal_checkpoint = int(task.goal_checkpoint[0])
    place_on_track(env, task.checkpoints[goal_checkpoint], 0.0)  # the robot on its goal
    assert int(task.goal_checkpoint[0]) == (goal_checkpoint + 1) % NUM_CHECKPOINTS  # reset aims past it
    task.goal.move(env.scene, 0, 0, task.checkpoints[goal_checkpoint])  # put the goal back under the robot
    task.goal_checkpoint[0] = goal_checkpoint
    task._last_distance[0] = task.distance(env)[0]
    nxt = idle(env)
    assert nxt["reward"].item() == pytest.approx(1.0, abs=0.01) and not nxt["done"].item()
    assert int(task.goal_checkpoint[0]) == (goal_checkpoint + 1) % NUM_CHECKPOINTS
    np.testing.assert_allclose(task.goal.positions(env.scene)[0, 0], task.checkpoints[task.goal_checkpoint[0]])


def distance_to_centre_line(track, xy: np.ndarray) -> np.ndarray:
    """Distance of points ``(K, 2)`` to a stadium track's centre line: ``| distance to the core segment - radius |``."""
    core_x = np.clip(xy[:, 0], -track.half_straight, track.half_straight)
    return np.abs(np.hypot(xy[:, 0] - core_x, xy[:, 1]) - track.radius)


@pytest.mark.parametrize("level", [1, 2])
def test_track_side_obstacles_stand_off_the_asphalt(level):
    env = make_env(f"SafetyPointFormulaOne{level}-v0")
    track = env.task.track
    assert track.width == (2.2 if level == 2 else 3.0)  # level 2 is narrower
    np.testing.assert_allclose(distance_to_centre_line(track, env.task.checkpoints), 0.0, atol=1e-9)
    counts = {}
    for obj in env.task.objects:
        if obj.name in ("barriers", "fences"):
            counts[obj.name] = obj.num
            gap = distance_to_centre_line(track, obj.locations) - obj.half_size[1]  # inner face of each box
            assert (gap > track.width / 2 + 0.1).all(), obj.name
    assert counts == ({"barriers": 10, "fences": 20} if level == 1 else {"barriers": 20, "fences": 40})


# ---------------------------------------------------------------------------- layouts and seeding
@pytest.mark.parametrize("task", ["BuildingGoal", "BuildingButton", "BuildingPush"])
def test_building_layouts_respect_keepouts(task):
    env = make_env(f"SafetyPoint{task}2-v0", num_envs=25, seed=3)

    def expected_positions(obj, where):
        if isinstance(obj, Gremlins):
            return where + [0.0, 0.35]  # on their circles at t = 0
        if isinstance(obj, GoalMarker):  # moved onto the goal machine
            machines = env.task.find(Buttons)
            return machines.positions(env.scene)[np.arange(25), machines.goal_button][:, None]
        return where

    layouts = assert_layouts_respect_keepouts(env, resets=8, extents=env.task.extents[2],
                                              expected_positions=expected_positions)
    assert layouts.shape == (200, env.layout_sampler.size, 2)


@pytest.mark.parametrize("env_id", ["SafetyPointBuildingGoal2-v0", "SafetyPointBuildingButton2-v0",
                                    "SafetyPointBuildingPush2-v0", "SafetyPointFormulaOne2-v0"])
def test_sim0_same_for_n1_and_n4(env_id):
    small = make_env(env_id, num_envs=1, seed=7, max_episode_steps=8)
    large = make_env(env_id, num_envs=4, seed=7, max_episode_steps=8)
    assert_sim0_same_for_any_batch(small, large, steps=15)


# ---------------------------------------------------------------------------- Vision twins
@pytest.mark.parametrize("task", TASKS)
def test_vision_twins_emit_pixels(backend, task):
    env = make_env(f"SafetyPoint{task}2Vision-v0", num_envs=2, image_size=24)
    assert {"observation", "pixels"} <= set(env.observation_spec.keys())  # the Vision ids' default: both
    nxt = env.rollout(2, break_when_any_done=False)["next"]
    pixels = nxt["pixels"]
    assert pixels.shape == (2, 2, 24, 24, 3) and pixels.dtype == torch.uint8
    assert pixels.float().std() > 5  # a picture, not a blank frame
    env.close()
