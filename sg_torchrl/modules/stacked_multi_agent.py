"""Seed-stacked multi-agent networks: S seeds' teams held in ``(S, A, ...)`` tensors, acting in one call.

A multi-agent seed group (:mod:`sg_torchrl.train.multi_agent_group`) trains S runs of a team whose every
agent has its own actor, reward critic and cost critic (:class:`~sg_torchrl.modules.MultiAgentNetworks`).
:class:`StackedMultiAgentNetworks` keeps every parameter of the S teams in one tensor per layer with a
leading seed and agent dimension: layer ``l`` of the actors is a weight ``(S, A, out, in)`` and a bias
``(S, A, out)``, the Gaussian heads' ``log_std`` one ``(S, A, Da)`` tensor (an agent with fewer actuators
leaves its padding slots unused), and likewise for both critics. Each seed's
:class:`~sg_torchrl.modules.MultiAgentNetworks` (:attr:`StackedMultiAgentNetworks.teams`) stays a module
of its own whose parameters are **views** of its rows, so what a seed's round or checkpoint does to its
team is done to the stack, and a seed is still its single-seed run's module (same names, same state dict).
The teams are built one per seed after ``torch.manual_seed(seed)`` (:func:`sg_torchrl.seeding.seed_torch`),
so seed ``s`` starts from its single-seed initialisation; :meth:`StackedMultiAgentNetworks.from_teams`
moves their values into the stack.

:class:`StackedMultiAgentPolicy` is every seed's team actor as the one TensorDict policy of the group's
batched env: one call per collection step for all ``S * N`` simulators. Seed ``s``'s action noise is
drawn from its own ``torch.Generator`` (:attr:`StackedMultiAgentPolicy.generators`) with the shape and in
the order its single-seed run draws from the global RNG (``IndependentNormal.rsample``:
``empty((N, A, Da)).normal_()``), started from the state that run's global RNG has after its networks
are built, so the numbers are the same. Everything but the matrix products is computed on the
stacked ``(S, N, A, Da)`` tensors at once, with the formulas of the per-agent modules (``masked_fill``
of the padding, the head's scale :func:`~sg_torchrl.modules.multi_agent.agent_gaussian_scale`, ``Normal.log_prob``
summed over action dims as :func:`~sg_torchrl.modules.gaussian.gaussian_log_prob` writes it).

**Why the matrix products go slice by slice.** Each ``(seed, agent)`` layer is applied with
``torch.addmm`` on its slice, the call ``nn.Linear`` makes in the per-agent module. A batched
``torch.baddbmm`` over the ``S * A`` slices rounds differently for small layers (measured on the
2-core CPU kind: 16-unit layers at 2 samples, 1 or 3 outputs at 1 sample, about 1e-7 apart), and a run
must stay its single-seed run and the recorded golden numbers bit for bit; the simulators are chaotic,
so 1e-7 in an action becomes a different trajectory. The loop is the few ``addmm`` calls per layer; the
TensorDict plumbing, distribution and random-state work it replaces was the per-seed cost.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn, Tensor

from sg_torchrl.modules.gaussian import gaussian_entropy, gaussian_log_prob
from sg_torchrl.modules.multi_agent import MultiAgentNetworks, agent_gaussian_scale

__all__ = ["AgentRows", "StackedMultiAgentNetworks", "StackedMultiAgentPolicy"]

#: The three per-agent networks of a team, by their attribute on MultiAgentNetworks.
NETWORKS = ("policy", "reward_value", "cost_value")
#: A Normal's entropy less its log-scale, per action dim.


def _linear_layers(net: nn.Module) -> list[nn.Linear]:
    return [module for module in net.modules() if isinstance(module, nn.Linear)]


def _stack_into(params: Sequence[Sequence[nn.Parameter]], pad_to: int | None = None) -> Tensor:
    """One ``(S, A, *shape)`` tensor holding ``params[s][a]``; each parameter becomes a view of its row.

    ``pad_to``: the last dim of the stack when the agents' parameters differ in length there (``log_std``);
    the parameter is then a view of its first slots, the rest stays zero.
    """
    first = params[0][0]
    shape = (*first.shape[:-1], pad_to) if pad_to is not None else tuple(first.shape)
    stack = first.new_zeros(len(params), len(params[0]), *shape)
    with torch.no_grad():
        for s, row in enumerate(params):
            for a, param in enumerate(row):
                view = stack[s, a] if pad_to is None else stack[s, a, ..., : param.shape[-1]]
                if view.shape != param.shape:
                    raise ValueError(f"seed {s} agent {a}: parameter of shape {tuple(param.shape)}, the others "
                                     f"{tuple(view.shape)}")
                view.copy_(param)
                param.data = view  # the same Parameter (optimisers keep it), now a view of the stack
    return stack


class StackedMultiAgentNetworks:
    """S seeds' team networks in ``(S, A, ...)`` tensors; see the module docstring.

    Attributes:
        teams: seed ``s``'s :class:`~sg_torchrl.modules.MultiAgentNetworks`, its parameters views of the stack.
        weights, biases: per network of :data:`NETWORKS`, per ``Linear`` layer, ``(S, A, out, in)`` and
            ``(S, A, out)``.
        log_std: ``(S, A, Da)``, the actors' heads (padding slots unused).
    """

    def __init__(self, teams: Sequence[MultiAgentNetworks]) -> None:
        if not teams:
            raise ValueError("StackedMultiAgentNetworks needs at least one team")
        sizes = {team.action_sizes for team in teams}
        if len(sizes) != 1:
            raise ValueError(f"the teams differ in their agents' action sizes: {sorted(sizes)}")
        self.teams = list(teams)
        self.weights: dict[str, list[Tensor]] = {}
        self.biases: dict[str, list[Tensor]] = {}
        for name in NETWORKS:
            layers = [[_linear_layers(net) for net in getattr(team, name).mlp.agent_networks] for team in teams]
            depth = len(layers[0][0])
            self.weights[name] = [_stack_into([[agent[l].weight for agent in seed] for seed in layers])
                                  for l in range(depth)]
            self.biases[name] = [_stack_into([[agent[l].bias for agent in seed] for seed in layers])
                                 for l in range(depth)]
        heads = [team.policy.heads for team in teams]
        self.log_std = _stack_into([[head.log_std for head in seed] for seed in heads],
                                   pad_to=max(teams[0].action_sizes))
        head = heads[0][0]
        self.std_x_coef, self.std_y_coef = head.std_x_coef, head.std_y_coef
        self.mask = teams[0].policy.mask  # (A, Da): True on each agent's real action slots
        # (bias, weight.t()) views of every actor layer per seed and agent, taken once (the stacks stay in place)
        policy = list(zip(self.biases["policy"], self.weights["policy"]))
        self._actor_layers = [[[(bias[s, a], weight[s, a].t()) for bias, weight in policy]
                               for a in range(self.n_agents)] for s in range(self.num_seeds)]

    @property
    def num_seeds(self) -> int:
        return len(self.teams)

    @property
    def device(self) -> torch.device:
        """Where the stacks live (the teams' parameters: a trainer moves its teams to ``cfg.device`` first)."""
        return self.log_std.device

    @property
    def n_agents(self) -> int:
        return self.teams[0].n_agents

    def tensors(self) -> list[Tensor]:
        """Every stacked tensor (each seed's parameters are its rows)."""
        return [*(t for name in NETWORKS for t in (*self.weights[name], *self.biases[name])), self.log_std]

    @torch.no_grad()
    def finite_seeds(self) -> Tensor:
        """``(S,)`` bool: which seeds' parameters are all finite (one check per stacked tensor)."""
        finite = torch.ones(self.num_seeds, dtype=torch.bool, device=self.device)
        for tensor in self.tensors():
            finite &= torch.isfinite(tensor.reshape(self.num_seeds, -1)).all(1)
        return finite

    @torch.no_grad()
    def actor_loc(self, observation: Tensor, seeds: Sequence[int]) -> Tensor:
        """The actors' means of the seeds ``seeds``: ``observation`` ``(S, N, A, D)`` to ``(S, N, A, Da)``.

        Seed ``s``'s agent ``a`` reads ``observation[s, :, a]``; rows of seeds not in ``seeds`` are zeros.
        Padding slots are 0. Bit for bit the per-agent module's output (see the module docstring).
        """
        num, n, agents = observation.shape[0], observation.shape[1], observation.shape[2]
        out = observation.new_zeros(num, agents, n, self.weights["policy"][-1].shape[-2])
        outputs = out.unbind(0)
        for s in seeds:
            for x, layers, result in zip(observation[s].unbind(1), self._actor_layers[s], outputs[s].unbind(0)):
                for bias, weight_t in layers[:-1]:
                    x = torch.addmm(bias, x, weight_t).relu_()
                bias, weight_t = layers[-1]
                torch.addmm(bias, x, weight_t, out=result)
        return out.transpose(1, 2).masked_fill(~self.mask, 0.0)

    def tensors_of(self, name: str) -> list[Tensor]:
        """Network ``name``'s stacked tensors in its modules' ``parameters()`` order (the actor's ``log_std`` last)."""
        tensors = [t for pair in zip(self.weights[name], self.biases[name]) for t in pair]
        return [*tensors, self.log_std] if name == "policy" else tensors

    def agent_rows(self, seeds: Tensor, agents: Tensor, *, flat_actor: bool = False) -> AgentRows:
        """Trainable copies of the networks of agent ``agents[i]`` of seed ``seeds[i]``, one row each
        (``flat_actor``: the actor's as one ``(R, P)`` buffer, see :class:`AgentRows`)."""
        return AgentRows(self, seeds, agents, flat_actor=flat_actor)

    @torch.no_grad()
    def actor_scale(self) -> Tensor:
        """The heads' scales, ``(S, 1, A, Da)``: :math:`\\mathrm{sigmoid}(\\ell / x)\\, y`, 1 on padding slots."""
        return agent_gaussian_scale(self.log_std, self.std_x_coef, self.std_y_coef, self.mask).unsqueeze(1)


class StackedMultiAgentPolicy(TensorDictModuleBase):
    """Every seed's team actor as one TensorDict policy of the group's batched env (what the collector calls).

    Reads ``(group, "observation")`` of the ``S * N`` simulators (seed ``s``'s the ``s``-th block of
    ``num_envs``) and writes ``(group, "loc" | "scale" | "action" | "action_log_prob")``, seed ``s``'s noise
    from ``generators[s]`` (see the module docstring). Seeds in :attr:`frozen` act with zeros (``loc`` 0,
    ``scale`` 1, action 0, log-probability 0), draw no noise and are not computed: a diverged seed's
    actions may not be finite, which the env refuses.

    With the networks on another device than the env's observations (``--device cuda``), a step copies the
    observation and the noise (drawn on the CPU generators, so a run draws the same numbers on every
    device) to the networks' device once each, and its four outputs back in one tensor.

    Args:
        networks: the seeds' stacked teams.
        generators: one per seed, each at the state its seed's global RNG has after its team is built.
        num_envs: simulators per seed.
        group: the agents' group key.
    """

    def __init__(self, networks: StackedMultiAgentNetworks, generators: Sequence[torch.Generator], num_envs: int,
                 group: str = "agents") -> None:
        super().__init__()
        if len(generators) != networks.num_seeds:
            raise ValueError(f"expected {networks.num_seeds} generators (one per seed), got {len(generators)}")
        self.networks = networks
        self.generators = list(generators)
        self.num_envs = int(num_envs)
        self.in_keys = [(group, "observation")]
        self.out_keys = [(group, name) for name in ("loc", "scale", "action", "action_log_prob")]
        #: ``(S,)`` bool of the seeds acting with zeros, or ``None`` when every seed acts.
        self.frozen: Tensor | None = None

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        observation = tensordict.get(self.in_keys[0])
        seeds, device, host = self.networks.num_seeds, self.networks.device, observation.device
        observation = observation.reshape(seeds, self.num_envs, *observation.shape[1:]).to(device, non_blocking=True)
        live = list(range(seeds)) if self.frozen is None else [s for s in range(seeds) if not bool(self.frozen[s])]
        loc = self.networks.actor_loc(observation, live)
        scale = self.networks.actor_scale().expand_as(loc)
        idle = None
        if len(live) < seeds:
            idle = torch.ones(seeds, dtype=torch.bool)
            idle[live] = False
            idle = idle.to(device)
            scale = torch.where(idle.view(-1, 1, 1, 1), 1.0, scale)
        # on the generators' device, laid out as loc (the draws fill it in memory order, as a single run's do)
        on = self.generators[0].device
        noise = torch.zeros_like(loc, device=on) if idle is not None else torch.empty_like(loc, device=on)
        for s in live:  # each seed's block drawn as its own run draws it: one (N, A, Da) normal_
            noise[s].normal_(generator=self.generators[s])
        action = loc + noise.to(device, non_blocking=True) * scale  # Normal.rsample: loc + eps * scale
        log_prob = gaussian_log_prob(action, loc, scale)
        if idle is not None:
            log_prob = torch.where(idle.view(-1, 1, 1), 0.0, log_prob)
        if device != host:  # the step's one copy back: what the env steps with and the batch keeps
            width = loc.shape[-1]
            packed = torch.cat((loc, scale, action, log_prob.unsqueeze(-1)), dim=-1).to(host)
            loc, scale, action, log_prob = packed.split((width, width, width, 1), dim=-1)
            log_prob = log_prob.squeeze(-1)
        for key, value in zip(self.out_keys, (loc, scale, action, log_prob)):
            tensordict.set(key, value.reshape(-1, *value.shape[2:]))
        return tensordict


class AgentRows:
    """One agent per row: trainable ``(R, ...)`` copies of the ``(seeds[i], agents[i])`` rows of a stack.

    The working set of a seed-batched multi-agent round (:mod:`sg_torchrl.train.multi_agent_round`):
    at stage ``k`` of a round, seed ``s`` updates agent ``order[s, k]``, so the round gathers those rows of
    every stacked tensor (:meth:`StackedMultiAgentNetworks.agent_rows`), trains them as leaf tensors with a
    leading row dimension (one optimiser step moves every row) and writes them back (:meth:`write_back`).
    Row ``i`` computes what agent ``agents[i]``'s own modules compute (``nn.Linear`` layers with ReLU
    between them, the head's ``sigmoid`` scale, 0 / 1 on the padding slots). The matrix products go row by
    row with ``addmm``, the call of ``nn.Linear``, for the reason :class:`StackedMultiAgentNetworks` gives: a
    batched ``baddbmm`` rounds a 1-output layer (the critics' heads) differently for 1 and for 2 rows, and
    a row must compute the same numbers whatever the number of rows.

    With ``flat_actor`` the actors' parameters are the rows of one ``(R, P)`` leaf, :attr:`flat_actor`, read
    through views at every evaluation: the :class:`~sg_torchrl.objectives.stacked_trust_region.StackedActor`
    a trust-region step moves (MACPO's), with :meth:`actor_parameters`, :meth:`dist_params` and
    :meth:`actor_rows`.
    """

    def __init__(self, networks: StackedMultiAgentNetworks | None, seeds: Tensor, agents: Tensor, *,
                 flat_actor: bool = False, _like: AgentRows | None = None, _actor: Tensor | None = None) -> None:
        self.seeds, self.agents = seeds, agents
        if _like is not None:  # a copy of some rows' actor (actor_rows: ``seeds`` are positions in _like)
            self.depth, self._shapes, self.mask = _like.depth, _like._shapes, _like.mask[seeds]
            self.std_x_coef, self.std_y_coef = _like.std_x_coef, _like.std_y_coef
            self._groups, self.flat_actor = {}, _actor
            return
        self.depth = {name: len(networks.weights[name]) for name in NETWORKS}
        self._groups = {name: [t[seeds, agents].requires_grad_(not (flat_actor and name == "policy"))
                               for t in networks.tensors_of(name)] for name in NETWORKS}
        self._shapes = [tuple(t.shape[1:]) for t in self._groups["policy"]]
        self.flat_actor = None
        if flat_actor:
            self.flat_actor = torch.cat([t.reshape(len(seeds), -1) for t in self._groups.pop("policy")], 1)
            self.flat_actor.requires_grad_()
        self.std_x_coef, self.std_y_coef = networks.std_x_coef, networks.std_y_coef
        self.mask = networks.mask[agents]

    @property
    def num_seeds(self) -> int:
        """R, the rows (a trust-region step calls them seeds)."""
        return len(self.seeds)

    def tensors(self, name: str) -> list[Tensor]:
        """Network ``name``'s tensors of every row, in :meth:`StackedMultiAgentNetworks.tensors_of` order."""
        if name == "policy" and self.flat_actor is not None:
            sizes = [math.prod(shape) for shape in self._shapes]
            return [part.view(-1, *shape) for part, shape in zip(self.flat_actor.split(sizes, 1), self._shapes)]
        return self._groups[name]

    def actor_parameters(self) -> list[Tensor]:
        """The leaf the trust-region step differentiates: :attr:`flat_actor` (``flat_actor=True`` only)."""
        return [self.flat_actor]

    def actor_rows(self, rows: Tensor) -> AgentRows:
        """The actors of the rows ``rows`` alone, on a copy of their :attr:`flat_actor` rows (``rows`` may live on
        the networks' device, a line search's indices: the agents are looked up there, without a read back)."""
        agents = self.agents.to(rows.device, non_blocking=True)[rows]
        return AgentRows(None, rows, agents, _like=self, _actor=self.flat_actor.detach()[rows].clone())

    def zero_grad(self) -> None:
        for name in NETWORKS:
            for tensor in ([self.flat_actor] if name == "policy" and self.flat_actor is not None else self._groups[name]):
                tensor.grad = None

    def _mlp(self, name: str, x: Tensor) -> Tensor:
        """Network ``name`` of every row on its inputs ``x (R, N, in)``: ``addmm`` per row and layer (see the class)."""
        tensors = [t.unbind(0) for t in self.tensors(name)[: 2 * self.depth[name]]]
        outputs = []
        for row, value in enumerate(x.unbind(0)):
            for layer in range(self.depth[name]):
                weight, bias = tensors[2 * layer][row], tensors[2 * layer + 1][row]
                value = torch.addmm(bias, value, weight.t())
                if layer < self.depth[name] - 1:
                    value = value.relu_()  # in place on the product (its backward needs the result only)
            outputs.append(value)
        return torch.stack(outputs)

    def std(self) -> Tensor:
        """``(R, 1, Da)``: each row's scale, 1 on its padding slots."""
        return agent_gaussian_scale(self.tensors("policy")[-1], self.std_x_coef, self.std_y_coef, self.mask).unsqueeze(1)

    def dist_params(self, observation: Tensor) -> tuple[Tensor, Tensor]:
        """``observation (R, N, D)`` to the policy's ``loc (R, N, Da)`` (0 on padding) and ``scale (R, 1, Da)``."""
        loc = self._mlp("policy", observation).masked_fill(~self.mask.unsqueeze(1), 0.0)
        return loc, self.std()

    def entropy(self) -> Tensor:
        """``(R,)``: each row's policy entropy over its real action slots (the same in every state)."""
        return gaussian_entropy(self.std().squeeze(1), self.mask)

    def critic(self, state: Tensor) -> Tensor:
        """The reward critics on ``state (R, N, Ds)``: ``(R, N, 1)``."""
        return self._mlp("reward_value", state)

    def cost_critic(self, state: Tensor) -> Tensor:
        """The cost critics on ``state (R, N, Ds)``: ``(R, N, 1)``."""
        return self._mlp("cost_value", state)

    @torch.no_grad()
    def write_back(self, networks: StackedMultiAgentNetworks) -> None:
        """Copy the rows into the stack they were gathered from (each seed's team sees them)."""
        for name in NETWORKS:
            for target, rows in zip(networks.tensors_of(name), self.tensors(name), strict=True):
                target[self.seeds, self.agents] = rows

