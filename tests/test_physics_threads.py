"""Threaded stepping of :class:`~sg_torchrl.envs.physics.MujocoBatch` (``physics_threads``).

Each simulator is stepped by exactly one thread with its own ``MjData``, so any thread count must
give bit-identical rollouts; these tests hold that for every env family (the driven-mocap path of
the button tasks' gremlins included), and check the option's validation and the pool's lifecycle.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from sg_torchrl.envs import make
from sg_torchrl.envs.registry import env_options
from sg_torchrl.envs.physics import MujocoBatch


def _rollout(env_id: str, threads: int, steps: int = 25):
    env = make(env_id, num_envs=5, seed=3, physics_threads=threads)
    try:
        torch.manual_seed(0)
        return env.rollout(steps, break_when_any_done=False)
    finally:
        env.close()


@pytest.mark.parametrize(
    "env_id",
    [
        "ShadowHandOverSafeJoint-v0",
        "SafetyPointButton1-v0",  # gremlins: the driven-mocap stepping path
        "SafetyHalfCheetahVelocity-v1",
        "Safety2x3HalfCheetahVelocity-v0",
    ],
)
def test_threads_give_bit_identical_rollouts(env_id):
    single, threaded = _rollout(env_id, 1), _rollout(env_id, 3)
    for key in single.keys(True, True):
        assert torch.equal(single[key], threaded[key]), key


@pytest.mark.parametrize("env_id", ["ShadowHandOverSafeJoint-v0", "SafetyPointGoal1-v0", "SafetyAntVelocity-v1",
                                    "Safety2x4AntVelocity-v0", "SafetyPointMultiGoal1-v0",
                                    "MultiAgentShadowHandOverSafeJoint-v0"])
def test_every_family_takes_the_option(env_id):
    assert "physics_threads" in env_options(env_id)
    env = make(env_id, num_envs=2, physics_threads=2)
    assert env.physics.threads == 2
    env.close()


def _model_batch(num_sims: int, threads) -> MujocoBatch:
    env = make("SafetyHalfCheetahVelocity-v1", num_envs=1)
    model = env.physics.model
    env.close()
    return MujocoBatch(model, num_sims, threads=threads)


@pytest.mark.parametrize("threads", [0, -2, 1.5, True, "2"])
def test_bad_thread_counts_are_rejected(threads):
    with pytest.raises(ValueError, match="threads must be a positive integer"):
        _model_batch(4, threads)


def test_threads_are_capped_at_the_simulator_count_and_cover_each_once():
    batch = _model_batch(3, 8)
    assert batch.threads == 3
    covered = sorted(i for rows in batch._slices for i in rows)
    assert covered == [0, 1, 2]
    uneven = _model_batch(7, 3)
    assert sorted(i for rows in uneven._slices for i in rows) == list(range(7))


def test_a_worker_error_reaches_the_caller_and_the_batch_still_steps():
    batch = _model_batch(4, 2)
    nu = batch.model.nu
    with pytest.raises(ValueError):
        batch.step(np.zeros((4, nu + 1)), 2)  # wrong control width, raised inside a worker thread
    assert not batch.step(np.zeros((4, nu)), 2).any()
    assert np.isfinite(batch.qpos()).all()


def test_close_stops_the_pool_and_a_later_step_restarts_it():
    batch = _model_batch(4, 2)
    ctrl = np.zeros((4, batch.model.nu))
    batch.step(ctrl, 1)
    pool = batch._pool
    assert pool is not None
    batch.close()
    assert batch._pool is None and pool._shutdown
    batch.step(ctrl, 1)
    assert batch._pool is not None
    batch.close()


def test_pickled_batch_drops_the_pool():
    batch = _model_batch(2, 2)
    batch.step(np.zeros((2, batch.model.nu)), 1)
    state = batch.__getstate__()
    assert state["_pool"] is None
    pickle.dumps(state["_slices"])
    batch.close()
