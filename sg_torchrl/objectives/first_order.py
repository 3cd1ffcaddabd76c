"""The other first-order SafePO losses: PG, FOCOPS and CUP, as small :class:`PPOLagLoss` subclasses.

SafePO's first-order family (Ji et al. 2023, "Safety-Gymnasium: A Unified Safe Reinforcement
Learning Benchmark", the algorithms behind its single-agent tables) shares one update loop:
minibatch Adam steps on actor + reward critic + cost critic with KL early stopping. The
algorithms differ only in the policy objective, so each loss here returns its own
:attr:`PPOLagLoss.surrogate` (what is made of the importance ratio and the advantage; the math is
written once, in :mod:`sg_torchrl.objectives.surrogates`, and the seed-batched engine trains the
same object), and keeps the actor evaluation, ratio diagnostics and both critic losses of
:class:`PPOLagLoss`:

* **PPO** (unconstrained) needs no class: ``PPOLagLoss(actor, critic, cost_critic, NoMultiplier())``
  optimises the clipped surrogate on the reward advantage alone, and still trains and reports the
  cost critic (``loss_cost_critic``) so that costs are learned and logged like every algorithm's.
* :class:`PGLoss`: the importance-weighted policy gradient :math:`-\\mathbb E[r A]`, no clipping.
* :class:`FOCOPSLoss`: Zhang, Vuong and Ross 2020, "First Order Constrained Optimization in
  Policy Space" (https://arxiv.org/abs/2002.06506).
* :class:`CUPLoss`: Yang et al. 2022, "Constrained Update Projection Approach to Safe Policy
  Optimization" (https://arxiv.org/abs/2209.07089); two stages, the first being PPO on the reward.

FOCOPS and CUP regularise towards a stored diagonal-Gaussian policy whose ``loc`` / ``scale`` are
in the batch; the KL to it is taken in closed form (:func:`~sg_torchrl.objectives.gaussian_kl`)
from the current policy the loss already evaluates, so no loss adds an actor forward pass.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor

from sg_torchrl.objectives.multipliers import _as_finite_float, Multiplier, NoMultiplier
from sg_torchrl.objectives.ppo_lag import _as_key_list, PPOLagLoss
from sg_torchrl.objectives.surrogates import CUPProjectionSurrogate, FOCOPSSurrogate, PGSurrogate

__all__ = ["CUPLoss", "FOCOPSLoss", "PGLoss"]


class PGLoss(PPOLagLoss):
    """Importance-weighted policy gradient (SafePO's ``pg.py`` baseline), plus both critics.

    .. math::

        L^{\\text{obj}} = -\\mathbb E\\left[r_t(\\theta) A_t\\right],\\qquad
        r_t(\\theta) = \\frac{\\pi_\\theta(a_t|s_t)}{\\pi_{\\text{old}}(a_t|s_t)},

    i.e. :class:`PPOLagLoss` without the clip: at :math:`\\theta = \\theta_{\\text{old}}` its gradient
    is the vanilla policy gradient, and later minibatch steps of the epoch stay importance
    weighted by the rollout log-probs. :math:`A_t` is ``multiplier.combine(A_r, A_c)``; SafePO's PG
    is unconstrained, hence the default :class:`~sg_torchrl.objectives.NoMultiplier`
    (:math:`A = A_r`), but any multiplier gives a Lagrangian PG. The reward and cost critics are
    trained and reported exactly as in :class:`PPOLagLoss`; ``clip_epsilon`` is accepted and unused.

    Args:
        actor_network, critic_network, cost_critic_network: as :class:`PPOLagLoss`.
        multiplier (Multiplier, optional): defaults to ``NoMultiplier()``.
        **kwargs: forwarded to :class:`PPOLagLoss` (``critic_l2_coeff``, ``functional``, ...).

    Output keys:
        those of :class:`PPOLagLoss` without ``clip_fraction``.
    """


    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        critic_network: TensorDictModule,
        cost_critic_network: TensorDictModule,
        multiplier: Multiplier | None = None,
        **kwargs: Any,
    ) -> None:
        if multiplier is None:
            multiplier = NoMultiplier()
        super().__init__(actor_network, critic_network, cost_critic_network, multiplier, **kwargs)

    @property
    def surrogate(self) -> PGSurrogate:
        """:math:`-r A`, no clip (:class:`~sg_torchrl.objectives.surrogates.PGSurrogate`)."""
        return PGSurrogate()


class FOCOPSLoss(PPOLagLoss):
    """FOCOPS: first-order constrained optimisation in policy space (Zhang et al. 2020).

    FOCOPS (https://arxiv.org/abs/2002.06506) solves the constrained trust-region problem in the
    space of policies: the optimal update is :math:`\\pi^*(a|s) \\propto \\pi_{\\text{old}}(a|s)
    \\exp(A(s,a) / \\lambda_F)` with :math:`A = A_r - \\nu A_c`, and the parametric policy is fitted to
    it by minimising, per sample (the estimate of the paper's Algorithm 1),

    .. math::

        L^{\\text{obj}} = \\mathbb E_i\\left[\\Big(\\mathrm{KL}_i - \\frac{1}{\\lambda_F}\\, r_i A_i\\Big)
        \\,\\mathbb 1\\{\\mathrm{KL}_i \\le \\delta\\}\\right],\\qquad
        \\mathrm{KL}_i = \\mathrm{KL}\\big(\\pi_\\theta(\\cdot|s_i) \\,\\|\\, \\pi_{\\text{old}}(\\cdot|s_i)\\big),

    with :math:`r_i = \\pi_\\theta(a_i|s_i) / \\pi_{\\text{old}}(a_i|s_i)` (``action_log_prob``) and
    the indicator (no gradient) dropping samples whose state already left the trust region. The
    Safety-Gymnasium paper's settings (SafePO ``focops.py``): temperature :math:`\\lambda_F = 1.5`,
    :math:`\\delta` = ``target_kl`` = 0.02 (also the epoch's KL early stop), and
    :math:`A = (A_r - \\nu A_c)/(1 + \\nu)` from ``multiplier.combine``.

    The multiplier :math:`\\nu` is SafePO's Lagrange multiplier capped at 2.0: the trainer builds
    ``LagrangeMultiplier(cost_limit=25.0, upper_bound=2.0)`` (Adam lr 0.035, init 0.001) and
    updates it once per epoch; the loss only reads it.

    .. note::
        **SafePO quirk** (``safepo_broadcast=True``): SafePO's per-sample KL has shape ``(B, 1)``
        and :math:`r A` shape ``(B,)``, so its expression broadcasts to a :math:`B \\times B` matrix
        and evaluates to :math:`\\overline{\\mathrm{KL}\\,\\mathbb 1} - \\frac{1}{\\lambda_F}
        \\overline{\\mathbb 1}\\;\\overline{r A}`: the indicator does not mask the advantage term
        per sample, it only scales it by the fraction of samples inside the trust region. The
        default is the paper's per-sample loss above; the option reproduces SafePO's value and
        gradient.

    Args:
        actor_network (ProbabilisticTensorDictSequential): a diagonal Gaussian policy (``Normal``
            or ``IndependentNormal``), as for :class:`PPOLagLoss`.
        critic_network, cost_critic_network: as :class:`PPOLagLoss`.
        multiplier (Multiplier): :math:`\\nu` (see above).

    Keyword Args:
        temperature (float): :math:`\\lambda_F` (> 0). Defaults to ``1.5``.
        target_kl (float): :math:`\\delta`, the per-sample KL above which a sample is dropped
            (>= 0). Defaults to ``0.02``.
        safepo_broadcast (bool): reproduce SafePO's broadcasting quirk (see the note). Defaults to
            ``False``.
        **kwargs: forwarded to :class:`PPOLagLoss`; ``clip_epsilon`` is accepted and unused.

    Input keys:
        those of :class:`PPOLagLoss` plus the rollout policy's parameters ``"loc"`` and
        ``"scale"`` (keys ``old_loc`` / ``old_scale``, the actor's outputs stored by the
        collector; remap with :meth:`set_keys`).

    Output keys:
        those of :class:`PPOLagLoss` with, instead of ``clip_fraction``, ``kl`` (batch mean of
        :math:`\\mathrm{KL}_i`) and ``kl_mask_fraction`` (fraction of samples with
        :math:`\\mathrm{KL}_i \\le \\delta`).
    """

    @dataclass
    class _AcceptedKeys(PPOLagLoss._AcceptedKeys):
        """:class:`PPOLagLoss`'s keys plus the rollout policy's stored parameters.

        Attributes:
            old_loc (NestedKey): mean of :math:`\\pi_{\\text{old}}` at each sample. Defaults to
                ``"loc"``.
            old_scale (NestedKey): standard deviation of :math:`\\pi_{\\text{old}}`. Defaults to
                ``"scale"``.
        """

        old_loc: NestedKey = "loc"
        old_scale: NestedKey = "scale"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    _schedulable_buffers = PPOLagLoss._schedulable_buffers | {"temperature", "target_kl"}

    temperature: Tensor
    target_kl: Tensor

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        critic_network: TensorDictModule,
        cost_critic_network: TensorDictModule,
        multiplier: Multiplier,
        *,
        temperature: float = 1.5,
        target_kl: float = 0.02,
        safepo_broadcast: bool = False,
        **kwargs: Any,
    ) -> None:
        temperature = _as_finite_float(temperature, "temperature")
        if temperature <= 0:
            raise ValueError(f"temperature must be > 0, got {temperature}.")
        target_kl = _as_finite_float(target_kl, "target_kl")
        if target_kl < 0:
            raise ValueError(f"target_kl must be >= 0, got {target_kl}.")
        super().__init__(actor_network, critic_network, cost_critic_network, multiplier, **kwargs)
        device = self.cost_critic_coeff.device
        self.register_coeff_buffer("temperature", temperature, device=device)
        self.register_coeff_buffer("target_kl", target_kl, device=device)
        self.safepo_broadcast = bool(safepo_broadcast)

    def _set_in_keys(self) -> None:
        super()._set_in_keys()
        extra = [*_as_key_list(self.tensor_keys.old_loc), *_as_key_list(self.tensor_keys.old_scale)]
        self.in_keys = list(dict.fromkeys([*self.in_keys, *extra]))

    @property
    def surrogate(self) -> FOCOPSSurrogate:
        """FOCOPS's masked objective with this loss's temperature, threshold and quirk option."""
        return FOCOPSSurrogate(float(self.temperature), float(self.target_kl), self.safepo_broadcast)

    def extra_repr(self) -> str:
        return (
            f"temperature={float(self.temperature)}, target_kl={float(self.target_kl)}, "
            f"safepo_broadcast={self.safepo_broadcast}"
        )


class CUPLoss(PPOLagLoss):
    """CUP: constrained update projection (Yang et al. 2022), both stages in one object.

    CUP (https://arxiv.org/abs/2209.07089) alternates, every epoch,

    1. **policy improvement**: PPO-clip on the reward advantage :math:`A_r` alone, with both critics
       trained: :attr:`reward_stage`, a ``PPOLagLoss`` with
       :class:`~sg_torchrl.objectives.NoMultiplier` over the *same* actor and critics (its
       parameters are this loss's parameters). The trainer runs its minibatch passes with the
       usual KL early stop, then stores the resulting stage-one policy's ``loc`` / ``scale`` in the
       batch (``stage1_loc`` / ``stage1_scale``);
    2. **projection** (this object's :meth:`forward`, actor only): minimise, per sample,

       .. math::

           L^{\\text{proj}} = \\mathbb E_i\\left[\\nu\\, c\\, r_i A^c_i
           + \\mathrm{KL}\\big(\\pi_\\theta(\\cdot|s_i) \\,\\|\\, \\pi_{\\text{stage1}}(\\cdot|s_i)\\big)\\right],
           \\qquad c = \\frac{1 - \\gamma \\lambda_{\\text{CUP}}}{1 - \\gamma},

       with :math:`r_i` the ratio to the *behaviour* (rollout) policy, ``action_log_prob``, and
       :math:`A^c` the cost advantage as given (SafePO only mean-centres it). The trainer stops the
       passes once :math:`\\mathrm{KL}(\\pi_{\\text{stage1}} \\| \\pi_\\theta)` over the batch exceeds
       ``target_kl``. The defaults :math:`\\gamma = 0.99`, :math:`\\lambda_{\\text{CUP}} = 0.95` give
       :math:`c = 5.95` (SafePO ``cup.py``; Safety-Gymnasium paper hyper-parameters).

    :math:`\\nu` is ``multiplier.value``, used as is (no :math:`1/(1+\\nu)` normalisation). SafePO's
    code (commit 8d0fa763) builds it as its standard Lagrange multiplier (Adam lr 0.035, init 0.001)
    clamped to the upper bound 0.2 (its constant ``CUP_NU``), while the Safety-Gymnasium paper's
    hyper-parameter table lists "nu 2.00" for CUP: the trainer chooses, e.g.
    ``LagrangeMultiplier(cost_limit=25.0, upper_bound=0.2)`` for SafePO's code.

    .. note::
        SafePO's projection loss has the same ``(B, 1) + (B,)`` broadcasting as its FOCOPS loss
        (:class:`FOCOPSLoss`), but here the two terms are only added, and the mean of the
        :math:`B \\times B` broadcast sum equals the per-sample mean above (value and gradient), so
        there is no separate quirk option.

    Args:
        actor_network (ProbabilisticTensorDictSequential): a diagonal Gaussian policy.
        critic_network, cost_critic_network: as :class:`PPOLagLoss` (trained by
            :attr:`reward_stage`; ``loss.critic_losses`` also works).
        multiplier (Multiplier): :math:`\\nu` (see above).

    Keyword Args:
        gamma (float): discount in :math:`c`, in ``[0, 1)``. Defaults to ``0.99``.
        cup_lambda (float): :math:`\\lambda_{\\text{CUP}}` in :math:`c`, in ``[0, 1]``. Defaults to
            ``0.95``.
        **kwargs: forwarded to both stages' :class:`PPOLagLoss` (``clip_epsilon`` for stage one,
            ``critic_l2_coeff``, ``functional``, ...).

    Input keys (stage two):
        the actor's ``in_keys``, ``"action"``, ``"action_log_prob"``, ``"cost_advantage"``,
        ``"stage1_loc"``, ``"stage1_scale"`` (remap with :meth:`set_keys`). Without
        ``"cost_advantage"`` the loss computes it from the input's trajectories, as
        :class:`PPOLagLoss` does (cost critic, cost GAE, mean-centred).

    Output keys (stage two):
        ``loss_objective`` (the only term; ``loss_entropy`` too with an entropy bonus), and detached
        ``kl`` (batch mean of :math:`\\mathrm{KL}(\\pi_\\theta \\| \\pi_{\\text{stage1}})`),
        ``lagrange_multiplier``, ``kl_approx``, ``ESS``, ``max_ratio``, ``mean_ratio``.
    """

    @dataclass
    class _AcceptedKeys(PPOLagLoss._AcceptedKeys):
        """:class:`PPOLagLoss`'s keys plus the stage-one policy's parameters.

        Attributes:
            stage1_loc (NestedKey): mean of the stage-one policy at each sample. Defaults to
                ``"stage1_loc"``.
            stage1_scale (NestedKey): its standard deviation. Defaults to ``"stage1_scale"``.
        """

        stage1_loc: NestedKey = "stage1_loc"
        stage1_scale: NestedKey = "stage1_scale"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    _schedulable_buffers = PPOLagLoss._schedulable_buffers | {"cost_coeff"}

    reward_stage: PPOLagLoss
    cost_coeff: Tensor

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        critic_network: TensorDictModule,
        cost_critic_network: TensorDictModule,
        multiplier: Multiplier,
        *,
        gamma: float = 0.99,
        cup_lambda: float = 0.95,
        **kwargs: Any,
    ) -> None:
        gamma = _as_finite_float(gamma, "gamma")
        if not 0.0 <= gamma < 1.0:
            raise ValueError(f"gamma must be in [0, 1), got {gamma}.")
        cup_lambda = _as_finite_float(cup_lambda, "cup_lambda")
        if not 0.0 <= cup_lambda <= 1.0:
            raise ValueError(f"cup_lambda must be in [0, 1], got {cup_lambda}.")
        super().__init__(actor_network, critic_network, cost_critic_network, multiplier, **kwargs)
        self.reward_stage = PPOLagLoss(
            actor_network,
            critic_network,
            cost_critic_network,
            NoMultiplier(cost_limit=float(multiplier.cost_limit)),
            **kwargs,
        )
        self.gamma = gamma
        self.cup_lambda = cup_lambda
        cost_coeff = (1.0 - gamma * cup_lambda) / (1.0 - gamma)
        self.register_coeff_buffer("cost_coeff", cost_coeff, device=self.cost_critic_coeff.device)

    def _set_in_keys(self) -> None:
        actor = getattr(self, "actor_network", None)
        keys: list[NestedKey] = list(actor.in_keys) if actor is not None else []
        for name in ("action", "sample_log_prob", "cost_advantage", "stage1_loc", "stage1_scale"):
            keys.extend(_as_key_list(getattr(self.tensor_keys, name)))
        self.in_keys = list(dict.fromkeys(keys))

    @property
    def out_keys(self) -> list[NestedKey]:
        """The projection's terms and diagnostics (no critic losses: stage two trains the actor alone)."""
        if self._output_keys is None:
            keys = ["loss_objective", *self.surrogate.diagnostic_names]
            if self.entropy_bonus:
                keys.extend(["entropy", "loss_entropy"])
            keys.extend(["ESS", "kl_approx", "max_ratio", "mean_ratio", "lagrange_multiplier"])
            self._output_keys = keys
        return self._output_keys

    @out_keys.setter
    def out_keys(self, values: list[NestedKey]) -> None:
        self._output_keys = values

    @property
    def surrogate(self) -> CUPProjectionSurrogate:
        """CUP's projection objective with this loss's :math:`c` (stage one is :attr:`reward_stage`'s)."""
        return CUPProjectionSurrogate(float(self.cost_coeff))

    def extra_repr(self) -> str:
        return (
            f"gamma={self.gamma}, cup_lambda={self.cup_lambda}, "
            f"cost_coeff={float(self.cost_coeff)}"
        )
