"""Lazy re-exports (PEP 562): a package names the module each public name lives in and imports it on first use.

So ``import sg_torchrl.train`` (the command line's option checks, the sweep) loads neither torch nor MuJoCo
until a trainer, a network or an env class is asked for::

    __getattr__, __dir__ = lazy_exports(__name__, {"SafeEnv": "sg_torchrl.envs.base"})
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(package: str, homes: Mapping[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module-level ``__getattr__`` and ``__dir__`` of ``package`` for the names of ``homes`` (name -> the
    dotted module holding it). A name is imported once, then kept in the package's namespace."""
    namespace = vars(sys.modules[package])

    def __getattr__(name: str) -> Any:
        if name in homes:
            value = namespace[name] = getattr(importlib.import_module(homes[name]), name)
            return value
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted({*namespace, *homes})

    return __getattr__, __dir__
