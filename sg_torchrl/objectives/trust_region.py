"""Trust-region policy steps: NPG / RCPO, TRPO / TRPO-Lag, CPO and PCPO.

Second-order methods do not minimise a loss with an optimiser. Once per epoch they linearise the
objective (and the cost) around the current policy :math:`\\theta_k`, model the KL divergence to
it by its quadratic form :math:`\\tfrac12 d^\\top H d` (:math:`H` the Fisher information matrix)
and move the actor's parameters directly:

.. math::

    \\max_d\\; g^\\top d \\quad \\text{s.t.} \\quad \\tfrac12 d^\\top H d \\le \\delta
    \\;\\;[\\text{and } c + b^\\top d \\le 0 \\text{ for CPO / PCPO}],

with :math:`g` and :math:`b` the gradients of the reward and cost surrogates
:math:`\\mathbb E[r_\\theta A]`, :math:`\\mathbb E[r_\\theta A^c]`
(:math:`r_\\theta = \\pi_\\theta(a|s) / \\pi_{\\text{behaviour}}(a|s)`) and
:math:`c = J_c - d` the constraint violation.

This module is the one-actor front of the package's single trust-region implementation
(:mod:`sg_torchrl.objectives.stacked_trust_region`): :class:`TrustRegionLoss`, a TorchRL
:class:`~torchrl.objectives.LossModule` giving the two surrogates and the mean KL of a TorchRL actor by
the steps' own evaluation, and the steps of one actor, :class:`NaturalPolicyStep`
(Kakade 2002), :class:`TRPOStep` (Schulman et al. 2015), :class:`CPOStep` (Achiam et al. 2017) and
:class:`PCPOStep` (Yang et al. 2020). Each is a rule of :mod:`sg_torchrl.objectives.step_rules` (home of
:func:`cpo_direction` and :func:`pcpo_direction`, unit-tested against an independent QP solver) over
the seed-group step with S = 1 (:class:`OneSeedActor`), so a single actor and a seed group move by the
same code (:data:`STACKED_STEPS` names the group class of each).

Lagrangian variants are not separate classes: TRPO-Lag is :class:`TRPOStep` fed the Lagrangian
advantage :math:`(A_r - \\lambda A_c)/(1 + \\lambda)` (``multiplier.combine``), and RCPO as SafePO
implements it (an NPG-Lagrangian, not Tessler et al.'s reward shaping) is :class:`NaturalPolicyStep`
fed the same. Defaults are the Safety-Gymnasium paper's (Ji et al. 2023): :math:`\\delta = 0.01`,
15 conjugate-gradient iterations, damping 0.1, 15 backtracking steps of 0.8 (PCPO 200).

**KL convention.** As in SafePO, the KL that defines :math:`H`, is checked by the line search and
is logged as ``Train/KL`` is averaged over samples *and action dimensions*
(``kl_action_reduction="mean"``). The TRPO / CPO papers use the KL of the joint action
distribution (summed over dimensions, ``"sum"``), for which the same :math:`\\delta` is a trust
region ``action_dim`` times tighter. We keep SafePO's convention by default because the paper's
:math:`\\delta = 0.01` was tuned with it.

**Where we follow the papers instead of SafePO** (SafePO's behaviour marked **[quirk]**):

* CPO's dual (cases 1, 2): SafePO applies the paper's loss-convention formulas to the ascent
  gradient, flipping the sign of :math:`r`, and projects onto empty intervals when
  :math:`r/c \\le 0`; its direction then is not the QP's solution. We solve the QP
  (:func:`cpo_direction`; ``safepo_dual=True`` reproduces SafePO).
* PCPO's reward step uses :math:`H^{-1} g` (Yang et al. 2020), not SafePO's :math:`H (H^{-1} g)`
  (``use_hx_direction=True`` reproduces SafePO).
* Line search: a candidate with a non-finite surrogate or KL is rejected and the step shrinks
  (SafePO retries the same fraction after a non-finite KL, and accepts non-finite surrogates).
* ``Loss/Loss_actor`` is minus the reward surrogate before the step for every method (SafePO logs
  the last line-search trial's loss for TRPO and reward + cost losses for CPO / PCPO).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from tensordict import TensorDict, TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.objectives import LossModule

from sg_torchrl.objectives.kl import diagonal_gaussian_params
from sg_torchrl.objectives.second_order import flat_params, set_flat_params
from sg_torchrl.objectives.stacked_trust_region import (
    SeedSurrogates,
    StackedCPOStep,
    StackedNaturalPolicyStep,
    StackedPCPOStep,
    StackedTRPOStep,
    StackedTrustRegionStep,
    _per_sample,  # value reshaped to the per-sample shape, refusing silent broadcasting
)
from sg_torchrl.objectives.step_rules import (  # the directions are re-exported (sg_torchrl.objectives)
    CPODirection,
    CPORule,
    NaturalRule,
    PCPORule,
    TRPORule,
    cpo_direction,
    pcpo_direction,
)

__all__ = [
    "STACKED_STEPS",
    "CPODirection",
    "CPOStep",
    "NaturalPolicyStep",
    "OneSeedActor",
    "PCPOStep",
    "TRPOStep",
    "TrustRegionLoss",
    "TrustRegionStep",
    "cpo_direction",
    "pcpo_direction",
]



def _log_prob_key(actor: ProbabilisticTensorDictSequential) -> NestedKey:
    """Where the collector stored the behaviour log-prob: the actor's ``log_prob_key``, else ``"action_log_prob"``."""
    key = getattr(actor, "log_prob_key", None)
    return key if isinstance(key, (str, tuple)) else "action_log_prob"


def _one_seed_rows(value: Tensor, shape: tuple[int, ...], name: str) -> Tensor:
    """A per-sample ``value`` (``shape`` or ``shape + (1,)``, checked) as one seed's ``(1, N)`` rows."""
    return _per_sample(value, shape, name).reshape(1, -1)


# ============================================================================ loss module
class TrustRegionLoss(LossModule):
    """Reward / cost surrogates and the mean KL of a Gaussian policy, for trust-region steps.

    With :math:`r_\\theta = \\exp(\\log\\pi_\\theta(a|s) - \\log\\pi_{\\text{behaviour}}(a|s))`
    (the behaviour log-prob is the collector's ``"action_log_prob"``):

    * ``loss_objective`` :math:`= -\\mathbb E[r_\\theta A]` (minus the reward surrogate of TRPO,
      Schulman et al. 2015, eq. 14; ``A`` may be a Lagrangian advantage);
    * ``loss_cost`` :math:`= \\mathbb E[r_\\theta A^c]`, the cost surrogate of CPO (Achiam et al.
      2017), only when the cost advantage is in the input;
    * ``kl`` :math:`= \\mathbb E_s[\\mathrm{KL}(\\pi_{\\text{old}}(\\cdot|s) \\,\\|\\, \\pi_\\theta(\\cdot|s))]`,
      with :math:`\\pi_{\\text{old}}` read from the input's ``"loc"`` / ``"scale"``; per sample
      averaged over action dimensions (``kl_action_reduction="mean"``, SafePO) or summed
      (``"sum"``, the joint-distribution KL of the papers).

    All three come from one forward pass of the actor and keep their graphs, so a step can
    differentiate them (gradients, Fisher-vector products) or evaluate them under
    :func:`torch.no_grad` during a line search. The actor is held as a plain sub-module (not
    functionalised): trust-region steps write its parameters in place.

    Args:
        actor_network (ProbabilisticTensorDictSequential): diagonal-Gaussian policy (e.g. a
            :class:`~torchrl.modules.ProbabilisticActor` with
            :class:`~torchrl.modules.IndependentNormal`); its distribution's ``mean`` / ``stddev``
            are the new ``loc`` / ``scale``.

    Keyword Args:
        kl_action_reduction (str): ``"mean"`` (default, SafePO) or ``"sum"`` over action dims.

    Input keys (configurable with :meth:`set_keys`): the actor's ``in_keys``, ``"action"``,
    ``"action_log_prob"`` (the actor's own ``log_prob_key`` when it has one), ``"advantage"``,
    optionally ``"cost_advantage"``, and the old policy's ``"loc"`` / ``"scale"``. Advantages may be
    ``[*B]`` or ``[*B, 1]``. The loss holds no critic, so it cannot compute a missing advantage
    (TorchRL's convention for losses with a critic): a missing ``"advantage"`` raises a ``KeyError``
    that says how to compute it.
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable input keys of :class:`TrustRegionLoss`."""

        advantage: NestedKey = "advantage"
        cost_advantage: NestedKey = "cost_advantage"
        action: NestedKey = "action"
        sample_log_prob: NestedKey = "action_log_prob"
        loc: NestedKey = "loc"
        scale: NestedKey = "scale"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    actor_network: ProbabilisticTensorDictSequential

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        *,
        kl_action_reduction: Literal["mean", "sum"] = "mean",
    ) -> None:
        if kl_action_reduction not in ("mean", "sum"):
            raise ValueError(f"kl_action_reduction must be 'mean' or 'sum', got {kl_action_reduction!r}.")
        super().__init__()
        self.actor_network = actor_network
        self.kl_action_reduction = kl_action_reduction
        log_prob_key = _log_prob_key(actor_network)
        if log_prob_key != self.tensor_keys.sample_log_prob:
            self.set_keys(sample_log_prob=log_prob_key)
        self._set_in_keys()
        self.out_keys = ["loss_objective", "loss_cost", "kl"]

    @property
    def functional(self) -> bool:
        return False

    def _set_in_keys(self) -> None:
        # LossModule's default _forward_value_estimator_keys calls it after set_keys (no estimator here).
        tk = self.tensor_keys
        keys = [*self.actor_network.in_keys, tk.action, tk.sample_log_prob, tk.advantage,
                tk.cost_advantage, tk.loc, tk.scale]
        self.in_keys = list(dict.fromkeys(keys))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes ``loss_objective``, ``loss_cost`` (if the cost advantage is given) and ``kl``."""
        tk = self.tensor_keys
        dist = self.actor_network.get_dist(tensordict.select(*self.actor_network.in_keys))
        loc, scale = diagonal_gaussian_params(dist, "A trust-region step")
        advantage = tensordict.get(tk.advantage, None)
        if advantage is None:
            raise KeyError(
                f"TrustRegionLoss did not find {tk.advantage!r} in the input. It has no critics, so "
                f"unlike the first-order losses it cannot compute advantages: compute them on the "
                f"whole batch first (PPOLagLoss.estimate_advantages, or make_gae / make_cost_gae and "
                f"normalize_advantages), or remap the key with loss.set_keys(...)."
            )
        # the trust-region step's own evaluation (one seed, the samples flattened)
        shape = loc.shape[:-1]

        def per_action(value: Tensor) -> Tensor:
            return value.expand_as(loc).reshape(1, shape.numel(), loc.shape[-1])

        cost_advantage = tensordict.get(tk.cost_advantage, None)
        surrogates = SeedSurrogates(
            None, per_action(tensordict.get(tk.action)),
            _one_seed_rows(tensordict.get(tk.sample_log_prob), shape, "action_log_prob"),
            _one_seed_rows(advantage, shape, "advantage"),
            None if cost_advantage is None else _one_seed_rows(cost_advantage, shape, "cost_advantage"),
            per_action(tensordict.get(tk.loc)), per_action(tensordict.get(tk.scale)), self.kl_action_reduction,
        )
        reward, cost, kl = surrogates.evaluate(per_action(loc), per_action(scale))
        out = {"loss_objective": -reward[0]}
        if cost_advantage is not None:
            out["loss_cost"] = cost[0]
        out["kl"] = kl[0]
        return TensorDict(out, batch_size=[])


# ============================================================================ one actor as one seed
class OneSeedActor:
    """One TorchRL Gaussian actor seen as a one-seed :class:`~sg_torchrl.objectives.stacked_trust_region.StackedActor`.

    The trust-region step moves rows of a flat ``(S, P)`` buffer and evaluates the policy through
    ``dist_params``. For a single actor this view holds a ``(1, P)`` copy of its trainable parameters
    (in :func:`~sg_torchrl.objectives.second_order.flat_params` order) and writes it into them before
    every evaluation, so gradients, Fisher-vector products and line-search candidates are the actor's
    own, whatever its network (MLP, CNN, a multi-agent policy's agent): the actor's parameter objects
    are never replaced, so optimisers and modules sharing them keep working. :meth:`load` copies
    the actor in (before a step), :meth:`store` writes the row back (after one).

    Args:
        actor: a policy whose ``get_dist`` is a diagonal Gaussian; observations are TensorDicts of
            its ``in_keys`` with batch ``[1, N]``.
    """

    num_seeds = 1

    def __init__(self, actor: ProbabilisticTensorDictSequential) -> None:
        self.actor = actor
        self.params = [p for p in actor.parameters() if p.requires_grad]
        self.load()

    def load(self) -> None:
        """Take the actor's current parameters as the row."""
        self.flat_actor = flat_params(self.params).unsqueeze(0)

    def store(self) -> None:
        """Write the row into the actor's parameters."""
        set_flat_params(self.params, self.flat_actor[0])

    def actor_parameters(self) -> list[Tensor]:
        return self.params

    def dist_params(self, obs: TensorDictBase) -> tuple[Tensor, Tensor]:
        """``(loc, scale)`` of the policy with the row's parameters, ``(1, N, A)`` each."""
        self.store()
        loc, scale = diagonal_gaussian_params(self.actor.get_dist(obs[0]), "A trust-region step")
        return loc.unsqueeze(0), scale.unsqueeze(0)

    def actor_rows(self, rows: Tensor) -> OneSeedActor:
        if rows.tolist() != [0]:
            raise IndexError(f"a one-seed actor has row 0 only, asked for {rows.tolist()}.")
        return self


class TrustRegionStep(StackedTrustRegionStep):
    """The trust-region step of one TorchRL actor: the seed-group step with S = 1.

    :meth:`step` (called by the trainer once per epoch on the whole flattened batch) puts the actor
    into a one-seed view (:class:`OneSeedActor`) and runs
    :meth:`~sg_torchrl.objectives.stacked_trust_region.StackedTrustRegionStep.step` on the batch as one
    seed's ``(1, N)`` rows: :math:`\\pi_{\\text{old}}` anchored at the actor as it is (for on-policy data the
    behaviour policy the collector stored; it keeps :math:`H` exactly the Fisher matrix at
    :math:`\\theta_k`), then the subclass's proposal (:meth:`_propose`) applied directly
    (``line_search_steps=0``) or backtracked; if no candidate passes the actor is left unchanged.

    Args:
        actor (ProbabilisticTensorDictSequential): the diagonal-Gaussian policy (e.g. with
            :class:`~torchrl.modules.IndependentNormal`); its parameters are changed in place.

    Keyword Args:
        **options: :class:`~sg_torchrl.objectives.step_rules.TrustRegionOptions` (see the module docstring).

    Returned metrics: those of :class:`~sg_torchrl.objectives.stacked_trust_region.TrustRegionEngine`
    as Python floats.
    """

    def __init__(self, actor: ProbabilisticTensorDictSequential, **options) -> None:
        super().__init__(OneSeedActor(actor), **options)
        self.action_key: NestedKey = "action"
        self.log_prob_key: NestedKey = _log_prob_key(actor)

    def step(self, data: TensorDictBase, advantage: Tensor, cost_advantage: Tensor | None,
             cost_violation: float) -> dict[str, float]:
        """One trust-region update of the actor on the whole batch.

        Args:
            data (TensorDictBase): batch ``[*B]`` with the actor's ``in_keys``, ``"action"`` and
                ``"action_log_prob"`` (behaviour log-prob; the actor's own ``log_prob_key`` when it
                has one). It is not modified.
            advantage (Tensor): the (Lagrangian, normalised) reward advantage ``[*B]`` or ``[*B, 1]``.
            cost_advantage (Tensor): the mean-centred cost advantage (same shape), or ``None`` for
                NPG / TRPO.
            cost_violation (float): :math:`c = J_c - d` (unused by NPG / TRPO).

        Returns:
            The metrics listed in the class docstring, as Python floats.
        """
        model, shape = self.model, data.batch_size
        model.load()
        rows = (1, data.numel())
        action = data.get(self.action_key)

        def per_sample(value: Tensor, name: str) -> Tensor:
            return _one_seed_rows(value.detach(), shape, name)

        batch = {"observation": data.select(*model.actor.in_keys).reshape(rows),
                 "action": action.reshape(*rows, *action.shape[len(shape):]),
                 "action_log_prob": per_sample(data.get(self.log_prob_key), "action_log_prob")}
        try:
            metrics = super().step(batch, per_sample(advantage, "advantage"),
                                   None if cost_advantage is None else per_sample(cost_advantage, "cost_advantage"),
                                   [float(cost_violation)])
        finally:
            model.store()
        return {name: float(value[0]) for name, value in metrics.items()}


class NaturalPolicyStep(NaturalRule, TrustRegionStep):
    """Natural policy gradient step :math:`\\theta \\leftarrow \\theta + \\sqrt{2\\delta/x^\\top Hx}\\; x`.

    Kakade 2002, "A Natural Policy Gradient", with the step length that puts the quadratic KL model
    on the trust-region boundary; no line search (``line_search_steps=0``). Fed the Lagrangian
    advantage this is SafePO's RCPO. ``Misc/AcceptanceStep`` is 1 (the step is always taken).
    """


class TRPOStep(TRPORule, NaturalPolicyStep):
    """TRPO (Schulman et al. 2015): the natural step, backtracked until it improves and stays in the region.

    Up to ``line_search_steps`` (15) trials of :math:`0.8^k` of the natural step; a trial is accepted
    when the surrogate did not decrease and :math:`\\mathrm{KL} \\le \\delta`; otherwise no update.
    Fed the Lagrangian advantage this is TRPO-Lag.
    """


class CPOStep(CPORule, TrustRegionStep):
    """Constrained Policy Optimization (Achiam et al. 2017): the step of :func:`cpo_direction`, backtracked.

    Up to ``line_search_steps`` (15) trials of :math:`0.8^k` of the direction, accepted when the KL is
    finite and :math:`\\le \\delta`, the cost surrogate grew by at most :math:`\\max(-c, 0)` and, in
    cases 2-4 (feasible policy), the reward surrogate did not decrease; otherwise no update.
    Extra metrics: ``Misc/cost_gradient_norm``, ``Misc/CPOCase``, ``Misc/Lambda_star``,
    ``Misc/Nu_star``.

    The direction solves the paper's QP; SafePO's dual has the sign of :math:`r` flipped
    **[quirk]** (see :func:`~sg_torchrl.objectives.step_rules._cpo_lambda`), available for comparison
    with ``safepo_dual=True``.

    Keyword Args:
        safepo_dual (bool): see :func:`cpo_direction`. Defaults to ``False``.
        **kwargs: see :class:`TrustRegionStep`.
    """


class PCPOStep(PCPORule, TrustRegionStep):
    """Projection-based CPO (Yang et al. 2020): :func:`pcpo_direction`, backtracked.

    Up to ``line_search_steps`` (200) trials of :math:`0.8^k`, with CPO's acceptance tests minus the
    reward-improvement test (SafePO fixes the CPO case to 0 for PCPO).

    Keyword Args:
        use_hx_direction (bool): ``False`` (default) uses the paper's reward step
            :math:`\\sqrt{2\\delta/q}\\, H^{-1} g`; ``True`` reproduces SafePO's **[quirk]** of
            stepping along :math:`Hx \\approx g` instead.
        **kwargs: see :class:`TrustRegionStep`.
    """


#: The seed-group step of each one-actor step class (what an algorithm row names, e.g. ``TRPOStep``).
STACKED_STEPS: dict[type[TrustRegionStep], type[StackedTrustRegionStep]] = {
    NaturalPolicyStep: StackedNaturalPolicyStep,
    TRPOStep: StackedTRPOStep,
    CPOStep: StackedCPOStep,
    PCPOStep: StackedPCPOStep,
}
