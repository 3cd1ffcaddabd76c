"""One agent's clipped-PPO loss in the sequential update (MAPPO, HAPPO, MAPPO-Lag; MACPO's critics).

:class:`AgentPPOLoss` is TorchRL's :class:`~torchrl.objectives.multiagent.MAPPOLoss` (Yu et al.
2022, "The Surprising Effectiveness of PPO in Cooperative Multi-Agent Games": decentralised actor,
centralised critic, optional :class:`~torchrl.modules.ValueNorm`) combined with sg_torchrl's
:class:`~sg_torchrl.objectives.PPOLagLoss` (cost critic, Lagrangian advantage through
:meth:`~sg_torchrl.objectives.Multiplier.combine`), applied to one agent's flat view of the batch
(:func:`~sg_torchrl.objectives.multi_agent.agent_view`). It adds the only multi-agent term: the
advantage is multiplied by the sequential update's factor :math:`M` (HAPPO, Kuba et al. 2022):

.. math::

    L^{\\text{obj}} = -\\mathbb E\\left[M \\min\\big(r A,\\ \\mathrm{clip}(r, 1 - \\epsilon, 1 + \\epsilon) A\\big)\\right]
    = -\\mathbb E\\left[\\min\\big(r\\, (M A),\\ \\mathrm{clip}(r, 1 - \\epsilon, 1 + \\epsilon)\\, (M A)\\big)\\right],

the two forms being equal because :math:`M > 0` (a product of probability ratios). So the factor is
folded into the advantage and the clipped surrogate, ratio diagnostics, entropy bonus and critic losses
are the parent classes' own.

The loss is a view of the seed-batched definition the rounds train
(:class:`~sg_torchrl.objectives.multi_agent.AgentObjective`, handed out by
:meth:`AgentPPOLoss.seed_batched_objective`): the weighted advantage and the cost surrogate are computed
by that object, the clipped surrogate is the same :class:`~sg_torchrl.objectives.surrogates.ClipSurrogate`.

With ``weighted=False`` the factor is ignored: independent per-agent PPO with centralised critics,
i.e. MAPPO with separate per-agent networks (what SafePO's ``mappo.py`` runs). The ratio is the
joint ratio of the agent's action (product over action dims, Yu et al. 2022); SafePO's MAPPO script
clips per action dimension and sums the clipped terms instead.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from tensordict import TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule
from tensordict.utils import NestedKey
from torch import distributions as D, Tensor
from torchrl.modules import ValueNorm
from torchrl.objectives.multiagent import MAPPOLoss

from sg_torchrl.objectives.multi_agent.objective import AgentObjective
from sg_torchrl.objectives.multipliers import Multiplier
from sg_torchrl.objectives.ppo_lag import PPOLagLoss

__all__ = ["AgentPPOLoss"]


class AgentPPOLoss(PPOLagLoss, MAPPOLoss):
    """Factor-weighted clipped PPO for one agent, with its reward and cost critics.

    The policy loss is :class:`~sg_torchrl.objectives.PPOLagLoss`'s clipped surrogate on
    :math:`M \\cdot \\mathrm{combine}(A_r, A_c)` (``multiplier.combine``: :math:`A_r` for
    :class:`~sg_torchrl.objectives.NoMultiplier`, :math:`A_r - \\lambda A_c` for MAPPO-Lag's
    :class:`~sg_torchrl.objectives.multi_agent.MAPPOLagMultiplier`), plus
    ``-entropy_coeff * entropy``. The reward critic's loss goes through
    :class:`~torchrl.objectives.multiagent.MAPPOLoss`'s ``value_norm`` hook (TorchRL semantics: the
    critic predicts real-scale values, the loss compares normalised prediction and target); the cost
    critic's loss is :class:`~sg_torchrl.objectives.PPOLagLoss`'s (not normalised).

    The loss does no advantage standardisation (advantages are standardised per agent on the whole
    batch before the factor is applied, see
    :func:`~sg_torchrl.objectives.multi_agent.make_multi_agent_gae`) and runs no value estimator.

    Args:
        actor_network: the agent's policy (:meth:`MultiAgentNetworks.agent_actor`).
        critic_network: the agent's reward critic, writing ``"state_value"``.
        cost_critic_network: the agent's cost critic, writing ``"cost_value"``.
        multiplier (Multiplier): read through ``multiplier.combine``; never updated by the loss.

    Keyword Args:
        weighted (bool): multiply the advantage by ``tensor_keys.factor`` (HAPPO, MAPPO-Lag).
            ``False``: plain per-agent PPO (MAPPO). Defaults to ``True``.
        clip_epsilon (float): defaults to ``0.2`` (paper).
        entropy_coeff (float): defaults to ``0.01`` (SafePO's multi-agent configs).
        value_norm (ValueNorm, optional): e.g. :class:`~torchrl.modules.PopArtValueNorm` for the
            reward critic. Defaults to ``None``.
        critic_l2_coeff (float, optional): SafePO's multi-agent critics have no L2 penalty
            (weight decay 0). Defaults to ``None``.
        **kwargs: forwarded to :class:`~sg_torchrl.objectives.PPOLagLoss` /
            :class:`~torchrl.objectives.ClipPPOLoss` (``clip_value``, ``loss_critic_type``,
            ``functional``, ...).

    Input keys: the actor's and critics' in-keys (``"observation"``, ``"state"``), ``"action"``,
    ``"action_log_prob"``, ``"advantage"``, ``"value_target"``, ``"cost_advantage"``,
    ``"cost_value_target"`` and, when ``weighted``, ``"factor"`` (``[B]`` or ``[B, 1]``).

    Output keys: :class:`~sg_torchrl.objectives.PPOLagLoss`'s (``loss_objective``, ``loss_critic``,
    ``loss_cost_critic``, ``loss_entropy``, ``entropy``, ``mean_ratio``, ...) plus
    ``cost_surrogate`` :math:`= \\mathbb E[r A_c]` (detached, without the factor), which MAPPO-Lag's
    multiplier update reads.
    """

    @dataclass
    class _AcceptedKeys(PPOLagLoss._AcceptedKeys):
        """:class:`~sg_torchrl.objectives.PPOLagLoss`'s keys plus ``factor`` (the sequential update's :math:`M`)."""

        factor: NestedKey = "factor"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    _surrogate_out_keys = ("clip_fraction", "cost_surrogate")
    # Fed one agent's flattened view: no trajectories left to estimate advantages on.
    _estimates_missing_advantages = False

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        critic_network: TensorDictModule,
        cost_critic_network: TensorDictModule,
        multiplier: Multiplier,
        *,
        weighted: bool = True,
        clip_epsilon: float = 0.2,
        entropy_coeff: float | Mapping[NestedKey, float] = 0.01,
        value_norm: ValueNorm | None = None,
        critic_l2_coeff: float | None = None,
        **kwargs: Any,
    ) -> None:
        self.weighted = bool(weighted)
        kwargs.setdefault("normalize_advantage", False)
        super().__init__(
            actor_network,
            critic_network,
            cost_critic_network,
            multiplier,
            clip_epsilon=clip_epsilon,
            entropy_coeff=entropy_coeff,
            critic_l2_coeff=critic_l2_coeff,
            value_norm=value_norm,
            **kwargs,
        )

    def _set_in_keys(self) -> None:
        super()._set_in_keys()
        if getattr(self, "weighted", False):
            self._in_keys = list(dict.fromkeys([*self._in_keys, self.tensor_keys.factor]))

    def seed_batched_objective(self, *, critics_only: bool = False) -> AgentObjective:
        """This loss in the seed-batched form the multi-agent rounds train (the public protocol).

        Raises:
            ValueError: ``critics_only`` (MACPO's critics train through this loss itself), or options the
                seed-batched form does not implement (value clipping, non-MSE critics, critic coefficients
                other than 1, ``delay_actor`` / ``max_importance_ratio``).
        """
        self.refuse_unbatched_options("the seed-batched multi-agent round", critics_only=critics_only)
        return AgentObjective(self.surrogate, combine=self.multiplier.combine_rule, weighted=self.weighted,
                              entropy_coeff=float(self.entropy_coeff) if self.entropy_bonus else 0.0,
                              critic_l2=0.0 if self.critic_l2_coeff is None else float(self.critic_l2_coeff))

    def _combined_advantage(self, tensordict: TensorDictBase) -> Tensor:
        """``multiplier.combine(A_r, A_c)``, times the factor :math:`M` when ``weighted`` (:meth:`AgentObjective.advantage`)."""
        advantage = self._get_required(tensordict, self.tensor_keys.advantage, "make_gae(critic)")
        cost_advantage = self._get_required(tensordict, self.tensor_keys.cost_advantage, "make_cost_gae(cost_critic)")
        if advantage.shape != cost_advantage.shape:
            raise ValueError(f"advantage {tuple(advantage.shape)} and cost advantage {tuple(cost_advantage.shape)} "
                             f"differ in shape")
        factor = None
        if self.weighted:
            factor = tensordict.get(self.tensor_keys.factor, None)
            if factor is None:
                raise KeyError(
                    f"AgentPPOLoss(weighted=True) needs the sequential update's factor under "
                    f"{self.tensor_keys.factor!r} (1 for the first agent of a round); use weighted=False to ignore it."
                )
            if factor.shape == advantage.shape[:-1]:
                factor = factor.unsqueeze(-1)
            if factor.shape != advantage.shape:
                raise ValueError(
                    f"the factor has shape {tuple(factor.shape)}; expected {tuple(advantage.shape)} or "
                    f"{tuple(advantage.shape[:-1])} (one value per sample)."
                )
        return self.seed_batched_objective().advantage(advantage, cost_advantage, self.multiplier.value, factor)

    def _surrogate(
        self,
        log_weight: Tensor,
        advantage: Tensor,
        dist: D.Distribution,
        tensordict: TensorDictBase,
        *,
        log_is_weight: Tensor | None = None,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        loss, diagnostics = super()._surrogate(log_weight, advantage, dist, tensordict, log_is_weight=log_is_weight)
        cost_advantage = tensordict.get(self.tensor_keys.cost_advantage)
        log_ratio = log_weight if log_is_weight is None else log_weight + log_is_weight
        diagnostics["cost_surrogate"] = AgentObjective.cost_surrogate(log_ratio, cost_advantage.reshape(log_ratio.shape))
        return loss, diagnostics
