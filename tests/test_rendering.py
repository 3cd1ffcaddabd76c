"""Headless rendering (``sg_torchrl.envs.rendering``): frames, follow cameras, videos, clean exit, façade.

Every test that draws needs an OpenGL backend (EGL or OSMesa through Mesa, no GPU needed): without
one it skips with the reason :func:`gl_backend` gives (``make install`` installs the libraries on
Debian when it runs as root). The backend-selection errors are tested without OpenGL.
"""

from __future__ import annotations

import copy
import os
import pickle
import subprocess
import sys
import textwrap
import warnings

import gymnasium
import imageio.v2 as imageio
import mujoco
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from tensordict import TensorDict

import sg_torchrl
import sg_torchrl.gym as sg_gym
from sg_torchrl.envs import opengl, rendering
from sg_torchrl.envs.rendering import CHASE_CAMERA, FollowCamera, RenderingUnavailable, record_video

torch.set_num_threads(1)

NAVIGATION_ID = "SafetyPointGoal1-v0"
VELOCITY_ID = "SafetyHalfCheetahVelocity-v1"


def robot_pixels(frame: np.ndarray) -> np.ndarray:
    """``(k, 2)`` row/column of the pixels showing the Point robot's red body."""
    r, g, b = (frame[..., c].astype(int) for c in range(3))
    return np.argwhere((r > 90) & (g < 60) & (b < 90) & (r > 2 * b))


def act(env, action) -> None:
    action = torch.as_tensor(np.asarray(action, dtype=np.float32)).expand(env.action_spec.shape)
    env.step(TensorDict({"action": action}, batch_size=env.batch_size))


# ---------------------------------------------------------------------------- frames
@pytest.mark.parametrize("env_id", [NAVIGATION_ID, VELOCITY_ID])
def test_frame_shape_dtype_and_content(backend, env_id):
    env = sg_torchrl.make(env_id, num_envs=2, seed=0)
    env.reset()
    frame = env.render(1, width=96, height=64)
    assert frame.shape == (64, 96, 3) and frame.dtype == np.uint8
    assert frame.flags.c_contiguous
    assert frame.std() > 10 and len(np.unique(frame.reshape(-1, 3), axis=0)) > 20  # a picture, not a blank
    square = env.render()  # defaults: simulator 0, 256 x 256
    assert square.shape == (rendering.DEFAULT_HEIGHT, rendering.DEFAULT_WIDTH, 3)
    if env_id == NAVIGATION_ID:  # two simulators, two layouts, two pictures
        assert not np.array_equal(env.render(0, 96, 64), frame)
    assert np.array_equal(env.render(1, 96, 64), frame)  # rendering only reads the state
    env.close()


def test_large_frame_and_model_cameras(backend):
    env = sg_torchrl.make(NAVIGATION_ID, seed=0)
    env.reset()
    model = env.physics.model
    saved = (model.vis.global_.offwidth, model.vis.global_.offheight, model.vis.quality.offsamples)
    assert env.render(width=800, height=600).shape == (600, 800, 3)  # beyond MuJoCo's 640 x 480 default
    assert env.render(width=64, height=64).shape == (64, 64, 3)  # smaller again: same renderer
    # The shared model keeps its own settings; anti-aliased frames on request.
    assert (model.vis.global_.offwidth, model.vis.global_.offheight, model.vis.quality.offsamples) == saved
    env.render_fast = False
    env.close_renderer()
    smooth = env.render(width=64, height=64)
    assert smooth.shape == (64, 64, 3) and not env._renderer.fast
    env.render_fast = True
    vision = env.render(camera="vision", width=64, height=64)  # the robot's egocentric camera
    assert vision.std() > 5
    camera_id = mujoco.mj_name2id(env.physics.model, mujoco.mjtObj.mjOBJ_CAMERA, "vision")
    assert np.array_equal(env.render(camera=camera_id, width=64, height=64), vision)
    assert env.render(camera="world", width=64, height=64).std() > 5
    with pytest.raises(ValueError, match="unknown camera"):
        env.render(camera="nope")
    with pytest.raises(IndexError):
        env.render(index=1)
    env.close()


# ---------------------------------------------------------------------------- the camera follows the robot
def test_follow_camera_keeps_the_robot_in_the_middle(backend):
    env = sg_torchrl.make(NAVIGATION_ID, seed=3)
    env.reset()
    layout = env.layout[0].copy()
    frames, fixed = [], []
    for xy in ([-1.0, -1.0], [1.2, 0.8]):  # two far-apart robot positions, objects unchanged
        layout[0] = xy
        env.set_layout([0], layout[None])
        camera = env.render_camera(0)
        np.testing.assert_allclose(camera.lookat, env.scene.agent_pos()[0])  # looks at the robot
        frames.append(env.render(width=128, height=128))
        fixed.append(env.render(width=128, height=128, camera="world"))
    assert not np.array_equal(frames[0], frames[1])  # the world moved under the camera
    for frame in frames:  # ... but the robot stays in the middle of the picture
        pixels = robot_pixels(frame)
        assert len(pixels) > 20
        np.testing.assert_allclose(pixels.mean(axis=0), [64, 64], atol=8)
    # A fixed camera sees the robot move across the picture instead.
    centres = [robot_pixels(frame).mean(axis=0) for frame in fixed if len(robot_pixels(frame))]
    assert len(centres) < 2 or np.abs(centres[0] - centres[1]).max() > 10
    env.close()


def test_chase_camera_turns_with_the_robot(backend):
    env = sg_torchrl.make(NAVIGATION_ID, seed=0)
    env.reset()
    layout = env.layout[0]
    azimuths = []
    for yaw in (0.0, np.pi / 2):
        yaws = np.zeros(layout.shape[0])
        yaws[0] = yaw
        env.set_layout([0], layout[None], yaws[None])
        azimuths.append(env.render_camera(0, "chase").azimuth)
    assert azimuths[1] - azimuths[0] == pytest.approx(90.0)
    assert env.render_camera(0, FollowCamera(distance=7.0)).distance == 7.0
    assert CHASE_CAMERA.heading
    env.close()


def test_camera_tracks_the_torso_of_a_running_robot(backend):
    env = sg_torchrl.make(VELOCITY_ID, seed=0)
    env.reset()
    torso = env.physics.model.body("torso").id
    before = env.render(width=96, height=96)
    start = env.render_camera(0).lookat.copy()
    generator = np.random.default_rng(0)
    for _ in range(40):
        act(env, generator.uniform(-1, 1, size=env.action_dim))
    camera = env.render_camera(0)
    np.testing.assert_allclose(camera.lookat, env.physics.datas[0].xpos[torso])
    assert np.abs(camera.lookat - start).max() > 0.05  # the robot moved, the camera with it
    assert not np.array_equal(env.render(width=96, height=96), before)
    env.close()


# ---------------------------------------------------------------------------- videos
def test_record_video_mp4_and_gif(backend, tmp_path):
    env = sg_torchrl.make(NAVIGATION_ID, num_envs=2, seed=0)
    path = record_video(env, None, tmp_path / "episode.mp4", steps=12, index=1, width=64, height=64)
    assert path == tmp_path / "episode.mp4" and path.stat().st_size > 0
    frames = imageio.mimread(path)
    assert len(frames) == 13 and frames[0].shape == (64, 64, 3)  # the reset state, then one per step

    # A policy, and an episode that ends before `steps`: the video stops with it.
    short = sg_torchrl.make(VELOCITY_ID, seed=0, max_episode_steps=5)

    def still(td):
        return td.set("action", torch.zeros(short.action_spec.shape))

    gif = record_video(short, still, tmp_path / "short.gif", steps=50, fps=10, width=48, height=32)
    frames = imageio.mimread(gif)
    assert len(frames) == 6 and frames[0].shape[:2] == (32, 48)
    short.close()
    env.close()


def test_record_video_falls_back_to_gif_without_ffmpeg(backend, tmp_path, monkeypatch):
    monkeypatch.setattr(rendering, "_ffmpeg_available", lambda: False)
    env = sg_gym.make(NAVIGATION_ID, seed=0)  # a façade env works too
    with pytest.warns(UserWarning, match="imageio-ffmpeg"):
        path = record_video(env, None, tmp_path / "clip.mp4", steps=3, width=32, height=32)
    assert path == tmp_path / "clip.gif" and len(imageio.mimread(path)) == 4
    env.close()


# ---------------------------------------------------------------------------- closing
def test_close_frees_the_renderer(backend):
    env = sg_torchrl.make(VELOCITY_ID, seed=0)
    env.reset()
    env.render(width=32, height=32)
    renderer = env._renderer
    assert renderer is not None and renderer in rendering._live_renderers
    env.close()
    assert renderer.closed and renderer not in rendering._live_renderers
    with pytest.raises(RuntimeError, match="close"):
        env.render()
    renderer.close()  # twice is fine


def test_copies_and_pickles_get_their_own_renderer(backend):
    env = sg_torchrl.make(NAVIGATION_ID, seed=0)
    env.reset()
    frame = env.render(width=48, height=48)
    for clone in (copy.deepcopy(env), pickle.loads(pickle.dumps(env))):
        assert clone._renderer is None  # GL contexts are not copied
        assert np.array_equal(clone.render(width=48, height=48), frame)
        assert clone._renderer is not env._renderer
        clone.close()
    assert np.array_equal(env.render(width=48, height=48), frame)
    env.close()


@pytest.mark.parametrize("gl", ["egl", "osmesa"])
def test_process_exits_cleanly_with_open_and_closed_renderers(gl):
    # OSMesa is the strict one: a context still alive at interpreter shutdown raises there.
    reason = opengl._probe(gl)
    if reason is not None:
        pytest.skip(f"{gl} cannot render here: {reason}")
    script = textwrap.dedent(
        """
        import sg_torchrl
        from sg_torchrl.envs.rendering import gl_backend
        closed = sg_torchrl.make("SafetyHalfCheetahVelocity-v1", seed=0)
        closed.reset()
        closed.render(width=32, height=32)
        closed.close()
        left_open = sg_torchrl.make("SafetyPointGoal1-v0", num_envs=2, seed=0)
        left_open.reset()
        left_open.render(1, width=32, height=32)  # never closed: freed by the exit hook
        print("rendered with", gl_backend())
        """
    )
    env = {**os.environ, "MUJOCO_GL": gl}
    result = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert f"rendered with {gl}" in result.stdout
    for marker in ("Traceback", "Exception ignored", "Error"):
        assert marker not in result.stderr, result.stderr


# ---------------------------------------------------------------------------- gymnasium façade
def test_facade_render_mode_rgb_array(backend):
    env = sg_gym.make(NAVIGATION_ID, render_mode="rgb_array", width=80, height=60, seed=0)
    assert env.render_mode == "rgb_array" and env.metadata["render_fps"] == 50
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (60, 80, 3) and frame.dtype == np.uint8 and frame.std() > 10
    env.step(env.action_space.sample())
    assert env.render().shape == (60, 80, 3)
    env.close()
    with pytest.raises(gymnasium.error.ClosedEnvironmentError):
        env.render()

    egocentric = sg_gym.make(NAVIGATION_ID, render_mode="rgb_array", camera_name="vision", width=32, height=32)
    egocentric.reset(seed=0)
    assert egocentric.render().shape == (32, 32, 3)
    egocentric.close()

    twin = gymnasium.make(sg_gym.gymnasium_twin_id(VELOCITY_ID), render_mode="rgb_array")
    twin.reset(seed=0)
    assert twin.render().shape == (256, 256, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unbounded observation space: advice only
        check_env(twin.unwrapped)  # render checks included
    twin.close()

    plain = sg_gym.make(NAVIGATION_ID)
    plain.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert plain.render() is None  # no render mode: gymnasium's convention
    plain.close()


# ---------------------------------------------------------------------------- backend selection (no GL needed)
@pytest.fixture
def fresh_selection(monkeypatch):
    monkeypatch.setattr(opengl, "_backend", None)
    monkeypatch.setattr(opengl, "_backend_error", None)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    return monkeypatch


def test_missing_libraries_name_the_packages(fresh_selection):
    fresh_selection.setattr(opengl.ctypes.util, "find_library", lambda name: None)
    with pytest.raises(RenderingUnavailable) as caught:
        opengl.gl_backend()
    message = str(caught.value)
    for fact in ("libEGL", "libOSMesa", "libegl1", "libosmesa6", "MUJOCO_GL"):
        assert fact in message
    with pytest.raises(RenderingUnavailable):  # remembered: no second probe
        opengl.gl_backend()


def test_backend_choice_order_and_overrides(fresh_selection):
    tried = []

    def probe(candidate):
        tried.append(candidate)
        return "no display" if candidate == "egl" else None

    fresh_selection.setattr(opengl, "_probe", probe)
    assert opengl.gl_backend() == "osmesa" and tried == ["egl", "osmesa"]  # EGL first, then OSMesa
    fresh_selection.setattr(opengl, "_backend", None)
    fresh_selection.setenv("MUJOCO_GL", "EGL")
    assert opengl.gl_backend() == "egl"  # MUJOCO_GL is honoured without probing
    fresh_selection.setattr(opengl, "_backend", None)
    fresh_selection.setenv("MUJOCO_GL", "disable")
    with pytest.raises(RenderingUnavailable, match="disabled"):
        opengl.gl_backend()
