"""``make`` / ``register``: Safety-Gymnasium 1.0.0's registry on sg_torchrl's envs.

(The original's ``safety_gymnasium.utils.registration``.)

* :data:`safe_registry`: the set of ids :func:`make` accepts: every sg_torchrl id
  (:func:`sg_torchrl.list_envs`: the original's navigation, vision and velocity ids, the
  multi-agent ids, and sg_torchrl's own additions) plus the ids added with :func:`register`.
* :func:`make` builds an sg_torchrl single-agent id as the original builds its envs: the env
  (:class:`sg_torchrl.gym.SafetyGymnasiumEnv`, 6-tuple steps) wrapped in
  :class:`~.wrappers.SafePassiveEnvChecker` (unless ``disable_env_checker=True``), gymnasium's
  ``OrderEnforcing``, :class:`~.wrappers.SafeTimeLimit` (``max_episode_steps``, or the id's
  registered length: 1000 for the Goal/Button/Push/velocity ids, 500 for Circle/Run/Race) and,
  with ``autoreset=True``, :class:`~.wrappers.SafeAutoResetWrapper`. So ``env.spec.max_episode_steps``
  is that integer, as in the original. A multi-agent id gives a :class:`~.multi_agent.SafeMAEnv`
  (what ``make_ma`` returns). An id added with :func:`register` is built from its entry point and
  wrapped the same way.
* Keyword arguments go to the env: render options (``render_mode``, ``width``, ``height``,
  ``camera_name``, ``camera_id``) and sg_torchrl's options (``cost_mode``, ``velocity_threshold``, ...);
  one it does not take raises ``TypeError``. Without a camera, the navigation ids render from the
  robot's ``"vision"`` camera, as the original's do (the velocity ids: the env's side view).

Differences from the original: ``max_episode_steps`` larger than the id's registered length lengthens
the episodes (the original's navigation tasks still stop at their own length); ``apply_api_compatibility``
is refused (current gymnasium no longer has the old gym step API's compatibility layer).
"""

from __future__ import annotations

import copy
from typing import Any

import gymnasium
from gymnasium.envs.registration import EnvSpec, load_env_creator
from gymnasium.wrappers import OrderEnforcing

from sg_torchrl.envs.registry import list_envs, registry_entry
from sg_torchrl.safety_gymnasium.wrappers import SafeAutoResetWrapper, SafePassiveEnvChecker, SafeTimeLimit

__all__ = ["make", "register", "safe_registry", "spec"]

safe_registry: set[str] = set(list_envs())
"""Ids :func:`make` accepts (sg_torchrl's ids and those added with :func:`register`)."""

_SG_IDS = frozenset(safe_registry)
# Families whose frames the original renders, by default, from the robot's own "vision" camera.
_EGOCENTRIC_FAMILIES = ("navigation", "vision")


def register(**kwargs: Any) -> None:
    """Register an env for :func:`make` (and in gymnasium's registry): ``gymnasium.register``'s arguments.

    The env's ``step`` must return Safety-Gymnasium's 6-tuple ``(obs, reward, cost, terminated,
    truncated, info)``.
    """
    if "id" not in kwargs:
        raise TypeError("register() needs an id=... (and an entry_point=...), as gymnasium.register")
    gymnasium.register(**kwargs)
    safe_registry.add(kwargs["id"])


def spec(env_id: str) -> EnvSpec:
    """The registered spec of ``env_id`` (gymnasium's registry), as ``gymnasium.spec``."""
    return gymnasium.spec(env_id)


def make(
    id: str | EnvSpec,  # noqa: A002 - the original's (and gymnasium's) keyword: clients pass make(id=...)
    max_episode_steps: int | None = None,
    autoreset: bool | None = None,
    apply_api_compatibility: bool | None = None,
    disable_env_checker: bool | None = None,
    **kwargs: Any,
) -> gymnasium.Env:
    """Build the env ``id`` with Safety-Gymnasium's wrappers (module docstring).

    Args:
        id: an id of :data:`safe_registry`, or an ``EnvSpec``.
        max_episode_steps: episode length of the :class:`~.wrappers.SafeTimeLimit` (default: the
            id's registered length).
        autoreset: add :class:`~.wrappers.SafeAutoResetWrapper` (same-step reset, the finished
            episode's last observation and info in ``info["final_observation"]`` / ``["final_info"]``).
        apply_api_compatibility: refused (gymnasium 1.x has no layer for the old gym step API).
        disable_env_checker: ``True`` leaves out :class:`~.wrappers.SafePassiveEnvChecker`.
        **kwargs: the env's keyword arguments (render options, sg_torchrl options).

    Raises:
        gymnasium.error.Error: ``id`` is not in :data:`safe_registry`.
        TypeError: a keyword argument the env does not take.
        ValueError: ``max_episode_steps`` not a positive integer; ``autoreset`` for a multi-agent id.
    """
    if max_episode_steps is not None and (isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, int)
                                          or max_episode_steps < 1):
        raise ValueError(f"max_episode_steps must be a positive integer or None, got {max_episode_steps!r}")
    if isinstance(id, EnvSpec):
        env_spec = id
    else:
        if not isinstance(id, str) or id not in safe_registry:
            raise gymnasium.error.Error(
                f"Environment {id!r} is not registered in safety-gymnasium (sg_torchrl's drop-in). "
                f"Known ids: sg_torchrl.list_envs() and those added with register(); twins "
                f"'<Name>Gymnasium-v<k>' are built with gymnasium.make")
        if id in _SG_IDS:
            return _make_sg(id, max_episode_steps, autoreset, apply_api_compatibility, disable_env_checker, kwargs)
        env_spec = gymnasium.spec(id)
    return _make_registered(env_spec, max_episode_steps, autoreset, apply_api_compatibility, disable_env_checker,
                            kwargs)


def _make_sg(env_id, max_episode_steps, autoreset, apply_api_compatibility, disable_env_checker, kwargs):
    """An sg_torchrl id: the gymnasium façade env (or the multi-agent env) with the original's wrappers."""
    if apply_api_compatibility:
        raise ValueError(f"{env_id}: apply_api_compatibility is for envs with the old gym step API; "
                         "sg_torchrl envs use the current one")
    if registry_entry(env_id).multi_agent:
        if autoreset:
            raise ValueError(f"{env_id} is a multi-agent env (PettingZoo API): autoreset is not available, "
                             "reset it when every agent is done")
        from sg_torchrl.safety_gymnasium.multi_agent import SafeMAEnv

        if max_episode_steps is not None:
            kwargs["max_episode_steps"] = max_episode_steps
        return SafeMAEnv.from_id(env_id, **kwargs)
    from sg_torchrl.gym import make as make_facade

    length = max_episode_steps if max_episode_steps is not None else registry_entry(env_id).max_episode_steps
    options = dict(kwargs)
    if (options.get("render_mode") is not None and registry_entry(env_id).family in _EGOCENTRIC_FAMILIES
            and all(options.get(key) is None for key in ("camera", "camera_name", "camera_id"))):
        options["camera_name"] = "vision"  # the original's navigation envs render from the robot's camera
    if max_episode_steps is not None and "max_episode_steps" not in options:
        options["max_episode_steps"] = max(max_episode_steps, registry_entry(env_id).max_episode_steps)
    env = make_facade(env_id, **options)
    return _wrap(env, length, autoreset, disable_env_checker)


def _make_registered(env_spec: EnvSpec, max_episode_steps, autoreset, apply_api_compatibility, disable_env_checker,
                     kwargs):
    """An env added with :func:`register` (or given as an ``EnvSpec``): built from its entry point."""
    env_kwargs = {**copy.deepcopy(env_spec.kwargs or {}), **kwargs}
    if env_spec.entry_point is None:
        raise gymnasium.error.Error(f"{env_spec.id} is registered without an entry_point")
    creator = env_spec.entry_point if callable(env_spec.entry_point) else load_env_creator(env_spec.entry_point)
    if apply_api_compatibility:  # gymnasium 1.x dropped the old-API compatibility layer
        raise NotImplementedError(f"{env_spec.id}: the old gym step API (apply_api_compatibility) is not supported")
    env = creator(**env_kwargs)
    env.unwrapped.spec = EnvSpec(
        id=env_spec.id, entry_point=env_spec.entry_point, reward_threshold=env_spec.reward_threshold,
        nondeterministic=env_spec.nondeterministic, max_episode_steps=None, order_enforce=False,
        disable_env_checker=True, kwargs=env_kwargs,
    )
    if disable_env_checker is None:
        disable_env_checker = env_spec.disable_env_checker
    length = max_episode_steps if max_episode_steps is not None else env_spec.max_episode_steps
    if autoreset is None:
        autoreset = getattr(env_spec, "autoreset", False)  # a field of gymnasium 0.28's EnvSpec, not of 1.x's
    return _wrap(env, length, autoreset, disable_env_checker, order_enforce=env_spec.order_enforce)


def _wrap(env: gymnasium.Env, length: int | None, autoreset: bool | None, disable_env_checker: bool | None,
          order_enforce: bool = True) -> gymnasium.Env:
    """The original's wrapper stack: checker, order enforcing, time limit, autoreset (inside out)."""
    if not disable_env_checker:
        env = SafePassiveEnvChecker(env)
    if order_enforce:
        env = OrderEnforcing(env)
    if length is not None:
        env = SafeTimeLimit(env, int(length))
    if autoreset:
        env = SafeAutoResetWrapper(env)
    return env
