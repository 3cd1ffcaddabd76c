"""A trained single-agent policy read back from an ``sg-train`` run: :func:`load_policy`.

A run keeps its networks in its checkpoint (:mod:`sg_torchrl.train.checkpoint`: a sha256-checked file
loaded with ``weights_only``, so loading never runs code): one entry per seed, the actor as the state
dict of the module :func:`~sg_torchrl.modules.mlp.make_actor` builds and the seed's observation
normaliser as an ungrouped :class:`~sg_torchrl.envs.normalization.RunningObservationNorm` state dict
(:func:`~sg_torchrl.train.seed_runs.seed_entry`). :func:`load_policy` rebuilds that actor and folds the
frozen normaliser in front of it:

* :class:`PolicyNetwork`: plain tensors in, ``(loc, scale)`` out, the normalisation included; what
  :func:`~sg_torchrl.evaluation.export.export_policy` exports;
* :class:`TrainedPolicy`: the TorchRL policy, a ``TensorDictModule`` reading the raw ``"observation"``
  (and ``"pixels"`` / ``"depth"`` for pixel runs) and writing ``"action"``: the mean action unless the
  exploration type says ``RANDOM`` (TorchRL's ``set_exploration_type``), and :meth:`TrainedPolicy.act`
  for numpy users.

Its actions are those of the trainer's own end-of-training evaluation, bit for bit: the same actor
weights and the same normalisation arithmetic (:class:`ObservationScaler`, RunningObservationNorm's
frozen formula, checked against it in ``tests/test_evaluation.py``).

Multi-agent runs are refused for now (their teams' networks have another checkpoint layout).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor, nn
from torchrl.data import TensorSpec
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import IndependentNormal

import sg_torchrl
from sg_torchrl.envs.normalization import RunningObservationNorm, standardize
from sg_torchrl.modules.mlp import ObservationLayout, make_actor
from sg_torchrl.train import refuse_retired_checkpoint
from sg_torchrl.train.checkpoint import CHECKPOINT_NAME, CheckpointError, checkpoint_file, load_checkpoint
from sg_torchrl.train.config import RETIRED_FIELDS, TrainConfig
from sg_torchrl.train.seed_runs import seed_entry

__all__ = ["ObservationScaler", "PolicyLoadError", "PolicyNetwork", "RunCheckpoint", "TrainedPolicy",
           "load_policy", "read_run"]

_SEED_DIR = re.compile(r"seed-(\d+)")
_DETERMINISTIC = (None, ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN)


class PolicyLoadError(ValueError):
    """A run whose policy cannot be loaded as asked (a missing or unknown seed, a multi-agent run, ...)."""


class ObservationScaler(nn.Module):
    """A frozen :class:`~sg_torchrl.envs.normalization.RunningObservationNorm` (one set of statistics) as a
    tensor module: :func:`~sg_torchrl.envs.normalization.standardize`, back in ``x``'s dtype, as the
    transform computes it (the same operations in the same order, so the same bits)."""

    def __init__(self, mean: Tensor, var: Tensor, epsilon: float = 1e-8) -> None:
        super().__init__()
        self.register_buffer("mean", mean.detach().to(torch.float64).clone())
        self.register_buffer("var", var.detach().to(torch.float64).clone())
        self.epsilon = float(epsilon)

    def forward(self, x: Tensor) -> Tensor:
        return standardize(x, self.mean, self.var, self.epsilon).to(x.dtype)


class PolicyNetwork(nn.Module):
    """The actor's Gaussian head with the observation normaliser folded in: raw inputs -> ``(loc, scale)``.

    ``forward(*inputs)`` takes the entries of ``in_keys`` (``ObservationLayout.in_keys``: ``pixels``,
    ``depth``, ``observation``, those the run reads) as tensors with any leading batch dims; only the
    flat ``observation`` is normalised (images are scaled inside the network, as in training).
    """

    def __init__(self, actor: nn.Module, in_keys: list[str], scaler: ObservationScaler | None) -> None:
        super().__init__()
        self.head = actor.module[0].module  # make_actor's (network, state-independent scale) chain
        self.in_keys = list(in_keys)
        self.scaler = scaler
        self._observation = self.in_keys.index("observation") if "observation" in self.in_keys else -1

    def forward(self, *inputs: Tensor) -> tuple[Tensor, Tensor]:
        if self.scaler is not None and self._observation >= 0:
            inputs = tuple(self.scaler(x) if i == self._observation else x for i, x in enumerate(inputs))
        loc, scale = self.head(*inputs)
        return loc, scale.expand_as(loc)


@dataclass(frozen=True)
class RunCheckpoint:
    """A run's checkpoint read for its policies: where it is, its config and which seeds it holds.

    ``default_seed``: the seed a path inside a group names (``seeds-0-1/seed-001``), else ``None``.
    """

    path: Path
    state: dict[str, Any]
    config: TrainConfig
    seeds: list[int]
    default_seed: int | None = None

    @property
    def group(self) -> bool:
        return self.config.group

    def pick_seed(self, seed: int | None) -> int:
        """The seed to load: ``seed``, or the run's only one; a clear error for a group without ``seed=``."""
        seed = self.default_seed if seed is None else seed
        if seed is None:
            if self.group:
                raise PolicyLoadError(f"{self.path.parent} is a seed group (seeds {_listed(self.seeds)}): give the "
                                      f"seed whose policy to load (seed=... / --seeds ...)")
            return self.seeds[0]
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or int(seed) not in self.seeds:
            raise PolicyLoadError(f"seed {seed!r} is not in the run {self.path.parent}: it holds seed"
                                  f"{'s' if len(self.seeds) > 1 else ''} {_listed(self.seeds)}")
        return int(seed)


def _listed(seeds: list[int]) -> str:
    return ", ".join(map(str, seeds))


def read_run(run_dir: str | Path) -> RunCheckpoint:
    """Read the checkpoint of a run: a run directory, a seed group's directory, one of its ``seed-XXX/``
    directories, or a checkpoint file.

    Raises:
        FileNotFoundError: no checkpoint there (committed benchmark runs keep none).
        CheckpointError: a damaged, foreign or retired checkpoint, or a config this version cannot read.
        PolicyLoadError: a multi-agent run.
    """
    path = Path(run_dir)
    default_seed = None
    if not path.exists():
        raise FileNotFoundError(f"no run at {path}")
    if path.is_dir() and not (path / CHECKPOINT_NAME).is_file():
        match = _SEED_DIR.fullmatch(path.name)
        if match and (path.parent / CHECKPOINT_NAME).is_file():  # a seed's directory inside its group's
            path, default_seed = path.parent, int(match[1])
        else:
            raise FileNotFoundError(f"no checkpoint in {path} (a run keeps its policy in {CHECKPOINT_NAME}; "
                                    f"directories that keep only logs and summaries, such as committed "
                                    f"benchmark runs, cannot be evaluated)")
    file = checkpoint_file(path)
    state = load_checkpoint(file)
    refuse_retired_checkpoint(state, file)
    try:
        config = TrainConfig.from_saved(state["config"])
    except (TypeError, ValueError) as error:
        unknown = sorted(set(state["config"]) - set(TrainConfig.__dataclass_fields__) - set(RETIRED_FIELDS))
        why = f"fields this sg_torchrl does not know ({', '.join(unknown)})" if unknown else str(error)
        raise CheckpointError(f"the config saved in {file} cannot be read: {why}") from None
    if config.multi_agent:
        raise PolicyLoadError(f"{file} is a multi-agent run ({config.algo} on {config.env_id}): loading and "
                              f"evaluating multi-agent policies is not supported yet (single-agent runs only)")
    seeds = [int(entry["seed"]) for entry in state.get("seeds") or []]
    if not seeds:
        raise CheckpointError(f"{file} holds no seed entries: not a checkpoint of this sg_torchrl's trainers")
    if default_seed is not None and default_seed not in seeds:
        raise PolicyLoadError(f"{run_dir} names seed {default_seed}, which its group {path} does not hold "
                              f"(seeds {_listed(seeds)})")
    return RunCheckpoint(file, state, config, seeds, default_seed)


class TrainedPolicy(TensorDictModuleBase):
    """One seed's trained actor with its frozen observation normaliser folded in (a TorchRL policy).

    Reads :attr:`in_keys` (the raw env entries: ``"observation"``, and ``"pixels"`` / ``"depth"`` for
    pixel runs) and writes ``"action"``: the mean action by default and under a deterministic exploration
    type, a sample of the Gaussian (global torch RNG) under ``ExplorationType.RANDOM``.

    Attributes:
        network: the :class:`PolicyNetwork` (raw tensors -> ``(loc, scale)``).
        config: the seed's single-seed :class:`~sg_torchrl.train.config.TrainConfig` (env id, options).
        seed: the run seed the policy was trained with.
        layout: what the policy reads (:class:`~sg_torchrl.modules.mlp.ObservationLayout`).
        action_spec: the env's action spec (one simulator's).
        epoch: the training epoch of the checkpoint.
        diverged: ``None``, or the seed's divergence record (its weights are those before it diverged).
    """

    def __init__(self, network: PolicyNetwork, *, config: TrainConfig, seed: int, layout: ObservationLayout,
                 action_spec: TensorSpec, epoch: int, diverged: dict[str, Any] | None = None) -> None:
        super().__init__()
        self.network = network
        self.in_keys = list(layout.in_keys)
        self.out_keys = ["action"]
        self.config, self.seed, self.layout, self.action_spec = config, seed, layout, action_spec
        self.epoch, self.diverged = epoch, diverged

    @property
    def device(self) -> torch.device:
        return next(self.network.parameters()).device

    def _actions(self, inputs: list[Tensor], deterministic: bool | None = None) -> Tensor:
        if deterministic is None:
            deterministic = exploration_type() in _DETERMINISTIC
        loc, scale = self.network(*inputs)
        return loc if deterministic else IndependentNormal(loc, scale).sample()

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        inputs = [tensordict.get(key) for key in self.in_keys]
        device = inputs[0].device
        action = self._actions([x.to(self.device) for x in inputs])
        tensordict.set("action", action.to(device))
        return tensordict

    @torch.no_grad()
    def act(self, observation: np.ndarray | Mapping[str, np.ndarray], deterministic: bool = True) -> np.ndarray:
        """Actions for numpy observations: ``(obs_dim,)`` -> ``(action_dim,)``, ``(B, obs_dim)`` -> ``(B, action_dim)``.

        ``observation``: the raw flat vector as the env emits it, or for a pixel run a mapping of
        :attr:`in_keys` to arrays (``"pixels"`` ``(H, W, 3)`` ``uint8`` ...). ``deterministic``: the mean
        action (default), else a sample (global torch RNG). Returns ``float32``.
        """
        if not isinstance(observation, Mapping):
            if self.in_keys != ["observation"]:
                raise ValueError(f"this policy reads {self.in_keys}: give a mapping of those keys to arrays")
            observation = {"observation": observation}
        missing = [key for key in self.in_keys if key not in observation]
        if missing:
            raise ValueError(f"observation lacks {missing} (this policy reads {self.in_keys})")
        inputs, single = [], None
        for key in self.in_keys:
            array = np.asarray(observation[key])
            trailing = self._trailing_shape(key)
            if array.shape[-len(trailing):] != trailing or array.ndim not in (len(trailing), len(trailing) + 1):
                raise ValueError(f"{key!r} has shape {array.shape}; this policy takes {trailing} or (B, *{trailing})")
            single = array.ndim == len(trailing) if single is None else single
            dtype = torch.uint8 if key == "pixels" else torch.float32
            tensor = torch.as_tensor(array, dtype=dtype, device=self.device)
            inputs.append(tensor.unsqueeze(0) if array.ndim == len(trailing) else tensor)
        action = self._actions(inputs, deterministic).cpu().numpy()
        return action[0] if single else action

    def _trailing_shape(self, key: str) -> tuple[int, ...]:
        layout = self.layout
        if key == "observation":
            return (layout.vector_dim,)
        return (*layout.image_shape, 3 if key == "pixels" else 1)


def load_policy(run_dir: str | Path, seed: int | None = None, device: torch.device | str = "cpu") -> TrainedPolicy:
    """The trained policy of an ``sg-train`` run, with its observation normaliser folded in.

    Args:
        run_dir: a single run's directory, a seed group's (then ``seed`` is needed), one of a group's
            ``seed-XXX/`` directories, or a ``checkpoint.pt``.
        seed: which seed of a group (a single run's own seed, or ``None``).
        device: where the network runs (observations given on another device are moved there and back).

    >>> policy = sg_torchrl.load_policy("runs/SafetyPointGoal1-v0/ppo_lag/seed-000")
    >>> action = policy.act(observation)              # numpy in, numpy out
    >>> td = env.rollout(1000, policy)                # a TorchRL policy (mean actions)

    Raises:
        FileNotFoundError: no run or checkpoint there.
        CheckpointError: a damaged or foreign checkpoint (nothing in it is run).
        PolicyLoadError: a group without ``seed``, a seed the run does not hold, a multi-agent run.
    """
    run = read_run(run_dir)
    return policy_of(run, run.pick_seed(seed), device)


def policy_of(run: RunCheckpoint, seed: int, device: torch.device | str = "cpu") -> TrainedPolicy:
    """Seed ``seed``'s policy from a run already read (:func:`read_run`), e.g. each seed of a group in turn."""
    entry = seed_entry(run.state, seed)
    config = TrainConfig.from_saved(entry["config"])
    env = sg_torchrl.make(config.env_id, num_envs=1, **config.env_options)  # its specs: what the actor reads
    try:
        layout = ObservationLayout.from_spec(env.observation_spec)
        action_spec = env.action_spec[0].clone()
    finally:
        env.close()
    with torch.random.fork_rng(devices=[]):  # its initial weights are overwritten at once: leave the RNG alone
        actor = make_actor(layout, action_spec, config.network_sizes)
    try:
        actor.load_state_dict(entry["networks"]["actor"])
    except (KeyError, RuntimeError) as error:
        raise CheckpointError(f"seed {seed}'s actor in {run.path} does not fit the networks its config describes "
                              f"({str(error).splitlines()[0]})") from None
    scaler = None
    if entry.get("obs_norm") is not None:  # the seed's normaliser as its trainer had it (its epsilon)
        norm = RunningObservationNorm((layout.vector_dim,))
        norm.load_state_dict(entry["obs_norm"])
        scaler = ObservationScaler(norm.mean, norm.var, norm.epsilon)
    network = PolicyNetwork(actor, layout.in_keys, scaler).requires_grad_(False).eval().to(device)
    return TrainedPolicy(network, config=config, seed=seed, layout=layout, action_spec=action_spec,
                         epoch=int(run.state["epoch"]), diverged=entry.get("diverged"))
