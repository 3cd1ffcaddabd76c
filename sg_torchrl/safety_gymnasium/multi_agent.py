"""``make_ma``: Safety-Gymnasium's multi-agent velocity tasks (``SafeMAEnv``), on sg_torchrl's envs.

(The original's ``safety_gymnasium.tasks.safe_multi_agent.safe_mujoco_multi``.)

>>> env = safety_gymnasium.make_ma("Ant", "2x4")
>>> observations, infos = env.reset(seed=0)
>>> actions = {agent: env.action_space(agent).sample() for agent in env.agents}
>>> observations, rewards, costs, terminations, truncations, infos = env.step(actions)
>>> env.state().shape, env.agent_action_partitions
((27,), ...)

``SafeMAEnv(scenario, agent_conf)`` builds the id ``Safety<agent_conf><scenario>Velocity-v0`` as a
:class:`sg_torchrl.pettingzoo.SafeParallelEnv` (kept as :attr:`SafeMAEnv.env`, like the original's
MaMuJoCo env) and reads everything the original's users read through it: ``possible_agents``,
``agents``, ``observation_spaces`` / ``action_spaces`` / ``observation_space(agent)`` /
``action_space(agent)``, ``state()``, ``state_space``, ``num_agents``, ``render``, ``close``; plus
``agent_action_partitions`` (each agent's joints, objects with a ``label``) and ``agent_obsk``.
Steps are the 6-tuple of dicts ``(observations, rewards, costs, terminations, truncations, infos)``;
the cost is the team's velocity indicator, equal for every agent. The class can be subclassed as
SafePO's ``ShareEnv`` does (it assigns ``num_agents``, ``observation_spaces`` on the instance).

The eight (scenario, agent_conf) pairs: Ant 2x4 / 4x2, HalfCheetah 2x3 / 6x1, Hopper 3x1,
Humanoid 9|8, Swimmer 2x1, Walker2d 2x3. Differences from the original: an unknown configuration
raises ``ValueError`` (the original warned and then failed inside MaMuJoCo), and
``agent_factorization`` / ``local_categories`` / ``global_categories`` are refused (MaMuJoCo's custom
partitions are not provided). :meth:`SafeMAEnv.from_id` builds any multi-agent id of sg_torchrl the
same way (``safety_gymnasium.make("SafetyPointMultiGoal1-v0")`` uses it).
"""

from __future__ import annotations

from typing import Any

from sg_torchrl.envs.multi_agent.partitions import scenario_of
from sg_torchrl.envs.registry import list_envs, registry_entry

__all__ = ["SafeMAEnv", "TASK_VELOCITY_THRESHOLD", "make_ma"]

TASK_VELOCITY_THRESHOLD: dict[str, dict[str, float]] = {
    "Ant": {"2x4": 2.522, "4x2": 2.418},
    "HalfCheetah": {"6x1": 2.932, "2x3": 3.227},
    "Hopper": {"3x1": 0.9613},
    "Humanoid": {"9|8": 0.58},
    "Swimmer": {"2x1": 0.04891},
    "Walker2d": {"2x3": 1.641},
}
"""The cost thresholds of the eight partitions (reference section 9), keyed like the original's."""


class SafeMAEnv:
    """A multi-agent velocity task behind the original's ``make_ma`` interface (module docstring).

    Args:
        scenario: the robot, one of :data:`TASK_VELOCITY_THRESHOLD`.
        agent_conf: its partition, e.g. ``"2x4"``.
        agent_obsk: graph distance of the joints each agent observes (1, the reference's, by default).
        agent_factorization, local_categories, global_categories: MaMuJoCo's custom partitions, not
            supported (must be ``None``).
        render_mode: ``None`` or a gymnasium render mode (:mod:`sg_torchrl.render_modes`).
        **kwargs: render options and sg_torchrl options (``max_episode_steps``, ``cost_mode``, ...).

    Raises:
        ValueError: an unknown scenario or configuration.
        NotImplementedError: a custom factorization or categories.
    """

    def __init__(self, scenario: str, agent_conf: str | None, agent_obsk: int | None = 1,
                 agent_factorization: dict | None = None, local_categories: list[list[str]] | None = None,
                 global_categories: tuple[str, ...] | None = None, render_mode: str | None = None,
                 **kwargs: Any) -> None:
        if scenario not in TASK_VELOCITY_THRESHOLD:
            raise ValueError(f"unknown scenario {scenario!r}: one of {sorted(TASK_VELOCITY_THRESHOLD)}")
        if agent_conf not in TASK_VELOCITY_THRESHOLD[scenario]:
            raise ValueError(f"unknown agent_conf {agent_conf!r} for {scenario}: one of "
                             f"{sorted(TASK_VELOCITY_THRESHOLD[scenario])}")
        custom = {name: value for name, value in (("agent_factorization", agent_factorization),
                                                   ("local_categories", local_categories),
                                                   ("global_categories", global_categories)) if value is not None}
        if custom:
            raise NotImplementedError(f"{sorted(custom)}: MaMuJoCo's custom partitions are not provided by "
                                      f"sg_torchrl; the eight standard ones are (module docstring)")
        if agent_obsk is not None and agent_obsk != 1:
            kwargs["agent_obsk"] = agent_obsk
        self.agent = scenario
        self.agent_conf = agent_conf
        self.agent_obsk = 1 if agent_obsk is None else agent_obsk
        self._build(f"Safety{agent_conf}{scenario}Velocity-v0", render_mode, kwargs)
        self.agent_action_partitions = scenario_of(scenario).agents(agent_conf)
        self._velocity_threshold = TASK_VELOCITY_THRESHOLD[scenario][agent_conf]

    @classmethod
    def from_id(cls, env_id: str, render_mode: str | None = None, **kwargs: Any) -> SafeMAEnv:
        """The multi-agent sg_torchrl env ``env_id`` behind this interface (velocity or MultiGoal ids).

        Raises:
            ValueError: ``env_id`` is not a multi-agent id.
        """
        if env_id not in list_envs() or not registry_entry(env_id).multi_agent:
            raise ValueError(f"{env_id!r} is not a multi-agent id of sg_torchrl")
        entry = registry_entry(env_id)
        if entry.family == "multi_agent_velocity":
            scenario, conf = entry.kwargs["scenario"], entry.kwargs["agent_conf"]
            return cls(scenario, conf, kwargs.pop("agent_obsk", 1), render_mode=render_mode, **kwargs)
        env = cls.__new__(cls)
        env.agent, env.agent_conf, env.agent_obsk = entry.robot, None, None
        env._build(env_id, render_mode, kwargs)
        env.agent_action_partitions = tuple((name,) for name in env.env.possible_agents)
        return env

    def _build(self, env_id: str, render_mode: str | None, kwargs: dict[str, Any]) -> None:
        from sg_torchrl.pettingzoo import SafeParallelEnv

        self.env_id = env_id
        self.env = SafeParallelEnv(env_id, render_mode=render_mode, **kwargs)

    def __getattr__(self, name: str) -> Any:
        """The wrapped :class:`~sg_torchrl.pettingzoo.SafeParallelEnv`'s public attributes."""
        env = self.__dict__.get("env")
        if name.startswith("_") or env is None:
            raise AttributeError(f"{type(self).__name__} has no attribute {name!r}")
        return getattr(env, name)

    def reset(self, *args: Any, **kwargs: Any) -> tuple[dict, dict]:
        """``(observations, infos)``; ``seed`` re-seeds the simulator."""
        return self.env.reset(*args, **kwargs)

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict, dict]:
        """``(observations, rewards, costs, terminations, truncations, infos)``, dicts keyed by agent."""
        return self.env.step(actions)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.env_id!r})"


make_ma = SafeMAEnv
"""``safety_gymnasium.make_ma(scenario, agent_conf, ...)``: the original's name for :class:`SafeMAEnv`."""
