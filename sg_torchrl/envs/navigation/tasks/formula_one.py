"""FormulaOne: race from checkpoint to checkpoint around a track (Safety-Gymnasium paper, race-track scene).

The paper describes a race track on which the robot starts at one of seven checkpoints and must
reach a goal further along the track, with track-side barriers as constraints; our reference notes
give no numbers, so everything below is our choice (documented here and in the tests):

* **World**: floor half-size 17.5 (like Run and Race), grass with a stadium-shaped asphalt loop
  (:class:`~sg_torchrl.envs.navigation.track.Track`: straights 10 m long, curve radius 4.5 m,
  centre line 48.3 m; width 3 m at levels 0-1, 2.2 m at level 2), kerbs, a start line and
  a white line at each of the 7 checkpoints, evenly spaced along the centre line (6.9 m apart).
* **Start**: the robot starts on one of the 7 checkpoints, drawn uniformly at reset from the
  simulator's generator (keep-out 0), with a uniform heading like every navigation task.
* **Goal**: the next checkpoint in the racing direction (counter-clockwise). Reward as Goal:
  ``(d_prev - d) * 1.0 + 1.0 * [d <= 0.5]`` with ``d`` the planar distance to the goal (radius 0.5,
  larger than Goal's 0.3 since it marks a place across a track); on reaching it the goal moves
  on to the following checkpoint (lap after lap), the episode goes on. Clipped to +-10; 500 steps.
* **Constraints** (levels 1-2): :class:`~sg_torchrl.envs.navigation.objects.track.Barriers` around
  the curves and :class:`~sg_torchrl.envs.navigation.objects.track.Fences` along the straights,
  0.35 m off the asphalt; each contact with one costs (``barriers``, ``fences``). Level 1:
  5 barriers outside each curve, fences outside both straights (20 panels). Level 2: a narrower
  track, 7 barriers outside and 3 inside each curve, fences on both sides of both straights (40).
* **Observation**: robot sensors, ``goal_lidar`` (Point: 28), then ``barriers_lidar``,
  ``fences_lidar`` at levels 1-2 (Point: 60). The asphalt is not observed. Lidar range 8 m
  (the reference's is 3 m, 6 m for Circle): checkpoints are 6.9 m apart, so with 3 m the goal
  would be invisible from the start.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from sg_torchrl.envs.navigation.objects import Barriers, Fences, Goal, NavObject
from sg_torchrl.envs.navigation.scenery import RaceTrackScenery
from sg_torchrl.envs.navigation.tasks.goal import GoalTask
from sg_torchrl.envs.navigation.track import Track

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.env import NavigationEnv

__all__ = ["FORMULA_ONE_LEVELS", "FormulaOneTask", "track_side"]

NUM_CHECKPOINTS = 7
#: how far barriers and fences stand off the asphalt's edge (to their centre line), metres
SIDE_CLEARANCE = 0.35


class FormulaOneTask(GoalTask):
    """Reach the next checkpoint, then the next, around :attr:`track` (see the module docstring).

    Attributes (per simulator):
        start_checkpoint: ``(N,)`` index of the checkpoint the episode started on.
        goal_checkpoint: ``(N,)`` index of the checkpoint the goal is on.
    """

    name: ClassVar[str] = "FormulaOne"
    max_episode_steps: ClassVar[int] = 500
    floor_half_size: ClassVar[float] = 17.5
    lidar_max_dist: ClassVar[float | None] = 8.0

    def __init__(self, level: int, *, track: Track, objects: Sequence[NavObject]) -> None:
        self.track = track
        #: ``(7, 2)`` the checkpoints on the centre line, in racing order
        self.checkpoints = track.checkpoints(NUM_CHECKPOINTS)
        starts = np.concatenate([self.checkpoints, self.checkpoints], axis=1)  # point rectangles, equal odds
        super().__init__(level, extents=self.floor_half_size, objects=objects, agent_placements=starts,
                         agent_keepout=0.0, scenery=RaceTrackScenery(track, num_checkpoints=NUM_CHECKPOINTS))

    def bind(self, env: NavigationEnv) -> None:
        super().bind(env)
        self.start_checkpoint = np.zeros(env.num_envs, dtype=np.int64)
        self.goal_checkpoint = np.zeros(env.num_envs, dtype=np.int64)

    def nearest_checkpoint(self, xy: np.ndarray) -> np.ndarray:
        """Index of the checkpoint nearest to each of ``xy`` ``(..., 2)``."""
        return np.linalg.norm(np.asarray(xy)[..., None, :] - self.checkpoints, axis=-1).argmin(axis=-1)

    def reset(self, env: NavigationEnv, indices: np.ndarray) -> None:
        starts = self.nearest_checkpoint(env.scene.agent_xy()[indices])
        self.start_checkpoint[indices] = starts
        for index, start in zip(indices, starts):
            self._aim(env, int(index), (int(start) + 1) % NUM_CHECKPOINTS)
        super().reset(env, indices)

    def next_goal(self, env: NavigationEnv, index: int) -> bool:
        self._aim(env, index, (int(self.goal_checkpoint[index]) + 1) % NUM_CHECKPOINTS)
        return True

    def _aim(self, env: NavigationEnv, index: int, checkpoint: int) -> None:
        """Put simulator ``index``'s goal on ``checkpoint``."""
        self.goal_checkpoint[index] = checkpoint
        self.goal.move(env.scene, index, 0, self.checkpoints[checkpoint])

    def state_dict(self) -> dict:
        return {**super().state_dict(), "start_checkpoint": self.start_checkpoint.copy(),
                "goal_checkpoint": self.goal_checkpoint.copy()}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.start_checkpoint[:] = state["start_checkpoint"]
        self.goal_checkpoint[:] = state["goal_checkpoint"]


def _straights(track: Track, spacing: float) -> np.ndarray:
    """Arc lengths of panel centres ``spacing`` apart along both straights."""
    h, arc = track.half_straight, np.pi * track.radius
    along = -h + spacing / 2 + spacing * np.arange(int(round(2 * h / spacing)))
    return np.concatenate([along, along + 2 * h + arc])


def _curves(track: Track, count: int) -> np.ndarray:
    """Arc lengths of ``count`` evenly spread points inside each of the two curves."""
    h, arc = track.half_straight, np.pi * track.radius
    along = h + arc * (np.arange(count) + 0.5) / count
    return np.concatenate([along, along + 2 * h + arc])


def track_side(track: Track, arcs: np.ndarray, sides: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Positions ``(K, 2)`` and headings of boxes at ``arcs`` on each of ``sides`` (+1 infield, -1 outside)."""
    positions, headings = [], []
    for side in sides:
        xy, heading = track.edge_line(arcs, side * (track.width / 2 + SIDE_CLEARANCE))
        positions.append(xy)
        headings.append(heading)
    return np.concatenate(positions), np.concatenate(headings)


def _goal() -> Goal:
    # Placed at the infield centre by the layout (far from every checkpoint), then moved by the task.
    return Goal(size=0.5, keepout=0.305, locations=[(0.0, 0.0)])


def _level(level: int) -> FormulaOneTask:
    track = Track(width=2.2 if level == 2 else 3.0)
    objects: list[NavObject] = [_goal()]
    if level == 1:
        objects += [Barriers(*track_side(track, _curves(track, 5), sides=(-1.0,))),
                    Fences(*track_side(track, _straights(track, 1.0), sides=(-1.0,)))]
    elif level == 2:
        outside = track_side(track, _curves(track, 7), sides=(-1.0,))
        inside = track_side(track, _curves(track, 3), sides=(1.0,))
        objects += [Barriers(np.concatenate([outside[0], inside[0]]), np.concatenate([outside[1], inside[1]])),
                    Fences(*track_side(track, _straights(track, 1.0), sides=(-1.0, 1.0)))]
    return FormulaOneTask(level, track=track, objects=objects)


FORMULA_ONE_LEVELS = {level: (lambda level=level: _level(level)) for level in range(3)}
