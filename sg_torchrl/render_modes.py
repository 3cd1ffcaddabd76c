"""Gymnasium's render modes for the façades (:mod:`sg_torchrl.gym`, :mod:`sg_torchrl.pettingzoo`).

A façade env built with ``render_mode=...`` hands its TorchRL env to a :class:`FrameSource`, which
renders simulator 0 the way gymnasium (and Safety-Gymnasium) define the mode:

* ``"rgb_array"``: ``render()`` returns the current frame, ``(height, width, 3)`` ``uint8``.
* ``"depth_array"``: ``render()`` returns the current depth image, ``(height, width)`` ``float32``,
  as MuJoCo's (and so gymnasium's) depth buffer: 0 at the near clipping plane, 1 at the far one,
  growing with distance (``far * (z - near) / (z * (far - near))`` for a point at ``z`` metres along
  the optical axis; the env's ``render_depth``, which also gives metres).
* ``"rgb_array_list"`` / ``"depth_array_list"``: a frame is taken after every ``reset`` and ``step``
  (``reset`` first drops what was collected); ``render()`` returns the frames since the last call
  and starts a new list, as gymnasium's ``RenderCollection`` does.
* ``"human"``: a window shows a frame after every ``reset`` and ``step``; ``render()`` returns
  ``None``. It needs a display and ``pygame``: without a display (``DISPLAY`` / ``WAYLAND_DISPLAY``
  unset on Linux) or without pygame, building the env raises :class:`HumanRenderingUnavailable`,
  which names the reason and the headless alternatives; ``env.metadata["render_modes"]`` leaves
  ``"human"`` out where there is no display (:func:`available_render_modes`).

Frames come from the env's public rendering interface (``render``, ``render_depth``,
``render_camera``); options ``width``, ``height`` (default 256) and the camera, given as ``camera``,
or as Safety-Gymnasium's ``camera_name`` / ``camera_id`` (at most one of the three): a name of the
env's ``camera_names`` (the original's ``"fixednear"``, ``"fixedfar"``, ``"vision"``, ``"track"``
where the scene has them, and ``"follow"``, ``"chase"``, ``"world"``), or a model camera's id
(:mod:`sg_torchrl.envs.cameras`).
"""

from __future__ import annotations

import os
import sys
from typing import Any

import gymnasium
import numpy as np

__all__ = ["RENDER_MODES", "FrameSource", "HumanRenderingUnavailable", "available_render_modes", "render_frames",
           "split_render_options"]

RENDER_MODES = ("human", "rgb_array", "depth_array", "rgb_array_list", "depth_array_list")
RENDER_OPTIONS = ("width", "height", "camera", "camera_name", "camera_id")
_DEFAULT_SIZE = 256


class HumanRenderingUnavailable(gymnasium.error.DependencyNotInstalled):
    """``render_mode="human"`` cannot open a window here (no display, or no pygame)."""


def _has_display() -> bool:
    return not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def available_render_modes() -> list[str]:
    """The render modes that work in this process: all of :data:`RENDER_MODES`, less ``"human"``
    without a display. The façades' ``env.metadata["render_modes"]`` is this list, so that tools which
    try every declared mode (gymnasium's ``check_env``) do not open windows on headless machines."""
    return [mode for mode in RENDER_MODES if mode != "human" or _has_display()]


def split_render_options(options: dict[str, Any]) -> dict[str, Any]:
    """Remove the render options from ``options`` (in place) and return them."""
    return {key: options.pop(key) for key in RENDER_OPTIONS if key in options}


def _check_mode(render_mode: str) -> None:
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode={render_mode!r} is not one of {list(RENDER_MODES)} (or None)")


def render_frames(frames: FrameSource | None) -> np.ndarray | list[np.ndarray] | None:
    """What a façade's ``render()`` returns: ``frames.render()``, or ``None`` with gymnasium's warning
    for an env built without a render mode (``frames`` is ``None``)."""
    if frames is None:
        gymnasium.logger.warn("render() called without a render_mode: pass render_mode='rgb_array' "
                              f"(or one of {list(RENDER_MODES)}) to make")
        return None
    return frames.render()


def _camera(options: dict[str, Any]) -> Any:
    given = {key: options[key] for key in ("camera", "camera_name", "camera_id") if options.get(key) is not None}
    if len(given) > 1:
        raise TypeError(f"pass only one of camera, camera_name, camera_id (got {sorted(given)})")
    return next(iter(given.values()), None)


def _size(options: dict[str, Any], key: str) -> int:
    value = options.get(key)
    if value is None:
        return _DEFAULT_SIZE
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{key} must be a positive integer, got {value!r}")
    return int(value)


class FrameSource:
    """Renders simulator 0 of a TorchRL env in one of gymnasium's render modes (module docstring).

    Args:
        env: a TorchRL env with the rendering interface of :class:`sg_torchrl.envs.rendering.RenderMixin`.
        render_mode: one of :data:`RENDER_MODES` (a façade built without one has no frame source:
            :func:`render_frames`).
        options: ``width``, ``height``, ``camera`` / ``camera_name`` / ``camera_id``.
        fps: the window's frame rate in ``"human"`` mode.

    Raises:
        ValueError: an unknown render mode, a bad size or camera (the camera is checked here, so a
            typo fails at construction rather than at the first frame).
        HumanRenderingUnavailable: ``"human"`` without a display or without pygame.
        NotImplementedError: the env cannot render.
    """

    def __init__(self, env: Any, render_mode: str, options: dict[str, Any], fps: float = 30.0) -> None:
        _check_mode(render_mode)
        unknown = sorted(set(options) - set(RENDER_OPTIONS))
        if unknown:
            raise TypeError(f"unknown render options {unknown}; the render options are {list(RENDER_OPTIONS)}")
        self.render_mode = render_mode
        self.width, self.height = _size(options, "width"), _size(options, "height")
        self.camera = _camera(options)
        self._env = env
        self._frames: list[np.ndarray] = []
        self._window = None
        needs = ("render_depth",) if self._depth else ("render",)
        if not all(hasattr(env, name) for name in (*needs, "render_camera")):
            raise NotImplementedError(f"{type(env).__name__} cannot render (render_mode={render_mode!r})")
        env.render_camera(0, self.camera)  # raises ValueError for an unknown camera
        if render_mode == "human":
            self._window = _HumanWindow(self.width, self.height, fps)

    @property
    def _depth(self) -> bool:
        return self.render_mode in ("depth_array", "depth_array_list")

    def frame(self) -> np.ndarray:
        """The current frame of the mode: RGB ``(H, W, 3)`` ``uint8`` or depth ``(H, W)`` ``float32``."""
        if not self._depth:
            return self._env.render(0, self.width, self.height, self.camera)
        return self._env.render_depth(0, self.width, self.height, self.camera, linear=False)

    def after_reset(self) -> None:
        """Call after every ``reset``: list modes start a new list with this frame; ``human`` shows it."""
        if self.render_mode in ("rgb_array_list", "depth_array_list"):
            self._frames = [self.frame()]
        elif self._window is not None:
            self._window.show(self.frame())

    def after_step(self) -> None:
        """Call after every ``step``: list modes keep the frame; ``human`` shows it."""
        if self.render_mode in ("rgb_array_list", "depth_array_list"):
            self._frames.append(self.frame())
        elif self._window is not None:
            self._window.show(self.frame())

    def copy_frames_from(self, other: FrameSource) -> None:
        """Take copies of the frames ``other`` has collected (a façade's ``deepcopy``)."""
        self._frames = [frame.copy() for frame in other._frames]

    def render(self) -> np.ndarray | list[np.ndarray] | None:
        """What the façade's ``render()`` returns in this mode (see the module docstring)."""
        if self.render_mode in ("rgb_array_list", "depth_array_list"):
            frames, self._frames = self._frames, []
            return frames
        if self.render_mode == "human":
            return None
        return self.frame()

    def close(self) -> None:
        """Release the window (the env's renderer closes with the env)."""
        if self._window is not None:
            self._window.close()
            self._window = None


class _HumanWindow:
    """A pygame window showing RGB frames at a fixed rate (``render_mode="human"``)."""

    def __init__(self, width: int, height: int, fps: float) -> None:
        if not _has_display():
            raise HumanRenderingUnavailable(
                "render_mode='human' opens a window, but there is no display here (DISPLAY and WAYLAND_DISPLAY "
                "are unset). On a headless machine use render_mode='rgb_array' (render() returns each frame) or "
                "'rgb_array_list' (the frames of an episode, e.g. for gymnasium.wrappers.RecordVideo)")
        try:
            import pygame
        except ImportError as error:
            raise HumanRenderingUnavailable(
                "render_mode='human' shows frames with pygame, which is not installed (pip install pygame); "
                "or use render_mode='rgb_array' and display the frames yourself") from error
        self._pygame = pygame
        pygame.init()
        pygame.display.init()
        self._screen = pygame.display.set_mode((width, height))
        self._clock = pygame.time.Clock()
        self._fps = fps

    def show(self, frame: np.ndarray) -> None:
        pygame = self._pygame
        surface = pygame.surfarray.make_surface(np.transpose(frame, (1, 0, 2)))
        self._screen.blit(surface, (0, 0))
        pygame.event.pump()
        self._clock.tick(self._fps)
        pygame.display.flip()

    def close(self) -> None:
        self._pygame.display.quit()
