"""MACPO (Gu et al. 2023): a CPO step per agent, in HAPPO's sequential order.

Multi-Agent Constrained Policy Optimisation (Gu et al. 2023, "Safe multi-agent reinforcement
learning for multi-robot control", Artificial Intelligence 319) applies Constrained Policy
Optimization (Achiam et al. 2017) to one agent at a time, in a random order, on surrogates that
carry the sequential factor :math:`M` of the agents updated before it in the round:

.. math::

    \\max_{\\theta^i}\\; \\mathbb E[M\\, r^i A_r] \\quad \\text{s.t.} \\quad
    c + \\mathbb E[M\\, r^i A^i_c] \\le 0, \\quad \\overline{\\mathrm{KL}}(\\pi^i_{\\text{old}} \\| \\pi^i) \\le \\delta,

with :math:`c = (J_c - d)(1 - \\gamma)` (SafePO's scaling of the mean episode cost). The step is
the single-agent machinery unchanged: :class:`MACPOStep` is a
:class:`~sg_torchrl.objectives.CPOStep` (the QP solution of
:func:`~sg_torchrl.objectives.cpo_direction`, the paper's dual, which is also what SafePO's MACPO
computes), fed :math:`M A_r` and :math:`M A^i_c` as advantages; only its step-size policy differs:

* the direction's norm is capped at ``max_step_norm`` (0.5) and the line search tries
  ``initial_step_fraction * step_fraction**k`` (:math:`0.1 \\cdot 0.5^k`, :math:`k < 10`) of it, as
  SafePO's MACPO does (the paper lists 10 search steps and fraction 0.5); a trial is accepted when
  the KL is at most :math:`\\delta = 0.01`, the cost surrogate grew by at most :math:`\\max(-c, 0)`
  and, in the feasible cases, the reward surrogate did not decrease; otherwise the agent keeps its
  parameters;
* the KL is summed over action dims (the agent's joint distribution; SafePO's MACPO does the same),
  conjugate gradient runs 10 iterations with damping 0.1.

The step-size policy is written once (:class:`MACPORule`) for one actor (:class:`MACPOStep`) and for the
rows of the seed-batched round (:class:`StackedMACPOStep`), whose stages and critic epochs are
:class:`~sg_torchrl.train.multi_agent_updates.MACPOUpdate`'s.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

from sg_torchrl.algorithms.manifest import MACPO_STEP_DEFAULTS
from sg_torchrl.objectives.second_order import Linearisation
from sg_torchrl.objectives.stacked_trust_region import StackedTrustRegionStep
from sg_torchrl.objectives.step_rules import CPORule, Proposal
from sg_torchrl.objectives.trust_region import TrustRegionStep

__all__ = ["MACPORule", "MACPOStep", "StackedMACPOStep"]


class MACPORule(CPORule):
    """CPO's proposal with MACPO's step-size policy (see the module docstring), for one actor or stacked rows.

    Keyword Args:
        target_kl, cg_iters, line_search_steps, step_fraction, max_step_norm (``None``: no cap on the
            direction's norm), initial_step_fraction (``1.0``: the plain CPO line search): default to
            :data:`~sg_torchrl.algorithms.manifest.MACPO_STEP_DEFAULTS` (the paper's and SafePO's, see the
            module docstring).
        kl_action_reduction (str): defaults to ``"sum"`` (joint KL of the agent's action).
        **options: see :class:`~sg_torchrl.objectives.CPOStep` (``cg_damping`` 0.1, ...).

    Raises:
        ValueError: a bad option (here, before any step).

    Extra metric: ``Misc/StepNormRaw`` (norm of the CPO direction before the cap and the initial
    fraction; ``Misc/FinalStepNorm`` is the norm of the step actually tried first).
    """

    def __init__(self, *args: Any, kl_action_reduction: Literal["mean", "sum"] = "sum", **options: Any) -> None:
        options = {**MACPO_STEP_DEFAULTS, **options}
        max_step_norm, initial_step_fraction = options.pop("max_step_norm"), options.pop("initial_step_fraction")
        if max_step_norm is not None and not max_step_norm > 0:
            raise ValueError(f"max_step_norm must be > 0 or None, got {max_step_norm}.")
        if not 0.0 < initial_step_fraction <= 1.0:
            raise ValueError(f"initial_step_fraction must be in (0, 1], got {initial_step_fraction}.")
        super().__init__(*args, kl_action_reduction=kl_action_reduction, **options)
        self.max_step_norm = None if max_step_norm is None else float(max_step_norm)
        self.initial_step_fraction = float(initial_step_fraction)

    def _propose(self, lin: Linearisation, cost_violation: float) -> Proposal:
        proposal = super()._propose(lin, cost_violation)
        direction = proposal.direction
        raw_norm = float(direction.norm())
        if self.max_step_norm is not None and raw_norm > self.max_step_norm:
            direction = direction * (self.max_step_norm / raw_norm)
        return dataclasses.replace(
            proposal,
            direction=self.initial_step_fraction * direction,
            metrics={**proposal.metrics, "Misc/StepNormRaw": raw_norm},
        )


class MACPOStep(MACPORule, TrustRegionStep):
    """MACPO's step of one agent's policy (:class:`MACPORule` on :class:`~sg_torchrl.objectives.CPOStep`'s engine).

    Args:
        actor (ProbabilisticTensorDictSequential): one agent's policy (its parameters only).

    Keyword Args:
        **options: see :class:`MACPORule`.
    """


class StackedMACPOStep(MACPORule, StackedTrustRegionStep):
    """MACPO's step of stacked rows (the seed-batched round's agents of a stage), each row its own CPO case."""
