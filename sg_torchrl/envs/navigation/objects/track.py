"""Track-side obstacles of FormulaOne: barriers and fences at fixed places along the track; touching one costs.

Both are :class:`TrackSide` objects: immovable boxes (mocap bodies) at fixed positions and headings
(tangent to the track), keep-out 0 (they stand off the asphalt, where no layout item goes), observed
through a 16-bin lidar group like every constraint, and constrained by contact: the cost entry
named after the object (``barriers``, ``fences``) is the number of robot contacts with its geoms,
as the reference counts pillar and gremlin contacts. The positions come from the task level
(:mod:`~sg_torchrl.envs.navigation.tasks.formula_one`), computed from its
:class:`~sg_torchrl.envs.navigation.track.Track`.
"""

from __future__ import annotations

from typing import ClassVar

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.objects.base import StaticObject
from sg_torchrl.envs.navigation.objects.contacts import ContactCost
from sg_torchrl.envs.navigation.world import ResetBuffers, Scene

__all__ = ["Barriers", "Fences", "TrackSide"]


class TrackSide(ContactCost, StaticObject):
    """Boxes of half-size ``half_size`` (along the track, across it, up) at ``positions`` facing ``headings``.

    Args:
        positions: ``(K, 2)`` centres; one instance each.
        headings: ``(K,)`` yaw of each box's long axis (the track's heading there).
        constrained: contacts cost (default).
    """

    half_size: ClassVar[tuple[float, float, float]]
    colours: ClassVar[tuple[tuple[float, float, float, float], ...]]

    def __init__(self, positions: np.ndarray, headings: np.ndarray, *, constrained: bool = True) -> None:
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
        headings = np.asarray(headings, dtype=np.float64).reshape(-1)
        if len(headings) != len(positions):
            raise ValueError(f"{type(self).__name__}: {len(positions)} positions but {len(headings)} headings")
        super().__init__(len(positions), size=self.half_size[0], keepout=0.0, locations=positions,
                         constrained=constrained)
        self.headings = headings
        self.height = self.half_size[2]

    def spec_key(self) -> tuple:
        return (*super().spec_key(), self.locations.round(6).tobytes(), self.headings.round(6).tobytes())

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        body.add_geom(name=self.body_name(i), type=mujoco.mjtGeom.mjGEOM_BOX, size=list(self.half_size), group=0,
                      rgba=list(self.colours[i % len(self.colours)]))

    def place(self, scene: Scene, indices: np.ndarray, rows: ResetBuffers, xy: np.ndarray, yaw: np.ndarray) -> None:
        super().place(scene, indices, rows, xy, np.broadcast_to(self.headings, yaw.shape))  # along the track


class Barriers(TrackSide):
    """Tyre-wall style barrier blocks (half-size 0.3 x 0.12 x 0.2, alternating red and white) at the curves."""

    name: ClassVar[str] = "barriers"
    prefix: ClassVar[str] = "barrier"
    half_size: ClassVar[tuple[float, float, float]] = (0.3, 0.12, 0.2)
    colours: ClassVar[tuple[tuple[float, float, float, float], ...]] = ((0.85, 0.1, 0.1, 1.0), (0.95, 0.95, 0.95, 1.0))


class Fences(TrackSide):
    """Fence panels (half-size 0.5 x 0.03 x 0.35, grey-blue) along the straights."""

    name: ClassVar[str] = "fences"
    prefix: ClassVar[str] = "fence"
    half_size: ClassVar[tuple[float, float, float]] = (0.5, 0.03, 0.35)
    colours: ClassVar[tuple[tuple[float, float, float, float], ...]] = ((0.45, 0.5, 0.6, 1.0),)
