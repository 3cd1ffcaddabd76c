"""RolloutCollector (layout, exact resume) and RunningObservationNorm (gymnasium's running statistics)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

torch.set_num_threads(1)

import sg_torchrl  # noqa: E402
from sg_torchrl.collectors import RolloutCollector  # noqa: E402
from sg_torchrl.envs.normalization import RunningObservationNorm  # noqa: E402
from sg_torchrl.modules import make_actor  # noqa: E402

ENV_ID = "SafetyHalfCheetahVelocity-v1"


def normalised_env(num_envs: int = 3, seed: int = 0, **options) -> tuple[TransformedEnv, RunningObservationNorm]:
    base = sg_torchrl.make(ENV_ID, num_envs=num_envs, seed=seed, **options)
    norm = RunningObservationNorm((base.observation_dim,))
    return TransformedEnv(base, norm), norm


class TestRunningObservationNorm:
    def test_matches_gymnasium_running_mean_std(self):
        from gymnasium.wrappers.utils import RunningMeanStd

        norm = RunningObservationNorm((4,))
        reference = RunningMeanStd(shape=(4,))
        rng = np.random.default_rng(0)
        for _ in range(5):
            batch = rng.normal(3.0, 2.0, size=(7, 4))
            norm.update(torch.as_tensor(batch))
            reference.update(batch)
        np.testing.assert_allclose(norm.mean.numpy(), reference.mean, rtol=1e-12)
        np.testing.assert_allclose(norm.var.numpy(), reference.var, rtol=1e-12)
        assert norm.count.item() == pytest.approx(reference.count)

    def test_transformed_env_passes_specs_updates_and_freezes(self):
        env, norm = normalised_env()
        check_env_specs(env)
        initial = norm.count.item()
        env.rollout(5)
        # TorchRL puts attached transforms in eval mode: the statistics must move regardless.
        count = norm.count.item()
        assert count == pytest.approx(initial + 5 * 3)
        norm.freeze()
        env.rollout(5)
        assert norm.count.item() == count
        copy = norm.unfreeze().frozen_copy()
        assert copy.frozen and torch.equal(copy.mean, norm.mean)
        env.rollout(5)
        assert norm.count.item() > count


class TestRolloutCollector:
    def test_layout_and_frames(self):
        env, _ = normalised_env(num_envs=3, max_episode_steps=4)
        actor = make_actor(env.observation_spec["observation"].shape[-1], env.action_spec, [8])
        collector = RolloutCollector(env, actor, steps=10)
        batch = collector.collect()
        assert batch.batch_size == torch.Size([3, 10]) and batch.names == [None, "time"]
        for key in ("observation", "action", "action_log_prob", "loc", "scale", ("next", "cost"), ("next", "reward")):
            assert key in batch.keys(True), key
        assert batch["next", "done"].sum() == 3 * 2  # episodes of 4 steps: done at t=3 and t=7
        assert collector.frames == 30

    def test_state_dict_resumes_exactly(self):
        def fresh():
            torch.manual_seed(0)
            env, _ = normalised_env(seed=1, max_episode_steps=6)
            actor = make_actor(env.observation_spec["observation"].shape[-1], env.action_spec, [8])
            return RolloutCollector(env, actor, steps=5), env

        straight, straight_env = fresh()
        straight.collect()
        state = straight.state_dict()
        norm_state = {k: v.clone() for k, v in straight_env.transform.state_dict().items()}  # buffers move on
        rng_state = torch.get_rng_state()
        expected = straight.collect()

        resumed, resumed_env = fresh()
        resumed.collect()
        resumed.collect()  # diverge first, then restore
        resumed.load_state_dict(state)
        resumed_env.transform.load_state_dict(norm_state)
        torch.set_rng_state(rng_state)
        actual = resumed.collect()
        for key in ("observation", "action", ("next", "reward"), ("next", "cost"), ("next", "done")):
            assert torch.equal(expected[key], actual[key]), key

    def test_rejects_empty_batches(self):
        env, _ = normalised_env()
        with pytest.raises(ValueError, match="steps per batch"):
            RolloutCollector(env, make_actor(17, env.action_spec, [8]), steps=0)
