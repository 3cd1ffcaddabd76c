"""The multi-agent training loop behind ``sg-train --algo mappo|happo|mappo_lag|macpo``.

The Safety-Gymnasium paper's safe multi-agent benchmark (SafePO's ``multi_agent`` scripts) on
TorchRL's multi-agent layout (group ``("agents", ...)``, a global ``"state"``). One epoch:

1. collect ``steps_per_epoch`` team transitions from ``num_envs`` batched simulators with every
   agent's actor in one vmapped call (:class:`~sg_torchrl.collectors.RolloutCollector`, which takes
   the group layout as it is);
2. per-agent reward and cost GAE, standardised per agent
   (:func:`~sg_torchrl.objectives.multi_agent.make_multi_agent_gae`);
3. the algorithm's round (:data:`MULTI_AGENT_ALGORITHMS`, built from the multi-agent rows of
   :mod:`sg_torchrl.algorithms.manifest`): the agents updated one at a time in a
   random order. The mean cost of the episodes finished in the epoch is handed to the round;
   MAPPO-Lag steps each agent's multiplier inside the round, after every minibatch step, so the
   trainer updates no multiplier itself;
4. log team metrics under SafePO's names (means over agents) and the same per agent
   (``Loss/Loss_actor/agent0``, ``Train/LagrangeMultiplier/agent1``, ...), checkpoint.

One run's networks, GAEs and round are a :class:`MultiAgentTeam`, built and updated by the same code
for a single-seed run and for each seed of a seed group (``--seeds``,
:class:`~sg_torchrl.train.multi_agent_group.MultiAgentGroupTrainer`: one team and one round per seed,
the rounds run one after another, simulation and collection batched).

Episode statistics are the team's: the return of the shared reward and the team cost (the root
``"cost"``; on the velocity tasks every agent pays the same indicator).

Observations are normalised by default (``normalize_obs=True``): running mean / std of each agent's
observation (per agent and feature) and of the global state. SafePO's multi-agent scripts feed raw
observations, but to networks whose first layer is a LayerNorm of the input; our per-agent MLPs
(TorchRL's ``MultiAgentMLP``) have no such layer, and on raw observations their outputs follow the
observations' scale (Safety9|8HumanoidVelocity-v0: initial action means up to about 40, so the
control cost swamps the reward). ``--normalize-obs false`` feeds raw observations. Checkpoints hold the networks, the round's optimisers, multipliers, value
normalisers and generator, the observation normalisers, the simulators, the collector's carry,
the episode statistics and the torch RNG, so ``--resume`` continues bit-identically; they are
written and verified by :class:`~sg_torchrl.train.trainer.EpochTrainer` in the weights-only format of
:mod:`sg_torchrl.train.checkpoint`, on the same schedule as single-agent runs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import Compose, EnvBase, TransformedEnv

import sg_torchrl
from sg_torchrl import seeding
from sg_torchrl.collectors import EpisodeStats, RolloutCollector
from sg_torchrl.envs.multi_agent import GROUP
from sg_torchrl.envs.normalization import RunningObservationNorm
from sg_torchrl.algorithms import manifest
from sg_torchrl.algorithms.manifest import AlgorithmEntry
from sg_torchrl.objectives.multi_agent import (
    make_multi_agent_cost_gae,
    make_multi_agent_gae,
    make_multi_agent_networks,
    MultiAgentNetworks,
    MultiAgentUpdate,
)
from sg_torchrl.train.config import TrainConfig
from sg_torchrl.train.evaluate import evaluate_policy
from sg_torchrl.train.trainer import EpochTrainer

__all__ = [
    "MULTI_AGENT_ALGORITHMS", "MultiAgentAlgorithm", "MultiAgentTeam", "MultiAgentTrainer", "num_minibatches",
    "observation_norms",
]

MakeUpdate = Callable[[MultiAgentNetworks, TrainConfig, torch.Generator], MultiAgentUpdate]


@dataclass(frozen=True)
class MultiAgentAlgorithm:
    """How to build one multi-agent algorithm's round from the team's networks and a config."""

    title: str
    make_update: MakeUpdate


def num_minibatches(cfg: TrainConfig) -> int:
    """Minibatches per epoch so that none exceeds ``minibatch_size`` samples (1 at the paper's defaults)."""
    return max(1, -(-cfg.steps_per_epoch // cfg.minibatch_size))


def _common(cfg: TrainConfig, generator: torch.Generator) -> dict[str, Any]:
    """Options every round takes (:class:`~sg_torchrl.objectives.multi_agent.MultiAgentUpdate`)."""
    options: dict[str, Any] = dict(
        cost_limit=cfg.cost_limit, gamma=cfg.gamma, critic_lr=cfg.critic_lr, max_grad_norm=cfg.max_grad_norm,
        clip_epsilon=cfg.clip_ratio, generator=generator,
    )
    if cfg.critic_l2:
        options["loss_kwargs"] = {"critic_l2_coeff": cfg.critic_l2}
    return options


def _ppo_round(entry: AlgorithmEntry) -> MakeUpdate:
    """A first-order row's round (MAPPO, HAPPO, MAPPO-Lag): its round class, with the multiplier's options
    when the row has a Lagrange multiplier (MAPPO-Lag's, one per agent)."""
    update_class = entry.round_class()

    def make(networks: MultiAgentNetworks, cfg: TrainConfig, generator: torch.Generator) -> MultiAgentUpdate:
        options = dict(actor_lr=cfg.actor_lr, epochs=cfg.update_iters, num_minibatches=num_minibatches(cfg),
                       target_kl=cfg.target_kl, **_common(cfg, generator))
        if entry.multiplier == "lagrange":
            options.update(multiplier_init=cfg.lagrangian_init, multiplier_lr=cfg.lagrangian_lr)
        return update_class(networks, **options)

    return make


def _cpo_round(entry: AlgorithmEntry) -> MakeUpdate:
    """A CPO-step row's round (MACPO): one trust-region step per agent, then critic epochs."""
    update_class = entry.round_class()

    def make(networks: MultiAgentNetworks, cfg: TrainConfig, generator: torch.Generator) -> MultiAgentUpdate:
        return update_class(
            networks, target_kl=cfg.target_kl, cg_iters=cfg.cg_iters, cg_damping=cfg.cg_damping,
            line_search_steps=cfg.line_search_steps, step_fraction=cfg.step_fraction,
            critic_epochs=cfg.update_iters, num_minibatches=num_minibatches(cfg), **_common(cfg, generator),
        )

    return make


#: Round builders by a multi-agent row's update kind.
_ROUNDS: dict[str, Callable[[AlgorithmEntry], MakeUpdate]] = {"first_order": _ppo_round, "cpo": _cpo_round}

#: The multi-agent algorithms of the Safety-Gymnasium paper, by ``--algo`` name (the manifest's multi-agent rows).
MULTI_AGENT_ALGORITHMS: dict[str, MultiAgentAlgorithm] = {
    entry.name: MultiAgentAlgorithm(entry.title, _ROUNDS[entry.update](entry))
    for entry in manifest.rows(agents="multi")
}


def observation_norms(env: EnvBase, group: str = GROUP, *, groups: int | None = None) -> list[RunningObservationNorm]:
    """Running normalisers of ``(group, "observation")`` (statistics per agent and feature) and ``"state"``.

    ``groups``: one row of statistics per block of simulators (a seed group's seeds,
    :class:`~sg_torchrl.envs.normalization.RunningObservationNorm`).
    """
    observation = env.observation_spec[group, "observation"].shape[-2:]
    state = env.observation_spec["state"].shape[-1:]
    return [
        RunningObservationNorm(observation, in_keys=[(group, "observation")], groups=groups),
        RunningObservationNorm(state, in_keys=["state"], groups=groups),
    ]


@dataclass
class MultiAgentTeam:
    """One multi-agent run's learning parts: the team's networks, both GAEs and the algorithm's round.

    Built by :meth:`build` for the single-seed :class:`MultiAgentTrainer` and for each seed of a
    seed group (:class:`~sg_torchrl.train.multi_agent_group.MultiAgentGroupTrainer`) alike, so a
    seed's team is its single-seed run's. :meth:`learn` is one epoch's update of the team.
    """

    networks: MultiAgentNetworks
    reward_gae: TensorDictModuleBase
    cost_gae: TensorDictModuleBase
    #: Agent orders and minibatch shuffles; its state is part of the round's state dict.
    update_rng: torch.Generator
    policy_update: MultiAgentUpdate

    @classmethod
    def build(cls, env: EnvBase, cfg: TrainConfig) -> MultiAgentTeam:
        """The team of ``cfg.algo`` for ``env``'s agents; the round's generator is seeded with ``cfg.seed``.

        The networks are initialised from the global torch RNG (as it stands: the caller seeds it).
        """
        networks = make_multi_agent_networks(
            env.observation_dim, env.action_sizes, env.state_dim, hidden_sizes=cfg.network_sizes, group=GROUP
        )
        update_rng = seeding.generator(cfg.seed, seeding.Purpose.MINIBATCHES)
        return cls(
            networks=networks,
            reward_gae=make_multi_agent_gae(networks.reward_critic, gamma=cfg.gamma, lmbda=cfg.gae_lambda),
            cost_gae=make_multi_agent_cost_gae(networks.cost_critic, gamma=cfg.gamma, lmbda=cfg.cost_gae_lambda),
            update_rng=update_rng,
            policy_update=MULTI_AGENT_ALGORITHMS[cfg.algo].make_update(networks, cfg, update_rng),
        )

    def learn(self, batch: TensorDictBase, mean_episode_cost: float, actor_lr: float) -> dict[str, float]:
        """Per-agent GAEs on the ``(N, T)`` batch, then the round (which steps MAPPO-Lag's multipliers)."""
        with torch.no_grad():
            self.reward_gae(batch)
            self.cost_gae(batch)
        info = self.policy_update(batch, mean_episode_cost)
        return {"Train/LagrangeMultiplier": info.pop("Train/LagrangeMultiplier"), "Train/LR": actor_lr, **info}


class MultiAgentTrainer(EpochTrainer):
    """Build everything a multi-agent run needs from a :class:`TrainConfig` and run its epochs.

    Attributes: ``team`` (:class:`MultiAgentTeam`) and its parts ``networks``
    (:class:`~sg_torchrl.objectives.multi_agent.MultiAgentNetworks`: one actor, reward critic and cost
    critic per agent), ``policy_update`` (the algorithm's round), ``reward_gae`` / ``cost_gae``;
    ``env`` / ``base_env``, ``obs_norms``, ``collector``, ``stats``.

    Args:
        cfg: the experiment (a multi-agent ``algo`` and env id).
        checkpoint: a checkpoint dict (from :meth:`load_checkpoint`) to continue from.
    """

    def __init__(self, cfg: TrainConfig, checkpoint: dict[str, Any] | None = None) -> None:
        if not cfg.multi_agent:
            raise ValueError(f"MultiAgentTrainer runs the multi-agent algorithms, not {cfg.algo!r} (use SingleSeedGroupTrainer)")
        super().__init__(cfg)
        self.algorithm = MULTI_AGENT_ALGORITHMS[cfg.algo]
        self.title = self.algorithm.title
        self.base_env = sg_torchrl.make(cfg.env_id, num_envs=cfg.num_envs,
                                        seed=seeding.env_seed(cfg.seed, seeding.Purpose.SIMULATORS), **cfg.env_options)
        self.obs_norms = observation_norms(self.base_env) if cfg.normalize_obs else []
        self.env: EnvBase = TransformedEnv(self.base_env, Compose(*self.obs_norms)) if self.obs_norms else self.base_env

        team = MultiAgentTeam.build(self.base_env, cfg)
        self.networks, self.reward_gae, self.cost_gae = team.networks, team.reward_gae, team.cost_gae
        self.update_rng, self.policy_update = team.update_rng, team.policy_update
        self.team = team
        self.collector = RolloutCollector(self.env, self.networks.actor, steps=cfg.steps_per_epoch // cfg.num_envs)
        self.stats = EpisodeStats(reward_key=("next", GROUP, "reward"), agent_dim=-2)
        self._start(checkpoint)

    # ------------------------------------------------------------------ epochs
    def _learn(self, batch: TensorDictBase) -> dict[str, float]:
        """Per-agent GAEs on the ``(N, T)`` batch, then the algorithm's round (:meth:`MultiAgentTeam.learn`)."""
        return self.team.learn(batch, self._last_mean_cost, self.cfg.actor_lr)

    def _evaluate(self) -> dict[str, float]:
        cfg = self.cfg
        return evaluate_policy(cfg.env_id, self.networks.actor, cfg.eval_episodes,
                               seed=seeding.env_seed(cfg.seed, seeding.Purpose.EVALUATION),
                               obs_norm=self.obs_norms, env_options=cfg.env_options)

    # ------------------------------------------------------------------ checkpoints
    def _algorithm_state(self) -> dict[str, Any]:
        return {
            "networks": self.networks.state_dict(),
            "update": self.policy_update.state_dict(),
            "obs_norms": [norm.state_dict() for norm in self.obs_norms],
        }

    def _load_algorithm_state(self, state: dict[str, Any]) -> None:
        self.networks.load_state_dict(state["networks"])
        self.policy_update.load_state_dict(state["update"])
        for norm, norm_state in zip(self.obs_norms, state["obs_norms"], strict=True):
            norm.load_state_dict(norm_state)
