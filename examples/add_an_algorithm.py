"""Add an algorithm: what one Surrogate and one loss subclass change, on one batch.

``sg_torchrl/objectives/pessimistic.py`` adds PPO-Lag with a pessimistic cost clip to the package as
one :class:`~sg_torchrl.objectives.surrogates.Surrogate` (its math, for any leading seed
dimensions) and one ``PPOLagLoss`` subclass that returns it; the ``ppo_lag_pessimistic`` row of
``sg_torchrl/algorithms/manifest.py`` makes ``sg-train --algo ppo_lag_pessimistic --seeds 0 1 2``
train it on the seed-batched engine, which gets the surrogate from the loss object.

This script shows the new term changing the update: the same batch, networks and multiplier value
give another policy gradient than PPO-Lag's once ratios leave the clip range.

    python examples/add_an_algorithm.py
"""
from __future__ import annotations

import torch

import sg_torchrl
from sg_torchrl.objectives import LagrangeMultiplier, PessimisticPPOLagLoss, PPOLagLoss
from sg_torchrl.modules import make_actor_critics


def main() -> None:
    env = sg_torchrl.make("SafetyPointGoal1-v0")
    torch.manual_seed(0)
    actor, critic, cost_critic = make_actor_critics(env.observation_spec["observation"].shape[-1], env.action_spec,
                                                    [32, 32])
    with torch.no_grad():
        batch = env.rollout(64, actor, break_when_any_done=False).reshape(-1)
        for key in ("advantage", "cost_advantage", "value_target", "cost_value_target"):
            batch.set(key, torch.randn(64, 1))
        for p in actor.parameters():  # move the policy so that ratios leave the clip range
            p.add_(0.3 * torch.randn_like(p))
    multiplier = LagrangeMultiplier(cost_limit=25.0, init=1.0)
    for loss_class in (PPOLagLoss, PessimisticPPOLagLoss):
        loss = loss_class(actor, critic, cost_critic, multiplier, functional=False)
        actor.zero_grad()
        loss(batch)["loss_objective"].backward()
        grad = torch.cat([p.grad.flatten() for p in actor.parameters()])
        print(f"{loss_class.__name__:>22}: |policy gradient| = {grad.norm():.4f}")


if __name__ == "__main__":
    main()
