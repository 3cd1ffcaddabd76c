"""One validation layer for env options and ``sg-train`` flags.

* ``sg_torchrl.make`` refuses bad options, ``num_envs``, ``seed`` and ``device`` with our exception
  types, naming the argument and the env id, before building anything;
* ``sg-train`` refuses every bad flag or option with one ``sg-train: error: ...`` line and exit status 2,
  before any env is built and without importing torch (a subprocess checks ``sys.modules``);
* the light metadata the checks read (the registry's table, the option annotations) equals what the env
  modules and the constructors' signatures say.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import sg_torchrl
from sg_torchrl.envs import (
    EnvOptionTypeError,
    InvalidEnvOptionError,
    UnknownEnvError,
    UnknownEnvOptionError,
    registry_entry,
    validate_env_options,
)
from sg_torchrl.envs.options import CONSTRUCTOR_OPTIONS, signature_options
from sg_torchrl.envs.registry import _REGISTRY, command_line_env_options
from sg_torchrl.train import TrainConfig, main
from sg_torchrl.train.command_line import parse_args

torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]
GOAL = "SafetyPointGoal1-v0"
CHEETAH = "SafetyHalfCheetahVelocity-v1"


# ------------------------------------------------------------------ sg_torchrl.make
class TestMake:
    @pytest.mark.parametrize("value", ["no", "False", "", 1, 0, None])
    def test_compass_takes_only_a_bool(self, value):
        # A non-empty string is truthy: compass="no" used to turn the compass on (observation 62, not 60).
        with pytest.raises(EnvOptionTypeError, match=rf"{GOAL}: option compass must be a bool"):
            sg_torchrl.make(GOAL, compass=value)

    def test_compass_false_is_off_and_true_is_on(self):
        assert sg_torchrl.make(GOAL, compass=False).observation_spec["observation"].shape[-1] == 60
        assert sg_torchrl.make(GOAL, compass=True).observation_spec["observation"].shape[-1] == 62

    @pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, np.float32("nan")])
    def test_velocity_threshold_must_be_finite(self, value):
        # A NaN threshold compares false with every speed: the cost never fired.
        with pytest.raises(InvalidEnvOptionError, match=rf"{CHEETAH}: option velocity_threshold must be a finite"):
            sg_torchrl.make(CHEETAH, velocity_threshold=value)

    def test_lidar_is_one_of_its_modes(self):
        with pytest.raises(InvalidEnvOptionError, match=r"option lidar must be one of 'pseudo', 'natural', got 'bogus'"):
            sg_torchrl.make(GOAL, lidar="bogus")

    @pytest.mark.parametrize("value", ["10", 10.0, True])
    def test_max_episode_steps_is_an_integer(self, value):
        with pytest.raises(EnvOptionTypeError, match=rf"{CHEETAH}: option max_episode_steps must be an integer"):
            sg_torchrl.make(CHEETAH, max_episode_steps=value)

    @pytest.mark.parametrize("name, value", [("max_episode_steps", 0), ("physics_threads", 0), ("image_size", -4)])
    def test_counts_are_positive(self, name, value):
        with pytest.raises(InvalidEnvOptionError, match=rf"option {name} must be >= 1, got {value}"):
            sg_torchrl.make(GOAL, **{name: value})

    def test_unknown_option_is_a_type_error_naming_it(self):
        with pytest.raises(UnknownEnvOptionError, match=r"unknown option\(s\) 'lidar'; it takes cost_mode"):
            sg_torchrl.make(CHEETAH, lidar="natural")

    @pytest.mark.parametrize("value, error", [(0, InvalidEnvOptionError), (-2, InvalidEnvOptionError),
                                              (True, EnvOptionTypeError), (2.0, EnvOptionTypeError),
                                              ("2", EnvOptionTypeError)])
    def test_num_envs(self, value, error):
        with pytest.raises(error, match=rf"{CHEETAH}: num_envs must be"):
            sg_torchrl.make(CHEETAH, num_envs=value)

    @pytest.mark.parametrize("value, error", [(-1, InvalidEnvOptionError), ("3", EnvOptionTypeError),
                                              (1.5, EnvOptionTypeError), (False, EnvOptionTypeError)])
    def test_seed(self, value, error):
        # numpy's own message ("expected non-negative integer") named no seed.
        with pytest.raises(error, match=rf"{CHEETAH}: seed must be"):
            sg_torchrl.make(CHEETAH, seed=value)

    def test_cuda_device_without_cuda_names_the_device(self, monkeypatch):
        # torch's own error is a bare AssertionError ("Torch not compiled with CUDA enabled").
        monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
        with pytest.raises(InvalidEnvOptionError, match=r"device 'cuda' needs CUDA, which is not available"):
            sg_torchrl.make(CHEETAH, device="cuda")

    def test_unparsable_device_names_it(self):
        with pytest.raises(InvalidEnvOptionError, match=r"device 'gpu0' is not a torch device"):
            sg_torchrl.make(CHEETAH, device="gpu0")

    def test_errors_are_value_errors_and_type_errors_as_python_has_them(self):
        assert issubclass(InvalidEnvOptionError, ValueError)
        assert issubclass(EnvOptionTypeError, InvalidEnvOptionError) and issubclass(EnvOptionTypeError, TypeError)
        assert issubclass(UnknownEnvOptionError, EnvOptionTypeError)
        assert issubclass(UnknownEnvError, KeyError) and issubclass(UnknownEnvError, ValueError)

    def test_numpy_numbers_are_accepted_as_plain_ones(self):
        checked = validate_env_options(CHEETAH, {"max_episode_steps": np.int64(7), "velocity_threshold": np.float32(2)})
        assert checked == {"max_episode_steps": 7, "velocity_threshold": 2.0}
        assert type(checked["max_episode_steps"]) is int and type(checked["velocity_threshold"]) is float

    def test_none_where_the_type_allows_it(self):
        assert validate_env_options(GOAL, {"max_episode_steps": None}) == {"max_episode_steps": None}
        assert validate_env_options(CHEETAH, {"velocity_threshold": None, "warp_options": None}) == {
            "velocity_threshold": None, "warp_options": None}


def test_constructors_built_directly_refuse_a_string_compass_and_a_nan_threshold():
    # Without sg_torchrl.make's check in front: the envs themselves.
    from sg_torchrl.envs.navigation import NavigationEnv
    from sg_torchrl.envs.velocity import VelocityEnv

    with pytest.raises(TypeError, match="compass must be True or False, got 'no'"):
        NavigationEnv(compass="no")
    with pytest.raises(ValueError, match="velocity_threshold must be a finite number, got nan"):
        VelocityEnv("Hopper", velocity_threshold=math.nan)


class TestComplexActions:
    def test_single_agent(self):
        env = sg_torchrl.make(CHEETAH, num_envs=2, seed=0)
        td = env.reset()
        td["action"] = torch.zeros(2, 6, dtype=torch.complex64)
        with pytest.raises(TypeError, match=r"VelocityEnv: action has complex dtype torch.complex64"):
            env.step(td)

    def test_multi_agent(self):
        env = sg_torchrl.make("Safety2x3HalfCheetahVelocity-v0", num_envs=2, seed=0)
        td = env.reset()
        td["agents", "action"] = torch.zeros(2, 2, 3, dtype=torch.complex128)
        with pytest.raises(TypeError, match=r"MultiAgentVelocityEnv: action has complex dtype torch.complex128"):
            env.step(td)


# ------------------------------------------------------------------ sg-train
def cli_error(capsys, *argv: str) -> str:
    """``main(argv)``'s one error line; asserts status 2 and that no env was built."""
    code = main(list(argv))
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.startswith("sg-train: error: ")]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture
def no_env_built(monkeypatch):
    """Building an env fails the test: every bad value must be refused before that."""
    def refuse(*args, **kwargs):
        raise AssertionError("an env was built before the configuration was checked")

    monkeypatch.setattr(sg_torchrl.envs.registry, "make", refuse)
    monkeypatch.setattr(sg_torchrl, "make", refuse)


@pytest.mark.usefixtures("no_env_built")
class TestCommandLine:
    @pytest.mark.parametrize(
        "argv, message",
        [
            (["--threads", "0"], "config: threads must be >= 1, got 0"),
            (["--seed", "-1"], "config: seed must be >= 0, got -1"),
            (["--eval-episodes", "-3"], "config: eval_episodes must be >= 0, got -3"),
            (["--cost-limit", "nan"], "config: cost_limit must be a finite number, got nan"),
            (["--gamma", "inf"], "config: gamma must be a finite number, got inf"),
            (["--actor-lr", "nan"], "config: actor_lr must be a finite number"),
        ],
    )
    def test_bad_values_name_the_field(self, capsys, argv, message):
        assert message in cli_error(capsys, *argv)

    def test_total_steps_must_be_whole_epochs(self, capsys):
        # 1500 steps of 1000-step epochs used to train 1000 steps without a word.
        line = cli_error(capsys, "--total-steps", "1500", "--steps-per-epoch", "1000")
        assert "total_steps (1500) is not a multiple of steps_per_epoch (1000)" in line
        assert "1000 or 2000" in line

    @pytest.mark.parametrize("word", ["maybe", "2", "on", ""])
    def test_booleans_parse_strictly(self, capsys, word):
        line = cli_error(capsys, "--normalize-obs", word)
        assert "argument --normalize-obs" in line and "true/1/yes/false/0/no" in line

    @pytest.mark.parametrize("word, value", [("TRUE", True), ("yes", True), ("1", True), ("No", False), ("0", False)])
    def test_boolean_words(self, word, value):
        assert parse_args(["--normalize-obs", word]).normalize_obs is value

    def test_unknown_env_id_names_the_closest(self, capsys):
        line = cli_error(capsys, "--env-id", "SafetyPointGoal1-v9")
        assert "config: env_id: unknown env id 'SafetyPointGoal1-v9'" in line and "Did you mean 'SafetyPointGoal1-v0'" in line

    @pytest.mark.parametrize(
        "option, message",
        [
            ("lidar=bogus", "option lidar must be one of 'pseudo', 'natural', got 'bogus'"),
            ("compass=maybe", "option compass must be a bool"),
            ("compass=2", "option compass must be a bool"),
            ("max_episode_steps=2.5", "option max_episode_steps must be an integer"),
            ("max_episode_steps=0", "option max_episode_steps must be >= 1"),
            ("obs_mode=pixels", "option obs_mode must be one of"),
        ],
    )
    def test_bad_env_options_name_the_option_and_the_env(self, capsys, option, message):
        line = cli_error(capsys, "--env-id", GOAL, "--env-options", option)
        assert f"config: env_options: {GOAL}: {message}" in line

    @pytest.mark.parametrize("value", ["NaN", "Infinity", "-Infinity"])
    def test_non_finite_velocity_threshold(self, capsys, value):
        line = cli_error(capsys, "--env-options", f"velocity_threshold={value}")
        assert f"{CHEETAH}: option velocity_threshold must be a finite number" in line

    @pytest.mark.parametrize("word, value", [("False", False), ("no", False), ("0", False), ("false", False),
                                             ("True", True), ("yes", True), ("1", True)])
    def test_bool_option_words_become_bools(self, word, value):
        cfg = parse_args(["--env-id", GOAL, "--env-options", f"compass={word}"])
        assert cfg.env_options["compass"] is value


class TestTrainConfig:
    @pytest.mark.parametrize(
        "field, value, message",
        [
            ("normalize_obs", "no", "normalize_obs must be a bool"),
            ("progress", 1, "progress must be a bool"),
            ("seed", True, "seed must be an integer"),
            ("total_steps", 1e6, "total_steps must be an integer"),
            ("threads", 0, "threads must be >= 1"),
            ("seed", -1, "seed must be >= 0"),
            ("eval_episodes", -3, "eval_episodes must be >= 0"),
            ("cost_limit", math.nan, "cost_limit must be a finite number"),
            ("target_kl", math.inf, "target_kl must be a finite number"),
            ("multiplier_upper_bound", math.nan, "multiplier_upper_bound must be a finite number or None"),
            ("hidden_sizes", [64, 6.5], "hidden_sizes must be a list"),
            ("env_id", "SafetyPointGoal1", "env_id: unknown env id"),
            ("env_options", {"velocity_threshold": math.nan}, "option velocity_threshold must be a finite number"),
            ("env_options", {"planar_cost": "no"}, "option planar_cost must be a bool"),
        ],
    )
    def test_bad_values_are_value_errors_naming_the_field(self, field, value, message):
        with pytest.raises(ValueError, match=message):
            TrainConfig(**{field: value})

    def test_total_steps_must_be_whole_epochs(self):
        with pytest.raises(ValueError, match=r"total_steps \(50000\) is not a multiple of steps_per_epoch \(20000\)"):
            TrainConfig(total_steps=50_000)


# ------------------------------------------------------------------ errors before the heavy imports
@pytest.mark.parametrize(
    "argv, field",
    [
        (["--threads", "0"], "threads"),
        (["--env-id", "SafetyPointGoal1-v9"], "env_id"),
        (["--env-id", GOAL, "--env-options", "lidar=bogus"], "lidar"),
        (["--normalize-obs", "maybe"], "--normalize-obs"),
    ],
)
def test_bad_flags_fail_without_importing_torch(argv, field):
    """``sg-train`` checks its command line before importing torch, TorchRL or MuJoCo (seconds on a busy
    machine), so a bad flag fails in about a second."""
    code = (
        "import sys\n"
        "from sg_torchrl.train import main\n"
        f"rc = main({argv!r})\n"
        "heavy = sorted({'torch', 'torchrl', 'tensordict', 'mujoco', 'numpy'} & set(sys.modules))\n"
        "assert not heavy, heavy\n"
        "sys.exit(rc)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert result.returncode == 2, result.stderr
    assert "sg-train: error: " in result.stderr and field in result.stderr


def test_importing_the_package_and_the_registry_loads_no_simulation_stack():
    code = (
        "import sys, sg_torchrl, sg_torchrl.envs, sg_torchrl.train, sg_torchrl.train.config\n"
        "sg_torchrl.envs.validate_env_options('SafetyPointGoal1-v0', {'compass': True})\n"
        "assert len(sg_torchrl.list_envs()) > 300\n"
        "heavy = sorted({'torch', 'mujoco', 'numpy'} & set(sys.modules))\n"
        "assert not heavy, heavy\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert result.returncode == 0, result.stderr


# ------------------------------------------------------------------ the light metadata equals the env modules
def registry_from_env_modules() -> dict[str, tuple]:
    """Every id as the env modules define it (the registry's table restates this as plain data)."""
    from sg_torchrl.envs.hands import SAFETY_VARIANTS, TASKS as HAND_TASKS, MultiAgentShadowHandEnv, ShadowHandEnv
    from sg_torchrl.envs.multi_agent import SCENARIOS, MultiAgentNavigationEnv, MultiAgentVelocityEnv
    from sg_torchrl.envs.navigation import MULTI_AGENT_TASKS, ROBOTS as NAV_ROBOTS, TASKS, NavigationEnv
    from sg_torchrl.envs.velocity import ROBOTS as VELOCITY_ROBOTS, VelocityEnv
    from sg_torchrl.envs.vision import DEFAULT_IMAGE_SIZE

    ids = {}
    for robot in VELOCITY_ROBOTS.values():
        for version in sorted(robot.thresholds):
            ids[f"Safety{robot.name}Velocity-v{version}"] = (
                VelocityEnv, "velocity", robot.name, "Velocity", None, 1000, {"robot": robot.name, "version": version}, {})
    for task, levels in TASKS.items():
        for level, factory in sorted(levels.items()):
            steps = factory().max_episode_steps
            for robot in NAV_ROBOTS:
                kwargs = {"robot": robot, "task": task, "level": level}
                ids[f"Safety{robot}{task}{level}-v0"] = (NavigationEnv, "navigation", robot, task, level, steps, kwargs, {})
                ids[f"Safety{robot}{task}{level}Vision-v0"] = (
                    NavigationEnv, "vision", robot, task, level, steps, kwargs,
                    {"obs_mode": "vector+rgb", "image_size": DEFAULT_IMAGE_SIZE})
    for scenario in SCENARIOS.values():
        for conf in scenario.partitions:
            ids[f"Safety{conf}{scenario.robot}Velocity-v0"] = (
                MultiAgentVelocityEnv, "multi_agent_velocity", scenario.robot, "Velocity", None, 1000,
                {"scenario": scenario.robot, "agent_conf": conf}, {})
    for task, levels in MULTI_AGENT_TASKS.items():
        for level, factory in sorted(levels.items()):
            for robot in ("Point", "Ant"):
                ids[f"Safety{robot}{task}{level}-v0"] = (
                    MultiAgentNavigationEnv, "multi_agent_navigation", robot, task, level,
                    factory().max_episode_steps, {"robot": robot, "task": task, "level": level}, {})
    for task in HAND_TASKS.values():
        for safety in SAFETY_VARIANTS:
            env_id = f"ShadowHand{task.name.removeprefix('Hand')}{safety}-v0"
            for prefix, constructor, family in (("", ShadowHandEnv, "dexhands"),
                                                ("MultiAgent", MultiAgentShadowHandEnv, "multi_agent_dexhands")):
                ids[prefix + env_id] = (constructor, family, "ShadowHand", task.name, None, task.max_episode_steps,
                                        {"task": task.name, "safety": safety}, {})
    return ids


def test_registry_table_equals_the_env_modules():
    expected = registry_from_env_modules()
    assert sorted(_REGISTRY) == sorted(expected)
    for env_id, (constructor, *metadata) in expected.items():
        entry = registry_entry(env_id)
        got = (entry.family, entry.robot, entry.task, entry.level, entry.max_episode_steps, entry.kwargs, entry.options)
        assert got == tuple(metadata), env_id
        assert entry.constructor is constructor, env_id


def test_option_table_equals_the_constructors_annotations():
    """``CONSTRUCTOR_OPTIONS`` restates the constructors' signatures (names, order, resolved annotations)."""
    fixed_by_path = {}
    for entry in _REGISTRY.values():
        fixed_by_path.setdefault(entry.constructor_path, set(entry.kwargs))
    assert set(fixed_by_path) == set(CONSTRUCTOR_OPTIONS)
    for path, table in CONSTRUCTOR_OPTIONS.items():
        entry = next(e for e in _REGISTRY.values() if e.constructor_path == path)
        options, open_ended = signature_options(entry.constructor, fixed_by_path[path])
        assert not open_ended, path
        assert list(table) == list(options), path
        for name, option in table.items():
            assert option.annotation == options[name].annotation, (path, name)


def test_command_line_words_only_convert_bool_options():
    options = {"compass": "no", "lidar": "natural", "max_episode_steps": 1, "obs_mode": "rgb"}
    assert command_line_env_options(GOAL, options) == {**options, "compass": False}
    assert command_line_env_options(CHEETAH, {"planar_cost": "Yes"}) == {"planar_cost": True}
    assert command_line_env_options("NoSuchEnv-v0", {"compass": "no"}) == {"compass": "no"}
