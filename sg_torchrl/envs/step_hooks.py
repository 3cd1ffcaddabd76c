"""Which step hooks an env class redefines, recorded when the class is created.

An env's fast paths do the work of its step hooks themselves: the one-simulator steps of
:class:`~sg_torchrl.envs.navigation.env.NavigationEnv` and :class:`~sg_torchrl.envs.velocity.env.VelocityEnv`
replace ``_advance``, ``_observe``, ``_compute_reward``, ... by Python-float forms, and the façades'
numpy step replaces the TorchRL ``_step``. A subclass that redefines one of those hooks must not be
given the fast path, which would silently skip its code.

So the hooks are marked where they are declared (:func:`step_hook` on the base class's method) and every
subclass records, in :meth:`StepHooks.__init_subclass__`, which marked hooks resolve to another function
than in each of its ancestors. A fast path asks :meth:`StepHooks.hooks_overridden_since` for the class it
was written against; no list of hook names is kept anywhere else. A hook added later is covered by
marking it. The façades' numpy step asks :attr:`StepHooks.numpy_step_interface`: which public numpy
interface the ``_step`` in use is marked (:func:`numpy_faced`) to reproduce, if any.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

__all__ = ["StepHooks", "numpy_faced", "step_hook"]

F = TypeVar("F", bound=Callable[..., Any])


def step_hook(function: F) -> F:
    """Mark ``function`` (a method) as a step hook that a fast path may do the work of (module docstring)."""
    function.__step_hook__ = True
    return function


def numpy_faced(interface: str) -> Callable[[F], F]:
    """Mark a ``_step`` whose work the env's public numpy ``interface`` reproduces exactly (also a
    :func:`step_hook`): ``"flat"``, :class:`~sg_torchrl.envs.numpy_step.NumpyStepInterface`'s ``step_one`` /
    ``step_arrays`` / ``output_arrays`` (the gymnasium façade's); ``"agent_group"``, the multi-agent
    layout's ``robot_control`` / ``step_arrays`` / ``output_arrays`` (the PettingZoo façade's)."""

    def mark(function: F) -> F:
        function.__numpy_faced__ = interface
        return step_hook(function)

    return mark


def _hook_names(cls: type) -> frozenset[str]:
    return frozenset(name for klass in cls.__mro__ for name, value in vars(klass).items()
                     if getattr(value, "__step_hook__", False))


class StepHooks:
    """Mixin of :class:`~sg_torchrl.envs.base.SafeEnv`: per class, the step hooks it redefines (module docstring)."""

    #: per ancestor (itself included), the marked hooks whose function here differs from the ancestor's
    _overridden_hooks: ClassVar[dict[type, frozenset[str]]] = {}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        names = _hook_names(cls)
        cls._overridden_hooks = {
            ancestor: frozenset(name for name in names if getattr(cls, name, None) is not getattr(ancestor, name, None))
            for ancestor in cls.__mro__ if ancestor is not object
        }

    @classmethod
    def hooks_overridden_since(cls, ancestor: type) -> frozenset[str]:
        """The step hooks this class (or a class between it and ``ancestor`` in its MRO) redefines,
        relative to ``ancestor``; empty when the class is ``ancestor``. ``ancestor`` must be one of its bases."""
        try:
            return cls._overridden_hooks[ancestor]
        except KeyError:
            raise TypeError(f"{ancestor.__name__} is not a base of {cls.__name__}") from None

    @property
    def numpy_step_interface(self) -> str | None:
        """The public numpy interface that gives exactly this env's TorchRL step (``"flat"`` or
        ``"agent_group"``, :func:`numpy_faced`), or ``None``: its ``_step`` is not marked (a subclass
        redefining ``_step`` without the mark steps only through TorchRL)."""
        return getattr(type(self)._step, "__numpy_faced__", None)
