"""Deterministic evaluation: K episodes with the policy's mean action.

The K episodes run side by side, one per simulator of a fresh batched env (seeded apart from the
training env), and each simulator's *first* episode is scored. The observation normalisers are
frozen copies of the training ones, so evaluation never shifts training statistics (SafePO's
evaluation kept updating them).

Single- and multi-agent envs are scored alike: the reward is read at the env's ``reward_key``
(``("agents", "reward")`` in the multi-agent layout, averaged over the agents, i.e. the team
reward) and the cost at the root ``"cost"`` (the team's cost in every sg_torchrl env).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import unravel_key
from torchrl.envs import Compose, EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

import sg_torchrl
from sg_torchrl.envs.normalization import RunningObservationNorm

__all__ = ["evaluate_policy"]


def _per_step(x: torch.Tensor) -> torch.Tensor:
    """``(K, T, ...)`` -> ``(K, T)``: the mean over trailing dims (the agents, the unit dim)."""
    return x.flatten(2).mean(-1)


@torch.no_grad()
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
    base = sg_torchrl.make(env_id, num_envs=episodes, seed=seed, **(env_options or {}))
    env: EnvBase = base
    norms = [obs_norm] if isinstance(obs_norm, RunningObservationNorm) else list(obs_norm or ())
    if norms:
        env = TransformedEnv(base, Compose(*(norm.frozen_copy() for norm in norms)))
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(base.max_episode_steps, policy, break_when_any_done=False)
    done = rollout["next", "done"].squeeze(-1)
    # Steps up to and including each simulator's first done belong to its first episode.
    first_episode = (done.cumsum(-1) - done.long()) == 0
    mask = first_episode.float()
    returns = (_per_step(rollout[unravel_key(("next", base.reward_key))]) * mask).sum(-1)
    costs = (_per_step(rollout["next", "cost"]) * mask).sum(-1)
    lengths = mask.sum(-1)
    env.close()
    return {
        "Metrics/EvalEpRet": returns.mean().item(),
        "Metrics/EvalEpRetStd": returns.std(unbiased=False).item(),
        "Metrics/EvalEpCost": costs.mean().item(),
        "Metrics/EvalEpCostStd": costs.std(unbiased=False).item(),
        "Metrics/EvalEpLen": lengths.mean().item(),
    }
