"""Race: drive along a village road from a fixed start to a fixed goal (reference sections 4-6).

Numbers from Safety-Gymnasium's Race levels (its placement unit is 3.5 m, written out here):

* floor half-size 17.5, 500 steps; the robot starts in a small fixed rectangle (keep-out 0, any
  heading): centre ``(-2.275, 1.05)``, 0.175 x 0.35 m at levels 0-1; centre ``(-2.275, -2.8)``,
  0.175 m square at level 2 (farther, round a corner of the road);
* the goal (radius 0.3) is always at ``(3.15, 1.05)``; reward ``(d_prev - d) + 10 [d <= 0.3]``
  clipped to +-11; reaching it **ends the episode** (no new goal);
* levels 1-2 add 7 hazards (radius 0.2625, keep-out 0.165) drawn from 7 fixed rectangles along the
  road (a slalom: alternately 0.315 m below and above its middle line), and make contact with the
  scenery cost: ``static_geoms_contact`` = number of robot-scenery contacts (coefficient 1).

Scenery (:mod:`~sg_torchrl.envs.navigation.scenery`): a grey road on a checkered grass floor, with
houses, trees and rocks beside it, present at every level (as the reference's village is) and
costly from level 1; level 2 adds the props along its extra stretch of road. The reference's props
are meshes it does not ship; here they are primitives at positions chosen to line the road (our
choice, not the reference's). Observation: the robot's sensors, then ``goal_lidar``, then
``hazards_lidar`` at levels 1-2 (scenery is not observed, as in the reference): Point 28 / 44 / 44.
"""

from __future__ import annotations

from functools import partial
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from sg_torchrl.envs.navigation.objects import Goal, Hazards
from sg_torchrl.envs.navigation.scenery import Prop, RoadSegment, Scenery
from sg_torchrl.envs.navigation.tasks.goal import GoalTask

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.env import NavigationEnv

__all__ = ["RACE_LEVELS", "RaceTask", "village"]

UNIT = 3.5  # the reference's placement unit (its "palcement_cal_factor")
GOAL_XY = (0.9 * UNIT, 0.3 * UNIT)
START = {0: (-0.65 * UNIT, 0.3 * UNIT, 0.05 * UNIT, 0.1 * UNIT),  # centre x, y, width, length
         1: (-0.65 * UNIT, 0.3 * UNIT, 0.05 * UNIT, 0.1 * UNIT),
         2: (-0.65 * UNIT, -0.8 * UNIT, 0.05 * UNIT, 0.05 * UNIT)}
HAZARD_RECTS = [(UNIT * (-0.45 + 0.2 * i) - 0.3, UNIT * (0.3 - 0.09 * (-1) ** i) - 0.35,
                 UNIT * (-0.45 + 0.2 * i) + 0.3, UNIT * (0.3 - 0.09 * (-1) ** i) + 0.35) for i in range(7)]


def start_rect(level: int) -> tuple[float, float, float, float]:
    """The robot's start rectangle ``(xmin, ymin, xmax, ymax)`` at ``level``."""
    x, y, width, length = START[level]
    return (x - width / 2, y - length / 2, x + width / 2, y + length / 2)


def village(level: int) -> Scenery:
    """The road and roadside props of a Race level (module docstring)."""
    road = [RoadSegment(-2.9, 0.15, 3.8, 1.95)]  # east-west, through the start and the goal
    props = [Prop("house", -1.6, 2.9), Prop("house", 0.6, 2.9), Prop("house", 2.8, 2.9),
             Prop("tree", -0.5, 2.6), Prop("tree", 1.7, 2.6), Prop("tree", 3.8, 2.6),
             Prop("tree", -0.9, -0.5), Prop("tree", 1.1, -0.5), Prop("tree", 3.1, -0.5),
             Prop("rock", 0.1, -0.35), Prop("rock", 2.1, -0.35),
             Prop("house", -3.7, 1.05), Prop("rock", 4.4, 1.05)]
    if level >= 2:  # the stretch from the far start up to the east-west road
        road.append(RoadSegment(-2.875, -3.4, -1.675, 0.15))
        props += [Prop("house", -3.6, -2.6), Prop("house", -3.6, -0.6), Prop("tree", -3.3, -1.6),
                  Prop("tree", -1.1, -2.9), Prop("rock", -1.2, -1.8)]
    return Scenery(props, road)


class RaceTask(GoalTask):
    """Reach one fixed goal; the episode ends there (module docstring).

    Args:
        level, extents, objects, agent_placements, agent_keepout: as :class:`Task`.
        scenery: the road and props.
        scenery_cost: charge robot-scenery contacts as ``static_geoms_contact``.
    """

    name: ClassVar[str] = "Race"
    max_episode_steps: ClassVar[int] = 500
    floor_half_size: ClassVar[float] = 17.5
    reward_clip: ClassVar[float | None] = 11.0

    def __init__(self, level: int, *, scenery: Scenery, scenery_cost: bool, **options) -> None:
        super().__init__(level, **options)
        self.scenery = scenery
        self.scenery_cost = scenery_cost

    def bind(self, env: NavigationEnv) -> None:
        super().bind(env)
        self.scenery.bind(env.scene.model)

    def next_goal(self, env: NavigationEnv, index: int) -> bool:
        """No new goal: reaching it ends the episode."""
        return False

    @property
    def cost_names(self) -> tuple[str, ...]:
        return ("static_geoms_contact",) if self.scenery_cost else ()

    def agent_costs(self, env: NavigationEnv, out: dict[str, np.ndarray]) -> None:
        if self.scenery_cost:
            for agent, view in enumerate(env.scene.views):
                out["static_geoms_contact"][:, agent] = self.scenery.robot_contacts(view)


def race_level(level: int) -> RaceTask:
    """A fresh Race task at ``level`` (0, 1, 2)."""
    if level not in START:
        raise ValueError(f"Race has levels 0, 1, 2, got {level}")
    objects = [Goal(size=0.3, keepout=0.305, reward_goal=10.0, locations=[GOAL_XY])]
    if level >= 1:
        objects.append(Hazards(7, size=0.075 * UNIT, keepout=0.165, placements=HAZARD_RECTS))
    # extents: unused (every item has a fixed location or its own rectangles)
    return RaceTask(level, extents=1.0, objects=objects, agent_placements=[start_rect(level)], agent_keepout=0.0,
                    scenery=village(level), scenery_cost=level >= 1)


RACE_LEVELS = {level: partial(race_level, level) for level in range(3)}
