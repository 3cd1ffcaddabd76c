"""Safe environments: the registry, the ``SafeEnv`` base and cost-aware transforms."""

from sg_torchrl.envs.base import CostMode, SafeEnv
from sg_torchrl.envs.registry import EnvEntry, UnknownEnvError, list_envs, make, registry_entry
from sg_torchrl.envs.transforms import EpisodeSum

__all__ = [
    "CostMode",
    "EnvEntry",
    "EpisodeSum",
    "SafeEnv",
    "UnknownEnvError",
    "list_envs",
    "make",
    "registry_entry",
]
