"""The bookkeeping every multi-agent round shares: the mean episode cost per agent and a round's metrics.

The rounds (:class:`~sg_torchrl.objectives.multi_agent.seed_round.SeedBatchedRound`) update the agents one
after another in a random order (Kuba et al. 2022, "Trust Region Policy Optimisation in Multi-Agent
Reinforcement Learning", ICLR 2022); :func:`round_metrics` reports such a round under SafePO's names.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

__all__ = ["episode_costs", "round_metrics"]


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
