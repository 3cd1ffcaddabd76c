"""Pseudo-lidar (reference section 2), vectorised over simulators and objects.

For each target, its position relative to the robot is expressed in the robot's frame (the
world offset ``(dx, dy, -z_robot)`` times the robot's rotation matrix, i.e. rotated into the body
frame), giving an angle (``atan2`` mod 2 pi) and a planar distance ``d``. 16 bins cover the full
circle: bin 0 starts at the robot's forward (+x) axis and bins go counter-clockwise. A target reads
``max(0, max_dist - d) / max_dist`` (linear mode; ``exp(-exp_gain * d)`` when ``max_dist`` is None)
in its bin; every bin keeps the maximum over targets. With aliasing, a target at fraction ``a`` of
the way through its bin also gives ``a * reading`` to the next bin (counter-clockwise) and
``(1 - a) * reading`` to the previous one. Computed from centre positions, not ray casts.
"""

from __future__ import annotations

import numpy as np

__all__ = ["pseudo_lidar", "egocentric_xy"]

TWO_PI = 2.0 * np.pi


def egocentric_xy(agent_pos: np.ndarray, agent_mat: np.ndarray, targets_xy: np.ndarray) -> np.ndarray:
    """Targets ``(N, K, 2)`` in each robot frame (``agent_pos`` ``(N, 3)``, ``agent_mat`` ``(N, 3, 3)``)."""
    offset = np.empty((*targets_xy.shape[:2], 3))
    offset[..., :2] = targets_xy - agent_pos[:, None, :2]
    offset[..., 2] = -agent_pos[:, None, 2]  # targets are taken at z = 0
    # Row vector times the body-to-world matrix = the world offset rotated into the body frame.
    return np.einsum("nki,nij->nkj", offset, agent_mat[:, :, :2])


def pseudo_lidar(
    agent_pos: np.ndarray,
    agent_mat: np.ndarray,
    targets_xy: np.ndarray,
    *,
    num_bins: int = 16,
    max_dist: float | None = 3.0,
    exp_gain: float = 1.0,
    alias: bool = True,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Lidar readings ``(N, num_bins)`` of ``targets_xy`` (``(N, K, 2)``) seen from each robot.

    ``out`` (``(N, num_bins)``, may be a view into the observation buffer) is filled and returned.
    """
    n, k = targets_xy.shape[:2]
    if out is None:
        out = np.empty((n, num_bins))
    if k == 0:
        out[:] = 0.0
        return out
    ego = egocentric_xy(agent_pos, agent_mat, targets_xy)
    distance = np.hypot(ego[..., 0], ego[..., 1])
    angle = np.arctan2(ego[..., 1], ego[..., 0]) % TWO_PI
    position = angle * (num_bins / TWO_PI)  # in bins
    bins = np.minimum(position.astype(np.int64), num_bins - 1)  # angles a hair below 2 pi round up to 2 pi
    if max_dist is None:
        reading = np.exp(-exp_gain * distance)
    else:
        reading = np.maximum(0.0, max_dist - distance) / max_dist
    # Every target writes three distinct bins of its own row; the per-bin maximum over targets is taken after.
    contributions = np.zeros((n, k, num_bins))
    rows, columns = np.arange(n)[:, None], np.arange(k)[None, :]
    if alias:
        fraction = np.clip(position - bins, 0.0, 1.0)
        contributions[rows, columns, (bins + 1) % num_bins] = fraction * reading
        contributions[rows, columns, (bins - 1) % num_bins] = (1.0 - fraction) * reading
    contributions[rows, columns, bins] = reading
    return contributions.max(axis=1, out=out)
