"""Safety-Gymnasium 1.0.0's public API on sg_torchrl: a drop-in for ``safety_gymnasium``.

Safety-Gymnasium 1.0.0 does not install on current Python. A script that alone imports it runs on
sg_torchrl's environments by changing one import::

    import sg_torchrl.safety_gymnasium as safety_gymnasium

That renames the module in the script only. Where a library imports ``safety_gymnasium`` in its own
modules (SafePO, OmniSafe), run the unchanged script with ``python -m sg_torchrl.safety_gymnasium
script.py [args...]`` (the alias in this process and in every worker process, :mod:`.__main__`), or
call ``sg_torchrl.safety_gymnasium.install_alias()`` first in the entry script, before the library is
imported (this process and its forked workers, :mod:`.alias`).

What it provides (the original's names, signatures and behaviour, on current gymnasium)
--------------------------------------------------------------------------------------
* :func:`make` ``(id, max_episode_steps=None, autoreset=None, apply_api_compatibility=None,
  disable_env_checker=None, **kwargs)``, :func:`register`, :data:`~.registration.safe_registry`
  (:mod:`.registration`; also as ``safety_gymnasium.utils.registration``): envs whose ``step`` returns
  ``(obs, reward, cost, terminated, truncated, info)``, wrapped like the original's, so
  ``env.spec.max_episode_steps`` is the id's episode length. Render modes ``rgb_array``,
  ``depth_array``, ``rgb_array_list``, ``depth_array_list``, ``human`` (needs a display), with
  ``width``, ``height``, ``camera_name`` / ``camera_id``.
* :func:`make_ma` ``(scenario, agent_conf)`` / :class:`~.multi_agent.SafeMAEnv` (:mod:`.multi_agent`;
  also as ``safety_gymnasium.tasks.safe_multi_agent.safe_mujoco_multi``): the eight multi-agent
  velocity partitions; multi-agent ids also through :func:`make`.
* :mod:`.wrappers`: ``SafeAutoResetWrapper``, ``SafeTimeLimit``, ``SafePassiveEnvChecker``,
  ``SafetyGymnasium2Gymnasium``, ``Gymnasium2SafetyGymnasium``, ``with_gymnasium_wrappers``,
  ``SafeNormalizeObservation`` / ``Reward`` / ``Cost``, ``SafeUnsqueeze``, ``SafeRescaleAction``.
* :mod:`.vector`: ``SafetySyncVectorEnv``, ``SafetyAsyncVectorEnv`` (explicit start method), ``make``,
  ``VectorEnv``; same-step autoreset with ``final_observation`` / ``final_info``, keeping the cost of
  an episode's final step.
* ``gymnasium_make`` / ``gymnasium_register`` (gymnasium's), ``__version__`` (``"1.0.0"``: the API
  version this module reproduces; sg_torchrl's own is ``sg_torchrl.__version__``), and the
  original's constants ``VERSION``, ``PREFIX``, ``ROBOT_NAMES`` / ``robots``, the task tables
  (``goal_tasks``, ...), ``MAKE_VISION_ENVIRONMENTS``.

``copy.deepcopy(env)`` copies the simulator (the copy's next step equals the original's) and
``reset(options=...)`` accepts the options. The original's engine modules (``builder``, ``bases``,
``assets``, ``agents``, ``world``, ``tasks.*`` other than the multi-agent one) are not provided:
sg_torchrl's engine is different (see ``sg_torchrl.envs``). README, "Migrating from
Safety-Gymnasium", lists the differences.
"""

from __future__ import annotations

from gymnasium import make as gymnasium_make
from gymnasium import register as gymnasium_register

from sg_torchrl.safety_gymnasium import vector, wrappers
from sg_torchrl.safety_gymnasium.alias import install_alias, is_alias_installed, uninstall_alias
from sg_torchrl.safety_gymnasium.multi_agent import SafeMAEnv, make_ma
from sg_torchrl.safety_gymnasium.registration import make, register, safe_registry

__version__ = "1.0.0"

__all__ = [
    "SafeMAEnv",
    "gymnasium_make",
    "gymnasium_register",
    "install_alias",
    "is_alias_installed",
    "make",
    "make_ma",
    "register",
    "safe_registry",
    "uninstall_alias",
    "vector",
    "wrappers",
]

VERSION = "v0"
PREFIX = "Safety"
ROBOT_NAMES = ("Point", "Car", "Doggo", "Racecar", "Ant")
robots = ROBOT_NAMES
MAKE_VISION_ENVIRONMENTS = True
MAKE_DEBUG_ENVIRONMENTS = False  # the original's keyboard-controlled Debug ids are not provided

# The original's task tables (task name -> configuration overrides), by task family.
button_tasks = {"Button0": {}, "Button1": {}, "Button2": {}}
push_tasks = {"Push0": {}, "Push1": {}, "Push2": {}}
goal_tasks = {"Goal0": {}, "Goal1": {}, "Goal2": {}}
circle_tasks = {"Circle0": {}, "Circle1": {}, "Circle2": {}}
run_tasks = {"Run0": {}}
race_tasks = {f"Race{level}": {"floor_conf.type": "village"} for level in range(3)}
fading_tasks = {f"FadingHard{level}": {} for level in range(3)}  # as the original's table (Easy ids exist too)
