"""sg_torchrl's ids and their ``<Name>Gymnasium-v<k>`` twins in gymnasium's registry, from ``import sg_torchrl``.

After ``import sg_torchrl`` (or any of its modules), ``gymnasium.make("SafetyPointGoal1Gymnasium-v0")``
and ``torchrl.envs.GymEnv("SafetyPointGoal1Gymnasium-v0")`` find the id: registering reads the
registry's plain data (ids, episode lengths) and names the entry point ``sg_torchrl.gym:make`` as a
string, so it builds no env and imports neither torch nor MuJoCo.

``import sg_torchrl`` does not import gymnasium itself (the package loads in a few hundredths of a
second, and gymnasium with numpy takes several times that). :func:`register_when_gymnasium_loads`
therefore registers at once if gymnasium is already imported, and otherwise the moment gymnasium's
own import finishes (a one-shot import hook that removes itself), so the ids are there whichever of
the two a program imports first. :mod:`sg_torchrl.gym` documents how each kind of id is registered.
"""

from __future__ import annotations

import importlib.abc
import importlib.util
import sys
import threading
import types
from typing import Any

from sg_torchrl.envs.registry import list_envs, registry_entry

__all__ = ["ENTRY_POINT", "gymnasium_twin_id", "register_envs", "register_when_gymnasium_loads"]

ENTRY_POINT = "sg_torchrl.gym:make"
TWIN_SUFFIX = "Gymnasium"
_LOCK = threading.Lock()


def gymnasium_twin_id(env_id: str) -> str:
    """The id of the 5-tuple twin: ``"SafetyAntVelocity-v1"`` -> ``"SafetyAntVelocityGymnasium-v1"``."""
    name, sep, version = env_id.rpartition("-v")
    if not sep or not version.isdigit():
        raise ValueError(f"env id {env_id!r} does not end in '-v<version>'")
    return f"{name}{TWIN_SUFFIX}-v{version}"


def register_envs() -> list[str]:
    """Register every single-agent sg_torchrl id and its 5-tuple twin in gymnasium's registry.

    Idempotent: ids already registered with :data:`ENTRY_POINT` are left alone. Returns the ids
    registered by this call. Call it again after adding ids to sg_torchrl's registry.
    """
    import gymnasium

    added = []
    registry = gymnasium.envs.registry
    with _LOCK:
        for env_id in list_envs():
            entry = registry_entry(env_id)
            if entry.multi_agent:  # PettingZoo envs: sg_torchrl.pettingzoo
                continue
            for gym_id, settings in (
                # 6-tuple: no checker, no OrderEnforcing, no TimeLimit (all assume or allow only 5
                # values; the env enforces order and time limit itself). See sg_torchrl.gym.
                (env_id, dict(max_episode_steps=None, order_enforce=False, disable_env_checker=True,
                              kwargs={"env_id": env_id})),
                # 5-tuple twin: standard gymnasium wrappers; gymnasium's TimeLimit is the only limit.
                (gymnasium_twin_id(env_id), dict(max_episode_steps=entry.max_episode_steps,
                                                 kwargs={"env_id": gymnasium_twin_id(env_id),
                                                         "max_episode_steps": None})),
            ):
                existing = registry.get(gym_id)
                if existing is not None and existing.entry_point == ENTRY_POINT:
                    continue
                gymnasium.register(id=gym_id, entry_point=ENTRY_POINT, **settings)
                added.append(gym_id)
    return added


class _RegisterAfterLoading(importlib.abc.Loader):
    """Runs gymnasium's own loader, then :func:`register_envs`; gives the module its own loader back."""

    def __init__(self, loader: importlib.abc.Loader) -> None:
        self._loader = loader

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType | None:
        return self._loader.create_module(spec)

    def exec_module(self, module: types.ModuleType) -> None:
        _remove_hook()
        module.__spec__.loader = self._loader
        module.__loader__ = self._loader
        self._loader.exec_module(module)
        register_envs()

    def __getattr__(self, name: str) -> Any:  # resource readers etc. of the real loader
        return getattr(self._loader, name)


class _GymnasiumImportHook(importlib.abc.MetaPathFinder):
    """Finds ``gymnasium`` as every other finder would, with :class:`_RegisterAfterLoading` around its loader.

    It stays in place until gymnasium is actually loaded: libraries probe for gymnasium with
    ``importlib.util.find_spec("gymnasium")`` (TorchRL does) without importing it.
    """

    def __init__(self) -> None:
        self._searching = threading.local()

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        if fullname != "gymnasium" or getattr(self._searching, "active", False):
            return None
        self._searching.active = True  # the search below asks the finders again, this one included
        try:
            spec = importlib.util.find_spec(fullname)
        finally:
            self._searching.active = False
        if spec is not None and spec.loader is not None:
            spec.loader = _RegisterAfterLoading(spec.loader)
        return spec


def _remove_hook() -> None:
    sys.meta_path[:] = [finder for finder in sys.meta_path if not isinstance(finder, _GymnasiumImportHook)]


def register_when_gymnasium_loads() -> None:
    """Register the ids now if gymnasium is imported, else right after its import (module docstring)."""
    if "gymnasium" in sys.modules:
        register_envs()
    elif not any(isinstance(finder, _GymnasiumImportHook) for finder in sys.meta_path):
        sys.meta_path.insert(0, _GymnasiumImportHook())
