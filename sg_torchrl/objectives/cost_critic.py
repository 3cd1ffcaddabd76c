"""The critics' side of the first-order losses: the cost critic's regression beside the reward critic's.

:class:`CostCriticLosses` is a mixin of :class:`~sg_torchrl.objectives.PPOLagLoss` (over TorchRL's
``ClipPPOLoss``, whose public ``loss_critic`` it calls, and whose ``_reduce_loss`` reduces every term
as TorchRL's own losses do, with ``reduction`` and ``loss_mask_key``): the
cost critic's loss mirrors TorchRL's reward-critic loss, and :meth:`CostCriticLosses.critic_losses`
reports both with SafePO's L2 penalty ``critic_l2_coeff * sum(p ** 2)``. The first-order losses'
``forward`` and the second-order updates' critic passes both train the critics with it.
"""
from __future__ import annotations

import contextlib

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn, Tensor
from torchrl.objectives.utils import distance_loss

from sg_torchrl.objectives.actor_terms import release_compile_refs

__all__ = ["CostCriticLosses"]


class CostCriticLosses:
    """The cost critic's loss and both critics' reduced losses with the L2 penalty (see the module docstring)."""

    def _squared_param_norm(self, network_name: str) -> Tensor | None:
        """Sum of squared parameters (weights and biases) of a critic; ``None`` if it has none."""
        if self.functional:
            params_td = getattr(self, network_name + "_params")
            params = [p for p in params_td.values(True, True) if isinstance(p, nn.Parameter)]
        else:
            params = list(getattr(self, network_name).parameters())
        if not params:
            return None
        return torch.stack([p.pow(2).sum() for p in params]).sum()

    def loss_cost_critic(
        self, tensordict: TensorDictBase
    ) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """Cost-critic regression loss, before reduction and without the L2 penalty.

        Mirrors :meth:`~torchrl.objectives.PPOLoss.loss_critic` for the cost critic: distance
        (``loss_critic_type``) between the cost critic's prediction and
        ``tensor_keys.cost_value_target``, optionally value-clipped around the stored
        ``tensor_keys.cost_value``, times ``cost_critic_coeff``. The reward critic's
        ``_critic_loss_inputs`` hook (e.g. PopArt value normalisation) is deliberately not applied:
        its statistics belong to the reward.

        Args:
            tensordict (TensorDictBase): the input batch.

        Returns:
            ``(loss, clip_fraction, explained_variance)``; ``loss`` is per sample, the other two
            are ``None`` when value clipping / explained-variance logging is off.
        """
        if self.separate_losses:
            tensordict = tensordict.detach()
        target = self._get_required(
            tensordict, self.tensor_keys.cost_value_target, "make_cost_gae(cost_critic)"
        )
        old_value = None
        if self.clip_value is not None:
            old_value = self._get_required(
                tensordict, self.tensor_keys.cost_value, "make_cost_gae(cost_critic)"
            )
        with (
            self.cost_critic_network_params.to_module(
                self.cost_critic_network, preserve_module_state=False
            )
            if self.functional
            else contextlib.nullcontext()
        ):
            out = self.cost_critic_network(tensordict.copy())
        value = out.get(self.tensor_keys.cost_value, None)
        if value is None:
            raise KeyError(
                f"The cost critic did not write {self.tensor_keys.cost_value!r}; check its out_keys "
                f"or call loss.set_keys(cost_value=...)."
            )
        loss = distance_loss(target, value, loss_function=self.loss_critic_type)
        clip_fraction = None
        if old_value is not None:
            delta = value - old_value
            clipped = delta.clamp(-self.clip_value, self.clip_value)
            loss_clipped = distance_loss(
                target, old_value + clipped, loss_function=self.loss_critic_type
            )
            loss = torch.maximum(loss, loss_clipped)
            with torch.no_grad():
                clip_fraction = (delta != clipped).to(value.dtype).mean()
        explained_variance = None
        if self.log_explained_variance:
            with torch.no_grad():
                tgt, pred = target.detach(), value.detach()
                eps = torch.finfo(tgt.dtype).eps
                resid = torch.var(tgt - pred, correction=0, dim=0)
                explained_variance = 1.0 - resid / (torch.var(tgt, correction=0, dim=0) + eps)
        return self.cost_critic_coeff * loss, clip_fraction, explained_variance

    def _reduce_losses(self, td_out: TensorDictBase, tensordict: TensorDictBase) -> TensorDictBase:
        """Applies the loss's reduction (and the input's loss mask) to every ``loss_*`` entry.

        Through ``LossModule._reduce_loss``, the one place TorchRL implements its documented
        ``reduction`` and ``loss_mask_key`` options (no public form exists); a copy here would drift
        from the reduction every TorchRL loss applies.
        """
        return td_out.named_apply(
            lambda name, value: self._reduce_loss(value, tensordict).squeeze(-1)
            if name.startswith("loss_")
            else value,
        )

    # --------------------------------------------------------------- forward
    def critic_losses(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The reduced reward- and cost-critic losses, each with the critic L2 penalty.

        ``loss_critic`` and ``loss_cost_critic`` (plus ``value_clip_fraction`` /
        ``cost_value_clip_fraction`` with ``clip_value``, and the explained variances with
        ``log_explained_variance``); the actor is not evaluated. :meth:`forward` uses it, and
        the second-order updates train their critics with it alone.
        """
        td_out = TensorDict()
        if self._trains_reward_critic:
            loss_critic, clip_fraction, explained_variance = self.loss_critic(tensordict.copy())
            td_out.set("loss_critic", loss_critic)
            if clip_fraction is not None:
                td_out.set("value_clip_fraction", clip_fraction)
            if explained_variance is not None:
                td_out.set("explained_variance", explained_variance)
        loss_cost, cost_clip_fraction, cost_ev = self.loss_cost_critic(tensordict)
        td_out.set("loss_cost_critic", loss_cost)
        if cost_clip_fraction is not None:
            td_out.set("cost_value_clip_fraction", cost_clip_fraction)
        if cost_ev is not None:
            td_out.set("cost_explained_variance", cost_ev)
        td_out = self._reduce_losses(td_out, tensordict)
        if self.critic_l2_coeff is not None:
            for key, network in (
                ("loss_critic", "critic_network"),
                ("loss_cost_critic", "cost_critic_network"),
            ):
                norm = self._squared_param_norm(network) if key in td_out.keys() else None
                if norm is not None:
                    td_out.set(key, td_out.get(key) + self.critic_l2_coeff * norm)
        release_compile_refs(tensordict, td_out, self.critic_network_params, self.cost_critic_network_params)
        return td_out

