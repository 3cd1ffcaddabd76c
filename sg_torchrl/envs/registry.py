"""The env registry: an explicit table from Safety-Gymnasium env id to constructor.

Ids are Safety-Gymnasium's, unchanged, so results and configs carry over. The table is
explicit (no class names derived from id strings), which lets the registry-wide tests iterate
it and lets an unknown id get a helpful error listing the closest valid ids.

This module imports neither torch nor MuJoCo: the table is declared from plain data (robots, tasks,
levels, episode lengths; ``tests/test_validation.py`` checks it against the env modules), constructors
are named as ``"module:Class"`` and imported by the first :func:`make` that needs them, and option types
come from :mod:`sg_torchrl.envs.options`. So ``sg-train`` can check an env id and its options (and
refuse a typo with the closest ids) in about a second, before loading the simulation stack.
"""

from __future__ import annotations

import difflib
import importlib
import numbers
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from sg_torchrl.envs.options import (
    CONSTRUCTOR_OPTIONS,
    EnvOptionTypeError,
    InvalidEnvOptionError,
    Option,
    UnknownEnvOptionError,
    check_options,
    command_line_options,
    signature_options,
)

if TYPE_CHECKING:
    import torch

    from sg_torchrl.envs.base import SafeEnv

__all__ = [
    "EnvEntry", "EnvOptionTypeError", "InvalidEnvOptionError", "MULTI_AGENT_FAMILIES", "UnknownEnvError",
    "UnknownEnvOptionError", "VISION_FAMILY", "command_line_env_options", "env_option_types", "env_options",
    "list_envs", "make", "register", "registry_entry", "unregister", "validate_env_options",
]

#: The family of the ``...Vision-v0`` ids: navigation tasks observed through the robot's camera.
VISION_FAMILY = "vision"

#: Families whose envs use TorchRL's multi-agent layout (group ``"agents"``, no root ``observation``).
MULTI_AGENT_FAMILIES = frozenset({"multi_agent_velocity", "multi_agent_navigation", "multi_agent_dexhands"})

#: Robots of the multi-agent navigation ids (Safety-Gymnasium's paper and SafePO name these six).
MULTI_AGENT_NAVIGATION_ROBOTS = ("Point", "Ant")


class UnknownEnvError(KeyError, ValueError):
    """Raised by :func:`make` (and ``sg-train``'s config check) for an id that is not registered.

    A ``KeyError`` (a missing key of the table) for code that catches that, and a ``ValueError`` (a bad
    value of ``env_id``) so that configuration checks report it like every other bad value.
    """

    def __str__(self) -> str:  # KeyError would quote the whole message
        return str(self.args[0])


class _Importable:
    """Descriptor of :attr:`EnvEntry.constructor`: holds a callable, or ``"module:Name"`` imported on first read.

    The registry names its constructors by path so that listing ids and checking options never imports
    the simulation stack; reading ``entry.constructor`` gives the class itself.
    """

    def __set_name__(self, owner: type, name: str) -> None:
        self.slot = f"_{name}"

    def __get__(self, entry: Any, owner: type | None = None) -> Callable[..., Any]:
        if entry is None:  # a dataclass asking for the field's default: there is none
            raise AttributeError(self.slot)
        target = entry.__dict__[self.slot]
        if isinstance(target, str):
            module, _, name = target.partition(":")
            target = getattr(importlib.import_module(module), name)
            entry.__dict__[self.slot] = target
        return target

    def __set__(self, entry: Any, value: Callable[..., Any] | str) -> None:
        entry.__dict__[self.slot] = value

    def path(self, entry: Any) -> str:
        """``"module:Name"`` of the entry's constructor, without importing it."""
        target = entry.__dict__[self.slot]
        return target if isinstance(target, str) else f"{target.__module__}:{target.__qualname__}"


@dataclass(frozen=True)
class EnvEntry:
    """One registered env id.

    Args:
        env_id: Safety-Gymnasium id, e.g. ``"SafetyHalfCheetahVelocity-v1"``.
        constructor: builds the env; receives ``num_envs``, ``device``, ``seed`` and options. A callable,
            or its path ``"module:Name"`` (imported when first read).
        family: ``"velocity"``, ``"navigation"``, ``"vision"`` (navigation seen through the robot's
            camera), ``"multi_agent_velocity"``, ``"multi_agent_navigation"``, ``"dexhands"`` (two
            Shadow Hands, :mod:`sg_torchrl.envs.hands`), ``"multi_agent_dexhands"`` (the same, one agent per hand).
        robot / task / level: metadata for filtering and tables (``level`` is ``None`` where the
            family has no levels).
        max_episode_steps: the reference's episode length.
        kwargs: fixed constructor arguments for this id (robot, task, level, ...).
        options: default values of options this id sets differently from the constructor
            (e.g. ``obs_mode="rgb"`` for the Vision ids); users may override them.
    """

    env_id: str
    constructor: Callable[..., SafeEnv] = _Importable()
    family: str
    robot: str
    task: str
    max_episode_steps: int
    level: int | None = None
    kwargs: dict[str, Any] = field(default_factory=dict)
    options: dict[str, Any] = field(default_factory=dict)

    @property
    def multi_agent(self) -> bool:
        """The env emits TorchRL's multi-agent layout (see :data:`MULTI_AGENT_FAMILIES`)."""
        return self.family in MULTI_AGENT_FAMILIES

    @property
    def constructor_path(self) -> str:
        """``"module:Class"`` of :attr:`constructor`, without importing it."""
        return EnvEntry.__dict__["constructor"].path(self)


_REGISTRY: dict[str, EnvEntry] = {}


def register(entry: EnvEntry) -> None:
    """Add an id to the registry; re-registering an id is an error."""
    if entry.env_id in _REGISTRY:
        raise ValueError(f"env id {entry.env_id!r} is already registered")
    _REGISTRY[entry.env_id] = entry


def unregister(env_id: str) -> EnvEntry:
    """Remove a registered id (a user's, to register it again with other settings); returns its entry."""
    registry_entry(env_id)  # an unknown id: UnknownEnvError with the closest ids
    return _REGISTRY.pop(env_id)


def registry_entry(env_id: str) -> EnvEntry:
    """The :class:`EnvEntry` for ``env_id``; unknown ids raise :class:`UnknownEnvError`."""
    try:
        return _REGISTRY[env_id]
    except (KeyError, TypeError):  # TypeError: an unhashable "id"
        close = difflib.get_close_matches(env_id, list(_REGISTRY), n=3, cutoff=0.5) if isinstance(env_id, str) else []
        hint = f" Did you mean {', '.join(repr(c) for c in close)}?" if close else ""
        raise UnknownEnvError(
            f"unknown env id {env_id!r}.{hint} `sg_torchrl.list_envs()` lists the {len(_REGISTRY)} registered ids."
        ) from None


def list_envs(family: str | None = None, robot: str | None = None) -> list[str]:
    """Registered env ids, sorted, optionally filtered by family and robot."""
    entries: Iterable[EnvEntry] = _REGISTRY.values()
    return sorted(
        e.env_id for e in entries if (family is None or e.family == family) and (robot is None or e.robot == robot)
    )


def make(
    env_id: str,
    num_envs: int = 1,
    device: torch.device | str = "cpu",
    seed: int | Sequence[int] | None = None,
    **options: Any,
) -> SafeEnv:
    """Build the env registered as ``env_id`` with ``num_envs`` simulators in one process.

    Args:
        env_id: a Safety-Gymnasium id (see :func:`list_envs`).
        num_envs: simulators stepped by the returned env (its ``batch_size`` is ``[num_envs]``).
        device: device of the emitted TensorDicts.
        seed: seed of the per-simulator generators, an int >= 0 (``None``: fresh OS entropy); or a
            list of ``K`` seeds whose length divides ``num_envs``: the simulators split into ``K``
            equal contiguous blocks, block ``k`` seeded exactly as
            ``make(env_id, num_envs // K, seed=seeds[k])`` (same trajectories for the same actions),
            which is how a seed group (``sg-train --seeds``) steps its runs' simulators in one env.
        **options: task options, e.g. ``cost_mode="raw"``, ``max_episode_steps=500``, or for the
            navigation ids ``obs_mode="vector+rgbd"``, ``image_size=256`` (pixel observations); see
            :func:`env_option_types`.

    Every argument is checked before anything is built: an unknown id raises :class:`UnknownEnvError`
    (naming the closest ids), a bad option, ``num_envs``, ``seed`` or ``device``
    :class:`InvalidEnvOptionError` (a ``ValueError``; :class:`EnvOptionTypeError`, also a ``TypeError``,
    for a wrong type) naming it and the id.

    Example:
        >>> env = make("SafetyHalfCheetahVelocity-v1", num_envs=8, seed=0)
        >>> rollout = env.rollout(10)
        >>> rollout["next", "cost"].shape
        torch.Size([8, 10, 1])
    """
    entry = registry_entry(env_id)
    if isinstance(num_envs, bool) or not isinstance(num_envs, numbers.Integral):
        raise EnvOptionTypeError(f"{env_id}: num_envs must be an integer, got {num_envs!r} ({type(num_envs).__name__})")
    if num_envs < 1:
        raise InvalidEnvOptionError(f"{env_id}: num_envs must be >= 1, got {num_envs}")
    seed = _checked_seed(env_id, seed, int(num_envs))
    options = validate_env_options(env_id, options)
    _check_device(env_id, device)
    kwargs = {**entry.kwargs, "max_episode_steps": entry.max_episode_steps, **entry.options, **options,
              "num_envs": int(num_envs), "device": device, "seed": seed}
    env = entry.constructor(**kwargs)
    if hasattr(env, "remember_construction"):  # copies rebuild the env this way (SafeEnv.__reduce_ex__)
        env.remember_construction(entry.constructor, kwargs)
    return env


def _checked_seed(env_id: str, seed: Any, num_envs: int) -> int | list[int] | None:
    """``seed`` as :func:`make` hands it on (an int, a list of ints or ``None``), or an error naming it."""
    if seed is None:
        return None
    if isinstance(seed, (list, tuple)):
        if not seed or num_envs % len(seed):
            raise InvalidEnvOptionError(
                f"{env_id}: a list of {len(seed)} seeds splits the simulators into equal blocks, so num_envs "
                f"({num_envs}) must be a positive multiple of its length")
        return [_checked_seed(env_id, value, num_envs) if not isinstance(value, (list, tuple)) else
                _checked_seed(env_id, str(value), num_envs) for value in seed]  # a nested list: refused below
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise EnvOptionTypeError(
            f"{env_id}: seed must be an integer, a list of integers or None, got {seed!r} ({type(seed).__name__})")
    if seed < 0:
        raise InvalidEnvOptionError(f"{env_id}: seed must be >= 0 (or None), got {seed}")
    return int(seed)


def _check_device(env_id: str, device: Any) -> None:
    """Refuse a device torch cannot parse or this machine lacks (torch's own error is a bare AssertionError)."""
    import torch

    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError, ValueError) as error:
        raise InvalidEnvOptionError(f"{env_id}: device {device!r} is not a torch device ({error})") from None
    if parsed.type == "cuda":
        if not torch.cuda.is_available():
            raise InvalidEnvOptionError(
                f"{env_id}: device {device!r} needs CUDA, which is not available here "
                f"(torch.cuda.is_available() is False); use device='cpu'"
            )
        if parsed.index is not None and parsed.index >= torch.cuda.device_count():
            raise InvalidEnvOptionError(
                f"{env_id}: device {device!r} does not exist; this machine has {torch.cuda.device_count()} "
                "CUDA device(s)"
            )
    if parsed.type == "mps" and not torch.backends.mps.is_available():
        raise InvalidEnvOptionError(f"{env_id}: device {device!r} needs Apple's MPS, which is not available here")


def env_option_types(env_id: str) -> tuple[dict[str, Option], bool]:
    """The options ``env_id`` takes (name -> :class:`~sg_torchrl.envs.options.Option`, in signature order)
    and whether it also takes arbitrary keywords (a constructor with ``**kwargs``, which checks them itself).

    They are the constructor's keyword parameters less ``num_envs``, ``device``, ``seed`` and the ones
    the registry entry fixes (robot, task, level, ...). Built-in constructors are looked up in
    :data:`~sg_torchrl.envs.options.CONSTRUCTOR_OPTIONS` (no import); others read from their signature.
    """
    entry = registry_entry(env_id)
    known = CONSTRUCTOR_OPTIONS.get(entry.constructor_path)
    if known is not None:
        return {name: option for name, option in known.items() if name not in entry.kwargs}, False
    return signature_options(entry.constructor, set(entry.kwargs))


def env_options(env_id: str) -> list[str] | None:
    """The keyword options :func:`make` accepts for ``env_id`` (besides ``num_envs``, ``device``, ``seed``).

    E.g. ``cost_mode``, ``max_episode_steps``, ``velocity_threshold`` (see :func:`env_option_types`).
    ``None`` when the constructor takes arbitrary keywords (``**kwargs``): then it checks them itself.
    """
    types, open_ended = env_option_types(env_id)
    return None if open_ended else list(types)


def validate_env_options(env_id: str, options: dict[str, Any]) -> dict[str, Any]:
    """``options`` for ``env_id`` checked against the constructor's annotations; returns the checked options.

    The one check of env options, used by :func:`make` and by ``sg-train``'s config: unknown names raise
    :class:`UnknownEnvOptionError`, wrong types :class:`EnvOptionTypeError` (a bool must be ``True`` /
    ``False``, an int not a bool or string, ...), bad values :class:`InvalidEnvOptionError` (NaN or inf, a
    ``Literal`` value not among the choices, a count below 1); each message names the option and ``env_id``.
    An unknown ``env_id`` raises :class:`UnknownEnvError`.
    """
    types, open_ended = env_option_types(env_id)
    return check_options(env_id, types, options, open_ended)


def command_line_env_options(env_id: str, options: dict[str, Any]) -> dict[str, Any]:
    """Options read from a command line (values parsed as JSON) with the words true/false/yes/no/1/0 of
    bool-typed options turned into bools (``compass=False`` is the string ``"False"`` to JSON); other
    values unchanged. Checking them is :func:`validate_env_options`'s job; an unknown id changes nothing."""
    if env_id not in _REGISTRY:
        return dict(options)
    return command_line_options(env_option_types(env_id)[0], options)


# ---------------------------------------------------------------------------------------------- the table
# Plain data, so that listing ids needs no simulation code; tests/test_validation.py checks every value
# against the env modules (velocity ROBOTS, navigation TASKS, multi-agent SCENARIOS, dexhands TASKS).

_VELOCITY = "sg_torchrl.envs.velocity.env:VelocityEnv"
_NAVIGATION = "sg_torchrl.envs.navigation.env:NavigationEnv"
_MULTI_AGENT_VELOCITY = "sg_torchrl.envs.multi_agent.env:MultiAgentVelocityEnv"
_MULTI_AGENT_NAVIGATION = "sg_torchrl.envs.multi_agent.navigation:MultiAgentNavigationEnv"
_SHADOW_HAND = "sg_torchrl.envs.hands.env:ShadowHandEnv"
_MULTI_AGENT_SHADOW_HAND = "sg_torchrl.envs.hands.multi_agent:MultiAgentShadowHandEnv"

#: Velocity robots (gymnasium's MuJoCo assets) in ``sg_torchrl.envs.velocity.ROBOTS`` order, and the task
#: versions each has (0: Safety-Gymnasium's v0 thresholds, 1: v1's).
VELOCITY_ROBOTS = ("HalfCheetah", "Hopper", "Walker2d", "Swimmer", "Ant", "Humanoid")
VELOCITY_VERSIONS = (0, 1)
#: Navigation robots in ``sg_torchrl.envs.navigation.ROBOTS`` order.
NAVIGATION_ROBOTS = ("Point", "Car", "Racecar", "Doggo", "Ant")
#: Navigation tasks (``sg_torchrl.envs.navigation.TASKS`` order): number of levels (0, 1, ...) and episode length.
NAVIGATION_TASKS = {
    "Goal": (3, 1000), "Button": (3, 1000), "Push": (3, 1000), "Circle": (3, 500), "Run": (1, 500),
    "FadingEasy": (3, 1000), "FadingHard": (3, 1000), "Race": (3, 500), "BuildingGoal": (3, 1000),
    "BuildingButton": (3, 1000), "BuildingPush": (3, 1000), "FormulaOne": (3, 500),
}
#: Multi-agent navigation tasks (``MULTI_AGENT_TASKS``): levels and episode length.
MULTI_AGENT_NAVIGATION_TASKS = {"MultiGoal": (3, 1000)}
#: MaMuJoCo scenarios (``sg_torchrl.envs.multi_agent.SCENARIOS`` order): robot -> agent partitions.
MULTI_AGENT_VELOCITY_PARTITIONS = {
    "HalfCheetah": ("2x3", "6x1"), "Ant": ("2x4", "4x2"), "Hopper": ("3x1",), "Humanoid": ("9|8",),
    "Swimmer": ("2x1",), "Walker2d": ("2x3",),
}
#: Two-hand tasks (``sg_torchrl.envs.hands.TASKS``): episode length (Isaac Gym's ``episodeLength``), and the
#: safety variants (``SAFETY_VARIANTS``).
HAND_TASKS = {"HandOver": 75, "CatchOver2Underarm": 75}
HAND_SAFETY_VARIANTS = ("SafeJoint", "SafeFinger")
#: The Vision ids' image side (``sg_torchrl.envs.vision.DEFAULT_IMAGE_SIZE``): Safety-Gymnasium's 256.
VISION_IMAGE_SIZE = 256
#: The Vision ids' ``obs_mode``: the vector and the image, as Safety-Gymnasium's Vision envs observe.
VISION_OBS_MODE = "vector+rgb"


def _register_velocity() -> None:
    for robot in VELOCITY_ROBOTS:
        for version in VELOCITY_VERSIONS:
            register(EnvEntry(
                env_id=f"Safety{robot}Velocity-v{version}", constructor=_VELOCITY, family="velocity", robot=robot,
                task="Velocity", max_episode_steps=1000, kwargs={"robot": robot, "version": version},
            ))


def _register_navigation() -> None:
    """``Safety{Robot}{Task}{Level}-v0`` and its ``...Vision-v0`` twin for every navigation task and level.

    A Vision id is the same env as the plain id (task, level, episode length, costs) that also sees
    through the robot's ``vision`` camera: by default the flat vector and a 256 x 256 RGB image
    (``obs_mode="vector+rgb"``, ``image_size=256``), what Safety-Gymnasium's Vision envs observe.
    Smaller images (``image_size=64``) or pixels only (``obs_mode="rgb"``) are options.
    """
    for task, (levels, steps) in NAVIGATION_TASKS.items():
        for level in range(levels):
            for robot in NAVIGATION_ROBOTS:
                for suffix, family, options in (
                    ("", "navigation", {}),
                    ("Vision", VISION_FAMILY, {"obs_mode": VISION_OBS_MODE, "image_size": VISION_IMAGE_SIZE}),
                ):
                    register(EnvEntry(
                        env_id=f"Safety{robot}{task}{level}{suffix}-v0", constructor=_NAVIGATION, family=family,
                        robot=robot, task=task, level=level, max_episode_steps=steps,
                        kwargs={"robot": robot, "task": task, "level": level}, options=options,
                    ))


def _register_multi_agent_velocity() -> None:
    for robot, partitions in MULTI_AGENT_VELOCITY_PARTITIONS.items():
        for conf in partitions:
            register(EnvEntry(
                env_id=f"Safety{conf}{robot}Velocity-v0", constructor=_MULTI_AGENT_VELOCITY,
                family="multi_agent_velocity", robot=robot, task="Velocity", max_episode_steps=1000,
                kwargs={"scenario": robot, "agent_conf": conf},
            ))


def _register_multi_agent_navigation() -> None:
    for task, (levels, steps) in MULTI_AGENT_NAVIGATION_TASKS.items():
        for level in range(levels):
            for robot in MULTI_AGENT_NAVIGATION_ROBOTS:
                register(EnvEntry(
                    env_id=f"Safety{robot}{task}{level}-v0", constructor=_MULTI_AGENT_NAVIGATION,
                    family="multi_agent_navigation", robot=robot, task=task, level=level, max_episode_steps=steps,
                    kwargs={"robot": robot, "task": task, "level": level},
                ))


def _register_dexhands() -> None:
    """``ShadowHand{Over,CatchOver2Underarm}{SafeJoint,SafeFinger}-v0``: the paper's safe dexterous-hand ids.

    Ids are the paper's task names (section 4.4: ShadowHandOver, ShadowHandCatchOver2Underarm, each
    SafeJoint or SafeFinger) with Safety-Gymnasium's ``-v0`` suffix; 75 steps per episode (Isaac
    Gym's ``episodeLength``). The paper uses one name for the single- and the multi-agent form (the
    algorithm decides); here the multi-agent form, one agent per hand, is ``MultiAgent`` + the id.
    See :mod:`sg_torchrl.envs.hands`.
    """
    for task, steps in HAND_TASKS.items():
        for safety in HAND_SAFETY_VARIANTS:
            env_id = f"ShadowHand{task.removeprefix('Hand')}{safety}-v0"
            for prefix, constructor, family in (("", _SHADOW_HAND, "dexhands"),
                                                ("MultiAgent", _MULTI_AGENT_SHADOW_HAND, "multi_agent_dexhands")):
                register(EnvEntry(
                    env_id=prefix + env_id, constructor=constructor, family=family, robot="ShadowHand", task=task,
                    max_episode_steps=steps, kwargs={"task": task, "safety": safety},
                ))


_register_velocity()
_register_navigation()
_register_multi_agent_velocity()
_register_multi_agent_navigation()
_register_dexhands()
