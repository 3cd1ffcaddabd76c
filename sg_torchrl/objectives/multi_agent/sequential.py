"""The sequential per-agent update shared by HAPPO, MAPPO-Lag, MACPO (and MAPPO).

Kuba et al. 2022 ("Trust Region Policy Optimisation in Multi-Agent Reinforcement Learning",
ICLR 2022, https://arxiv.org/abs/2109.11251) show with the multi-agent advantage decomposition
that updating agents *one after another* in a random order
:math:`i_{1:n}`, each maximising

.. math::

    \\mathbb E\\left[ M^{i_{1:m-1}} \\min\\big(r^{i_m} A,\\ \\mathrm{clip}(r^{i_m}, 1 \\pm \\epsilon) A\\big) \\right],
    \\qquad M^{i_{1:m-1}} = \\prod_{k < m} \\frac{\\bar\\pi^{i_k}(a^{i_k} | o^{i_k})}{\\pi^{i_k}(a^{i_k} | o^{i_k})},

improves the joint policy monotonically: :math:`M` corrects the joint advantage for the updates
the earlier agents of the round already made (:math:`\\bar\\pi` their new, :math:`\\pi` their old
policy). Gu et al. 2023 ("Safe multi-agent reinforcement learning for multi-robot control",
Artificial Intelligence; MACPO and MAPPO-Lagrangian) use the same scheme for the cost surrogate.

:class:`SequentialAgentUpdate` is that scheme once, independent of what an agent's update is: it
draws the permutation, keeps the running factor (a per-sample tensor, detached), hands it to the
caller's per-agent update and multiplies in the updated agent's ratio afterwards. HAPPO and
MAPPO-Lag plug in clipped-PPO epochs, MACPO a CPO step; MAPPO runs through it with
``weighted=False`` (the factor stays 1 and no ratio is computed). The seed-batched round of MAPPO,
HAPPO and MAPPO-Lag (:class:`~sg_torchrl.objectives.multi_agent.MultiAgentPPOUpdate`) runs the same scheme
for S seeds at once, with one order per seed; :func:`episode_costs` and :func:`round_metrics` serve both.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from sg_torchrl import seeding

__all__ = ["AgentStage", "SequentialAgentUpdate", "SequentialResult", "episode_costs", "round_metrics"]

#: ``update_agent(agent, factor) -> metrics``: one agent's whole update for the round.
UpdateAgent = Callable[[int, Tensor], dict[str, float]]
#: ``log_prob(agent) -> [B]``: the agent's log-probability of its own batch actions under its current policy.
LogProb = Callable[[int], Tensor]


@dataclass(frozen=True)
class AgentStage:
    """One stage of a round: the agent updated, the factor it was given and its metrics."""

    agent: int
    factor: Tensor
    metrics: dict[str, float]


@dataclass
class SequentialResult:
    """A round: :attr:`stages` in update order and the factor after the last agent."""

    stages: list[AgentStage] = field(default_factory=list)
    final_factor: Tensor | None = None

    @property
    def order(self) -> list[int]:
        return [stage.agent for stage in self.stages]


class SequentialAgentUpdate:
    """Random-order, one-agent-at-a-time update with HAPPO's running ratio product.

    Each call to :meth:`run` is one round: draw a permutation of the agents (``shuffle=True``,
    from ``generator``), start with :math:`M = 1` per sample, and for each agent :math:`i` in turn

    1. ``log_prob(i)`` (before; only when ``weighted``),
    2. ``update_agent(i, M)`` (the algorithm's per-agent update, with :math:`M` detached),
    3. ``log_prob(i)`` (after) and :math:`M \\leftarrow M \\cdot \\exp(\\log\\bar\\pi^i - \\log\\pi^i)`.

    The "old" log-probability is taken just before the agent's update (SafePO does the same); on
    on-policy data it equals the behaviour log-probability. ``log_prob`` must return the log-density
    of the agent's *joint* action (summed over action dims), so the ratio is the product over action
    dims as in SafePO and the HAPPO paper.

    Args:
        n_agents (int): number of agents.

    Keyword Args:
        weighted (bool): maintain the factor (HAPPO, MAPPO-Lag, MACPO). ``False`` (MAPPO) hands
            every agent :math:`M = 1` and skips the log-probabilities. Defaults to ``True``.
        shuffle (bool): random permutation per round (the paper); ``False`` keeps ``0..n-1``.
            Defaults to ``True``.
        generator (torch.Generator, optional): source of the permutations (checkpoint its state
            for bit-exact resumes). Defaults to a fresh generator seeded with 0 (the ``minibatches``
            stream of seed 0, :mod:`sg_torchrl.seeding`).
    """

    def __init__(
        self,
        n_agents: int,
        *,
        weighted: bool = True,
        shuffle: bool = True,
        generator: torch.Generator | None = None,
    ) -> None:
        if n_agents < 1:
            raise ValueError(f"n_agents must be >= 1, got {n_agents}.")
        self.n_agents = int(n_agents)
        self.weighted = bool(weighted)
        self.shuffle = bool(shuffle)
        self.generator = generator if generator is not None else seeding.generator(0, seeding.Purpose.MINIBATCHES)

    def permutation(self) -> list[int]:
        """The next round's agent order."""
        if not self.shuffle:
            return list(range(self.n_agents))
        return torch.randperm(self.n_agents, generator=self.generator).tolist()

    def run(self, update_agent: UpdateAgent, log_prob: LogProb, batch_size: int) -> SequentialResult:
        """One round over all agents.

        Args:
            update_agent: ``(agent, factor) -> metrics``, the agent's update; ``factor`` has shape
                ``[batch_size]`` and no graph.
            log_prob: ``agent -> [batch_size]`` log-probabilities of the agent's batch actions
                under its current parameters (called under :func:`torch.no_grad`).
            batch_size (int): number of samples (the factor's length).

        Returns:
            A :class:`SequentialResult` with one :class:`AgentStage` per agent, in update order.
        """
        factor = torch.ones(batch_size)
        result = SequentialResult()
        for agent in self.permutation():
            before = self._log_prob(log_prob, agent) if self.weighted else None
            if before is not None and factor.dtype != before.dtype:
                factor = factor.to(device=before.device, dtype=before.dtype)
            metrics = update_agent(agent, factor)
            result.stages.append(AgentStage(agent, factor, metrics))
            if before is not None:
                factor = factor * (self._log_prob(log_prob, agent) - before).exp()
        result.final_factor = factor
        return result

    def _log_prob(self, log_prob: LogProb, agent: int) -> Tensor:
        with torch.no_grad():
            value = log_prob(agent).detach()
        if value.dim() != 1:
            raise ValueError(f"log_prob({agent}) must return a vector [batch], got shape {tuple(value.shape)}.")
        return value


def episode_costs(mean_episode_cost: float | Tensor, n_agents: int) -> list[float]:
    """:math:`J_c` per agent: one finite value for the team (every agent's), or one per agent."""
    value = torch.as_tensor(mean_episode_cost, dtype=torch.float64).detach().reshape(-1)
    if value.numel() == 1:
        value = value.expand(n_agents)
    if value.numel() != n_agents or not torch.isfinite(value).all():
        raise ValueError(f"mean_episode_cost must be one finite value or one per agent ({n_agents}), "
                         f"got {mean_episode_cost!r}.")
    return value.tolist()


def round_metrics(stages: Sequence[tuple[int, Mapping[str, float]]], multipliers: Sequence[float]) -> dict[str, float]:
    """A round's metrics from its stages ``(agent, metrics)`` in update order and the agents' multiplier values.

    ``Train/AgentOrder/agent<i>`` (the stage at which agent ``i`` was updated), each metric per agent as
    ``"<name>/agent<i>"`` and its mean over the agents under ``<name>``; ``Train/LagrangeMultiplier`` is the
    mean multiplier.
    """
    per_name: dict[str, list[float]] = defaultdict(list)
    metrics: dict[str, float] = {}
    for position, (agent, values) in enumerate(stages):
        metrics[f"Train/AgentOrder/agent{agent}"] = float(position)
        for name, value in values.items():
            per_name[name].append(float(value))
            metrics[f"{name}/agent{agent}"] = float(value)
    for name, values in per_name.items():
        metrics[name] = sum(values) / len(values)
    metrics["Train/LagrangeMultiplier"] = sum(multipliers) / len(multipliers)
    return metrics
