"""Update time per epoch at the paper's batch sizes, eager against ``compile=True``, in one run.

For each ``--algos`` entry this builds two sg-train trainers with the algorithm's paper defaults
(20,000 env steps per epoch from 10 simulators; first order: up to 40 passes of minibatch 64 with
the KL stop at 0.02; second order: one trust-region step, then 10 critic passes of minibatch 128),
identical but for ``compile``, and trains them epoch by epoch, alternating, so that both see the
same machine load. Reported per algorithm:

* seconds of update per epoch (``Time/Update``, collection excluded) for eager and compiled, the
  compiled trainer's first epoch (which compiles) shown apart;
* milliseconds per minibatch gradient step (the epochs' update time over their minibatch steps, so
  epochs that stop on KL after different numbers of passes compare);
* the speed-up, eager over compiled, per gradient step.

Both trainers run the same algorithm from the same seed; their results drift apart by float
rounding (the compiled kernels sum in another order), so their KL stops may differ.

    python benchmarks/update_time.py --algos ppo_lag cpo --epochs 3
"""

from __future__ import annotations

import argparse
import math
import tempfile

import torch

from _report import write_json
from sg_torchrl.train import OnPolicyGroupTrainer, TrainConfig


def minibatch_steps(cfg: TrainConfig, metrics: dict[str, float]) -> int:
    """Gradient steps of one epoch's update: passes times minibatches per pass (CUP: both stages)."""
    per_pass = math.ceil(cfg.steps_per_epoch / cfg.minibatch_size)
    passes = cfg.update_iters if cfg.second_order else metrics["Train/StopIter"]
    return int((passes + metrics.get("Train/ProjectionStopIter", 0)) * per_pass)


def measure(algo: str, env_id: str, epochs: int, output_dir: str) -> dict[str, float]:
    trainers = {
        mode: OnPolicyGroupTrainer(TrainConfig(
            algo=algo, env_id=env_id, compile=mode == "compiled", total_steps=epochs * 20_000, wandb="disabled",
            eval_episodes=0, progress=False, output_dir=output_dir, run_name=f"{algo}-{mode}"))
        for mode in ("eager", "compiled")
    }
    history: dict[str, list[tuple[float, int]]] = {mode: [] for mode in trainers}
    for epoch in range(epochs):
        for mode, trainer in trainers.items():
            metrics = trainer.train_epoch()
            history[mode].append((metrics["Time/Update"], minibatch_steps(trainer.cfg, metrics)))
            print(f"  {algo} {mode:8s} epoch {epoch}: update {metrics['Time/Update']:6.1f} s, "
                  f"{history[mode][-1][1]} minibatch steps", flush=True)
    row: dict[str, float] = {"algo": algo, "env_id": env_id, "compile_first_epoch_s": history["compiled"][0][0]}
    for mode, runs in history.items():
        later = runs[1:] or runs  # the compiled trainer's first epoch includes compiling
        seconds = sum(s for s, _ in later)
        steps = sum(n for _, n in later)
        row[f"{mode}_s_per_epoch"] = seconds / len(later)
        row[f"{mode}_ms_per_step"] = 1e3 * seconds / steps
    row["speedup_per_step"] = row["eager_ms_per_step"] / row["compiled_ms_per_step"]
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algos", nargs="+", default=["ppo_lag", "cpo"])
    parser.add_argument("--env-id", default="SafetyHalfCheetahVelocity-v1")
    parser.add_argument("--epochs", type=int, default=3, help="per trainer; the first is left out of the means")
    parser.add_argument("--json", default=None, help="also write the rows here")
    args = parser.parse_args()
    if args.epochs < 2:
        parser.error("--epochs must be >= 2: the first (compiling) epoch is reported apart")
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        rows = [measure(algo, args.env_id, args.epochs, tmp) for algo in args.algos]
    print(f"\nUpdate time per 20,000-step epoch on {args.env_id} (epochs 2-{args.epochs}; one torch thread)")
    print("| algorithm | eager s / epoch | compiled s / epoch | eager ms / step | compiled ms / step | speed-up "
          "| first compiled epoch s |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['algo']} | {r['eager_s_per_epoch']:.1f} | {r['compiled_s_per_epoch']:.1f} | "
              f"{r['eager_ms_per_step']:.2f} | {r['compiled_ms_per_step']:.2f} | {r['speedup_per_step']:.2f}x | "
              f"{r['compile_first_epoch_s']:.1f} |")
    if args.json:
        write_json(args.json, rows, threads=1)


if __name__ == "__main__":
    main()
