"""One round of MAPPO, HAPPO and MAPPO-Lag, seed-batched: S seeds' rounds in one update call (S >= 1).

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
                  :mod:`~sg_torchrl.objectives.multi_agent.macpo`)
================  =============================================  ==========  =======================

The first three are :class:`MultiAgentPPOUpdate`: the round written once for S seeds, each seed with
its own random agent order, the agent of every seed at a stage updated in one call (see the class).

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

Defaults are the paper's multi-agent hyper-parameters (Safety-Gymnasium paper appendix: lr 5e-4
for actor and critics, 5 epochs, 1 minibatch, clip 0.2, target KL 0.016, gamma 0.99) and SafePO's
settings the paper does not list (Adam eps 1e-5, entropy coefficient 0.01, gradient-norm clip 10
per network, PopArt value normalisation). Deviations from SafePO's scripts:

* the KL early stop at ``target_kl`` (the paper lists 0.016; SafePO's MaMuJoCo scripts never read
  it): after each epoch, stop the agent's epochs once :math:`\\mathrm{KL}(\\pi_{\\text{old}} \\|
  \\pi)` (summed over action dims) exceeds it; ``target_kl=None`` disables it;
* critic losses are MSE, the reward critic's through TorchRL's PopArt (``MAPPOLoss``'s semantics, see
  :class:`~sg_torchrl.objectives.multi_agent.AgentObjective`; no value clipping) instead of SafePO's Huber(10) with value
  clipping, where the cost values are normalised with the reward critic's PopArt statistics
  **[quirk]**;
* GAE bootstraps truncated episodes (SafePO treats time-limit ends as terminal).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import torch
from tensordict import TensorDictBase
from torch import nn, Tensor

from sg_torchrl import seeding
from sg_torchrl.modules.gaussian import gaussian_log_prob
from sg_torchrl.modules.multi_agent import MultiAgentNetworks
from sg_torchrl.modules.stacked_multi_agent import AgentRows, NETWORKS, StackedMultiAgentNetworks
from sg_torchrl.objectives.kl import gaussian_kl
from sg_torchrl.objectives.multi_agent.loss import AgentPPOLoss
from sg_torchrl.objectives.multi_agent.multiplier import MAPPOLagMultiplier
from sg_torchrl.objectives.multi_agent.objective import AgentObjective, seed_popart
from sg_torchrl.objectives.multi_agent.sequential import episode_costs, round_metrics
from sg_torchrl.objectives.multipliers import Multiplier, NoMultiplier
from sg_torchrl.objectives.passes import RowMeans, run_passes, whole_batch
from sg_torchrl.train.fused import SeedBatch, SeedShuffler
from sg_torchrl.train.seed_adam import clip_grad_norm_per_seed_, SeedMaskedAdam

__all__ = ["HAPPOUpdate", "MAPPOLagUpdate", "MAPPOUpdate", "MultiAgentPPOUpdate"]

#: The critics' losses averaged over an agent's steps, by SafePO's metric names.
CRITIC_METRICS = {"Loss/Loss_reward_critic": "loss_critic", "Loss/Loss_cost_critic": "loss_cost_critic"}
#: Everything a stage averages over its optimiser steps (metric name: step output).
STEP_METRICS = {"Loss/Loss_actor": "loss_objective", **CRITIC_METRICS, "Misc/Ratio": "mean_ratio",
                "Misc/Reward_critic_norm": "reward_norm", "Misc/Cost_critic_norm": "cost_norm"}
#: The batch fields of an agent's step (``state`` is the team's; ``factor`` only when weighted).
_FIELDS = ("observation", "state", "action", "action_log_prob", "advantage", "value_target", "cost_advantage",
           "cost_value_target")
_POPART = ("running_mean", "running_mean_sq", "debiasing_term")
_ADAM_GROUP = dict(weight_decay=0, amsgrad=False, maximize=False, foreach=None, capturable=False,
                   differentiable=False, fused=None, decoupled_weight_decay=False)


class MultiAgentPPOUpdate:
    """The sequential clipped-PPO round of MAPPO, HAPPO and MAPPO-Lag, for S seeds at once (S >= 1).

    Built on one team (:class:`~sg_torchrl.modules.MultiAgentNetworks`, S = 1: ``update(batch,
    mean_episode_cost)``) or on S seeds' stacked teams
    (:class:`~sg_torchrl.modules.stacked_multi_agent.StackedMultiAgentNetworks`, one generator per seed:
    :meth:`step_seeds`). Per round and live seed: its agent order from its own generator; at stage ``k`` every
    seed updates its agent ``order[s, k]``: those rows are gathered
    (:class:`~sg_torchrl.modules.stacked_multi_agent.AgentRows`) and take up to ``epochs`` passes of
    ``num_minibatches`` steps together, each step :attr:`objective`'s losses
    (:class:`~sg_torchrl.objectives.multi_agent.AgentObjective`, obtained from the agents' loss,
    :meth:`AgentPPOLoss.seed_batched_objective`), their backward, the gradients clipped per seed and network
    (actor, reward critic, cost critic: :func:`~sg_torchrl.train.seed_adam.clip_grad_norm_per_seed_`) and a
    :class:`~sg_torchrl.train.seed_adam.SeedMaskedAdam` step whose moments are those rows of the round's
    stacked moments; MAPPO-Lag then steps each row's multiplier. A seed whose KL early stop fires is masked
    for the rest of its stage (its parameters, moments, PopArt statistics, multiplier and generator do not
    move), the others go on. The rows are written back, and the factor :math:`M` takes the updated agent's
    ratio. So seed ``s`` of the group does what its round alone does (S = 1), up to float rounding.

    Keyword Args:
        actor_lr (float): defaults to ``5e-4`` (paper).
        epochs (int): passes over the batch per agent. Defaults to ``5`` (paper).
        num_minibatches (int): defaults to ``1`` (paper: the whole batch per step).
        target_kl (float, optional): KL early stop per agent. Defaults to ``0.016`` (paper); ``None`` disables it.
        cost_limit (float): :math:`d`. Defaults to ``25.0`` (paper).
        gamma (float): discount of MAPPO-Lag's :math:`(1 - \\gamma)` constraint scaling. Defaults to ``0.99``.
        critic_lr (float): Adam learning rate of both critics. Defaults to ``5e-4`` (paper).
        max_grad_norm (float): gradient-norm clip of the actor, the reward critic and the cost critic,
            each on its own (SafePO). Defaults to ``10.0``.
        adam_eps (float): Adam's eps. Defaults to ``1e-5`` (SafePO).
        value_norm (bool): PopArt normalisation of each reward critic's loss
            (:class:`~torchrl.modules.PopArtValueNorm`). Defaults to ``True`` (SafePO).
        multipliers (sequence of Multiplier, optional): one per agent (S = 1 only).
        clip_epsilon (float), entropy_coeff (float): :class:`AgentPPOLoss` options. Defaults ``0.2``, ``0.01``.
        shuffle (bool): random agent order per round. Defaults to ``True``.
        generator (torch.Generator, optional): S = 1: agent orders and minibatch shuffles.
        generators (sequence of torch.Generator, optional): one per seed (stacked teams).
        group (str): the group key. Defaults to ``"agents"``.
        loss_kwargs (dict, optional): extra :class:`AgentPPOLoss` options (``critic_l2_coeff``).

    Per-agent metrics: ``Loss/Loss_actor``, ``Loss/Loss_reward_critic``, ``Loss/Loss_cost_critic``
    (means over the agent's steps), ``Misc/Reward_critic_norm``, ``Misc/Cost_critic_norm`` (gradient norms
    before clipping), ``Misc/Ratio`` (mean ratio to the behaviour policy), ``Misc/Entropy`` (policy
    entropy over the real action dims, after the update), ``Misc/Factor`` (mean :math:`M` handed to the
    agent), ``Train/KL``, ``Train/StopIter`` (epochs run), ``Train/LagrangeMultiplier``.
    """

    #: Whether the round maintains HAPPO's factor :math:`M`.
    weighted: ClassVar[bool] = True
    #: Whether each agent's multiplier is stepped after every minibatch step (MAPPO-Lag).
    steps_multiplier: ClassVar[bool] = False

    def __init__(
        self,
        networks: MultiAgentNetworks | StackedMultiAgentNetworks,
        *,
        actor_lr: float = 5e-4,
        epochs: int = 5,
        num_minibatches: int = 1,
        target_kl: float | None = 0.016,
        cost_limit: float = 25.0,
        gamma: float = 0.99,
        critic_lr: float = 5e-4,
        max_grad_norm: float = 10.0,
        adam_eps: float = 1e-5,
        value_norm: bool = True,
        multipliers: Sequence[Multiplier] | None = None,
        clip_epsilon: float = 0.2,
        entropy_coeff: float = 0.01,
        shuffle: bool = True,
        generator: torch.Generator | None = None,
        generators: Sequence[torch.Generator] | None = None,
        group: str = "agents",
        loss_kwargs: dict[str, Any] | None = None,
    ) -> None:
        if epochs < 1 or num_minibatches < 1:
            raise ValueError(f"need epochs >= 1 and num_minibatches >= 1, got {epochs}, {num_minibatches}.")
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
        self.actor_lr, self.critic_lr, self.adam_eps = float(actor_lr), float(critic_lr), float(adam_eps)
        self.epochs, self.num_minibatches = int(epochs), int(num_minibatches)
        self.target_kl = None if target_kl is None else float(target_kl)
        self.gamma, self.max_grad_norm, self.shuffle = float(gamma), float(max_grad_norm), bool(shuffle)
        #: Each seed's generator (agent orders, then its minibatch shuffles).
        self.shuffler = SeedShuffler.from_generators(generators)
        #: Per seed, one multiplier per agent.
        self.team_multipliers = [
            nn.ModuleList(multipliers if multipliers is not None else
                          [self._make_multiplier(cost_limit) for _ in range(n)])
            for _ in range(seeds)
        ]
        # The agents' loss (a view of the objective) hands the round its seed-batched form.
        team = networks.teams[0]
        self.loss = AgentPPOLoss(team.agent_actor(0), team.agent_critic(0), team.agent_cost_critic(0),
                                 self.team_multipliers[0][0], weighted=self.weighted, clip_epsilon=clip_epsilon,
                                 entropy_coeff=entropy_coeff, functional=False, **(loss_kwargs or {}))
        self.objective: AgentObjective = self.loss.seed_batched_objective()
        self.value_norm = bool(value_norm)
        zeros = dict(dtype=torch.float32)
        self.popart = {name: torch.zeros(seeds, n, 1, **zeros) for name in _POPART}
        # Adam's moments as (S, A, ...) stacks beside the networks' (actor group, critics group) and step counts
        self._stacks = self._stacked_groups()
        self.exp_avg = [[torch.zeros_like(t) for t in group_] for group_ in self._stacks]
        self.exp_avg_sq = [[torch.zeros_like(t) for t in group_] for group_ in self._stacks]
        self.steps = torch.zeros(len(self._stacks), seeds, n, dtype=torch.float64)

    def _make_multiplier(self, cost_limit: float) -> Multiplier:
        return NoMultiplier(cost_limit)

    @classmethod
    def for_seeds(cls, networks: StackedMultiAgentNetworks, generators: Sequence[torch.Generator],
                  **options: Any) -> MultiAgentPPOUpdate:
        """The round of S seeds' stacked teams (what the multi-agent engine builds): one object for all seeds."""
        return cls(networks, generators=generators, **options)

    def _stacked_groups(self) -> list[list[Tensor]]:
        """The optimiser groups' stacked tensors, in :class:`AgentRows` order: the actor's, both critics'."""
        net = self.networks
        def layers(name: str) -> list[Tensor]:
            return [t for pair in zip(net.weights[name], net.biases[name]) for t in pair]
        return [[*layers("policy"), net.log_std], [*layers("reward_value"), *layers("cost_value")]]

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
        factor = torch.ones(len(live), size) if self.weighted else None
        stages = []
        for stage in range(self.n_agents):
            metrics, factor = self._stage(rows, orders[:, stage], fields, factor, costs)
            stages.append(metrics)
        results: list[dict[str, float] | None] = [None] * seeds
        for index, s in enumerate(live):
            lam = [float(m.value) for m in self.team_multipliers[s]]
            results[s] = round_metrics([(int(orders[index, k]), {name: values[index] for name, values in stage.items()})
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

    def _stage(self, seeds: Tensor, agents: Tensor, fields: dict[str, Tensor], factor: Tensor | None,
               costs: Tensor) -> tuple[dict[str, list[float]], Tensor | None]:
        """Stage ``k``: seed ``seeds[i]`` updates agent ``agents[i]``; returns its metrics per row and the new factor."""
        live = len(seeds)
        index = torch.arange(live)
        data = {key: value if key == "state" else value[index, :, agents] for key, value in fields.items()}
        if factor is not None:
            data["factor"] = factor.unsqueeze(-1)
        batch = SeedBatch.pack(data)
        rows = self.networks.agent_rows(seeds, agents)
        observation, action = data["observation"], data["action"]
        with torch.no_grad():
            old_loc, old_scale = rows.dist_params(observation)
            before = gaussian_log_prob(action, old_loc, old_scale)
        optimizer = self._optimizer(rows, seeds, agents)
        multipliers = [self.team_multipliers[int(s)][int(a)] for s, a in zip(seeds, agents)]
        lam = torch.stack([m.value.to(torch.float64) for m in multipliers])
        violation = costs[index, agents] - torch.stack([m.cost_limit for m in multipliers])
        value_norm = (seed_popart(*(self.popart[name][seeds, agents] for name in _POPART)) if self.value_norm
                      else None)
        active = torch.ones(live, dtype=torch.bool)
        passes = torch.zeros(live, dtype=torch.float64)
        kl = torch.zeros(live, dtype=torch.float32)
        means = RowMeans(STEP_METRICS, (live,))

        def step(minibatch: SeedBatch):
            nonlocal lam
            out = self.objective.losses(rows, minibatch.fields(), lam, value_norm, active)
            total = out["loss_objective"] + out["loss_critic"] + out["loss_cost_critic"] + out["loss_entropy"]
            for group in rows.groups.values():
                for tensor in group:
                    tensor.grad = None
            total.sum().backward()
            _, out["reward_norm"], out["cost_norm"] = (
                clip_grad_norm_per_seed_([t.grad for t in rows.groups[name]], self.max_grad_norm) for name in NETWORKS)
            optimizer.step(active)
            if self.steps_multiplier:
                stepped = MAPPOLagMultiplier.step_rule(lam, violation, out["cost_surrogate"].to(torch.float64),
                                                       torch.tensor([m.lr for m in multipliers], dtype=torch.float64),
                                                       torch.tensor([m.gamma for m in multipliers], dtype=torch.float64))
                lam = torch.where(active, stepped, lam)
            return out, ()

        done = 0
        policy_now: tuple[Tensor, Tensor] | None = None  # the rows' policy as it is after their last pass

        def go_on() -> bool:
            nonlocal done, kl, policy_now
            done += 1
            passes.add_(active.to(torch.float64))
            if self.target_kl is not None or done == self.epochs:  # always so after the last pass
                with torch.no_grad():
                    policy_now = rows.dist_params(observation)
                    now = gaussian_kl(old_loc, old_scale, *policy_now).mean(1)
                kl = torch.where(active, now, kl)
                if self.target_kl is not None:
                    active.logical_and_(now.to(torch.float64) <= self.target_kl)
            means.weight = active.to(torch.float64)
            return bool(active.any())

        report = run_passes(batch, step, passes=self.epochs, order=self._order(seeds, active), metrics=means,
                            go_on=go_on)
        self._write_back(rows, optimizer, value_norm, multipliers, lam)
        with torch.no_grad():
            metrics = {name: value.tolist() for name, value in report.means.items()}
            metrics.update({
                "Misc/Entropy": rows.entropy().tolist(),
                "Misc/Factor": (factor.mean(1) if factor is not None else torch.ones(live)).tolist(),
                "Train/KL": kl.tolist(),
                "Train/StopIter": passes.tolist(),
                "Train/LagrangeMultiplier": lam.tolist(),
            })
            if factor is not None:
                factor = factor * (gaussian_log_prob(action, *policy_now) - before).exp()
        return metrics, factor

    def _order(self, seeds: Tensor, active: Tensor):
        """The minibatches of a pass: the whole batch, or each active seed's permutation cut in chunks."""
        if self.num_minibatches == 1:
            return whole_batch
        chunks = self.num_minibatches

        def order(size: int, generator: torch.Generator | None) -> list[Tensor]:
            drawing = [False] * self.networks.num_seeds
            for row, seed in enumerate(seeds.tolist()):
                drawing[seed] = bool(active[row])
            permutation = self.shuffler.permutation(size, drawing)[seeds]
            return list(permutation.split(-(-size // chunks), dim=1))

        return order

    def _optimizer(self, rows: AgentRows, seeds: Tensor, agents: Tensor) -> SeedMaskedAdam:
        """Adam over the rows: the actor at ``actor_lr``, the critics at ``critic_lr``, moments of those rows."""
        optimizer = SeedMaskedAdam([{"params": rows.groups["policy"], "lr": self.actor_lr},
                                    {"params": [*rows.groups["reward_value"], *rows.groups["cost_value"]],
                                     "lr": self.critic_lr}], eps=self.adam_eps)
        optimizer.load_state_dict({
            "state": [{"step": self.steps[g, seeds, agents], "exp_avg": [m[seeds, agents] for m in self.exp_avg[g]],
                       "exp_avg_sq": [m[seeds, agents] for m in self.exp_avg_sq[g]]} for g in range(2)],
            "lr": [self.actor_lr, self.critic_lr],
        })
        return optimizer

    @torch.no_grad()
    def _write_back(self, rows: AgentRows, optimizer: SeedMaskedAdam, value_norm, multipliers: list[Multiplier],
                    lam: Tensor) -> None:
        """The rows' parameters, moments, PopArt statistics and multipliers back into the round's stacks."""
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
        if self.steps_multiplier:
            for multiplier, value in zip(multipliers, lam, strict=True):
                multiplier.multiplier.copy_(value)

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
        for g, (group, lr) in enumerate(zip(self._agent_slices(agent), (self.actor_lr, self.critic_lr))):
            start = index
            for position, (_, size) in enumerate(group):
                step = float(self.steps[g, seed, agent])
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
        for g, (group, ids) in enumerate(zip(self._agent_slices(agent), (pg["params"] for pg in adam["param_groups"]),
                                            strict=True)):
            if len(ids) != len(group):
                raise ValueError(f"agent {agent}'s optimiser state has {len(ids)} tensors in group {g}, the networks "
                                 f"{len(group)}: not this team's checkpoint")
            steps = {float(saved[i]["step"]) for i in ids if i in saved}
            self.steps[g, seed, agent] = steps.pop() if len(steps) == 1 else 0.0
            for position, ((_, size), i) in enumerate(zip(group, ids)):
                for stacks, key in ((self.exp_avg, "exp_avg"), (self.exp_avg_sq, "exp_avg_sq")):
                    row = stacks[g][position][seed, agent]
                    row.zero_()
                    if i in saved:
                        (row if size is None else row[..., :size]).copy_(saved[i][key])


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
