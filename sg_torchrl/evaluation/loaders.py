"""One loader per kind of run: a seed's checkpoint entry -> its :class:`~sg_torchrl.evaluation.networks.TrainedPolicy`.

:func:`loader_for` picks the loader from the algorithm manifest's ``agents`` and ``family`` fields
(:mod:`sg_torchrl.algorithms.manifest`), so a new row of a known kind loads with no change here:

* single-agent on-policy (first and second order): :func:`load_actor_policy`, the seed-group engine's actor
  (:func:`~sg_torchrl.modules.mlp.make_actor`) and its observation normaliser;
* single-agent off-policy (SAC, TD3, DDPG and their -Lag / -PID forms): :func:`load_off_policy_policy`, the
  actor of :func:`~sg_torchrl.modules.off_policy.make_off_policy_networks`, as the engine's
  :func:`~sg_torchrl.train.off_policy.off_policy_network_options` build it (no normaliser: the family
  takes none);
* multi-agent (MAPPO, HAPPO, MAPPO-Lag, MACPO): :func:`load_team_policy`, the team's per-agent actors
  (:func:`~sg_torchrl.train.multi_agent.make_team_networks`) reading ``("agents", "observation")`` and
  writing ``("agents", "action")``, with the per-agent observation normaliser (the state's is the critics'
  alone and has no part in the actions).

Each rebuilds its actor with the engine's own builder, loads the entry's weights into it (a clear
:class:`~sg_torchrl.train.checkpoint.CheckpointError` when they do not fit) and folds the frozen normaliser
in. A loader's arguments: the run read (:class:`~sg_torchrl.evaluation.policy.RunCheckpoint`), the seed, its
entry (:func:`~sg_torchrl.train.seed_runs.seed_entry`), its config, the device.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

import sg_torchrl
from sg_torchrl.algorithms import manifest
from sg_torchrl.envs.multi_agent import GROUP
from sg_torchrl.envs.normalization import RunningObservationNorm
from sg_torchrl.evaluation.networks import ObservationScaler, OffPolicyActorNetwork, PolicyNetwork, TrainedPolicy
from sg_torchrl.modules.mlp import ObservationLayout, make_actor
from sg_torchrl.modules.off_policy import make_off_policy_networks
from sg_torchrl.train.checkpoint import CheckpointError
from sg_torchrl.train.config import TrainConfig
from sg_torchrl.train.multi_agent import make_team_networks, observation_norms
from sg_torchrl.train.off_policy import off_policy_network_options

if TYPE_CHECKING:
    from sg_torchrl.evaluation.policy import RunCheckpoint

__all__ = ["LOADERS", "Loader", "load_actor_policy", "load_off_policy_policy", "load_team_policy", "loader_for"]

Loader = Callable[["RunCheckpoint", int, dict[str, Any], TrainConfig, "torch.device | str"], TrainedPolicy]


@contextmanager
def _env_of(config: TrainConfig) -> Iterator[Any]:
    """A one-simulator env of the run (its specs: what the actor reads and writes)."""
    env = sg_torchrl.make(config.env_id, num_envs=1, **config.env_options)
    try:
        yield env
    finally:
        env.close()


def _load_weights(module: nn.Module, state: dict[str, Any], run: RunCheckpoint, seed: int) -> None:
    try:
        module.load_state_dict(state)
    except (KeyError, RuntimeError) as error:
        raise CheckpointError(f"seed {seed}'s actor in {run.path} does not fit the networks its config describes "
                              f"({str(error).splitlines()[0]})") from None


def _built(build: Callable[[], Any]) -> Any:
    """``build()`` with the global torch RNG left as it was (the initial weights are overwritten at once)."""
    with torch.random.fork_rng(devices=[]):
        return build()


def _policy(network: nn.Module, run: RunCheckpoint, seed: int, entry: dict[str, Any], config: TrainConfig,
            device: torch.device | str, **keys: Any) -> TrainedPolicy:
    network = network.requires_grad_(False).eval().to(device)
    return TrainedPolicy(network, config=config, seed=seed, epoch=int(run.state["epoch"]),
                         diverged=entry.get("diverged"), **keys)


def _single_agent_keys(env: Any) -> dict[str, Any]:
    layout = ObservationLayout.from_spec(env.observation_spec)
    shapes = {key: (layout.vector_dim,) if key == "observation" else (*layout.image_shape, 3 if key == "pixels" else 1)
              for key in layout.in_keys}
    return {"layout": layout, "in_keys": layout.in_keys, "out_key": "action", "input_shapes": shapes,
            "action_spec": env.action_spec[0].clone()}


def load_actor_policy(run: RunCheckpoint, seed: int, entry: dict[str, Any], config: TrainConfig,
                      device: torch.device | str = "cpu") -> TrainedPolicy:
    """A single-agent on-policy seed: its Gaussian actor, its observation normaliser (if it had one) folded in."""
    with _env_of(config) as env:
        keys = _single_agent_keys(env)
    layout = keys["layout"]
    actor = _built(lambda: make_actor(layout, keys["action_spec"], config.network_sizes))
    _load_weights(actor, entry["networks"]["actor"], run, seed)
    scaler = None
    if entry.get("obs_norm") is not None:  # the seed's normaliser as its trainer had it (its epsilon)
        norm = RunningObservationNorm((layout.vector_dim,))
        norm.load_state_dict(entry["obs_norm"])
        scaler = ObservationScaler(norm.mean, norm.var, norm.epsilon)
    network = PolicyNetwork(actor.module[0].module, layout.in_keys, scaler)  # make_actor's Gaussian head
    return _policy(network, run, seed, entry, config, device, **keys)


def load_off_policy_policy(run: RunCheckpoint, seed: int, entry: dict[str, Any], config: TrainConfig,
                           device: torch.device | str = "cpu") -> TrainedPolicy:
    """An off-policy seed: its actor (SAC's squashed Gaussian, TD3's / DDPG's deterministic one), no normaliser."""
    with _env_of(config) as env:
        keys = _single_agent_keys(env)
    options = off_policy_network_options(config.algo)
    spec = keys["action_spec"]
    actor = _built(lambda: make_off_policy_networks(keys["layout"].vector_dim, spec, config.network_sizes,
                                                    **options)[0])
    _load_weights(actor, entry["networks"]["actor"], run, seed)
    network = OffPolicyActorNetwork.from_actor(actor, stochastic=options["stochastic"])
    return _policy(network, run, seed, entry, config, device, **keys)


def load_team_policy(run: RunCheckpoint, seed: int, entry: dict[str, Any], config: TrainConfig,
                     device: torch.device | str = "cpu") -> TrainedPolicy:
    """A multi-agent seed: the team's per-agent actors in one module, its per-agent normaliser folded in."""
    observation = (GROUP, "observation")
    with _env_of(config) as env:
        networks = _built(lambda: make_team_networks(env, config))
        norms = observation_norms(env, groups=1) if entry.get("obs_norms") else []
        input_shape = tuple(env.observation_spec[observation].shape[1:])
        action_spec = env.full_action_spec[env.action_key][0].clone()
    _load_weights(networks, entry["networks"], run, seed)
    scaler = None
    for norm, state in zip(norms, entry.get("obs_norms") or [], strict=True):  # the engine's order
        if observation in norm.in_keys:
            norm.load_group_state_dict(0, state)
            own = norm.group_copy(0)  # the seed's normaliser as its evaluation had it
            scaler = ObservationScaler(own.mean, own.var, own.epsilon)
    network = PolicyNetwork(networks.policy, [observation], scaler, normalized_key=observation)
    return _policy(network, run, seed, entry, config, device, in_keys=[observation], out_key=(GROUP, "action"),
                   input_shapes={observation: input_shape}, action_spec=action_spec)


#: The loader of each kind of run, by the manifest's ``(agents, family)``.
LOADERS: dict[tuple[str, str], Loader] = {
    ("single", "first_order"): load_actor_policy,
    ("single", "second_order"): load_actor_policy,
    ("single", "off_policy"): load_off_policy_policy,
    ("multi", "first_order"): load_team_policy,
    ("multi", "second_order"): load_team_policy,
}


def loader_for(config: TrainConfig) -> Loader:
    """The loader of ``config``'s algorithm (its manifest row's ``agents`` and ``family``).

    Raises:
        CheckpointError: no loader for that kind of run.
    """
    entry = manifest.get(config.algo)
    try:
        return LOADERS[entry.agents, entry.family]
    except KeyError:
        raise CheckpointError(f"{entry.title} is a {entry.agents}-agent {entry.family} algorithm, whose policies "
                              f"cannot be loaded by this sg_torchrl") from None
