"""A trained policy read back from an ``sg-train`` run: :func:`load_policy`.

A run keeps its networks in its checkpoint (:mod:`sg_torchrl.train.checkpoint`: a sha256-checked file
loaded with ``weights_only``, so loading never runs code): one entry per seed
(:func:`~sg_torchrl.train.seed_runs.seed_entry`) with its networks' state dicts and its observation
normalisers' statistics. :func:`read_run` reads the checkpoint; :func:`load_policy` / :func:`policy_of` hand a
seed's entry to the loader of its kind of run (:func:`~sg_torchrl.evaluation.loaders.loader_for`, by the
algorithm manifest's ``agents`` and ``family``: single-agent on-policy, off-policy, multi-agent), which
rebuilds the actor with the engine's own builder and folds the frozen normaliser in front of it:

* the network (:mod:`sg_torchrl.evaluation.networks`): plain tensors in, the mean action out, the
  normalisation included; what :func:`~sg_torchrl.evaluation.export.export_policy` exports;
* :class:`TrainedPolicy`: the TorchRL policy, a ``TensorDictModule`` reading the raw observation entries
  (``"observation"``, ``"pixels"`` / ``"depth"`` for pixel runs, a team's ``("agents", "observation")``) and
  writing the action (``"action"``, a team's ``("agents", "action")``): the mean action unless the
  exploration type says ``RANDOM`` (TorchRL's ``set_exploration_type``), and :meth:`TrainedPolicy.act`
  for numpy users.

Its actions are those of the trainer's own end-of-training evaluation, bit for bit: the same actor
weights and the same normalisation arithmetic (:class:`ObservationScaler`, RunningObservationNorm's
frozen formula), checked in ``tests/test_evaluation.py`` and ``tests/test_evaluation_families.py``.

A checkpoint of the single-seed multi-agent trainer the group engine replaced (its team's entries at the
top level) is read as its one-seed group's (:func:`~sg_torchrl.train.multi_agent_group.team_checkpoint_as_group`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sg_torchrl.evaluation.loaders import loader_for
from sg_torchrl.evaluation.networks import ObservationScaler, PolicyNetwork, TrainedPolicy
from sg_torchrl.train import refuse_retired_checkpoint
from sg_torchrl.train.checkpoint import CHECKPOINT_NAME, CheckpointError, checkpoint_file, load_checkpoint
from sg_torchrl.train.config import RETIRED_FIELDS, TrainConfig
from sg_torchrl.train.multi_agent_group import team_checkpoint_as_group
from sg_torchrl.train.seed_runs import seed_entry

__all__ = ["ObservationScaler", "PolicyLoadError", "PolicyNetwork", "RunCheckpoint", "TrainedPolicy",
           "load_policy", "read_run"]

_SEED_DIR = re.compile(r"seed-(\d+)")


class PolicyLoadError(ValueError):
    """A run whose policy cannot be loaded as asked (a missing or unknown seed, ...)."""


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
        PolicyLoadError: a seed directory its group does not hold.
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
        state = team_checkpoint_as_group(state)  # the replaced single-seed trainer's layout, if it is that
    seeds = [int(entry["seed"]) for entry in state.get("seeds") or []]
    if not seeds:
        raise CheckpointError(f"{file} holds no seed entries: not a checkpoint of this sg_torchrl's trainers")
    if default_seed is not None and default_seed not in seeds:
        raise PolicyLoadError(f"{run_dir} names seed {default_seed}, which its group {path} does not hold "
                              f"(seeds {_listed(seeds)})")
    return RunCheckpoint(file, state, config, seeds, default_seed)


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
    >>> team = sg_torchrl.load_policy("runs/Safety2x3HalfCheetahVelocity-v0/mappo/seed-000")
    >>> actions = team.act(agent_observations)        # (A, obs_dim) -> (A, max action size)

    Raises:
        FileNotFoundError: no run or checkpoint there.
        CheckpointError: a damaged or foreign checkpoint (nothing in it is run).
        PolicyLoadError: a group without ``seed``, a seed the run does not hold.
    """
    run = read_run(run_dir)
    return policy_of(run, run.pick_seed(seed), device)


def policy_of(run: RunCheckpoint, seed: int, device: torch.device | str = "cpu") -> TrainedPolicy:
    """Seed ``seed``'s policy from a run already read (:func:`read_run`), e.g. each seed of a group in turn, by
    the loader of its kind of run (:func:`~sg_torchrl.evaluation.loaders.loader_for`)."""
    entry = seed_entry(run.state, seed)
    config = TrainConfig.from_saved(entry["config"])
    return loader_for(config)(run, seed, entry, config, device)
