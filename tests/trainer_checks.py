"""Checks shared by the trainer tests (vector and pixel observations)."""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDictBase

from sg_torchrl.train import OnPolicyGroupTrainer, TrainConfig


def flat_parameters(trainer: OnPolicyGroupTrainer) -> torch.Tensor:
    """Every parameter of every seed's actor and critics, flattened into one vector (for exact-equality checks)."""
    model = trainer.model
    return torch.cat([model.flat_actor.detach().reshape(-1), model.flat_critics.detach().reshape(-1)]).clone()


def tiny_config(tmp_path, **overrides) -> TrainConfig:
    """Three 200-step epochs of PPO-Lag on HalfCheetah (2 simulators, 2 passes): a run in about a second."""
    values = dict(
        env_id="SafetyHalfCheetahVelocity-v1", num_envs=2, steps_per_epoch=200, total_steps=600,
        update_iters=2, minibatch_size=64, eval_episodes=0, wandb="disabled", progress=False,
        output_dir=str(tmp_path), run_name="run", checkpoint_every=100,
    )
    values.update(overrides)
    return TrainConfig(**values)


def recording(trainer) -> list:
    """Keep a copy of every batch ``trainer`` collects (any trainer with a ``collector``)."""
    batches, collect = [], trainer.collector.collect

    def collect_and_keep():
        batch = collect()
        batches.append(batch.clone())
        return batch

    trainer.collector.collect = collect_and_keep
    return batches


def assert_same_state(mine, theirs, path="entry", *, timings=False, nan_equal=True):
    """Two nested states (checkpoint entries, progress rows) equal bit for bit: tensors and arrays of the same
    dtype with ``torch.equal`` / ``np.array_equal``, the rest with ``==``.

    ``timings``: compare the ``Time/*`` entries of dicts too (else skipped: progress rows' timings differ);
    ``nan_equal``: NaN equals NaN (a metric undefined in both).
    """
    options = dict(timings=timings, nan_equal=nan_equal)
    if isinstance(mine, TensorDictBase):
        assert_same_state(mine.to_dict(), theirs.to_dict(), path, **options)
    elif isinstance(mine, np.ndarray):
        assert mine.dtype == theirs.dtype, path
        assert np.array_equal(mine, theirs, equal_nan=nan_equal and mine.dtype.kind == "f"), path
    elif isinstance(mine, dict):
        assert mine.keys() == theirs.keys(), path
        for key in (k for k in mine if timings or not str(k).startswith("Time/")):
            assert_same_state(mine[key], theirs[key], f"{path}[{key!r}]", **options)
    elif isinstance(mine, (list, tuple)):
        assert len(mine) == len(theirs), path
        for i, (a, b) in enumerate(zip(mine, theirs)):
            assert_same_state(a, b, f"{path}[{i}]", **options)
    elif isinstance(mine, torch.Tensor):
        assert mine.dtype == theirs.dtype and torch.equal(mine, theirs), path
    else:
        assert mine == theirs or (nan_equal and mine != mine and theirs != theirs), path
