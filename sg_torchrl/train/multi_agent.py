"""The multi-agent algorithms behind ``sg-train --algo mappo|happo|mappo_lag|macpo``, and one run's team.

The Safety-Gymnasium paper's safe multi-agent benchmark (SafePO's ``multi_agent`` scripts) on
TorchRL's multi-agent layout (group ``("agents", ...)``, a global ``"state"``). One epoch of a run:

1. collect ``steps_per_epoch`` team transitions from ``num_envs`` batched simulators with every
   agent's actor in one vmapped call (:class:`~sg_torchrl.collectors.RolloutCollector`, which takes
   the group layout as it is);
2. per-agent reward and cost GAE, standardised per agent
   (:func:`~sg_torchrl.objectives.multi_agent.make_multi_agent_gae`);
3. the algorithm's round (:data:`MULTI_AGENT_ALGORITHMS`, built from the multi-agent rows of
   :mod:`sg_torchrl.algorithms.manifest` for all seeds of the engine at once, the round class's
   ``for_seeds``): the agents updated one at a time in a random order per seed. The mean cost of the
   episodes finished in the epoch is handed to the round;
   MAPPO-Lag steps each agent's multiplier inside the round, after every minibatch step, so the
   trainer updates no multiplier itself;
4. log team metrics under SafePO's names (means over agents) and the same per agent
   (``Loss/Loss_actor/agent0``, ``Train/LagrangeMultiplier/agent1``, ...), checkpoint.

Step 2 is one run's :class:`MultiAgentTeam` (its networks and GAEs). The engine that runs the epochs is
:mod:`sg_torchrl.train.multi_agent_group`: one team per seed and one round for all seeds, S >= 1
(:class:`~sg_torchrl.train.multi_agent_group.MultiAgentGroupTrainer`: ``--seeds`` or, with S = 1,
``--seed s``).

Episode statistics are the team's: the return of the shared reward and the team cost (the root
``"cost"``; on the velocity tasks every agent pays the same indicator).

Observations are normalised by default (``normalize_obs=True``): running mean / std of each agent's
observation (per agent and feature) and of the global state (:func:`observation_norms`). SafePO's
multi-agent scripts feed raw observations, but to networks whose first layer is a LayerNorm of the
input; our per-agent MLPs (TorchRL's ``MultiAgentMLP``) have no such layer, and on raw observations
their outputs follow the observations' scale (Safety9|8HumanoidVelocity-v0: initial action means up to
about 40, so the control cost swamps the reward). ``--normalize-obs false`` feeds raw observations.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from sg_torchrl.envs.multi_agent import GROUP
from sg_torchrl.envs.normalization import RunningObservationNorm
from sg_torchrl.algorithms import manifest
from sg_torchrl.algorithms.manifest import AlgorithmEntry
from sg_torchrl.modules.multi_agent import make_multi_agent_networks, MultiAgentNetworks
from sg_torchrl.modules.stacked_multi_agent import StackedMultiAgentNetworks
from sg_torchrl.objectives.multi_agent import make_multi_agent_cost_gae, make_multi_agent_gae
from sg_torchrl.train.config import TrainConfig

__all__ = ["MULTI_AGENT_ALGORITHMS", "MultiAgentAlgorithm", "MultiAgentTeam", "make_team_networks", "num_minibatches",
           "observation_norms"]

#: ``make_round(networks, cfg, generators)``: the round of S seeds' stacked teams, one generator per seed. The
#: round answers ``step_seeds(batches, mean_episode_costs)``, ``seed_state_dict(s)``, ``load_seed_state_dict(s, state)``.
MakeRound = Callable[[StackedMultiAgentNetworks, TrainConfig, Sequence[torch.Generator]], Any]


@dataclass(frozen=True)
class MultiAgentAlgorithm:
    """How to build one multi-agent algorithm's round for S seeds' stacked teams from a config."""

    title: str
    make_round: MakeRound


def num_minibatches(cfg: TrainConfig) -> int:
    """Minibatches per epoch so that none exceeds ``minibatch_size`` samples (1 at the paper's defaults)."""
    return max(1, -(-cfg.steps_per_epoch // cfg.minibatch_size))


def _round_builder(entry: AlgorithmEntry) -> MakeRound:
    """A multi-agent row's round builder: its round class with the config's options, those of every round and
    the update kind's: MACPO's CPO step and critic epochs (``cpo``), or the clipped-PPO epochs (``first_order``)
    with the multiplier's options when the row has a Lagrange multiplier (MAPPO-Lag's, one per agent)."""
    if entry.update not in ("first_order", "cpo"):
        raise ValueError(f"algorithm {entry.name!r}: no multi-agent round for update kind {entry.update!r}")
    update_class = entry.round_class()

    def make(networks: StackedMultiAgentNetworks, cfg: TrainConfig, generators: Sequence[torch.Generator]) -> Any:
        options: dict[str, Any] = dict(
            cost_limit=cfg.cost_limit, gamma=cfg.gamma, critic_lr=cfg.critic_lr, max_grad_norm=cfg.max_grad_norm,
            clip_epsilon=cfg.clip_ratio, num_minibatches=num_minibatches(cfg), target_kl=cfg.target_kl,
        )
        if cfg.critic_l2:
            options["loss_kwargs"] = {"critic_l2_coeff": cfg.critic_l2}
        if entry.update == "cpo":
            options.update(cg_iters=cfg.cg_iters, cg_damping=cfg.cg_damping, line_search_steps=cfg.line_search_steps,
                           step_fraction=cfg.step_fraction, critic_epochs=cfg.update_iters)
        else:
            options.update(actor_lr=cfg.actor_lr, epochs=cfg.update_iters)
            if entry.multiplier == "lagrange":
                options.update(multiplier_init=cfg.lagrangian_init, multiplier_lr=cfg.lagrangian_lr)
        return update_class.for_seeds(networks, generators, **options)

    return make


#: The multi-agent algorithms of the Safety-Gymnasium paper, by ``--algo`` name (the manifest's multi-agent rows).
MULTI_AGENT_ALGORITHMS: dict[str, MultiAgentAlgorithm] = {
    entry.name: MultiAgentAlgorithm(entry.title, _round_builder(entry))
    for entry in manifest.rows(agents="multi")
}


def observation_norms(env: EnvBase, *, groups: int) -> list[RunningObservationNorm]:
    """Running normalisers of ``("agents", "observation")`` (statistics per agent and feature) and ``"state"``.

    ``groups``: one row of statistics per block of simulators (a seed group's seeds,
    :class:`~sg_torchrl.envs.normalization.RunningObservationNorm`).
    """
    observation = env.observation_spec[GROUP, "observation"].shape[-2:]
    state = env.observation_spec["state"].shape[-1:]
    return [
        RunningObservationNorm(observation, in_keys=[(GROUP, "observation")], groups=groups),
        RunningObservationNorm(state, in_keys=["state"], groups=groups),
    ]


def make_team_networks(env: EnvBase, cfg: TrainConfig) -> MultiAgentNetworks:
    """A team's networks for ``env``'s agents at ``cfg``'s sizes, initialised from the global torch RNG (a run's
    team, and the networks a loaded policy's checkpoint entry is read into)."""
    return make_multi_agent_networks(
        env.observation_dim, env.action_sizes, env.state_dim, hidden_sizes=cfg.network_sizes, group=GROUP
    )


@dataclass
class MultiAgentTeam:
    """One multi-agent run's team: its networks and both GAEs.

    Built by :meth:`build` for each seed of the multi-agent engine
    (:class:`~sg_torchrl.train.multi_agent_group.MultiAgentGroupTrainer`; one seed for ``--seed s``), so a
    seed's team in a group is its single-seed run's. :meth:`estimate_advantages` is step 2 of an epoch.
    """

    networks: MultiAgentNetworks
    reward_gae: TensorDictModuleBase
    cost_gae: TensorDictModuleBase

    @classmethod
    def build(cls, env: EnvBase, cfg: TrainConfig) -> MultiAgentTeam:
        """The team for ``env``'s agents, initialised from the global torch RNG (as it stands: the caller seeds it)."""
        networks = make_team_networks(env, cfg)
        return cls(
            networks=networks,
            reward_gae=make_multi_agent_gae(networks.reward_critic, gamma=cfg.gamma, lmbda=cfg.gae_lambda),
            cost_gae=make_multi_agent_cost_gae(networks.cost_critic, gamma=cfg.gamma, lmbda=cfg.cost_gae_lambda),
        )

    def to(self, device: torch.device | str) -> MultiAgentTeam:
        """Move the networks and both GAEs to ``device`` (built on the CPU, from the global RNG); returns the team."""
        self.networks.to(device)
        self.reward_gae.to(device)
        self.cost_gae.to(device)
        return self

    @torch.no_grad()
    def estimate_advantages(self, batch: TensorDictBase) -> None:
        """Per-agent reward and cost GAEs on the ``(N, T)`` batch, written into it."""
        self.reward_gae(batch)
        self.cost_gae(batch)
