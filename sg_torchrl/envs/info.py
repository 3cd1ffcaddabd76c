"""Step ``info`` dicts that TorchRL's ``default_info_dict_reader`` can read.

TorchRL's ``GymEnv`` / ``GymWrapper`` copy info entries into the step's TensorDict with
``default_info_dict_reader(keys)``, which reads each value's ``dtype``: a Python ``float`` has none
(``AttributeError: 'float' object has no attribute 'dtype'``). :func:`numpy_scalar_info` turns the
Python numbers of an info into numpy scalars (``float`` -> ``np.float64``, ``int`` -> ``np.int64``,
``bool`` -> ``np.bool_``). ``np.float64`` is a subclass of ``float``, so code that treats the cost
as a Python float (arithmetic, ``isinstance(cost, float)``, formatting) is unaffected.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["numpy_scalar_info"]

_NUMPY_TYPES = {bool: np.bool_, int: np.int64, float: np.float64}


def numpy_scalar_info(info: dict[str, Any]) -> dict[str, Any]:
    """Replace (in place) the Python ``bool`` / ``int`` / ``float`` values of ``info`` by numpy scalars; return it."""
    for key, value in info.items():
        kind = _NUMPY_TYPES.get(type(value))
        if kind is not None:
            info[key] = kind(value)
    return info
