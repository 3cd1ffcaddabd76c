"""The Building tasks' construction site: a sandy gravel floor and, from level 1 on, site hoardings
(concrete wall segments) and two shipping containers just outside the placement extents. They
collide, cost nothing and are not observed."""

from __future__ import annotations

from typing import ClassVar

import mujoco
import numpy as np

from sg_torchrl.envs.navigation.scenery.base import FloorTexture, Scenery

__all__ = ["ConstructionSite"]


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

    prefix: ClassVar[str] = "site"
    floor = FloorTexture("site_gravel", mujoco.mjtBuiltin.mjBUILTIN_FLAT, (0.64, 0.55, 0.42), (0.64, 0.55, 0.42),
                         mark=mujoco.mjtMark.mjMARK_RANDOM, markrgb=(0.42, 0.36, 0.28), random=0.3, repeat=6.0)
    light: ClassVar[float] = 0.3
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

    def add_geoms(self, world: mujoco.MjsBody) -> None:
        if not self.obstacles:
            return
        box = mujoco.mjtGeom.mjGEOM_BOX
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
