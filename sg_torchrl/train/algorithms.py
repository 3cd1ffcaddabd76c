"""The algorithms ``sg-train`` can run, as an explicit table.

An algorithm is a multiplier rule plus a loss built from the shared actor and critics: PPO-Lag is
:class:`~sg_torchrl.objectives.PPOLagLoss` with a :class:`~sg_torchrl.objectives.LagrangeMultiplier`
(Ray et al. 2019; Safety-Gymnasium paper, section 5), CPPO-PID is the *same loss* with a
:class:`~sg_torchrl.objectives.PIDLagrangeMultiplier` (Stooke et al. 2020). Later algorithm
families add rows here, not trainer code.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from torch import nn
from torchrl.objectives import LossModule

from sg_torchrl.objectives import LagrangeMultiplier, Multiplier, PIDLagrangeMultiplier, PPOLagLoss
from sg_torchrl.train.config import TrainConfig

__all__ = ["Algorithm", "ALGORITHMS"]


@dataclass(frozen=True)
class Algorithm:
    """How to build one algorithm's multiplier and loss from a config."""

    title: str
    make_multiplier: Callable[[TrainConfig], Multiplier]
    make_loss: Callable[[nn.Module, nn.Module, nn.Module, Multiplier, TrainConfig], LossModule]


def _lagrange(cfg: TrainConfig) -> Multiplier:
    return LagrangeMultiplier(cost_limit=cfg.cost_limit, init=cfg.lagrangian_init, lr=cfg.lagrangian_lr)


def _pid(cfg: TrainConfig) -> Multiplier:
    return PIDLagrangeMultiplier(
        cost_limit=cfg.cost_limit, kp=cfg.pid_kp, ki=cfg.pid_ki, kd=cfg.pid_kd, d_delay=cfg.pid_d_delay,
        init=cfg.lagrangian_init,
    )


def _ppo_lag_loss(actor, critic, cost_critic, multiplier, cfg: TrainConfig) -> LossModule:
    # functional=False: these losses need no functional parameter swapping (no target networks,
    # no meta-RL), and calling the modules directly saves ~0.35 ms per minibatch step on CPU.
    return PPOLagLoss(
        actor, critic, cost_critic, multiplier, clip_epsilon=cfg.clip_ratio, critic_l2_coeff=cfg.critic_l2,
        functional=False,
    )


ALGORITHMS: dict[str, Algorithm] = {
    "ppo_lag": Algorithm("PPO-Lag", _lagrange, _ppo_lag_loss),
    "cppo_pid": Algorithm("CPPO-PID", _pid, _ppo_lag_loss),
}
