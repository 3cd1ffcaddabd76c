"""PPO-Lagrangian (and CPPO-PID) as a thin :class:`~torchrl.objectives.ClipPPOLoss` subclass.

PPO-Lag (Ray et al. 2019, "Benchmarking Safe Exploration in Deep Reinforcement Learning"; the
SafePO implementation benchmarked in Ji et al. 2023, "Safety-Gymnasium: A Unified Safe
Reinforcement Learning Benchmark") optimises the PPO clipped surrogate on the Lagrangian
advantage :math:`A = (A_r - \\lambda A_c) / (1 + \\lambda)`, trains a reward critic and a cost
critic, and adapts :math:`\\lambda \\ge 0` once per epoch from the mean episode cost. In sg_torchrl the three concerns are separate objects:

* :class:`PPOLagLoss` (this module) computes the surrogate and both critic losses; it reads the
  multiplier's current :attr:`~sg_torchrl.objectives.Multiplier.value` and never updates it;
* :class:`~sg_torchrl.objectives.LagrangeMultiplier` /
  :class:`~sg_torchrl.objectives.PIDLagrangeMultiplier` hold :math:`\\lambda` and its update rule
  (the trainer calls ``multiplier.update(mean_episode_cost)`` once per epoch);
* :func:`~sg_torchrl.objectives.make_gae`, :func:`~sg_torchrl.objectives.make_cost_gae` and
  :func:`~sg_torchrl.objectives.normalize_advantages` produce the advantages on the whole batch;
  the loss computes them itself (both, SafePO-normalised) when its input lacks them, as TorchRL's
  losses do (:class:`~sg_torchrl.objectives.value.AdvantageEstimation`).

**CPPO-PID** (Stooke et al. 2020, "Responsive Safety in Reinforcement Learning by PID Lagrangian
Methods") is the same loss with the PID multiplier, not a separate class::

    loss = PPOLagLoss(actor, critic, cost_critic, multiplier=PIDLagrangeMultiplier(cost_limit=25.0))

Everything that differs between the two algorithms lives in the multiplier, including how the
advantages are combined (``multiplier.sum_norm`` / ``multiplier.diff_norm``).
"""
from __future__ import annotations

import inspect
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase, TensorDictParams
from tensordict.nn import dispatch, ProbabilisticTensorDictSequential, TensorDictModule
from tensordict.utils import NestedKey
from torch import distributions as D, Tensor
from torchrl.objectives import ClipPPOLoss

from sg_torchrl.objectives.actor_terms import ActorTerms, release_compile_refs
from sg_torchrl.objectives.cost_critic import CostCriticLosses
from sg_torchrl.objectives.kl import kl_to_stored_gaussian
from sg_torchrl.objectives.multipliers import Multiplier
from sg_torchrl.objectives.surrogates import ClipSurrogate, SeedBatchedObjective, Surrogate
from sg_torchrl.objectives.value import AdvantageEstimation

__all__ = ["PPOLagLoss"]


#: The methods that define a first-order loss's math; a subclass overriding one of them must define its own
#: ``seed_batched_objective`` (see :meth:`PPOLagLoss.seed_batched_objective`).
_MATH_HOOKS = ("_surrogate", "_combined_advantage", "_actor_loss", "forward", "critic_losses", "loss_cost_critic",
               "loss_critic")


def _as_key_list(keys: NestedKey | list[NestedKey]) -> list[NestedKey]:
    if isinstance(keys, list):
        return list(keys)
    return [keys]


class PPOLagLoss(ActorTerms, CostCriticLosses, AdvantageEstimation, ClipPPOLoss):
    """PPO-Lagrangian loss: clipped PPO on the Lagrangian advantage, plus reward and cost critics.

    With :math:`r_t(\\theta) = \\pi_\\theta(a_t|s_t) / \\pi_{\\text{old}}(a_t|s_t)` and
    :math:`\\lambda` = ``multiplier.value``, the objective is

    .. math::

        L^{\\text{obj}} = -\\mathbb E\\left[\\min\\big(r_t A_t,\\ \\mathrm{clip}(r_t, 1-\\epsilon, 1+\\epsilon) A_t\\big)\\right],
        \\qquad A_t = \\frac{A^r_t - \\lambda A^c_t}{1 + \\lambda}

    (``multiplier.sum_norm``; :math:`A^r - \\lambda A^c` without it, and
    :math:`(1 - \\lambda) A^r - \\lambda A^c` with ``multiplier.diff_norm``). What the first-order
    variants change is one object, :attr:`surrogate` (what is made of the ratio and the advantage:
    the clipped surrogate here; plain importance weighting in :class:`~sg_torchrl.objectives.PGLoss`,
    the KL-regularised targets of :class:`~sg_torchrl.objectives.FOCOPSLoss` and
    :class:`~sg_torchrl.objectives.CUPLoss`), written once in :mod:`sg_torchrl.objectives.surrogates`
    and trained by the seed-batched engine through :meth:`seed_batched_objective`; the advantage rule
    is the multiplier's. The actor is evaluated once per call
    (:class:`~sg_torchrl.objectives.actor_terms.ActorTerms`: TorchRL's PPO ratio, ratio diagnostics
    and entropy); the reward-critic loss is :class:`~torchrl.objectives.ClipPPOLoss`'s public
    ``loss_critic``.

    Critic losses follow SafePO: mean squared error to the GAE targets plus an L2 penalty
    ``critic_l2_coeff * sum(p ** 2)`` over *all* parameters (weights and biases) of the network
    ("critic norm", coefficient 0.001):

    .. math::

        L^{\\text{critic}} = c_v\\,\\mathrm{MSE}(V, V^{\\text{targ}}) + \\beta \\sum_p \\|p\\|^2,\\qquad
        L^{\\text{cost\\_critic}} = c_c\\,\\mathrm{MSE}(V^c, V^{c,\\text{targ}}) + \\beta \\sum_{p^c} \\|p^c\\|^2 .

    Defaults match SafePO / the Safety-Gymnasium paper: clip 0.2, no entropy bonus, MSE critic
    losses. Advantages are normalised once per batch (SafePO), never inside the loss: use
    :func:`~sg_torchrl.objectives.normalize_advantages` (or :meth:`estimate_advantages`) before the
    minibatch loop; TorchRL's per-minibatch ``normalize_advantage`` / ``advantage_norm`` are refused.

    Advantages follow TorchRL's convention: when the input lacks ``"advantage"`` (or
    ``"cost_advantage"``), the loss computes it and its value target from the input's trajectories
    (a raw ``env.rollout(...)`` can be passed as is); given ones are used as they are
    (:class:`~sg_torchrl.objectives.value.AdvantageEstimation`).

    Args:
        actor_network (ProbabilisticTensorDictSequential): the policy; must write the action
            log-probability when sampling (``return_log_prob=True``). With torchrl 0.14 the
            log-prob key is ``"action_log_prob"``; the loss picks up the actor's own key.
        critic_network (TensorDictModule): reward critic writing ``"state_value"``.
        cost_critic_network (TensorDictModule): cost critic writing ``"cost_value"``. Registered
            functionally like the reward critic, so its parameters are in ``loss.parameters()``.
        multiplier (Multiplier): the Lagrange multiplier whose :attr:`~Multiplier.value` is used.
            Registered as a sub-module (its buffers are in ``loss.state_dict()``; it has no
            parameters, so optimisers over ``loss.parameters()`` never touch it).

    Keyword Args:
        clip_epsilon (float): PPO ratio clip. Defaults to ``0.2``.
        entropy_bonus (bool, optional): add ``loss_entropy``. ``None`` (default) means "only if
            ``entropy_coeff`` is non-zero"; SafePO uses no entropy bonus.
        entropy_coeff (float): entropy weight. Defaults to ``0.0``. (TorchRL's per-head mapping is
            for composite action distributions, which these losses do not take.)
        critic_l2_coeff (float, optional): weight :math:`\\beta` of the squared-parameter penalty
            added to both critic losses. Defaults to ``0.001`` (SafePO). ``None`` disables it.
        cost_critic_coeff (float, optional): weight :math:`c_c` of the cost-critic MSE. ``None``
            (default) uses the reward critic's ``critic_coeff`` (1.0 by default).
        loss_critic_type (str): ``"l2"`` (default, SafePO's MSE), ``"l1"`` or ``"smooth_l1"``;
            used for both critics.
        **kwargs: forwarded to :class:`~torchrl.objectives.ClipPPOLoss` (``critic_coeff``,
            ``clip_value``, ``separate_losses``, ``reduction``, ``delay_actor``, ...).
            ``clip_value`` also clips the cost critic (against the stored ``"cost_value"``).

    Input keys (all configurable with :meth:`set_keys`, see :class:`_AcceptedKeys`, or moved into
    a multi-agent env's group at once with ``loss.set_group("agents")``,
    :meth:`~sg_torchrl.objectives.value.AdvantageEstimation.set_group`):
        the actor's and both critics' ``in_keys`` (e.g. ``"observation"``), ``"action"``,
        ``"action_log_prob"``, ``"advantage"``, ``"value_target"``, ``"cost_advantage"``,
        ``"cost_value_target"``; ``"state_value"`` / ``"cost_value"`` only with ``clip_value``.
        Without the advantages: the ``"next"`` entries their estimators read instead (reward,
        cost, done, terminated, the critics' inputs); ``in_keys`` lists the minibatch inputs.

    Output keys:
        ``loss_objective``, ``loss_critic``, ``loss_cost_critic`` (and ``loss_entropy`` with an
        entropy bonus) are the terms to sum. Detached diagnostics: ``lagrange_multiplier``,
        ``clip_fraction``, ``kl_approx``, ``ESS``, ``max_ratio``, ``mean_ratio``,
        ``explained_variance`` and ``cost_explained_variance`` (with ``log_explained_variance``),
        ``entropy`` (with an entropy bonus), ``value_clip_fraction`` and
        ``cost_value_clip_fraction`` (with ``clip_value``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
        >>> from torchrl.modules import MLP, IndependentNormal, ProbabilisticActor, ValueOperator
        >>> from sg_torchrl.objectives import LagrangeMultiplier, PPOLagLoss
        >>> actor = ProbabilisticActor(
        ...     TensorDictModule(
        ...         torch.nn.Sequential(MLP(in_features=5, out_features=2, num_cells=[8]),
        ...                             AddStateIndependentNormalScale(2)),
        ...         in_keys=["observation"], out_keys=["loc", "scale"]),
        ...     in_keys=["loc", "scale"], distribution_class=IndependentNormal, return_log_prob=True)
        >>> critic = ValueOperator(MLP(in_features=5, out_features=1, num_cells=[8]),
        ...                        in_keys=["observation"])
        >>> cost_critic = ValueOperator(MLP(in_features=5, out_features=1, num_cells=[8]),
        ...                             in_keys=["observation"], out_keys=["cost_value"])
        >>> loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(cost_limit=25.0))
        >>> data = actor(TensorDict(observation=torch.randn(16, 5), batch_size=[16])).detach()
        >>> _ = data.update({k: torch.randn(16, 1) for k in
        ...     ("advantage", "value_target", "cost_advantage", "cost_value_target")})
        >>> out = loss(data)
        >>> total = sum(v for k, v in out.items() if k.startswith("loss_"))
        >>> total.backward()
    """

    @dataclass
    class _AcceptedKeys(ClipPPOLoss._AcceptedKeys):
        """Configurable tensordict keys: :class:`~torchrl.objectives.PPOLoss`'s plus the cost ones.

        Attributes:
            cost (NestedKey): the per-step cost signal, under ``"next"``; read by the cost value
                estimator only (:attr:`cost_value_estimator`). Defaults to ``"cost"``.
            cost_value (NestedKey): output key of the cost critic (and the stored rollout cost
                value used for value clipping). Defaults to ``"cost_value"``.
            cost_advantage (NestedKey): the cost advantage :math:`A^c` (input). Defaults to
                ``"cost_advantage"``.
            cost_value_target (NestedKey): the cost critic's regression target (input). Defaults
                to ``"cost_value_target"``.
        """

        cost: NestedKey = "cost"
        cost_value: NestedKey = "cost_value"
        cost_advantage: NestedKey = "cost_advantage"
        cost_value_target: NestedKey = "cost_value_target"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    _schedulable_buffers = frozenset({"critic_l2_coeff", "cost_critic_coeff"})

    cost_critic_network: TensorDictModule
    cost_critic_network_params: TensorDictParams
    target_cost_critic_network_params: TensorDictParams
    multiplier: Multiplier
    critic_l2_coeff: Tensor | None
    cost_critic_coeff: Tensor

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        critic_network: TensorDictModule,
        cost_critic_network: TensorDictModule,
        multiplier: Multiplier,
        *,
        clip_epsilon: float = 0.2,
        entropy_bonus: bool | None = None,
        entropy_coeff: float | Mapping[NestedKey, float] = 0.0,
        critic_l2_coeff: float | None = 0.001,
        cost_critic_coeff: float | None = None,
        loss_critic_type: str = "l2",
        **kwargs: Any,
    ) -> None:
        if not isinstance(multiplier, Multiplier):
            raise TypeError(
                f"multiplier must be a sg_torchrl Multiplier (LagrangeMultiplier, "
                f"PIDLagrangeMultiplier, ...), got {type(multiplier).__name__}."
            )
        if cost_critic_network is None:
            raise TypeError("PPOLagLoss needs a cost_critic_network.")
        if critic_network is None:
            raise TypeError("PPOLagLoss needs a critic_network.")
        if isinstance(entropy_coeff, Mapping):
            raise TypeError("entropy_coeff must be a float: per-head coefficients are for composite action "
                            "distributions, which PPOLagLoss does not take.")
        if entropy_bonus is None:
            entropy_bonus = float(entropy_coeff) != 0.0
        super().__init__(
            actor_network,
            critic_network,
            clip_epsilon=clip_epsilon,
            entropy_bonus=entropy_bonus,
            entropy_coeff=entropy_coeff,
            loss_critic_type=loss_critic_type,
            **kwargs,
        )
        if self.normalize_advantage or self.advantage_norm is not None:
            raise ValueError(
                "PPOLagLoss does not normalise advantages per minibatch (normalize_advantage / advantage_norm): "
                "SafePO normalises them once per batch, with normalize_advantages or loss.estimate_advantages."
            )
        # Fixed at construction, as TorchRL's losses do: whether the reward critic is trained, and the clip's form.
        self._trains_reward_critic = self.critic_coeff is not None and bool(self.critic_coeff > 0)
        self._asymmetric_clip_epsilon = isinstance(clip_epsilon, (tuple, list))
        device = next(iter(self.buffers()), torch.empty(())).device
        if self.functional:
            # Same treatment as the reward critic in PPOLoss: with separate_losses, parameters
            # shared with the actor are kept out of the critic's gradient path.
            policy_params = list(actor_network.parameters()) if self.separate_losses else None
            self.convert_to_functional(
                cost_critic_network, "cost_critic_network", compare_against=policy_params
            )
        else:
            self.cost_critic_network = cost_critic_network
            self.cost_critic_network_params = None
            self.target_cost_critic_network_params = None
        self.multiplier = multiplier
        self.register_coeff_buffer("critic_l2_coeff", critic_l2_coeff, device=device)
        if cost_critic_coeff is None:
            cost_critic_coeff = float(self.critic_coeff) if self.critic_coeff is not None else 1.0
        self.register_coeff_buffer("cost_critic_coeff", cost_critic_coeff, device=device)
        self._cost_value_estimator = None  # built on first use, with the reward one
        # in_keys were cached by the parent before the cost critic existed.
        self.in_keys = None

    # ------------------------------------------------------------------ keys
    def _set_in_keys(self) -> None:
        # The parent lists the value-estimation inputs ("next" reward, done, observation); here
        # in_keys are what a minibatch needs (the trainer selects them): the networks' inputs and
        # the entries below; the estimators' inputs are only read when advantages are missing.
        # Called by the parent constructor before the cost critic is registered.
        keys: list[NestedKey] = []
        for name in ("actor_network", "critic_network", "cost_critic_network"):
            module = getattr(self, name, None)
            if module is not None:
                keys.extend(module.in_keys)
        names = ["action", "sample_log_prob", "advantage", "value_target"]
        names += ["cost_advantage", "cost_value_target"]
        if getattr(self, "clip_value", None) is not None:
            names += ["value", "cost_value"]
        for name in names:
            keys.extend(_as_key_list(getattr(self.tensor_keys, name)))
        self.in_keys = list(dict.fromkeys(keys))

    _output_keys: list[NestedKey] | None = None

    @property
    def out_keys(self) -> list[NestedKey]:
        """ClipPPOLoss's output keys (its ``clip_fraction`` is the surrogate's), the surrogate's and the cost ones."""
        if self._output_keys is None:
            clip_value = self.clip_value is not None
            keys = ["loss_objective", *(["entropy", "loss_entropy"] if self.entropy_bonus else []), "loss_critic",
                    *(["value_clip_fraction"] if clip_value else []), "ESS", "kl_approx", "max_ratio", "mean_ratio",
                    *self.surrogate.diagnostic_names, "loss_cost_critic", "lagrange_multiplier",
                    *(["cost_value_clip_fraction"] if clip_value else [])]
            self._output_keys = keys
        return self._output_keys

    @out_keys.setter
    def out_keys(self, values: list[NestedKey]) -> None:
        self._output_keys = values

    # ------------------------------------------------------------------ hook
    def _combined_advantage(self, tensordict: TensorDictBase) -> Tensor:
        """The advantage fed to the clipped surrogate: the multiplier's Lagrangian mix of :math:`A^r` and
        :math:`A^c` (:meth:`~sg_torchrl.objectives.Multiplier.combine`, no gradient into the multiplier).

        Args:
            tensordict (TensorDictBase): the input batch, holding ``tensor_keys.advantage`` and
                ``tensor_keys.cost_advantage`` (same shape, typically ``[*B, 1]``).

        Returns:
            The combined advantage, same shape and dtype as the reward advantage.

        Raises:
            KeyError: if an advantage is missing.
            ValueError: if the two advantages have different shapes.
        """
        adv = self._get_required(tensordict, self.tensor_keys.advantage, "make_gae(critic)")
        cost_adv = self._get_required(
            tensordict, self.tensor_keys.cost_advantage, "make_cost_gae(cost_critic)"
        )
        return self.multiplier.combine(adv, cost_adv)

    @staticmethod
    def _get_required(tensordict: TensorDictBase, key: NestedKey, producer: str) -> Tensor:
        value = tensordict.get(key, None)
        if value is None:
            raise KeyError(
                f"PPOLagLoss did not find {key!r} in the input: compute it on the whole batch first "
                f"(e.g. with {producer}, or loss.estimate_advantages), or remap the key with "
                f"loss.set_keys(...)."
            )
        return value

    # --------------------------------------------------------------- policy
    @property
    def surrogate(self) -> Surrogate:
        """The policy objective (:mod:`sg_torchrl.objectives.surrogates`): PPO's clipped surrogate here.

        The one definition of the algorithm's per-sample math: :meth:`_surrogate` evaluates it on this
        loss's batch and the seed-batched engine on S stacked seeds (:meth:`seed_batched_objective`).
        Subclasses return their own (``PGLoss``, ``FOCOPSLoss``, ``CUPLoss``); a new first-order
        algorithm is a new :class:`~sg_torchrl.objectives.surrogates.Surrogate` returned here.
        """
        if self._asymmetric_clip_epsilon:
            return ClipSurrogate(float(self.clip_epsilon_low), float(self.clip_epsilon_high))
        return ClipSurrogate(float(self.clip_epsilon))

    def _surrogate(
        self,
        log_weight: Tensor,
        advantage: Tensor,
        dist: D.Distribution,
        tensordict: TensorDictBase,
        *,
        log_is_weight: Tensor | None = None,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """The per-sample policy loss (the negated surrogate) and its detached diagnostics.

        Evaluates :attr:`surrogate` on the batch: the KL to the stored policy it names (if any) is
        taken in closed form from ``dist``, and :math:`\\lambda` is the multiplier's value.

        Args:
            log_weight (Tensor): :math:`\\log \\pi_\\theta(a|s) - \\log \\pi_{\\text{prox}}(a|s)`,
                shape ``[*B, 1]``, differentiable. Without torchrl's ``delay_actor`` /
                ``max_importance_ratio`` options the proximal policy is the behaviour policy whose
                log-prob is stored under ``tensor_keys.sample_log_prob``.
            advantage (Tensor): the advantage the policy optimises, same shape as ``log_weight``.
            dist (Distribution): the current policy at the batch's observations (differentiable).
            tensordict (TensorDictBase): the input batch as given to ``forward`` (stored entries,
                e.g. the rollout ``loc`` / ``scale``, keep their stored values).

        Keyword Args:
            log_is_weight (Tensor, optional): :math:`\\log \\pi_{\\text{prox}} - \\log
                \\pi_{\\text{behav}}` (torchrl's importance correction), ``None`` when the proximal
                policy is the behaviour policy.

        Returns:
            ``(loss, diagnostics)``: the unreduced loss, shape ``[*B, 1]``, and a dict of detached
            scalars keyed by the surrogate's ``diagnostic_names``.
        """
        surrogate = self.surrogate
        kl = None
        if surrogate.reference is not None:
            loc_key, scale_key = self._reference_keys(surrogate.reference)
            kl = kl_to_stored_gaussian(dist, tensordict, loc_key, scale_key)
        loss = surrogate.loss(log_weight, advantage, cost_advantage=tensordict.get(self.tensor_keys.cost_advantage, None),
                              kl=kl, lam=self.multiplier.value, log_is_weight=log_is_weight)
        return loss, surrogate.diagnostics(log_weight, kl=kl)

    def _policy_advantage(self, tensordict: TensorDictBase) -> Tensor:
        """The advantage :attr:`surrogate` optimises: the combined one, or :math:`A_r` / :math:`A_c` itself."""
        kind = self.surrogate.advantage
        if kind == "combined":
            return self._combined_advantage(tensordict)
        key, producer = ((self.tensor_keys.advantage, "make_gae(critic)") if kind == "reward"
                         else (self.tensor_keys.cost_advantage, "make_cost_gae(cost_critic)"))
        return self._get_required(tensordict, key, producer)

    def _reference_keys(self, reference: str) -> tuple[NestedKey, NestedKey]:
        """The batch keys of the stored policy a surrogate's KL goes to (``"rollout"`` or ``"stage1"``)."""
        names = {"rollout": ("old_loc", "old_scale"), "stage1": ("stage1_loc", "stage1_scale")}[reference]
        try:
            return tuple(getattr(self.tensor_keys, name) for name in names)
        except AttributeError:
            raise TypeError(
                f"{type(self).__name__}'s surrogate reads the {reference!r} policy, but its tensor_keys have no "
                f"{names[0]!r} / {names[1]!r}: declare them in its _AcceptedKeys"
            ) from None

    # --------------------------------------------------------------- the engine's form
    def seed_batched_objective(self, *, critics_only: bool = False) -> SeedBatchedObjective:
        """This loss in the form the seed-batched engine trains (S seeds, one pass): the public protocol.

        The engine never builds an objective from an algorithm's name: it asks the loss object.
        The objective holds this loss's :attr:`surrogate`, the multiplier's advantage rule and the
        critics' L2 weight, so seed ``s`` of the engine's step is this loss's step on seed ``s``.
        With ``critics_only``, the critics' regression alone (what the second-order updates train
        the critics with, :meth:`critic_losses`).

        Raises:
            TypeError: if a subclass overrides the math (``_surrogate``, ``_combined_advantage``,
                ``forward``, ...) without defining its own ``seed_batched_objective``: the engine
                would train another algorithm than the one the class defines.
            ValueError: for options the seed-batched form does not implement (entropy bonus,
                value clipping, non-MSE critics, critic
                coefficients other than 1, ``delay_actor`` / ``max_importance_ratio``).
        """
        overrides = self._unbatched_overrides()
        if overrides:
            raise TypeError(
                f"{type(self).__name__} overrides {', '.join(overrides)} but not seed_batched_objective(): the "
                f"seed-batched engine cannot train it as defined. Give the loss a Surrogate (the 'surrogate' "
                f"property) instead of overriding the hooks, or define seed_batched_objective()."
            )
        self.refuse_unbatched_options("the seed-batched engine", entropy_bonus=bool(self.entropy_bonus))
        l2 = 0.0 if self.critic_l2_coeff is None else float(self.critic_l2_coeff)
        surrogate = None if critics_only else self.surrogate
        return SeedBatchedObjective(surrogate, combine=self.multiplier.combine_rule, critic_l2=l2)

    def refuse_unbatched_options(self, engine: str, **more: bool) -> None:
        """Raise ``ValueError`` naming the options used here that ``engine``'s form lacks (``more``: name -> used)."""
        unsupported = {
            **more,
            "clip_value": self.clip_value is not None,
            "loss_critic_type != 'l2'": self.loss_critic_type != "l2",
            "critic_coeff != 1": self.critic_coeff is not None and float(self.critic_coeff) != 1.0,
            "cost_critic_coeff != 1": float(self.cost_critic_coeff) != 1.0,
            "delay_actor / max_importance_ratio": bool(self.delay_actor) or self.max_importance_ratio is not None,
        }
        used = [name for name, present in unsupported.items() if present]
        if used:
            raise ValueError(f"{engine} does not implement: {', '.join(used)}")

    def _unbatched_overrides(self) -> list[str]:
        """The math hooks this object's class redefines below the class that defines ``seed_batched_objective``.

        Compared through ``inspect.unwrap``: TorchRL's loss metaclass re-wraps ``forward`` in every
        subclass, so a wrapper alone is no redefinition.
        """
        cls = type(self)
        owner = next(klass for klass in cls.__mro__ if "seed_batched_objective" in vars(klass))
        return [f"{cls.__name__}.{name}" for name in _MATH_HOOKS
                if inspect.unwrap(getattr(cls, name)) is not inspect.unwrap(getattr(owner, name))]

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes the losses on a batch (see the class docstring for keys); the critics' only when the surrogate
        trains them (not CUP's projection, which needs no reward advantage either)."""
        trains_critics = self.surrogate.trains_critics
        reward = trains_critics or self.surrogate.advantage != "cost"
        tensordict = self._with_advantages(tensordict, reward=reward)  # computed if missing
        td_out = self._actor_loss(tensordict, self._policy_advantage(tensordict))
        td_out = self._reduce_losses(td_out, tensordict)
        if trains_critics:
            td_out.update(self.critic_losses(tensordict))
        ref = td_out.get("loss_objective")
        td_out.set(
            "lagrange_multiplier",
            self.multiplier.value.to(device=ref.device, dtype=ref.dtype),
        )
        release_compile_refs(tensordict, td_out, self.actor_network_params,
                             self.target_actor_network_params if self.delay_actor else None)
        return td_out
