"""The rounds of MAPPO, HAPPO, MAPPO-Lag and MACPO, seed-batched: S seeds' rounds in one update call per stage.

Every algorithm of the Safety-Gymnasium paper's multi-agent benchmark (Ji et al. 2023) updates the
agents one at a time in a random order (Kuba et al. 2022's sequential scheme). The algorithms differ only
in what one agent's update is:

================  =============================================  ==========  =======================
class             agent update                                   factor M    multiplier
================  =============================================  ==========  =======================
MAPPOUpdate       clipped-PPO epochs (Yu et al. 2022)             unused      none
HAPPOUpdate       factor-weighted clipped-PPO epochs              yes         none
                  (Kuba et al. 2022)
MAPPOLagUpdate    factor-weighted clipped PPO on                  yes         per agent, stepped
                  :math:`A_r - \\lambda^i A^i_c` (Gu et al. 2023)               after every minibatch
MACPOUpdate       one CPO step on factor-weighted surrogates,     yes         none (the CPO step)
                  then critic epochs (Gu et al. 2023;
                  the step: :mod:`~sg_torchrl.objectives.multi_agent.macpo`)
================  =============================================  ==========  =======================

All are :class:`~sg_torchrl.train.multi_agent_round.SeedBatchedRound` s (the first three through
:class:`MultiAgentPPOUpdate`): the round written once for S seeds, each seed with its own random agent
order, the agent of every seed at a stage updated in one call.

Usage, once per collected batch (after both GAEs, see
:func:`~sg_torchrl.objectives.multi_agent.make_multi_agent_gae`)::

    nets = make_multi_agent_networks(obs_size, env.action_sizes, state_size)
    update = MAPPOLagUpdate(nets, cost_limit=25.0)
    ...
    metrics = update(batch, mean_episode_cost)   # dict[str, float], SafePO's metric names

``batch`` has batch dims ``[*B]`` (e.g. ``[N, T]``) and holds, per agent under the group key,
``observation``, ``action``, ``action_log_prob`` (the collector's behaviour log-prob),
``advantage``, ``value_target``, ``cost_advantage``, ``cost_value_target`` (``[*B, A, ...]``) and
the root ``"state"``. ``mean_episode_cost`` is :math:`J_c`, the mean undiscounted episode cost of
the episodes finished in the rollout: a float for the team, or one value per agent.

Defaults are the paper's multi-agent hyper-parameters and, where it lists none, SafePO's (each option's
in the classes' docstrings and :class:`~sg_torchrl.train.multi_agent_round.SeedBatchedRound`'s).
Deviations from SafePO's scripts:

* the KL early stop at ``target_kl`` (the paper lists 0.016; SafePO's MaMuJoCo scripts never read
  it): after each epoch, stop the agent's epochs once :math:`\\mathrm{KL}(\\pi_{\\text{old}} \\|
  \\pi)` (summed over action dims) exceeds it; ``target_kl=None`` disables it;
* critic losses are MSE, the reward critic's through TorchRL's PopArt (``MAPPOLoss``'s semantics, see
  :class:`~sg_torchrl.objectives.multi_agent.AgentObjective`; no value clipping) instead of SafePO's Huber(10) with value
  clipping, where the cost values are normalised with the reward critic's PopArt statistics
  **[quirk]**;
* the GAEs bootstrap truncated episodes (:mod:`~sg_torchrl.objectives.multi_agent.advantages`).
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
from torch import Tensor

from sg_torchrl.algorithms.manifest import MACPO_STEP_DEFAULTS
from sg_torchrl.modules.gaussian import gaussian_log_prob
from sg_torchrl.modules.multi_agent import MultiAgentNetworks
from sg_torchrl.modules.stacked_multi_agent import NETWORKS, StackedMultiAgentNetworks
from sg_torchrl.objectives.kl import gaussian_kl
from sg_torchrl.objectives.multi_agent.macpo import StackedMACPOStep
from sg_torchrl.objectives.multi_agent.multiplier import MAPPOLagMultiplier
from sg_torchrl.objectives.multipliers import Multiplier
from sg_torchrl.objectives.passes import RowMeans, run_passes
from sg_torchrl.train.fused import SeedBatch
from sg_torchrl.train.multi_agent_round import CRITIC_METRICS, SeedBatchedRound, host_lists

__all__ = ["HAPPOUpdate", "MACPOUpdate", "MAPPOLagUpdate", "MAPPOUpdate", "MultiAgentPPOUpdate"]

#: Everything a stage averages over its optimiser steps (metric name: step output).
STEP_METRICS = {"Loss/Loss_actor": "loss_objective", **CRITIC_METRICS, "Misc/Ratio": "mean_ratio"}
#: The options of MACPOUpdate that go to its step (:class:`~sg_torchrl.objectives.multi_agent.MACPORule`).
_STEP_OPTIONS = frozenset((*MACPO_STEP_DEFAULTS, "cg_damping"))


class MultiAgentPPOUpdate(SeedBatchedRound):
    """The sequential clipped-PPO round of MAPPO, HAPPO and MAPPO-Lag, for S seeds at once (S >= 1).

    At stage ``k`` the rows (each live seed's agent ``order[s, k]``,
    :class:`~sg_torchrl.train.multi_agent_round.SeedBatchedRound`) take up to ``epochs`` passes of
    ``num_minibatches`` steps together, each step :attr:`objective`'s losses
    (:class:`~sg_torchrl.objectives.multi_agent.AgentObjective`, obtained from the agents' loss,
    :meth:`AgentPPOLoss.seed_batched_objective`), their backward, the gradients clipped per seed and network
    (actor, reward critic, cost critic) and a :class:`~sg_torchrl.train.seed_adam.SeedMaskedAdam` step;
    MAPPO-Lag then steps each row's multiplier. A seed whose KL early stop fires is masked for the rest of
    its stage (its parameters, moments, PopArt statistics, multiplier and generator do not move), the
    others go on. So seed ``s`` of a group does what its round alone does (S = 1).

    Keyword Args:
        actor_lr (float): defaults to ``5e-4`` (paper).
        epochs (int): passes over the batch per agent. Defaults to ``5`` (paper).
        target_kl (float, optional): KL early stop per agent. Defaults to ``0.016`` (paper); ``None`` disables it.
        **kwargs: see :class:`~sg_torchrl.train.multi_agent_round.SeedBatchedRound` (``cost_limit``,
            ``gamma``, ``critic_lr``, ``max_grad_norm``, ``num_minibatches``, ``entropy_coeff`` 0.01, ...).

    Per-agent metrics: ``Loss/Loss_actor``, ``Loss/Loss_reward_critic``, ``Loss/Loss_cost_critic``
    (means over the agent's steps), ``Misc/Reward_critic_norm``, ``Misc/Cost_critic_norm`` (gradient norms
    before clipping), ``Misc/Ratio`` (mean ratio to the behaviour policy), ``Misc/Entropy`` (policy
    entropy over the real action dims, after the update), ``Misc/Factor`` (mean :math:`M` handed to the
    agent), ``Train/KL``, ``Train/StopIter`` (epochs run), ``Train/LagrangeMultiplier``.
    """

    #: Whether each agent's multiplier is stepped after every minibatch step (MAPPO-Lag).
    steps_multiplier: ClassVar[bool] = False

    def __init__(self, networks: MultiAgentNetworks | StackedMultiAgentNetworks, *, actor_lr: float = 5e-4,
                 epochs: int = 5, target_kl: float | None = 0.016, **kwargs: Any) -> None:
        if epochs < 1:
            raise ValueError(f"need epochs >= 1, got {epochs}.")
        self.actor_lr, self.epochs = float(actor_lr), int(epochs)
        self.target_kl = None if target_kl is None else float(target_kl)
        super().__init__(networks, **kwargs)

    def _learning_rates(self) -> tuple[float, ...]:
        return (self.actor_lr, self.critic_lr)

    def _stage(self, seeds: Tensor, agents: Tensor, fields: dict[str, Tensor], factor: Tensor | None,
               costs: Tensor) -> tuple[dict[str, list[float]], Tensor | None]:
        """Stage ``k``: seed ``seeds[i]`` updates agent ``agents[i]``; returns its metrics per row and the new factor."""
        live, device = len(seeds), self.networks.device
        batch = self._stage_data(seeds, agents, fields, factor)
        rows = self.networks.agent_rows(seeds, agents)
        observation, action = batch["observation"], batch["action"]
        # The actor on the whole batch is evaluated before the first pass (the old policy) and after each
        # pass (the KL); with one minibatch per pass the next step needs exactly that evaluation, so it is
        # taken with its graph and handed to that step instead of evaluated again.
        reuse = self.num_minibatches == 1
        with torch.set_grad_enabled(reuse):
            policy_now: tuple[Tensor, Tensor] | None = rows.dist_params(observation)  # at the rows' parameters now
        old_loc, old_scale = (t.detach() for t in policy_now)
        pending = policy_now if reuse else None  # the evaluation the next whole-batch step takes
        with torch.no_grad():
            before = gaussian_log_prob(action, old_loc, old_scale)
        optimizer = self._optimizer(rows, seeds, agents)
        multipliers = [self.team_multipliers[int(s)][int(a)] for s, a in zip(seeds, agents)]
        lam = torch.stack([m.value.to(torch.float64) for m in multipliers])
        violation = (costs[torch.arange(live), agents].to(device, non_blocking=True)
                     - torch.stack([m.cost_limit for m in multipliers]))
        if self.steps_multiplier:  # the multipliers' constants, on the device once per stage
            f64 = dict(dtype=torch.float64, device=device)
            multiplier_lr = torch.tensor([m.lr for m in multipliers], **f64)
            multiplier_gamma = torch.tensor([m.gamma for m in multipliers], **f64)
        value_norm = self._value_norm(seeds, agents)
        active = torch.ones(live, dtype=torch.bool, device=device)
        passes = torch.zeros(live, dtype=torch.float64, device=device)
        kl = torch.zeros(live, dtype=torch.float32, device=device)
        means = RowMeans(STEP_METRICS, (live,), device)

        def step(minibatch: SeedBatch):
            nonlocal lam, pending
            policy = pending if minibatch is batch else None
            pending = None
            out = self.objective.losses(rows, minibatch.fields(), lam, value_norm, active, policy)
            total = out["loss_objective"] + out["loss_critic"] + out["loss_cost_critic"] + out["loss_entropy"]
            rows.zero_grad()
            total.sum().backward()
            _, out["reward_norm"], out["cost_norm"] = self._clip(rows, NETWORKS)
            optimizer.step(active)
            if self.steps_multiplier:
                stepped = MAPPOLagMultiplier.step_rule(lam, violation, out["cost_surrogate"].to(torch.float64),
                                                       multiplier_lr, multiplier_gamma)
                lam = torch.where(active, stepped, lam)
            return out, ()

        done = 0

        def go_on() -> bool:
            nonlocal done, kl, policy_now, pending
            done += 1
            passes.add_(active.to(torch.float64))
            if self.target_kl is not None or done == self.epochs:  # always so after the last pass
                handed_on = reuse and done < self.epochs  # the next pass's step may take it
                with torch.set_grad_enabled(handed_on):
                    policy_now = rows.dist_params(observation)
                pending = policy_now if handed_on else None
                with torch.no_grad():
                    now = gaussian_kl(old_loc, old_scale, *policy_now).mean(1)
                kl = torch.where(active, now, kl)
                if self.target_kl is not None:
                    active.logical_and_(now.to(torch.float64) <= self.target_kl)
            means.weight = active.to(torch.float64)
            return bool(active.any())

        report = run_passes(batch, step, passes=self.epochs, order=self._order(seeds, active), metrics=means,
                            go_on=go_on)
        self._write_back(rows, optimizer, value_norm)
        if self.steps_multiplier:
            for multiplier, value in zip(multipliers, lam, strict=True):
                multiplier.multiplier.copy_(value)
        with torch.no_grad():
            metrics = host_lists({
                **report.means,
                "Misc/Entropy": rows.entropy(),
                "Misc/Factor": factor.mean(1) if factor is not None else torch.ones(live, device=device),
                "Train/KL": kl,
                "Train/StopIter": passes,
                "Train/LagrangeMultiplier": lam,
            })
            if factor is not None:
                factor = factor * (gaussian_log_prob(action, *policy_now) - before).exp()
        return metrics, factor

class MAPPOUpdate(MultiAgentPPOUpdate):
    """MAPPO (Yu et al. 2022) with per-agent networks: independent clipped PPO per agent.

    The agents still go through the sequential round (SafePO's shared loop) but the factor is neither
    computed nor used, so the order does not matter: each agent's update depends on the batch and its own
    networks only. Costs are learned by the cost critics and logged, not optimised.
    """

    weighted = False


class HAPPOUpdate(MultiAgentPPOUpdate):
    """HAPPO (Kuba et al. 2022): each agent's clipped surrogate weighted by the earlier agents' ratio product.

    :math:`L^i = -\\mathbb E[M \\min(r^i A, \\mathrm{clip}(r^i, 1 \\pm \\epsilon) A)] - 0.01\\, H(\\pi^i)`
    with :math:`M` the product of the ratios of the agents updated before it in the round. Unconstrained;
    costs are only learned and logged.
    """

    weighted = True


class MAPPOLagUpdate(MultiAgentPPOUpdate):
    """MAPPO-Lagrangian (Gu et al. 2023): HAPPO's sequential update on :math:`A_r - \\lambda^i A^i_c`.

    Each agent has a :class:`~sg_torchrl.objectives.multi_agent.MAPPOLagMultiplier`, stepped after every
    minibatch step from the rollout's mean episode cost and the step's cost surrogate
    :math:`\\mathbb E[r^i A^i_c]` (see that class for the rule and for the paper's vs SafePO's initial
    value and step size).

    Keyword Args:
        multiplier_init (float): initial :math:`\\lambda`. Defaults to ``1e-5`` (paper table).
        multiplier_lr (float): multiplier step size. Defaults to ``0.78`` (paper table).
        **kwargs: see :class:`MultiAgentPPOUpdate` (``multipliers`` overrides the two options above).
    """

    weighted = True
    steps_multiplier = True

    def __init__(self, networks: MultiAgentNetworks | StackedMultiAgentNetworks, *, multiplier_init: float = 1e-5,
                 multiplier_lr: float = 0.78, **kwargs: Any) -> None:
        self.multiplier_init, self.multiplier_lr = multiplier_init, multiplier_lr
        super().__init__(networks, **kwargs)

    def _make_multiplier(self, cost_limit: float) -> Multiplier:
        return MAPPOLagMultiplier(cost_limit, init=self.multiplier_init, lr=self.multiplier_lr, gamma=self.gamma)


class MACPOUpdate(SeedBatchedRound):
    """MACPO's round: per agent in each seed's random order, a MACPO step on the factor-weighted surrogates,
    then critic epochs; the stage's agents of every seed at once.

    Args:
        networks: one team, or S seeds' stacked teams (:meth:`for_seeds`).

    Keyword Args:
        target_kl, cg_iters, line_search_steps, step_fraction, max_step_norm, initial_step_fraction,
            cg_damping, ...: the step's options (:class:`~sg_torchrl.objectives.multi_agent.MACPORule`, which
            holds their defaults and refuses bad values here, at construction).
        critic_epochs (int): critic passes of Adam per agent and round. Defaults to ``15`` (the paper's
            "SGD iters"; SafePO's script: one step at 5e-3).
        **kwargs: see :class:`~sg_torchrl.train.multi_agent_round.SeedBatchedRound` (``cost_limit``,
            ``gamma``, ``critic_lr`` 5e-4, ``max_grad_norm``, ``value_norm``, ``num_minibatches``, ...).

    Per-agent metrics: the step's (``Misc/CPOCase``, ``Misc/AcceptanceStep``, ``Misc/FinalStepNorm``,
    ``Misc/StepNormRaw``, ``Misc/Lambda_star``, ``Misc/Nu_star``, ``Misc/xHx``, ``Misc/gradient_norm``,
    ``Misc/cost_gradient_norm``, ``Train/KL`` (KL after the step, 0 when rejected),
    ``Loss/Loss_actor`` (minus the weighted reward surrogate before the step)), the critics'
    (``Loss/Loss_reward_critic``, ``Loss/Loss_cost_critic``, ``Misc/Reward_critic_norm``,
    ``Misc/Cost_critic_norm``), ``Misc/Entropy``, ``Misc/Ratio``, ``Misc/Factor`` and
    ``Misc/ConstraintValue`` (:math:`c`).
    """

    optimised = (("reward_value", "cost_value"),)
    _loss_weighted = False  # the agents' loss trains the critics only; the factor enters through the step

    def __init__(self, networks: MultiAgentNetworks | StackedMultiAgentNetworks, *, critic_epochs: int = 15,
                 **kwargs: Any) -> None:
        if critic_epochs < 1:
            raise ValueError(f"need critic_epochs >= 1, got {critic_epochs}.")
        self.step_options = {name: kwargs.pop(name) for name in [*kwargs] if name in _STEP_OPTIONS}
        StackedMACPOStep(None, **self.step_options)  # refuses bad options now, not at the first stage
        kwargs["entropy_coeff"] = 0.0  # the critic losses only; the CPO step has no entropy term
        super().__init__(networks, **kwargs)
        self.critic_epochs = int(critic_epochs)

    def cost_violations(self, seeds: Tensor, agents: Tensor, costs: Tensor) -> list[float]:
        """:math:`c = (J_c - d)(1 - \\gamma)` per row, with :math:`J_c - d` from the agent's multiplier (which holds the limit)."""
        return [self.team_multipliers[int(s)][int(a)].violation(float(costs[i, int(a)])) * (1.0 - self.gamma)
                for i, (s, a) in enumerate(zip(seeds, agents))]

    def _stage(self, seeds: Tensor, agents: Tensor, fields: dict[str, Tensor], factor: Tensor | None,
               costs: Tensor) -> tuple[dict[str, list[float]], Tensor | None]:
        batch = self._stage_data(seeds, agents, fields, factor)
        data = batch.fields()
        rows = self.networks.agent_rows(seeds, agents, flat_actor=True)
        observation, action = data["observation"], data["action"]
        with torch.no_grad():
            before = gaussian_log_prob(action, *rows.dist_params(observation))
        c = self.cost_violations(seeds, agents, costs)
        weight = data["factor"]
        step = StackedMACPOStep(rows, **self.step_options)
        step_metrics = step.step(data, weight * data["advantage"], weight * data["cost_advantage"],
                                 torch.tensor(c, dtype=torch.float64))
        with torch.no_grad():
            after = gaussian_log_prob(action, *rows.dist_params(observation))
            ratio = (after - data["action_log_prob"].squeeze(-1)).exp().mean(1)
        optimizer = self._optimizer(rows, seeds, agents)
        value_norm = self._value_norm(seeds, agents)
        critic_metrics = self._critic_passes(rows, batch, optimizer, value_norm, self.critic_epochs, seeds)
        self._write_back(rows, optimizer, value_norm)
        with torch.no_grad():
            metrics = {name: [v if v == v else None for v in value]
                       for name, value in host_lists(step_metrics).items()}
            metrics.update(host_lists({**critic_metrics, "Misc/Entropy": rows.entropy(), "Misc/Ratio": ratio,
                                       "Misc/Factor": factor.mean(1)}))
            metrics["Misc/ConstraintValue"] = c
            factor = factor * (after - before).exp()
        return metrics, factor
