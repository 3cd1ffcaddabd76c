"""Make ``import safety_gymnasium`` (and its submodules) resolve to :mod:`sg_torchrl.safety_gymnasium`.

One line at the top of a project's entry script switches every ``import safety_gymnasium`` in the
process (the script's, and those of the libraries it uses, such as SafePO or OmniSafe):

>>> import sg_torchrl.safety_gymnasium; sg_torchrl.safety_gymnasium.install_alias()
>>> import safety_gymnasium                      # sg_torchrl.safety_gymnasium
>>> from safety_gymnasium.wrappers import SafeAutoResetWrapper
>>> from safety_gymnasium.vector.async_vector_env import SafetyAsyncVectorEnv

or, without touching the script, ``python -m sg_torchrl.safety_gymnasium script.py [args...]``, which
also makes every child process (``spawn`` / ``forkserver`` workers, Python subprocesses) install the
alias and restores the platform's multiprocessing start method (:mod:`.__main__`). A script that calls
:func:`install_alias` itself gets it in forked workers only.

How: :func:`install_alias` puts a finder at the front of ``sys.meta_path``. For a name
``safety_gymnasium[.rest]`` it returns the module ``sg_torchrl.safety_gymnasium[.rest]`` itself (the
same module object under both names, so classes, ``isinstance`` and pickling agree), or, for the
few paths where the original keeps a name in a module we do not mirror (:data:`LEGACY_PATHS`, e.g.
``safety_gymnasium.tasks.safe_multi_agent.safe_mujoco_multi``), a module holding the names of ours.
Any other submodule of the original (its engine: ``builder``, ``bases``, ``assets``, ...) raises
``ModuleNotFoundError`` saying that the drop-in does not provide it, rather than silently importing
the original package's file. Installing while the original ``safety_gymnasium`` is already imported
raises ``ImportError``: the two cannot share the name in one process.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import types

__all__ = ["LEGACY_PATHS", "install_alias", "is_alias_installed", "uninstall_alias"]

ALIAS = "safety_gymnasium"
TARGET = "sg_torchrl.safety_gymnasium"

# Paths of the original whose names live elsewhere here: alias -> our module holding them.
# Entries whose value is None are namespaces (packages whose children are listed here too).
LEGACY_PATHS: dict[str, str | None] = {
    "utils": None,
    "utils.registration": f"{TARGET}.registration",
    "utils.passive_env_checker": f"{TARGET}.wrappers.env_checker",
    "version": TARGET,
    "tasks": None,
    "tasks.safe_multi_agent": None,
    "tasks.safe_multi_agent.safe_mujoco_multi": f"{TARGET}.multi_agent",
}


class _AliasLoader(importlib.abc.Loader):
    """Hands the import system a module that already exists (ours, or a namespace holding ours)."""

    def __init__(self, module: types.ModuleType) -> None:
        self._module = module
        self._own_spec = getattr(module, "__spec__", None)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        return self._module

    def exec_module(self, module: types.ModuleType) -> None:
        """Nothing to run (the module was imported when it was found); the import system has just set
        ``__spec__`` to the alias's spec, so the module gets its own back."""
        if self._own_spec is not None:
            module.__spec__ = self._own_spec


class _AliasFinder(importlib.abc.MetaPathFinder):
    """Finds ``safety_gymnasium[.rest]`` as ``sg_torchrl.safety_gymnasium[.rest]`` (module docstring)."""

    def find_spec(self, fullname: str, path=None, target=None) -> importlib.machinery.ModuleSpec | None:
        if fullname != ALIAS and not fullname.startswith(ALIAS + "."):
            return None
        rest = fullname[len(ALIAS) + 1:]
        module = _resolve(rest)
        is_package = hasattr(module, "__path__")
        return importlib.machinery.ModuleSpec(fullname, _AliasLoader(module), is_package=is_package)


def _resolve(rest: str) -> types.ModuleType:
    """Our module for the original's ``safety_gymnasium.<rest>`` (``rest == ""``: the package)."""
    if rest in LEGACY_PATHS:
        source = LEGACY_PATHS[rest]
        if source is None:
            namespace = types.ModuleType(f"{ALIAS}.{rest}", f"Namespace of sg_torchrl's drop-in for {ALIAS}.{rest}.")
            namespace.__path__ = []  # a package, so that its listed children import
            return namespace
        return importlib.import_module(source)
    name = f"{TARGET}.{rest}" if rest else TARGET
    try:
        found = importlib.util.find_spec(name)
    except ModuleNotFoundError:
        found = None
    if found is None:
        raise ModuleNotFoundError(
            f"No module named '{ALIAS}.{rest}' in sg_torchrl's drop-in for Safety-Gymnasium: it provides the "
            f"original's public API (make, make_ma, register, wrappers, vector, ...; see "
            f"{TARGET}.__doc__), not its engine modules",
            name=f"{ALIAS}.{rest}",
        )
    return importlib.import_module(name)


def is_alias_installed() -> bool:
    """Whether :func:`install_alias` is in effect in this process."""
    return any(isinstance(finder, _AliasFinder) for finder in sys.meta_path)


def install_alias() -> types.ModuleType:
    """Make every ``import safety_gymnasium[...]`` in this process resolve to sg_torchrl's drop-in.

    Idempotent; returns the ``safety_gymnasium`` module (which is :mod:`sg_torchrl.safety_gymnasium`).

    Raises:
        ImportError: the original ``safety_gymnasium`` package is already imported here.
    """
    existing = sys.modules.get(ALIAS)
    if existing is not None and getattr(existing, "__name__", None) != TARGET:
        raise ImportError(
            f"the original {ALIAS} ({getattr(existing, '__file__', '?')}) is already imported in this process: "
            f"call {TARGET}.install_alias() before anything imports {ALIAS} (e.g. first in the entry script), "
            f"or run the script with `python -m {TARGET} script.py`")
    if not is_alias_installed():
        sys.meta_path.insert(0, _AliasFinder())
    return importlib.import_module(ALIAS)


def uninstall_alias() -> None:
    """Undo :func:`install_alias`: remove the finder and the ``safety_gymnasium*`` entries of ``sys.modules``."""
    sys.meta_path[:] = [finder for finder in sys.meta_path if not isinstance(finder, _AliasFinder)]
    for name in [name for name in sys.modules if name == ALIAS or name.startswith(ALIAS + ".")]:
        del sys.modules[name]
