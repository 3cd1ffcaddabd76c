"""Safe environments: the registry, the ``SafeEnv`` base and cost-aware transforms.

The registry (``make``, ``list_envs``, ``registry_entry``) and its option checks import neither torch
nor MuJoCo; ``SafeEnv``, ``CostMode`` and ``EpisodeSum`` load them and are imported on first use
(PEP 562), so that ``sg-train`` can check its configuration before paying for that.
"""

from __future__ import annotations

from sg_torchrl.lazy import lazy_exports
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


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
