"""End-to-end training throughput at the paper's hyper-parameters (collection plus update).

Runs ``--epochs`` epochs of ``sg-train``'s loop for ``--algo`` on ``--env-id`` with the algorithm's
paper defaults (single agent: 20,000 steps per epoch from 10 simulators, PPO-Lag's 40 passes of
minibatch 64 with KL early stop 0.02; multi agent: 10,000 steps per epoch from 10 simulators, 5
epochs of one full-batch step per agent, KL stop 0.016) and reports env steps per second of wall
time, split into collection and update. Single agent: beside the reference SafePO figure for this
machine kind (roughly 100-300 env steps/s, measured earlier) and the update cost per gradient step, so
a run that stops early on KL is comparable. Multi agent: also the update time per agent.

    python benchmarks/train_throughput.py --env-id SafetyHalfCheetahVelocity-v1 --epochs 3
    python benchmarks/train_throughput.py --algo mappo_lag --env-id Safety2x3HalfCheetahVelocity-v0 --epochs 5
"""

from __future__ import annotations

import argparse
import tempfile
import time

import torch

from sg_torchrl.train import TrainConfig, trainer_class
from sg_torchrl.train.config import ALGORITHM_DEFAULTS
from sg_torchrl.train.multi_agent import num_minibatches

REFERENCE_STEPS_PER_S = (100, 300)  # SafePO ppo_lag.py on this machine kind (measured earlier)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default=None, help="default: the algorithm's (sg-train's default)")
    parser.add_argument("--algo", default="ppo_lag")
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--steps-per-epoch", type=int, default=None, help="default: the algorithm's paper value")
    parser.add_argument("--num-envs", type=int, default=10)
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        steps_per_epoch = args.steps_per_epoch or ALGORITHM_DEFAULTS[args.algo]["steps_per_epoch"]
        cfg = TrainConfig(algo=args.algo, env_id=args.env_id, num_envs=args.num_envs, steps_per_epoch=steps_per_epoch,
                          total_steps=args.epochs * steps_per_epoch, wandb="disabled", eval_episodes=0,
                          progress=False, output_dir=tmp)
        trainer = trainer_class(cfg)(cfg)
        rows = []
        start = time.perf_counter()
        for _ in range(args.epochs):
            rows.append(trainer.train_epoch())
        wall = time.perf_counter() - start
    steps = args.epochs * cfg.steps_per_epoch
    rollout = sum(r["Time/Rollout"] for r in rows)
    update = sum(r["Time/Update"] for r in rows)
    passes = sum(r.get("Train/StopIter", cfg.update_iters) for r in rows) / args.epochs
    print(f"| {args.algo} on {cfg.env_id} | value |")
    print("|---|---|")
    print(f"| env steps ({args.epochs} epochs of {cfg.steps_per_epoch}, {cfg.num_envs} simulators) | {steps} |")
    print(f"| end-to-end env steps/s | {steps / wall:.0f} |")
    print(f"| collection env steps/s | {steps / rollout:.0f} |")
    print(f"| update s per epoch | {update / args.epochs:.2f} |")
    if cfg.multi_agent:
        n_agents = trainer.networks.n_agents
        print(f"| agents | {n_agents} |")
        print(f"| update s per agent and epoch | {update / args.epochs / n_agents:.2f} |")
        if not cfg.second_order:
            grad_steps = passes * num_minibatches(cfg) * n_agents * args.epochs
            print(f"| epochs per agent (KL early stop {cfg.target_kl}) | {passes:.1f} |")
            print(f"| ms per gradient step (one agent, {cfg.steps_per_epoch // num_minibatches(cfg)} samples) | "
                  f"{1e3 * update / grad_steps:.1f} |")
        return
    grad_steps = passes * args.epochs * -(-cfg.steps_per_epoch // cfg.minibatch_size)
    print(f"| passes per epoch (KL early stop) | {passes:.1f} |")
    print(f"| ms per gradient step (minibatch {cfg.minibatch_size}) | {1e3 * update / grad_steps:.2f} |")
    low, high = REFERENCE_STEPS_PER_S
    print(f"| ratio to SafePO reference ({low}-{high} steps/s) | {steps / wall / high:.1f}x-{steps / wall / low:.1f}x |")


if __name__ == "__main__":
    main()
