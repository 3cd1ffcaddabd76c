"""Task objects (see :mod:`.base`): goal and constraints, each owning placement, geometry and cost."""

from sg_torchrl.envs.navigation.objects.base import FreeObject, NavObject, StaticObject, yaw_quat
from sg_torchrl.envs.navigation.objects.buttons import Buttons, GoalMarker
from sg_torchrl.envs.navigation.objects.circle import CircleZone
from sg_torchrl.envs.navigation.objects.contacts import ContactCost
from sg_torchrl.envs.navigation.objects.goal import AgentGoal, Goal, GoalBlue, GoalRed
from sg_torchrl.envs.navigation.objects.gremlins import Gremlins
from sg_torchrl.envs.navigation.objects.hazards import Hazards
from sg_torchrl.envs.navigation.objects.pillars import Pillars
from sg_torchrl.envs.navigation.objects.push_box import PushBox
from sg_torchrl.envs.navigation.objects.sigwalls import Sigwalls
from sg_torchrl.envs.navigation.objects.vases import Vases
from sg_torchrl.envs.navigation.objects.construction import (Columns, Crate, DockingGoal, FuelDrums, Machines,
                                                             RestrictedAreas, SiteRobots)
from sg_torchrl.envs.navigation.objects.track import Barriers, Fences, TrackSide

__all__ = ["AgentGoal", "Buttons", "CircleZone", "ContactCost", "FreeObject", "Goal", "GoalBlue", "GoalMarker",
           "GoalRed", "Gremlins", "Hazards", "NavObject", "Pillars", "PushBox", "Sigwalls", "StaticObject", "Vases",
           "yaw_quat"]
__all__ += ["Barriers", "Columns", "Crate", "DockingGoal", "Fences", "FuelDrums", "Machines", "RestrictedAreas",
            "SiteRobots", "TrackSide"]
