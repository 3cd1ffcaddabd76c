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

After its step each agent's critics take ``critic_epochs`` (15, the paper's "SGD iters") passes of
Adam at 5e-4 (SafePO's script: one step at 5e-3 per round).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential
from torch import Tensor

from sg_torchrl.modules.multi_agent import MultiAgentNetworks
from sg_torchrl.objectives.multi_agent.updates import CRITIC_METRICS, MultiAgentUpdate
from sg_torchrl.objectives.passes import run_passes, shuffled_chunks
from sg_torchrl.objectives.second_order import Linearisation
from sg_torchrl.objectives.step_rules import Proposal
from sg_torchrl.objectives.trust_region import CPOStep

__all__ = ["MACPOStep", "MACPOUpdate"]


class MACPOStep(CPOStep):
    """:class:`~sg_torchrl.objectives.CPOStep` with MACPO's step-size policy (see the module docstring).

    Args:
        actor (ProbabilisticTensorDictSequential): one agent's policy (its parameters only).

    Keyword Args:
        target_kl (float): :math:`\\delta`. Defaults to ``0.01`` (paper).
        cg_iters (int): defaults to ``10`` (paper).
        line_search_steps (int): defaults to ``10`` (paper).
        step_fraction (float): defaults to ``0.5`` (paper).
        max_step_norm (float, optional): cap on the direction's norm. Defaults to ``0.5`` (SafePO);
            ``None`` for no cap.
        initial_step_fraction (float): fraction of the (capped) direction tried first. Defaults to
            ``0.1`` (SafePO's ``fraction_coef``); ``1.0`` gives the plain CPO line search.
        kl_action_reduction (str): defaults to ``"sum"`` (joint KL of the agent's action).
        **kwargs: see :class:`~sg_torchrl.objectives.CPOStep` (``cg_damping`` 0.1, ...).

    Extra metric: ``Misc/StepNormRaw`` (norm of the CPO direction before the cap and the initial
    fraction; ``Misc/FinalStepNorm`` is the norm of the step actually tried first).
    """

    def __init__(
        self,
        actor: ProbabilisticTensorDictSequential,
        *,
        target_kl: float = 0.01,
        cg_iters: int = 10,
        line_search_steps: int = 10,
        step_fraction: float = 0.5,
        max_step_norm: float | None = 0.5,
        initial_step_fraction: float = 0.1,
        kl_action_reduction: Literal["mean", "sum"] = "sum",
        **kwargs: Any,
    ) -> None:
        if max_step_norm is not None and not max_step_norm > 0:
            raise ValueError(f"max_step_norm must be > 0 or None, got {max_step_norm}.")
        if not 0.0 < initial_step_fraction <= 1.0:
            raise ValueError(f"initial_step_fraction must be in (0, 1], got {initial_step_fraction}.")
        super().__init__(
            actor, target_kl=target_kl, cg_iters=cg_iters, line_search_steps=line_search_steps,
            step_fraction=step_fraction, kl_action_reduction=kl_action_reduction, **kwargs,
        )
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


class MACPOUpdate(MultiAgentUpdate):
    """MACPO's round: per agent in random order, a :class:`MACPOStep` on the factor-weighted surrogates, then critic epochs.

    Args:
        networks (MultiAgentNetworks): the team's networks.

    Keyword Args:
        target_kl (float): per-agent trust region :math:`\\delta`. Defaults to ``0.01`` (paper).
        cg_iters (int): defaults to ``10`` (paper).
        line_search_steps (int): defaults to ``10`` (paper).
        step_fraction (float): defaults to ``0.5`` (paper).
        max_step_norm (float, optional), initial_step_fraction (float): see :class:`MACPOStep`.
        cg_damping (float): defaults to ``0.1``.
        critic_epochs (int): critic passes per agent and round. Defaults to ``15`` (paper).
        num_minibatches (int): critic minibatches per pass. Defaults to ``1``.
        **kwargs: see :class:`~sg_torchrl.objectives.multi_agent.MultiAgentUpdate` (``cost_limit``,
            ``gamma``, ``critic_lr`` 5e-4, ``max_grad_norm``, ``value_norm``, ...).

    Per-agent metrics: the step's (``Misc/CPOCase``, ``Misc/AcceptanceStep``, ``Misc/FinalStepNorm``,
    ``Misc/StepNormRaw``, ``Misc/Lambda_star``, ``Misc/Nu_star``, ``Misc/xHx``, ``Misc/gradient_norm``,
    ``Misc/cost_gradient_norm``, ``Train/KL`` (KL after the step, 0 when rejected),
    ``Loss/Loss_actor`` (minus the weighted reward surrogate before the step)), the critics'
    (``Loss/Loss_reward_critic``, ``Loss/Loss_cost_critic``, ``Misc/Reward_critic_norm``,
    ``Misc/Cost_critic_norm``), ``Misc/Entropy``, ``Misc/Ratio``, ``Misc/Factor`` and
    ``Misc/ConstraintValue`` (:math:`c`).
    """

    weighted = True

    def __init__(
        self,
        networks: MultiAgentNetworks,
        *,
        target_kl: float = 0.01,
        cg_iters: int = 10,
        line_search_steps: int = 10,
        step_fraction: float = 0.5,
        max_step_norm: float | None = 0.5,
        initial_step_fraction: float = 0.1,
        cg_damping: float = 0.1,
        critic_epochs: int = 15,
        num_minibatches: int = 1,
        **kwargs: Any,
    ) -> None:
        if critic_epochs < 1 or num_minibatches < 1:
            raise ValueError(f"need critic_epochs >= 1 and num_minibatches >= 1, got {critic_epochs}, {num_minibatches}.")
        kwargs.setdefault("entropy_coeff", 0.0)  # the critic losses only; the CPO step has no entropy term
        super().__init__(networks, **kwargs)
        self.critic_epochs = int(critic_epochs)
        self.num_minibatches = int(num_minibatches)
        self.steps = [
            MACPOStep(
                networks.agent_actor(i), target_kl=target_kl, cg_iters=cg_iters, cg_damping=cg_damping,
                line_search_steps=line_search_steps, step_fraction=step_fraction, max_step_norm=max_step_norm,
                initial_step_fraction=initial_step_fraction,
            )
            for i in range(networks.n_agents)
        ]

    def _loss_weighted(self) -> bool:
        return False  # the losses only train the critics here; the factor enters through the step

    def cost_violation(self, agent: int, episode_cost: float) -> float:
        """:math:`c = (J_c - d)(1 - \\gamma)`, with :math:`J_c - d` from the agent's multiplier (which holds the limit)."""
        return self.multipliers[agent].violation(episode_cost) * (1.0 - self.gamma)

    def _update_agent(self, agent: int, view: TensorDictBase, factor: Tensor, episode_cost: float) -> dict[str, float]:
        weight = factor.unsqueeze(-1)
        c = self.cost_violation(agent, episode_cost)
        metrics = dict(self.steps[agent].step(view, weight * view.get("advantage"), weight * view.get("cost_advantage"), c))
        with torch.no_grad():
            ratio = (self._log_prob(agent, view) - view.get("action_log_prob")).exp().mean()
        metrics.update(self._critic_epochs(agent, view))
        metrics.update({
            "Misc/Entropy": float(self.networks.agent_entropy(agent)),
            "Misc/Ratio": float(ratio),
            "Misc/Factor": float(factor.mean()),
            "Misc/ConstraintValue": c,
        })
        return metrics

    def _critic_epochs(self, agent: int, view: TensorDictBase) -> dict[str, float]:
        """``critic_epochs`` passes of ``num_minibatches`` Adam steps on the agent's two critics, no early stop."""
        step = self._gradient_step(agent, self.losses[agent].critic_losses, ("loss_critic", "loss_cost_critic"), actor=False)
        return run_passes(view, step, passes=self.critic_epochs, order=shuffled_chunks(self.num_minibatches),
                          generator=self.generator, metrics=CRITIC_METRICS).means
