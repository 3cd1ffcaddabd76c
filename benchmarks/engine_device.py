"""The whole seed-group engine on a GPU beside the CPU: per-seed cost of 1,000 env steps at S = 1 ... 256.

``benchmarks/group_step_device.py`` times the fused minibatch step alone. This script trains the
engine itself, as ``sg-train --seeds 0 .. S-1 --device D`` does (``TrainConfig`` and
``trainer_class``): the simulators on CPU MuJoCo (or the backend ``--env-options`` selects), one
observation copy to the device and one action copy back per env step, then GAE and the algorithm's
update on the device. Rows, in one run, each in a fresh (spawned) process with one torch thread:

* ``cuda``: S of ``--seeds`` (default 1, 8, 64, 256) with ``--device cuda``;
* ``cpu``: S of ``--cpu-seeds`` (default 1, 8) with ``--device cpu``: the baseline, on the same machine.

Each row trains ``--epochs`` epochs of ``--steps-per-epoch`` env steps per seed from ``--num-envs``
simulators per seed (the algorithm's own update settings: PPO-Lag 40 passes of minibatch 64 with KL
early stop). Reported per row over the epochs after the first (no warm-up, no CUDA start-up):
seconds per 1,000 env steps *per seed* of wall time and of CPU time (``time.process_time``, every
thread of the process), the wall split into collection and update, the update passes the KL stop
allowed (rows that stop at different passes do different work), the peak GPU memory, and the
per-seed wall speed against the CPU row with S = 1.

Without CUDA the script refuses to run; ``--allow-cpu`` runs the CPU rows alone (to try it, or as a
smoke test).

    python benchmarks/engine_device.py                                   # on a GPU machine: minutes
    python benchmarks/engine_device.py --seeds 1 64 --cpu-seeds 1 --epochs 2 --json engine.json
    python benchmarks/engine_device.py --allow-cpu --cpu-seeds 1 2 --steps-per-epoch 200 --num-envs 2
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def train_row(device: str, seeds: int, args: dict) -> dict:
    """Train one configuration (in its own process); its per-epoch timings and passes."""
    torch.set_num_threads(1)
    from sg_torchrl.train import TrainConfig, trainer_class

    with tempfile.TemporaryDirectory() as tmp:
        cfg = TrainConfig(algo=args["algo"], env_id=args["env_id"], env_options=dict(args["env_options"]),
                          seeds=list(range(seeds)), total_steps=args["epochs"] * args["steps_per_epoch"],
                          steps_per_epoch=args["steps_per_epoch"], num_envs=args["num_envs"], device=device,
                          wandb="disabled", eval_episodes=0, progress=False, output_dir=tmp,
                          checkpoint_every=10**6, checkpoint_minutes=10**6)
        trainer = trainer_class(cfg)(cfg)
        epochs = []
        for _ in range(args["epochs"]):
            if device != "cpu":
                torch.cuda.synchronize()
            wall, cpu = time.perf_counter(), time.process_time()
            trainer.train_epoch()  # outside run(): no checkpoint
            if device != "cpu":
                torch.cuda.synchronize()
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            rows = [run.last_row for run in trainer.runs if run.last_row is not None]
            epochs.append({"wall": wall, "cpu": cpu, "collect": rows[0]["Time/Rollout"],
                           "update": rows[0]["Time/Update"],
                           "passes": statistics.mean(row["Train/StopIter"] for row in rows)})
        memory = torch.cuda.max_memory_allocated() / 2**20 if device != "cpu" else None
    return {"device": device, "seeds": seeds, "epochs": epochs, "gpu_mib": memory}


def summarise(row: dict, steps_per_epoch: int) -> dict:
    """Seconds per 1,000 env steps per seed over the epochs after the first (all when there is one)."""
    steady = row["epochs"][1:] or row["epochs"]
    thousands = len(steady) * steps_per_epoch / 1000 * row["seeds"]  # per-seed steps, all seeds
    total = {key: sum(epoch[key] for epoch in steady) / thousands for key in ("wall", "cpu", "collect", "update")}
    return {**row, **{f"{key}_per_1k_per_seed": value for key, value in total.items()},
            "passes": statistics.mean(epoch["passes"] for epoch in steady)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", default="ppo_lag")
    parser.add_argument("--env-id", default="SafetyHalfCheetahVelocity-v1")
    parser.add_argument("--env-options", nargs="*", default=[], metavar="KEY=VALUE",
                        help="env options (e.g. physics_threads=8), as sg-train takes them")
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 8, 64, 256], help="S on the GPU")
    parser.add_argument("--cpu-seeds", nargs="+", type=int, default=[1, 8], help="S on the CPU (baseline)")
    parser.add_argument("--steps-per-epoch", type=int, default=2000, help="env steps per seed per epoch")
    parser.add_argument("--num-envs", type=int, default=10, help="simulators per seed")
    parser.add_argument("--epochs", type=int, default=3, help="epochs per row; the first is not counted")
    parser.add_argument("--allow-cpu", action="store_true", help="run the CPU rows alone when CUDA is missing")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    if not torch.cuda.is_available() and not args.allow_cpu:
        sys.exit("engine_device.py: no CUDA device (pass --allow-cpu to run the CPU rows alone)")
    from sg_torchrl.train.command_line import parse_env_option

    settings = {"algo": args.algo, "env_id": args.env_id, "env_options": dict(map(parse_env_option, args.env_options)),
                "epochs": args.epochs, "steps_per_epoch": args.steps_per_epoch, "num_envs": args.num_envs}
    plan = [("cpu", s) for s in args.cpu_seeds]
    if torch.cuda.is_available():
        plan += [("cuda", s) for s in args.seeds]
        print(f"GPU: {torch.cuda.get_device_name()}, torch {torch.__version__}", flush=True)
    rows = []
    for device, seeds in plan:
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
            row = summarise(pool.submit(train_row, device, seeds, settings).result(), args.steps_per_epoch)
        rows.append(row)
        print(f"  {device} S={seeds}: {row['wall_per_1k_per_seed']:.3f} s wall, {row['cpu_per_1k_per_seed']:.3f} s "
              f"CPU per 1k steps per seed", flush=True)
    base = next((r for r in rows if r["device"] == "cpu" and r["seeds"] == 1), None)
    print(f"\n{args.algo} on {args.env_id}, {args.steps_per_epoch} steps per seed per epoch from {args.num_envs} "
          f"simulators per seed; seconds per 1,000 env steps per seed (epochs 2..{args.epochs})")
    print("| device | S | wall | CPU | collect | update | passes | GPU MiB | per-seed wall speed vs CPU S=1 |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        speed = f"{base['wall_per_1k_per_seed'] / row['wall_per_1k_per_seed']:.2f}x" if base else "-"
        memory = "-" if row["gpu_mib"] is None else f"{row['gpu_mib']:.0f}"
        print(f"| {row['device']} | {row['seeds']} | {row['wall_per_1k_per_seed']:.3f} | {row['cpu_per_1k_per_seed']:.3f} "
              f"| {row['collect_per_1k_per_seed']:.3f} | {row['update_per_1k_per_seed']:.3f} | {row['passes']:.1f} "
              f"| {memory} | {speed} |")
    if args.json:
        from _report import write_json

        write_json(args.json, rows, threads=1)


if __name__ == "__main__":
    main()
