"""Race's village: a road, roadside houses, trees and rocks on a checkered grass floor.

Safety-Gymnasium's Race uses meshes of a village (houses, trees, bushes, a flower-bush goal) whose
assets it does not ship (its Race ids do not run); these props, MuJoCo primitives, stand in for them
with the same role: solid obstacles beside the road. Race charges robot contacts with them
(:meth:`~sg_torchrl.envs.navigation.scenery.base.Scenery.robot_contacts`: ``static_geoms_contact``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar, Literal

import mujoco

from sg_torchrl.envs.navigation.scenery.base import FloorTexture, Scenery

__all__ = ["Prop", "RoadSegment", "Village"]

PropKind = Literal["house", "tree", "rock"]

_GEOM = mujoco.mjtGeom


@dataclass(frozen=True)
class Prop:
    """One solid roadside object at ``(x, y)``: a ``"house"`` (walls and a roof, boxes), a ``"tree"``
    (trunk cylinder, canopy sphere) or a ``"rock"`` (ellipsoid). :attr:`footprint` is its half extent."""

    kind: PropKind
    x: float
    y: float

    # (geom type, half sizes, centre height, rgba) of each part, per kind
    PARTS = {
        "house": ((_GEOM.mjGEOM_BOX, (0.45, 0.35, 0.3), 0.3, (0.86, 0.78, 0.62, 1.0)),
                  (_GEOM.mjGEOM_BOX, (0.52, 0.42, 0.06), 0.66, (0.62, 0.2, 0.15, 1.0))),
        "tree": ((_GEOM.mjGEOM_CYLINDER, (0.07, 0.25, 0.0), 0.25, (0.45, 0.3, 0.15, 1.0)),
                 (_GEOM.mjGEOM_SPHERE, (0.3, 0.0, 0.0), 0.75, (0.18, 0.5, 0.2, 1.0))),
        "rock": ((_GEOM.mjGEOM_ELLIPSOID, (0.3, 0.22, 0.15), 0.1, (0.5, 0.5, 0.52, 1.0)),),
    }

    def __post_init__(self) -> None:
        if self.kind not in self.PARTS:
            raise ValueError(f"unknown prop kind {self.kind!r}; choose from {sorted(self.PARTS)}")

    @property
    def footprint(self) -> tuple[float, float]:
        """Half extent in x and y of the widest part, metres (what a robot bumps into first)."""
        extents = [(size[0], size[1] if kind in (_GEOM.mjGEOM_BOX, _GEOM.mjGEOM_ELLIPSOID) else size[0])
                   for kind, size, _, _ in self.PARTS[self.kind]]
        return max(x for x, _ in extents), max(y for _, y in extents)


@dataclass(frozen=True)
class RoadSegment:
    """A flat road rectangle ``(xmin, ymin, xmax, ymax)``: drawn only (it neither collides nor costs)."""

    xmin: float
    ymin: float
    xmax: float
    ymax: float


class Village(Scenery):
    """Race's road, roadside props and grass floor (see the module docstring).

    Args:
        props: the solid objects.
        road: the road's rectangles (drawn a few millimetres above the floor).
        grass: the two colours of the floor's checker texture (``None``: keep the plain floor).
        tiles: checker squares along the floor's side.
    """

    prefix: ClassVar[str] = "scenery"
    road_rgba = (0.32, 0.32, 0.34, 1.0)

    def __init__(self, props: Sequence[Prop], road: Sequence[RoadSegment] = (),
                 grass: tuple[tuple[float, float, float], tuple[float, float, float]] | None = (
                     (0.36, 0.55, 0.28), (0.32, 0.5, 0.25)),
                 tiles: int = 70) -> None:
        self.props = tuple(props)
        self.road = tuple(road)
        self.floor = None if grass is None else FloorTexture(
            "scenery_grass", mujoco.mjtBuiltin.mjBUILTIN_CHECKER, tuple(grass[0]), tuple(grass[1]),
            repeat=int(tiles), size=64)

    @property
    def key(self) -> tuple:
        return (type(self).__qualname__, self.props, self.road, self.floor)

    def add_geoms(self, world: mujoco.MjsBody) -> None:
        for index, prop in enumerate(self.props):
            for part, (kind, size, height, rgba) in enumerate(Prop.PARTS[prop.kind]):
                world.add_geom(name=f"scenery_{prop.kind}{index}_{part}", type=kind, size=list(size),
                               pos=[prop.x, prop.y, height], rgba=list(rgba), group=0)
        for index, segment in enumerate(self.road):
            half = [(segment.xmax - segment.xmin) / 2, (segment.ymax - segment.ymin) / 2, 0.001]
            centre = [(segment.xmax + segment.xmin) / 2, (segment.ymax + segment.ymin) / 2, 0.002]
            world.add_geom(name=f"scenery_road{index}", type=_GEOM.mjGEOM_BOX, size=half, pos=centre,
                           contype=0, conaffinity=0, group=0, rgba=list(self.road_rgba))
