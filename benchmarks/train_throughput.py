"""End-to-end PPO-Lag throughput at the paper's hyper-parameters (collection plus update).

Runs ``--epochs`` epochs of ``sg-train``'s loop (20,000 steps per epoch from 10 simulators, 40
passes of minibatch 64 with KL early stop 0.02) and reports env steps per second of wall time,
split into collection and update, beside the reference SafePO figure for this machine kind
(roughly 100-300 env steps/s, from the issue). Also reports the update cost per gradient step so
a run that stops early on KL is comparable.

    python benchmarks/train_throughput.py --env-id SafetyHalfCheetahVelocity-v1 --epochs 3
"""

from __future__ import annotations

import argparse
import tempfile
import time

import torch

from sg_torchrl.train import TrainConfig, Trainer

REFERENCE_STEPS_PER_S = (100, 300)  # SafePO ppo_lag.py on this machine kind (issue text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="SafetyHalfCheetahVelocity-v1")
    parser.add_argument("--algo", default="ppo_lag")
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--steps-per-epoch", type=int, default=20_000)
    parser.add_argument("--num-envs", type=int, default=10)
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = TrainConfig(algo=args.algo, env_id=args.env_id, num_envs=args.num_envs,
                          steps_per_epoch=args.steps_per_epoch, total_steps=args.epochs * args.steps_per_epoch,
                          wandb="disabled", eval_episodes=0, progress=False, output_dir=tmp)
        trainer = Trainer(cfg)
        rows = []
        start = time.perf_counter()
        for _ in range(args.epochs):
            rows.append(trainer.train_epoch())
        wall = time.perf_counter() - start
    steps = args.epochs * args.steps_per_epoch
    rollout = sum(r["Time/Rollout"] for r in rows)
    update = sum(r["Time/Update"] for r in rows)
    grad_steps = sum(r["Train/StopIter"] for r in rows) * -(-args.steps_per_epoch // cfg.minibatch_size)
    print(f"| {args.algo} on {args.env_id} | value |")
    print("|---|---|")
    print(f"| env steps | {steps} |")
    print(f"| end-to-end env steps/s | {steps / wall:.0f} |")
    print(f"| collection env steps/s | {steps / rollout:.0f} |")
    print(f"| update s per epoch | {update / args.epochs:.1f} |")
    print(f"| passes per epoch (KL early stop) | {sum(r['Train/StopIter'] for r in rows) / args.epochs:.1f} |")
    print(f"| ms per gradient step (minibatch {cfg.minibatch_size}) | {1e3 * update / grad_steps:.2f} |")
    low, high = REFERENCE_STEPS_PER_S
    print(f"| ratio to SafePO reference ({low}-{high} steps/s) | {steps / wall / high:.1f}x-{steps / wall / low:.1f}x |")


if __name__ == "__main__":
    main()
