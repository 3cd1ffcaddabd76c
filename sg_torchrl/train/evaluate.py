"""Deterministic evaluation: K episodes with the policy's mean action.

The K episodes run side by side, one per simulator of a fresh batched env (seeded apart from the
training env), and each simulator's *first* episode is scored. The observation normaliser is a
frozen copy of the training one, so evaluation never shifts training statistics (SafePO's
evaluation kept updating them).
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

import sg_torchrl
from sg_torchrl.envs.normalization import RunningObservationNorm

__all__ = ["evaluate_policy"]


@torch.no_grad()
def evaluate_policy(
    env_id: str,
    policy: TensorDictModuleBase,
    episodes: int,
    *,
    seed: int,
    obs_norm: RunningObservationNorm | None = None,
) -> dict[str, float]:
    """Mean and std of return, cost and length over ``episodes`` deterministic episodes."""
    base = sg_torchrl.make(env_id, num_envs=episodes, seed=seed)
    env: EnvBase = base
    if obs_norm is not None:
        frozen = RunningObservationNorm(obs_norm.mean.shape, in_keys=obs_norm.in_keys, epsilon=obs_norm.epsilon)
        frozen.load_state_dict(obs_norm.state_dict())
        env = TransformedEnv(base, frozen.eval())
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(base.max_episode_steps, policy, break_when_any_done=False)
    done = rollout["next", "done"].squeeze(-1)
    # Steps up to and including each simulator's first done belong to its first episode.
    first_episode = (done.cumsum(-1) - done.long()) == 0
    mask = first_episode.float()
    returns = (rollout["next", "reward"].squeeze(-1) * mask).sum(-1)
    costs = (rollout["next", "cost"].squeeze(-1) * mask).sum(-1)
    lengths = mask.sum(-1)
    env.close()
    return {
        "Metrics/EvalEpRet": returns.mean().item(),
        "Metrics/EvalEpRetStd": returns.std(unbiased=False).item(),
        "Metrics/EvalEpCost": costs.mean().item(),
        "Metrics/EvalEpCostStd": costs.std(unbiased=False).item(),
        "Metrics/EvalEpLen": lengths.mean().item(),
    }
