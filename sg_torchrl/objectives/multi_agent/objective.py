"""One agent's MAPPO / HAPPO / MAPPO-Lag objective, written once for a leading seed dimension.

:class:`AgentObjective` is the multi-agent counterpart of
:class:`~sg_torchrl.objectives.surrogates.SeedBatchedObjective`: the math of one agent's gradient step in
the sequential round, evaluated on ``(S, N, ...)`` tensors of S rows (S seeds, each updating its own
agent of the stage; S = 1 is one run). It is built from the single-agent pieces:

* the advantage :math:`M \\cdot \\mathrm{combine}(A_r, A_c)`
  (:func:`~sg_torchrl.objectives.surrogates.combine_advantages` with the multiplier's rule, times HAPPO's
  factor :math:`M` when ``weighted``);
* PPO's clipped surrogate (:class:`~sg_torchrl.objectives.surrogates.ClipSurrogate`) on it, and the
  cost surrogate :math:`\\mathbb E[r A_c]` MAPPO-Lag's multiplier steps on;
* the entropy bonus ``-entropy_coeff * H(pi)`` (over the real action slots, averaged over the samples as
  a per-agent loss averages its distribution's entropy, so the gradients are that loss's bit for bit);
* the reward critic's MSE through TorchRL's :class:`~torchrl.modules.PopArtValueNorm` (update with the
  targets, then compare normalised target and prediction: :class:`~torchrl.objectives.multiagent.MAPPOLoss`'s
  semantics), the cost critic's plain MSE, each plus ``critic_l2 * sum(p ** 2)``.

:class:`~sg_torchrl.objectives.multi_agent.AgentPPOLoss` is its TorchRL ``LossModule`` view (see
:mod:`~sg_torchrl.objectives.multi_agent.loss`); the seed-batched round
(:mod:`sg_torchrl.train.multi_agent_updates`) evaluates :meth:`losses` on its rows.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor
from torchrl.modules import PopArtValueNorm

from sg_torchrl.modules.gaussian import gaussian_entropy, gaussian_log_prob
from sg_torchrl.objectives.surrogates import ClipSurrogate, CombineRule, combine_advantages, sample_mean

__all__ = ["AgentObjective", "seed_popart"]

#: A unit Gaussian's entropy per action dimension, :math:`\\tfrac12 \\log(2 \\pi e)`.


def seed_popart(running_mean: Tensor, running_mean_sq: Tensor, debiasing_term: Tensor) -> PopArtValueNorm:
    """TorchRL's :class:`~torchrl.modules.PopArtValueNorm` holding one row of statistics per seed.

    ``running_mean`` / ``running_mean_sq`` / ``debiasing_term``: ``(S, 1)`` (copied). The norm takes
    values laid out ``(N, S, 1)`` (samples first): TorchRL reduces over the leading dims. The norm lives where the
    statistics do (the round's device).
    """
    norm = PopArtValueNorm(shape=tuple(running_mean.shape), device=running_mean.device)
    norm.running_mean.copy_(running_mean)
    norm.running_mean_sq.copy_(running_mean_sq)
    norm.debiasing_term = debiasing_term.clone()  # one debiasing term per seed: seeds stop at different steps
    return norm


@dataclass(frozen=True)
class AgentObjective:
    """One agent's clipped-PPO step objective for S rows at once (see the module docstring).

    Attributes:
        surrogate: PPO's clipped surrogate.
        combine: the multiplier's advantage rule (:func:`~sg_torchrl.objectives.surrogates.combine_advantages`).
        weighted: multiply the advantage by the sequential factor :math:`M` (HAPPO, MAPPO-Lag).
        entropy_coeff: weight of the entropy bonus.
        critic_l2: weight of ``sum(p ** 2)`` over each critic's parameters.
    """

    surrogate: ClipSurrogate
    combine: CombineRule = "plain"
    weighted: bool = True
    entropy_coeff: float = 0.01
    critic_l2: float = 0.0

    def advantage(self, advantage: Tensor, cost_advantage: Tensor, lam: Tensor, factor: Tensor | None) -> Tensor:
        """:math:`M \\cdot \\mathrm{combine}(A_r, A_c)` (:math:`M` only when :attr:`weighted`), detached factor.

        ``lam``: 0-d, or one value per seed ``(S,)``; ``factor``: shaped like the advantages.
        """
        combined = combine_advantages(advantage, cost_advantage, lam, self.combine)
        if not self.weighted:
            return combined
        if factor is None:
            raise KeyError("a weighted agent objective needs the sequential update's factor M (1 for the first agent)")
        return factor.detach() * combined

    @staticmethod
    def cost_surrogate(log_weight: Tensor, cost_advantage: Tensor, seed_dims: int = 0) -> Tensor:
        """:math:`\\mathbb E[r A_c]` per seed, detached (what MAPPO-Lag's multiplier steps on)."""
        with torch.no_grad():
            return sample_mean(log_weight.exp() * cost_advantage, seed_dims)

    def losses(self, rows, batch: Mapping[str, Tensor], lam: Tensor, value_norm: PopArtValueNorm | None,
               active: Tensor | None = None, policy: tuple[Tensor, Tensor] | None = None) -> dict[str, Tensor]:
        """Each row's losses and diagnostics on its minibatch, ``(S,)`` each.

        ``rows``: the rows' networks (:class:`~sg_torchrl.modules.stacked_multi_agent.AgentRows`:
        ``dist_params``, ``mask`` (each row's real action slots), ``critic``, ``cost_critic``, ``tensors``);
        ``batch``: ``(S, N, width)`` fields ``observation``, ``state``, ``action``, ``action_log_prob``,
        ``advantage``, ``cost_advantage``, ``value_target``, ``cost_value_target`` (and ``factor`` when
        weighted); ``lam``: ``(S,)``; ``value_norm``: the rows' PopArt statistics (:func:`seed_popart`),
        updated here with the targets of the rows in ``active`` (all when ``None``); the others keep theirs.
        ``policy``: the rows' ``rows.dist_params(batch["observation"])`` when the caller already has it (with
        its graph, at the rows' current parameters), so it is not evaluated twice.

        Returns ``loss_objective``, ``loss_entropy``, ``loss_critic``, ``loss_cost_critic`` (the terms a step
        sums) and ``mean_ratio``, ``cost_surrogate`` (detached).
        """
        loc, scale = rows.dist_params(batch["observation"]) if policy is None else policy
        # The scale per sample, as the agent's distribution has it: the log-density and the entropy bonus reach
        # the scale's parameters through one sum over the samples (the order a per-agent loss sums them in).
        scale = scale.expand_as(loc)
        log_weight = gaussian_log_prob(batch["action"], loc, scale).unsqueeze(-1) - batch["action_log_prob"]
        cost_advantage = batch["cost_advantage"]
        advantage = self.advantage(batch["advantage"], cost_advantage, lam, batch.get("factor"))
        entropy = gaussian_entropy(scale, rows.mask.unsqueeze(1))  # (S, N)
        out = {"loss_objective": self.surrogate.loss(log_weight, advantage, seed_dims=1).mean((1, 2)),
               "loss_entropy": (-self.entropy_coeff * entropy).mean(1)}
        out.update(self.critic_losses(rows, batch, value_norm, active))
        with torch.no_grad():
            out["mean_ratio"] = log_weight.exp().mean((1, 2))
        out["cost_surrogate"] = self.cost_surrogate(log_weight, cost_advantage, seed_dims=1)
        return out

    def critic_losses(self, rows, batch: Mapping[str, Tensor], value_norm: PopArtValueNorm | None,
                      active: Tensor | None = None) -> dict[str, Tensor]:
        """Each row's ``loss_critic`` (through ``value_norm``, see :meth:`losses`) and ``loss_cost_critic``, ``(S,)``."""
        state = batch["state"]
        out = {"loss_critic": self._critic_loss(rows.critic(state), batch["value_target"], value_norm, active),
               "loss_cost_critic": self._critic_loss(rows.cost_critic(state), batch["cost_value_target"], None, None)}
        if self.critic_l2:
            out["loss_critic"] = out["loss_critic"] + self.critic_l2 * _squared_norm(rows.tensors("reward_value"))
            out["loss_cost_critic"] = out["loss_cost_critic"] + self.critic_l2 * _squared_norm(rows.tensors("cost_value"))
        return out

    @staticmethod
    def _critic_loss(value: Tensor, target: Tensor, value_norm: PopArtValueNorm | None,
                     active: Tensor | None) -> Tensor:
        """MSE per row; with ``value_norm``: update it with the targets, then normalised target vs prediction."""
        if value_norm is not None:
            # (N, S, 1): TorchRL reduces the samples. The target is a strided view of the packed batch: made
            # contiguous first, each row's mean sums its samples in the order of a contiguous (N, 1) column.
            value, target = value.transpose(0, 1), target.contiguous().transpose(0, 1)
            before = None if active is None else [t.clone() for t in value_norm.buffers()]
            value_norm.update(target)
            if before is not None:
                keep = ~active.view(-1, 1)
                for buffer, old in zip(value_norm.buffers(), before, strict=True):
                    buffer.copy_(torch.where(keep, old, buffer))
            target = value_norm.normalize(target.detach()).transpose(0, 1)
            value = value_norm.normalize(value).transpose(0, 1)
        return ((target - value) ** 2).mean((1, 2))


def _squared_norm(tensors: Sequence[Tensor]) -> Tensor:
    """Each row's ``sum(p ** 2)`` over ``tensors`` (leading row dim)."""
    return sum((t**2).reshape(t.shape[0], -1).sum(1) for t in tensors)
