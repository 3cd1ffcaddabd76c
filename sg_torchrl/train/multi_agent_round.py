"""The seed-batched multi-agent round: S seeds' sequential rounds in one update call per stage (S >= 1).

Every algorithm of the Safety-Gymnasium paper's multi-agent benchmark updates the agents one at a time in
a random order, HAPPO's factor :math:`M` (the product of the ratios of the agents updated before) weighting
the later agents' surrogates (Kuba et al. 2022). :class:`SeedBatchedRound` is that round once, for S seeds'
stacked teams (:class:`~sg_torchrl.modules.stacked_multi_agent.StackedMultiAgentNetworks`; one team is
S = 1): each seed draws its own agent order from its own generator; at stage ``k`` the agents
``order[s, k]`` of every live seed are gathered into rows
(:class:`~sg_torchrl.modules.stacked_multi_agent.AgentRows`: parameters, and here their Adam moments,
PopArt statistics and multipliers), updated together by the subclass's :meth:`SeedBatchedRound._stage`
and written back; the factor then takes each row's ratio. Subclasses
(:mod:`sg_torchrl.train.multi_agent_updates`): the clipped-PPO epochs of MAPPO, HAPPO and MAPPO-Lag
(:class:`~sg_torchrl.train.multi_agent_updates.MultiAgentPPOUpdate`) and MACPO's CPO step and critic epochs
(:class:`~sg_torchrl.train.multi_agent_updates.MACPOUpdate`). The math is the objectives' (one agent's
:class:`~sg_torchrl.objectives.multi_agent.AgentObjective`, handed out by its
:class:`~sg_torchrl.objectives.multi_agent.AgentPPOLoss`; MACPO's step rule); the rounds are training
machinery (optimiser state, generators, the rows gathered and written back), so they live here. The single-seed pieces are
reused as they are: :class:`~sg_torchrl.train.seed_adam.SeedMaskedAdam` and its per-seed clip,
:class:`~sg_torchrl.train.fused.SeedShuffler` (each seed's generator), :class:`~sg_torchrl.train.fused.SeedBatch`
and :func:`~sg_torchrl.objectives.passes.run_passes`.

A seed's round state is written in a single team's checkpoint format (:meth:`SeedBatchedRound.seed_state_dict`:
per-agent ``torch.optim.Adam`` state dicts, the multipliers' and PopArt normalisers' module state dicts,
the generator), so checkpoints of the rounds before they were seed-batched load as they are.

**Device.** The round's state lives where the stacked networks do (``networks.device``): Adam's moments
and step counts, the PopArt statistics and the multipliers (moved there when the round is built), and the
stage's batch, factor, masks and metric sums. What stays on the host: the agent orders and the
generators, the seeds and agents a stage gathers (CPU index tensors), and :math:`J_c`. A stage reads back
once per pass (the KL stop's active seeds) and once for its metrics (:func:`host_lists`), never per
minibatch. :meth:`SeedBatchedRound.seed_state_dict` gives the state where it lives; a trainer copies it to
the CPU for its checkpoint.
"""

from __future__ import annotations

import abc
from collections import defaultdict
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import torch
from tensordict import TensorDictBase
from torch import nn, Tensor

from sg_torchrl import seeding
from sg_torchrl.modules.multi_agent import MultiAgentNetworks
from sg_torchrl.modules.stacked_multi_agent import AgentRows, StackedMultiAgentNetworks
from sg_torchrl.objectives.multi_agent.loss import AgentPPOLoss
from sg_torchrl.objectives.multi_agent.objective import AgentObjective, seed_popart
from sg_torchrl.objectives.multipliers import Multiplier, NoMultiplier
from sg_torchrl.objectives.passes import RowMeans, run_passes, whole_batch
from sg_torchrl.train.fused import SeedBatch, SeedShuffler
from sg_torchrl.train.seed_adam import clip_grad_norm_per_seed_, SeedMaskedAdam

__all__ = ["CRITIC_METRICS", "SeedBatchedRound", "episode_costs", "host_lists", "round_metrics"]

#: The critics' losses averaged over an agent's steps, by SafePO's metric names.
CRITIC_METRICS = {"Loss/Loss_reward_critic": "loss_critic", "Loss/Loss_cost_critic": "loss_cost_critic",
                  "Misc/Reward_critic_norm": "reward_norm", "Misc/Cost_critic_norm": "cost_norm"}
#: The batch fields of an agent's step (``state`` is the team's).
_FIELDS = ("observation", "state", "action", "action_log_prob", "advantage", "value_target", "cost_advantage",
           "cost_value_target")
_POPART = ("running_mean", "running_mean_sq", "debiasing_term")
_ADAM_GROUP = dict(weight_decay=0, amsgrad=False, maximize=False, foreach=None, capturable=False,
                   differentiable=False, fused=None, decoupled_weight_decay=False)
_CRITICS = ("reward_value", "cost_value")


class SeedBatchedRound(abc.ABC):
    """The sequential round of S seeds at once; see the module docstring. Subclasses implement :meth:`_stage`.

    Args:
        networks: one team (S = 1; call the round as ``update(batch, mean_episode_cost)``) or S seeds'
            stacked teams (:meth:`step_seeds`; built by :meth:`for_seeds` with one generator per seed).

    Keyword Args:
        cost_limit (float): :math:`d`. Defaults to ``25.0`` (paper).
        gamma (float): discount of the :math:`(1 - \\gamma)` constraint scaling. Defaults to ``0.99``.
        critic_lr (float): Adam learning rate of both critics. Defaults to ``5e-4`` (paper).
        max_grad_norm (float): gradient-norm clip of each network on its own (SafePO). Defaults to ``10.0``.
        adam_eps (float): Adam's eps. Defaults to ``1e-5`` (SafePO).
        value_norm (bool): PopArt normalisation of each reward critic's loss
            (:class:`~torchrl.modules.PopArtValueNorm`). Defaults to ``True`` (SafePO).
        multipliers (sequence of Multiplier, optional): one per agent (S = 1 only).
        num_minibatches (int): minibatches per pass. Defaults to ``1`` (paper: the whole batch).
        clip_epsilon (float), entropy_coeff (float): :class:`AgentPPOLoss` options.
        shuffle (bool): random agent order per round. Defaults to ``True``.
        generator (torch.Generator, optional): S = 1: agent orders and minibatch shuffles.
        generators (sequence of torch.Generator, optional): one per seed (stacked teams).
        group (str): the group key. Defaults to ``"agents"``.
        loss_kwargs (dict, optional): extra :class:`AgentPPOLoss` options (``critic_l2_coeff``).

    ``batch`` (one per seed) has batch dims ``[*B]`` and holds, per agent under the group key,
    ``observation``, ``action``, ``action_log_prob``, ``advantage``, ``value_target``, ``cost_advantage``,
    ``cost_value_target`` (``[*B, A, ...]``) and the root ``"state"``.
    """

    #: Whether the round maintains HAPPO's factor :math:`M`.
    weighted: ClassVar[bool] = True
    #: The networks Adam trains, by optimiser group (each a tuple of :data:`~sg_torchrl.modules.stacked_multi_agent.NETWORKS` names).
    optimised: ClassVar[tuple[tuple[str, ...], ...]] = (("policy",), _CRITICS)

    def __init__(
        self,
        networks: MultiAgentNetworks | StackedMultiAgentNetworks,
        *,
        cost_limit: float = 25.0,
        gamma: float = 0.99,
        critic_lr: float = 5e-4,
        max_grad_norm: float = 10.0,
        adam_eps: float = 1e-5,
        value_norm: bool = True,
        multipliers: Sequence[Multiplier] | None = None,
        num_minibatches: int = 1,
        clip_epsilon: float = 0.2,
        entropy_coeff: float = 0.01,
        shuffle: bool = True,
        generator: torch.Generator | None = None,
        generators: Sequence[torch.Generator] | None = None,
        group: str = "agents",
        loss_kwargs: dict[str, Any] | None = None,
    ) -> None:
        if num_minibatches < 1:
            raise ValueError(f"need num_minibatches >= 1, got {num_minibatches}.")
        if isinstance(networks, MultiAgentNetworks):  # one team: a stack of one seed
            networks = StackedMultiAgentNetworks([networks])
        seeds, n = networks.num_seeds, networks.n_agents
        if generators is None:
            if seeds > 1:
                raise ValueError("stacked teams need one generator per seed (generators=...)")
            generators = [generator if generator is not None else seeding.generator(0, seeding.Purpose.MINIBATCHES)]
        if len(generators) != seeds:
            raise ValueError(f"need one generator per seed ({seeds}), got {len(generators)}.")
        if multipliers is not None and (seeds > 1 or len(multipliers) != n):
            raise ValueError(f"multipliers=: one per agent ({n}) of a single team, got {len(multipliers)}.")
        self.networks, self.n_agents, self.group = networks, n, group
        self.critic_lr, self.adam_eps = float(critic_lr), float(adam_eps)
        self.num_minibatches = int(num_minibatches)
        self.gamma, self.max_grad_norm, self.shuffle = float(gamma), float(max_grad_norm), bool(shuffle)
        #: Each seed's generator (agent orders, then its minibatch shuffles).
        self.shuffler = SeedShuffler.from_generators(generators)
        #: Per seed, one multiplier per agent (they hold the cost limit).
        self.team_multipliers = [
            nn.ModuleList(multipliers if multipliers is not None else
                          [self._make_multiplier(cost_limit) for _ in range(n)]).to(networks.device)
            for _ in range(seeds)
        ]
        # The agents' loss (a view of the objective) hands the round its seed-batched form.
        team = networks.teams[0]
        self.loss = AgentPPOLoss(team.agent_actor(0), team.agent_critic(0), team.agent_cost_critic(0),
                                 self.team_multipliers[0][0], weighted=self.weighted and self._loss_weighted,
                                 clip_epsilon=clip_epsilon, entropy_coeff=entropy_coeff, functional=False,
                                 **(loss_kwargs or {}))
        self.objective: AgentObjective = self.loss.seed_batched_objective()
        self.value_norm = bool(value_norm)
        self.popart = {name: torch.zeros(seeds, n, 1, device=networks.device) for name in _POPART}
        # Adam's moments as (S, A, ...) stacks beside the networks', per optimiser group, and step counts
        self._stacks = [[t for name in names for t in networks.tensors_of(name)] for names in self.optimised]
        self.exp_avg = [[torch.zeros_like(t) for t in group_] for group_ in self._stacks]
        self.exp_avg_sq = [[torch.zeros_like(t) for t in group_] for group_ in self._stacks]
        self.steps = torch.zeros(len(self._stacks), seeds, n, dtype=torch.float64, device=networks.device)

    #: Whether the agents' loss weights its advantage by the factor (MACPO's trains the critics only).
    _loss_weighted: ClassVar[bool] = True

    def _make_multiplier(self, cost_limit: float) -> Multiplier:
        return NoMultiplier(cost_limit)

    def _learning_rates(self) -> tuple[float, ...]:
        """Adam's learning rate of each group of :attr:`optimised`."""
        return (self.critic_lr,) * len(self.optimised)

    @classmethod
    def for_seeds(cls, networks: StackedMultiAgentNetworks, generators: Sequence[torch.Generator],
                  **options: Any) -> SeedBatchedRound:
        """The round of S seeds' stacked teams (what the multi-agent engine builds): one object for all seeds."""
        return cls(networks, generators=generators, **options)

    @property
    def multipliers(self) -> nn.ModuleList:
        """The team's multipliers (one team, S = 1)."""
        if len(self.team_multipliers) != 1:
            raise AttributeError("a round of several seeds has team_multipliers[s], one list per seed")
        return self.team_multipliers[0]

    # ------------------------------------------------------------------ round
    def __call__(self, data: TensorDictBase, mean_episode_cost: float | Tensor) -> dict[str, float]:
        """One team's round (S = 1) on ``data`` (batch ``[*B]``, group entries ``[*B, A, ...]``, after both GAEs).

        Returns the team metrics (mean over agents) under SafePO's names, the same per agent under
        ``"<name>/agent<i>"``, and ``Train/AgentOrder/agent<i>`` (the stage at which agent ``i`` was updated).
        """
        return self.step_seeds([data], [mean_episode_cost])[0]

    def step_seeds(self, batches: Sequence[TensorDictBase | None],
                   mean_episode_costs: Sequence[float | Tensor | None]) -> list[dict[str, float] | None]:
        """One round of every seed whose batch is given (``None``: a frozen seed, untouched); its metrics per seed."""
        seeds = self.networks.num_seeds
        if len(batches) != seeds or len(mean_episode_costs) != seeds:
            raise ValueError(f"need one batch and one mean episode cost per seed ({seeds})")
        live = [s for s, batch in enumerate(batches) if batch is not None]
        if not live:
            return [None] * seeds
        rows = torch.tensor(live)
        costs = torch.tensor([episode_costs(mean_episode_costs[s], self.n_agents) for s in live], dtype=torch.float64)
        fields = self._stack_fields([batches[s] for s in live])
        orders = torch.stack([self._permutation(s) for s in live])
        size = fields["state"].shape[1]
        factor = torch.ones(len(live), size, device=self.networks.device) if self.weighted else None
        stages = []
        for stage in range(self.n_agents):
            metrics, factor = self._stage(rows, orders[:, stage], fields, factor, costs)
            stages.append(metrics)
        results: list[dict[str, float] | None] = [None] * seeds
        multipliers = torch.stack([m.value.to(torch.float64) for s in live for m in self.team_multipliers[s]])
        values = multipliers.view(len(live), self.n_agents).tolist()  # the round's one read of them
        for index, s in enumerate(live):
            lam = values[index]
            # a metric a row's stage does not have (None: another row's CPO case had it) is left out, as alone
            results[s] = round_metrics([(int(orders[index, k]), {name: values[index] for name, values in stage.items()
                                                                 if values[index] is not None})
                                        for k, stage in enumerate(stages)], lam)
        return results

    def _permutation(self, seed: int) -> Tensor:
        if not self.shuffle:
            return torch.arange(self.n_agents)
        return torch.randperm(self.n_agents, generator=self.shuffler.generators[seed])

    def _stack_fields(self, batches: Sequence[TensorDictBase]) -> dict[str, Tensor]:
        """The live seeds' group entries ``(L, M, A, ...)`` and states ``(L, M, Ds)`` (``M`` samples per seed)."""
        out = {}
        for key in _FIELDS:
            values = []
            for batch in batches:
                dims = batch.batch_dims
                value = batch.get(key, None) if key == "state" else batch.get((self.group, key), None)
                if value is None:
                    raise KeyError(f"the round needs {key!r} ({(self.group, key)!r} per agent; run the GAEs first?)")
                values.append(value.reshape(-1, *value.shape[dims:]))
            out[key] = torch.stack(values)
        out["action_log_prob"] = out["action_log_prob"].unsqueeze(-1)
        return out

    @abc.abstractmethod
    def _stage(self, seeds: Tensor, agents: Tensor, fields: dict[str, Tensor], factor: Tensor | None,
               costs: Tensor) -> tuple[dict[str, list[float]], Tensor | None]:
        """Stage ``k``: seed ``seeds[i]`` updates agent ``agents[i]``; returns each row's metrics and the new factor.

        ``fields``: the live seeds' ``(L, M, A, ...)`` group entries and ``(L, M, Ds)`` states; ``factor``:
        ``(L, M)`` (``None`` unweighted); ``costs``: ``(L, A)`` float64 mean episode costs.
        """

    def _stage_data(self, seeds: Tensor, agents: Tensor, fields: dict[str, Tensor],
                    factor: Tensor | None) -> SeedBatch:
        """The stage's rows' batches: each row's agent's entries and the state, ``(L, M, width)``."""
        index = torch.arange(len(seeds))
        data = {key: value if key == "state" else value[index, :, agents] for key, value in fields.items()}
        if factor is not None:
            data["factor"] = factor.unsqueeze(-1)
        return SeedBatch.pack(data)

    def _value_norm(self, seeds: Tensor, agents: Tensor):
        """The rows' PopArt statistics (:func:`seed_popart`), or ``None`` without value normalisation."""
        return seed_popart(*(self.popart[name][seeds, agents] for name in _POPART)) if self.value_norm else None

    def _clip(self, rows: AgentRows, names: Sequence[str]) -> list[Tensor]:
        """Clip each network's gradient of every row on its own (SafePO); returns the norms before clipping."""
        return [clip_grad_norm_per_seed_([t.grad for t in rows.tensors(name)], self.max_grad_norm) for name in names]

    def _critic_passes(self, rows: AgentRows, batch: SeedBatch, optimizer: SeedMaskedAdam, value_norm,
                       passes: int, seeds: Tensor) -> dict[str, Tensor]:
        """``passes`` passes of Adam steps on the rows' two critics (MACPO's), no early stop; the means per row."""
        means = RowMeans(CRITIC_METRICS, (len(seeds),), self.networks.device)

        def step(minibatch: SeedBatch):
            out = self.objective.critic_losses(rows, minibatch.fields(), value_norm, None)
            rows.zero_grad()
            (out["loss_critic"] + out["loss_cost_critic"]).sum().backward()
            out["reward_norm"], out["cost_norm"] = self._clip(rows, _CRITICS)
            optimizer.step()
            return out, ()

        active = torch.ones(len(seeds), dtype=torch.bool, device=self.networks.device)
        return run_passes(batch, step, passes=passes, order=self._order(seeds, active), metrics=means).means

    def _order(self, seeds: Tensor, active: Tensor):
        """The minibatches of a pass: the whole batch, or each active seed's permutation cut in chunks (drawn on
        the host, moved to the networks' device once per pass)."""
        if self.num_minibatches == 1:
            return whole_batch
        chunks = self.num_minibatches

        def order(size: int, generator: torch.Generator | None) -> list[Tensor]:
            drawing = [False] * self.networks.num_seeds
            for seed, flag in zip(seeds.tolist(), active.tolist(), strict=True):  # one read per pass
                drawing[seed] = flag
            permutation = self.shuffler.permutation(size, drawing)[seeds].to(self.networks.device, non_blocking=True)
            return list(permutation.split(-(-size // chunks), dim=1))

        return order

    def _optimizer(self, rows: AgentRows, seeds: Tensor, agents: Tensor) -> SeedMaskedAdam:
        """Adam over the rows' groups of :attr:`optimised` (:meth:`_learning_rates`), with those rows' moments."""
        lrs = self._learning_rates()
        optimizer = SeedMaskedAdam([{"params": [t for name in names for t in rows.tensors(name)], "lr": lr}
                                    for names, lr in zip(self.optimised, lrs)], eps=self.adam_eps)
        optimizer.load_state_dict({
            "state": [{"step": self.steps[g, seeds, agents], "exp_avg": [m[seeds, agents] for m in self.exp_avg[g]],
                       "exp_avg_sq": [m[seeds, agents] for m in self.exp_avg_sq[g]]} for g in range(len(lrs))],
            "lr": list(lrs),
        })
        return optimizer

    @torch.no_grad()
    def _write_back(self, rows: AgentRows, optimizer: SeedMaskedAdam, value_norm) -> None:
        """The rows' parameters, moments and PopArt statistics back into the round's stacks."""
        seeds, agents = rows.seeds, rows.agents
        rows.write_back(self.networks)
        for g, state in enumerate(optimizer.state_dict()["state"]):
            self.steps[g, seeds, agents] = state["step"]
            for stack, moment in zip(self.exp_avg[g], state["exp_avg"], strict=True):
                stack[seeds, agents] = moment
            for stack, moment in zip(self.exp_avg_sq[g], state["exp_avg_sq"], strict=True):
                stack[seeds, agents] = moment
        if value_norm is not None:
            for name in _POPART:
                self.popart[name][seeds, agents] = getattr(value_norm, name)

    # ------------------------------------------------------------------ checkpoints
    def seed_state_dict(self, seed: int) -> dict[str, Any]:
        """Seed ``seed``'s round state in a single team's format: per-agent ``torch.optim.Adam`` state dicts,
        multipliers, PopArt normalisers and the generator (the networks are the caller's)."""
        return {
            "optimizers": [self._adam_state(seed, agent) for agent in range(self.n_agents)],
            "multipliers": self.team_multipliers[seed].state_dict(),
            "value_norms": None if not self.value_norm else {
                f"{agent}.{name}": self.popart[name][seed, agent].reshape(() if name == "debiasing_term" else (1,)).clone()
                for agent in range(self.n_agents) for name in _POPART},
            "generator": self.shuffler.generators[seed].get_state(),
        }

    @torch.no_grad()
    def load_seed_state_dict(self, seed: int, state: dict[str, Any]) -> None:
        """Restore what :meth:`seed_state_dict` saved; per-agent Adam state dicts of ``torch.optim.Adam``
        (a single team's round before the rounds were seed-batched) are the same format and read alike."""
        for agent, adam in enumerate(state["optimizers"]):
            self._load_adam_state(seed, agent, adam)
        self.team_multipliers[seed].load_state_dict(state["multipliers"])
        if self.value_norm:
            for agent in range(self.n_agents):
                for name in _POPART:
                    self.popart[name][seed, agent] = state["value_norms"][f"{agent}.{name}"].reshape(1)
        self.shuffler.generators[seed].set_state(state["generator"])

    def state_dict(self) -> dict[str, Any]:
        """One team's round state (S = 1)."""
        return self.seed_state_dict(0)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.load_seed_state_dict(0, state)

    def _agent_slices(self, agent: int) -> list[list[tuple[Tensor, int | None]]]:
        """Per group, the stacked tensors of ``agent``'s parameters and how much of the last dim is its own."""
        size = self.networks.teams[0].action_sizes[agent]
        return [[(t, size if t is self.networks.log_std else None) for t in group] for group in self._stacks]

    def _adam_state(self, seed: int, agent: int) -> dict[str, Any]:
        state, param_groups, index = {}, [], 0
        steps = self.steps[:, seed, agent].tolist()
        for g, (group, lr) in enumerate(zip(self._agent_slices(agent), self._learning_rates(), strict=True)):
            start = index
            for position, (_, size) in enumerate(group):
                step = steps[g]
                if step > 0:
                    avg, avg_sq = self.exp_avg[g][position][seed, agent], self.exp_avg_sq[g][position][seed, agent]
                    if size is not None:
                        avg, avg_sq = avg[..., :size], avg_sq[..., :size]
                    state[index] = {"step": torch.tensor(step), "exp_avg": avg.clone(), "exp_avg_sq": avg_sq.clone()}
                index += 1
            param_groups.append({"lr": lr, "betas": (0.9, 0.999), "eps": self.adam_eps, **_ADAM_GROUP,
                                 "params": list(range(start, index))})
        return {"state": state, "param_groups": param_groups}

    def _load_adam_state(self, seed: int, agent: int, adam: dict[str, Any]) -> None:
        saved = adam["state"]
        if len(adam["param_groups"]) != len(self.optimised):
            raise ValueError(f"agent {agent}'s optimiser state has {len(adam['param_groups'])} groups, the round "
                             f"{len(self.optimised)}: not this algorithm's checkpoint")
        for g, (group, ids) in enumerate(zip(self._agent_slices(agent), (pg["params"] for pg in adam["param_groups"]))):
            if len(ids) != len(group):
                raise ValueError(f"agent {agent}'s optimiser state has {len(ids)} tensors in group {g}, the round "
                                 f"{len(group)}: not this algorithm's or this team's checkpoint")
            steps = {float(saved[i]["step"]) for i in ids if i in saved}
            self.steps[g, seed, agent] = steps.pop() if len(steps) == 1 else 0.0
            for position, ((_, size), i) in enumerate(zip(group, ids)):
                for stacks, key in ((self.exp_avg, "exp_avg"), (self.exp_avg_sq, "exp_avg_sq")):
                    row = stacks[g][position][seed, agent]
                    row.zero_()
                    if i in saved:
                        (row if size is None else row[..., :size]).copy_(saved[i][key])


def episode_costs(mean_episode_cost: float | Tensor, n_agents: int) -> list[float]:
    """:math:`J_c` per agent: one finite value for the team (every agent's), or one per agent."""
    value = torch.as_tensor(mean_episode_cost, dtype=torch.float64).detach().reshape(-1)
    if value.numel() == 1:
        value = value.expand(n_agents)
    if value.numel() != n_agents or not torch.isfinite(value).all():
        raise ValueError(f"mean_episode_cost must be one finite value or one per agent ({n_agents}), "
                         f"got {mean_episode_cost!r}.")
    return value.tolist()


def host_lists(values: Mapping[str, Tensor]) -> dict[str, list[float]]:
    """Each ``(R,)`` tensor of ``values`` as a list of floats, read back to the host in one copy (a stage's metrics)."""
    if not values:
        return {}
    device = next(iter(values.values())).device
    rows = torch.stack([value.detach().to(device, torch.float64) for value in values.values()]).tolist()
    return dict(zip(values, rows))


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
