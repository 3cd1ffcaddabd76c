"""Env options: their types, the one check of their values, and its exceptions.

``sg_torchrl.make(env_id, **options)`` and ``sg-train --env-options`` both check options here
(through :func:`sg_torchrl.envs.registry.validate_env_options`), so a value is accepted or refused the
same way from Python and from the command line, before anything is built. The types are the env
constructors' parameter annotations, interpreted strictly by :mod:`sg_torchrl.validation` (a bool is
``True`` / ``False``, never the string ``"no"``; a float is finite; a ``Literal`` is one of its values).

The constructors live in modules that import torch and MuJoCo, which take seconds to load. So that
``sg-train`` can refuse a bad option in about a second, :data:`CONSTRUCTOR_OPTIONS` restates the
annotations of the built-in constructors here, in a module that imports neither;
``tests/test_validation.py`` checks it against the real signatures (``typing.get_type_hints``), so the
two cannot drift apart. A constructor not in the table (registered by a user) is read from its own
signature (:func:`signature_options`).

How an env's simulators run (threads, backend, Warp device and buffer sizes) is one frozen object,
:class:`SimulatorOptions`: the velocity, multi-agent velocity and two-hand constructors take its fields
as keywords, build it once and hand it to :func:`~sg_torchrl.envs.backends.make_physics`; their rows of
:data:`CONSTRUCTOR_OPTIONS` are read from its fields (:data:`SIMULATOR_OPTIONS`).
"""

from __future__ import annotations

import inspect
import numbers
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from typing import Any, Literal

from sg_torchrl.validation import BOOL_WORDS, describe, fits

__all__ = [
    "BACKENDS", "CONSTRUCTOR_OPTIONS", "EnvOptionTypeError", "InvalidEnvOptionError", "Option", "SIMULATOR_OPTIONS",
    "SimulatorOptions", "UnknownEnvOptionError", "check_options", "command_line_options", "signature_options",
]


class InvalidEnvOptionError(ValueError):
    """An argument of ``sg_torchrl.make`` (an option, ``num_envs``, ``seed`` or ``device``) has a bad value.

    The message names the env id and the argument. A ``ValueError``, so ``sg-train`` reports it as a bad
    configuration (exit status 2) like any other.
    """


class EnvOptionTypeError(InvalidEnvOptionError, TypeError):
    """An argument of ``sg_torchrl.make`` has the wrong type (a string for a bool, a float for an int).

    Also a ``TypeError``, what Python raises for a wrong argument type.
    """


class UnknownEnvOptionError(EnvOptionTypeError):
    """An option the env id does not take (a ``TypeError``, like an unexpected keyword argument)."""


# The option types of the built-in constructors. Each alias equals the one its constructor uses
# (``sg_torchrl.envs.base.CostMode``, ``...navigation.lidar.LidarMode``, ...; tests/test_validation.py).
CostMode = Literal["indicator", "raw"]
Backend = Literal["cpu", "warp"]
BACKENDS: tuple[str, ...] = typing.get_args(Backend)
LidarMode = Literal["pseudo", "natural"]
ObsMode = Literal["vector", "rgb", "rgbd", "vector+rgb", "vector+rgbd"]
AgentView = Literal["joint", "own"]
CostSource = Literal["joints", "actions"]


@dataclass(frozen=True)
class Option:
    """One keyword option of an env constructor.

    Args:
        annotation: its type, as the constructor's signature annotates it.
        minimum: for numbers, the smallest valid value (``None``: any); a range the type cannot say.
    """

    annotation: Any
    minimum: int | float | None = None


@dataclass(frozen=True)
class SimulatorOptions:
    """How an env's simulators run: the one bundle of the simulator keywords (module docstring).

    Args:
        physics_threads: threads stepping the simulators (``backend="cpu"`` only; 2 pays when a core is
            idle, see :mod:`sg_torchrl.envs.physics`).
        backend: ``"cpu"`` (MuJoCo C, float64) or ``"warp"`` (MuJoCo Warp, on a GPU when one is visible);
            see :mod:`sg_torchrl.envs.backends`.
        warp_device: the Warp device with ``backend="warp"`` (``None``: ``"cuda:0"`` if available, else ``"cpu"``).
        warp_options: more :class:`~sg_torchrl.envs.warp_physics.WarpBatch` keywords with ``backend="warp"``
            (``nconmax``, ``njmax``, ``graph``).

    Raises:
        ValueError: an unknown backend, a thread count below 1, or a setting of the other backend.
    """

    physics_threads: int = 1
    backend: Backend = "cpu"
    warp_device: str | None = None
    warp_options: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"unknown physics backend {self.backend!r}; choose from {list(BACKENDS)}")
        threads = self.physics_threads
        if isinstance(threads, bool) or not isinstance(threads, numbers.Integral) or threads < 1:
            raise ValueError(f"physics_threads must be a positive integer, got {threads!r}")
        if self.backend == "cpu":
            for name in ("warp_device", "warp_options"):
                if getattr(self, name) is not None:
                    raise ValueError(f"{name}={getattr(self, name)!r} applies to backend='warp' only")
        elif threads != 1:
            raise ValueError(f"physics_threads={threads} applies to backend='cpu' only (MuJoCo Warp parallelises "
                             "over worlds itself); leave it at 1 with backend='warp'")


_COUNT = Option(int, minimum=1)
#: The option types of :class:`SimulatorOptions`' fields, in their order (the constructors take them as keywords).
SIMULATOR_OPTIONS: dict[str, Option] = {
    field.name: Option(typing.get_type_hints(SimulatorOptions)[field.name],
                       minimum=_COUNT.minimum if field.name == "physics_threads" else None)
    for field in fields(SimulatorOptions)
}
_SHADOW_HAND = {
    "cost_mode": Option(CostMode),
    "cost_source": Option(CostSource),
    "max_episode_steps": _COUNT,
    "distance_scale": Option(float),
    "fall_height": Option(float | None),
    **SIMULATOR_OPTIONS,
}

#: Per constructor (``"module:Class"``, the module that defines it), the keyword options the registry
#: leaves open (all but ``num_envs``, ``device``, ``seed`` and what an id fixes: robot, task, level, ...),
#: in signature order.
CONSTRUCTOR_OPTIONS: dict[str, dict[str, Option]] = {
    "sg_torchrl.envs.velocity.env:VelocityEnv": {
        "cost_mode": Option(CostMode),
        "max_episode_steps": _COUNT,
        "velocity_threshold": Option(float | None),
        "planar_cost": Option(bool | None),
        **SIMULATOR_OPTIONS,
    },
    "sg_torchrl.envs.navigation.env:NavigationEnv": {
        "cost_mode": Option(CostMode),
        "max_episode_steps": Option(int | None, minimum=1),
        "lidar": Option(LidarMode),
        "compass": Option(bool),
        "obs_mode": Option(ObsMode),
        "image_size": _COUNT,
        "physics_threads": _COUNT,
    },
    "sg_torchrl.envs.multi_agent.env:MultiAgentVelocityEnv": {
        "agent_obsk": Option(int, minimum=0),
        "cost_mode": Option(CostMode),
        "max_episode_steps": _COUNT,
        "velocity_threshold": Option(float | None),
        **SIMULATOR_OPTIONS,
    },
    "sg_torchrl.envs.multi_agent.navigation:MultiAgentNavigationEnv": {
        "agent_view": Option(AgentView),
        "cost_mode": Option(CostMode),
        "max_episode_steps": Option(int | None, minimum=1),
        "lidar": Option(LidarMode),
        "compass": Option(bool),
        "physics_threads": _COUNT,
    },
    "sg_torchrl.envs.hands.env:ShadowHandEnv": _SHADOW_HAND,
    "sg_torchrl.envs.hands.multi_agent:MultiAgentShadowHandEnv": _SHADOW_HAND,
}

#: Constructor parameters that are ``make``'s own arguments, never options.
MAKE_ARGUMENTS = frozenset({"num_envs", "device", "seed"})


def signature_options(constructor: Callable[..., Any], fixed: set[str] | frozenset[str] = frozenset()
                      ) -> tuple[dict[str, Option], bool]:
    """The keyword options of ``constructor`` read from its signature, less ``fixed`` and ``make``'s arguments.

    Returns the options (their resolved annotations; no minimum) and whether the constructor also takes
    arbitrary keywords (``**kwargs``: then it checks unknown names itself). Imports nothing; the
    constructor's module is loaded already.
    """
    # A class's own __init__: EnvBase's metaclass hides it behind ``__call__(*args, **kwargs)``.
    function = constructor.__init__ if isinstance(constructor, type) else constructor
    try:
        hints = typing.get_type_hints(function)
    except (NameError, TypeError):  # an annotation that does not resolve: left unchecked
        hints = {}
    options, open_ended = {}, False
    for parameter in inspect.signature(function).parameters.values():
        if parameter.kind is parameter.VAR_KEYWORD:
            open_ended = True
        elif (parameter.kind in (parameter.KEYWORD_ONLY, parameter.POSITIONAL_OR_KEYWORD)
              and parameter.name not in {"self", *MAKE_ARGUMENTS, *fixed}):
            options[parameter.name] = Option(hints.get(parameter.name, Any))
    return options, open_ended


def check_options(env_id: str, types: Mapping[str, Option], options: Mapping[str, Any], open_ended: bool = False
                  ) -> dict[str, Any]:
    """``options`` checked against ``types``; returns them with numbers as plain ``int`` / ``float``.

    Raises :class:`UnknownEnvOptionError` for names not in ``types`` (unless ``open_ended``),
    :class:`EnvOptionTypeError` for a value of the wrong type and :class:`InvalidEnvOptionError` for
    one below its minimum or not finite, each naming the option and ``env_id``.
    """
    unknown = [name for name in options if name not in types]
    if unknown and not open_ended:
        raise UnknownEnvOptionError(
            f"{env_id}: unknown option(s) {', '.join(map(repr, unknown))}; it takes {', '.join(types)}"
        )
    checked = dict(options)
    for name, value in options.items():
        if name not in types:
            continue
        option = types[name]
        if not fits(option.annotation, value):
            # The right type (a string for a Literal of strings, NaN for a float) is a bad value: a
            # ValueError; anything else is a bad type, also a TypeError.
            error = InvalidEnvOptionError if fits(option.annotation, value, values=False) else EnvOptionTypeError
            raise error(f"{env_id}: option {name} must be {describe(option.annotation)}, "
                        f"got {value!r} ({type(value).__name__})")
        if option.minimum is not None and value is not None and value < option.minimum:
            raise InvalidEnvOptionError(f"{env_id}: option {name} must be >= {option.minimum}, got {value!r}")
        if isinstance(value, numbers.Integral) and not isinstance(value, (bool, int)):
            checked[name] = int(value)  # a numpy integer
        elif isinstance(value, numbers.Real) and not isinstance(value, (bool, int, float)):
            checked[name] = float(value)  # a numpy float32
    return checked


def command_line_options(types: Mapping[str, Option], options: Mapping[str, Any]) -> dict[str, Any]:
    """``options`` read from a command line, with bool options' words turned into bools.

    ``sg-train --env-options`` reads values as JSON, so ``compass=false`` is already ``False`` but
    ``compass=False`` or ``compass=no`` is a string (and ``compass=1`` the number 1). For an option
    whose type takes a bool and no string, the words of :data:`sg_torchrl.validation.BOOL_WORDS` and the
    numbers 0 / 1 become ``False`` / ``True``; any other value is left for :func:`check_options` to refuse.
    """
    converted = dict(options)
    for name, value in options.items():
        option = types.get(name)
        if option is None or not fits(option.annotation, True) or fits(option.annotation, "true"):
            continue
        if isinstance(value, str) and value.strip().lower() in BOOL_WORDS:
            converted[name] = BOOL_WORDS[value.strip().lower()]
        elif type(value) is int and value in (0, 1):
            converted[name] = bool(value)
    return converted
