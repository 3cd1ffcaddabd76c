"""Evaluation: K episodes of a policy, deterministic (its mean action) unless asked otherwise.

The K episodes run side by side, one per simulator of a fresh batched env (seeded apart from the
training env), and each simulator's *first* episode is scored. The observation normalisers are
frozen copies of the training ones, so evaluation never shifts training statistics (SafePO's
evaluation kept updating them).

Single- and multi-agent envs are scored alike: the reward is read at the env's ``reward_key``
(``("agents", "reward")`` in the multi-agent layout, averaged over the agents, i.e. the team
reward) and the cost at the root ``"cost"`` (the team's cost in every sg_torchrl env).

:func:`evaluate_policy` is what a trainer runs at the end of training (the means and stds its
``summary.json`` holds); :func:`evaluate_episodes` is the same rollout returning every episode's
figures, which ``sg-eval`` (:mod:`sg_torchrl.evaluation`) writes and can watch through ``callback``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import unravel_key
from torchrl.envs import Compose, EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

import sg_torchrl
from sg_torchrl.envs.normalization import RunningObservationNorm

__all__ = ["evaluate_episodes", "evaluate_policy", "summarize_episodes"]


def _per_step(x: torch.Tensor) -> torch.Tensor:
    """``(K, T, ...)`` -> ``(K, T)``: the mean over trailing dims (the agents, the unit dim)."""
    return x.flatten(2).mean(-1)


@torch.no_grad()
def evaluate_episodes(
    env_id: str,
    policy: TensorDictModuleBase,
    episodes: int,
    *,
    seed: int,
    obs_norm: RunningObservationNorm | Sequence[RunningObservationNorm] | None = None,
    env_options: Mapping[str, Any] | None = None,
    exploration: ExplorationType = ExplorationType.DETERMINISTIC,
    callback: Callable[[EnvBase, EnvBase, TensorDictBase], None] | None = None,
) -> dict[str, torch.Tensor]:
    """Return, cost and length of each of ``episodes`` episodes: ``{"return", "cost", "length"}``, ``(K,)`` each.

    Episode ``k`` is the first episode of simulator ``k`` of ``sg_torchrl.make(env_id, num_envs=episodes,
    seed=seed, **env_options)``. ``obs_norm``: the training normaliser(s), applied frozen in the given order.
    ``exploration``: the exploration type the policy acts under (deterministic: its mean action).
    ``callback(base_env, env, tensordict)`` is called after every step but the last with the step's
    TensorDict (TorchRL's ``rollout`` callback; simulators whose episode ended are already reset), e.g.
    to render frames: it only reads the simulators, so the figures are those of a run without it.
    """
    base = sg_torchrl.make(env_id, num_envs=episodes, seed=seed, **(env_options or {}))
    env: EnvBase = base
    norms = [obs_norm] if isinstance(obs_norm, RunningObservationNorm) else list(obs_norm or ())
    if norms:
        env = TransformedEnv(base, Compose(*(norm.frozen_copy() for norm in norms)))
    step_callback = None if callback is None else (lambda stepped, tensordict: callback(base, stepped, tensordict))
    try:
        with set_exploration_type(exploration):
            rollout = env.rollout(base.max_episode_steps, policy, break_when_any_done=False,
                                  callback=step_callback)
    finally:
        env.close()
    done = rollout["next", "done"].squeeze(-1)
    # Steps up to and including each simulator's first done belong to its first episode.
    first_episode = (done.cumsum(-1) - done.long()) == 0
    mask = first_episode.float()
    return {
        "return": (_per_step(rollout[unravel_key(("next", base.reward_key))]) * mask).sum(-1),
        "cost": (_per_step(rollout["next", "cost"]) * mask).sum(-1),
        "length": mask.sum(-1),
    }


def summarize_episodes(episodes: Mapping[str, torch.Tensor]) -> dict[str, float]:
    """The evaluation figures of :func:`evaluate_episodes`' episodes, under the names ``summary.json`` uses."""
    returns, costs, lengths = episodes["return"], episodes["cost"], episodes["length"]
    return {
        "Metrics/EvalEpRet": returns.mean().item(),
        "Metrics/EvalEpRetStd": returns.std(unbiased=False).item(),
        "Metrics/EvalEpCost": costs.mean().item(),
        "Metrics/EvalEpCostStd": costs.std(unbiased=False).item(),
        "Metrics/EvalEpLen": lengths.mean().item(),
    }


def evaluate_policy(
    env_id: str,
    policy: TensorDictModuleBase,
    episodes: int,
    *,
    seed: int,
    obs_norm: RunningObservationNorm | Sequence[RunningObservationNorm] | None = None,
    env_options: Mapping[str, Any] | None = None,
) -> dict[str, float]:
    """Mean and std of return, cost and length over ``episodes`` deterministic episodes.

    ``obs_norm``: the training normaliser(s), applied frozen in the given order. ``env_options``:
    the task options the policy was trained with (``sg_torchrl.make``'s keywords).
    """
    return summarize_episodes(evaluate_episodes(env_id, policy, episodes, seed=seed, obs_norm=obs_norm,
                                                env_options=env_options))
