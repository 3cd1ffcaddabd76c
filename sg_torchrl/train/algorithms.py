"""The algorithms ``sg-train`` can run: the single-agent rows of the algorithm manifest, built.

An algorithm is three choices over the shared actor and critics: a multiplier rule, a loss and an
update loop (:mod:`sg_torchrl.train.group_updates`). The twelve SafePO single-agent algorithms of the
Safety-Gymnasium paper (section 5) are the single-agent rows of :mod:`sg_torchrl.algorithms.manifest`,
which names them and says their kinds; here each kind has its builder, and :data:`ALGORITHMS` holds,
per row, the builders its kinds choose:

* the multiplier kind (``none``, ``lagrange``, ``pid``): :class:`~sg_torchrl.objectives.NoMultiplier`,
  :class:`~sg_torchrl.objectives.LagrangeMultiplier`, :class:`~sg_torchrl.objectives.PIDLagrangeMultiplier`;
* the row's loss class (``PGLoss``, ``PPOLagLoss``, ``FOCOPSLoss``, ``CUPLoss``, ...), built with the
  row's ``loss_options`` from the config;
* the update kind: ``first_order`` and ``two_stage`` (CUP's reward stage, then its projection), or a
  trust-region step of the actor, :data:`TRUST_REGION_STEPS` (``natural``: NPG / RCPO, no line search;
  ``trpo``; ``cpo``; ``pcpo``), with PPO-Lag's critic losses.

So PPO is PPO-Lag with :class:`~sg_torchrl.objectives.NoMultiplier`, CPPO-PID is PPO-Lag with the PID
multiplier, TRPO-Lag is TRPO with a Lagrange multiplier and RCPO (as SafePO implements it) is NPG
with one. Adding an algorithm of known kinds is a loss class and a manifest row, not code here.

A row's ``make_group_update`` is its update loop on the seed-group engine (every single-agent run,
``--seed`` or ``--seeds``), built from one seed's loss, the ``LossModule`` users compose in their own
code (the loss object's :meth:`~sg_torchrl.objectives.PPOLagLoss.seed_batched_objective`, through
:func:`~sg_torchrl.train.fused.objective_of`, which refuses a loss without one) and, for the
second-order rows, from the row's step class through
:data:`~sg_torchrl.objectives.trust_region.STACKED_STEPS` with the config's options
(:func:`_trust_region_options`) and the row's ``step_options`` (PCPO's reward direction).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType

from torch import nn
from torchrl.objectives import LossModule

from sg_torchrl.objectives import (
    CPOStep,
    LagrangeMultiplier,
    Multiplier,
    NaturalPolicyStep,
    NoMultiplier,
    PCPOStep,
    PIDLagrangeMultiplier,
    TRPOStep,
)
from sg_torchrl.algorithms import manifest
from sg_torchrl.algorithms.manifest import AlgorithmEntry
from sg_torchrl.train.config import TrainConfig
from sg_torchrl.train.fused import objective_of
from sg_torchrl.train.group_updates import (
    FirstOrderGroupUpdate,
    GroupParts,
    GroupUpdate,
    TrustRegionGroupUpdate,
    TwoStageGroupUpdate,
)
from sg_torchrl.objectives.trust_region import STACKED_STEPS

__all__ = ["Algorithm", "ALGORITHMS", "TRUST_REGION_STEPS", "make_multiplier"]

MakeLoss = Callable[[nn.Module, nn.Module, nn.Module, Multiplier, TrainConfig], LossModule]
#: ``(parts, loss, cfg) -> GroupUpdate``: ``loss`` is one seed's single-seed loss (``make_loss``), which
#: carries the objective and its hyper-parameters.
MakeGroupUpdate = Callable[[GroupParts, LossModule, TrainConfig], GroupUpdate]


@dataclass(frozen=True)
class Algorithm:
    """How to build one algorithm's multiplier, loss and update loop from a config."""

    title: str
    make_multiplier: Callable[[TrainConfig], Multiplier]
    make_loss: MakeLoss
    make_group_update: MakeGroupUpdate


# ---------------------------------------------------------------------------- multipliers
def _none(cfg: TrainConfig) -> Multiplier:
    return NoMultiplier(cost_limit=cfg.cost_limit)


def _lagrange(cfg: TrainConfig) -> Multiplier:
    return LagrangeMultiplier(cost_limit=cfg.cost_limit, init=cfg.lagrangian_init, lr=cfg.lagrangian_lr,
                              upper_bound=cfg.multiplier_upper_bound)


def _pid(cfg: TrainConfig) -> Multiplier:
    return PIDLagrangeMultiplier(
        cost_limit=cfg.cost_limit, kp=cfg.pid_kp, ki=cfg.pid_ki, kd=cfg.pid_kd, d_delay=cfg.pid_d_delay,
        init=cfg.lagrangian_init,
    )


# ---------------------------------------------------------------------------- losses
def _loss_builder(entry: AlgorithmEntry) -> MakeLoss:
    """The row's loss class with its ``loss_options`` read from the config.

    ``functional=False``: these losses need no functional parameter swapping (no target networks, no
    meta-RL), and calling the modules directly saves ~0.35 ms per minibatch step on CPU.
    """
    def make(actor, critic, cost_critic, multiplier, cfg: TrainConfig) -> LossModule:
        options = cfg.keyword_options(entry.loss_options)
        return entry.loss_class()(actor, critic, cost_critic, multiplier, functional=False, **options)

    return make


# ---------------------------------------------------------------------------- updates
def _trust_region_options(cfg: TrainConfig, line_search: bool) -> dict:
    """The options of a trust-region step class (its stacked form takes the same) from the config."""
    options = dict(target_kl=cfg.target_kl, cg_iters=cfg.cg_iters, cg_damping=cfg.cg_damping)
    if line_search:
        options.update(line_search_steps=cfg.line_search_steps, step_fraction=cfg.step_fraction)
    return options


def _trust_region_group(step_class: type, *, line_search: bool = True,
                        step_options: Mapping[str, str] = MappingProxyType({})) -> MakeGroupUpdate:
    """The seed-group update of a second-order row: ``step_class``'s stacked step, critics-only passes.

    ``step_options`` are the row's own step keywords, read from the config (``{keyword: TrainConfig field}``).
    """
    def make(parts: GroupParts, loss: LossModule, cfg: TrainConfig) -> GroupUpdate:
        options = _trust_region_options(cfg, line_search)
        options.update(cfg.keyword_options(step_options))
        step = STACKED_STEPS[step_class](parts.model, **options)
        return TrustRegionGroupUpdate(parts, step, objective_of(loss, critics_only=True))

    return make


def _first_order_group(parts: GroupParts, loss: LossModule, cfg: TrainConfig) -> GroupUpdate:
    return FirstOrderGroupUpdate(parts, objective_of(loss))


def _two_stage_group(parts: GroupParts, loss: LossModule, cfg: TrainConfig) -> GroupUpdate:
    return TwoStageGroupUpdate(parts, objective_of(loss.reward_stage), objective_of(loss))


#: The trust-region step class of each second-order update kind (the manifest rows' ``update``).
TRUST_REGION_STEPS: dict[str, type] = {"natural": NaturalPolicyStep, "trpo": TRPOStep, "cpo": CPOStep,
                                       "pcpo": PCPOStep}
#: The update kinds whose step takes no line search (NPG's natural step, and RCPO's).
_NO_LINE_SEARCH = frozenset({"natural"})

# ---------------------------------------------------------------------------- the rows
#: Builders by multiplier kind and update kind; the loss is the row's own.
_MULTIPLIERS: dict[str, Callable[[TrainConfig], Multiplier]] = {"none": _none, "lagrange": _lagrange, "pid": _pid}
_FIRST_ORDER_UPDATES: dict[str, MakeGroupUpdate] = {"first_order": _first_order_group, "two_stage": _two_stage_group}


def _update_builder(entry: AlgorithmEntry) -> MakeGroupUpdate:
    """The row's update loop: a first-order kind's, or its trust-region step with the row's step options."""
    if entry.update in _FIRST_ORDER_UPDATES:
        return _FIRST_ORDER_UPDATES[entry.update]
    return _trust_region_group(TRUST_REGION_STEPS[entry.update], line_search=entry.update not in _NO_LINE_SEARCH,
                               step_options=entry.step_options)


def make_multiplier(kind: str, cfg: TrainConfig) -> Multiplier:
    """A multiplier of ``kind`` (a manifest row's ``multiplier``: ``none``, ``lagrange``, ``pid``) from the config."""
    return _MULTIPLIERS[kind](cfg)


def _algorithm(entry: AlgorithmEntry) -> Algorithm:
    """A manifest row's builders, chosen by its multiplier kind and update kind, and its loss class."""
    return Algorithm(entry.title, _MULTIPLIERS[entry.multiplier], _loss_builder(entry), _update_builder(entry))


#: The single-agent on-policy algorithms by ``--algo`` name, in the manifest's order (the off-policy rows are
#: built by :mod:`sg_torchrl.train.off_policy`).
ALGORITHMS: dict[str, Algorithm] = {entry.name: _algorithm(entry) for entry in manifest.rows(agents="single")
                                    if not entry.off_policy}
