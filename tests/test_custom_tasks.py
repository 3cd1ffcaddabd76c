"""Users' own tasks: the navigation composition API, any env plus a cost function, and the two examples
trained for a short budget through sg-train's engine (docs/custom_tasks.md)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

import sg_torchrl
from sg_torchrl.envs.navigation import NavigationEnv
from sg_torchrl.envs.navigation.layout import LayoutError
from sg_torchrl.envs.navigation.levels import BUTTON_SPECS, GOAL_SPECS, PUSH_SPECS
from sg_torchrl.envs.navigation.objects import Goal, Hazards, Vases
from sg_torchrl.envs.navigation.tasks import GoalTask
from sg_torchrl.tasks import TaskSpec, TaskSpecError, make_cost_env, register_cost_env, register_task, unregister

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
HAZARDS = TaskSpec("Hazardous", extents=1.5, objects={"hazards": {"count": 4, "size": 0.3}}, max_episode_steps=50)


@pytest.fixture
def registered():
    """Ids registered by a test, removed afterwards (the registry-wide tests see only the built-in ids)."""
    ids: list[str] = []
    yield ids
    for env_id in ids:
        if env_id in sg_torchrl.list_envs():
            unregister(env_id)


@pytest.fixture
def examples(registered):
    """The two example modules, imported fresh (they register their ids on import)."""
    sys.path.insert(0, str(EXAMPLES))
    try:
        import custom_cost_env
        import custom_task
        registered += [custom_task.ENV_ID, custom_cost_env.ENV_ID]
        yield custom_task, custom_cost_env
    finally:
        sys.path.remove(str(EXAMPLES))
        for name in ("custom_task", "custom_cost_env"):
            sys.modules.pop(name, None)


# ------------------------------------------------------------------ the composition API
def test_a_registered_task_is_made_like_a_built_in_id(registered):
    registered.append(register_task("TestHazardous-v0", HAZARDS, robot="Car"))
    env = sg_torchrl.make("TestHazardous-v0", num_envs=2, seed=0, cost_mode="raw")
    assert isinstance(env, NavigationEnv) and env.robot.name == "Car" and env.max_episode_steps == 50
    assert list(env.observation_spec["cost_info"].keys()) == ["hazards"]
    assert "hazards_lidar" in env.observation_slices and "goal_lidar" in env.observation_slices
    rollout = env.rollout(60, break_when_any_done=False)
    assert rollout["next", "truncated"][:, 49].all()
    assert sg_torchrl.envs.registry_entry("TestHazardous-v0").task == "Hazardous"


def test_the_goal_levels_are_specs_building_the_reference_levels():
    reference = GoalTask(1, extents=1.5, objects=[Goal(keepout=0.305), Hazards(8, keepout=0.18),
                                                  Vases(1, constrained=False)])
    built = GOAL_SPECS[1].build()
    assert built.key == reference.key and built.extents == reference.extents and type(built) is GoalTask
    assert [repr(obj) for obj in built.objects] == [repr(obj) for obj in reference.objects]
    assert [type(s.build()).__name__ for s in (*BUTTON_SPECS.values(), *PUSH_SPECS.values())] == ["ButtonTask"] * 3 + ["PushTask"] * 3


@pytest.mark.parametrize("kwargs, message", [
    ({"objective": "goals"}, "unknown objective 'goals'; valid: 'goal', 'button', 'push', 'circle'"),
    ({"objects": {"hazard": {}}}, "unknown object for objective 'goal' 'hazard'; valid: 'hazards', 'vases'"),
    ({"objects": {"hazards": {"cout": 3}}}, "unknown field of 'hazards' 'cout'; valid: 'count', 'size', 'keepout'"),
    ({"objects": {"buttons": {}}}, "unknown object for objective 'goal' 'buttons'"),
    ({"reward": {"goals": 1.0}}, "unknown reward term for objective 'goal' 'goals'; valid: 'distance', 'goal'"),
    ({"objects": {"hazards": {"count": 0}}}, "object 'hazards': Hazards: num must be >= 1, got 0"),
    ({"max_episode_steps": 0}, "max_episode_steps must be a positive integer"),
    ({"extents": None}, "objective 'goal' needs extents"),
])
def test_typos_fail_at_construction_naming_the_key_and_the_valid_ones(kwargs, message):
    with pytest.raises(TaskSpecError, match=message.replace("(", r"\(").replace(")", r"\)")) as error:
        TaskSpec("Typo", **{"extents": 1.0, **kwargs})
    assert "task 'Typo'" in str(error.value)


def test_an_unknown_robot_names_the_valid_ones():
    with pytest.raises(TaskSpecError, match="unknown robot 'Pointy'; valid: 'Point', 'Car'"):
        register_task("TestTypo-v0", HAZARDS, robot="Pointy")


def test_more_objects_than_fit_are_refused_at_registration_naming_the_task_and_object():
    crowded = TaskSpec("Packed", extents=1.0, objects={"hazards": {"count": 40, "keepout": 0.2}})
    with pytest.raises(TaskSpecError, match=r"task 'Packed': hazards \(instance \d+ of 40\) does not fit"):
        register_task("TestPacked-v0", crowded)
    with pytest.raises(LayoutError, match="task 'Packed': hazards"):  # building the env directly: the same check
        NavigationEnv("Point", crowded)


def test_a_layout_too_crowded_to_draw_fails_at_the_first_reset_naming_the_object():
    tight = TaskSpec("Tight", extents=1.0, objects={"hazards": {"count": 10, "keepout": 0.25}})  # fits on paper
    env = NavigationEnv("Point", tight, seed=0)
    start = time.perf_counter()
    with pytest.raises(LayoutError, match=r"task 'Tight': no valid layout in 10000 attempts; placing hazards"):
        env.reset()
    assert time.perf_counter() - start < 60


def test_a_spec_is_frozen_and_copies_its_inputs():
    objects = {"hazards": {"count": 2}}
    spec = TaskSpec("Copy", extents=1.0, objects=objects)
    objects["hazards"]["count"] = 99
    assert spec.objects["hazards"]["count"] == 2 and hash(spec) == hash(TaskSpec("Copy", extents=1.0, objects={"hazards": {"count": 2}}))
    with pytest.raises(Exception):
        spec.name = "Other"


# ------------------------------------------------------------------ any env plus a cost function
def speed_cost(obs, action, next_obs, info):
    return (next_obs[..., 2].abs() > 1.0).float()


def test_a_cost_env_emits_cost_and_cost_info_like_a_safe_env():
    env = make_cost_env("Pendulum-v1", speed_cost, num_envs=3, seed=4, cost_name="speed")
    check_env_specs(env)
    rollout = env.rollout(20)
    cost, info = rollout["next", "cost"], rollout["next", "cost_info", "speed"]
    assert cost.shape == (3, 20, 1) and cost.dtype == rollout["next", "reward"].dtype
    assert torch.equal(cost, info)
    assert torch.equal(cost[..., 0], (rollout["next", "observation"][..., 2].abs() > 1.0).float())
    assert env.max_episode_steps == 200  # Pendulum-v1's own limit


def test_cost_env_seeding_follows_the_safe_env_rule():
    alone = make_cost_env("Pendulum-v1", speed_cost, num_envs=1, seed=7).reset()["observation"]
    block = make_cost_env("Pendulum-v1", speed_cost, num_envs=4, seed=[3, 7]).reset()["observation"]
    assert torch.equal(block[2], alone[0])  # block 1, simulator 0: seeded as a one-simulator env with seed 7
    again = make_cost_env("Pendulum-v1", speed_cost, num_envs=4, seed=[3, 7]).reset()["observation"]
    assert torch.equal(block, again)


def test_a_cost_of_the_wrong_shape_is_an_error():
    env = make_cost_env("Pendulum-v1", lambda obs, action, next_obs, info: torch.zeros(5), num_envs=2)
    env.reset()
    with pytest.raises(ValueError, match=r"cost_fn returned shape \(5,\)"):
        env.rand_step()


def test_a_registered_cost_env_takes_make_s_arguments(registered):
    registered.append(register_cost_env("TestSpeedPendulum-v0", "Pendulum-v1", speed_cost, max_episode_steps=30))
    env = sg_torchrl.make("TestSpeedPendulum-v0", num_envs=2, seed=0)
    assert env.batch_size == (2,) and env.max_episode_steps == 30
    assert env.rollout(40, break_when_any_done=False)["next", "truncated"][:, 29].all()


# ------------------------------------------------------------------ the examples, trained through the engine
def test_both_examples_train_for_a_short_budget(examples, tmp_path):
    custom_task, custom_cost_env = examples
    for module in (custom_task, custom_cost_env):
        metrics = module.train(400, str(tmp_path / module.__name__))
        assert metrics["Train/TotalSteps"] == 400 and np.isfinite(metrics["Loss/Loss_actor"])
    assert (tmp_path / "custom_task" / custom_task.ENV_ID).is_dir()


def test_the_command_line_imports_a_task_module(examples, monkeypatch):
    from sg_torchrl.train.config import command_line_values

    custom_task, _ = examples
    unregister(custom_task.ENV_ID)
    sys.modules.pop("custom_task")
    values = command_line_values(["--task-module", "custom_task", "--env-id", custom_task.ENV_ID])
    assert values["env_id"] == custom_task.ENV_ID and "task_modules" not in values
    assert custom_task.ENV_ID in sg_torchrl.list_envs()
    with pytest.raises(SystemExit):
        command_line_values(["--task-module", "no_such_module_of_tasks"])
