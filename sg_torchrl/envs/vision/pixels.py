"""Pixel observations: what each simulator's robot-mounted ``vision`` camera sees, as TorchRL entries.

A navigation env built with ``obs_mode`` other than ``"vector"`` (every ``...Vision-v0`` id is)
emits, besides or instead of the flat ``observation`` vector:

* ``"pixels"``: ``(*B, H, W, 3)`` ``uint8`` RGB, channels last: TorchRL's convention for raw
  pixels (its gym and DMControl wrappers emit the same), so stock transforms apply unchanged:
  ``ToTensorImage(in_keys=["pixels"])`` gives ``(*B, 3, H, W)`` floats in ``[0, 1]``, as ConvNets
  take them (sg_torchrl's own CNN encoders, :mod:`sg_torchrl.modules.mlp`, read the uint8 images
  and do that inside the network, so batches stay compact);
* ``"depth"`` (RGB-D modes): ``(*B, H, W, 1)`` ``float32`` metres along the camera's optical axis
  (planar depth, as OpenGL's depth buffer measures it), in ``[near, far]`` of the model's clipping
  planes; pixels that see nothing read ``far``. Channels last like ``pixels``: the same
  ``ToTensorImage(in_keys=["pixels", "depth"])`` turns both channels first, and leaves the float
  depth in metres (it scales only integer images).

``obs_mode`` is one of :data:`OBS_MODES`: ``"vector"`` (the flat vector only, the default of the
plain ids), ``"rgb"``, ``"rgbd"`` (pixels only), ``"vector+rgb"``, ``"vector+rgbd"`` (both; the
Vision ids' default is ``"vector+rgb"``, what Safety-Gymnasium's Vision envs observe). Images are
square, ``image_size`` pixels a side: 256 by default, Safety-Gymnasium's size; ``image_size=64`` (or
less) makes them 16 times cheaper to render, store and learn from. :class:`~.layout.DictLayout` splits
``observation`` and ``pixels`` into the original's dict (``accelerometer``, ..., ``goal_lidar``, ...,
``vision``).

How: one :class:`PixelObserver` per env owns one offscreen
:class:`~sg_torchrl.envs.rendering.Renderer` that renders the ``N`` simulators one after the other
into ``(N, H, W, 3)`` / ``(N, H, W)`` buffers allocated once, without anti-aliasing or shadows (several
times faster on a software rasteriser) but with the floor's reflections and the starry skybox of the
original (``Renderer(fast=True, effects=True)``: about 10% more). The
env renders after every step (all simulators) and after a reset (only the simulators reset: a
partial reset draws nothing for the others), and copies the buffers into fresh tensors when it
emits a TensorDict. Rendering only reads ``MjData``: trajectories are the same with or without
pixels. The renderer is created at the first frame (so copies and pickles of an env make their
own: GL contexts belong to one process) and freed by :meth:`PixelObserver.close` (``env.close()``).
Without a working OpenGL backend, building a pixel env raises
:class:`~sg_torchrl.envs.rendering.RenderingUnavailable`, which says what is missing.

The scene is the original's (:func:`sg_torchrl.envs.navigation.world.add_look`: checkered floor,
one directional light, a starry sky; each robot's camera pose and field of view; the clipping planes
of its extent), so images agree in their statistics (``tests/test_vision_fidelity.py`` measures
them against safety-gymnasium 1.0.0). Differences from Safety-Gymnasium's Vision envs, whose
``vision`` image goes through ``render()``: theirs shows the lidar indicator spheres above the agent
when they come into view, these show only the world (the markers are a debugging aid, not part of
what a camera on the robot would see); their stars are photographs, ours MuJoCo's random marks;
theirs is anti-aliased. The key is TorchRL's ``"pixels"`` next to the flat ``"observation"``, in the
same channels-last layout; the gymnasium façade gives the original's ``"vision"`` key back.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Literal, get_args

import mujoco
import numpy as np
import torch
from torchrl.data import Bounded, TensorSpec

from sg_torchrl.envs.physics import MujocoBatch
from sg_torchrl.envs.rendering import GeomAlpha, Renderer, gl_backend

__all__ = ["OBS_MODES", "ObsMode", "ObservationContent", "PixelObserver", "DEFAULT_IMAGE_SIZE"]

ObsMode = Literal["vector", "rgb", "rgbd", "vector+rgb", "vector+rgbd"]
#: every accepted ``obs_mode``
OBS_MODES: tuple[str, ...] = get_args(ObsMode)
#: default side of the square images, pixels: Safety-Gymnasium's (its ``vision_size`` is 256 x 256)
DEFAULT_IMAGE_SIZE = 256


@dataclass(frozen=True)
class ObservationContent:
    """What an ``obs_mode`` puts in the TensorDict: the flat vector, RGB pixels, depth."""

    vector: bool
    rgb: bool
    depth: bool

    @classmethod
    def parse(cls, obs_mode: str) -> ObservationContent:
        """The content of ``obs_mode``; anything but one of :data:`OBS_MODES` raises ``ValueError``."""
        if obs_mode not in OBS_MODES:
            raise ValueError(f"obs_mode must be one of {', '.join(map(repr, OBS_MODES))}, got {obs_mode!r}")
        parts = set(obs_mode.split("+"))
        return cls(vector="vector" in parts, rgb=bool(parts & {"rgb", "rgbd"}), depth="rgbd" in parts)

    @property
    def pixels(self) -> bool:
        """Whether images are rendered at all."""
        return self.rgb or self.depth


class PixelObserver:
    """Renders one camera of every simulator of a :class:`MujocoBatch` into batched image buffers.

    Args:
        physics: the simulators (one shared model).
        camera: name of the model camera to render (the robots' egocentric ``"vision"``).
        image_size: side of the square images, pixels (a positive int).
        depth: also render depth.
        geom_alpha: ``geom_alpha(index)``: the alphas simulator ``index`` draws some geoms with (the
            env's :meth:`~sg_torchrl.envs.rendering.RenderMixin.geom_alpha`: fading objects), or
            ``None`` to draw the model's colours.

    Attributes:
        rgb: ``(N, H, W, 3)`` uint8, the last frame rendered of each simulator (channels last:
            what OpenGL reads and what :meth:`observation` emits).
        depth: ``(N, H, W)`` float32 metres, or ``None``.
        near, far: the depth range (the model's clipping planes), metres.
    """

    def __init__(self, physics: MujocoBatch, camera: str, image_size: int, *, depth: bool,
                 geom_alpha: Callable[[int], GeomAlpha | None] | None = None) -> None:
        if isinstance(image_size, bool) or not isinstance(image_size, (int, np.integer)) or image_size < 1:
            raise ValueError(f"image_size must be a positive integer, got {image_size!r}")
        model = physics.model
        camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if camera_id < 0:
            names = [model.camera(i).name for i in range(model.ncam)]
            raise ValueError(f"the model has no camera {camera!r} (cameras: {names})")
        gl_backend()  # fail now, with the reason, rather than at the first reset
        self.physics = physics
        self.geom_alpha = geom_alpha
        self.image_size = int(image_size)
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self.camera.fixedcamid = camera_id
        n, size = len(physics.datas), self.image_size
        self.rgb = np.zeros((n, size, size, 3), dtype=np.uint8)
        self.depth = np.zeros((n, size, size), dtype=np.float32) if depth else None
        extent = float(model.stat.extent)
        self.near, self.far = float(model.vis.map.znear) * extent, float(model.vis.map.zfar) * extent
        self._renderer: Renderer | None = None
        self._closed = False

    @property
    def renderer(self) -> Renderer | None:
        """The renderer, once the first frame was drawn (``None`` before and after :meth:`close`)."""
        return self._renderer

    def specs(self, num_envs: int, device: torch.device | str | None) -> dict[str, TensorSpec]:
        """The observation-spec entries: ``pixels`` and, with depth, ``depth`` (shapes include ``N``)."""
        size = self.image_size
        specs: dict[str, TensorSpec] = {
            "pixels": Bounded(low=0, high=255, shape=(num_envs, size, size, 3), dtype=torch.uint8, device=device)
        }
        if self.depth is not None:
            specs["depth"] = Bounded(low=self.near, high=self.far, shape=(num_envs, size, size, 1),
                                     dtype=torch.float32, device=device)
        return specs

    def render(self, indices: Iterable[int]) -> None:
        """Draw simulators ``indices`` into :attr:`rgb` (and :attr:`depth`); the others keep their frames."""
        if self._closed:
            raise RuntimeError("the pixel observer is closed (env.close() was called)")
        renderer = self._renderer
        if renderer is None:
            size = self.image_size
            renderer = self._renderer = Renderer(self.physics.model, size, size, fast=True, effects=True)
        datas, camera, depth, alpha = self.physics.datas, self.camera, self.depth, self.geom_alpha
        for index in indices:
            renderer.render_into(datas[index], camera, self.rgb[index], None if depth is None else depth[index],
                                 geom_alpha=None if alpha is None else alpha(index))

    def observation(self) -> dict[str, torch.Tensor]:
        """Fresh tensors of the current frames: ``pixels`` ``(N, H, W, 3)`` and ``depth`` ``(N, H, W, 1)``."""
        entries = {"pixels": torch.from_numpy(self.rgb).clone()}  # the buffers are redrawn: emit copies
        if self.depth is not None:
            entries["depth"] = torch.from_numpy(self.depth).unsqueeze(-1).clone()
        return entries

    def close(self) -> None:
        """Free the renderer; rendering afterwards raises. Calling it again does nothing."""
        self._closed = True
        renderer, self._renderer = self._renderer, None
        if renderer is not None:
            renderer.close()

    def __getstate__(self) -> dict:
        # Copies and pickles get no renderer (a GL context belongs to one process and one owner);
        # they create their own at their first frame. MjvCamera is not picklable: keep its id.
        state = dict(self.__dict__)
        state["_renderer"] = None
        state["camera"] = int(self.camera.fixedcamid)
        return state

    def __setstate__(self, state: dict) -> None:
        camera_id = state.pop("camera")
        self.__dict__.update(state)
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self.camera.fixedcamid = camera_id
