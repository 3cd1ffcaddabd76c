"""Safe-RL objectives: Lagrange multipliers, cost value estimation and Lagrangian PPO losses.

* :class:`Multiplier`, :class:`LagrangeMultiplier`, :class:`PIDLagrangeMultiplier`: the
  multiplier update rules (Adam projected ascent, Ray et al. 2019; PID, Stooke et al. 2020).
* :func:`make_gae`, :func:`make_cost_gae`, :func:`normalize_advantages`: reward and cost GAE side by
  side and SafePO's batch normalisation; :class:`AdvantageEstimation`, the same inside the
  first-order losses, which compute missing advantages themselves (TorchRL's convention).
* :class:`PPOLagLoss`: PPO-Lag; CPPO-PID is ``PPOLagLoss(..., multiplier=PIDLagrangeMultiplier())``
  and PPO is ``PPOLagLoss(..., multiplier=NoMultiplier())``.
* :class:`PGLoss`, :class:`FOCOPSLoss`, :class:`CUPLoss`: the other first-order SafePO losses;
  :class:`PessimisticPPOLagLoss`, PPO-Lag with a pessimistic cost clip (beyond the paper). Their math is
  one :class:`~sg_torchrl.objectives.surrogates.Surrogate` each (:mod:`sg_torchrl.objectives.surrogates`).
* :func:`gaussian_kl`: closed-form KL between diagonal Gaussian policies (KL early stop).
* :func:`run_passes` (and :func:`whole_batch`): the one minibatch update loop that the seed-group
  passes and the multi-agent rounds share (:mod:`sg_torchrl.objectives.passes`).
* :class:`NaturalPolicyStep`, :class:`TRPOStep`, :class:`CPOStep`, :class:`PCPOStep`: trust-region
  policy steps (NPG / RCPO, TRPO / TRPO-Lag, CPO, PCPO) of one TorchRL actor, the one-seed case of
  the seed-batched step (:mod:`sg_torchrl.objectives.stacked_trust_region`) and of the second-order
  tools (:mod:`sg_torchrl.objectives.second_order`: Fisher-vector products, conjugate gradient, line
  search, each written once for a leading seed dimension); :class:`TrustRegionLoss` gives the same
  surrogates and KL as a TorchRL loss.
"""
from sg_torchrl.objectives.kl import gaussian_kl
from sg_torchrl.objectives.multipliers import (
    LagrangeMultiplier,
    Multiplier,
    NoMultiplier,
    PIDLagrangeMultiplier,
)
from sg_torchrl.objectives.ppo_lag import PPOLagLoss
from sg_torchrl.objectives.first_order import CUPLoss, FOCOPSLoss, PGLoss
from sg_torchrl.objectives.pessimistic import PessimisticPPOLagLoss
from sg_torchrl.objectives.value import AdvantageEstimation, make_cost_gae, make_gae, normalize_advantages
from sg_torchrl.objectives.passes import PassesReport, run_passes, whole_batch
from sg_torchrl.objectives.second_order import (
    backtracking_line_search,
    conjugate_gradient,
    FisherVectorProduct,
    flat_grad,
    flat_params,
    linearise,
    Linearisation,
    LineSearchResult,
    natural_step_size,
    set_flat_params,
)
from sg_torchrl.objectives.trust_region import (
    cpo_direction,
    CPODirection,
    CPOStep,
    NaturalPolicyStep,
    pcpo_direction,
    PCPOStep,
    TRPOStep,
    TrustRegionLoss,
    TrustRegionStep,
)

__all__ = [
    "LagrangeMultiplier",
    "Multiplier",
    "NoMultiplier",
    "PIDLagrangeMultiplier",
    "PPOLagLoss",
    "PGLoss",
    "FOCOPSLoss",
    "CUPLoss",
    "PessimisticPPOLagLoss",
    "gaussian_kl",
    "AdvantageEstimation",
    "make_cost_gae",
    "make_gae",
    "normalize_advantages",
    "PassesReport",
    "run_passes",
    "whole_batch",
    "backtracking_line_search",
    "conjugate_gradient",
    "FisherVectorProduct",
    "flat_grad",
    "flat_params",
    "LineSearchResult",
    "natural_step_size",
    "set_flat_params",
    "cpo_direction",
    "CPODirection",
    "CPOStep",
    "linearise",
    "Linearisation",
    "NaturalPolicyStep",
    "pcpo_direction",
    "PCPOStep",
    "TRPOStep",
    "TrustRegionLoss",
    "TrustRegionStep",
]
