"""Safe environments: the registry, the ``SafeEnv`` base and cost-aware transforms.

The registry (``make``, ``list_envs``, ``registry_entry``) and its option checks import neither torch
nor MuJoCo; ``SafeEnv``, ``CostMode`` and ``EpisodeSum`` load them and are imported on first use
(PEP 562), so that ``sg-train`` can check its configuration before paying for that.
"""

from __future__ import annotations

import importlib
from typing import Any

from sg_torchrl.envs.options import EnvOptionTypeError, InvalidEnvOptionError, UnknownEnvOptionError
from sg_torchrl.envs.registry import (
    EnvEntry,
    UnknownEnvError,
    env_option_types,
    list_envs,
    make,
    registry_entry,
    validate_env_options,
)

#: Names exported lazily: name -> module that defines it.
_LAZY = {"CostMode": "sg_torchrl.envs.base", "SafeEnv": "sg_torchrl.envs.base", "EpisodeSum": "sg_torchrl.envs.transforms"}

__all__ = [
    "CostMode",
    "EnvEntry",
    "EnvOptionTypeError",
    "EpisodeSum",
    "InvalidEnvOptionError",
    "SafeEnv",
    "UnknownEnvError",
    "UnknownEnvOptionError",
    "env_option_types",
    "list_envs",
    "make",
    "registry_entry",
    "validate_env_options",
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})
