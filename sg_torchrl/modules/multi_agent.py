"""Per-agent actors and centralised critics for the safe multi-agent algorithms.

SafePO's multi-agent scripts (the networks behind the Safety-Gymnasium paper's MAPPO, HAPPO,
MAPPO-Lag and MACPO results, Ji et al. 2023) give **every agent its own actor, reward critic and
cost critic** (no parameter sharing, as HAPPO requires: Kuba et al. 2022 prove monotonic
improvement for heterogeneous agents). Actors see the agent's local observation; the critics are
centralised (Yu et al. 2022, MAPPO): they read the global ``"state"``.

The networks are TorchRL :class:`~torchrl.modules.MultiAgentMLP` s (``share_params=False``,
``centralized=False``), whose forward pass evaluates all agents at once with ``torch.vmap``. One
change is made, in :class:`PerAgentMLP`: each agent's parameters are **separate leaf tensors**
(``agent_networks[i]``, a plain :class:`~torchrl.modules.MLP`), stacked on the fly for the
vmapped group forward. :class:`~torchrl.modules.MultiAgentMLP` stores one stacked tensor per
layer instead, so an optimiser or a trust-region step could not touch one agent alone (Adam's
moments would keep moving the other agents' slices). The sequential update
(:mod:`sg_torchrl.train.multi_agent_updates`) needs exactly that: at each stage only one
agent's parameters change.

Heterogeneous partitions (e.g. Humanoid 9|8) are padded to the largest agent, as the env does:
an agent's observation is ``[..., :observation_size]`` then zeros (an MLP ignores zero inputs), and
its action ``[..., :action_size]`` then padding slots. On padding slots the policy outputs the
constant ``loc = 0``, ``scale = 1``: their log-probability terms are identical before and after an
update, so they cancel in every importance ratio, contribute nothing to the KL, and receive no
gradient.

Paper choices (Safety-Gymnasium paper, multi-agent hyper-parameters): MLP, ReLU, hidden
``[128, 128]``. The Gaussian head is SafePO's (the paper does not specify it): a state-independent
per-agent parameter :math:`\\ell` with :math:`\\sigma = \\mathrm{sigmoid}(\\ell / x) \\cdot y`,
:math:`x = 1`, :math:`y = 0.5`, :math:`\\ell_0 = 1` (initial :math:`\\sigma \\approx 0.366`, never
above 0.5). SafePO's LayerNorm / ELU / orthogonal initialisation details are not reproduced: the
MLPs use PyTorch's default ``Linear`` initialisation, like the single-agent networks.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn, Tensor
from torchrl.modules import IndependentNormal, MultiAgentMLP, ProbabilisticActor

from sg_torchrl.modules.direct import DirectTensorDictModule

__all__ = [
    "AgentGaussianHead",
    "MultiAgentGaussianPolicy",
    "MultiAgentNetworks",
    "MultiAgentStateValue",
    "PerAgentMLP",
    "agent_gaussian_scale",
    "make_multi_agent_networks",
]


class PerAgentMLP(MultiAgentMLP):
    """:class:`~torchrl.modules.MultiAgentMLP` without parameter sharing, one set of leaves per agent.

    Same constructor and group forward as ``MultiAgentMLP(..., share_params=False)`` (inputs
    ``[*B, n_agents, n_agent_inputs]``, outputs ``[*B, n_agents, n_agent_outputs]``, all agents in
    one vmapped call), but the parameters live in ``agent_networks[i]`` (a
    :class:`~torchrl.modules.MLP` per agent) and :attr:`params` stacks them for every forward. So
    ``agent_networks[i].parameters()`` are agent ``i``'s own leaves: an optimiser or a trust-region
    step over them changes agent ``i`` only, and ``agent_networks[i](x)`` evaluates one agent
    without computing the others.

    Args:
        n_agent_inputs (int): input size of each agent (padded to the largest agent).
        n_agent_outputs (int): output size of each agent.
        n_agents (int): number of agents.

    Keyword Args:
        centralized (bool): see :class:`~torchrl.modules.MultiAgentMLP`. Defaults to ``False``.
        **kwargs: forwarded to :class:`~torchrl.modules.MultiAgentMLP` (``num_cells``,
            ``activation_class``, ``depth``, ``device``, ...).
    """

    def __init__(
        self,
        n_agent_inputs: int,
        n_agent_outputs: int,
        n_agents: int,
        *,
        centralized: bool = False,
        **kwargs,
    ) -> None:
        if kwargs.pop("share_params", False):
            raise ValueError("PerAgentMLP never shares parameters; use MultiAgentMLP(share_params=True).")
        if not kwargs.pop("use_td_params", True):
            raise ValueError("PerAgentMLP keeps its parameters in agent_networks; use_td_params=False is not supported.")
        super().__init__(
            n_agent_inputs, n_agent_outputs, n_agents, centralized=centralized, share_params=False, **kwargs
        )

    def _make_params(self, agent_networks: list[nn.Module]) -> None:
        # Called by MultiAgentNetBase.__init__ instead of stacking the agents' parameters.
        self.agent_networks = nn.ModuleList(agent_networks)

    def forward(self, *inputs: Tensor) -> Tensor:
        """Each agent's network on its own slice of the input, outputs stacked along the agent dim.

        The parent vmaps one network over parameters stacked on every call (a TensorDict stack of
        every agent's leaves): with the 2-17 agents of the paper's tasks that stacking costs more
        than the networks themselves (about half of a multi-agent collection step measured on the
        2-core machine kind). A Python loop over the agents computes the same function (up to
        float rounding: ``addmm`` per agent instead of a batched matmul). Centralised networks
        (every agent reads the whole input) keep the parent's path.
        """
        if self.centralized:
            return super().forward(*inputs)
        x = torch.cat(inputs, -1) if len(inputs) > 1 else inputs[0]
        agent_dim = self.agent_dim if self.agent_dim >= 0 else x.ndim + self.agent_dim
        x = self._pre_forward_check(x)
        return torch.stack([net(x.select(agent_dim, i)) for i, net in enumerate(self.agent_networks)], agent_dim)

    @property
    def params(self) -> TensorDict:  # type: ignore[override]
        """The agents' parameters stacked along a leading agent dim (differentiable in every agent's leaves)."""
        return torch.stack([TensorDict.from_module(net) for net in self.agent_networks])

    def reset_parameters(self) -> None:
        """Re-initialises every agent's network (PyTorch's default ``Linear`` initialisation)."""
        for net in self.agent_networks:
            for module in net.modules():
                if module is not net and hasattr(module, "reset_parameters"):
                    module.reset_parameters()

    def get_stateful_net(self, copy: bool = True) -> nn.Module:
        raise NotImplementedError("PerAgentMLP's agents are ordinary modules already: use agent_networks[i].")

    def from_stateful_net(self, stateful_net: nn.Module) -> None:
        raise NotImplementedError("PerAgentMLP's agents are ordinary modules already: use agent_networks[i].")


def agent_gaussian_scale(log_std: Tensor, std_x_coef: float, std_y_coef: float, mask: Tensor | None = None) -> Tensor:
    """SafePO's multi-agent Gaussian scale :math:`\\sigma = \\mathrm{sigmoid}(\\ell / x)\\, y` of ``log_std``
    (:math:`\\ell`); with a ``mask`` (``True`` on real action slots) 1 on the padding slots.

    The one formula of :class:`AgentGaussianHead` and its seed-stacked copies, so they agree to the last bit.
    """
    std = torch.sigmoid(log_std / std_x_coef) * std_y_coef
    return std if mask is None else torch.where(mask, std, 1.0)


class AgentGaussianHead(nn.Module):
    """One agent's state-independent Gaussian scale and padding mask (SafePO's multi-agent head).

    :math:`\\sigma = \\mathrm{sigmoid}(\\ell / x)\\, y` per real action dim, with a learnable
    :math:`\\ell` (``log_std``, shape ``[action_size]``); on the ``padded_size - action_size``
    padding slots :meth:`forward` returns ``loc = 0`` and ``scale = 1`` (constants).

    Args:
        action_size (int): the agent's number of actuators.
        padded_size (int): the largest agent's action size (the group action's last dim).

    Keyword Args:
        init_log_std (float): :math:`\\ell_0`. Defaults to ``1.0`` (SafePO).
        std_x_coef (float): :math:`x`. Defaults to ``1.0`` (SafePO).
        std_y_coef (float): :math:`y`, the largest possible std. Defaults to ``0.5`` (SafePO).
    """

    mask: Tensor

    def __init__(
        self,
        action_size: int,
        padded_size: int,
        *,
        init_log_std: float = 1.0,
        std_x_coef: float = 1.0,
        std_y_coef: float = 0.5,
    ) -> None:
        super().__init__()
        if not 0 < action_size <= padded_size:
            raise ValueError(f"need 0 < action_size <= padded_size, got {action_size} and {padded_size}.")
        self.action_size = int(action_size)
        self.padded_size = int(padded_size)
        self.std_x_coef = float(std_x_coef)
        self.std_y_coef = float(std_y_coef)
        self.log_std = nn.Parameter(torch.full((action_size,), float(init_log_std)))
        mask = torch.zeros(padded_size, dtype=torch.bool)
        mask[:action_size] = True
        self.register_buffer("mask", mask, persistent=False)

    def std(self) -> Tensor:
        """The real dims' standard deviations, shape ``[action_size]``."""
        return agent_gaussian_scale(self.log_std, self.std_x_coef, self.std_y_coef)

    def padded_scale(self) -> Tensor:
        """The scale of every slot, shape ``[padded_size]`` (1 on padding slots)."""
        pad = self.padded_size - self.action_size
        return nn.functional.pad(self.std(), (0, pad), value=1.0)

    def forward(self, raw_loc: Tensor) -> tuple[Tensor, Tensor]:
        loc = raw_loc.masked_fill(~self.mask, 0.0)
        return loc, self.padded_scale().expand_as(loc)


class _AgentPolicy(nn.Module):
    """Agent ``i``'s policy alone: its MLP and head (the same modules the group policy uses)."""

    def __init__(self, net: nn.Module, head: AgentGaussianHead) -> None:
        super().__init__()
        self.net = net
        self.head = head

    def forward(self, observation: Tensor) -> tuple[Tensor, Tensor]:
        return self.head(self.net(observation))


class MultiAgentGaussianPolicy(nn.Module):
    """Every agent's diagonal-Gaussian policy: :class:`PerAgentMLP` means and per-agent heads.

    :meth:`forward` maps the group observation ``[*B, A, D]`` to ``loc`` and ``scale``
    ``[*B, A, Da]`` for all agents in one vmapped pass (collection); :meth:`agent` returns agent
    ``i``'s policy as a module of its own parameters only (updates).

    Args:
        observation_size (int): the (padded) per-agent observation size ``D``.
        action_sizes (sequence of int): each agent's number of actuators (``Da`` is the largest).
        hidden_sizes (sequence of int): hidden layers. Defaults to ``(128, 128)`` (paper).

    Keyword Args:
        activation_class (type): hidden activation. Defaults to :class:`torch.nn.ReLU` (paper).
        **head_kwargs: forwarded to :class:`AgentGaussianHead`.
    """

    def __init__(
        self,
        observation_size: int,
        action_sizes: Sequence[int],
        hidden_sizes: Sequence[int] = (128, 128),
        *,
        activation_class: type[nn.Module] = nn.ReLU,
        **head_kwargs,
    ) -> None:
        super().__init__()
        self.action_sizes = tuple(int(a) for a in action_sizes)
        padded = max(self.action_sizes)
        self.mlp = PerAgentMLP(
            observation_size, padded, len(self.action_sizes), num_cells=list(hidden_sizes),
            activation_class=activation_class,
        )
        self.heads = nn.ModuleList(AgentGaussianHead(a, padded, **head_kwargs) for a in self.action_sizes)
        self.register_buffer("mask", torch.stack([head.mask for head in self.heads]), persistent=False)
        self._agents = tuple(_AgentPolicy(net, head) for net, head in zip(self.mlp.agent_networks, self.heads))

    @property
    def n_agents(self) -> int:
        return len(self.action_sizes)

    def forward(self, observation: Tensor) -> tuple[Tensor, Tensor]:
        loc = self.mlp(observation).masked_fill(~self.mask, 0.0)
        scale = torch.stack([head.padded_scale() for head in self.heads]).expand_as(loc)
        return loc, scale

    def agent(self, index: int) -> nn.Module:
        """Agent ``index``'s policy, ``observation [*B, D] -> (loc, scale) [*B, Da]``; its parameters are that agent's only."""
        return self._agents[index]


class MultiAgentStateValue(nn.Module):
    """Every agent's centralised value of the global state, ``state [*B, S] -> [*B, A, 1]``.

    One :class:`PerAgentMLP` evaluated on the state broadcast to every agent (each agent has its
    own critic of the same global input, as in SafePO). :meth:`agent` is agent ``i``'s critic,
    ``state [*B, S] -> [*B, 1]``.
    """

    def __init__(
        self,
        state_size: int,
        n_agents: int,
        hidden_sizes: Sequence[int] = (128, 128),
        *,
        activation_class: type[nn.Module] = nn.ReLU,
    ) -> None:
        super().__init__()
        self.mlp = PerAgentMLP(state_size, 1, n_agents, num_cells=list(hidden_sizes), activation_class=activation_class)

    def forward(self, state: Tensor) -> Tensor:
        n_agents = self.mlp.n_agents
        return self.mlp(state.unsqueeze(-2).expand(*state.shape[:-1], n_agents, state.shape[-1]))

    def agent(self, index: int) -> nn.Module:
        return self.mlp.agent_networks[index]


class MultiAgentNetworks(nn.Module):
    """The actors and both centralised critics of a team, as TorchRL modules, group-wise and per agent.

    Group modules (collection and GAE), over TorchRL's multi-agent layout with group ``group``:

    * :attr:`actor`: :class:`~torchrl.modules.ProbabilisticActor` reading ``(group, "observation")``,
      writing ``(group, "loc")``, ``(group, "scale")``, ``(group, "action")`` ``[*B, A, Da]`` and
      ``(group, "action_log_prob")`` ``[*B, A]`` (an :class:`~torchrl.modules.IndependentNormal`
      per agent; actions are unbounded samples, as in SafePO);
    * :attr:`reward_critic` / :attr:`cost_critic`: read ``"state"``, write
      ``(group, "state_value")`` / ``(group, "cost_value")`` ``[*B, A, 1]``.

    Per-agent modules (the sequential update), over one agent's *view* (flat keys, see
    :func:`~sg_torchrl.objectives.multi_agent.agent_view`): :meth:`agent_actor` reads
    ``"observation"`` and writes ``"loc"``, ``"scale"``, ``"action"``, ``"action_log_prob"``;
    :meth:`agent_critic` / :meth:`agent_cost_critic` read ``"state"`` and write ``"state_value"`` /
    ``"cost_value"``. Their parameters are that agent's only, and they share them with the group
    modules. The state dict holds each parameter once (under ``policy``, ``reward_value``,
    ``cost_value``).

    Build with :func:`make_multi_agent_networks`.
    """

    def __init__(
        self,
        policy: MultiAgentGaussianPolicy,
        reward_value: MultiAgentStateValue,
        cost_value: MultiAgentStateValue,
        *,
        group: str = "agents",
    ) -> None:
        super().__init__()
        self.policy = policy
        self.reward_value = reward_value
        self.cost_value = cost_value
        self.group = group
        g = group
        # Wrappers are kept out of the module tree (plain tuples) so the state dict lists each
        # parameter once.
        self._group_modules = (
            _probabilistic_actor(policy, (g, "observation"), (g, "loc"), (g, "scale"), (g, "action")),
            DirectTensorDictModule(reward_value, in_keys=["state"], out_keys=[(g, "state_value")]),
            DirectTensorDictModule(cost_value, in_keys=["state"], out_keys=[(g, "cost_value")]),
        )
        self._agent_modules = tuple(
            (
                _probabilistic_actor(policy.agent(i), "observation", "loc", "scale", "action"),
                DirectTensorDictModule(reward_value.agent(i), in_keys=["state"], out_keys=["state_value"]),
                DirectTensorDictModule(cost_value.agent(i), in_keys=["state"], out_keys=["cost_value"]),
            )
            for i in range(policy.n_agents)
        )

    @property
    def n_agents(self) -> int:
        return self.policy.n_agents

    @property
    def action_sizes(self) -> tuple[int, ...]:
        return self.policy.action_sizes

    @property
    def actor(self) -> ProbabilisticActor:
        return self._group_modules[0]

    @property
    def reward_critic(self) -> TensorDictModule:
        return self._group_modules[1]

    @property
    def cost_critic(self) -> TensorDictModule:
        return self._group_modules[2]

    def agent_actor(self, index: int) -> ProbabilisticActor:
        return self._agent_modules[index][0]

    def agent_critic(self, index: int) -> TensorDictModule:
        return self._agent_modules[index][1]

    def agent_cost_critic(self, index: int) -> TensorDictModule:
        return self._agent_modules[index][2]


def _probabilistic_actor(
    module: nn.Module, observation: NestedKey, loc: NestedKey, scale: NestedKey, action: NestedKey
) -> ProbabilisticActor:
    return ProbabilisticActor(
        DirectTensorDictModule(module, in_keys=[observation], out_keys=[loc, scale]),
        in_keys=[loc, scale],
        out_keys=[action],
        distribution_class=IndependentNormal,
        return_log_prob=True,
        default_interaction_type="random",
    )


def make_multi_agent_networks(
    observation_size: int,
    action_sizes: Sequence[int],
    state_size: int,
    *,
    hidden_sizes: Sequence[int] = (128, 128),
    activation_class: type[nn.Module] = nn.ReLU,
    group: str = "agents",
    **head_kwargs,
) -> MultiAgentNetworks:
    """One actor, one reward critic and one cost critic per agent, no sharing.

    Args:
        observation_size (int): the padded per-agent observation size (the env's
            ``("agents", "observation")`` last dim).
        action_sizes (sequence of int): each agent's true number of actuators (the env's
            ``action_sizes``); the group action has ``max(action_sizes)`` slots.
        state_size (int): the global ``"state"`` size read by the centralised critics.

    Keyword Args:
        hidden_sizes (sequence of int): hidden layers of every network. Defaults to ``(128, 128)``
            (Safety-Gymnasium paper, multi-agent table).
        activation_class (type): defaults to :class:`torch.nn.ReLU` (paper).
        group (str): the agents' group key. Defaults to ``"agents"``.
        **head_kwargs: :class:`AgentGaussianHead` options (``init_log_std``, ``std_x_coef``,
            ``std_y_coef``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from sg_torchrl.modules import make_multi_agent_networks
        >>> nets = make_multi_agent_networks(observation_size=10, action_sizes=[3, 2], state_size=17)
        >>> td = TensorDict({"agents": {"observation": torch.randn(4, 2, 10)}, "state": torch.randn(4, 17)}, [4])
        >>> td = nets.actor(td); td = nets.reward_critic(td)
        >>> td["agents", "action"].shape, td["agents", "state_value"].shape
        (torch.Size([4, 2, 3]), torch.Size([4, 2, 1]))
    """
    n_agents = len(action_sizes)
    if n_agents < 1:
        raise ValueError("make_multi_agent_networks needs at least one agent.")
    policy = MultiAgentGaussianPolicy(
        observation_size, action_sizes, hidden_sizes, activation_class=activation_class, **head_kwargs
    )
    reward_value = MultiAgentStateValue(state_size, n_agents, hidden_sizes, activation_class=activation_class)
    cost_value = MultiAgentStateValue(state_size, n_agents, hidden_sizes, activation_class=activation_class)
    return MultiAgentNetworks(policy, reward_value, cost_value, group=group)
