"""Slow learning checks (``pytest -m slow``): the safe algorithms actually satisfy the constraint.

SafetySwimmerVelocity-v1 is the quickest velocity task whose *initial* policy breaks the limit
(a random Swimmer exceeds the 0.2282 m/s threshold on about a third of its steps, an episode
cost near 300 against a limit of 25), so the test fails unless the multiplier and the
Lagrangian advantage drive the cost down.
"""

from __future__ import annotations

import pytest
import torch

from sg_torchrl.train import TrainConfig, Trainer

torch.set_num_threads(1)


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["ppo_lag", "cppo_pid"])
def test_safe_algorithm_brings_episode_cost_under_the_limit(tmp_path, algo):
    cfg = TrainConfig(
        algo=algo, env_id="SafetySwimmerVelocity-v1", seed=0, num_envs=10, steps_per_epoch=10_000,
        total_steps=400_000, update_iters=10, eval_episodes=0, wandb="disabled", progress=False,
        output_dir=str(tmp_path),
    )
    trainer = Trainer(cfg)
    first = trainer.train_epoch()
    assert first["Metrics/EpCost"] > 2 * cfg.cost_limit, "the initial policy must violate the constraint"
    trainer.run()
    final = trainer.stats.window(20)
    assert final["cost"] <= cfg.cost_limit, f"{algo}: final mean episode cost {final['cost']:.1f}"
