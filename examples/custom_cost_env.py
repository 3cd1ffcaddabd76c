"""Any gymnasium env plus a cost function becomes a safe env that sg-train's engine trains (docs/custom_tasks.md).

    python examples/custom_cost_env.py --total-steps 20000
"""

import argparse

import torch

import sg_torchrl
from sg_torchrl.tasks import register_cost_env


def fast_swing(obs, action, next_obs, info):
    """Pendulum's safety constraint: cost 1 whenever the pendulum spins faster than 4 rad/s (obs[2])."""
    return (next_obs[..., 2].abs() > 4.0).to(torch.float32)


ENV_ID = "SafePendulum-v0"
if ENV_ID not in sg_torchrl.list_envs():
    register_cost_env(ENV_ID, "Pendulum-v1", fast_swing, cost_name="fast_swing")


def train(total_steps: int, output_dir: str = "runs") -> dict:
    from sg_torchrl.train import TrainConfig, train

    cfg = TrainConfig(algo="ppo_lag", env_id=ENV_ID, total_steps=total_steps, steps_per_epoch=total_steps // 2,
                      num_envs=2, output_dir=output_dir, overwrite=True, eval_episodes=0, cost_limit=5.0)
    return train(cfg)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--total-steps", type=int, default=20_000)
    metrics = train(parser.parse_args().total_steps)
    nan = float("nan")
    print(f"EpRet {metrics.get('Metrics/EpRet', nan):.2f}  EpCost {metrics.get('Metrics/EpCost', nan):.2f}")
