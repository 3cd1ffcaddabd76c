"""Construction-site versions of the reference objects (Building tasks): new names, looks and sizes, same rules.

The Safety-Gymnasium paper describes Building scenes as a construction site where the robot docks at
positions, operates machines and moves a box among restricted areas, with construction-site
obstacles as constraints. Its reference notes give no object table for them, so each themed object
here is a small subclass of the reference object whose behaviour it copies (placement, cost,
lidar), with its own ``name`` (lidar group ``<name>_lidar``, cost entries named after it) and look:

==========================  ==================  ===============================================
object                      behaves like        cost entries (when constrained)
==========================  ==================  ===============================================
:class:`DockingGoal`        ``Goal``            none (``goal_lidar``; a docking pad)
:class:`RestrictedAreas`    ``Hazards``         ``restricted_areas``: depth inside, summed
:class:`FuelDrums`          ``Vases``           ``fuel_drums_contact``, ``fuel_drums_velocity``
:class:`SiteRobots`         ``Gremlins``        ``robots``: contacts with the moving robots
:class:`Machines`           ``Buttons``         ``machines``: pressing a machine that is not the goal
:class:`Columns`            ``Pillars``         ``columns``: contacts
:class:`Crate`              ``PushBox``         none (``push_box_lidar``: same name as Push's box)
==========================  ==================  ===============================================

Geometry that the reference's physics depends on (sizes of colliding geoms, densities) is kept;
what is added for the look (the fuel drum's rim, a machine's mast and lamp, a site robot's sensor
dome) never collides and, on free bodies, has the body's density so it adds a negligible mass.
"""

from __future__ import annotations

from typing import ClassVar

import mujoco

from sg_torchrl.envs.navigation.objects.buttons import Buttons
from sg_torchrl.envs.navigation.objects.goal import Goal
from sg_torchrl.envs.navigation.objects.gremlins import Gremlins
from sg_torchrl.envs.navigation.objects.hazards import Hazards
from sg_torchrl.envs.navigation.objects.pillars import Pillars
from sg_torchrl.envs.navigation.objects.push_box import PushBox
from sg_torchrl.envs.navigation.objects.vases import Vases

__all__ = ["Columns", "Crate", "DockingGoal", "FuelDrums", "Machines", "RestrictedAreas", "SiteRobots"]

_GHOST = {"contype": 0, "conaffinity": 0}


class DockingGoal(Goal):
    """The docking position: a Goal (radius 0.3, same reward) drawn as a translucent yellow-green pad."""

    rgba: ClassVar[tuple[float, float, float, float]] = (0.55, 0.95, 0.1, 0.35)


class RestrictedAreas(Hazards):
    """Restricted areas (e.g. under exhaust fans): Hazards in warning orange; cost ``restricted_areas``."""

    name: ClassVar[str] = "restricted_areas"
    prefix: ClassVar[str] = "restricted_area"
    rgba: ClassVar[tuple[float, float, float, float]] = (1.0, 0.45, 0.0, 0.4)


class FuelDrums(Vases):
    """Fuel drums: Vases (half-size 0.1, density 0.001, keep-out 0.15) shaped as upright red drums.

    Each drum is a cylinder of radius ``size`` and half-height ``half_height`` (0.15) with a
    non-colliding darker rim on top; touching one or setting it in motion costs
    (``fuel_drums_contact``, ``fuel_drums_velocity``) when constrained.
    """

    name: ClassVar[str] = "fuel_drums"
    prefix: ClassVar[str] = "fuel_drum"
    rgba: ClassVar[tuple[float, float, float, float]] = (0.75, 0.1, 0.06, 1.0)

    def __init__(self, num: int = 1, *, half_height: float = 0.15, **options) -> None:
        super().__init__(num, **options)
        self.half_height = float(half_height)
        self.height = self.half_height - self.sink

    def spec_key(self) -> tuple:
        return (*super().spec_key(), self.half_height)

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        body.add_geom(name=self.body_name(i), type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[self.size, self.half_height, 0.0],
                      density=self.density, group=0, rgba=list(self.rgba))
        body.add_geom(name=f"{self.body_name(i)}_rim", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                      size=[0.8 * self.size, 0.005, 0.0], pos=[0.0, 0.0, self.half_height], density=self.density,
                      group=0, rgba=[0.3, 0.3, 0.3, 1.0], **_GHOST)


class SiteRobots(Gremlins):
    """Moving site robots: Gremlins (box 0.1, circling radius 0.35) in yellow with a dark sensor dome; cost ``robots``."""

    name: ClassVar[str] = "robots"
    prefix: ClassVar[str] = "site_robot"
    rgba: ClassVar[tuple[float, float, float, float]] = (0.95, 0.75, 0.05, 1.0)

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        super().add_geoms(body, i)
        body.add_geom(name=f"{self.body_name(i)}_dome", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.5 * self.size, 0, 0],
                      pos=[0.0, 0.0, self.size], density=self.density, group=0, rgba=[0.1, 0.1, 0.1, 1.0], **_GHOST)


class Machines(Buttons):
    """Machines to operate: Buttons (sphere 0.1, keep-out 0.2) whose button is a machine's control knob.

    The knob (the first geom of each body, the one that is pressed) is a green start button; a thin grey mast with
    an amber lamp rises from it (never collides). Pressing a machine other than the goal one costs
    ``machines`` when constrained.
    """

    name: ClassVar[str] = "machines"
    prefix: ClassVar[str] = "machine"
    rgba: ClassVar[tuple[float, float, float, float]] = (0.1, 0.75, 0.2, 1.0)
    mast_height: ClassVar[float] = 0.45

    def add_geoms(self, body: mujoco.MjsBody, i: int) -> None:
        super().add_geoms(body, i)  # the knob first: Buttons reads each body's first geom
        top = self.size + self.mast_height
        body.add_geom(name=f"{self.body_name(i)}_mast", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                      size=[0.02, self.mast_height / 2, 0.0], pos=[0.0, 0.0, self.size + self.mast_height / 2],
                      group=0, rgba=[0.4, 0.4, 0.4, 1.0], **_GHOST)
        body.add_geom(name=f"{self.body_name(i)}_lamp", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.05, 0.0, 0.0],
                      pos=[0.0, 0.0, top], group=0, rgba=[1.0, 0.55, 0.0, 1.0], **_GHOST)


class Columns(Pillars):
    """Concrete columns: Pillars (radius 0.2, half-height 0.5, keep-out 0.3) in concrete grey; cost ``columns``."""

    name: ClassVar[str] = "columns"
    prefix: ClassVar[str] = "column"
    rgba: ClassVar[tuple[float, float, float, float]] = (0.6, 0.6, 0.58, 1.0)


class Crate(PushBox):
    """The box to move: the PushBox (same sizes per robot, same name ``push_box``) as a wooden crate."""

    rgba: ClassVar[tuple[float, float, float, float]] = (0.62, 0.43, 0.2, 1.0)
