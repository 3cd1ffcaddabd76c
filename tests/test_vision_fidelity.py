"""The Vision ids against Safety-Gymnasium 1.0.0: observation layout, camera poses, image statistics.

What is compared, and why it matters: a policy trained on one implementation's Vision ids must see the
same inputs on the other. So

* the layout: by default the flat vector and a ``256 x 256 x 3`` ``uint8`` image (``obs_mode="vector+rgb"``,
  ``image_size=256``), which :class:`~sg_torchrl.envs.vision.DictLayout` maps to the original's dict
  (its keys, order, shapes and bounds are hard-coded below from the original's observation space);
  smaller images stay an option;
* each robot's ``vision`` camera: position and axes relative to its root body, and field of view
  (hard-coded from the original's compiled models);
* what the camera sees: the mean pixel value and the share of black pixels over a few layouts and
  random steps, within a stated tolerance of numbers measured on the original (see
  :data:`REFERENCE_STATISTICS`).

An optional test compares directly with the original (``SG_ORACLE_PYTHON``, default
``/root/sg_oracle/bin/python``; see ``tests/test_env_fidelity_oracle.py``) and skips without it.
Tests that draw need an OpenGL backend and skip without one (the ``backend`` fixture). All but
one use small images: statistics of area (mean, share of black pixels) agree between 64 x 64 and
256 x 256 within 0.5 and 0.01 (measured on PointGoal1, CarButton1 and RacecarGoal1).
"""

from __future__ import annotations

import functools
import json
import os
import subprocess
import textwrap

import mujoco
import numpy as np
import pytest
import torch

import sg_torchrl
from sg_torchrl.envs import registry_entry
from sg_torchrl.envs.vision import DictLayout

torch.set_num_threads(1)

ORACLE_PYTHON = os.environ.get("SG_ORACLE_PYTHON", "/root/sg_oracle/bin/python")
VISION_IDS = sg_torchrl.list_envs(family="vision")

_SENSORS = [("accelerometer", (3,)), ("velocimeter", (3,)), ("gyro", (3,)), ("magnetometer", (3,))]
_ANT_JOINTS = [f"{part}_{leg}" for leg in range(1, 5) for part in ("hip", "ankle")]
#: The original's dict observation space (``env.observation_space.spaces``, safety-gymnasium 1.0.0):
#: keys in order with their shapes; vector entries are float64, lidar bounded by [0, 1], the rest unbounded.
ORIGINAL_LAYOUTS = {
    "SafetyPointGoal1Vision-v0": [*_SENSORS, ("goal_lidar", (16,)), ("hazards_lidar", (16,)),
                                  ("vases_lidar", (16,))],
    "SafetyCarButton1Vision-v0": [*_SENSORS, ("ballangvel_rear", (3,)), ("ballquat_rear", (3, 3)),
                                  ("buttons_lidar", (16,)), ("goal_lidar", (16,)), ("hazards_lidar", (16,)),
                                  ("gremlins_lidar", (16,))],
    "SafetyRacecarPush2Vision-v0": [*_SENSORS, ("goal_lidar", (16,)), ("hazards_lidar", (16,)),
                                    ("pillars_lidar", (16,)), ("push_box_lidar", (16,))],
    "SafetyAntGoal0Vision-v0": [*_SENSORS, *((f"{joint}_vel", (1,)) for joint in _ANT_JOINTS),
                                ("agent_pos", (1,)), ("agent_qvel", (3,)), *((joint, (2,)) for joint in _ANT_JOINTS),
                                ("goal_lidar", (16,))],
}

#: Each robot's ``vision`` camera in the original, relative to its root body (its compiled model after
#: ``reset``): position, the camera's axes as the columns of a rotation matrix, vertical field of view.
#: Car's body frame here is the original's turned by 90 degrees (it drives along +x, the original's
#: along -y; sg_torchrl/envs/navigation/robots/car.py), so its values are given in this frame.
ORIGINAL_CAMERAS = {
    "Point": ((0.0, 0.0, 0.15), [[0, 0.3714, -0.9285], [-1, 0, 0], [0, 0.9285, 0.3714]], 90.0),
    "Car": ((-0.1, 0.0, 0.2), [[0, 0.3714, -0.9285], [-1, 0, 0], [0, 0.9285, 0.3714]], 45.0),
    "Racecar": ((0.2, 0.0, 0.05), [[0, 0, -1], [-1, 0, 0], [0, 1, 0]], 45.0),
    "Ant": ((0.0, 0.05, 0.05), [[1, 0, 0], [0, 0, -1], [0, 1, 0]], 45.0),
    "Doggo": ((0.0625, 0.0, 0.1), [[0, 0.3714, -0.9285], [-1, 0, 0], [0, 0.9285, 0.3714]], 100.0),
}

#: Image statistics of the original: (mean pixel value in [0, 255], share of black pixels, i.e. all three
#: channels <= 10). Measured on safety-gymnasium 1.0.0 (Python 3.10, mujoco 2.3.3, MUJOCO_GL=egl, 256 x
#: 256) with the protocol of :func:`statistics`: seeds 0, 1 and 2; the frame after ``reset`` and after
#: every 5th of 20 uniform random actions; 15 frames per id. Ours before this fix (plain grey floor under a
#: spot light, black sky, other camera poses): PointGoal1 87.1 / 0.347, CarButton1 96.9 / 0.337,
#: RacecarGoal1 122.8 / 0.331, DoggoGoal1 93.4 / 0.367, PointCircle1 90.8 / 0.149.
REFERENCE_STATISTICS = {
    "SafetyPointGoal1Vision-v0": (109.1, 0.344),
    "SafetyCarButton1Vision-v0": (152.0, 0.097),
    "SafetyRacecarGoal1Vision-v0": (93.8, 0.536),
    "SafetyDoggoGoal1Vision-v0": (112.0, 0.365),
    "SafetyPointCircle1Vision-v0": (116.1, 0.177),
}
#: Not compared here, measured the same way (ours / original's): AntGoal1 79.6 / 0.548 against 76.1 / 0.645
#: (the ant turns over within 20 random steps in both, but not in the same frames: its black share follows
#: the dynamics, not the scene) and RacecarGoal0 55.2 / 0.046 against 71.1 / 0.199 (the original's near
#: plane, 1% of a per-layout extent of 1.2-1.5 m, clips the bumper 13.5 mm ahead of the camera in some layouts
#: and not in others; ours, at the mean extent, never clips it). Race cannot be built by the original
#: (its village floor texture is missing from the 1.0.0 wheel).
#: Tolerances: layouts and dynamics differ between the implementations (different random streams), so
#: the same seed shows a different scene; 15 frames vary by a few units. The old scene failed both by far
#: in every id but one (PointGoal1's mean was 22 lower; CarButton1 had 3.5 times the black pixels).
MEAN_TOLERANCE = 10.0
BLACK_TOLERANCE = 0.06


def statistics(env_id: str, image_size: int = 64, seeds=(0, 1, 2), steps: int = 20) -> tuple[float, float]:
    """Mean pixel value and share of black pixels of ``env_id``'s images (protocol: :data:`REFERENCE_STATISTICS`)."""
    env = sg_torchrl.make(env_id, num_envs=len(seeds), seed=list(seeds), obs_mode="rgb", image_size=image_size)
    generator = np.random.default_rng(0)
    td = env.reset()
    frames = [td["pixels"]]
    for step in range(steps):
        action = torch.as_tensor(generator.uniform(-1.0, 1.0, env.action_spec.shape), dtype=torch.float32)
        td = env.step(td.set("action", action))["next"]
        if (step + 1) % 5 == 0:
            frames.append(td["pixels"])
    env.close()
    images = torch.stack(frames).numpy().astype(np.float64)
    return float(images.mean()), float((images.max(axis=-1) <= 10).mean())


# ---------------------------------------------------------------------------- layout
def test_vision_ids_default_to_the_original_layout():
    for env_id in VISION_IDS:
        assert registry_entry(env_id).options == {"obs_mode": "vector+rgb", "image_size": 256}, env_id


def test_default_observation_is_the_vector_and_a_256_pixel_image(backend):
    env = sg_torchrl.make("SafetyPointGoal1Vision-v0", seed=0)
    spec = env.observation_spec
    assert spec["pixels"].shape == (1, 256, 256, 3) and spec["pixels"].dtype == torch.uint8
    assert spec["observation"].shape == (1, 60)
    td = env.reset()
    assert td["pixels"].shape == (1, 256, 256, 3) and td["pixels"].dtype == torch.uint8
    observation = DictLayout.of(env).split(td)
    assert list(observation) == [name for name, _ in ORIGINAL_LAYOUTS["SafetyPointGoal1Vision-v0"]] + ["vision"]
    assert observation["vision"].shape == (256, 256, 3) and observation["vision"].dtype == np.uint8
    np.testing.assert_array_equal(observation["vision"], td["pixels"][0].numpy())
    np.testing.assert_array_equal(np.concatenate([observation[name].reshape(-1) for name in list(observation)[:-1]]),
                                  td["observation"][0].numpy().astype(np.float64))
    env.close()


@pytest.mark.parametrize("env_id", sorted(ORIGINAL_LAYOUTS))
def test_dict_layout_equals_the_original(backend, env_id):
    env = sg_torchrl.make(env_id, seed=0, image_size=16)
    layout = DictLayout.of(env)
    expected = [*ORIGINAL_LAYOUTS[env_id], ("vision", (16, 16, 3))]
    assert [(entry.name, entry.shape) for entry in layout.entries] == expected
    for entry in layout.entries[:-1]:
        assert entry.dtype == "float64"
        bounds = (0.0, 1.0) if entry.name.endswith("_lidar") else (-np.inf, np.inf)
        assert (entry.low, entry.high) == bounds, entry.name
    assert (layout.entries[-1].dtype, layout.entries[-1].low, layout.entries[-1].high) == ("uint8", 0.0, 255.0)
    observation = layout.split(env.reset())
    for entry in layout.entries:
        assert observation[entry.name].shape == entry.shape and observation[entry.name].dtype == entry.dtype
    if "ballquat_rear" in observation:  # a rotation matrix, row-major as the original's
        matrix = observation["ballquat_rear"]
        np.testing.assert_allclose(matrix @ matrix.T, np.eye(3), atol=1e-5)
    env.close()


def test_smaller_images_and_pixels_only_are_options(backend):
    env = sg_torchrl.make("SafetyCarGoal1Vision-v0", num_envs=2, seed=0, image_size=64)
    td = env.reset()
    assert td["pixels"].shape == (2, 64, 64, 3) and td["observation"].shape == (2, 72)
    env.close()
    pixels_only = sg_torchrl.make("SafetyCarGoal1Vision-v0", num_envs=2, seed=0, obs_mode="rgb", image_size=32)
    assert set(pixels_only.reset().keys()) >= {"pixels"} and "observation" not in pixels_only.observation_spec.keys()
    with pytest.raises(ValueError, match="obs_mode='vector\\+rgb'"):
        DictLayout.of(pixels_only)
    pixels_only.close()


# ---------------------------------------------------------------------------- the camera and the scene
@pytest.mark.parametrize("robot", sorted(ORIGINAL_CAMERAS))
def test_vision_camera_pose_and_field_of_view_are_the_originals(robot):
    env = sg_torchrl.make(f"Safety{robot}Goal1-v0", seed=0)  # the camera is in every world; no drawing
    env.reset()
    model, data = env.physics.model, env.physics.datas[0]
    camera = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "vision")
    root = env.scene.agent_body
    body = data.xmat[root].reshape(3, 3)
    position, axes, fovy = ORIGINAL_CAMERAS[robot]
    np.testing.assert_allclose(body.T @ (data.cam_xpos[camera] - data.xpos[root]), position, atol=1e-6)
    np.testing.assert_allclose(body.T @ data.cam_xmat[camera].reshape(3, 3), axes, atol=2e-3)
    assert model.cam_fovy[camera] == pytest.approx(fovy)


def test_clipping_planes_follow_the_originals_extent():
    # Near plane 1% of the extent: 2.9 cm at Goal level 1, 9.3 cm at Circle level 1 (its walls' extent).
    for env_id, near in (("SafetyRacecarGoal1-v0", 0.0288), ("SafetyPointCircle1-v0", 0.0928)):
        near_plane, _ = sg_torchrl.make(env_id).depth_range()
        assert near_plane == pytest.approx(near, rel=1e-3), env_id


@pytest.mark.parametrize("env_id", sorted(REFERENCE_STATISTICS))
def test_image_statistics_match_the_original(backend, env_id):
    mean, black = statistics(env_id)
    reference_mean, reference_black = REFERENCE_STATISTICS[env_id]
    assert abs(mean - reference_mean) <= MEAN_TOLERANCE, (env_id, mean, reference_mean)
    assert abs(black - reference_black) <= BLACK_TOLERANCE, (env_id, black, reference_black)


# ---------------------------------------------------------------------------- optional: the original itself
_PROBE = textwrap.dedent("""
    import json, sys, warnings
    warnings.filterwarnings("ignore")
    import numpy as np
    import safety_gymnasium

    out = {}
    for env_id in sys.argv[1:]:
        env = safety_gymnasium.make(env_id)
        space = env.observation_space.spaces
        frames = []
        for seed in (0, 1, 2):
            obs, _ = env.reset(seed=seed)
            frames.append(obs["vision"])
            generator = np.random.default_rng(seed)
            for step in range(20):
                obs, _, _, terminated, truncated, _ = env.step(generator.uniform(-1, 1, env.action_space.shape))
                if terminated or truncated:
                    break
                if (step + 1) % 5 == 0:
                    frames.append(obs["vision"])
        images = np.stack(frames).astype(np.float64)
        out[env_id] = {"keys": [[key, list(box.shape), str(box.dtype)] for key, box in space.items()],
                       "mean": float(images.mean()), "black": float((images.max(axis=-1) <= 10).mean())}
    print(json.dumps(out))
""")
_ORACLE_IDS = ("SafetyPointGoal1Vision-v0", "SafetyCarButton1Vision-v0")


@functools.lru_cache(maxsize=1)
def oracle() -> dict:
    if not os.path.exists(ORACLE_PYTHON):
        pytest.skip(f"no safety-gymnasium 1.0.0 oracle at {ORACLE_PYTHON} (set SG_ORACLE_PYTHON; module docstring)")
    result = subprocess.run([ORACLE_PYTHON, "-c", _PROBE, *_ORACLE_IDS], capture_output=True, text=True,
                            timeout=600, env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    if result.returncode != 0:
        pytest.skip(f"the oracle failed: {result.stderr.strip().splitlines()[-1:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("env_id", _ORACLE_IDS)
def test_against_the_oracle(backend, env_id):
    theirs = oracle()[env_id]
    env = sg_torchrl.make(env_id, seed=0)  # the default: 256 x 256, the vector and the image
    ours = [[entry.name, list(entry.shape), entry.dtype] for entry in DictLayout.of(env).entries]
    env.close()
    assert ours == theirs["keys"]
    mean, black = statistics(env_id)
    assert abs(mean - theirs["mean"]) <= MEAN_TOLERANCE and abs(black - theirs["black"]) <= BLACK_TOLERANCE
