"""What every wrapper of the drop-in shares: gymnasium 0.28's attribute forwarding and a rebuildable spec.

* **Forwarding.** Gymnasium 0.28's ``Wrapper.__getattr__`` passed the read of an attribute the
  wrapper does not have to the env inside, so ``env.obs_rms`` on a ``SafeUnsqueeze`` around a
  ``SafeNormalizeObservation`` found the statistics (SafePO saves them that way). Gymnasium 1.x
  dropped it (``get_wrapper_attr`` replaces it). :class:`ForwardingWrapper` restores it for the
  drop-in's wrappers, without 1.x's deprecation warning: a public name the wrapper does not have is
  looked up through the envs inside (through gymnasium's own wrappers too, with
  ``get_wrapper_attr``); a name starting with ``_`` raises ``AttributeError``, as in 0.28.
  ``set_wrapper_attr`` still sets an attribute where it lives (forwarding does not make an inner
  env's attribute the wrapper's own).
* **Rebuildable.** :class:`SafeWrapper` is also a ``gymnasium.utils.RecordConstructorArgs``, so the
  wrapper appears in ``env.spec.additional_wrappers`` with its arguments and ``gymnasium.make(env.spec)``
  (which ``gymnasium.utils.env_checker.check_env`` calls) can rebuild it.
"""

from __future__ import annotations

from typing import Any

import gymnasium

__all__ = ["ForwardingWrapper", "SafeWrapper", "has_own_attribute"]


def has_own_attribute(obj: Any, name: str) -> bool:
    """Whether ``obj`` has ``name`` itself (instance, class or property), not through forwarding."""
    try:
        object.__getattribute__(obj, name)
    except AttributeError:
        return False
    return True


class ForwardingWrapper:
    """Mixin for ``gymnasium.Wrapper`` subclasses: unknown public attributes are read from the env inside.

    Put it first among the bases (``class W(ForwardingWrapper, gymnasium.Wrapper)``).
    """

    def __getattr__(self, name: str) -> Any:
        # Only called when normal lookup failed. The env is read from __dict__ directly, so that a
        # half-built wrapper (during unpickling or deepcopy) raises instead of recursing.
        if name.startswith("_"):
            raise AttributeError(f"accessing private attribute {name!r} is prohibited")
        env = self.__dict__.get("env")
        if env is None:
            raise AttributeError(f"{type(self).__name__} has no attribute {name!r} (it wraps no env yet)")
        try:
            getter = getattr(env, "get_wrapper_attr", None)
            return getter(name) if getter is not None else getattr(env, name)
        except AttributeError:
            raise AttributeError(f"{type(self).__name__} and the envs it wraps have no attribute {name!r}") from None

    def set_wrapper_attr(self, name: str, value: Any, *, force: bool = True) -> bool:
        """Set ``name`` on this wrapper if it has it, else on the innermost env that has it, else (``force``) here."""
        if has_own_attribute(self, name):
            setattr(self, name, value)
            return True
        inner = getattr(self.env, "set_wrapper_attr", None)
        if inner is not None and inner(name, value, force=False):
            return True
        if force:
            setattr(self, name, value)
            return True
        return False


class SafeWrapper(ForwardingWrapper, gymnasium.Wrapper, gymnasium.utils.RecordConstructorArgs):
    """Base of the drop-in's wrappers: forwarding (:class:`ForwardingWrapper`) and recorded arguments.

    A subclass with constructor arguments passes them to ``__init__`` (``super().__init__(env,
    gamma=gamma)``) so that ``env.spec`` records them.
    """

    def __init__(self, env: gymnasium.Env, **recorded: Any) -> None:
        gymnasium.utils.RecordConstructorArgs.__init__(self, **recorded)
        gymnasium.Wrapper.__init__(self, env)
