"""The actor's side of the first-order losses: the log importance weight, the policy terms, their diagnostics.

:class:`ActorTerms` is a mixin of :class:`~sg_torchrl.objectives.PPOLagLoss` (over TorchRL's
``ClipPPOLoss``), the counterpart of :class:`~sg_torchrl.objectives.cost_critic.CostCriticLosses`.
It evaluates the actor once per call and hands the log ratio to the loss's ``_surrogate`` hook. The
ratio, the entropy bonus and the diagnostics are computed here from public TorchRL / tensordict
APIs (the actor's ``get_dist``, the functional parameters' ``to_module``, the loss's public
``delay_actor`` / ``max_importance_ratio`` / ``entropy_coeff`` attributes) rather than through
``ClipPPOLoss``'s private helpers: the same operations in the same order, so the numbers are
TorchRL's, and a private rename in TorchRL cannot change them.

What this covers is what sg_torchrl's actors are: one action distribution (not a TorchRL
composite of several heads); a composite distribution gets a clear error.
"""
from __future__ import annotations

import contextlib

import torch
from tensordict import is_tensor_collection, TensorDict, TensorDictBase, TensorDictParams
from torch import distributions as D, Tensor

from sg_torchrl.objectives.surrogates import Surrogate

__all__ = ["ActorTerms", "release_compile_refs"]


def release_compile_refs(*tensordicts: TensorDictBase | None) -> None:
    """Drops the tensordicts' weak references when traced by ``torch.compile`` (a no-op otherwise).

    What TorchRL's losses do before returning from ``forward`` so that a compiled loss can hand its
    TensorDicts out of the compiled region (``clear_refs_for_compile_``, tensordict's public method).
    """
    if torch.compiler.is_compiling():
        for td in tensordicts:
            if is_tensor_collection(td):
                td.clear_refs_for_compile_()


class ActorTerms:
    """The actor's log ratio, entropy and policy terms of a first-order loss (see the module docstring)."""

    def _current_log_prob(
        self, tensordict: TensorDictBase, params: TensorDictParams | None
    ) -> tuple[Tensor, D.Distribution]:
        """``log pi(a|s)`` of the stored action under the actor with ``params``, and the distribution."""
        with (
            params.to_module(self.actor_network, preserve_module_state=False)
            if self.functional
            else contextlib.nullcontext()
        ):
            dist = self.actor_network.get_dist(tensordict)
        action = tensordict.get(self.tensor_keys.action)
        if action.requires_grad:
            raise RuntimeError(f"tensordict stored {self.tensor_keys.action} requires grad.")
        log_prob = dist.log_prob(action)
        if is_tensor_collection(log_prob):
            raise TypeError(
                f"{type(self).__name__} supports actors with one action distribution; this actor's "
                f"{type(dist).__name__} gives one log-probability per action head."
            )
        return log_prob, dist

    def _policy_log_ratio(
        self, tensordict: TensorDictBase
    ) -> tuple[Tensor, D.Distribution, Tensor, Tensor | None]:
        """The actor evaluated once: ``(log_weight, dist, kl_approx, log_is_weight)``, TorchRL's PPO ratio.

        ``log_weight`` is :math:`\\log \\pi_\\theta - \\log \\pi_{\\text{prox}}` (shape ``[*B, 1]``,
        differentiable), ``kl_approx`` its negation (a diagnostic), ``log_is_weight``
        :math:`\\log \\pi_{\\text{prox}} - \\log \\pi_{\\text{behav}}` (gradient-free). The proximal
        policy is the behaviour policy (``log_is_weight`` is ``None``) unless ``delay_actor`` (the
        target actor's parameters) or ``max_importance_ratio`` (the behaviour log-prob lifted so that
        :math:`\\pi_\\theta / \\pi_{\\text{behav}}` stays under the cap) is set, as in TorchRL's PPO.
        """
        key = self.tensor_keys.sample_log_prob
        prev_log_prob = tensordict.get(key, None)
        if prev_log_prob is None:
            raise KeyError(f"Couldn't find the log-prob {key} in the input data.")
        if prev_log_prob.requires_grad:
            raise RuntimeError(f"tensordict stored {key} requires grad.")
        log_prob, dist = self._current_log_prob(tensordict, self.actor_network_params)
        if self.delay_actor:
            with torch.no_grad():
                prox_log_prob, _ = self._current_log_prob(tensordict, self.target_actor_network_params)
        else:
            prox_log_prob = prev_log_prob
        log_weight = (log_prob - prox_log_prob).unsqueeze(-1)
        kl_approx = (prox_log_prob - log_prob).unsqueeze(-1)
        log_is_weight = None
        if self.delay_actor:
            log_is_weight = (prox_log_prob - prev_log_prob).unsqueeze(-1)
        if self.max_importance_ratio is not None:
            if log_is_weight is None:
                log_is_weight = torch.zeros_like(log_weight)
            log_is_weight = torch.minimum(log_is_weight, self.max_importance_ratio.log() - log_weight.detach())
        return log_weight, dist, kl_approx, log_is_weight

    def _entropy(self, dist: D.Distribution) -> Tensor:
        """The policy's entropy per sample, ``[*B, 1]``: analytic, else a ``samples_mc_entropy``-sample estimate."""
        try:
            entropy = dist.entropy()
        except NotImplementedError:
            shape = (self.samples_mc_entropy,)
            samples = dist.rsample(shape) if dist.has_rsample else dist.sample(shape)
            entropy = -dist.log_prob(samples).mean(0)
        return entropy.unsqueeze(-1)

    def _actor_loss(self, tensordict: TensorDictBase, advantage: Tensor) -> TensorDictBase:
        """Unreduced policy terms on ``advantage``: the ``_surrogate`` hook, ratio diagnostics, entropy.

        Evaluates the actor once (:meth:`_policy_log_ratio`, on a shallow copy of ``tensordict``,
        which therefore keeps its stored values), then the loss's ``_surrogate`` hook. Diagnostics as
        :class:`~torchrl.objectives.ClipPPOLoss`: ``kl_approx``, ``ESS``, ``max_ratio``,
        ``mean_ratio`` (of the behaviour ratio), plus ``entropy`` / ``loss_entropy``
        (:math:`-c_H H`) with an entropy bonus.

        Raises:
            ValueError: if ``advantage`` does not have the log-ratio's shape ``[*B, 1]``.
        """
        log_weight, dist, kl_approx, log_is_weight = self._policy_log_ratio(tensordict.copy())
        if advantage.shape != log_weight.shape:
            raise ValueError(
                f"The advantage has shape {tuple(advantage.shape)} but the log-ratio has shape "
                f"{tuple(log_weight.shape)}; the advantage needs the trailing value dimension "
                f"(batch shape + (1,))."
            )
        loss, diagnostics = self._surrogate(
            log_weight, advantage, dist, tensordict, log_is_weight=log_is_weight
        )
        td_out = TensorDict({"loss_objective": loss, **diagnostics})
        with torch.no_grad():
            log_ratio = Surrogate.log_ratio(log_weight, log_is_weight).detach()
            flat = log_ratio.reshape(-1)  # over every sample, also of an [N, T] rollout
            ess = (2 * flat.logsumexp(0) - (2 * flat).logsumexp(0)).exp()
            ratio = log_ratio.exp()
            td_out.set("kl_approx", kl_approx.detach().mean())
            td_out.set("ESS", ess / flat.numel())
            td_out.set("max_ratio", ratio.max())
            td_out.set("mean_ratio", ratio.mean())
        if self.entropy_bonus:
            entropy = self._entropy(dist)
            td_out.set("entropy", entropy.detach().mean())
            td_out.set("loss_entropy", -self.entropy_coeff * entropy)
        return td_out
