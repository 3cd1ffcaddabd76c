"""Strict checks of values against type annotations, shared by ``sg_torchrl.make`` and ``sg-train``.

One rule set for env options (:mod:`sg_torchrl.envs.options`) and for :class:`~sg_torchrl.train.TrainConfig`
fields, so the same value is accepted or rejected the same way from Python and from the command line:

* ``bool`` takes only ``True`` / ``False``: a non-empty string such as ``"no"`` is truthy, and accepting it
  turned options *on* that the user meant to turn off. From the command line the words of
  :data:`BOOL_WORDS` are converted first (:func:`parse_bool`), anything else is an error;
* ``int`` takes integers but not ``bool`` (``True`` is an ``int`` to Python, never a count) and not strings;
* ``float`` takes finite real numbers (not ``bool``): NaN compares false with everything, so a NaN
  threshold or limit silently disables what it bounds;
* ``Literal[...]`` takes one of its values, of the same type; ``X | None`` takes ``None`` or an ``X``;
  ``list[X]`` / ``dict[K, V]`` check their items; ``Any`` and annotations left as strings take anything.

Only the standard library is imported: ``sg-train`` validates its whole configuration with this module
before torch, TorchRL or MuJoCo are loaded, so a bad option fails in about a second.
"""

from __future__ import annotations

import math
import numbers
from types import NoneType, UnionType
from typing import Any, Literal, Union, get_args, get_origin

__all__ = ["BOOL_WORDS", "describe", "fits", "parse_bool"]

#: Command-line spellings of the two booleans (case-insensitive).
BOOL_WORDS: dict[str, bool] = {"true": True, "1": True, "yes": True, "false": False, "0": False, "no": False}


def parse_bool(text: str) -> bool:
    """``"yes"`` -> ``True``: one of :data:`BOOL_WORDS`, else ``ValueError`` listing them."""
    try:
        return BOOL_WORDS[text.strip().lower()]
    except KeyError:
        raise ValueError(f"expected a boolean ({'/'.join(BOOL_WORDS)}), got {text!r}") from None


def fits(annotation: Any, value: Any, values: bool = True) -> bool:
    """Whether ``value`` is a valid value of ``annotation`` under the strict rules of the module docstring.

    ``values=False`` checks the type only: a ``Literal`` takes any value of its values' types, a float NaN
    or inf (to tell a bad value, a ``ValueError``, from a bad type, a ``TypeError``).
    """
    if annotation is Any or isinstance(annotation, str):  # unresolved forward reference: nothing to check
        return True
    if annotation is None or annotation is NoneType:
        return value is None
    origin, args = get_origin(annotation), get_args(annotation)
    if origin in (Union, UnionType):
        return any(fits(arg, value, values) for arg in args)
    if origin is Literal:
        return any((value == arg or not values) and type(value) is type(arg) for arg in args)
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if annotation is float:
        return isinstance(value, numbers.Real) and not isinstance(value, bool) and (math.isfinite(value) or not values)
    if origin in (list, tuple):
        return isinstance(value, (list, tuple)) and all(fits(args[0] if args else Any, item, values) for item in value)
    if origin is dict:
        key, item = args if args else (Any, Any)
        return isinstance(value, dict) and all(fits(key, k, values) and fits(item, v, values) for k, v in value.items())
    if isinstance(annotation, type):
        return isinstance(value, annotation)
    return True  # a typing construct this module does not interpret


def describe(annotation: Any) -> str:
    """What :func:`fits` accepts for ``annotation``, for error messages (``"a finite number or None"``)."""
    if annotation is None or annotation is NoneType:
        return "None"
    origin, args = get_origin(annotation), get_args(annotation)
    if origin in (Union, UnionType):
        return " or ".join(describe(arg) for arg in args)
    if origin is Literal:
        return "one of " + ", ".join(map(repr, args))
    if origin in (list, tuple):
        return f"a list, each item {describe(args[0])}" if args else "a list"
    if origin is dict:
        return "a dict"
    names = {bool: "a bool (True or False)", int: "an integer", float: "a finite number", str: "a string"}
    if annotation in names:
        return names[annotation]
    return getattr(annotation, "__name__", str(annotation))
