"""Race-track geometry for FormulaOne: a stadium-shaped loop parametrised by arc length.

The centre line runs counter-clockwise around the origin: the bottom straight ``y = -radius`` from
``x = -half_straight`` to ``+half_straight`` (heading 0), the right half-circle around
``(half_straight, 0)``, the top straight ``y = +radius`` back to ``-half_straight`` (heading pi) and the
left half-circle around ``(-half_straight, 0)``. Arc length ``s = 0`` is the middle of the bottom
straight (the start line); ``s`` grows in the racing direction and wraps at :attr:`Track.length`.
Left of the racing direction is the infield.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Track"]


@dataclass(frozen=True)
class Track:
    """A stadium loop (see the module docstring).

    Args:
        half_straight: half the length of each straight, metres.
        radius: radius of the two half-circles (the straights are ``2 * radius`` apart), metres.
        width: width of the asphalt, metres.
    """

    half_straight: float = 5.0
    radius: float = 4.5
    width: float = 3.0

    @property
    def length(self) -> float:
        """Length of the centre line, metres."""
        return 4.0 * self.half_straight + 2.0 * np.pi * self.radius

    def pose(self, s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Points ``(..., 2)`` of the centre line at arc lengths ``s`` and the racing headings there ``(...)``."""
        s = np.mod(np.asarray(s, dtype=np.float64), self.length)
        h, r = self.half_straight, self.radius
        straight, arc = 2.0 * h, np.pi * r
        # The loop starting at s = 0 (middle of the bottom straight): half a straight, arc, straight, arc, half.
        u = s + h  # distance from the bottom straight's start (-h, -r)
        u = np.where(u >= self.length, u - self.length, u)
        xy = np.empty((*u.shape, 2))
        heading = np.empty(u.shape)
        bottom = u < straight
        right = (u >= straight) & (u < straight + arc)
        top = (u >= straight + arc) & (u < 2 * straight + arc)
        left = u >= 2 * straight + arc
        xy[bottom] = np.stack([-h + u[bottom], np.full(bottom.sum(), -r)], axis=-1)
        heading[bottom] = 0.0
        phi = -np.pi / 2 + (u[right] - straight) / r
        xy[right] = np.stack([h + r * np.cos(phi), r * np.sin(phi)], axis=-1)
        heading[right] = phi + np.pi / 2
        xy[top] = np.stack([h - (u[top] - straight - arc), np.full(top.sum(), r)], axis=-1)
        heading[top] = np.pi
        phi = np.pi / 2 + (u[left] - 2 * straight - arc) / r
        xy[left] = np.stack([-h + r * np.cos(phi), r * np.sin(phi)], axis=-1)
        heading[left] = phi + np.pi / 2
        return xy, np.mod(heading, 2.0 * np.pi)

    @staticmethod
    def offset(xy: np.ndarray, heading: np.ndarray | float, lateral: np.ndarray | float) -> np.ndarray:
        """Points ``lateral`` metres left of ``xy`` (right when negative) across the racing ``heading``."""
        heading = np.asarray(heading, dtype=np.float64)
        normal = np.stack([-np.sin(heading), np.cos(heading)], axis=-1)
        return np.asarray(xy) + np.asarray(lateral, dtype=np.float64)[..., None] * normal

    def checkpoint_arcs(self, count: int) -> np.ndarray:
        """Arc lengths of ``count`` checkpoints evenly spaced around the loop, the first at the start line."""
        return np.arange(count) * self.length / count

    def checkpoints(self, count: int) -> np.ndarray:
        """Positions ``(count, 2)`` of :meth:`checkpoint_arcs` on the centre line."""
        return self.pose(self.checkpoint_arcs(count))[0]

    def edge_line(self, arcs: np.ndarray, lateral: float) -> tuple[np.ndarray, np.ndarray]:
        """Points ``lateral`` metres left of the centre line at ``arcs`` (``(K, 2)``) and the headings there."""
        xy, heading = self.pose(arcs)
        return self.offset(xy, heading, lateral), heading
