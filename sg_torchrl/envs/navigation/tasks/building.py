"""Building tasks: Goal, Button and Push on a construction site (Safety-Gymnasium paper, "Building" scenes).

The paper describes the scenes (dock at positions, operate machines, move a box among restricted
areas, construction-site obstacles as constraints) but our reference notes give no tables for them.
So each Building task is the reference task of the same kind (same reward, events, episode length
1000, extents, counts, sizes and keep-outs per level), composed of the themed objects of
:mod:`~sg_torchrl.envs.navigation.objects.construction` instead of the reference's, on a
:class:`~sg_torchrl.envs.navigation.scenery.ConstructionSite` (sandy floor; from level 1 on, site walls
and two containers just outside the extents: obstacles that neither cost nor are observed).

==============  =====  =======  ===========================================================  =====
task            level  extents  objects (in observation order after the robot's sensors)     Point
==============  =====  =======  ===========================================================  =====
BuildingGoal    0      +-1      goal (docking pad)                                            28
BuildingGoal    1      +-1.5    goal, 8 restricted_areas, 1 fuel_drums (unconstrained)       60
BuildingGoal    2      +-2      goal, 10 restricted_areas, 10 fuel_drums                     60
BuildingButton  0      +-1      4 machines (unconstrained), goal (marker)                    44
BuildingButton  1      +-1.5    4 machines, goal, 4 restricted_areas, 4 robots               76
BuildingButton  2      +-1.8    4 machines, goal, 8 restricted_areas, 6 robots               76
BuildingPush    0      +-1      goal, push_box (crate)                                        44
BuildingPush    1      +-1.5    goal, 2 restricted_areas (r 0.3), 1 columns (unconstrained),  76
                                push_box
BuildingPush    2      +-2      goal, 4 restricted_areas (r 0.3), 4 columns, push_box        76
==============  =====  =======  ===========================================================  =====

Each object observed adds a 16-bin ``<name>_lidar`` group; the sizes for the other robots follow by
adding their sensor counts as for the reference tasks (Car +12, Racecar +0, Doggo +44, Ant +28).
Cost entries: ``restricted_areas``, ``fuel_drums_contact``, ``fuel_drums_velocity``, ``machines``,
``robots``, ``columns`` (level 0: none).
"""

from __future__ import annotations

from typing import ClassVar

from sg_torchrl.envs.navigation.objects import (Columns, Crate, DockingGoal, FuelDrums, GoalMarker, Machines,
                                                RestrictedAreas, SiteRobots)
from sg_torchrl.envs.navigation.scenery import ConstructionSite
from sg_torchrl.envs.navigation.tasks.button import ButtonTask
from sg_torchrl.envs.navigation.tasks.goal import GoalTask
from sg_torchrl.envs.navigation.tasks.push import PushTask

__all__ = ["BUILDING_BUTTON_LEVELS", "BUILDING_GOAL_LEVELS", "BUILDING_PUSH_LEVELS", "BuildingButtonTask",
           "BuildingGoalTask", "BuildingPushTask"]


class BuildingGoalTask(GoalTask):
    """Dock at positions one after another: :class:`GoalTask` on the construction site."""

    name: ClassVar[str] = "BuildingGoal"


class BuildingButtonTask(ButtonTask):
    """Operate the goal machine, then the next: :class:`ButtonTask` with machines for buttons."""

    name: ClassVar[str] = "BuildingButton"


class BuildingPushTask(PushTask):
    """Move the crate onto goals among restricted areas: :class:`PushTask` on the construction site."""

    name: ClassVar[str] = "BuildingPush"


def site(extent: float, level: int) -> ConstructionSite:
    """The scenery of a Building level: obstacles from level 1 on."""
    return ConstructionSite(extent, obstacles=level >= 1)


# Extents, counts, sizes and keep-outs: the reference's Goal, Button and Push levels (reference section 6).
BUILDING_GOAL_LEVELS = {
    0: lambda: BuildingGoalTask(0, extents=1.0, objects=[DockingGoal(keepout=0.305)], scenery=site(1.0, 0)),
    1: lambda: BuildingGoalTask(1, extents=1.5, objects=[
        DockingGoal(keepout=0.305), RestrictedAreas(8, keepout=0.18), FuelDrums(1, constrained=False)],
        scenery=site(1.5, 1)),
    2: lambda: BuildingGoalTask(2, extents=2.0, objects=[
        DockingGoal(keepout=0.305), RestrictedAreas(10, keepout=0.18), FuelDrums(10)], scenery=site(2.0, 2)),
}

BUILDING_BUTTON_LEVELS = {
    0: lambda: BuildingButtonTask(0, extents=1.0, objects=[Machines(4, constrained=False), GoalMarker()],
                                  scenery=site(1.0, 0)),
    1: lambda: BuildingButtonTask(1, extents=1.5, objects=[
        Machines(4), GoalMarker(), RestrictedAreas(4, keepout=0.18), SiteRobots(4)], scenery=site(1.5, 1)),
    2: lambda: BuildingButtonTask(2, extents=1.8, objects=[
        Machines(4), GoalMarker(), RestrictedAreas(8, keepout=0.18), SiteRobots(6)], scenery=site(1.8, 2)),
}

BUILDING_PUSH_LEVELS = {
    0: lambda: BuildingPushTask(0, extents=1.0, objects=[DockingGoal(), Crate()], scenery=site(1.0, 0)),
    1: lambda: BuildingPushTask(1, extents=1.5, objects=[
        DockingGoal(), RestrictedAreas(2, size=0.3, keepout=0.4), Columns(1, constrained=False), Crate()],
        scenery=site(1.5, 1)),
    2: lambda: BuildingPushTask(2, extents=2.0, objects=[
        DockingGoal(), RestrictedAreas(4, size=0.3, keepout=0.4), Columns(4), Crate()], scenery=site(2.0, 2)),
}
