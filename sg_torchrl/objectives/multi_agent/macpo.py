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

MACPO's round is not seed-batched: a seed group runs its seeds' rounds one after another
(:class:`SeedRounds`, what :meth:`MACPOUpdate.for_seeds` builds). Its trust-region step is already the
seed-batched step on one row (:class:`~sg_torchrl.objectives.CPOStep`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential
from torch import nn, Tensor
from torchrl.modules import PopArtValueNorm

from sg_torchrl import seeding
from sg_torchrl.modules.multi_agent import MultiAgentNetworks
from sg_torchrl.modules.stacked_multi_agent import StackedMultiAgentNetworks
from sg_torchrl.objectives.multi_agent.advantages import agent_view, AGENT_VIEW_KEYS
from sg_torchrl.objectives.multi_agent.loss import AgentPPOLoss
from sg_torchrl.objectives.multi_agent.sequential import episode_costs, round_metrics, SequentialAgentUpdate
from sg_torchrl.objectives.multi_agent.updates import CRITIC_METRICS
from sg_torchrl.objectives.multipliers import NoMultiplier
from sg_torchrl.objectives.passes import ClipGroup, GradientStep, run_passes, shuffled_chunks
from sg_torchrl.objectives.second_order import Linearisation
from sg_torchrl.objectives.step_rules import Proposal
from sg_torchrl.objectives.trust_region import CPOStep

__all__ = ["MACPOStep", "MACPOUpdate", "SeedRounds"]


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


class MACPOUpdate:
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
        cost_limit (float): :math:`d`. Defaults to ``25.0`` (paper).
        gamma (float): discount of the :math:`(1 - \\gamma)` constraint scaling. Defaults to ``0.99``.
        critic_lr (float): Adam learning rate of both critics. Defaults to ``5e-4`` (paper).
        max_grad_norm (float): gradient-norm clip of each critic on its own (SafePO). Defaults to ``10.0``.
        adam_eps (float): Adam's eps. Defaults to ``1e-5`` (SafePO).
        value_norm (bool): PopArt normalisation of each reward critic's loss. Defaults to ``True`` (SafePO).
        shuffle (bool): random agent order per round. Defaults to ``True``.
        generator (torch.Generator, optional): agent orders and minibatch shuffles.
        group (str): the group key. Defaults to ``"agents"``.
        loss_kwargs (dict, optional): extra :class:`AgentPPOLoss` options for the critics' losses.

    Per-agent metrics: the step's (``Misc/CPOCase``, ``Misc/AcceptanceStep``, ``Misc/FinalStepNorm``,
    ``Misc/StepNormRaw``, ``Misc/Lambda_star``, ``Misc/Nu_star``, ``Misc/xHx``, ``Misc/gradient_norm``,
    ``Misc/cost_gradient_norm``, ``Train/KL`` (KL after the step, 0 when rejected),
    ``Loss/Loss_actor`` (minus the weighted reward surrogate before the step)), the critics'
    (``Loss/Loss_reward_critic``, ``Loss/Loss_cost_critic``, ``Misc/Reward_critic_norm``,
    ``Misc/Cost_critic_norm``), ``Misc/Entropy``, ``Misc/Ratio``, ``Misc/Factor`` and
    ``Misc/ConstraintValue`` (:math:`c`).
    """

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
        cost_limit: float = 25.0,
        gamma: float = 0.99,
        critic_lr: float = 5e-4,
        max_grad_norm: float = 10.0,
        adam_eps: float = 1e-5,
        value_norm: bool = True,
        clip_epsilon: float = 0.2,
        shuffle: bool = True,
        generator: torch.Generator | None = None,
        group: str = "agents",
        loss_kwargs: dict[str, Any] | None = None,
    ) -> None:
        if critic_epochs < 1 or num_minibatches < 1:
            raise ValueError(f"need critic_epochs >= 1 and num_minibatches >= 1, got {critic_epochs}, {num_minibatches}.")
        n = networks.n_agents
        self.networks, self.n_agents, self.group = networks, n, group
        self.gamma, self.max_grad_norm = float(gamma), float(max_grad_norm)
        self.critic_epochs, self.num_minibatches = int(critic_epochs), int(num_minibatches)
        self.generator = generator if generator is not None else seeding.generator(0, seeding.Purpose.MINIBATCHES)
        self.multipliers = nn.ModuleList(NoMultiplier(cost_limit) for _ in range(n))  # they hold the cost limit
        self.value_norms = nn.ModuleList(PopArtValueNorm(shape=1) for _ in range(n)) if value_norm else None
        # the losses train the critics only (no entropy term: the CPO step moves the actor); the factor enters
        # through the step
        self.losses = [
            AgentPPOLoss(networks.agent_actor(i), networks.agent_critic(i), networks.agent_cost_critic(i),
                         self.multipliers[i], weighted=False, clip_epsilon=clip_epsilon, entropy_coeff=0.0,
                         value_norm=None if self.value_norms is None else self.value_norms[i], functional=False,
                         **(loss_kwargs or {}))
            for i in range(n)
        ]
        self.sequential = SequentialAgentUpdate(n, weighted=True, shuffle=shuffle, generator=self.generator)
        self._critic_params = [(list(networks.agent_critic(i).parameters()),
                                list(networks.agent_cost_critic(i).parameters())) for i in range(n)]
        self.optimizers = [torch.optim.Adam([{"params": [*reward, *cost], "lr": critic_lr}], eps=adam_eps)
                           for reward, cost in self._critic_params]
        self.steps = [
            MACPOStep(
                networks.agent_actor(i), target_kl=target_kl, cg_iters=cg_iters, cg_damping=cg_damping,
                line_search_steps=line_search_steps, step_fraction=step_fraction, max_step_norm=max_step_norm,
                initial_step_fraction=initial_step_fraction,
            )
            for i in range(n)
        ]

    @classmethod
    def for_seeds(cls, networks: StackedMultiAgentNetworks, generators: Sequence[torch.Generator],
                  **options: Any) -> SeedRounds:
        """S seeds' rounds (one per team of the stack, each with its generator), run one after another."""
        return SeedRounds([cls(team, generator=generator, **options)
                           for team, generator in zip(networks.teams, generators, strict=True)])

    def __call__(self, data: TensorDictBase, mean_episode_cost: float | Tensor) -> dict[str, float]:
        """One round on ``data`` (the keys of :class:`~sg_torchrl.objectives.multi_agent.MultiAgentPPOUpdate`).

        Returns the team metrics (mean over agents) under SafePO's names, the same per agent under
        ``"<name>/agent<i>"``, and ``Train/AgentOrder/agent<i>``.
        """
        costs = episode_costs(mean_episode_cost, self.n_agents)
        keys = AGENT_VIEW_KEYS
        if self.losses[0].clip_value is not None:
            keys = (*keys, "state_value", "cost_value")
        views = [agent_view(data, i, group=self.group, keys=keys) for i in range(self.n_agents)]
        result = self.sequential.run(
            lambda i, factor: self._update_agent(i, views[i], factor, costs[i]),
            lambda i: self._log_prob(i, views[i]),
            views[0].batch_size[0],
        )
        return round_metrics([(stage.agent, stage.metrics) for stage in result.stages],
                             [float(m.value) for m in self.multipliers])

    def _log_prob(self, agent: int, view: TensorDictBase) -> Tensor:
        actor = self.networks.agent_actor(agent)
        return actor.get_dist(view.select(*actor.in_keys)).log_prob(view.get("action"))

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
        """``critic_epochs`` passes of ``num_minibatches`` Adam steps on the agent's two critics, each clipped
        on its own, no early stop."""
        reward, cost = self._critic_params[agent]
        groups = (ClipGroup(reward, "Misc/Reward_critic_norm"), ClipGroup(cost, "Misc/Cost_critic_norm"))
        step = GradientStep(self.losses[agent].critic_losses, self.optimizers[agent],
                            ("loss_critic", "loss_cost_critic"), groups, self.max_grad_norm)
        return run_passes(view, step, passes=self.critic_epochs, order=shuffled_chunks(self.num_minibatches),
                          generator=self.generator, metrics=CRITIC_METRICS).means

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Optimiser states, multipliers, value normalisers and the generator (the networks are the caller's)."""
        return {
            "optimizers": [opt.state_dict() for opt in self.optimizers],
            "multipliers": self.multipliers.state_dict(),
            "value_norms": None if self.value_norms is None else self.value_norms.state_dict(),
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for opt, opt_state in zip(self.optimizers, state["optimizers"], strict=True):
            opt.load_state_dict(opt_state)
        self.multipliers.load_state_dict(state["multipliers"])
        if self.value_norms is not None:
            self.value_norms.load_state_dict(state["value_norms"])
        self.generator.set_state(state["generator"])


class SeedRounds:
    """S single-team rounds side by side with the seed-batched round's interface, run one after another.

    What a seed group trains MACPO with (:meth:`MACPOUpdate.for_seeds`); seed ``s`` is its round alone.
    """

    def __init__(self, rounds: Sequence[MACPOUpdate]) -> None:
        self.rounds = list(rounds)

    def step_seeds(self, batches: Sequence[TensorDictBase | None],
                   mean_episode_costs: Sequence[float | Tensor | None]) -> list[dict[str, float] | None]:
        """Each seed's round on its batch (``None``: a frozen seed, untouched)."""
        return [None if batch is None else update(batch, cost)
                for update, batch, cost in zip(self.rounds, batches, mean_episode_costs, strict=True)]

    def seed_state_dict(self, seed: int) -> dict[str, Any]:
        return self.rounds[seed].state_dict()

    def load_seed_state_dict(self, seed: int, state: dict[str, Any]) -> None:
        self.rounds[seed].load_state_dict(state)
