"""FormulaOne's race track: a grass floor with an asphalt loop, red-and-white kerbs, a start line and
white checkpoint lines. Nothing of it collides (the barriers and fences that cost are task objects,
:mod:`~sg_torchrl.envs.navigation.objects.track`)."""

from __future__ import annotations

from typing import ClassVar

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.objects.base import yaw_quat
from sg_torchrl.envs.navigation.scenery.base import FloorTexture, Scenery
from sg_torchrl.envs.navigation.track import Track

__all__ = ["RaceTrackScenery"]


class RaceTrackScenery(Scenery):
    """The look of a :class:`~sg_torchrl.envs.navigation.track.Track` (see the module docstring).

    The asphalt is ``segments`` flat boxes along the centre line (``track.width`` wide), kerbs are
    alternating red and white blocks on both edges, a white line marks each of ``num_checkpoints``
    checkpoints (the first one, the start line, is chequered). Nothing collides.
    """

    prefix: ClassVar[str] = "track"
    floor = FloorTexture("track_grass", mujoco.mjtBuiltin.mjBUILTIN_CHECKER, (0.24, 0.5, 0.2), (0.28, 0.56, 0.23),
                         repeat=17.5)
    light: ClassVar[float] = 0.5

    def __init__(self, track: Track, *, num_checkpoints: int, segments: int = 96) -> None:
        self.track = track
        self.num_checkpoints = int(num_checkpoints)
        self.segments = int(segments)

    @property
    def key(self) -> tuple:
        return (type(self).__qualname__, self.track, self.num_checkpoints, self.segments)

    def add_geoms(self, world: mujoco.MjsBody) -> None:
        track, box = self.track, mujoco.mjtGeom.mjGEOM_BOX
        ghost = {"contype": 0, "conaffinity": 0}
        step = track.length / self.segments
        centres = (np.arange(self.segments) + 0.5) * step
        xy, heading = track.pose(centres)
        half_width = track.width / 2
        # In the curves the outer edge is longer than the centre line: stretch segments so no gap opens there.
        half_length = 0.5 * step * (1.0 + (half_width + 0.16) / track.radius) + 0.01
        for i, ((x, y), yaw) in enumerate(zip(xy, heading)):
            world.add_geom(name=f"asphalt{i}", type=box, pos=[x, y, 0.001], size=[half_length, half_width, 0.001],
                           quat=yaw_quat(yaw).tolist(), rgba=[0.22, 0.22, 0.24, 1.0], **ghost)
            colour = [0.85, 0.1, 0.1, 1.0] if i % 2 else [0.95, 0.95, 0.95, 1.0]
            for side in (-1.0, 1.0):
                kx, ky = track.offset(xy[i], yaw, side * (half_width + 0.08))
                z = 0.004 + 0.001 * (i % 2)  # neighbours overlap in the curves: alternate heights, no z-fighting
                world.add_geom(name=f"kerb{i}_{'left' if side > 0 else 'right'}", type=box, pos=[kx, ky, z],
                               size=[half_length, 0.08, 0.004], quat=yaw_quat(yaw).tolist(), rgba=colour, **ghost)
        checkpoints, checkpoint_heading = track.pose(track.checkpoint_arcs(self.num_checkpoints))
        for k, ((x, y), yaw) in enumerate(zip(checkpoints, checkpoint_heading)):
            world.add_geom(name=f"checkpoint_line{k}", type=box, pos=[x, y, 0.003], size=[0.06, half_width, 0.003],
                           quat=yaw_quat(yaw).tolist(), rgba=[1.0, 1.0, 1.0, 1.0], **ghost)
        # the start line: a chequered band just behind checkpoint 0
        (x0, y0), yaw0 = checkpoints[0], checkpoint_heading[0]
        cells = int(round(track.width / 0.25))
        for j in range(cells):
            for row in range(2):
                lateral = -half_width + (j + 0.5) * track.width / cells
                cx, cy = track.offset(np.array([x0, y0]), yaw0, lateral)
                cx -= (0.18 + 0.125 * row) * np.cos(yaw0)
                cy -= (0.18 + 0.125 * row) * np.sin(yaw0)
                shade = 0.05 if (j + row) % 2 else 0.95
                world.add_geom(name=f"start_cell{j}_{row}", type=box, pos=[cx, cy, 0.003],
                               size=[0.0625, 0.5 * track.width / cells, 0.003], quat=yaw_quat(yaw0).tolist(),
                               rgba=[shade, shade, shade, 1.0], **ghost)
