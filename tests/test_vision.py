"""Pixel observations of the navigation envs (``sg_torchrl.envs.vision``) and the ``...Vision-v0`` ids.

Tests that draw need an OpenGL backend (EGL or OSMesa through Mesa, no GPU needed): without one they
skip with the reason :func:`~sg_torchrl.envs.rendering.gl_backend` gives. The option checks, the
registry entries and the error a pixel env raises without OpenGL are tested without drawing.
Depth is checked against geometry worked out from the camera pose: with an odd image size the centre
pixel lies on the camera's optical axis, so its depth is the distance along that axis to what it hits.
"""

from __future__ import annotations

import copy
import warnings

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from torchrl.envs import ToTensorImage, TransformedEnv
from torchrl.envs.utils import check_env_specs

import sg_torchrl
import sg_torchrl.gym as sg_gym
from sg_torchrl.envs import registry_entry
from sg_torchrl.envs import opengl, rendering
from sg_torchrl.envs.navigation import ROBOTS, NavigationEnv
from sg_torchrl.envs.rendering import RenderingUnavailable
from sg_torchrl.envs.vision import OBS_MODES, ObservationContent

from test_navigation import action_td, arrange, idle, make_env

torch.set_num_threads(1)

VISION_ID = "SafetyPointGoal1Vision-v0"
VISION_IDS = sg_torchrl.list_envs(family="vision")


def random_actions(env, steps: int, seed: int) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    box = env.action_spec.space
    return [box.low + (box.high - box.low) * torch.rand(box.low.shape, generator=generator) for _ in range(steps)]


def run(env, actions: list[torch.Tensor]) -> list:
    """Reset, then step ``actions``: the emitted TensorDicts (reset first)."""
    outputs = [env.reset()]
    for action in actions:
        outputs.append(env.step(action_td(env, action))["next"])
    return outputs


# ---------------------------------------------------------------------------- options (no OpenGL needed)
def test_obs_modes_parse():
    assert OBS_MODES == ("vector", "rgb", "rgbd", "vector+rgb", "vector+rgbd")
    assert ObservationContent.parse("vector") == ObservationContent(vector=True, rgb=False, depth=False)
    assert ObservationContent.parse("rgbd") == ObservationContent(vector=False, rgb=True, depth=True)
    assert ObservationContent.parse("vector+rgb") == ObservationContent(vector=True, rgb=True, depth=False)
    assert not ObservationContent.parse("vector").pixels and ObservationContent.parse("rgb").pixels


@pytest.mark.parametrize("obs_mode", ["pixels", "RGB", "rgb+vector", "", None])
def test_bad_obs_mode_names_the_valid_ones(obs_mode):
    with pytest.raises(ValueError, match=r"obs_mode must be one of 'vector', 'rgb', 'rgbd', 'vector\+rgb'"):
        make_env(VISION_ID, obs_mode=obs_mode)


def test_pixels_are_for_single_robot_tasks():
    with pytest.raises(ValueError, match="single-robot"):
        NavigationEnv("Point", "MultiGoal", 0, obs_mode="rgb")


def test_vision_ids_in_the_registry():
    navigation = sg_torchrl.list_envs(family="navigation")
    assert len(VISION_IDS) == 170 == len(navigation)  # 22 per robot (reference, Fading, Race), 12 Building/FormulaOne
    assert VISION_IDS == sorted(i.replace("-v0", "Vision-v0") for i in navigation)
    for robot in ROBOTS:
        for task in ("Goal", "Button", "Push", "Circle", "FadingEasy", "FadingHard", "Race", "BuildingGoal",
                     "BuildingButton", "BuildingPush", "FormulaOne"):
            for level in range(3):
                assert f"Safety{robot}{task}{level}Vision-v0" in VISION_IDS
        assert f"Safety{robot}Run0Vision-v0" in VISION_IDS
    for env_id in VISION_IDS:
        entry, plain = registry_entry(env_id), registry_entry(env_id.replace("Vision", ""))
        assert (entry.family, entry.constructor) == ("vision", NavigationEnv)
        assert (entry.robot, entry.task, entry.level, entry.max_episode_steps, entry.kwargs) == (
            plain.robot, plain.task, plain.level, plain.max_episode_steps, plain.kwargs)
        assert entry.options == {"obs_mode": "vector+rgb", "image_size": 256}  # the original's (test_vision_fidelity)
    assert not set(VISION_IDS) & set(sg_torchrl.list_envs(family="navigation"))


def test_sg_train_takes_pixel_envs_and_refuses_images_too_small_for_its_cnn():
    from sg_torchrl.train.config import TrainConfig

    # Pixel envs train through CNN encoders (tests/test_train_vision.py runs them).
    assert TrainConfig(env_id=VISION_ID).env_id == VISION_ID
    assert TrainConfig(env_id="SafetyPointGoal1-v0", env_options={"obs_mode": "rgbd"}).env_options["obs_mode"] == "rgbd"
    with pytest.raises(ValueError, match="image_size=16 is too small for sg-train's CNN encoder.*>= 36"):
        TrainConfig(env_id=VISION_ID, env_options={"image_size": 16})
    assert TrainConfig(env_id=VISION_ID, env_options={"image_size": 36}).env_options["image_size"] == 36
    assert TrainConfig(env_id=VISION_ID, env_options={"obs_mode": "vector", "image_size": 16}).env_id == VISION_ID


def test_without_opengl_a_pixel_env_says_why(monkeypatch):
    monkeypatch.setattr(opengl, "_backend", None)
    monkeypatch.setattr(opengl, "_backend_error", None)
    monkeypatch.setenv("MUJOCO_GL", "disable")
    with pytest.raises(RenderingUnavailable, match="disabled"):
        make_env(VISION_ID)
    assert make_env("SafetyPointGoal1-v0").vision is None  # vector envs never need OpenGL


# ---------------------------------------------------------------------------- shapes, dtypes, ranges
@pytest.mark.parametrize("robot", sorted(ROBOTS))
def test_every_robot_sees_through_its_camera(backend, robot):
    # Pixels only (obs_mode="rgb"), 64 x 64: the Vision ids' default, the vector and 256 x 256 images, is
    # tested in tests/test_vision_fidelity.py.
    env = make_env(f"Safety{robot}Goal1Vision-v0", num_envs=2, obs_mode="rgb", image_size=64)
    assert "observation" not in env.observation_spec.keys()
    spec = env.observation_spec["pixels"]
    assert spec.shape == (2, 64, 64, 3) and spec.dtype == torch.uint8  # TorchRL's raw pixels: channels last
    assert spec.space.low.min() == 0 and spec.space.high.max() == 255
    outputs = run(env, random_actions(env, 3, seed=0))
    for td in outputs:
        assert "observation" not in td.keys()
        pixels = td["pixels"]
        assert pixels.shape == (2, 64, 64, 3) and pixels.dtype == torch.uint8 and pixels.is_contiguous()
        assert env.observation_spec.is_in(td.select(*env.observation_spec.keys()))
        for image in pixels:  # a picture of the world, not a blank frame
            assert image.float().std() > 5 and len(image.reshape(-1, 3).unique(dim=0)) > 10
        assert torch.isfinite(td["cost"]).all()
    assert not torch.equal(outputs[0]["pixels"][0], outputs[0]["pixels"][1])  # two layouts, two pictures
    with pytest.raises(ValueError, match="no flat 'observation'"):
        env.observation_dim
    env.close()


def test_every_vision_id_builds_and_renders(backend):
    # The registry-wide tests (tests/test_registry.py) leave the Vision ids to this file: every scene and
    # robot camera, small images, one simulator, two steps (about 20 s for the 170 ids).
    for env_id in VISION_IDS:
        env = sg_torchrl.make(env_id, num_envs=1, seed=0, image_size=8)
        nxt = env.rollout(2, break_when_any_done=False)["next"]
        assert nxt["pixels"].shape == (1, 2, 8, 8, 3) and nxt["pixels"].dtype == torch.uint8, env_id
        assert nxt["pixels"].float().std() > 1, env_id
        assert set(nxt["cost_info"].keys()) == set(env.constraint_names), env_id
        assert env.max_episode_steps == registry_entry(env_id).max_episode_steps
        env.close()


def test_rgbd_and_vector_entries(backend):
    env = make_env(VISION_ID, num_envs=2, obs_mode="vector+rgbd", image_size=24)
    near, far = env.vision.near, env.vision.far
    depth_spec = env.observation_spec["depth"]
    assert depth_spec.shape == (2, 24, 24, 1) and depth_spec.dtype == torch.float32
    assert depth_spec.space.low.min().item() == pytest.approx(near) and depth_spec.space.high.max().item() == pytest.approx(far)
    assert 0 < near < 0.05 and far > 20  # metres: the model's clipping planes
    assert env.observation_spec["observation"].shape == (2, 60) and env.observation_dim == 60
    for td in run(env, random_actions(env, 2, seed=1)):
        assert td["pixels"].shape == (2, 24, 24, 3) and td["observation"].shape == (2, 60)
        depth = td["depth"]
        assert depth.shape == (2, 24, 24, 1) and depth.dtype == torch.float32
        assert ((depth >= near) & (depth <= far)).all()
        assert (depth < far).float().mean() > 0.5  # the floor fills the lower part of the picture
        assert env.observation_spec.is_in(td.select(*env.observation_spec.keys()))
    env.close()


def test_check_env_specs(backend):
    env = make_env(VISION_ID, num_envs=2, image_size=16)
    check_env_specs(env, seed=0)
    env.close()
    rgbd = make_env(VISION_ID, num_envs=2, obs_mode="vector+rgbd", image_size=16)
    check_env_specs(rgbd, seed=0)
    rgbd.close()


def test_torchrl_image_transforms(backend):
    # Stock ToTensorImage, no options: channels-last uint8 in, channels-first floats in [0, 1] out.
    base = make_env(VISION_ID, num_envs=2, image_size=16)
    env = TransformedEnv(base, ToTensorImage(in_keys=["pixels"]))
    check_env_specs(env, seed=0)
    spec = env.observation_spec["pixels"]
    assert spec.shape == (2, 3, 16, 16) and spec.dtype == torch.float32
    assert spec.space.low.min() == 0 and spec.space.high.max() == 1
    rollout = env.rollout(3)
    pixels = rollout["next", "pixels"]
    assert pixels.shape == (2, 3, 3, 16, 16) and pixels.dtype == torch.float32
    assert 0 <= pixels.min() and pixels.max() <= 1 and pixels.std() > 0.01
    raw = base.vision.observation()["pixels"]  # the last frames, channels last
    torch.testing.assert_close(pixels[:, -1], raw.permute(0, 3, 1, 2).float() / 255)
    env.close()


def test_torchrl_image_transforms_with_depth(backend):
    # Depth is channels last too: the same transform turns it channels first and keeps its metres.
    base = make_env(VISION_ID, num_envs=2, obs_mode="rgbd", image_size=16)
    env = TransformedEnv(base, ToTensorImage(in_keys=["pixels", "depth"]))
    check_env_specs(env, seed=0)
    assert env.observation_spec["depth"].shape == (2, 1, 16, 16)
    nxt = env.rollout(2)["next"]
    assert nxt["pixels"].shape == (2, 2, 3, 16, 16) and nxt["depth"].shape == (2, 2, 1, 16, 16)
    torch.testing.assert_close(nxt["depth"][:, -1], base.vision.observation()["depth"].permute(0, 3, 1, 2))
    env.close()


# ---------------------------------------------------------------------------- the camera sees the geometry
def optical_axis(env) -> tuple[np.ndarray, np.ndarray]:
    """Position and viewing direction (unit) of simulator 0's vision camera in the world."""
    data, camera = env.physics.datas[0], env.vision.camera.fixedcamid
    return data.cam_xpos[camera].copy(), -data.cam_xmat[camera].reshape(3, 3)[:, 2]


def test_depth_matches_the_geometry(backend):
    env = make_env(VISION_ID, obs_mode="rgbd", image_size=65)  # odd: the centre pixel is on the optical axis
    centre = (0, 32, 32)

    # Nothing ahead but the floor: the axis meets the plane z = 0 at t = height / -dz.
    arrange(env, agent=(0.0, 0.0))
    position, direction = optical_axis(env)
    assert direction[2] < -0.1 and abs(direction[1]) < 1e-9 and direction[0] > 0  # ahead along +x, tilted down
    floor = position[2] / -direction[2]
    assert env.vision.depth[centre] == pytest.approx(floor, abs=0.005)

    # A vase (a box, faces along the axes) whose near face the axis meets halfway up: closer than the floor.
    vases = next(obj for obj in env.task.objects if obj.name == "vases")
    half, vase_z = vases.size, vases.height  # half-size of the box, height of its centre at rest
    distance = (position[2] - vase_z) / -direction[2]  # along the axis, down to the vase's mid-height
    face_x = position[0] + distance * direction[0]
    arrange(env, agent=(0.0, 0.0), vases=[(face_x + half, 0.0)])
    assert env.vision.depth[centre] == pytest.approx(distance, abs=0.01)
    assert distance < floor - 0.1

    # The emitted entry after a still step shows the same (the robot and the vase settle by millimetres).
    nxt = idle(env)
    assert nxt["depth"][0, 32, 32, 0].item() == pytest.approx(distance, abs=0.02)
    env.close()


def test_images_are_the_vision_camera_and_change_when_the_robot_moves(backend):
    env = make_env(VISION_ID, num_envs=1, image_size=48)
    before = env.reset()["pixels"][0]
    # Exactly what render() draws from the robot's own "vision" camera (same renderer settings).
    drawn = env.render(0, width=48, height=48, camera="vision")
    assert torch.equal(before, torch.from_numpy(drawn))  # both channels last
    for _ in range(8):  # drive forward and turn
        nxt = env.step(action_td(env, [[1.0, 1.0]]))["next"]
    after = nxt["pixels"][0]
    assert (after.float() - before.float()).abs().mean() > 3
    turned = env.layout[0].copy()
    env.set_layout([0], turned[None], np.array([[np.pi] + [0.0] * (len(turned) - 1)]))
    facing_back = env.vision.observation()["pixels"][0]  # set_layout redraws the simulator
    assert not torch.equal(facing_back, after)
    env.close()


# ---------------------------------------------------------------------------- seeding, physics, resets
def test_same_seed_same_images(backend):
    first, second, other = (make_env(VISION_ID, num_envs=2, seed=seed, image_size=32) for seed in (3, 3, 4))
    actions = random_actions(first, 4, seed=5)
    a, b, c = run(first, actions), run(second, actions), run(other, actions)
    for x, y in zip(a, b):
        assert torch.equal(x["pixels"], y["pixels"])
    assert not torch.equal(a[0]["pixels"], c[0]["pixels"])
    for env in (first, second, other):
        env.close()


def test_rendering_does_not_change_the_trajectory(backend):
    plain = make_env("SafetyPointGoal1-v0", num_envs=2, seed=7)
    seen = make_env(VISION_ID, num_envs=2, seed=7, obs_mode="vector+rgbd", image_size=16)
    actions = random_actions(plain, 12, seed=8)
    for x, y in zip(run(plain, actions), run(seen, actions)):
        for key in ("observation", "cost"):
            assert torch.equal(x[key], y[key]), key
        if "reward" in x.keys():
            assert torch.equal(x["reward"], y["reward"])
    seen.close()


def test_partial_reset_draws_only_the_reset_simulators(backend, monkeypatch):
    env = make_env(VISION_ID, num_envs=3, image_size=32)
    env.reset()
    for action in random_actions(env, 3, seed=2):
        td = env.step(action_td(env, action))["next"]
    before = td["pixels"].clone()
    layouts = env.layout.copy()
    drawn = []
    original = env.vision.render
    monkeypatch.setattr(env.vision, "render", lambda indices: (drawn.append(list(indices)), original(indices)))
    td.set("_reset", torch.tensor([[False], [True], [False]]))
    out = env.reset(td)
    assert drawn == [[1]]  # only the reset simulator was drawn
    assert torch.equal(out["pixels"][0], before[0]) and torch.equal(out["pixels"][2], before[2])
    assert not np.array_equal(env.layout[1], layouts[1])  # a new layout ...
    assert not torch.equal(out["pixels"][1], before[1])  # ... and its first frame
    fresh = torch.from_numpy(env.render(1, width=32, height=32, camera="vision"))
    assert torch.equal(out["pixels"][1], fresh)
    env.close()


def test_auto_resets_in_a_rollout_start_from_the_new_layout(backend):
    # Episodes of 3 steps: TorchRL's step_and_maybe_reset resets the finished simulators between steps.
    env = make_env(VISION_ID, num_envs=2, image_size=16, max_episode_steps=3)
    rollout = env.rollout(7, break_when_any_done=False)
    done = rollout["next", "done"][..., 0]
    assert done[:, 2].all() and done[:, 5].all()
    for t in range(6):
        for i in range(2):
            carried = torch.equal(rollout["pixels"][i, t + 1], rollout["next", "pixels"][i, t])
            assert carried != bool(done[i, t]), (i, t)  # a new episode shows its new layout
    env.close()


def test_snapshots_restore_the_frames(backend):
    env = make_env(VISION_ID, num_envs=2, image_size=16)
    frames = env.reset()["pixels"]
    state = env.sim_state()
    for action in random_actions(env, 3, seed=4):
        moved = env.step(action_td(env, action))["next", "pixels"]
    assert not torch.equal(moved, frames)
    env.load_sim_state(state)
    assert torch.equal(env.vision.observation()["pixels"], frames)
    env.close()


# ---------------------------------------------------------------------------- renderer lifetime, copies
def test_close_frees_the_renderer(backend):
    env = make_env(VISION_ID, image_size=16)
    env.reset()
    renderer = env.vision.renderer
    assert renderer is not None and renderer in rendering._live_renderers
    env.close()
    assert renderer.closed and renderer not in rendering._live_renderers and env.vision.renderer is None
    with pytest.raises(RuntimeError, match="closed"):
        env.vision.render([0])


def test_copies_render_with_their_own_renderer(backend):
    env = make_env(VISION_ID, image_size=16)
    frame = env.reset()["pixels"]
    clone = copy.deepcopy(env)
    # A copy is the env rebuilt and its simulators loaded (SafeEnv.__reduce_ex__): its own renderer, never env's.
    assert clone.vision.renderer is not env.vision.renderer
    assert clone.vision.camera.fixedcamid == env.vision.camera.fixedcamid
    clone.vision.render([0])
    assert torch.equal(clone.vision.observation()["pixels"], frame)
    assert clone.vision.renderer is not env.vision.renderer
    clone.close()
    env.close()


# ---------------------------------------------------------------------------- gymnasium façade
def test_facade_dict_observation(backend):
    # With the vector and the image, the façade's dict is Safety-Gymnasium's: one entry per vector part
    # (in observation order), then "vision", then (RGB-D) "depth".
    env = sg_gym.make(VISION_ID, obs_mode="vector+rgbd", image_size=16)
    space = env.observation_space
    parts = env.torchrl_env.observation_slices
    assert isinstance(space, gymnasium.spaces.Dict)
    assert list(space.spaces) == [*parts, "vision", "depth"]
    assert space["vision"].shape == (16, 16, 3) and space["vision"].dtype == np.uint8
    obs, info = env.reset(seed=0)
    assert obs in space and obs["depth"].shape == (16, 16, 1)
    td = env.torchrl_env.vision.observation()
    np.testing.assert_array_equal(obs["vision"], td["pixels"][0].numpy())  # both channels last
    np.testing.assert_array_equal(obs["depth"], td["depth"][0].numpy())
    flat = np.concatenate([obs[name].reshape(-1) for name in parts])
    assert flat.dtype == np.float64 and flat.shape == (sum(p.stop - p.start for p in parts.values()),)
    pixels_only = sg_gym.make(VISION_ID, obs_mode="rgb", image_size=16)
    assert list(pixels_only.observation_space.spaces) == ["vision"]
    pixels_only.close()
    obs, reward, cost, terminated, truncated, info = env.step(env.action_space.sample())
    assert obs in space and type(cost) is float
    env.close()
    twin = gymnasium.make(sg_gym.gymnasium_twin_id(VISION_ID), image_size=16)
    # The id's default holds the vector too: the original's keys (tests/test_vision_fidelity.py compares them).
    assert list(twin.observation_space.spaces)[-1] == "vision" and "accelerometer" in twin.observation_space.spaces
    assert twin.observation_space["vision"].shape == (16, 16, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(twin.unwrapped, skip_render_check=True)
    twin.close()
