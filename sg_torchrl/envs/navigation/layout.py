"""Layout sampling (reference section 6), vectorised with numpy.

Items are placed one by one in a fixed order: the agent (the agents, one after the other, in a
multi-agent task), then every object instance in world order
(:func:`~sg_torchrl.envs.navigation.world.world_order`; ``hazard0, hazard1, ...``). For each
item up to 100 candidate points are drawn uniformly from its region (the task extents shrunk by
the item's keep-out, or one of its ``placements`` rectangles, shrunk the same way and chosen with
probability proportional to area, or its fixed location); the first candidate whose distance to
every placed item is at least ``own keepout + other keepout`` is taken. If an item finds none,
the whole layout is redrawn, up to 10000 times. Then one yaw per agent and one yaw per object
instance are drawn uniformly in ``[0, 2 pi)``.

The 100 candidates of every item are drawn in one generator call per layout attempt and tested
against all placed items at once, so a layout costs a few numpy operations per item. Drawing all
100 at once and taking the first valid one has the same distribution as drawing one at a time
until one is valid. When the first attempt fails, the next ones are tried 32 at a time (the first
success of the batch is taken: the same distribution as one at a time), which keeps crowded levels
such as Button's fast. All randomness comes from the generator passed in: the simulator's own.

Impossible layouts are refused early. At construction: the items placed in the task's extents are
disks of their keep-out radius that may not overlap and lie inside the extents, so if their areas add
up to more than the extents' area no layout exists (:class:`LayoutError` names the object that no
longer fits). A layout that is possible on paper but too crowded to be drawn fails at the first reset,
after :data:`LAYOUT_TRIES` attempts, naming the object whose placement failed most often.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sg_torchrl.envs.navigation.objects.base import NavObject

__all__ = ["LayoutError", "LayoutSampler", "Region"]

CANDIDATES = 100  # candidate points per item and attempt
LAYOUT_TRIES = 10_000  # whole-layout redraws before giving up
BATCH = 32  # layout attempts tried at once after a first failed attempt
_PREFIX = 4  # candidates tested first in a batch (the rest only for attempts where none of these fits)
RESAMPLE_TRIES = 10_000  # candidate points when re-placing one item mid-episode


class LayoutError(RuntimeError):
    """No valid layout (or re-placement) was found within the retry budget."""


@dataclass(frozen=True)
class Region:
    """Where one item may be placed: rectangles ``(R, 4)`` already shrunk by its keep-out, and their weights."""

    rects: np.ndarray
    probs: np.ndarray

    @classmethod
    def make(cls, rects: np.ndarray, keepout: float, fixed: bool = False) -> Region:
        rects = np.asarray(rects, dtype=np.float64).reshape(-1, 4)
        if not fixed:
            rects = rects + np.array([keepout, keepout, -keepout, -keepout])
            rects = rects[(rects[:, 0] <= rects[:, 2]) & (rects[:, 1] <= rects[:, 3])]
            if not len(rects):
                raise ValueError(f"no placement rectangle leaves room for keep-out {keepout}")
        areas = (rects[:, 2] - rects[:, 0]) * (rects[:, 3] - rects[:, 1])
        probs = areas / areas.sum() if areas.sum() > 0 else np.full(len(rects), 1.0 / len(rects))
        return cls(rects, probs)

    def draw(self, rng: np.random.Generator, count: int) -> np.ndarray:
        """``count`` points ``(count, 2)`` drawn uniformly over the region."""
        u = rng.random((count, 2))
        if len(self.rects) == 1:
            rect = self.rects[0]
            return rect[:2] + u * (rect[2:] - rect[:2])
        rects = self.rects[rng.choice(len(self.rects), size=count, p=self.probs)]
        return rects[:, :2] + u * (rects[:, 2:] - rects[:, :2])


class LayoutSampler:
    """Samples layouts for one task level (see the module docstring).

    Args:
        extents: ``(xmin, ymin, xmax, ymax)`` of the default placement area.
        agent_keepout: the agent's keep-out radius.
        objects: the task objects, in world order.
        agent_placements: rectangles for the agent (default: the extents).
        num_agents: number of agents (robots), items ``0 .. num_agents - 1``, all placed with the
            agent's keep-out and placements.
        label: what the layout belongs to, for error messages (``"task 'Goal'"``).

    Raises:
        LayoutError: the items placed in the extents cannot fit in them (module docstring).

    Attributes:
        slices: item range of each object in the layout arrays (the agents come first: item 0, ...).
        keepouts: ``(M,)`` keep-out radius per item.
    """

    def __init__(
        self,
        extents: Sequence[float],
        agent_keepout: float,
        objects: Sequence[NavObject],
        agent_placements: np.ndarray | None = None,
        num_agents: int = 1,
        label: str = "layout",
    ) -> None:
        if num_agents < 1:
            raise ValueError(f"num_agents must be >= 1, got {num_agents}")
        extents = np.asarray(extents, dtype=np.float64).reshape(1, 4)
        self.objects = list(objects)
        self.num_agents = int(num_agents)
        agent_rects = extents if agent_placements is None else agent_placements
        regions = [Region.make(agent_rects, agent_keepout)] * self.num_agents
        keepouts = [agent_keepout] * self.num_agents
        self.slices: dict[int, slice] = {}
        for obj in self.objects:
            start = len(regions)
            for i in range(obj.num):
                if i < len(obj.locations):
                    location = obj.locations[i]
                    regions.append(Region.make(np.r_[location, location], obj.keepout, fixed=True))
                else:
                    regions.append(Region.make(extents if obj.placements is None else obj.placements, obj.keepout))
                keepouts.append(obj.keepout)
            self.slices[id(obj)] = slice(start, len(regions))
        self.regions = regions
        self.keepouts = np.array(keepouts)
        self.size = len(regions)
        self.label = label
        # Who each item is, for error messages: "the agent", "hazards (instance 3 of 8)".
        self._item_names = ["the agent"] * self.num_agents + [
            f"{obj.name} (instance {i + 1} of {obj.num})" for obj in self.objects for i in range(obj.num)]
        self._check_room(extents[0], agent_placements is None)
        self._failures = np.zeros(self.size, dtype=np.int64)  # per item: layout attempts it ended (sample)
        # Squared minimum distances between items, and the items whose region is one rectangle
        # (their candidates are an affine map of one shared uniform draw).
        self._min_d2 = np.square(self.keepouts[:, None] + self.keepouts[None, :])
        simple = [len(r.rects) == 1 for r in regions]
        self._simple = np.array(simple)
        lows = np.array([r.rects[0, :2] for r in regions])
        self._low = lows
        self._span = np.array([r.rects[0, 2:] for r in regions]) - lows

    def _check_room(self, extents: np.ndarray, agent_in_extents: bool) -> None:
        """Raise :class:`LayoutError` when the disks of the items placed in ``extents`` outgrow its area."""
        area = (extents[2] - extents[0]) * (extents[3] - extents[1])
        used = 0.0
        in_extents = [agent_in_extents] * self.num_agents + [
            obj.placements is None and i >= len(obj.locations) for obj in self.objects for i in range(obj.num)]
        for item, placed_in_extents in enumerate(in_extents):
            if placed_in_extents:
                used += np.pi * self.keepouts[item] ** 2
                if used > area:
                    raise LayoutError(
                        f"{self.label}: {self._item_names[item]} does not fit: the keep-out disks of the items "
                        f"placed so far cover {used:.3g} m^2, more than the {area:.3g} m^2 of the extents "
                        f"{tuple(float(e) for e in extents)}; use fewer or smaller objects (keepout), or larger extents")

    def slice_of(self, obj: NavObject) -> slice:
        return self.slices[id(obj)]

    def sample(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """One layout: positions ``(M, 2)`` and yaws ``(M,)`` (the agents first)."""
        size = self.size
        xy = np.empty((size, 2))
        if not self._place_all(self._draw_candidates(rng), xy):
            # A crowded level (Button: gremlins need 0.8 m from each other, the agent and the goal)
            # rejects most attempts: try the next ones BATCH at a time, all at once.
            for start in range(1, LAYOUT_TRIES, BATCH):
                placed = self._place_batch(rng, min(BATCH, LAYOUT_TRIES - start))
                if placed is not None:
                    xy[:] = placed
                    break
            else:
                worst = int(self._failures.argmax())
                raise LayoutError(f"{self.label}: no valid layout in {LAYOUT_TRIES} attempts; placing "
                                  f"{self._item_names[worst]} failed most often: use fewer or smaller objects "
                                  "(keepout), or larger extents")
        yaw = rng.uniform(0.0, 2.0 * np.pi, size=size)
        return xy, yaw

    def _draw_candidates(self, rng: np.random.Generator) -> np.ndarray:
        """The candidates of one layout attempt, ``(M, CANDIDATES, 2)``."""
        candidates = self._low[:, None, :] + rng.random((self.size, CANDIDATES, 2)) * self._span[:, None, :]
        for item in np.flatnonzero(~self._simple):
            candidates[item] = self.regions[item].draw(rng, CANDIDATES)
        return candidates

    def _place_batch(self, rng: np.random.Generator, attempts: int) -> np.ndarray | None:
        """:meth:`_place_all` for ``attempts`` independent attempts at once; the first one that succeeds, or None.

        Taking the first success of a batch of i.i.d. attempts gives the same layout distribution as
        trying them one after another. Candidates are drawn as they are needed: the first
        :data:`_PREFIX` of an item for every attempt still going, the other ones only for the
        attempts where none of those fits.
        """
        xy = np.empty((attempts, self.size, 2))
        xy[:, 0] = self.regions[0].draw(rng, attempts)  # the first agent: its first candidate always fits
        alive = np.arange(attempts)  # attempts that placed every item so far
        for item in range(1, self.size):
            count, region = len(alive), self.regions[item]
            placed, min_d2 = xy[alive, None, :item], self._min_d2[item, :item]
            candidates = region.draw(rng, count * _PREFIX).reshape(count, _PREFIX, 2)
            first = self._first_valid(candidates, placed, min_d2)
            chosen = candidates[np.arange(count), first]
            retry = np.flatnonzero(first < 0)
            if len(retry):
                more = region.draw(rng, len(retry) * (CANDIDATES - _PREFIX)).reshape(len(retry), -1, 2)
                rest = self._first_valid(more, placed[retry], min_d2)
                first[retry] = rest
                chosen[retry] = more[np.arange(len(retry)), rest]
            found = first >= 0
            self._failures[item] += count - np.count_nonzero(found)
            alive = alive[found]
            if not len(alive):
                return None
            xy[alive, item] = chosen[found]
        return xy[alive[0]]

    @staticmethod
    def _first_valid(candidates: np.ndarray, placed: np.ndarray, min_d2: np.ndarray) -> np.ndarray:
        """Per attempt, the index of the first of ``candidates`` ``(A, C, 2)`` at least ``sqrt(min_d2)`` from
        every ``placed`` item ``(A, 1, K, 2)``, or -1, ``(A,)``."""
        dx = candidates[:, :, None, 0] - placed[..., 0]  # (A, C, K); x and y apart: 4x faster than one (A, C, K, 2)
        dy = candidates[:, :, None, 1] - placed[..., 1]
        dx *= dx
        dy *= dy
        dx += dy
        valid = (dx >= min_d2).all(axis=2)
        first = valid.argmax(axis=1)
        return np.where(valid[np.arange(len(first)), first], first, -1)

    def _place_all(self, candidates: np.ndarray, xy: np.ndarray) -> bool:
        """Place items in order, each at its first candidate clear of the ones placed before it.

        The first :data:`_PREFIX` candidates of an item are tested on their own and the rest only
        when none of those fits: the chosen candidate is the same, at a fraction of the work
        (resets of a sparse level test a handful of points per item, not all of them).
        """
        xy[0] = candidates[0, 0]
        for item in range(1, self.size):
            placed, min_d2 = xy[:item], self._min_d2[item, :item]
            for chunk in (candidates[item, :_PREFIX], candidates[item, _PREFIX:]):
                dx = chunk[:, None, 0] - placed[:, 0]  # (C, item)
                dy = chunk[:, None, 1] - placed[:, 1]
                valid = (dx * dx + dy * dy >= min_d2).all(axis=1)
                first = int(valid.argmax())
                if valid[first]:
                    xy[item] = chunk[first]
                    break
            else:
                self._failures[item] += 1
                return False
        return True

    def resample(self, rng: np.random.Generator, item: int, others_xy: np.ndarray, others_keepout: np.ndarray,
                 tries: int = RESAMPLE_TRIES) -> np.ndarray | None:
        """A new position for ``item`` against other items at ``others_xy`` (``(K, 2)``) with ``others_keepout``.

        Draws up to ``tries`` candidates from the item's region, :data:`CANDIDATES` at a time;
        returns the first valid one, or ``None`` if none is.
        """
        min_d2 = np.square(self.keepouts[item] + others_keepout)
        region = self.regions[item]
        for _ in range(-(-tries // CANDIDATES)):
            candidates = region.draw(rng, CANDIDATES)
            delta = candidates[:, None, :] - others_xy[None, :, :]
            valid = (np.einsum("cki,cki->ck", delta, delta) >= min_d2).all(axis=1)
            first = int(valid.argmax())
            if valid[first]:
                return candidates[first]
        return None
