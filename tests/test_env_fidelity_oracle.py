"""Optional oracle for the fidelity fixes of ``test_env_fidelity.py`` and ``test_cameras.py``:
safety-gymnasium 1.0.0 itself, probed in a subprocess of its own Python 3.10 virtual environment.

Set it up with ``python3.10 -m venv /root/sg_oracle && /root/sg_oracle/bin/pip install
safety-gymnasium==1.0.0`` (or point ``SG_ORACLE_PYTHON`` at such an interpreter); without it every
test here skips, so the suite passes without the oracle. What is compared: the button timer and
``buttons_lidar`` right after ``reset``, the norm of the first observation's torso quaternion
(Ant, Humanoid), the velocity ids' ``info`` keys, and the world pose of the navigation cameras.
"""

from __future__ import annotations

import functools
import json
import math
import os
import subprocess
import textwrap

import numpy as np
import pytest

import sg_torchrl

ORACLE_PYTHON = os.environ.get("SG_ORACLE_PYTHON", "/root/sg_oracle/bin/python")
VELOCITY_ROBOTS = ("HalfCheetah", "Hopper", "Walker2d", "Swimmer", "Ant", "Humanoid")

_PROBE = textwrap.dedent("""
    import json, warnings
    warnings.filterwarnings("ignore")
    import gymnasium
    import mujoco
    import numpy as np
    import safety_gymnasium

    out = {"button": [], "quaternion": {}, "info": {}, "cameras": {}}
    env = safety_gymnasium.make("SafetyPointButton1-v0")
    for seed in range(4):
        obs, _ = env.reset(seed=seed)
        task = env.unwrapped.task
        lidar = gymnasium.spaces.utils.unflatten(env.unwrapped.obs_space_dict, obs)["buttons_lidar"]
        out["button"].append({"timer": int(task.buttons.timer), "lidar_max": float(np.max(lidar))})
    for robot in ("Ant", "Humanoid"):
        env = safety_gymnasium.make(f"Safety{robot}Velocity-v1")
        out["quaternion"][robot] = [float(np.linalg.norm(env.reset(seed=s)[0][1:5])) for s in range(20)]
    for robot in %(robots)r:
        env = safety_gymnasium.make(f"Safety{robot}Velocity-v1")
        env.reset(seed=0)
        out["info"][robot] = list(env.step(env.action_space.sample())[5])
    env = safety_gymnasium.make("SafetyCarGoal1-v0")
    for seed in range(3):
        env.reset(seed=seed)
        task = env.unwrapped.task
        model, data = task.model, task.data
        poses = {}
        for name in ("fixednear", "fixedfar", "track"):
            cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
            frame = data.cam_xmat[cam].reshape(3, 3)
            origin = data.xpos[model.cam_bodyid[cam]] if name == "track" else np.zeros(3)
            poses[name] = {"offset": (data.cam_xpos[cam] - origin).tolist(), "forward": (-frame[:, 2]).tolist(),
                           "up": frame[:, 1].tolist(), "fovy": float(model.cam_fovy[cam])}
        out["cameras"][seed] = poses
    print(json.dumps(out))
""") % {"robots": VELOCITY_ROBOTS}


@functools.lru_cache(maxsize=1)
def oracle() -> dict:
    if not os.path.exists(ORACLE_PYTHON):
        pytest.skip(f"no safety-gymnasium 1.0.0 oracle at {ORACLE_PYTHON} (set SG_ORACLE_PYTHON; module docstring)")
    result = subprocess.run([ORACLE_PYTHON, "-c", _PROBE], capture_output=True, text=True, timeout=600,
                            env={**os.environ, "MUJOCO_GL": "egl"})
    if result.returncode != 0:
        pytest.skip(f"the oracle failed: {result.stderr.strip().splitlines()[-1:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_button_timer_is_zero_after_reset_in_both():
    for probe in oracle()["button"]:
        assert probe["timer"] == 0 and probe["lidar_max"] > 0
    env = sg_torchrl.make("SafetyPointButton1-v0", num_envs=4, seed=0)
    obs = env.reset()["observation"].numpy()
    assert (env.task.buttons.timer == 0).all()
    assert (obs[:, env.observation_slices["buttons_lidar"]].max(axis=1) > 0).all()


@pytest.mark.parametrize("robot", ["Ant", "Humanoid"])
def test_first_quaternion_is_unit_in_both(robot):
    np.testing.assert_allclose(oracle()["quaternion"][robot], 1.0, atol=1e-12)
    env = sg_torchrl.make(f"Safety{robot}Velocity-v1", num_envs=20, seed=0)
    quat = env.reset()["observation"][:, 1:5].double().norm(dim=1).numpy()
    np.testing.assert_allclose(quat, 1.0, atol=1e-6)


@pytest.mark.parametrize("robot", VELOCITY_ROBOTS)
def test_velocity_info_keys_equal(robot):
    env = sg_torchrl.make(f"Safety{robot}Velocity-v1", seed=0)
    assert list(env.info_keys) == oracle()["info"][robot]


def test_navigation_camera_poses_equal():
    env = sg_torchrl.make("SafetyCarGoal1-v0", num_envs=3, seed=0)
    env.reset()
    model = env.physics.model
    root = env._render_body()
    for seed, poses in oracle()["cameras"].items():
        index = int(seed)
        data = env.physics.datas[index]
        for name, expected in poses.items():
            cam = model.camera(name).id
            frame = data.cam_xmat[cam].reshape(3, 3)
            origin = data.xpos[root] if name == "track" else np.zeros(3)
            np.testing.assert_allclose(data.cam_xpos[cam] - origin, expected["offset"], atol=1e-6, err_msg=name)
            np.testing.assert_allclose(-frame[:, 2], expected["forward"], atol=1e-6, err_msg=name)
            np.testing.assert_allclose(frame[:, 1], expected["up"], atol=1e-6, err_msg=name)
            assert math.isclose(model.cam_fovy[cam], expected["fovy"]), name
