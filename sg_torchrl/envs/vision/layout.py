"""Safety-Gymnasium's dict observation of the Vision envs, rebuilt from a TorchRL env's entries.

Why: Safety-Gymnasium 1.0.0's ``Safety...Vision-v0`` observation is a ``gymnasium.spaces.Dict`` that
is not flattened: one entry per vector part, in observation order (``accelerometer``,
``velocimeter``, ``gyro``, ``magnetometer``, the robot's joint entries, then one ``<object>_lidar``
per observed object), each ``float64``, then ``vision``, ``uint8`` ``(256, 256, 3)``. A script
written for it indexes those keys. A TorchRL env keeps the flat ``observation`` (what networks and
transforms take) and ``pixels``; :class:`DictLayout` maps one to the other, with the original's
shapes (a ball joint's orientation ``ballquat_*`` is ``(3, 3)``), bounds (sensors unbounded, lidar in
``[0, 1]``, compass in ``[-1, 1]``) and key order (checked against the original in ``tests/test_vision_fidelity.py``).

Usage, for a navigation env built with an ``obs_mode`` that holds the vector and RGB pixels (the
Vision ids' default, ``"vector+rgb"``)::

    layout = DictLayout.of(env)
    layout.entries        # (("accelerometer", (3,), -inf, inf, "float64"), ..., ("vision", (H, W, 3), 0, 255, "uint8"))
    layout.split(td, 0)   # simulator 0's observation: {"accelerometer": array(...), ..., "vision": array(...)}

``depth`` (RGB-D modes) comes last, ``(H, W, 1)`` ``float32`` metres: the original has no depth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["DictEntry", "DictLayout"]

#: the original's bounds of the task entries, by name suffix (its robot sensors are unbounded); the
#: TorchRL spec of the flat vector is unbounded throughout, so they are restated here
_BOUNDS = {"_lidar": (0.0, 1.0), "_comp": (-1.0, 1.0)}
#: observation terms whose values are a row-major 3 x 3 matrix in the original's dict (a ball joint's
#: quaternion as a rotation matrix; :class:`~sg_torchrl.envs.navigation.robots.base.SensorTerm` ``"rotmat"``)
_MATRIX_TRANSFORM = "rotmat"


def _bounds(values, width: int) -> np.ndarray:
    """One simulator's bounds as float64, the float32 extremes of an unbounded TorchRL spec as infinities
    (the original's sensors are bounded by -inf and inf)."""
    values = values.reshape(-1, width)[0].cpu().numpy().astype(np.float64)
    largest = float(np.finfo(np.float32).max)
    values[values >= largest] = np.inf
    values[values <= -largest] = -np.inf
    return values


@dataclass(frozen=True)
class DictEntry:
    """One key of the dict: its ``name``, ``shape``, bounds ``low`` / ``high``, numpy ``dtype`` and where
    its values come from: ``source`` (the TorchRL entry) and ``part`` (a slice of it, vector parts only)."""

    name: str
    shape: tuple[int, ...]
    low: float
    high: float
    dtype: str
    source: str
    part: slice | None = None


@dataclass(frozen=True)
class DictLayout:
    """The original's dict observation of one env (see the module docstring); build it with :meth:`of`."""

    entries: tuple[DictEntry, ...]

    @classmethod
    def of(cls, env: Any) -> DictLayout:
        """The layout of a navigation ``env`` whose observations hold ``observation`` and ``pixels``.

        Raises ``ValueError`` naming the ``obs_mode`` to use when either is missing (the original's
        Vision observation has both).
        """
        spec = env.observation_spec
        keys = set(spec.keys())
        if not {"observation", "pixels"} <= keys:
            raise ValueError("Safety-Gymnasium's Vision dict holds the vector and the image: build the env with "
                             f"obs_mode='vector+rgb' (or 'vector+rgbd'); its observations hold {sorted(keys)}")
        matrices = {term.sensor for term in getattr(env.robot, "observation_terms", ())
                    if term.transform == _MATRIX_TRANSFORM}
        low, high = (_bounds(getattr(spec["observation"].space, side), spec["observation"].shape[-1])
                     for side in ("low", "high"))
        entries = []
        for name, part in env.observation_slices.items():
            width = part.stop - part.start
            shape = (3, 3) if name in matrices and width == 9 else (width,)
            bounds = next((b for suffix, b in _BOUNDS.items() if name.endswith(suffix)),
                          (float(low[part].min()), float(high[part].max())))
            entries.append(DictEntry(name, shape, *bounds, "float64", "observation", part))
        height, width, channels = spec["pixels"].shape[-3:]
        entries.append(DictEntry("vision", (height, width, channels), 0.0, 255.0, "uint8", "pixels"))
        if "depth" in keys:
            box = spec["depth"].space
            entries.append(DictEntry("depth", (height, width, 1), float(box.low.min()), float(box.high.max()),
                                     "float32", "depth"))
        return cls(tuple(entries))

    @property
    def keys(self) -> tuple[str, ...]:
        """The dict's keys, in order."""
        return tuple(entry.name for entry in self.entries)

    def split(self, td: Any, index: int = 0) -> dict[str, np.ndarray]:
        """Simulator ``index``'s observation in ``td`` (a TensorDict, or a mapping of arrays with a leading
        simulator dimension) as the original's dict: new numpy arrays of each entry's shape and dtype."""
        sources: dict[str, np.ndarray] = {}
        observation = {}
        for entry in self.entries:
            values = sources.get(entry.source)
            if values is None:
                raw = td[entry.source][index]
                values = sources[entry.source] = np.asarray(raw.cpu() if hasattr(raw, "cpu") else raw)
            if entry.part is not None:
                values = values[entry.part]
            observation[entry.name] = values.astype(entry.dtype).reshape(entry.shape)
        return observation
