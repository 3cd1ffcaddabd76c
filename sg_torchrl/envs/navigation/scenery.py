"""Scenery: static set dressing of a task level (floor look, fixed obstacles), built once into the world.

A :class:`Scenery` is not a task object: it has no layout item, no state, no lidar group and no cost.
It restyles the floor with one of MuJoCo's built-in procedural textures (no image files are shipped)
and adds fixed world geoms. Geoms that collide are obstacles the robot can bump into; they cost
nothing and are not observed, like the reference's boundary walls (constraints that must be seen
and cost belong in :mod:`~sg_torchrl.envs.navigation.objects`). A task level passes its scenery to
:class:`~sg_torchrl.envs.navigation.tasks.base.Task`, whose :meth:`decorate` builds it after the
floor and the objects; the scenery's :attr:`Scenery.key` is part of the compiled-model cache key.

* :class:`Village` (the Race tasks): a road, roadside houses, trees and rocks (solid) on a checkered
  grass floor. Safety-Gymnasium's Race uses village meshes it does not ship; these primitives stand
  in for them with the same role. Race charges robot contacts with them (:meth:`Village.robot_contacts`:
  ``static_geoms_contact``).
* :class:`ConstructionSite` (the Building tasks): a sandy gravel floor; from level 1 on, site
  hoardings (concrete wall segments) and two shipping containers just outside the placement extents.
* :class:`RaceTrackScenery` (FormulaOne): a grass floor with an asphalt loop, red-and-white kerbs,
  a start line and white checkpoint lines; nothing of it collides (the barriers and fences that
  cost are task objects, :mod:`~sg_torchrl.envs.navigation.objects.track`).
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.track import Track

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.world import Scene

__all__ = ["ConstructionSite", "Prop", "RaceTrackScenery", "RoadSegment", "Scenery", "Village", "daylight",
           "texture_floor"]

PropKind = Literal["house", "tree", "rock"]

_GEOM = mujoco.mjtGeom

RGB = Sequence[float]


def texture_floor(spec: mujoco.MjSpec, name: str, *, builtin: mujoco.mjtBuiltin, rgb1: RGB, rgb2: RGB,
                  mark: mujoco.mjtMark = mujoco.mjtMark.mjMARK_NONE, markrgb: RGB = (0.0, 0.0, 0.0),
                  random: float = 0.0, repeat: float = 4.0, size: int = 128) -> None:
    """Give the world's ``floor`` geom a material with a built-in 2-D texture named ``name``.

    The floor's colour becomes white so the texture shows its own colours; ``repeat`` tiles it
    that many times across the floor.
    """
    spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=builtin, rgb1=list(rgb1),
                     rgb2=list(rgb2), mark=mark, markrgb=list(markrgb), random=random, width=size, height=size)
    material = spec.add_material(name=f"{name}_material", texrepeat=[repeat, repeat], reflectance=0.0)
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name
    floor = spec.geom("floor")
    floor.material = material.name
    floor.rgba = [1.0, 1.0, 1.0, 1.0]


def daylight(spec: mujoco.MjSpec, name: str, strength: float = 0.45) -> None:
    """Add a directional light that lights the whole floor evenly (the world's own light is a spot
    above the origin, which leaves a large scene's edges dark)."""
    spec.worldbody.add_light(name=name, type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, dir=[0.3, 0.4, -1.0],
                             castshadow=False, diffuse=[strength] * 3, specular=[0.0, 0.0, 0.0])


def _yaw_quat(yaw: float) -> list[float]:
    return [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))]


class Scenery(abc.ABC):
    """Static set dressing of one task level (see the module docstring)."""

    @property
    @abc.abstractmethod
    def key(self) -> tuple:
        """What :meth:`build` depends on (part of the compiled-model cache key)."""

    @abc.abstractmethod
    def build(self, spec: mujoco.MjSpec) -> None:
        """Restyle the floor and add the scenery's geoms to the world ``spec``."""


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

    @property
    def key(self) -> tuple:
        return (type(self).__qualname__, self.props, self.road, self.grass, self.tiles)

    def prop_geom_name(self, index: int, part: int) -> str:
        return f"scenery_{self.props[index].kind}{index}_{part}"

    def build(self, spec: mujoco.MjSpec) -> None:
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


class ConstructionSite(Scenery):
    """A construction site around placement extents ``+-extent`` (see the module docstring).

    Args:
        extent: half-width of the level's placement area; obstacles stand ``margin`` beyond it, so a
            sampled layout never overlaps them.
        obstacles: add the hoardings and containers (levels 1 and 2; level 0 is the floor only).
        margin: distance from the extents to the obstacles' inner faces.

    Obstacles (all collide, cost nothing, unobserved): ``site_wall0`` along ``y = +d`` over most of
    the site's width (a gap at one end), ``site_wall1`` along ``x = -d`` over half its depth, and
    containers ``site_container0`` / ``1`` (half-size 0.6 x 0.25 x 0.3, orange and blue, with
    darker non-colliding ribs) in the two corners at ``y = -d``; ``d = extent + margin``.
    """

    wall_rgba = (0.62, 0.62, 0.6, 1.0)
    container_rgba = ((0.85, 0.4, 0.1, 1.0), (0.15, 0.35, 0.65, 1.0))
    wall_half_height = 0.35
    wall_half_thickness = 0.05
    container_half = (0.6, 0.25, 0.3)

    def __init__(self, extent: float, *, obstacles: bool, margin: float = 0.8) -> None:
        self.extent = float(extent)
        self.obstacles = bool(obstacles)
        self.margin = float(margin)

    @property
    def key(self) -> tuple:
        return (type(self).__qualname__, self.extent, self.obstacles, self.margin)

    def build(self, spec: mujoco.MjSpec) -> None:
        texture_floor(spec, "site_gravel", builtin=mujoco.mjtBuiltin.mjBUILTIN_FLAT, rgb1=(0.64, 0.55, 0.42),
                      rgb2=(0.64, 0.55, 0.42), mark=mujoco.mjtMark.mjMARK_RANDOM, markrgb=(0.42, 0.36, 0.28),
                      random=0.3, repeat=6.0)
        daylight(spec, "site_daylight", 0.3)
        if not self.obstacles:
            return
        world, box = spec.worldbody, mujoco.mjtGeom.mjGEOM_BOX
        d, e, t, h = self.extent + self.margin, self.extent, self.wall_half_thickness, self.wall_half_height
        walls = [((-0.25 * e, d + t), (1.05 * e, t)),  # along y = +d, open at the +x end
                 ((-d - t, 0.5 * e), (t, 0.75 * e))]  # along x = -d, the +y half
        for i, ((x, y), (hx, hy)) in enumerate(walls):
            world.add_geom(name=f"site_wall{i}", type=box, pos=[x, y, h], size=[hx, hy, h], rgba=list(self.wall_rgba))
        hx, hy, hz = self.container_half
        for i, x in enumerate((-d + hx, d - hx)):
            y = -d - hy
            rgba = self.container_rgba[i]
            world.add_geom(name=f"site_container{i}", type=box, pos=[x, y, hz], size=[hx, hy, hz], rgba=list(rgba))
            rib = [0.6 * c for c in rgba[:3]] + [1.0]
            for k, rx in enumerate(np.linspace(-hx + 0.1, hx - 0.1, 6)):
                world.add_geom(name=f"site_container{i}_rib{k}", type=box, pos=[x + rx, y + hy, hz],
                               size=[0.015, 0.01, 0.95 * hz], rgba=rib, contype=0, conaffinity=0)


class RaceTrackScenery(Scenery):
    """The look of a :class:`~sg_torchrl.envs.navigation.track.Track` (see the module docstring).

    The asphalt is ``segments`` flat boxes along the centre line (``track.width`` wide), kerbs are
    alternating red and white blocks on both edges, a white line marks each of ``num_checkpoints``
    checkpoints (the first one, the start line, is chequered). Nothing collides.
    """

    def __init__(self, track: Track, *, num_checkpoints: int, segments: int = 96) -> None:
        self.track = track
        self.num_checkpoints = int(num_checkpoints)
        self.segments = int(segments)

    @property
    def key(self) -> tuple:
        return (type(self).__qualname__, self.track, self.num_checkpoints, self.segments)

    def build(self, spec: mujoco.MjSpec) -> None:
        texture_floor(spec, "track_grass", builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER, rgb1=(0.24, 0.5, 0.2),
                      rgb2=(0.28, 0.56, 0.23), repeat=17.5)
        daylight(spec, "track_daylight", 0.5)
        track, world, box = self.track, spec.worldbody, mujoco.mjtGeom.mjGEOM_BOX
        ghost = {"contype": 0, "conaffinity": 0}
        step = track.length / self.segments
        centres = (np.arange(self.segments) + 0.5) * step
        xy, heading = track.pose(centres)
        half_width = track.width / 2
        # In the curves the outer edge is longer than the centre line: stretch segments so no gap opens there.
        half_length = 0.5 * step * (1.0 + (half_width + 0.16) / track.radius) + 0.01
        for i, ((x, y), yaw) in enumerate(zip(xy, heading)):
            world.add_geom(name=f"asphalt{i}", type=box, pos=[x, y, 0.001], size=[half_length, half_width, 0.001],
                           quat=_yaw_quat(yaw), rgba=[0.22, 0.22, 0.24, 1.0], **ghost)
            colour = [0.85, 0.1, 0.1, 1.0] if i % 2 else [0.95, 0.95, 0.95, 1.0]
            for side in (-1.0, 1.0):
                kx, ky = track.offset(xy[i], yaw, side * (half_width + 0.08))
                z = 0.004 + 0.001 * (i % 2)  # neighbours overlap in the curves: alternate heights, no z-fighting
                world.add_geom(name=f"kerb{i}_{'left' if side > 0 else 'right'}", type=box, pos=[kx, ky, z],
                               size=[half_length, 0.08, 0.004], quat=_yaw_quat(yaw), rgba=colour, **ghost)
        checkpoints, checkpoint_heading = track.pose(track.checkpoint_arcs(self.num_checkpoints))
        for k, ((x, y), yaw) in enumerate(zip(checkpoints, checkpoint_heading)):
            world.add_geom(name=f"checkpoint_line{k}", type=box, pos=[x, y, 0.003], size=[0.06, half_width, 0.003],
                           quat=_yaw_quat(yaw), rgba=[1.0, 1.0, 1.0, 1.0], **ghost)
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
                               size=[0.0625, 0.5 * track.width / cells, 0.003], quat=_yaw_quat(yaw0),
                               rgba=[shade, shade, shade, 1.0], **ghost)
