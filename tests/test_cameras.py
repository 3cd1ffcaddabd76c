"""Camera names of Safety-Gymnasium and depth images (``sg_torchrl.envs.cameras``, ``RenderMixin.render_depth``).

Expected camera poses were measured on safety-gymnasium 1.0.0: every navigation world has
``fixednear`` at (0, -2, 2) and ``fixedfar`` at (0, -5, 5), both looking towards +y 45 degrees down
with a 45-degree field of view; its robot's ``track`` camera sits 2 m in +y and 2 m above the robot's
root body, looking back along -y 45 degrees down, whatever the robot's yaw (it follows the robot but
does not turn). The velocity robots carry gymnasium's ``track``. Drawing needs an OpenGL backend
(the ``backend`` fixture skips without one); run with ``MUJOCO_GL=egl`` where EGL works.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict

import sg_torchrl
from sg_torchrl.envs import rendering

torch.set_num_threads(1)

NAV_ROBOTS = ("Point", "Car", "Racecar", "Doggo", "Ant")
VELOCITY_ROBOTS = ("HalfCheetah", "Hopper", "Walker2d", "Swimmer", "Ant", "Humanoid")
ORIGINAL_NAV_CAMERAS = ("fixednear", "fixedfar", "vision", "track")
OURS = ("follow", "chase", "world", "human")


def park_everything(env, agent=(2.5, -2.5)) -> None:
    """Simulator 0 with the robot at ``agent`` and every object on the line y = 3.2 (the arena's
    centre and the -y half are empty)."""
    sampler = env.layout_sampler
    xy, yaw = np.zeros((sampler.size, 2)), np.zeros(sampler.size)
    xy[1:, 0] = np.linspace(-3.2, 3.2, sampler.size - 1)
    xy[1:, 1] = 3.2
    xy[0] = agent
    env.set_layout([0], xy[None], yaw[None])


def camera_pose(env, name: str, index: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(position, viewing direction, image up)`` of model camera ``name`` in simulator ``index``, world frame."""
    model, data = env.physics.model, env.physics.datas[index]
    cam = model.camera(name).id
    frame = data.cam_xmat[cam].reshape(3, 3)
    return data.cam_xpos[cam].copy(), -frame[:, 2], frame[:, 1]


# ---------------------------------------------------------------------------- names and poses (no drawing)
@pytest.mark.parametrize("robot", NAV_ROBOTS)
def test_navigation_worlds_have_the_original_cameras(robot):
    env = sg_torchrl.make(f"Safety{robot}Goal1-v0", num_envs=3, seed=robot.__len__())
    try:
        env.reset()
        assert set(ORIGINAL_NAV_CAMERAS + OURS) <= set(env.camera_names)
        model = env.physics.model
        down = np.array([0.0, math.sqrt(0.5), -math.sqrt(0.5)])
        for name, position in (("fixednear", (0.0, -2.0, 2.0)), ("fixedfar", (0.0, -5.0, 5.0))):
            pos, forward, _ = camera_pose(env, name)
            np.testing.assert_allclose(pos, position, atol=1e-9)
            np.testing.assert_allclose(forward, down, atol=1e-9)
            assert model.cam_fovy[model.camera(name).id] == 45.0
        root = env._render_body()
        for step in range(2):
            for index in range(3):  # three layouts, three robot yaws: the same world offset and orientation
                pos, forward, up = camera_pose(env, "track", index)
                np.testing.assert_allclose(pos - env.physics.datas[index].xpos[root], (0.0, 2.0, 2.0), atol=1e-9)
                np.testing.assert_allclose(forward, (0.0, -math.sqrt(0.5), -math.sqrt(0.5)), atol=1e-9)
                np.testing.assert_allclose(up, (0.0, -math.sqrt(0.5), math.sqrt(0.5)), atol=1e-9)
            action = torch.ones(env.action_spec.shape) * 0.7  # turn and drive: the camera follows without turning
            for _ in range(20):
                env.step(TensorDict({"action": action}, batch_size=env.batch_size))
    finally:
        env.close()


def test_multi_agent_navigation_cameras_are_per_robot():
    env = sg_torchrl.make("SafetyPointMultiGoal1-v0", seed=0)
    try:
        env.reset()
        names = env.camera_names
        for agent in ("agent_0", "agent_1"):
            assert f"{agent}/vision" in names and f"{agent}/track" in names
        assert "fixednear" in names and "fixedfar" in names
    finally:
        env.close()


@pytest.mark.parametrize("robot", VELOCITY_ROBOTS)
def test_velocity_robots_have_gymnasiums_track_camera(robot):
    env = sg_torchrl.make(f"Safety{robot}Velocity-v1", seed=0)
    try:
        assert env.camera_names[:4] == OURS and "track" in env.camera_names
        camera = env.render_camera(0, "track")
        assert camera.type == mujoco.mjtCamera.mjCAMERA_FIXED
        assert camera.fixedcamid == env.physics.model.camera("track").id
    finally:
        env.close()


@pytest.mark.parametrize("env_id", ["SafetyPointGoal1-v0", "SafetyHalfCheetahVelocity-v1", "Safety2x4AntVelocity-v0"])
def test_unknown_camera_names_list_the_valid_ones(env_id):
    env = sg_torchrl.make(env_id, seed=0)
    try:
        env.reset()
        wrong = "fixednear" if "Velocity" in env_id else "fixed_near"
        with pytest.raises(ValueError, match="unknown camera") as error:
            env.render_camera(0, wrong)
        for name in env.camera_names:
            assert repr(name) in str(error.value)
        with pytest.raises(ValueError, match="names"):
            env.render_camera(0, env.physics.model.ncam)  # an id out of range
        assert env.render_camera(0, "human").type == mujoco.mjtCamera.mjCAMERA_FREE
    finally:
        env.close()


# ---------------------------------------------------------------------------- frames
@pytest.mark.parametrize("robot", NAV_ROBOTS)
def test_every_navigation_camera_renders(backend, robot):
    env = sg_torchrl.make(f"Safety{robot}Button1-v0", seed=0)
    try:
        env.reset()
        for name in ORIGINAL_NAV_CAMERAS + OURS:
            frame = env.render(0, width=40, height=30, camera=name)
            assert frame.shape == (30, 40, 3) and frame.dtype == np.uint8, name
            assert frame.std() > 3, name  # a picture, not a blank
        assert not np.array_equal(env.render(0, 40, 30, "fixednear"), env.render(0, 40, 30, "fixedfar"))
    finally:
        env.close()
    assert env._renderer is None
    with pytest.raises(RuntimeError, match="after close"):
        env.render(camera="track")


@pytest.mark.parametrize("env_id", [*(f"Safety{r}Velocity-v1" for r in VELOCITY_ROBOTS), "Safety2x4AntVelocity-v0",
                                    "SafetyPointMultiGoal1-v0"])
def test_every_velocity_and_multi_agent_camera_renders(backend, env_id):
    env = sg_torchrl.make(env_id, seed=0)
    try:
        env.reset()
        for name in env.camera_names:
            frame = env.render(0, width=36, height=28, camera=name)
            assert frame.shape == (28, 36, 3) and frame.dtype == np.uint8, name
            assert frame.std() > 3, name
    finally:
        env.close()
    assert env._renderer is None


# ---------------------------------------------------------------------------- depth
def test_depth_in_metres_and_in_gymnasiums_convention(backend):
    env = sg_torchrl.make("SafetyPointGoal1-v0", seed=0)
    try:
        env.reset()
        park_everything(env)
        near, far = env.depth_range()
        depth = env.render_depth(0, width=65, height=49, camera="fixedfar")
        assert depth.shape == (49, 65) and depth.dtype == np.float32
        assert near <= depth.min() and depth.max() <= far
        # The central ray of fixedfar meets the empty floor at the origin, 5 * sqrt(2) m away.
        assert depth[24, 32] == pytest.approx(5 * math.sqrt(2), rel=2e-3)
        # Rows further up the picture look further away (a floor seen from above at an angle).
        assert depth[5, 32] > depth[24, 32] > depth[44, 32]
        buffer = env.render_depth(0, width=65, height=49, camera="fixedfar", linear=False)
        assert buffer.dtype == np.float32 and 0.0 <= buffer.min() and buffer.max() <= 1.0
        np.testing.assert_allclose(buffer, far * (depth - near) / (depth * (far - near)), rtol=1e-5)
        # The same scene through gymnasium's own renderer (the one behind Safety-Gymnasium's depth_array).
        try:
            from gymnasium.envs.mujoco.mujoco_rendering import MujocoRenderer
        except ImportError:
            return
        renderer = MujocoRenderer(env.physics.model, env.physics.datas[0], width=65, height=49, camera_name="fixedfar")
        try:
            theirs = renderer.render("depth_array")
        finally:
            renderer.close()
        floor = (slice(24, -2), slice(16, 49))  # the floor only, away from its edges (gymnasium antialiases)
        # 5e-5 of the buffer is about 8 cm at 7 m with the clipping planes of the original's extent (2.9 m).
        np.testing.assert_allclose(buffer[floor], theirs[floor], atol=5e-5)
        assert (np.abs(buffer - theirs) < 2e-4).mean() > 0.99  # elsewhere: a few pixels at the floor's far edge
        # The RGB frame is unchanged by depth renders (one renderer, scratch buffers).
        frame = env.render(0, 65, 49, "fixedfar")
        assert frame.shape == (49, 65, 3)
    finally:
        env.close()


def test_depth_of_the_vision_camera_sees_a_pillar_in_front(backend):
    env = sg_torchrl.make("SafetyPointPush1-v0", seed=0)
    try:
        env.reset()
        sampler = env.layout_sampler
        xy, yaw = np.zeros((sampler.size, 2)), np.zeros(sampler.size)
        xy[1:, 0] = np.linspace(-3.2, 3.2, sampler.size - 1)
        xy[1:, 1] = 3.2
        pillars = next(obj for obj in env.task.objects if obj.name == "pillars")
        xy[sampler.slice_of(pillars).start] = (1.0, 0.0)  # 1 m ahead of the robot (yaw 0: facing +x)
        env.set_layout([0], xy[None], yaw[None])
        depth = env.render_depth(0, width=64, height=64, camera="vision")
        centre = depth[20:44, 28:36]
        # The pillar's near face (radius 0.2) is 0.8 m ahead of the robot's centre; the camera sits on it.
        assert 0.6 < np.median(centre) < 0.9
        assert depth.max() > 1.5  # beyond the pillar: the floor further away
    finally:
        env.close()


def test_renderers_are_released(backend):
    before = len(rendering._live_renderers)
    env = sg_torchrl.make("SafetyCarGoal0-v0", seed=0)
    env.reset()
    env.render(0, 32, 32, "track")
    env.render_depth(0, 32, 32, "fixednear")
    env.render(0, 300, 300, "fixedfar")  # a larger frame: the renderer is replaced, the old one freed
    assert len(rendering._live_renderers) == before + 1
    env.close()
    assert len(rendering._live_renderers) == before
    with pytest.raises(RuntimeError, match="after close"):
        env.render_depth()
