"""Scenery: static set dressing of a task level (floor look, fixed geoms), built once into the world.

A :class:`Scenery` is not a task object: it has no layout item, no state and no lidar group, and it
never moves. It restyles the floor with one of MuJoCo's built-in procedural textures (no image or
mesh files are shipped), may add a daylight, and adds fixed geoms to the world body, so they cost
nothing at reset and MuJoCo never collides them with the floor (two geoms of the world body). Geoms
that collide are obstacles the robot can bump into; they are not observed, like the reference's
static village meshes and boundary walls (constraints that must be seen belong in
:mod:`~sg_torchrl.envs.navigation.objects`). A task may still charge robot contacts with them
(:meth:`Scenery.robot_contacts`: Race's ``static_geoms_contact``).

A task level passes its scenery to :class:`~sg_torchrl.envs.navigation.tasks.base.Task`
(``scenery=...``); the world builder (:func:`~sg_torchrl.envs.navigation.world.build_spec`) builds it
after the floor, and its :attr:`Scenery.key` is part of the compiled-model cache key.

* ``base.py``              :class:`Scenery`, :class:`FloorTexture`, :func:`daylight`
* ``village.py``           :class:`Village` (Race): a road, houses, trees and rocks on grass
* ``construction_site.py`` :class:`ConstructionSite` (Building): gravel, site walls and containers
* ``race_track.py``        :class:`RaceTrackScenery` (FormulaOne): asphalt loop, kerbs, start and checkpoint lines
"""

from sg_torchrl.envs.navigation.scenery.base import FloorTexture, Scenery, daylight
from sg_torchrl.envs.navigation.scenery.construction_site import ConstructionSite
from sg_torchrl.envs.navigation.scenery.race_track import RaceTrackScenery
from sg_torchrl.envs.navigation.scenery.village import Prop, RoadSegment, Village

__all__ = ["ConstructionSite", "FloorTexture", "Prop", "RaceTrackScenery", "RoadSegment", "Scenery", "Village",
           "daylight"]
