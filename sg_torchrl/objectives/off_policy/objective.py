"""The off-policy actor-critic objectives (SAC, TD3, DDPG and their Lagrangian forms), written once, seed-batched.

What SAC-Lag, TD3-Lag and DDPG-Lag compute from their networks' outputs is one
:class:`OffPolicyObjective`: the reward critic's and the cost critic's one-step targets, their
regression losses, and the actor loss with the multiplier's penalty. It reads tensors only, so the
same object serves

* the TorchRL ``LossModule`` s (:class:`~sg_torchrl.objectives.off_policy.SACLagLoss`, ...), which
  evaluate their functional networks on one batch and call :meth:`OffPolicyObjective.losses` with
  ``seed_dims=0``;
* the seed-group engine (:mod:`sg_torchrl.train.off_policy`), which evaluates S stacked seeds' networks
  and calls the same method with ``seed_dims=1`` (every tensor then leads with the seed dimension).

The loss object hands it over through ``loss.seed_batched_objective()``, the package's protocol for
the one definition of an algorithm (:mod:`sg_torchrl.objectives.surrogates` for the first-order family).

Shapes: a critic's values are ``(*seeds, K, *samples)`` (``K`` critics, twin: 2, the critic dimension right
after the seed dimensions); rewards, costs, ``terminated`` and log-probabilities are ``(*seeds, *samples)``.

**Targets.** :math:`y_r = r + \\gamma (1 - \\text{terminated}) (\\min_k Q^{targ}_k(s', a') - \\alpha \\log\\pi(a'|s'))`
(TorchRL's TD(0) target; :math:`\\alpha = 0` for TD3 / DDPG) and
:math:`y_c = c + \\gamma (1 - \\text{terminated}) \\operatorname{reduce}_k Q^{targ}_{c,k}(s', a')`, with
:math:`a'` the reward target's next action (SAC: sampled from the current policy; TD3: the target actor's
with clipped smoothing noise; DDPG: the target actor's). Only termination stops the bootstrap: a time-limit
truncation bootstraps from the true next observation. The cost target has no entropy term: the entropy
bonus is part of the reward the policy maximises, not of the cost it bounds.

**Twin cost critic: ``max`` by default.** Clipped double-Q (TD3, SAC) takes the *minimum* of two critics
because the actor maximises :math:`Q_r` and so exploits its over-estimates. The actor *minimises*
:math:`Q_c`, so it exploits the cost critic's *under*-estimates; the mirror image of the clipped double-Q
fix is the maximum (pessimistic for cost, so the constraint errs on the safe side). The same reduction
gives the actor's penalty term. ``"mean"`` (unbiased but not corrective) and ``"min"`` are options.

**Actor.** Unconstrained: TorchRL's loss, :math:`\\alpha \\log\\pi(a|s) - \\min_k Q_k(s, a)` (SAC),
:math:`-Q_1(s, a)` (TD3: the first critic) or :math:`-Q(s, a)` (DDPG), with :math:`a` the actor's own action.
With a multiplier :math:`\\lambda` (OmniSafe's form): :math:`(\\ell_r + \\lambda Q_c(s, a)) / (1 + \\lambda)`,
the reward term and the cost penalty divided by :math:`1 + \\lambda` so that a large multiplier does not scale
the actor's gradient up (the :math:`1 / (1 + \\lambda)` of SafePO's Lagrangian advantage).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor
from torchrl.objectives.utils import distance_loss

from sg_torchrl.objectives.surrogates import over_samples, sample_mean

__all__ = ["COST_REDUCTIONS", "OffPolicyObjective"]

#: How the twin cost critic's values are reduced (module docstring).
COST_REDUCTIONS = ("max", "mean", "min")
_ACTOR_Q = ("min", "first")
_LOSS_FUNCTIONS = ("l2", "l1", "smooth_l1")


@dataclass(frozen=True)
class OffPolicyObjective:
    """One off-policy algorithm's losses from its networks' outputs, for any leading seed dimensions.

    Args:
        gamma: the discount of reward and cost.
        alpha: SAC's (fixed) entropy weight; 0 for the deterministic actors (TD3, DDPG).
        actor_q: what the actor maximises of the reward critics: ``"min"`` (SAC) or ``"first"`` (TD3,
            DDPG: critic 1).
        cost_reduction: reduction of the cost critics (:data:`COST_REDUCTIONS`; module docstring).
        loss_function: the critics' regression loss (TorchRL's ``distance_loss``: ``"l2"``, ``"l1"``,
            ``"smooth_l1"``).
        constrained: whether there is a cost critic and a multiplier (SAC-Lag ...); ``False``: SAC, TD3, DDPG.
        policy_noise, noise_clip: TD3's target policy smoothing (0: none).

    Raises:
        ValueError: an unknown reduction, critic choice or loss function, or a negative coefficient.
    """

    gamma: float
    alpha: float = 0.0
    actor_q: Literal["min", "first"] = "min"
    cost_reduction: Literal["max", "mean", "min"] = "max"
    loss_function: str = "l2"
    constrained: bool = True
    policy_noise: float = 0.0
    noise_clip: float = 0.0

    def __post_init__(self) -> None:
        if self.cost_reduction not in COST_REDUCTIONS:
            raise ValueError(f"cost_reduction must be one of {', '.join(COST_REDUCTIONS)}, got {self.cost_reduction!r}")
        if self.actor_q not in _ACTOR_Q:
            raise ValueError(f"actor_q must be one of {', '.join(_ACTOR_Q)}, got {self.actor_q!r}")
        if self.loss_function not in _LOSS_FUNCTIONS:
            raise ValueError(f"loss_function must be one of {', '.join(_LOSS_FUNCTIONS)}, got {self.loss_function!r}")
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {self.gamma}")
        for name in ("alpha", "policy_noise", "noise_clip"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")

    @property
    def stochastic(self) -> bool:
        """Whether the actor is SAC's sampled one (an entropy term in the targets and the actor loss)."""
        return self.alpha > 0.0

    # ------------------------------------------------------------------ pieces
    def smoothed_action(self, action: Tensor, noise: Tensor, low: Tensor, high: Tensor) -> Tensor:
        """TD3's target action: ``action`` plus ``noise`` (standard normal) scaled by ``policy_noise``, clipped at
        ``noise_clip``, the sum clamped to the action bounds. Without ``policy_noise``: ``action``."""
        if self.policy_noise == 0.0:
            return action
        return (action + (noise * self.policy_noise).clamp(-self.noise_clip, self.noise_clip)).clamp(low, high)

    def bootstrap(self, reward: Tensor, terminated: Tensor, next_value: Tensor) -> Tensor:
        """The one-step target :math:`r + \\gamma (1 - \\text{terminated}) V(s')` (only termination stops it)."""
        return reward + self.gamma * (~terminated.bool()).to(reward.dtype) * next_value

    def reward_next_value(self, next_q: Tensor, next_log_prob: Tensor | None, seed_dims: int) -> Tensor:
        """:math:`\\min_k Q^{targ}_k(s', a') - \\alpha \\log\\pi(a'|s')` (TorchRL's order: the entropy term, then the minimum)."""
        if self.stochastic:
            next_q = next_q - self.alpha * next_log_prob.unsqueeze(seed_dims)
        return next_q.min(seed_dims).values

    def reduce_cost(self, cost_q: Tensor, seed_dims: int) -> Tensor:
        """The cost critics' values reduced over the critic dimension by :attr:`cost_reduction`."""
        if self.cost_reduction == "max":
            return cost_q.max(seed_dims).values
        if self.cost_reduction == "min":
            return cost_q.min(seed_dims).values
        return cost_q.mean(seed_dims)

    def critic_loss(self, q: Tensor, target: Tensor, seed_dims: int) -> Tensor:
        """Every critic's regression to ``target``, summed over the critics, averaged over the samples (per seed)."""
        target = target.unsqueeze(seed_dims).expand_as(q)
        return sample_mean(distance_loss(q, target, loss_function=self.loss_function).sum(seed_dims), seed_dims)

    def actor_loss(self, q: Tensor, log_prob: Tensor | None, cost_q: Tensor | None, lam: Tensor | None,
                   seed_dims: int) -> Tensor:
        """The actor loss (module docstring), averaged over the samples (per seed).

        ``q`` / ``cost_q``: the critics at the actor's own (reparameterised) action, computed with
        parameters that carry no gradient; ``lam``: the multiplier, 0-d or one per seed.
        """
        value = q.min(seed_dims).values if self.actor_q == "min" else q.select(seed_dims, 0)
        loss = self.alpha * log_prob - value if self.stochastic else -value
        if self.constrained:
            lam = over_samples(lam, loss)
            loss = (loss + lam * self.reduce_cost(cost_q, seed_dims)) / (1 + lam)
        return sample_mean(loss, seed_dims)

    # ------------------------------------------------------------------ all of it
    def losses(
        self, *, q: Tensor, next_q: Tensor, reward: Tensor, terminated: Tensor, seed_dims: int,
        next_log_prob: Tensor | None = None, cost_q: Tensor | None = None, next_cost_q: Tensor | None = None,
        cost: Tensor | None = None, actor_q: Tensor | None = None, actor_log_prob: Tensor | None = None,
        actor_cost_q: Tensor | None = None, lam: Tensor | None = None,
    ) -> dict[str, Tensor]:
        """Every loss of one gradient step from the networks' outputs (shapes in the module docstring).

        ``q`` / ``cost_q``: the critics at the stored ``(s, a)``; ``next_q`` / ``next_cost_q``: the target
        critics at ``(s', a')`` (no gradient); ``next_log_prob``: SAC's :math:`\\log\\pi(a'|s')`;
        ``actor_q`` / ``actor_cost_q`` / ``actor_log_prob``: the actor's terms (omit them on a step that does
        not move the actor). Returns per-seed (0-d for ``seed_dims=0``) ``loss_qvalue``, and
        ``loss_cost_qvalue`` when constrained, ``loss_actor`` when the actor terms are given, and the targets
        ``target_value`` / ``target_cost_value`` (per sample, detached).
        """
        with torch.no_grad():
            target = self.bootstrap(reward, terminated, self.reward_next_value(next_q, next_log_prob, seed_dims))
        out = {"loss_qvalue": self.critic_loss(q, target, seed_dims), "target_value": target}
        if self.constrained:
            with torch.no_grad():
                cost_target = self.bootstrap(cost, terminated, self.reduce_cost(next_cost_q, seed_dims))
            out["loss_cost_qvalue"] = self.critic_loss(cost_q, cost_target, seed_dims)
            out["target_cost_value"] = cost_target
        if actor_q is not None:
            out["loss_actor"] = self.actor_loss(actor_q, actor_log_prob, actor_cost_q, lam, seed_dims)
        return out
