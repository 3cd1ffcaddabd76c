"""The env registry: an explicit table from Safety-Gymnasium env id to constructor.

Ids are Safety-Gymnasium's, unchanged, so results and configs carry over. The table is
explicit (no class names derived from id strings), which lets the registry-wide tests iterate
it and lets an unknown id get a helpful error listing the closest valid ids.
"""

from __future__ import annotations

import difflib
import inspect
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import torch

from sg_torchrl.envs.base import SafeEnv

__all__ = ["EnvEntry", "env_options", "MULTI_AGENT_FAMILIES", "VISION_FAMILY", "UnknownEnvError", "make", "list_envs", "register", "registry_entry"]

#: The family of the ``...Vision-v0`` ids: navigation tasks observed through the robot's camera.
VISION_FAMILY = "vision"

#: Families whose envs use TorchRL's multi-agent layout (group ``"agents"``, no root ``observation``).
MULTI_AGENT_FAMILIES = frozenset({"multi_agent_velocity", "multi_agent_navigation", "multi_agent_dexhands"})

#: Robots of the multi-agent navigation ids (Safety-Gymnasium's paper and SafePO name these six).
MULTI_AGENT_NAVIGATION_ROBOTS = ("Point", "Ant")


class UnknownEnvError(KeyError):
    """Raised by :func:`make` for an id that is not registered."""

    def __str__(self) -> str:  # KeyError would quote the whole message
        return str(self.args[0])


@dataclass(frozen=True)
class EnvEntry:
    """One registered env id.

    Args:
        env_id: Safety-Gymnasium id, e.g. ``"SafetyHalfCheetahVelocity-v1"``.
        constructor: builds the env; receives ``num_envs``, ``device``, ``seed`` and options.
        family: ``"velocity"``, ``"navigation"``, ``"vision"`` (navigation seen through the robot's
            camera), ``"multi_agent_velocity"``, ``"multi_agent_navigation"``, ``"dexhands"`` (two
            Shadow Hands, :mod:`sg_torchrl.dexhands`), ``"multi_agent_dexhands"`` (the same, one agent per hand).
        robot / task / level: metadata for filtering and tables (``level`` is ``None`` where the
            family has no levels).
        max_episode_steps: the reference's episode length.
        kwargs: fixed constructor arguments for this id (robot, task, level, ...).
        options: default values of options this id sets differently from the constructor
            (e.g. ``obs_mode="rgb"`` for the Vision ids); users may override them.
    """

    env_id: str
    constructor: Callable[..., SafeEnv]
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


_REGISTRY: dict[str, EnvEntry] = {}


def register(entry: EnvEntry) -> None:
    """Add an id to the registry; re-registering an id is an error."""
    if entry.env_id in _REGISTRY:
        raise ValueError(f"env id {entry.env_id!r} is already registered")
    _REGISTRY[entry.env_id] = entry


def registry_entry(env_id: str) -> EnvEntry:
    """The :class:`EnvEntry` for ``env_id``; unknown ids raise :class:`UnknownEnvError`."""
    try:
        return _REGISTRY[env_id]
    except KeyError:
        close = difflib.get_close_matches(env_id, list(_REGISTRY), n=3, cutoff=0.5)
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
    seed: int | None = None,
    **options: Any,
) -> SafeEnv:
    """Build the env registered as ``env_id`` with ``num_envs`` simulators in one process.

    Args:
        env_id: a Safety-Gymnasium id (see :func:`list_envs`).
        num_envs: simulators stepped by the returned env (its ``batch_size`` is ``[num_envs]``).
        device: device of the emitted TensorDicts.
        seed: seed of the per-simulator generators (``None``: fresh OS entropy).
        **options: task options, e.g. ``cost_mode="raw"``, ``max_episode_steps=500``, or for the
            navigation ids ``obs_mode="vector+rgbd"``, ``image_size=256`` (pixel observations).

    Example:
        >>> env = make("SafetyHalfCheetahVelocity-v1", num_envs=8, seed=0)
        >>> rollout = env.rollout(10)
        >>> rollout["next", "cost"].shape
        torch.Size([8, 10, 1])
    """
    entry = registry_entry(env_id)
    accepted = env_options(env_id)
    unknown = sorted(set(options) - set(accepted)) if accepted is not None else []
    if unknown:
        raise TypeError(
            f"{env_id}: unknown option(s) {', '.join(map(repr, unknown))}; it takes {', '.join(accepted)}"
        )
    kwargs = {**entry.kwargs, "max_episode_steps": entry.max_episode_steps, **entry.options, **options}
    return entry.constructor(num_envs=num_envs, device=device, seed=seed, **kwargs)


def env_options(env_id: str) -> list[str] | None:
    """The keyword options :func:`make` accepts for ``env_id`` (besides ``num_envs``, ``device``, ``seed``).

    They are the constructor's keyword parameters less the ones the registry entry fixes (robot,
    task, level, ...): e.g. ``cost_mode``, ``max_episode_steps``, ``velocity_threshold``. ``None``
    when the constructor takes arbitrary keywords (``**kwargs``): then it checks them itself.
    """
    entry = registry_entry(env_id)
    fixed = {"self", "num_envs", "device", "seed", *entry.kwargs}
    # A class's own __init__: EnvBase's metaclass hides it behind ``__call__(*args, **kwargs)``.
    constructor = entry.constructor.__init__ if isinstance(entry.constructor, type) else entry.constructor
    parameters = inspect.signature(constructor).parameters.values()
    if any(p.kind is p.VAR_KEYWORD for p in parameters):
        return None
    return [p.name for p in parameters if p.name not in fixed and p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)]


def _register_velocity() -> None:
    from sg_torchrl.envs.velocity import ROBOTS, VelocityEnv

    for robot in ROBOTS.values():
        for version in sorted(robot.thresholds):
            register(
                EnvEntry(
                    env_id=f"Safety{robot.name}Velocity-v{version}",
                    constructor=VelocityEnv,
                    family="velocity",
                    robot=robot.name,
                    task="Velocity",
                    max_episode_steps=1000,
                    kwargs={"robot": robot.name, "version": version},
                )
            )


def _register_navigation() -> None:
    """``Safety{Robot}{Task}{Level}-v0`` and its ``...Vision-v0`` twin for every navigation task and level.

    A Vision id is the same env as the plain id (task, level, episode length, costs) observed through
    the robot's ``vision`` camera: ``obs_mode="rgb"`` at 64 x 64 by default (Safety-Gymnasium's
    Vision envs render 256 x 256 next to the vector: ``obs_mode="vector+rgb"``, ``image_size=256``).
    """
    from sg_torchrl.envs.navigation import ROBOTS, TASKS, NavigationEnv
    from sg_torchrl.envs.vision import DEFAULT_IMAGE_SIZE

    for task, levels in TASKS.items():
        for level, factory in sorted(levels.items()):
            steps = factory().max_episode_steps
            for robot in ROBOTS:
                for suffix, family, options in (
                    ("", "navigation", {}),
                    ("Vision", VISION_FAMILY, {"obs_mode": "rgb", "image_size": DEFAULT_IMAGE_SIZE}),
                ):
                    register(
                        EnvEntry(
                            env_id=f"Safety{robot}{task}{level}{suffix}-v0",
                            constructor=NavigationEnv,
                            family=family,
                            robot=robot,
                            task=task,
                            level=level,
                            max_episode_steps=steps,
                            kwargs={"robot": robot, "task": task, "level": level},
                            options=options,
                        )
                    )


def _register_multi_agent_velocity() -> None:
    from sg_torchrl.envs.multi_agent import SCENARIOS, MultiAgentVelocityEnv

    for scenario in SCENARIOS.values():
        for conf in scenario.partitions:
            register(
                EnvEntry(
                    env_id=f"Safety{conf}{scenario.robot}Velocity-v0",
                    constructor=MultiAgentVelocityEnv,
                    family="multi_agent_velocity",
                    robot=scenario.robot,
                    task="Velocity",
                    max_episode_steps=1000,
                    kwargs={"scenario": scenario.robot, "agent_conf": conf},
                )
            )


def _register_multi_agent_navigation() -> None:
    from sg_torchrl.envs.multi_agent import MultiAgentNavigationEnv
    from sg_torchrl.envs.navigation import MULTI_AGENT_TASKS

    for task, levels in MULTI_AGENT_TASKS.items():
        for level, factory in sorted(levels.items()):
            for robot in MULTI_AGENT_NAVIGATION_ROBOTS:
                register(
                    EnvEntry(
                        env_id=f"Safety{robot}{task}{level}-v0",
                        constructor=MultiAgentNavigationEnv,
                        family="multi_agent_navigation",
                        robot=robot,
                        task=task,
                        level=level,
                        max_episode_steps=factory().max_episode_steps,
                        kwargs={"robot": robot, "task": task, "level": level},
                    )
                )


def _register_dexhands() -> None:
    """``ShadowHand{Over,CatchOver2Underarm}{SafeJoint,SafeFinger}-v0``: the paper's safe dexterous-hand ids.

    Ids are the paper's task names (section 4.4: ShadowHandOver, ShadowHandCatchOver2Underarm, each
    SafeJoint or SafeFinger) with Safety-Gymnasium's ``-v0`` suffix; 75 steps per episode (Isaac
    Gym's ``episodeLength``). The paper uses one name for the single- and the multi-agent form (the
    algorithm decides); here the multi-agent form, one agent per hand, is ``MultiAgent`` + the id.
    See :mod:`sg_torchrl.dexhands`.
    """
    from sg_torchrl.dexhands import SAFETY_VARIANTS, TASKS, MultiAgentShadowHandEnv, ShadowHandEnv

    for task in TASKS.values():
        for safety in SAFETY_VARIANTS:
            env_id = f"ShadowHand{task.name.removeprefix('Hand')}{safety}-v0"
            for prefix, constructor, family in (("", ShadowHandEnv, "dexhands"),
                                                ("MultiAgent", MultiAgentShadowHandEnv, "multi_agent_dexhands")):
                register(
                    EnvEntry(
                        env_id=prefix + env_id,
                        constructor=constructor,
                        family=family,
                        robot="ShadowHand",
                        task=task.name,
                        max_episode_steps=task.max_episode_steps,
                        kwargs={"task": task.name, "safety": safety},
                    )
                )


_register_velocity()
_register_navigation()
_register_multi_agent_velocity()
_register_multi_agent_navigation()
_register_dexhands()
