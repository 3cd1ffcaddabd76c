"""Scenery: fixed world geometry around a task (a road, houses, trees, rocks) and the floor's texture.

Unlike task objects (:mod:`.objects`), scenery is never placed by the layout and never moves: its
geoms belong to the world body, added once when the world is built (:meth:`Scenery.add_to`), so
they cost nothing at reset and their contacts with the floor are filtered out by MuJoCo (two
geoms of the world body never collide). It is not observed by the lidar (Safety-Gymnasium's static
village meshes are not task objects either); a task may charge robot contacts with it
(:meth:`Scenery.robot_contacts`: Race's ``static_geoms_contact``).

Everything is built from MuJoCo primitives and MuJoCo's builtin procedural textures (a checker for
the grass): no mesh or image files. Safety-Gymnasium's Race uses meshes of a village (houses,
trees, bushes, a flower-bush goal) whose assets it does not ship (its Race ids do not run); these
props stand in for them, with the same role: solid obstacles beside the road.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import mujoco
import numpy as np

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.world import Scene

__all__ = ["Prop", "RoadSegment", "Scenery"]

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


class Scenery:
    """Fixed props, road and ground texture of a world (see the module docstring).

    Args:
        props: the solid objects.
        road: the road's rectangles (drawn a few millimetres above the floor).
        grass: the two colours of the floor's checker texture (``None``: keep the plain floor).
        tiles: checker squares along the floor's side.
    """

    road_rgba = (0.32, 0.32, 0.34, 1.0)

    def __init__(self, props: Sequence[Prop], road: Sequence[RoadSegment] = (),
                 grass: tuple[tuple[float, float, float], tuple[float, float, float]] | None = (
                     (0.36, 0.55, 0.28), (0.32, 0.5, 0.25)),
                 tiles: int = 70) -> None:
        self.props = tuple(props)
        self.road = tuple(road)
        self.grass = grass
        self.tiles = int(tiles)
        self.geom_mask = np.zeros(0, dtype=bool)

    def spec_key(self) -> tuple:
        """What :meth:`add_to` builds: part of the compiled-model cache key."""
        return ("scenery", self.props, self.road, self.grass, self.tiles)

    def prop_geom_name(self, index: int, part: int) -> str:
        return f"scenery_{self.props[index].kind}{index}_{part}"

    def add_to(self, spec: mujoco.MjSpec) -> None:
        """Add the props and road to the world body, and the grass texture to the geom named ``floor``."""
        world = spec.worldbody
        for index, prop in enumerate(self.props):
            for part, (kind, size, height, rgba) in enumerate(Prop.PARTS[prop.kind]):
                world.add_geom(name=self.prop_geom_name(index, part), type=kind, size=list(size),
                               pos=[prop.x, prop.y, height], rgba=list(rgba), group=0)
        for index, segment in enumerate(self.road):
            half = [(segment.xmax - segment.xmin) / 2, (segment.ymax - segment.ymin) / 2, 0.001]
            centre = [(segment.xmax + segment.xmin) / 2, (segment.ymax + segment.ymin) / 2, 0.002]
            world.add_geom(name=f"scenery_road{index}", type=_GEOM.mjGEOM_BOX, size=half, pos=centre,
                           contype=0, conaffinity=0, group=0, rgba=list(self.road_rgba))
        if self.grass is not None:
            spec.add_texture(name="scenery_grass", type=mujoco.mjtTexture.mjTEXTURE_2D,
                             builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER, rgb1=list(self.grass[0]),
                             rgb2=list(self.grass[1]), width=64, height=64)
            material = spec.add_material(name="scenery_grass", texrepeat=[self.tiles, self.tiles])
            material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "scenery_grass"
            floor = spec.geom("floor")
            floor.material = "scenery_grass"
            floor.rgba = [1.0, 1.0, 1.0, 1.0]

    def bind(self, model: mujoco.MjModel) -> None:
        """Resolve the props' geoms in the compiled model."""
        ids = [model.geom(self.prop_geom_name(i, part)).id
               for i, prop in enumerate(self.props) for part in range(len(Prop.PARTS[prop.kind]))]
        #: ``(ngeom,)`` bool, the props' geoms (the road is not solid)
        self.geom_mask = np.zeros(model.ngeom, dtype=bool)
        self.geom_mask[ids] = True

    def robot_contacts(self, scene: Scene) -> np.ndarray:
        """Number of contacts between the (scene's) robot and any prop, ``(N,)``."""
        return scene.robot_contacts()[:, self.geom_mask].sum(axis=1)
