"""Add an algorithm: PPO-Lag with a pessimistic clip on the cost term, as one Surrogate and one loss subclass.

PPO-Lag clips the ratio of the *combined* advantage :math:`(A_r - \\lambda A_c) / (1 + \\lambda)`.
Clipping both terms together lets the clip help the constraint: where the cost advantage is
negative, the clipped cost term is optimistic. This variant clips the two terms apart, the reward
term as PPO does (:math:`\\min`) and the cost term pessimistically (:math:`\\max`, the cost
surrogate of P3O, Zhang et al. 2022):

.. math::

    L = \\frac{-\\min(r A_r,\\ \\mathrm{clip}(r) A_r) + \\lambda \\max(r A_c,\\ \\mathrm{clip}(r) A_c)}{1 + \\lambda}

The math is written once, in :class:`PessimisticCostSurrogate`, for any leading seed dimensions;
:class:`PessimisticCostPPOLagLoss` is the TorchRL ``LossModule`` that returns it. Its inherited
``seed_batched_objective()`` hands the same object to ``sg-train``'s seed-group engine, so the loss
you compose here is exactly what trains there. The row in ``sg_torchrl/algorithms/manifest.py``
(``ppo_lag_pessimistic``) names this loss, so ``sg-train --algo ppo_lag_pessimistic --seeds 0 1 2``
trains it.

Run this file to see that the new term changes the update: the same batch, the same networks, the
same multiplier value give a different gradient from PPO-Lag's as soon as some ratios leave the
clip range.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from sg_torchrl.objectives import PPOLagLoss
from sg_torchrl.objectives.surrogates import ClipSurrogate, per_seed


@dataclass(frozen=True)
class PessimisticCostSurrogate(ClipSurrogate):
    """PPO's clip on the reward term, a pessimistic (max) clip on the cost term, normalised by 1 + lambda."""

    advantage = "reward"  # receive A_r itself; A_c comes as cost_advantage

    def loss(self, log_weight, advantage, *, cost_advantage=None, kl=None, lam=None, log_is_weight=None,
             seed_dims=0):
        ratio = self.log_ratio(log_weight, log_is_weight).exp()
        clipped = log_weight.clamp(*self.bounds).exp()
        lam = per_seed(lam, log_weight)
        reward_term = torch.minimum(ratio * advantage, clipped * advantage)
        cost_term = torch.maximum(ratio * cost_advantage, clipped * cost_advantage)
        return (-reward_term + lam * cost_term) / (1 + lam)


class PessimisticCostPPOLagLoss(PPOLagLoss):
    """PPO-Lag whose cost term is clipped apart and pessimistically (:class:`PessimisticCostSurrogate`)."""

    @property
    def surrogate(self) -> PessimisticCostSurrogate:
        return PessimisticCostSurrogate(float(self.clip_epsilon))


def main() -> None:
    import sg_torchrl
    from sg_torchrl.objectives import LagrangeMultiplier
    from sg_torchrl.train.models import make_actor_critics

    env = sg_torchrl.make("SafetyPointGoal1-v0")
    obs_dim = env.observation_spec["observation"].shape[-1]
    torch.manual_seed(0)
    actor, critic, cost_critic = make_actor_critics(obs_dim, env.action_spec, [32, 32])
    multiplier = LagrangeMultiplier(cost_limit=25.0, init=1.0)
    with torch.no_grad():
        batch = env.rollout(64, actor, break_when_any_done=False).reshape(-1)
    batch.set("advantage", torch.randn(64, 1))
    batch.set("cost_advantage", torch.randn(64, 1))
    batch.set("value_target", torch.randn(64, 1))
    batch.set("cost_value_target", torch.randn(64, 1))
    with torch.no_grad():  # move the policy so that ratios leave the clip range
        for p in actor.parameters():
            p.add_(0.3 * torch.randn_like(p))
    for loss_class in (PPOLagLoss, PessimisticCostPPOLagLoss):
        loss = loss_class(actor, critic, cost_critic, multiplier, functional=False)
        actor.zero_grad()
        loss(batch)["loss_objective"].backward()
        grad = torch.cat([p.grad.flatten() for p in actor.parameters()])
        print(f"{loss_class.__name__:>26}: |grad| = {grad.norm():.4f}")


if __name__ == "__main__":
    main()
