"""Batched quaternion helpers for the Shadow-Hand tasks (MuJoCo's ``(w, x, y, z)`` order).

Isaac Gym stores quaternions as ``(x, y, z, w)``; the formulas of the paper's reward
(``2 asin(min(|vector part of q_object * conj(q_goal)|, 1))``) are order-independent once the
vector part is taken from the right slots, which is all these helpers do differently.
"""

from __future__ import annotations

import numpy as np

__all__ = ["quat_conjugate", "quat_multiply", "rotation_distance", "random_quaternion"]


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """``conj(q)`` for ``(..., 4)`` quaternions ``(w, x, y, z)``."""
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The Hamilton product ``a * b`` of ``(..., 4)`` quaternions ``(w, x, y, z)``."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        axis=-1,
    )


def rotation_distance(q_object: np.ndarray, q_goal: np.ndarray) -> np.ndarray:
    """The paper's rotation distance ``d_r = 2 asin(min(|vec(q_object * conj(q_goal))|, 1))``, radians, ``(...)``.

    For unit quaternions it is the angle of the rotation taking the goal orientation to the
    object's, in [0, pi].
    """
    difference = quat_multiply(q_object, quat_conjugate(q_goal))
    return 2.0 * np.arcsin(np.minimum(np.linalg.norm(difference[..., 1:], axis=-1), 1.0))


def random_quaternion(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed unit quaternion ``(4,)`` (normalised 4-D Gaussian), ``w >= 0``."""
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q
