"""Gymnasium façade: Safety-Gymnasium's single-env API on top of the TorchRL envs.

This is the migration path for code written against Safety-Gymnasium:

>>> import sg_torchrl.gym
>>> env = sg_torchrl.gym.make("SafetyHalfCheetahVelocity-v1")
>>> obs, info = env.reset(seed=0)
>>> obs, reward, cost, terminated, truncated, info = env.step(env.action_space.sample())
>>> sorted(info)
['cost_sum', 'cost_velocity']

API
---
* :func:`make` ``(env_id, *, cost_in_info=False, render_mode=None, **options)`` builds one
  simulator of the sg_torchrl env ``env_id`` (``sg_torchrl.make(env_id, num_envs=1, **options)``)
  and wraps it in a :class:`gymnasium.Env`. ``options`` are the sg_torchrl options
  (``max_episode_steps``, ``cost_mode``, ``seed``, ...).
* :class:`SafetyGymnasiumEnv` (what ``make`` returns by default): ``step(action)`` returns
  Safety-Gymnasium's **6-tuple** ``(obs, reward, cost, terminated, truncated, info)``; ``obs`` is a
  ``float64`` numpy array, ``reward`` and ``cost`` python floats, the flags python bools, and
  ``info`` holds one ``cost_<name>`` per constraint (the ``("cost_info", name)`` entries of the
  TorchRL env, e.g. ``cost_hazards``) plus ``cost_sum`` (equal to ``cost``); envs with a
  ``step_info`` (the velocity ids) first put gymnasium's terms there (``x_velocity``,
  ``reward_ctrl``, ... as Safety-Gymnasium's info).
  ``reset(seed=None, options=None)`` returns ``(obs, {})``. A seed re-seeds the simulator (same
  seed, same initial observation and, with the same actions, the same trajectory); no seed continues
  the random stream. ``options`` (a dict or ``None``) is ignored, as by Safety-Gymnasium's own envs.
* :class:`GymnasiumEnv` (``make(env_id, cost_in_info=True)``, or ``make`` of a twin id): the same
  env with gymnasium's usual **5-tuple** ``(obs, reward, terminated, truncated, info)`` and the cost
  in ``info["cost"]``, like Safety-Gymnasium's ``Safety<Name>Gymnasium-v<k>`` twins. It passes
  :func:`gymnasium.utils.env_checker.check_env`.
* Errors: ``step`` before the first ``reset`` or after the episode ended raises
  :class:`EpisodeEndedError` (a ``gymnasium.error.ResetNeeded`` that is also an ``AssertionError``,
  which is what Safety-Gymnasium raises there); an action whose shape differs from
  ``action_space.shape``, or that is not finite, raises ``ValueError``; an option the env does not
  take raises ``TypeError`` worded as Python words it (``... got an unexpected keyword argument
  'frameskip'``), which TorchRL's ``GymEnv`` relies on to drop its ``frameskip``. Actions outside the bounds
  are clipped, as in Safety-Gymnasium. An unknown ``render_mode`` raises ``ValueError``, reset
  ``options`` that are not a dict ``TypeError``. Using a closed env raises
  ``gymnasium.error.ClosedEnvironmentError``; ``close()`` may be called twice.
* Rendering: gymnasium's render modes (``"rgb_array"``, ``"depth_array"``, their ``*_list`` forms and
  ``"human"``) with options ``width``, ``height`` and ``camera`` (or Safety-Gymnasium's ``camera_name`` /
  ``camera_id``); the default camera follows the robot. See :mod:`sg_torchrl.render_modes`.
* ``copy.deepcopy(env)`` builds a new env with the same id and options and loads the simulator's
  state into it (:meth:`~sg_torchrl.envs.base.SafeEnv.sim_state`: physics, random streams, step
  counter, layout): the copy's next step, given the same action, equals the original's.
* Pixel observations (the ``...Vision-v0`` ids, or ``obs_mode="rgb"`` etc.): ``obs`` is a dict under a
  ``gymnasium.spaces.Dict`` observation space. With the vector and the image (the Vision ids' default,
  ``obs_mode="vector+rgb"``) it is Safety-Gymnasium's own dict: one ``float64`` entry per vector part
  in observation order (``accelerometer``, ..., ``<object>_lidar``), then ``"vision"`` ``(H, W, 3)``
  ``uint8`` (:class:`~sg_torchrl.envs.vision.DictLayout`; ``"depth"`` ``(H, W, 1)`` ``float32`` metres
  last in RGB-D modes). Pixels alone give ``"vision"`` (and ``"depth"``). These envs step through the
  TorchRL ``step``.
* The values are exactly the TorchRL env's (``float32`` observations, rewards and costs widened to
  ``float64`` / python floats; actions cast to ``float32``, the action spec's dtype): a policy
  evaluated through the façade sees the same inputs as in TorchRL training.

Gymnasium's registry and the 6-tuple
------------------------------------
Importing sg_torchrl registers, for every single-agent id of :func:`sg_torchrl.list_envs`, the id itself and
its twin ``<Name>Gymnasium-v<k>`` in gymnasium's registry (:func:`register_envs`, idempotent; call
it again after registering new sg_torchrl ids; :mod:`sg_torchrl.gym_registration`). What ``gymnasium.make`` (1.4) does to an env: it
wraps it in ``PassiveEnvChecker`` (whose first ``step`` raises ``gymnasium.error.Error`` unless the
result has 4 or 5 elements), then ``OrderEnforcing`` (passes any result through), then
``TimeLimit`` when the spec or the call gives ``max_episode_steps`` (it unpacks exactly 5 values, so
a 6-tuple env fails with "too many values to unpack"). Hence:

* **Plain ids** (6-tuple) are registered with ``disable_env_checker=True``, ``order_enforce=False``
  and ``max_episode_steps=None``: ``gymnasium.make(id)`` returns the bare
  :class:`SafetyGymnasiumEnv`, which checks call order itself and truncates episodes itself at the
  registry's length (``env.max_episode_steps``). Do **not** pass ``max_episode_steps`` to
  ``gymnasium.make`` for these ids (gymnasium would add its 5-tuple ``TimeLimit``): use
  ``sg_torchrl.gym.make(id, max_episode_steps=k)`` or a twin id.
* **Twin ids** (5-tuple) are ordinary gymnasium envs: passive checker, ``OrderEnforcing`` and
  ``TimeLimit(max_episode_steps=<registry length>)``. Gymnasium's ``TimeLimit`` is the one time
  limit (the spec kwargs build the inner env with ``max_episode_steps=None``, no internal limit), so
  ``gymnasium.make(twin, max_episode_steps=k)`` gives episodes of ``k`` steps and ``-1`` none.

Speed
-----
For a :class:`~sg_torchrl.envs.base.SafeEnv` whose ``_step`` is SafeEnv's own the step runs the env's public numpy interface
(:meth:`~sg_torchrl.envs.base.SafeEnv.step_one`: the body of its TorchRL step without building
TensorDicts, on Python values), several times cheaper than ``env.step(td)`` on one simulator
(``benchmarks/single_env_speed.py`` sets it beside bare MuJoCo and Safety-Gymnasium 1.0.0); envs
that override ``_step`` (or are not a ``SafeEnv``) go through the public TorchRL ``step``. Both paths give identical data (tested).
"""

from __future__ import annotations

import copy
import math
from collections import OrderedDict
from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDict

from sg_torchrl.envs.info import numpy_scalar_info
from sg_torchrl.envs.vision.layout import DictLayout
from sg_torchrl.envs.registry import env_options, list_envs, registry_entry
from sg_torchrl.envs.registry import make as make_torchrl_env
from sg_torchrl.facade import EpisodeEndedError, SimulatorFacade
from sg_torchrl.gym_registration import ENTRY_POINT, TWIN_SUFFIX, gymnasium_twin_id, register_envs
from sg_torchrl.render_modes import (
    RENDER_MODES,
    RENDER_OPTIONS,
    FrameSource,
    available_render_modes,
    split_render_options,
)

__all__ = [
    "EpisodeEndedError",
    "GymnasiumEnv",
    "SafetyGymnasiumEnv",
    "gymnasium_twin_id",
    "make",
    "register_envs",
]

_ENTRY_POINT = ENTRY_POINT  # not __name__: stable when this file runs as a script
_TWIN_SUFFIX = TWIN_SUFFIX
# What ``max_episode_steps=None`` ("no internal limit") becomes for the TorchRL env, which needs an
# int: effectively unlimited, and within int32 wherever a task stores it.
_NO_LIMIT = 2**31 - 1


def _split_twin_id(env_id: str) -> tuple[str, bool]:
    """``(sg_torchrl id, is_twin)`` for a plain or a twin id."""
    name, sep, version = env_id.rpartition("-v")
    if sep and name.endswith(_TWIN_SUFFIX):
        base = f"{name[: -len(_TWIN_SUFFIX)]}-v{version}"
        if base in list_envs():
            return base, True
    return env_id, False


def make(
    env_id: str,
    *,
    cost_in_info: bool = False,
    render_mode: str | None = None,
    **options: Any,
) -> SafetyGymnasiumEnv:
    """Build a gymnasium env for one simulator of the sg_torchrl env ``env_id``.

    Args:
        env_id: an id of :func:`sg_torchrl.list_envs`, or its twin ``<Name>Gymnasium-v<k>`` (which
            implies ``cost_in_info=True``).
        cost_in_info: ``False``: Safety-Gymnasium's 6-tuple step (:class:`SafetyGymnasiumEnv`).
            ``True``: gymnasium's 5-tuple with ``info["cost"]`` (:class:`GymnasiumEnv`).
        render_mode: ``None`` or one of :data:`~sg_torchrl.render_modes.RENDER_MODES` (then
            ``width``, ``height``, ``camera`` / ``camera_name`` / ``camera_id`` options too).
        **options: sg_torchrl options, e.g. ``max_episode_steps=500`` (``None``: no internal limit),
            ``cost_mode="raw"``, ``seed=0`` (seed at construction; ``reset(seed=...)`` also works).

    This is also the entry point of every id registered in gymnasium's registry.
    """
    base_id, is_twin = _split_twin_id(env_id)
    cls = GymnasiumEnv if (cost_in_info or is_twin) else SafetyGymnasiumEnv
    env = cls(base_id, render_mode=render_mode, **options)
    # A spec that re-creates this very env (bare, same options) with ``gymnasium.make(env.spec)``;
    # gymnasium.make replaces it by its own when it built the env.
    env.spec = gymnasium.envs.registration.EnvSpec(
        id=env_id,
        entry_point=_ENTRY_POINT,
        max_episode_steps=None,
        order_enforce=False,
        disable_env_checker=True,
        kwargs={"env_id": env_id, "cost_in_info": cost_in_info, **options},
    )
    return env


class SafetyGymnasiumEnv(SimulatorFacade, gymnasium.Env):
    """One sg_torchrl simulator behind Safety-Gymnasium's ``gymnasium.Env`` API (6-tuple step).

    Args:
        env_id: an id of :func:`sg_torchrl.list_envs`.
        render_mode: ``None`` or one of :data:`~sg_torchrl.render_modes.RENDER_MODES`.
        **options: sg_torchrl options and render options (see :func:`make`).

    The wrapped TorchRL env is :attr:`torchrl_env` (``batch_size=[1]``).
    """

    metadata = {"render_modes": list(RENDER_MODES)}

    def __init__(self, env_id: str, render_mode: str | None = None, **options: Any) -> None:
        self._options = dict(options)  # what a deepcopy rebuilds the env from
        self.metadata = {**self.metadata, "render_modes": available_render_modes()}  # no "human" when headless
        render_options = split_render_options(options)
        if "num_envs" in options:
            raise TypeError(
                "the gymnasium façade steps one simulator; use sg_torchrl.make(env_id, num_envs=N) "
                "for a batched TorchRL env"
            )
        if registry_entry(env_id).multi_agent:
            raise ValueError(f"{env_id!r} is a multi-agent env: use sg_torchrl.pettingzoo.make({env_id!r})")
        _check_options(env_id, options)
        if "max_episode_steps" in options and options["max_episode_steps"] is None:
            options["max_episode_steps"] = _NO_LIMIT
        self.env_id = env_id
        self.render_mode = render_mode
        env = make_torchrl_env(env_id, num_envs=1, **options)
        self._env = env
        fps = 30.0
        if render_mode is not None and hasattr(env, "physics"):
            fps = 1.0 / (env.frame_skip * env.physics.timestep)
            self.metadata = {**self.metadata, "render_fps": round(fps)}
        self._frames = FrameSource(env, render_mode, render_options, fps=fps) if render_mode is not None else None
        observation_spec = env.observation_spec
        self._pixels = "pixels" in observation_spec.keys()
        # Navigation envs with the vector and the image (the Vision ids' default): Safety-Gymnasium's dict.
        self._dict_layout = _original_dict_layout(env) if self._pixels else None
        if self._dict_layout is not None:
            # An OrderedDict keeps the original's key order (gymnasium sorts a plain dict's keys).
            self.observation_space = spaces.Dict(OrderedDict(
                (entry.name, spaces.Box(entry.low, entry.high, shape=entry.shape, dtype=np.dtype(entry.dtype)))
                for entry in self._dict_layout.entries))
        else:
            self.observation_space = _observation_space(observation_spec, getattr(env, "observation_slices", None))
        action_spec = env.action_spec
        box = getattr(action_spec, "space", None)
        if box is not None and hasattr(box, "low"):
            low, high = box.low[0].cpu().numpy(), box.high[0].cpu().numpy()
        else:
            low = np.full(action_spec.shape[1:], -np.inf, dtype=np.float32)
            high = np.full(action_spec.shape[1:], np.inf, dtype=np.float32)
        self.action_space = spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)
        self._action_shape = self.action_space.shape
        self._constraints = tuple(observation_spec["cost_info"].keys())
        self._info_keys = tuple(f"cost_{name}" for name in self._constraints)
        # Gymnasium's info terms (x_velocity, reward_ctrl, ...) where the env reports them (velocity ids).
        self._step_info = getattr(env, "step_info", None)
        # Numpy fast path: only where the env's _step is marked as the one its flat numpy interface
        # reproduces (sg_torchrl.envs.step_hooks), so every hook it calls is the one the TorchRL step would
        # call. Anything else goes through the public TorchRL step. Pixel observations are emitted by the
        # TorchRL step only.
        self._fast = getattr(env, "numpy_step_interface", None) == "flat" and not self._pixels
        self._needs_reset = True
        self._closed = False

    # ------------------------------------------------------------------ properties
    @property
    def max_episode_steps(self) -> int | None:
        """Steps after which the env truncates an episode by itself (``None``: never)."""
        steps = int(self._env.max_episode_steps)
        return None if steps >= _NO_LIMIT else steps

    @property
    def constraint_names(self) -> tuple[str, ...]:
        """Names of the per-constraint costs (``info`` keys are ``cost_<name>``)."""
        return self._constraints

    # ------------------------------------------------------------------ gymnasium API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode; ``seed`` re-seeds the simulator, ``None`` continues its random stream.

        ``options`` (a dict or ``None``) is accepted and ignored, as Safety-Gymnasium's envs do.
        """
        self._check_reset_options(options)
        super().reset(seed=seed)  # seeds self.np_random and validates the seed
        if seed is not None:
            self._env.set_seed(int(seed), static_seed=True)
        td = self._env.reset()
        self._needs_reset = False
        if self._frames is not None:
            self._frames.after_reset()
        return self._observation(td), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, float, bool, bool, dict[str, float]]:
        """Advance one step: ``(obs, reward, cost, terminated, truncated, info)``."""
        return self._transition(action)

    def close(self) -> None:
        """Release the simulator; calling it twice is allowed."""
        if not self._closed:
            self._needs_reset = True  # so that step() reaches the closed-env check
            self._release()

    def __deepcopy__(self, memo: dict) -> SafetyGymnasiumEnv:
        """A new env with the same id and options whose simulator continues exactly from this one's.

        The simulator's state (:meth:`~sg_torchrl.envs.base.SafeEnv.sim_state`) is loaded into the
        copy, so the same action gives both the same next step. Render frames collected so far
        (``*_list`` modes) are copied; the copy opens its own renderer and window.
        """
        clone = self._clone(memo)
        clone._needs_reset = self._needs_reset
        clone._np_random = copy.deepcopy(self._np_random, memo)
        clone._np_random_seed = self._np_random_seed
        clone.spec = copy.deepcopy(self.spec, memo)
        if self._frames is not None:
            clone._frames.copy_frames_from(self._frames)
        return clone

    # ------------------------------------------------------------------ internals
    def _action(self, action: Any) -> np.ndarray:
        """The action as the ``(1, act_dim)`` float32 array the TorchRL env would receive."""
        array = np.asarray(action, dtype=np.float32)
        if array.shape != self._action_shape:
            raise ValueError(
                f"{self.env_id}: action has shape {array.shape}, expected {self._action_shape} "
                f"(action_space={self.action_space})"
            )
        # One float64 sum decides it: float32 values cannot overflow it, and NaN or inf propagates.
        if not math.isfinite(sum(array.tolist() if array.ndim == 1 else array.reshape(-1).tolist())):
            raise ValueError(f"{self.env_id}: action is not finite: {array}")
        return array.reshape(1, -1)

    def _transition(self, action: Any) -> tuple[np.ndarray, float, float, bool, bool, dict[str, float]]:
        if self._needs_reset:
            self._raise_episode_ended()
        action32 = self._action(action)
        if self._fast:
            out = self._fast_step(action32)
        else:
            out = self._torchrl_step(action32)
        self._needs_reset = out[3] or out[4]
        if self._frames is not None:
            self._frames.after_step()
        return out

    def _fast_step(self, action32: np.ndarray):
        """The env's public one-simulator step (:meth:`~sg_torchrl.envs.base.SafeEnv.step_one`), emitting
        the values its TorchRL step would emit (float32 rounding included) without TensorDicts."""
        obs, reward, cost, terminated, truncated, cost_info = self._env.step_one(action32)
        step_info = self._step_info
        info = step_info(0) if step_info is not None else {}
        for key, name in zip(self._info_keys, self._constraints):
            info[key] = cost_info[name]
        info["cost_sum"] = cost
        return obs, reward, cost, terminated, truncated, info

    def _observation(self, td: TensorDict) -> np.ndarray | dict[str, np.ndarray]:
        """Simulator 0's observation in :attr:`observation_space`'s layout (see :func:`_observation_space`)."""
        if not self._pixels:
            return td.get("observation")[0].cpu().numpy().astype(np.float64)
        if self._dict_layout is not None:
            return self._dict_layout.split(td, 0)
        obs = {}
        if "observation" in td.keys():
            obs["observation"] = td.get("observation")[0].cpu().numpy().astype(np.float64)
        # Channels last in both layouts (TorchRL's raw pixels, Safety-Gymnasium's "vision"): no permute.
        obs["vision"] = td.get("pixels")[0].cpu().numpy()
        if "depth" in td.keys():
            obs["depth"] = td.get("depth")[0].cpu().numpy()
        return obs

    def _torchrl_step(self, action32: np.ndarray):
        """The same transition through the public TorchRL ``step``."""
        env = self._env
        td = TensorDict({"action": torch.from_numpy(action32).to(env.device)}, batch_size=env.batch_size)
        nxt = env.step(td).get("next").cpu()
        cost = float(nxt.get("cost")[0, 0])
        cost_info = nxt.get("cost_info")
        info = self._step_info(0) if self._step_info is not None else {}
        info.update((key, float(cost_info.get(name)[0, 0])) for key, name in zip(self._info_keys, self._constraints))
        info["cost_sum"] = cost
        obs = self._observation(nxt)
        terminated, truncated = bool(nxt.get("terminated")[0, 0]), bool(nxt.get("truncated")[0, 0])
        return obs, float(nxt.get("reward")[0, 0]), cost, terminated, truncated, info


def _check_options(env_id: str, options: dict[str, Any]) -> None:
    """Reject options ``env_id`` does not take, in Python's own words for an unknown keyword.

    Callers that build gymnasium envs generically rely on that wording: TorchRL's ``GymEnv`` passes
    ``frameskip`` to ``gymnasium.make`` and drops it (skipping frames in its wrapper instead) only when
    the ``TypeError`` says ``unexpected keyword argument 'frameskip'``; any other message is re-raised.
    """
    accepted = env_options(env_id)
    if accepted is None:  # the constructor takes **kwargs and checks them itself
        return
    accepted = [*accepted, "seed", "device"]  # what sg_torchrl.make takes besides the env's own options
    unknown = [key for key in options if key not in accepted]
    if unknown:
        takes = ", ".join([*accepted, *RENDER_OPTIONS])
        raise TypeError(f"make() got an unexpected keyword argument {unknown[0]!r} "
                        f"({env_id} takes {takes}; unknown: {', '.join(map(repr, unknown))})")


def _original_dict_layout(env) -> DictLayout | None:
    """Safety-Gymnasium's Vision dict layout of ``env`` (one key per vector part, then ``"vision"``),
    or ``None`` where it has none: pixels without the vector (``obs_mode="rgb"``) or an env without
    named observation parts (:class:`~sg_torchrl.envs.vision.DictLayout` needs the navigation envs'
    ``observation_slices``)."""
    keys = env.observation_spec.keys()
    if "observation" not in keys or not hasattr(env, "observation_slices") or not hasattr(env, "robot"):
        return None
    return DictLayout.of(env)


def _observation_space(observation_spec, slices: dict[str, slice] | None = None) -> spaces.Space:
    """The gymnasium space of a TorchRL env's observations.

    The flat vector alone: a ``float64`` ``Box``, unbounded except the lidar parts named in
    ``slices`` (the navigation envs' ``observation_slices``), in ``[0, 1]`` as Safety-Gymnasium
    declares them. With pixel observations (``obs_mode`` other than
    ``"vector"``, the Vision ids): a ``Dict`` in Safety-Gymnasium's channels-last layout, ``"vision"``
    ``(H, W, 3)`` ``uint8`` (Safety-Gymnasium's key), ``"depth"`` ``(H, W, 1)`` ``float32`` metres in
    RGB-D modes, and ``"observation"`` (the flat ``float64`` vector) in ``vector+`` modes.
    """
    keys = observation_spec.keys()
    vector = None
    if "observation" in keys:
        shape = tuple(observation_spec["observation"].shape[1:])
        low, high = np.full(shape, -np.inf), np.full(shape, np.inf)
        for name, part in (slices or {}).items():
            if name.endswith("_lidar") and len(shape) == 1:
                low[part], high[part] = 0.0, 1.0
        vector = spaces.Box(low, high, dtype=np.float64)
    if "pixels" not in keys:
        return vector
    entries: dict[str, spaces.Space] = {}
    if vector is not None:
        entries["observation"] = vector
    height, width, channels = observation_spec["pixels"].shape[1:]
    entries["vision"] = spaces.Box(0, 255, shape=(height, width, channels), dtype=np.uint8)
    if "depth" in keys:
        box = observation_spec["depth"].space
        entries["depth"] = spaces.Box(float(box.low.min()), float(box.high.max()), shape=(height, width, 1),
                                      dtype=np.float32)
    return spaces.Dict(entries)


class GymnasiumEnv(SafetyGymnasiumEnv):
    """:class:`SafetyGymnasiumEnv` with gymnasium's 5-tuple step; the cost is ``info["cost"]``.

    The info's numbers are numpy scalars (``np.float64``, a ``float`` subclass), which TorchRL's
    ``default_info_dict_reader`` reads: ``GymEnv(twin_id)`` with
    ``set_info_dict_reader(default_info_dict_reader(["cost"]))`` puts the cost in its TensorDicts.

    The counterpart of Safety-Gymnasium's ``Safety<Name>Gymnasium-v<k>`` twins, for code that
    expects a plain :class:`gymnasium.Env` (wrappers, vector envs, other libraries).
    """

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, float]]:
        """Advance one step: ``(obs, reward, terminated, truncated, info)`` with ``info["cost"]``."""
        obs, reward, cost, terminated, truncated, info = self._transition(action)
        info["cost"] = cost
        return obs, reward, terminated, truncated, numpy_scalar_info(info)


register_envs()
