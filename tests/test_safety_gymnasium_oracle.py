"""Optional oracle: sg_torchrl.safety_gymnasium against safety-gymnasium 1.0.0 itself.

The original only installs on Python <= 3.10, so it runs in its own virtual environment, in a
subprocess that prints what these tests compare (spaces, ``spec.max_episode_steps``, the 6-tuple's
types, info keys, ``make_ma``'s agents and sizes, the vector envs' spaces). Set it up with::

    python3.10 -m venv /root/sg_oracle && /root/sg_oracle/bin/pip install safety-gymnasium==1.0.0

(or point ``SG_ORACLE_PYTHON`` at such an interpreter). Without it every test here skips with that
reason, so the suite passes without the oracle.
"""

from __future__ import annotations

import json
import os
import subprocess
import textwrap

import numpy as np
import pytest

import sg_torchrl.safety_gymnasium as safety_gymnasium

ORACLE_PYTHON = os.environ.get("SG_ORACLE_PYTHON", "/root/sg_oracle/bin/python")
SINGLE_IDS = ["SafetyPointGoal1-v0", "SafetyCarButton1-v0", "SafetyPointCircle1-v0", "SafetyAntGoal0-v0",
              "SafetyHalfCheetahVelocity-v1", "SafetyHumanoidVelocity-v0"]
PARTITIONS = [("Ant", "2x4"), ("HalfCheetah", "6x1"), ("Hopper", "3x1"), ("Humanoid", "9|8")]

_PROBE = textwrap.dedent("""
    import json, sys, warnings
    warnings.filterwarnings("ignore")
    import numpy as np
    import safety_gymnasium

    def box(space):
        return {"shape": list(space.shape), "dtype": str(space.dtype),
                "low": np.asarray(space.low, dtype=float).tolist(), "high": np.asarray(space.high, dtype=float).tolist()}

    single_ids, partitions = json.loads(sys.argv[1])
    out = {"single": {}, "ma": {}, "vector": None}
    for env_id in single_ids:
        env = safety_gymnasium.make(env_id)
        env.reset(seed=0)
        step = env.step(env.action_space.sample())
        out["single"][env_id] = {
            "observation": box(env.observation_space), "action": box(env.action_space),
            "max_episode_steps": env.spec.max_episode_steps, "step_len": len(step),
            "types": [type(step[i]).__name__ for i in (3, 4)], "cost": float(step[2]),
            "info_keys": sorted(step[5]), "render_modes": env.metadata["render_modes"],
        }
        env.close()
    for scenario, conf in partitions:
        env = safety_gymnasium.make_ma(scenario, conf)
        env.reset(seed=0)
        out["ma"][f"{scenario} {conf}"] = {
            "agents": list(env.possible_agents),
            "observation": [list(env.observation_space(a).shape) for a in env.possible_agents],
            "action": [box(env.action_space(a)) for a in env.possible_agents],
            "state": list(env.state().shape),
            "partitions": [[node.label for node in part] for part in env.agent_action_partitions],
        }
    envs = safety_gymnasium.vector.make("SafetyPointGoal1-v0", num_envs=2, asynchronous=False)
    out["vector"] = {"observation": list(envs.observation_space.shape), "single": list(envs.single_observation_space.shape),
                     "action": list(envs.action_space.shape)}
    print("ORACLE" + json.dumps(out))
""")


@pytest.fixture(scope="module")
def oracle() -> dict:
    if not os.path.exists(ORACLE_PYTHON):
        pytest.skip(f"no safety-gymnasium 1.0.0 oracle at {ORACLE_PYTHON} (see this module's docstring)")
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "PYTHONPATH": ""}
    result = subprocess.run([ORACLE_PYTHON, "-c", _PROBE, json.dumps([SINGLE_IDS, PARTITIONS])], capture_output=True,
                            text=True, timeout=600, env=env, cwd="/tmp")
    lines = [line for line in result.stdout.splitlines() if line.startswith("ORACLE")]
    if result.returncode != 0 or not lines:
        pytest.skip(f"the oracle at {ORACLE_PYTHON} did not run: {result.stderr[-1500:]}")
    return json.loads(lines[-1][len("ORACLE"):])


@pytest.mark.parametrize("env_id", SINGLE_IDS)
def test_single_agent_ids_match_the_oracle(oracle, env_id):
    theirs = oracle["single"][env_id]
    env = safety_gymnasium.make(env_id)
    assert list(env.observation_space.shape) == theirs["observation"]["shape"]
    assert str(env.observation_space.dtype) == theirs["observation"]["dtype"] == "float64"
    np.testing.assert_array_equal(env.observation_space.low, theirs["observation"]["low"])  # lidar in [0, 1]
    np.testing.assert_array_equal(env.observation_space.high, theirs["observation"]["high"])
    assert list(env.action_space.shape) == theirs["action"]["shape"]
    np.testing.assert_allclose(env.action_space.low, theirs["action"]["low"], rtol=1e-6)
    np.testing.assert_allclose(env.action_space.high, theirs["action"]["high"], rtol=1e-6)
    assert env.spec.max_episode_steps == theirs["max_episode_steps"]
    env.reset(seed=0)
    step = env.step(env.action_space.sample())
    assert len(step) == theirs["step_len"] == 6
    assert [type(step[i]).__name__ for i in (3, 4)] == theirs["types"]
    if "Velocity" not in env_id:  # the velocity ids' info is gymnasium's terms there (x_velocity, ...)
        assert sorted(step[5]) == theirs["info_keys"]
    assert set(theirs["render_modes"]) <= set(safety_gymnasium.make(env_id).unwrapped.metadata["render_modes"]) | {
        "human"}
    env.close()


@pytest.mark.parametrize(("scenario", "conf"), PARTITIONS)
def test_make_ma_matches_the_oracle(oracle, scenario, conf):
    theirs = oracle["ma"][f"{scenario} {conf}"]
    env = safety_gymnasium.make_ma(scenario, conf)
    env.reset(seed=0)
    assert env.possible_agents == theirs["agents"]
    assert [list(env.observation_space(a).shape) for a in env.possible_agents] == theirs["observation"]
    for agent, box in zip(env.possible_agents, theirs["action"]):
        space = env.action_space(agent)
        assert list(space.shape) == box["shape"] and str(space.dtype) == box["dtype"]
        np.testing.assert_allclose(space.low, box["low"], rtol=1e-6)
        np.testing.assert_allclose(space.high, box["high"], rtol=1e-6)
    assert list(env.state().shape) == theirs["state"]
    assert [[node.label for node in part] for part in env.agent_action_partitions] == theirs["partitions"]
    env.close()


def test_vector_spaces_match_the_oracle(oracle):
    envs = safety_gymnasium.vector.make("SafetyPointGoal1-v0", num_envs=2, asynchronous=False)
    assert list(envs.observation_space.shape) == oracle["vector"]["observation"]
    assert list(envs.single_observation_space.shape) == oracle["vector"]["single"]
    assert list(envs.action_space.shape) == oracle["vector"]["action"]
    envs.close()


def test_top_level_constants_match_the_oracle():
    if not os.path.exists(ORACLE_PYTHON):
        pytest.skip(f"no safety-gymnasium 1.0.0 oracle at {ORACLE_PYTHON} (see this module's docstring)")
    names = ["VERSION", "PREFIX", "ROBOT_NAMES", "MAKE_VISION_ENVIRONMENTS", "goal_tasks", "button_tasks",
             "push_tasks", "circle_tasks", "run_tasks", "race_tasks", "fading_tasks", "__version__"]
    code = ("import json, warnings; warnings.filterwarnings('ignore'); import safety_gymnasium as s; "
            f"print('ORACLE' + json.dumps({{n: getattr(s, n) for n in {names!r}}}))")
    result = subprocess.run([ORACLE_PYTHON, "-c", code], capture_output=True, text=True, timeout=300,
                            env={**os.environ, "PYTHONPATH": ""}, cwd="/tmp")
    lines = [line for line in result.stdout.splitlines() if line.startswith("ORACLE")]
    if result.returncode != 0 or not lines:
        pytest.skip(f"the oracle at {ORACLE_PYTHON} did not run: {result.stderr[-1500:]}")
    theirs = json.loads(lines[-1][len("ORACLE"):])
    ours = json.loads(json.dumps({name: getattr(safety_gymnasium, name) for name in names}))
    assert ours == theirs
