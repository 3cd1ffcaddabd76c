"""One round of the multi-agent algorithms: MAPPO, HAPPO, MAPPO-Lag (and the common body of MACPO).

Every algorithm of the Safety-Gymnasium paper's multi-agent benchmark (Ji et al. 2023) updates the
agents one at a time in a random order (:class:`~sg_torchrl.objectives.multi_agent.SequentialAgentUpdate`).
The algorithms differ only in what one agent's update is:

================  =============================================  ==========  =======================
class             agent update                                   factor M    multiplier
================  =============================================  ==========  =======================
MAPPOUpdate       clipped-PPO epochs (Yu et al. 2022)             unused      none
HAPPOUpdate       factor-weighted clipped-PPO epochs              yes         none
                  (Kuba et al. 2022)
MAPPOLagUpdate    factor-weighted clipped PPO on                  yes         per agent, stepped
                  :math:`A_r - \\lambda^i A^i_c` (Gu et al. 2023)               after every minibatch
MACPOUpdate       one CPO step on factor-weighted surrogates,     yes         none (the CPO step)
                  then critic epochs (Gu et al. 2023)
================  =============================================  ==========  =======================

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
* critic losses are TorchRL's (MSE, PopArt through :class:`~torchrl.objectives.multiagent.MAPPOLoss`
  on the reward critic, no value clipping by default) instead of SafePO's Huber(10) with value
  clipping, where the cost values are normalised with the reward critic's PopArt statistics
  **[quirk]**;
* GAE bootstraps truncated episodes (SafePO treats time-limit ends as terminal).
"""

from __future__ import annotations

import abc
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar

import torch
from tensordict import TensorDictBase
from torch import distributions as D, nn, Tensor
from torchrl.modules import PopArtValueNorm

from sg_torchrl import seeding
from sg_torchrl.modules.multi_agent import MultiAgentNetworks
from sg_torchrl.objectives.kl import gaussian_kl
from sg_torchrl.objectives.multi_agent.advantages import agent_view, AGENT_VIEW_KEYS
from sg_torchrl.objectives.multi_agent.loss import AgentPPOLoss
from sg_torchrl.objectives.multi_agent.multiplier import MAPPOLagMultiplier
from sg_torchrl.objectives.multi_agent.sequential import SequentialAgentUpdate, SequentialResult
from sg_torchrl.objectives.multipliers import Multiplier, NoMultiplier
from sg_torchrl.objectives.passes import ClipGroup, GradientStep, LossFn, run_passes, shuffled_chunks

__all__ = ["HAPPOUpdate", "MAPPOLagUpdate", "MAPPOUpdate", "MultiAgentPPOUpdate", "MultiAgentUpdate"]

#: The critics' losses averaged over an agent's steps, by SafePO's metric names.
CRITIC_METRICS = {"Loss/Loss_reward_critic": "loss_critic", "Loss/Loss_cost_critic": "loss_cost_critic"}


class MultiAgentUpdate(abc.ABC):
    """Common body of the four algorithms: per-agent losses and optimisers, the sequential round, metrics.

    Subclasses implement :meth:`_update_agent` (one agent's update given the factor :math:`M`) and
    say through :attr:`weighted` whether the factor is maintained.

    Args:
        networks (MultiAgentNetworks): the team's networks (:func:`make_multi_agent_networks`).

    Keyword Args:
        cost_limit (float): :math:`d`. Defaults to ``25.0`` (paper).
        gamma (float): discount (MAPPO-Lag's and MACPO's :math:`(1 - \\gamma)` constraint scaling).
            Defaults to ``0.99``.
        critic_lr (float): Adam learning rate of both critics. Defaults to ``5e-4`` (paper).
        max_grad_norm (float): gradient-norm clip applied to the actor, the reward critic and the
            cost critic separately (SafePO). Defaults to ``10.0``.
        adam_eps (float): Adam's eps. Defaults to ``1e-5`` (SafePO).
        value_norm (bool): PopArt normalisation of each reward critic's loss
            (:class:`~torchrl.modules.PopArtValueNorm`, via :class:`~torchrl.objectives.multiagent.MAPPOLoss`).
            Defaults to ``True`` (SafePO).
        multipliers (sequence of Multiplier, optional): one per agent; defaults to
            :class:`~sg_torchrl.objectives.NoMultiplier` s.
        clip_epsilon (float), entropy_coeff (float): :class:`AgentPPOLoss` options. Defaults
            ``0.2`` and ``0.01``.
        shuffle (bool): random agent order per round. Defaults to ``True``.
        generator (torch.Generator, optional): agent orders and minibatch shuffles.
        group (str): the group key. Defaults to ``"agents"``.
        loss_kwargs (dict, optional): extra :class:`AgentPPOLoss` options (``clip_value``,
            ``loss_critic_type``, ...).
    """

    #: Whether the sequential update maintains HAPPO's factor :math:`M`.
    weighted: ClassVar[bool] = True

    def __init__(
        self,
        networks: MultiAgentNetworks,
        *,
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
        group: str = "agents",
        loss_kwargs: dict[str, Any] | None = None,
    ) -> None:
        n = networks.n_agents
        if multipliers is None:
            multipliers = [NoMultiplier(cost_limit) for _ in range(n)]
        if len(multipliers) != n:
            raise ValueError(f"need one multiplier per agent ({n}), got {len(multipliers)}.")
        self.networks = networks
        self.n_agents = n
        self.gamma = float(gamma)
        self.max_grad_norm = float(max_grad_norm)
        self.group = group
        self.generator = generator if generator is not None else seeding.generator(0, seeding.Purpose.MINIBATCHES)
        self.multipliers = nn.ModuleList(multipliers)
        self.value_norms = nn.ModuleList(PopArtValueNorm(shape=1) for _ in range(n)) if value_norm else None
        self.losses = [
            AgentPPOLoss(
                networks.agent_actor(i), networks.agent_critic(i), networks.agent_cost_critic(i), self.multipliers[i],
                weighted=self._loss_weighted(), clip_epsilon=clip_epsilon, entropy_coeff=entropy_coeff,
                value_norm=None if self.value_norms is None else self.value_norms[i], functional=False,
                **(loss_kwargs or {}),
            )
            for i in range(n)
        ]
        self.sequential = SequentialAgentUpdate(n, weighted=self.weighted, shuffle=shuffle, generator=self.generator)
        # (actor, reward critic, cost critic) parameter lists per agent, for the per-network gradient clip
        self._networks_params = [
            tuple(list(m.parameters()) for m in (networks.agent_actor(i), networks.agent_critic(i),
                                                 networks.agent_cost_critic(i)))
            for i in range(n)
        ]
        self.optimizers = [
            torch.optim.Adam(self._param_groups(i, critic_lr), eps=adam_eps) for i in range(n)
        ]

    # ------------------------------------------------------------------ hooks
    def _loss_weighted(self) -> bool:
        return self.weighted

    def _param_groups(self, agent: int, critic_lr: float) -> list[dict[str, Any]]:
        """The agent's optimiser groups; the critics here, subclasses with an actor optimiser add it."""
        critics = [*self.networks.agent_critic(agent).parameters(), *self.networks.agent_cost_critic(agent).parameters()]
        return [{"params": critics, "lr": critic_lr}]

    @abc.abstractmethod
    def _update_agent(self, agent: int, view: TensorDictBase, factor: Tensor, episode_cost: float) -> dict[str, float]:
        """One agent's whole update for the round; returns its metrics (SafePO names)."""

    # ------------------------------------------------------------------ round
    def __call__(self, data: TensorDictBase, mean_episode_cost: float | Tensor) -> dict[str, float]:
        """One training round on ``data`` (see the module docstring for the keys).

        Returns:
            The team metrics (mean over agents) under SafePO's names, the same per agent under
            ``"<name>/agent<i>"``, and ``Train/AgentOrder/agent<i>`` (the stage at which agent ``i``
            was updated).
        """
        costs = self._episode_costs(mean_episode_cost)
        self._policy_now = None
        keys = self._view_keys()
        views = [agent_view(data, i, group=self.group, keys=keys) for i in range(self.n_agents)]
        size = views[0].batch_size[0]
        result = self.sequential.run(
            lambda i, factor: self._update_agent(i, views[i], factor, costs[i]),
            lambda i: self._log_prob(i, views[i]),
            size,
        )
        return self._aggregate(result)

    def _view_keys(self) -> tuple[str, ...]:
        keys = AGENT_VIEW_KEYS
        if self.losses[0].clip_value is not None:
            keys = (*keys, "state_value", "cost_value")
        return keys

    def _episode_costs(self, mean_episode_cost: float | Tensor) -> list[float]:
        value = torch.as_tensor(mean_episode_cost, dtype=torch.float64).detach().reshape(-1)
        if value.numel() == 1:
            value = value.expand(self.n_agents)
        if value.numel() != self.n_agents or not torch.isfinite(value).all():
            raise ValueError(
                f"mean_episode_cost must be one finite value or one per agent ({self.n_agents}), "
                f"got {mean_episode_cost!r}."
            )
        return value.tolist()

    def _log_prob(self, agent: int, view: TensorDictBase) -> Tensor:
        return self._dist(agent, view).log_prob(view.get("action"))

    def _dist(self, agent: int, view: TensorDictBase) -> D.Distribution:
        """The agent's policy on its view, as its parameters are now."""
        actor = self.networks.agent_actor(agent)
        return actor.get_dist(view.select(*actor.in_keys))

    def _aggregate(self, result: SequentialResult) -> dict[str, float]:
        per_name: dict[str, list[float]] = defaultdict(list)
        metrics: dict[str, float] = {}
        for position, stage in enumerate(result.stages):
            metrics[f"Train/AgentOrder/agent{stage.agent}"] = float(position)
            for name, value in stage.metrics.items():
                per_name[name].append(float(value))
                metrics[f"{name}/agent{stage.agent}"] = float(value)
        for name, values in per_name.items():
            metrics[name] = sum(values) / len(values)
        metrics["Train/LagrangeMultiplier"] = sum(float(m.value) for m in self.multipliers) / self.n_agents
        return metrics

    # ------------------------------------------------------------------ shared pieces
    def _gradient_step(
        self, agent: int, loss_fn: LossFn, terms: Sequence[str], *, actor: bool,
        after_step: Callable[[Mapping[str, Tensor]], None] | None = None,
    ) -> GradientStep:
        """One Adam step of the agent's optimiser on ``terms``, gradients clipped per network (SafePO).

        The actor (when ``actor``), the reward critic and the cost critic are clipped separately
        at ``max_grad_norm``; the critics' pre-clip norms are reported as
        ``Misc/Reward_critic_norm`` and ``Misc/Cost_critic_norm``.
        """
        actor_params, reward_params, cost_params = self._networks_params[agent]
        groups = (ClipGroup(reward_params, "Misc/Reward_critic_norm"), ClipGroup(cost_params, "Misc/Cost_critic_norm"))
        if actor:
            groups = (ClipGroup(actor_params), *groups)
        return GradientStep(loss_fn, self.optimizers[agent], tuple(terms), groups, self.max_grad_norm,
                            after_step=after_step)

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


class MultiAgentPPOUpdate(MultiAgentUpdate):
    """Sequential clipped-PPO epochs per agent: the body of MAPPO, HAPPO and MAPPO-Lag.

    For each agent in the round's order: up to ``epochs`` passes of ``num_minibatches`` Adam steps
    on :class:`AgentPPOLoss` (actor + reward critic + cost critic, gradient norms clipped per
    network), the agent's advantage multiplied by the factor :math:`M` when :attr:`weighted`, with
    the KL early stop after each pass; MAPPO-Lag also steps the agent's multiplier after every
    minibatch step (:attr:`steps_multiplier`).

    Keyword Args:
        actor_lr (float): defaults to ``5e-4`` (paper).
        epochs (int): passes over the batch per agent. Defaults to ``5`` (paper).
        num_minibatches (int): defaults to ``1`` (paper: the whole batch per step).
        target_kl (float, optional): KL early stop per agent. Defaults to ``0.016`` (paper);
            ``None`` disables it.
        **kwargs: see :class:`MultiAgentUpdate`.

    Per-agent metrics: ``Loss/Loss_actor``, ``Loss/Loss_reward_critic``, ``Loss/Loss_cost_critic``
    (means over the agent's steps), ``Misc/Reward_critic_norm``, ``Misc/Cost_critic_norm``
    (gradient norms before clipping), ``Misc/Entropy`` (policy entropy over the real action dims,
    after the update), ``Misc/Ratio`` (mean ratio to the behaviour policy), ``Misc/Factor`` (mean
    :math:`M` handed to the agent), ``Train/KL``, ``Train/StopIter`` (epochs run),
    ``Train/LagrangeMultiplier``.
    """

    #: Whether each agent's multiplier is stepped after every minibatch step (MAPPO-Lag).
    steps_multiplier: ClassVar[bool] = False

    def __init__(
        self,
        networks: MultiAgentNetworks,
        *,
        actor_lr: float = 5e-4,
        epochs: int = 5,
        num_minibatches: int = 1,
        target_kl: float | None = 0.016,
        **kwargs: Any,
    ) -> None:
        if epochs < 1 or num_minibatches < 1:
            raise ValueError(f"need epochs >= 1 and num_minibatches >= 1, got {epochs}, {num_minibatches}.")
        self.actor_lr = float(actor_lr)
        self.epochs = int(epochs)
        self.num_minibatches = int(num_minibatches)
        self.target_kl = None if target_kl is None else float(target_kl)
        super().__init__(networks, **kwargs)

    def _param_groups(self, agent: int, critic_lr: float) -> list[dict[str, Any]]:
        actor = {"params": list(self.networks.agent_actor(agent).parameters()), "lr": self.actor_lr}
        return [actor, *super()._param_groups(agent, critic_lr)]

    #: ``(agent, distribution)``: the agent's policy on its view at its current parameters, last evaluated by
    #: the sequential update's log-probability before the agent's update or by the KL after its last pass
    #: (nothing moves the agent in between), read once instead of a second forward pass; ``None`` otherwise.
    _policy_now: tuple[int, D.Distribution] | None = None

    def _dist(self, agent: int, view: TensorDictBase) -> D.Distribution:
        cached, self._policy_now = self._policy_now, None
        if cached is not None and cached[0] == agent:
            return cached[1]
        dist = super()._dist(agent, view)
        self._policy_now = (agent, dist)  # the policy before the agent's update: its epochs' reference
        return dist

    def _update_agent(self, agent: int, view: TensorDictBase, factor: Tensor, episode_cost: float) -> dict[str, float]:
        loss, multiplier = self.losses[agent], self.multipliers[agent]
        if self.weighted:
            view.set(loss.tensor_keys.factor, factor)
        with torch.no_grad():
            old = self._dist(agent, view)
            old_loc, old_scale = old.mean, old.stddev
        self._policy_now = None  # the steps below move the agent
        # the loss has a ``loss_entropy`` output exactly when its entropy bonus is on
        terms = ("loss_objective", "loss_critic", "loss_cost_critic", *(("loss_entropy",) if loss.entropy_bonus else ()))
        after_step = None
        if self.steps_multiplier:  # MAPPO-Lag: the multiplier moves after every minibatch step
            after_step = lambda out: multiplier.update(episode_cost, cost_surrogate=out["cost_surrogate"])  # noqa: E731
        epochs_run, kl, metrics = run_passes(
            view, self._gradient_step(agent, loss, terms, actor=True, after_step=after_step), passes=self.epochs,
            order=shuffled_chunks(self.num_minibatches), generator=self.generator,
            metrics={"Loss/Loss_actor": "loss_objective", **CRITIC_METRICS, "Misc/Ratio": "mean_ratio"},
            stop=lambda: self._kl(agent, view, old_loc, old_scale), target_kl=self.target_kl,
        )
        metrics.update({
            "Misc/Entropy": float(self.networks.agent_entropy(agent)),
            "Misc/Factor": float(factor.mean()),
            "Train/KL": kl,
            "Train/StopIter": float(epochs_run),
            "Train/LagrangeMultiplier": float(multiplier.value),
        })
        return metrics

    def _kl(self, agent: int, view: TensorDictBase, old_loc: Tensor, old_scale: Tensor) -> float:
        """Mean KL(old || current) of the agent's policy, summed over action dims (padding adds 0).

        The policy evaluated is kept for the sequential update's log-probability after the agent's update
        (the KL runs after every pass, the last one included, and nothing moves the agent after it).
        """
        with torch.no_grad():
            self._policy_now = None
            new = self._dist(agent, view)
            return gaussian_kl(old_loc, old_scale, new.mean, new.stddev).mean().item()


class MAPPOUpdate(MultiAgentPPOUpdate):
    """MAPPO (Yu et al. 2022) with per-agent networks: independent clipped PPO per agent.

    The agents still go through :class:`SequentialAgentUpdate` (SafePO's shared loop) but the
    factor is neither computed nor used, so the order does not matter: each agent's update depends
    on the batch and its own networks only. Costs are learned by the cost critics and logged, not
    optimised.
    """

    weighted = False


class HAPPOUpdate(MultiAgentPPOUpdate):
    """HAPPO (Kuba et al. 2022): each agent's clipped surrogate weighted by the earlier agents' ratio product.

    :math:`L^i = -\\mathbb E[M \\min(r^i A, \\mathrm{clip}(r^i, 1 \\pm \\epsilon) A)] - 0.01\\, H(\\pi^i)`
    with :math:`M` from :class:`SequentialAgentUpdate`. Unconstrained; costs are only learned and logged.
    """

    weighted = True


class MAPPOLagUpdate(MultiAgentPPOUpdate):
    """MAPPO-Lagrangian (Gu et al. 2023): HAPPO's sequential update on :math:`A_r - \\lambda^i A^i_c`.

    Each agent has a :class:`~sg_torchrl.objectives.multi_agent.MAPPOLagMultiplier`, stepped after
    every minibatch step from the rollout's mean episode cost and the step's cost surrogate
    :math:`\\mathbb E[r^i A^i_c]` (see that class for the rule and for the paper's vs SafePO's
    initial value and step size).

    Keyword Args:
        multiplier_init (float): initial :math:`\\lambda`. Defaults to ``1e-5`` (paper table).
        multiplier_lr (float): multiplier step size. Defaults to ``0.78`` (paper table).
        multipliers (sequence of Multiplier, optional): overrides the two options above.
        **kwargs: see :class:`MultiAgentPPOUpdate`.
    """

    weighted = True
    steps_multiplier = True

    def __init__(
        self,
        networks: MultiAgentNetworks,
        *,
        multiplier_init: float = 1e-5,
        multiplier_lr: float = 0.78,
        cost_limit: float = 25.0,
        gamma: float = 0.99,
        multipliers: Sequence[Multiplier] | None = None,
        **kwargs: Any,
    ) -> None:
        if multipliers is None:
            multipliers = [
                MAPPOLagMultiplier(cost_limit, init=multiplier_init, lr=multiplier_lr, gamma=gamma)
                for _ in range(networks.n_agents)
            ]
        super().__init__(networks, cost_limit=cost_limit, gamma=gamma, multipliers=multipliers, **kwargs)
