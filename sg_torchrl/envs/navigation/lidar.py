"""Pseudo-lidar (reference section 2), vectorised over simulators and objects.

For each target, its position relative to the robot is expressed in the robot's frame (the
world offset ``(dx, dy, -z_robot)`` times the robot's rotation matrix, i.e. rotated into the body
frame), giving an angle (``atan2`` mod 2 pi) and a planar distance ``d``. 16 bins cover the full
circle: bin 0 starts at the robot's forward (+x) axis and bins go counter-clockwise. A target reads
``max(0, max_dist - d) / max_dist`` (linear mode; ``exp(-exp_gain * d)`` when ``max_dist`` is None)
in its bin; every bin keeps the maximum over targets. With aliasing, a target at fraction ``a`` of
the way through its bin also gives ``a * reading`` to the next bin (counter-clockwise) and
``(1 - a) * reading`` to the previous one. Computed from centre positions, not ray casts.

Options (off by default, so observation sizes stay the reference's; ``sg_torchrl.make(id, lidar=...,
compass=...)``):

* ``lidar="natural"`` (:class:`NaturalLidar`): ray casting. Per lidar group, one horizontal ray per
  bin (bin ``i`` at ``i * 2 pi / 16`` counter-clockwise from the robot's heading, as in the
  reference's unused natural mode) from the robot's position at the group's height, so flat
  objects such as hazards and the Circle zone are seen too; a ray sees only its group's geoms and
  reads the same function of the distance to the first surface it hits as the pseudo-lidar does of
  the distance to a centre (no aliasing). Same size as the pseudo-lidar.
* ``compass=True`` (:func:`compass_vector`): a ``<name>_comp`` entry of 2 values, the unit vector to the
  target in the robot frame (normalised by ``norm + 0.001``), after the ``<name>_lidar`` entry of
  each goal-like object (``NavObject.compass_target``: the goal). +2 values per such object, e.g.
  SafetyPointGoal1-v0 62.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Literal

import mujoco
import numpy as np

if TYPE_CHECKING:
    from sg_torchrl.envs.navigation.objects.base import NavObject
    from sg_torchrl.envs.navigation.world import Scene

__all__ = ["LidarMode", "NaturalLidar", "compass_vector", "lidar_block", "pseudo_lidar", "pseudo_lidars",
           "pseudo_lidars_one", "egocentric_xy"]

LidarMode = Literal["pseudo", "natural"]

TWO_PI = 2.0 * np.pi


def egocentric_xy(agent_pos: np.ndarray, agent_mat: np.ndarray, targets_xy: np.ndarray) -> np.ndarray:
    """Targets ``(N, K, 2)`` in each robot frame (``agent_pos`` ``(N, 3)``, ``agent_mat`` ``(N, 3, 3)``).

    The world offset ``(dx, dy, -z_robot)`` (targets at z = 0) as a row vector times the first two
    columns of the body-to-world matrix, i.e. rotated into the body frame: ``x_j = dx m0j + dy m1j +
    dz m2j``, summed in that order (``np.einsum``'s order, so the values are the same bit for bit),
    in five array operations whatever ``K`` (a one-simulator step is mostly per-operation
    overhead, and einsum's own is several of them).
    """
    delta = targets_xy - agent_pos[:, None, :2]  # (N, K, 2): dx, dy
    products = delta[..., None] * agent_mat[:, None, :2, :2]  # (N, K, 2, 2): d_i m_ij
    lift = agent_pos[:, 2, None, None] * agent_mat[:, 2, None, :2]  # (N, 1, 2): -dz m_2j (exact negation)
    return products[..., 0, :] + products[..., 1, :] - lift  # x + (-z m) and x - z m: the same IEEE value


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
    if out is None:
        out = np.empty((targets_xy.shape[0], num_bins))
    pseudo_lidars(agent_pos, agent_mat, [targets_xy], [out], num_bins=num_bins, max_dist=max_dist,
                  exp_gain=exp_gain, alias=alias)
    return out


def pseudo_lidars(
    agent_pos: np.ndarray,
    agent_mat: np.ndarray,
    groups: Sequence[np.ndarray],
    outs: Sequence[np.ndarray] | np.ndarray,
    *,
    num_bins: int = 16,
    max_dist: float | None = 3.0,
    exp_gain: float = 1.0,
    alias: bool = True,
) -> None:
    """:func:`pseudo_lidar` of several target groups (``(N, K_g, 2)`` each) seen from the same robots,
    readings written to ``outs``: one ``(N, num_bins)`` array per group, or one ``(N, G, num_bins)``
    array holding them all (e.g. a view of the observation columns where the groups' readings follow
    each other: :func:`lidar_block`).

    Why: every lidar group of an observation is seen from the same robot pose, so the targets of all
    groups go through the frame change, distances, angles and bin writes together (one pass of
    array operations instead of one per group, which is most of a one-simulator navigation step);
    only the per-bin maximum is taken per group (into a block: one ``np.maximum.reduceat`` over all
    groups, the same maxima). Each target's values do not depend on the others, so every group reads
    as it would alone.
    """
    sizes = [targets.shape[1] for targets in groups]
    total = sum(sizes)
    block = outs if isinstance(outs, np.ndarray) else None
    if total == 0:
        for out in (outs if block is None else [block]):
            out[...] = 0.0
        return
    targets_xy = groups[0] if len(groups) == 1 else np.concatenate(groups, axis=1)
    n, k = targets_xy.shape[:2]
    ego = egocentric_xy(agent_pos, agent_mat, targets_xy)
    distance = np.hypot(ego[..., 0], ego[..., 1])
    angle = np.arctan2(ego[..., 1], ego[..., 0]) % TWO_PI
    position = angle * (num_bins / TWO_PI)  # in bins
    bins = np.minimum(position.astype(np.int64), num_bins - 1)  # angles a hair below 2 pi round up to 2 pi
    reading = _reading(distance, max_dist, exp_gain)
    # Every target writes three distinct bins of its own row; the per-bin maximum over targets is taken after.
    # The writes go through flat indices (row and target offsets computed once per shape): cheaper than
    # indexing with three broadcast index arrays, and the same elements get the same values. (Measured: one
    # assignment of all three bins, through (N, K, 3) index and value arrays, is slower than three.)
    contributions = np.zeros((n, k, num_bins))
    flat, offsets = contributions.reshape(-1), _target_offsets(n, k, num_bins)
    if alias:
        # np.clip(position - bins, 0, 1): position >= 0 (a remainder by 2 pi) and bins <= position, so the
        # difference is >= +0.0 (and NaN stays NaN either way): only the upper bound can bite.
        fraction = np.minimum(position - bins, 1.0)
        flat[offsets + (bins + 1) % num_bins] = fraction * reading
        flat[offsets + (bins - 1) % num_bins] = (1.0 - fraction) * reading
    flat[offsets + bins] = reading
    if block is not None and all(sizes):
        np.maximum.reduceat(contributions, _group_starts(tuple(sizes)), axis=1, out=block)
        return
    if block is not None:
        outs = [block[:, g] for g in range(block.shape[1])]
    start = 0
    for size, out in zip(sizes, outs):
        if size:
            contributions[:, start : start + size].max(axis=1, out=out)
        else:
            out[:] = 0.0
        start += size


def pseudo_lidars_one(
    agent_pos: np.ndarray,
    agent_mat: np.ndarray,
    groups: Sequence[np.ndarray],
    out: np.ndarray,
    *,
    num_bins: int = 16,
    max_dist: float | None = 3.0,
) -> bool:
    """:func:`pseudo_lidars` of one simulator (``agent_pos`` ``(1, 3)``, ``agent_mat`` ``(1, 3, 3)``, groups
    ``(1, K_g, 2)``), aliased, into ``out``: the ``(G * num_bins,)`` row of every group's readings one after
    the other (a view of the observation). Returns whether it applied; when it did not (exponential
    readings, fewer than 3 bins, or a frame change that is not finite), ``out`` is untouched and the caller
    runs :func:`pseudo_lidars`.

    Why a second form: at one simulator the array form's thirty-odd numpy calls on a dozen targets cost
    more than the arithmetic. Here the frame change is the same float64 products, sums and differences
    in :func:`egocentric_xy`'s order on Python floats; the distance and the angle stay numpy's
    (``np.hypot``, ``np.arctan2``: their rounding may differ from :mod:`math`'s), one call each over all
    targets. The angle's remainder by 2 pi is Python's float ``%``: CPython's ``float_rem`` and numpy's
    ``npy_divmod`` (its float ``remainder`` loop) are the same steps, C's ``fmod``, then ``+ 2 pi`` for a
    negative non-zero result and ``+0.0`` for a zero one (``-0.0`` included). Bins, fractions and
    readings are the same IEEE operations on floats
    (``int`` truncates a non-negative position as ``astype`` does; ``min``/``max`` of non-NaN values are
    ``np.minimum``/``np.maximum``'s). Every contribution is ``+0.0`` or positive, so keeping each bin's
    largest as it comes is the array form's maximum over targets, and a target beyond ``max_dist`` reads
    0 and adds nothing. The three bins of a target are distinct from 3 bins on (with fewer, the array
    form's later writes overwrite earlier ones, which a maximum does not reproduce: not covered).
    """
    if max_dist is None or num_bins < 3:
        return False
    px, py, pz = agent_pos[0].tolist()
    (m00, m01, _), (m10, m11, _), (m20, m21, _) = agent_mat[0].tolist()
    lift0, lift1 = pz * m20, pz * m21
    xs: list[float] = []
    ys: list[float] = []
    bases: list[int] = []  # per target, its group's first bin in the row
    for group, targets in enumerate(groups):
        for tx, ty in targets[0].tolist():
            dx = tx - px
            dy = ty - py
            xs.append(dx * m00 + dy * m10 - lift0)
            ys.append(dx * m01 + dy * m11 - lift1)
            bases.append(group * num_bins)
    row = [0.0] * (len(groups) * num_bins)
    if xs:
        x, y = np.array(xs), np.array(ys)  # two flat arrays: cheaper than one (2, K) array and its rows
        distances = np.hypot(x, y).tolist()
        # A non-finite x or y makes its distance inf or NaN (hypot(inf, NaN) is inf); an overflowing sum of
        # finite distances declines too, harmlessly.
        if not math.isfinite(sum(distances)):
            return False
        scale, last = num_bins / TWO_PI, num_bins - 1
        for distance, angle, base in zip(distances, np.arctan2(y, x).tolist(), bases):
            margin = max_dist - distance
            if margin > 0.0:  # else the reading is 0.0 in every bin: nothing to keep
                reading = margin / max_dist
                position = (angle % TWO_PI) * scale
                bin_ = int(position)
                if bin_ > last:  # an angle a hair below 2 pi rounds up to 2 pi
                    bin_ = last
                fraction = position - bin_
                if fraction > 1.0:
                    fraction = 1.0
                index = base + bin_
                if reading > row[index]:
                    row[index] = reading
                index = base + (bin_ + 1) % num_bins
                value = fraction * reading
                if value > row[index]:
                    row[index] = value
                index = base + (bin_ - 1) % num_bins
                value = (1.0 - fraction) * reading
                if value > row[index]:
                    row[index] = value
    out[:] = row
    return True


@functools.lru_cache(maxsize=64)
def _target_offsets(n: int, k: int, num_bins: int) -> np.ndarray:
    """Flat index of bin 0 of each target's row in an ``(n, k, num_bins)`` array, ``(n, k)`` (read-only)."""
    offsets = np.arange(n * k, dtype=np.int64).reshape(n, k) * num_bins
    offsets.flags.writeable = False
    return offsets


@functools.lru_cache(maxsize=64)
def _group_starts(sizes: tuple[int, ...]) -> np.ndarray:
    """Index of each group's first target among all targets (``np.maximum.reduceat``'s), read-only."""
    starts = np.cumsum((0, *sizes[:-1]), dtype=np.intp)
    starts.flags.writeable = False
    return starts


def lidar_block(observation: np.ndarray, parts: Sequence[slice], num_bins: int) -> np.ndarray | None:
    """The ``(N, G, num_bins)`` view of ``observation``'s lidar columns ``parts`` (``G`` slices of
    ``num_bins`` columns) when they follow each other, for :func:`pseudo_lidars`; else ``None``."""
    if not parts or any(part.stop - part.start != num_bins for part in parts) or any(
            a.stop != b.start for a, b in zip(parts, parts[1:])):
        return None
    columns = observation[:, parts[0].start : parts[-1].stop]
    block = columns.view()
    block.shape = (columns.shape[0], len(parts), num_bins)  # raises rather than copy: it must stay a view
    return block


def _reading(distance: np.ndarray, max_dist: float | None, exp_gain: float) -> np.ndarray:
    if max_dist is None:
        return np.exp(-exp_gain * distance)
    return np.maximum(0.0, max_dist - distance) / max_dist


def compass_vector(
    agent_pos: np.ndarray, agent_mat: np.ndarray, target_xy: np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    """Unit vectors ``(N, 2)`` from each robot to ``target_xy`` (``(N, 2)``) in the robot frame.

    The egocentric offset (as for the lidar) divided by its norm + 0.001, as the reference does.
    """
    ego = egocentric_xy(agent_pos, agent_mat, target_xy[:, None, :])[:, 0]
    norm = np.hypot(ego[:, 0], ego[:, 1])
    return np.divide(ego, (norm + 0.001)[:, None], out=out)


class NaturalLidar:
    """Ray-cast lidar for the lidar groups of one world (see the module docstring).

    Each ray only sees the geoms of its own group: group ``g`` (1 to 5, in observation order) of the
    world's geom groups holds exactly the geoms of the ``g``-th observed object (its
    ``geom_mask``) and every other geom is moved to group 0. Built with ``lidar="natural"``, a
    world gets its own compiled model (the env adds the mode to the cache key), so this never
    changes the model of a pseudo-lidar env. Renderers show geom groups 0-2 by default: enable
    groups 3-5 (``mjvOption.geomgroup``) to see the later groups of such a world.

    Rays start at the robot's position, at the mean height of the group's geom centres at rest;
    they are horizontal whatever the robot's tilt and ignore geoms beyond ``max_dist``. A ray
    starting inside a geom reads the distance to where it leaves it. Computed per simulator with
    ``mujoco.mj_multiRay`` (one call per group), after refreshing positions with
    ``mj_kinematics`` so that objects moved since the last step (a re-sampled goal) are seen where
    they are now.

    Args:
        scene: the simulators.
        objects: the lidar-observed objects, bound to ``scene``, in observation order.
        num_bins, max_dist, exp_gain: as for :func:`pseudo_lidar`.
    """

    max_groups = mujoco.mjNGROUP - 1  # group 0 holds everything else

    def __init__(self, scene: Scene, objects: Sequence[NavObject], *, num_bins: int = 16,
                 max_dist: float | None = 3.0, exp_gain: float = 1.0) -> None:
        if len(objects) > self.max_groups:
            raise ValueError(f"natural lidar casts at most {self.max_groups} object groups, got {len(objects)}")
        model = scene.model
        groups = np.zeros(model.ngeom, dtype=model.geom_group.dtype)
        for group, obj in enumerate(objects, start=1):
            groups[obj.geom_mask] = group
        model.geom_group[:] = groups
        rest = mujoco.MjData(model)
        mujoco.mj_forward(model, rest)
        self.heights = {id(obj): float(rest.geom_xpos[obj.geom_mask, 2].mean()) for obj in objects}
        self.masks = {id(obj): np.eye(mujoco.mjNGROUP, dtype=np.uint8)[group] for group, obj in enumerate(objects, 1)}
        self.num_bins, self.max_dist, self.exp_gain = num_bins, max_dist, exp_gain
        self.cutoff = mujoco.mjMAXVAL if max_dist is None else float(max_dist)
        self._angles = np.arange(num_bins) * (TWO_PI / num_bins)
        self._directions = np.zeros((scene.num_envs, num_bins, 3))
        self._origins = np.zeros((scene.num_envs, 3))
        self._distance = np.zeros((scene.num_envs, num_bins))
        self._geom_ids = np.zeros(num_bins, dtype=np.int32)

    def prepare(self, scene: Scene) -> None:
        """Refresh geom positions and the ray directions; call once per observation, before :meth:`observe`."""
        model = scene.model
        for data in scene.physics.datas:
            mujoco.mj_kinematics(model, data)
        heading = scene.agent_mat()[:, :2, 0]  # the body x axis, projected on the floor
        yaw = np.arctan2(heading[:, 1], heading[:, 0])[:, None] + self._angles
        self._directions[..., 0] = np.cos(yaw)
        self._directions[..., 1] = np.sin(yaw)
        self._origins[:, :2] = scene.agent_xy()

    def observe(self, scene: Scene, obj: NavObject, out: np.ndarray) -> np.ndarray:
        """Readings ``(N, num_bins)`` of ``obj``'s group, written to ``out``."""
        model, exclude, mask = scene.model, scene.agent_body, self.masks[id(obj)]
        self._origins[:, 2] = self.heights[id(obj)]
        for data, origin, directions, distance in zip(scene.physics.datas, self._origins, self._directions,
                                                      self._distance):
            mujoco.mj_multiRay(model, data, origin, directions.reshape(-1), mask, 1, exclude, self._geom_ids,
                               distance, None, self.num_bins, self.cutoff)
        hit = self._distance >= 0.0
        np.multiply(_reading(self._distance, self.max_dist, self.exp_gain), hit, out=out)
        return out
