"""Per-agent reward and cost advantages, and one agent's flat view of a group batch.

Every agent has its own reward critic and cost critic, so each gets its own Generalized Advantage
Estimates (Schulman et al. 2016) of the team reward and of its own cost. Both are the single-agent
factories :func:`~sg_torchrl.objectives.make_gae` / :func:`~sg_torchrl.objectives.make_cost_gae`
(the package's one GAE home) with every key under the group and TorchRL's
:class:`~torchrl.objectives.value.MultiAgentGAE` as the estimator: it broadcasts team-level
signals (a root ``"done"``, a shared reward) along the agent dim and leaves per-agent ones
(``("agents", "cost")``, ``("agents", "done")``) as they are. Termination stops the bootstrap,
truncation bootstraps from the critic at the final state (the paper's, and TorchRL's, handling;
SafePO's multi-agent scripts treat time-limit ends as terminal, ``use_proper_time_limits=False``).

Standardisation: SafePO's multi-agent trainers standardise **both** advantages, per agent, over
the whole batch (unlike its single-agent buffer, which only centres the cost advantage); that is
:class:`~torchrl.objectives.value.MultiAgentGAE`'s ``average_gae=True`` (mean / std over batch and
time, agent dim excluded, std floored at 1e-4 where SafePO adds 1e-5 or 1e-8). The value targets are
computed before the standardisation.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.objectives.value import MultiAgentGAE

from sg_torchrl.objectives.value import make_cost_gae, make_gae

__all__ = ["AGENT_VIEW_KEYS", "agent_view", "make_multi_agent_cost_gae", "make_multi_agent_gae"]


def make_multi_agent_gae(
    reward_critic: TensorDictModuleBase,
    *,
    group: str = "agents",
    gamma: float = 0.99,
    lmbda: float = 0.95,
    standardize: bool = True,
    **gae_kwargs: Any,
) -> MultiAgentGAE:
    """Each agent's reward GAE: reads ``("next", group, "reward")`` and the group's done flags.

    Writes ``(group, "advantage")`` and ``(group, "value_target")`` ``[*B, T, A, 1]`` from the
    group critic's ``(group, "state_value")`` (e.g. :attr:`MultiAgentNetworks.reward_critic`).
    Remap with ``.set_keys(...)`` (e.g. ``done="done"`` for team-level flags only).

    Keyword Args:
        group (str): the group key. Defaults to ``"agents"``.
        gamma (float): defaults to ``0.99`` (paper).
        lmbda (float): defaults to ``0.95`` (paper).
        standardize (bool): per-agent standardisation of the advantage (SafePO multi-agent).
            Defaults to ``True``.
        **gae_kwargs: forwarded to :class:`~torchrl.objectives.value.MultiAgentGAE`
            (``time_dim``, ``device``, ...).
    """
    return make_gae(reward_critic, gamma=gamma, lmbda=lmbda, group=group, estimator=MultiAgentGAE,
                    average_gae=standardize, **gae_kwargs)


def make_multi_agent_cost_gae(
    cost_critic: TensorDictModuleBase,
    *,
    group: str = "agents",
    gamma: float = 0.99,
    lmbda: float = 0.95,
    standardize: bool = True,
    **gae_kwargs: Any,
) -> MultiAgentGAE:
    """Each agent's cost GAE: reads ``("next", group, "cost")`` (the agent's own cost).

    Writes ``(group, "cost_advantage")`` and ``(group, "cost_value_target")`` from
    ``(group, "cost_value")``. Same options as :func:`make_multi_agent_gae`; the cost advantage is
    standardised too by default (SafePO's multi-agent trainers).
    """
    return make_cost_gae(cost_critic, gamma=gamma, lmbda=lmbda, group=group, estimator=MultiAgentGAE,
                         average_gae=standardize, **gae_kwargs)


#: Group entries an agent's update reads (``state_value`` / ``cost_value`` only with value clipping).
AGENT_VIEW_KEYS: tuple[str, ...] = (
    "observation", "action", "action_log_prob", "advantage", "value_target", "cost_advantage", "cost_value_target",
)


def agent_view(
    data: TensorDictBase,
    agent: int,
    *,
    group: str = "agents",
    keys: Sequence[str] = AGENT_VIEW_KEYS,
    root_keys: Sequence[NestedKey] = ("state",),
) -> TensorDict:
    """Agent ``agent``'s slice of a group batch as a flat single-agent TensorDict.

    ``data`` has batch ``[*B]`` (e.g. ``[N, T]``) and holds ``(group, key)`` entries with the agent
    dim right after the batch dims (``[*B, A, ...]``). The result has batch ``[prod(B)]`` and holds
    ``key`` (agent ``agent``'s entry, agent dim removed) for every ``key`` in ``keys`` and the root
    entries ``root_keys`` (the global ``"state"`` of the centralised critics). Entries are views
    where the layout allows, not copies.

    Raises:
        KeyError: if a requested entry is missing.
    """
    dim = data.batch_dims
    out = {}
    for key in keys:
        value = data.get((group, key), None)
        if value is None:
            raise KeyError(f"agent_view: {(group, key)!r} is not in the batch (run the GAEs first?).")
        out[key] = value.select(dim, agent)
    for key in root_keys:
        value = data.get(key, None)
        if value is None:
            raise KeyError(f"agent_view: {key!r} is not in the batch.")
        out[key] = value
    return TensorDict(out, batch_size=data.batch_size).reshape(-1)
