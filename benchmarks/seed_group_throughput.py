"""CPU cost of training per seed: the single-seed ``Trainer`` against seed groups of S = 1, 3, 8 (issue 18).

A seed group (``sg-train --seeds``, :mod:`sg_torchrl.train.seed_group`) steps S seeds' simulators in
one batched env and their networks as one stacked model, so what one seed costs should fall with S.
This script trains PPO-Lag at the paper's settings (20,000 steps per epoch from 10 simulators per
seed, 40 passes of minibatch 64, KL early stop 0.02) for ``--epochs`` epochs per configuration, in
one run and one after the other:

* ``Trainer``: today's single-seed trainer (eager), the baseline;
* ``group S=k``: a seed group of seeds 0..k-1, eager, and with ``--compile true`` (the fused minibatch
  losses and the masked Adam through ``torch.compile``; its first epoch includes the compiling).

Reported per env: CPU seconds (``time.process_time``, every thread of the process) per 1,000 env
steps *per seed*, over all epochs and over the epochs after the first (steady state: no compiling,
warm caches), the ratio of the baseline's steady figure to each configuration's (> 1: cheaper per
seed than the single-seed trainer), the share of wall time spent collecting, and the passes the KL
stop allowed (the mean over seeds: configurations that stop at different passes do different work).
Every configuration runs with one torch thread, as ``sg-train`` does.

    python benchmarks/seed_group_throughput.py                      # the paper's settings (minutes per row)
    python benchmarks/seed_group_throughput.py --epochs 3 --seeds 1 3
    python benchmarks/seed_group_throughput.py --quick              # a smoke test: small epochs, S = 1, 3
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import dataclass

import torch

from sg_torchrl.train import GroupTrainer, TrainConfig, Trainer

ENVS = ("SafetyHalfCheetahVelocity-v1", "SafetyPointGoal1-v0")
PAPER = dict(steps_per_epoch=20_000, num_envs=10, update_iters=40, minibatch_size=64, target_kl=0.02)
QUICK = dict(steps_per_epoch=1_000, num_envs=4, update_iters=4, minibatch_size=64, target_kl=0.02)


@dataclass
class Row:
    label: str
    seeds: int
    cpu: list[float]  # CPU seconds per epoch
    rollout: float  # wall seconds collecting, all epochs
    wall: float  # wall seconds, all epochs
    passes: float  # mean passes per epoch (mean over seeds)
    compile_error: str | None = None

    def per_seed_k(self, settings: dict, epochs: list[float]) -> float:
        """CPU seconds per 1,000 env steps per seed over ``epochs``."""
        return sum(epochs) / (len(epochs) * self.seeds * settings["steps_per_epoch"] / 1000)


def measure(env_id: str, seeds: int | None, compile: bool, settings: dict, epochs: int) -> Row:
    """Train ``epochs`` epochs of PPO-Lag: the single-seed ``Trainer`` (``seeds`` None) or a group of ``seeds``."""
    with tempfile.TemporaryDirectory() as tmp:
        common = dict(algo="ppo_lag", env_id=env_id, total_steps=epochs * settings["steps_per_epoch"],
                      wandb="disabled", eval_episodes=0, progress=False, output_dir=tmp, compile=compile, **settings)
        if seeds is None:
            trainer, label, count = Trainer(TrainConfig(seed=0, **common)), "Trainer (single seed)", 1
        else:
            trainer = GroupTrainer(TrainConfig(seeds=list(range(seeds)), **common))
            label, count = f"group S={seeds}" + (" compiled" if compile else ""), seeds
        cpu, rows = [], []
        for _ in range(epochs):
            start = time.process_time()
            rows.append(trainer.train_epoch())
            cpu.append(time.process_time() - start)
        error = None
        if seeds is not None and compile:
            step = getattr(trainer.group_update, "step", None)
            error = getattr(step, "compile_error", None) or trainer.optimizer.compile_error
    return Row(label, count, cpu, sum(r["Time/Rollout"] for r in rows),
               sum(r["Time/Rollout"] + r["Time/Update"] for r in rows),
               sum(r["Train/StopIter"] for r in rows) / epochs, error)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=list(ENVS))
    parser.add_argument("--seeds", nargs="+", type=int, default=None, help="group sizes S (default 1 3 8; quick 1 3)")
    parser.add_argument("--epochs", type=int, default=2, help="epochs per configuration (the first is reported apart)")
    parser.add_argument("--no-compile", action="store_true", help="skip the compiled groups")
    parser.add_argument("--quick", action="store_true",
                        help=f"smoke test: {QUICK['steps_per_epoch']}-step epochs from {QUICK['num_envs']} simulators "
                             f"per seed, {QUICK['update_iters']} passes, S = 1, 3")
    args = parser.parse_args()
    torch.set_num_threads(1)
    settings = QUICK if args.quick else PAPER
    sizes = args.seeds or ([1, 3] if args.quick else [1, 3, 8])
    steady = slice(1, None) if args.epochs > 1 else slice(None)
    print(f"PPO-Lag, {settings['steps_per_epoch']} steps per epoch from {settings['num_envs']} simulators per seed, "
          f"{settings['update_iters']} passes of minibatch {settings['minibatch_size']}, KL stop "
          f"{settings['target_kl']}; {args.epochs} epoch(s) per row; CPU s = time.process_time()\n")
    for env_id in args.envs:
        runs = [measure(env_id, None, False, settings, args.epochs)]
        for compile in ([False] if args.no_compile else [False, True]):
            runs += [measure(env_id, size, compile, settings, args.epochs) for size in sizes]
        base = runs[0].per_seed_k(settings, runs[0].cpu[steady])
        print(f"### {env_id}\n")
        print("| configuration | CPU s / 1k steps / seed, all epochs | after the first epoch | speed-up vs Trainer "
              "| collection share of wall | passes per epoch |")
        print("|---|---|---|---|---|---|")
        for row in runs:
            after = row.per_seed_k(settings, row.cpu[steady])
            note = f" (compile failed, eager: {row.compile_error})" if row.compile_error else ""
            print(f"| {row.label}{note} | {row.per_seed_k(settings, row.cpu):.3f} | {after:.3f} | {base / after:.2f}x "
                  f"| {row.rollout / row.wall:.0%} | {row.passes:.1f} |")
        print()


if __name__ == "__main__":
    main()
