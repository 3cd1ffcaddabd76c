"""Headless rendering of the MuJoCo envs: ``rgb_array`` frames and episode videos.

>>> env = sg_torchrl.make("SafetyPointGoal1-v0", num_envs=4, seed=0)
>>> td = env.reset()
>>> frame = env.render(index=2)               # (256, 256, 3) uint8, camera following robot 2
>>> record_video(env, policy, "episode.mp4")  # one episode of simulator 0

What renders
------------
:class:`RenderMixin` gives an env with a :class:`~sg_torchrl.envs.physics.MujocoBatch` ``physics``
(navigation, velocity and two-hand envs) :meth:`~RenderMixin.render` (RGB) and
:meth:`~RenderMixin.render_depth` of one simulator, from a camera of :mod:`sg_torchrl.envs.cameras`.
The env owns one :class:`Renderer`, created at the first frame and released by ``env.close()`` (or
at interpreter exit, whichever comes first). Rendering only reads ``MjData``: it never changes a
trajectory.

The OpenGL backend is chosen once per process (:func:`~sg_torchrl.envs.opengl.gl_backend`); frame
quality is :class:`Renderer`'s ``fast`` / ``effects``. Frames of any size work (the renderer's
offscreen buffer is sized for them; the shared model is left as is).

Videos
------
:func:`record_video` runs an episode (a policy, or random actions) and writes one frame per step:
MP4 through ``imageio-ffmpeg`` when it is installed (a dependency of sg_torchrl), else an animated
GIF next to the requested path.

Per-simulator transparency
--------------------------
All simulators of an env share one ``MjModel``, so a colour that differs between simulators (the
Fading tasks' goal, fading step by step in each simulator's own episode) cannot live in the model.
:meth:`RenderMixin.geom_alpha` returns, for simulator ``index``, the geoms whose alpha differs from
the model's and their alphas (a :data:`GeomAlpha`); :meth:`Renderer.render_into` writes them into
``model.geom_rgba`` only for the duration of ``mjv_updateScene`` (the one call that reads model
colours: it copies them into the scene) and restores the model's values right after, even on error.
MuJoCo itself then handles the rest as for any model colour: geoms below alpha 1 are drawn as
transparent, geoms at alpha 0 are left out of the scene (no colour, no depth). Nothing outlives the
call, so frames of one simulator never carry another's alphas, and envs sharing the model (or
building their own renderer) see the model's colours. (This assumes that envs sharing a model do not
render from several threads at once, as nothing in sg_torchrl does: each process compiles its own
models.)
"""

from __future__ import annotations

import atexit
import importlib.util
import os
import sys
import warnings
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import mujoco
import numpy as np
import torch

from sg_torchrl.envs.cameras import (
    CHASE_CAMERA,
    LOCOMOTION_CAMERA,
    NAVIGATION_CAMERA,
    FollowCamera,
    camera_names,
    resolve_camera,
)
from sg_torchrl.envs.opengl import INSTALL_HINT, RenderingUnavailable, context_class, gl_backend

__all__ = [
    "CHASE_CAMERA",
    "DEFAULT_HEIGHT",
    "DEFAULT_WIDTH",
    "FollowCamera",
    "GeomAlpha",
    "LOCOMOTION_CAMERA",
    "NAVIGATION_CAMERA",
    "RenderMixin",
    "Renderer",
    "RenderingUnavailable",
    "depth_range",
    "gl_backend",
    "record_video",
]

DEFAULT_WIDTH = 256
DEFAULT_HEIGHT = 256

#: Alphas one simulator draws some geoms with: ``(geom_ids (K,) int, alphas (K,) float)`` (see the module docstring)
GeomAlpha = tuple[np.ndarray, np.ndarray]


# ---------------------------------------------------------------------------- renderer
def depth_range(model: mujoco.MjModel) -> tuple[float, float]:
    """``(near, far)``: the clipping planes of ``model``'s cameras in metres, the range of depth values
    (``model.vis.map.znear`` and ``zfar`` times ``model.stat.extent``)."""
    extent = float(model.stat.extent)
    return float(model.vis.map.znear) * extent, float(model.vis.map.zfar) * extent


_live_renderers: weakref.WeakSet = weakref.WeakSet()
_exit_hook_registered = False


def _close_all_renderers() -> None:
    """At interpreter exit, free every renderer still open while its GL backend is still alive."""
    for renderer in list(_live_renderers):
        renderer.close()


class Renderer:
    """Offscreen renderer of one model: a GL context, MuJoCo's render context and a scene.

    Args:
        model: the compiled model (shared by the simulators it renders).
        width / height: the largest frame this renderer will produce (smaller ones are fine).
        max_geom: capacity of the scene in geoms.
        fast: no multisample anti-aliasing (about 3x faster on a software rasteriser), no shadows
            and, unless ``effects`` says otherwise, no reflections or skybox (stack notes: up to 8x).
        effects: draw reflections and the skybox (default: ``not fast``). The env renderers and the
            pixel observations use ``fast=True, effects=True``: Safety-Gymnasium's floor reflects and
            its sky has stars, and these cost about 10% at 256 x 256 here, where anti-aliasing and
            shadows cost most (:mod:`sg_torchrl.envs.vision`).

    Prefer :meth:`RenderMixin.render`; use this class directly to render ``MjData`` you manage.
    :meth:`close` frees the GL resources (also done at interpreter exit).
    """

    def __init__(self, model: mujoco.MjModel, width: int, height: int, *, max_geom: int = 10_000,
                 fast: bool = True, effects: bool | None = None) -> None:
        global _exit_hook_registered
        if width < 1 or height < 1:
            raise ValueError(f"frame size must be positive, got width={width}, height={height}")
        self.model = model
        self.fast = fast
        self.effects = (not fast) if effects is None else bool(effects)
        self._gl = None
        self._context = None
        backend = gl_backend()
        gl_context = context_class(backend)
        # The render context takes its offscreen buffer's size and multisampling from the model
        # when it is created; set them for this renderer only and restore the (shared) model after.
        buffer, quality = model.vis.global_, model.vis.quality
        saved = (buffer.offwidth, buffer.offheight, quality.offsamples)
        self.max_width, self.max_height = max(int(buffer.offwidth), width), max(int(buffer.offheight), height)
        try:
            buffer.offwidth, buffer.offheight = self.max_width, self.max_height
            if fast:
                quality.offsamples = 0
            self._gl = gl_context(self.max_width, self.max_height)
            self._gl.make_current()
            self._context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150.value)
            self._context.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR  # see render_into
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._context)
        except Exception as error:
            self.close()
            raise RenderingUnavailable(
                f"cannot create an OpenGL context with the {backend!r} backend: {error}. {INSTALL_HINT}"
            ) from error
        finally:
            buffer.offwidth, buffer.offheight, quality.offsamples = saved
        self._scene = mujoco.MjvScene(model, maxgeom=max_geom)
        self._option = mujoco.MjvOption()
        self._buffers: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        _live_renderers.add(self)
        if not _exit_hook_registered:
            # Registered after the first GL context exists, so that it runs before the backend's own
            # exit hook (EGL terminates its display at exit; atexit runs hooks last-in first-out).
            atexit.register(_close_all_renderers)
            _exit_hook_registered = True

    @property
    def closed(self) -> bool:
        return self._context is None

    def fits(self, width: int, height: int) -> bool:
        """Whether this (open) renderer can produce a ``width`` x ``height`` frame."""
        return not self.closed and width <= self.max_width and height <= self.max_height

    def render(self, data: mujoco.MjData, camera: mujoco.MjvCamera, width: int, height: int, *,
               geom_alpha: GeomAlpha | None = None) -> np.ndarray:
        """``data`` seen from ``camera`` as a new ``(height, width, 3)`` ``uint8`` array (``geom_alpha``:
        see :meth:`render_into`)."""
        pixels = np.empty((height, width, 3), dtype=np.uint8)
        self.render_into(data, camera, pixels, geom_alpha=geom_alpha)
        return pixels

    def render_into(self, data: mujoco.MjData, camera: mujoco.MjvCamera, rgb: np.ndarray,
                    depth: np.ndarray | None = None, *, geom_alpha: GeomAlpha | None = None) -> None:
        """Render ``data`` seen from ``camera`` into ``rgb`` and, if given, ``depth`` (rows top to bottom).

        Args:
            rgb: ``(height, width, 3)`` ``uint8`` array written in place (a view into a batch
                buffer is fine); its shape sets the frame size.
            depth: ``(height, width)`` ``float32`` array or ``None``: the depth of every pixel in
                metres, measured along the camera's optical axis (OpenGL's planar depth, not the
                length of the pixel's ray), in ``[near, far]`` (:meth:`depth_range`); pixels that
                see nothing read ``far``.

        No array is allocated per call beyond the first at a given size (OpenGL's rows run bottom
        to top: frames are read into reused scratch buffers, then flipped into the outputs).
        """
        if self.closed:
            raise RuntimeError("the renderer is closed")
        height, width = rgb.shape[:2]
        if rgb.shape != (height, width, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be a (height, width, 3) uint8 array, got {rgb.shape} {rgb.dtype}")
        if depth is not None and (depth.shape != (height, width) or depth.dtype != np.float32):
            raise ValueError(f"depth must be a ({height}, {width}) float32 array, got {depth.shape} {depth.dtype}")
        if not self.fits(width, height):
            raise ValueError(f"frame {width}x{height} exceeds this renderer's {self.max_width}x{self.max_height}")
        self._gl.make_current()
        self._update_scene(data, camera, geom_alpha)
        flags = self._scene.flags
        if self.fast:
            flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        if not self.effects:
            flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
            flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = 0
        viewport = mujoco.MjrRect(0, 0, width, height)
        mujoco.mjr_render(viewport, self._scene, self._context)
        raw_rgb, raw_depth = self._scratch(width, height)
        mujoco.mjr_readPixels(raw_rgb, raw_depth if depth is not None else None, viewport, self._context)
        np.copyto(rgb, raw_rgb[::-1])
        if depth is not None:
            # The render context reads the depth buffer as MuJoCo's "zero far" map (reversed Z, the
            # precise end of a float buffer): f = near (far - z) / (z (far - near)) for a point at
            # planar depth z, 0 at the far plane and 1 at the near plane. Inverted:
            # z = near far / (near + f (far - near)).
            near, far = self.depth_range()
            np.multiply(raw_depth[::-1], far - near, out=depth)
            depth += near
            np.divide(near * far, depth, out=depth)
            np.clip(depth, near, far, out=depth)  # float32 rounding at the planes

    def _update_scene(self, data: mujoco.MjData, camera: mujoco.MjvCamera, geom_alpha: GeomAlpha | None) -> None:
        """``mjv_updateScene`` with ``geom_alpha`` in the model's colours for that call only."""
        model = self.model
        if geom_alpha is None:
            mujoco.mjv_updateScene(model, data, self._option, None, camera, mujoco.mjtCatBit.mjCAT_ALL.value,
                                   self._scene)
            return
        ids, alphas = geom_alpha
        saved = model.geom_rgba[ids, 3].copy()
        try:
            model.geom_rgba[ids, 3] = alphas
            mujoco.mjv_updateScene(model, data, self._option, None, camera, mujoco.mjtCatBit.mjCAT_ALL.value,
                                   self._scene)
        finally:
            model.geom_rgba[ids, 3] = saved

    def depth_range(self) -> tuple[float, float]:
        """``(near, far)``: the clipping planes of the model's cameras in metres (:func:`depth_range`)."""
        return depth_range(self.model)

    def _scratch(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Reused ``(height, width, 3)`` uint8 and ``(height, width)`` float32 read-back buffers."""
        buffers = self._buffers.get((width, height))
        if buffers is None:
            buffers = self._buffers[width, height] = (np.empty((height, width, 3), dtype=np.uint8),
                                                      np.empty((height, width), dtype=np.float32))
        return buffers

    def close(self) -> None:
        """Free the GL resources; calling it again does nothing."""
        _live_renderers.discard(self)
        gl, context = self._gl, self._context
        self._gl = self._context = None
        try:
            if context is not None:
                if gl is not None:
                    gl.make_current()
                context.free()
        finally:
            if gl is not None:
                gl.free()

    def __del__(self) -> None:
        if sys.is_finalizing():  # the exit hook already closed it; the GL modules may be gone
            return
        try:
            self.close()
        except Exception:  # noqa: BLE001 - never raise from a finaliser
            pass


# ---------------------------------------------------------------------------- the env interface
class RenderMixin:
    """``render`` for an env holding a :class:`~sg_torchrl.envs.physics.MujocoBatch` as ``physics``.

    Put it before the env's base class (``class NavigationEnv(RenderMixin, SafeEnv)``); an env sets
    :attr:`default_camera` and overrides :meth:`_render_body` when its robot is not body 1. Its
    ``close`` also frees the renderer.
    """

    default_camera: ClassVar[FollowCamera] = FollowCamera()
    #: see :class:`Renderer` ``fast``; set it to ``False`` (then :meth:`close_renderer`) for anti-aliased frames
    render_fast: bool = True
    _renderer: Renderer | None = None
    _render_closed: bool = False

    def _render_body(self) -> int:
        """Id of the body the follow cameras track (default 1: the first body after the world)."""
        return 1

    def geom_alpha(self, index: int) -> GeomAlpha | None:
        """Geoms simulator ``index`` draws with other alphas than the model's, or ``None`` (the default:
        none). Envs whose objects fade per simulator override it (module docstring)."""
        return None

    @property
    def camera_names(self) -> tuple[str, ...]:
        """The camera names :meth:`render` accepts here (:func:`~sg_torchrl.envs.cameras.camera_names`):
        ``follow``, ``chase``, ``world``, ``human`` and the model's cameras (navigation: Safety-Gymnasium's
        ``fixednear``, ``fixedfar``, ``vision``, ``track``; velocity: ``track``)."""
        return camera_names(self.physics.model)

    def render_camera(self, index: int = 0, camera: Any = None) -> mujoco.MjvCamera:
        """The ``MjvCamera`` :meth:`render` uses for simulator ``index`` (``camera`` as in :meth:`render`;
        an unknown name raises ``ValueError`` listing :attr:`camera_names`)."""
        return resolve_camera(self.physics.model, self._render_data(index), camera, default=self.default_camera,
                              body=self._render_body())

    def render(self, index: int = 0, width: int = DEFAULT_WIDTH, height: int = DEFAULT_HEIGHT,
               camera: Any = None) -> np.ndarray:
        """Simulator ``index`` as an RGB image, ``(height, width, 3)`` ``uint8``.

        ``camera``: ``None``/``"follow"`` (the env's follow camera), ``"chase"``, ``"world"``/``"human"``,
        a model camera's name (:attr:`camera_names`) or id, a :class:`FollowCamera`, or an
        ``MjvCamera`` (:mod:`sg_torchrl.envs.cameras`). Raises :class:`RenderingUnavailable` when no
        OpenGL backend works here.
        """
        data, mjv_camera, renderer = self._render_setup(index, width, height, camera)
        return renderer.render(data, mjv_camera, width, height, geom_alpha=self.geom_alpha(index))

    def render_depth(self, index: int = 0, width: int = DEFAULT_WIDTH, height: int = DEFAULT_HEIGHT,
                     camera: Any = None, *, linear: bool = True) -> np.ndarray:
        """Simulator ``index``'s depth image from ``camera`` (as in :meth:`render`), ``(height, width)`` ``float32``.

        Args:
            linear: ``True``: metres along the camera's optical axis, in :meth:`depth_range` (pixels
                that see nothing read ``far``). ``False``: the convention of gymnasium's (and so
                Safety-Gymnasium's) ``depth_array`` render mode, MuJoCo's raw depth buffer: 0 at the
                near plane, 1 at the far one, ``far * (z - near) / (z * (far - near))`` for a point at
                ``z`` metres, not linear in ``z``. The planes scale with the model's extent, which
                Safety-Gymnasium recomputes with every layout; convert with this env's
                :meth:`depth_range`.
        """
        data, mjv_camera, renderer = self._render_setup(index, width, height, camera)
        rgb = np.empty((height, width, 3), dtype=np.uint8)
        depth = np.empty((height, width), dtype=np.float32)
        renderer.render_into(data, mjv_camera, rgb, depth, geom_alpha=self.geom_alpha(index))
        if linear:
            return depth
        near, far = self.depth_range()
        metres = depth.astype(np.float64)
        return np.clip(far * (metres - near) / (metres * (far - near)), 0.0, 1.0).astype(np.float32)

    def depth_range(self) -> tuple[float, float]:
        """``(near, far)``: the clipping planes of this env's cameras in metres (:func:`depth_range`)."""
        return depth_range(self.physics.model)

    def _render_setup(self, index: int, width: int, height: int, camera: Any) -> tuple:
        """``(data, MjvCamera, renderer)`` for one frame; (re)creates the renderer when the frame does not fit."""
        if self._render_closed:
            raise RuntimeError(f"{type(self).__name__}: render() after close()")
        data = self._render_data(index)
        mjv_camera = self.render_camera(index, camera)
        renderer = self._renderer
        if renderer is None or not renderer.fits(width, height):
            if renderer is not None:
                renderer.close()
            self._renderer = None
            renderer = self._renderer = Renderer(self.physics.model, width, height, fast=self.render_fast, effects=True)
        return data, mjv_camera, renderer

    def close_renderer(self) -> None:
        """Free the renderer (the next :meth:`render` creates a new one)."""
        renderer, self._renderer = self._renderer, None
        if renderer is not None:
            renderer.close()

    def close(self, *args, **kwargs):
        self.close_renderer()
        self._render_closed = True
        return super().close(*args, **kwargs)

    def __getstate__(self):
        # Copies and pickles (collectors, worker processes) get no renderer: GL contexts belong to
        # one process and one owner. The copy creates its own at its first render().
        state = dict(super().__getstate__())
        state.pop("_renderer", None)
        return state

    def _render_data(self, index: int) -> mujoco.MjData:
        datas = self.physics.datas
        if not isinstance(index, (int, np.integer)) or not 0 <= index < len(datas):
            raise IndexError(f"simulator index {index!r} out of range for {len(datas)} simulators")
        return datas[index]


# ---------------------------------------------------------------------------- videos
def _ffmpeg_available() -> bool:
    return importlib.util.find_spec("imageio_ffmpeg") is not None


def _frame_rate(env) -> float:
    dt = env.frame_skip * env.physics.model.opt.timestep
    return 1.0 / dt if dt > 0 else 30.0


def record_video(
    env,
    policy: Callable | None = None,
    path: str | os.PathLike = "episode.mp4",
    steps: int | None = None,
    *,
    fps: float | None = None,
    index: int = 0,
    width: int = DEFAULT_WIDTH,
    height: int = DEFAULT_HEIGHT,
    camera: Any = None,
    stop_when_done: bool = True,
) -> Path:
    """Reset ``env``, run it and write the frames of simulator ``index`` as a video.

    Args:
        env: an env with :class:`RenderMixin` (``sg_torchrl.make(...)``), or a gymnasium façade env
            (``sg_torchrl.gym.make(...)``; its TorchRL env is used).
        policy: maps the TensorDict of the current step to one holding ``"action"`` (an actor,
            e.g. inside ``set_exploration_type(ExplorationType.DETERMINISTIC)``), run under
            ``torch.no_grad``; ``None``: uniform random actions.
        path: ``.mp4`` (needs ``imageio-ffmpeg``; without it a GIF is written next to it and a
            warning says so) or ``.gif``.
        steps: at most this many env steps (default: the env's ``max_episode_steps``).
        fps: frame rate (default: real time, one frame per env step of ``frame_skip * timestep`` s).
        stop_when_done: stop when simulator ``index``'s episode ends (its last frame is included).

    Returns:
        The path written (the first frame is the reset state, then one frame per step).
    """
    import imageio.v2 as imageio
    from torchrl.envs.utils import step_mdp

    env = getattr(env, "torchrl_env", env)
    if not hasattr(env, "render"):
        raise TypeError(f"{type(env).__name__} cannot render")
    path = Path(path)
    fps = float(fps if fps is not None else _frame_rate(env))
    steps = int(steps if steps is not None else env.max_episode_steps)
    if path.suffix.lower() != ".gif" and not _ffmpeg_available():
        gif = path.with_suffix(".gif")
        warnings.warn(f"imageio-ffmpeg is not installed: writing {gif} instead of {path}", stacklevel=2)
        path = gif
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".gif":
        writer = imageio.get_writer(path, mode="I", duration=1000.0 / fps, loop=0)
    else:
        # macro_block_size=1: keep the frame size as is (libx264 still needs even sizes).
        writer = imageio.get_writer(path, fps=fps, macro_block_size=1)
    try:
        with torch.no_grad():
            td = env.reset()
            writer.append_data(env.render(index, width, height, camera))
            for _ in range(steps):
                if policy is None:
                    td.set("action", env.action_spec.rand())
                else:
                    td = policy(td)
                td = env.step(td)
                writer.append_data(env.render(index, width, height, camera))
                if stop_when_done and bool(td.get(("next", "done"))[index].any()):
                    break
                td = env.maybe_reset(step_mdp(td))
    finally:
        writer.close()
    return path
