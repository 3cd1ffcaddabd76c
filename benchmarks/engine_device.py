"""The whole seed-group engine on a GPU beside the CPU: per-seed cost of 1,000 env steps at S = 1 ... 256.

``benchmarks/group_step_device.py`` times the fused minibatch step alone. This script trains the
engine itself, as ``sg-train --seeds 0 .. S-1 --device D`` does (``TrainConfig`` and
``trainer_class``): the simulators on CPU MuJoCo (or the backend ``--env-options`` selects), one
observation copy to the device and one action copy back per env step, then GAE and the algorithm's
update on the device. Rows, in one run, each in a fresh (spawned) process with one torch thread, for
each algorithm of ``--algos`` (default one per family: PPO-Lag, MAPPO-Lag, SAC-Lag):

* ``cuda``: S of ``--seeds`` (default 1, 8, 64, 256) with ``--device cuda``;
* ``cpu``: S of ``--cpu-seeds`` (default 1, 8) with ``--device cpu``: the baseline, on the same machine.

Each row trains ``--epochs`` epochs of ``--steps-per-epoch`` env steps per seed from ``--num-envs``
simulators per seed, on ``--env-id`` or the algorithm's default env (``sg-train``'s: SafetyHalfCheetahVelocity-v1,
for the multi-agent algorithms Safety2x3HalfCheetahVelocity-v0), with the algorithm's own update settings
(PPO-Lag 40 passes of minibatch 64 with KL early stop; MAPPO-Lag 5 passes of one whole-batch minibatch
per agent; SAC-Lag one gradient step of minibatch 256 per env step), except that an off-policy row's
first epoch is its warm-up (random actions) and its replay buffer holds the run's steps. Reported per
row over the epochs after the first (no warm-up, no CUDA start-up): seconds per 1,000 env steps *per
seed* of wall time and of CPU time (``time.process_time``, every thread of the process), the wall split
into collection and update (off-policy: the gradient steps taken during collection), the update passes
the KL stop allowed (rows that stop at different passes do different work; off-policy: gradient steps per
epoch), the peak GPU memory, and the per-seed wall speed against the same algorithm's CPU row with S = 1.

Without CUDA the script refuses to run; ``--allow-cpu`` runs the CPU rows alone (to try it, or as a
smoke test).

    python benchmarks/engine_device.py                                   # on a GPU machine: minutes
    python benchmarks/engine_device.py --seeds 1 64 --cpu-seeds 1 --epochs 2 --json engine.json
    python benchmarks/engine_device.py --algos mappo_lag --seeds 1 8 64 --cpu-seeds 1
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


def row_config(algo: str, device: str, seeds: int, args: dict, output_dir: str):
    """The ``TrainConfig`` of one row (an off-policy row: its first epoch warm-up, its replay the run's steps)."""
    from sg_torchrl.train import TrainConfig

    total = args["epochs"] * args["steps_per_epoch"]
    probe = TrainConfig(algo=algo)  # the family's default env and options
    env_id = args["env_id"] or probe.env_id
    extra = dict(warmup_steps=args["steps_per_epoch"], replay_size=total) if probe.off_policy else {}
    return TrainConfig(algo=algo, env_id=env_id, env_options=dict(args["env_options"]), seeds=list(range(seeds)),
                       total_steps=total, steps_per_epoch=args["steps_per_epoch"], num_envs=args["num_envs"],
                       device=device, wandb="disabled", eval_episodes=0, progress=False, output_dir=output_dir,
                       checkpoint_every=10**6, checkpoint_minutes=10**6, **extra)


def train_row(algo: str, device: str, seeds: int, args: dict) -> dict:
    """Train one configuration (in its own process); its per-epoch timings and passes."""
    torch.set_num_threads(1)
    from sg_torchrl.train import trainer_class

    with tempfile.TemporaryDirectory() as tmp:
        cfg = row_config(algo, device, seeds, args, tmp)
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
            passes = "Train/GradientSteps" if cfg.off_policy else "Train/StopIter"  # off-policy: gradient steps so far
            epochs.append({"wall": wall, "cpu": cpu, "collect": rows[0]["Time/Rollout"],
                           "update": rows[0]["Time/Update"],
                           "passes": statistics.mean(row[passes] for row in rows)})
        memory = torch.cuda.max_memory_allocated() / 2**20 if device != "cpu" else None
    if cfg.off_policy:  # the gradient steps of each epoch, from the running count
        counts = [0.0] + [epoch["passes"] for epoch in epochs]
        for epoch, before, after in zip(epochs, counts, counts[1:]):
            epoch["passes"] = after - before
    return {"algo": algo, "device": device, "seeds": seeds, "epochs": epochs, "gpu_mib": memory}


def summarise(row: dict, steps_per_epoch: int) -> dict:
    """Seconds per 1,000 env steps per seed over the epochs after the first (all when there is one)."""
    steady = row["epochs"][1:] or row["epochs"]
    thousands = len(steady) * steps_per_epoch / 1000 * row["seeds"]  # per-seed steps, all seeds
    total = {key: sum(epoch[key] for epoch in steady) / thousands for key in ("wall", "cpu", "collect", "update")}
    return {**row, **{f"{key}_per_1k_per_seed": value for key, value in total.items()},
            "passes": statistics.mean(epoch["passes"] for epoch in steady)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algos", nargs="+", default=["ppo_lag", "mappo_lag", "sac_lag"],
                        help="algorithms, each with its rows (default: one per family)")
    parser.add_argument("--env-id", default=None,
                        help="the env of every row (default: each algorithm's sg-train default)")
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

    settings = {"env_id": args.env_id, "env_options": dict(map(parse_env_option, args.env_options)),
                "epochs": args.epochs, "steps_per_epoch": args.steps_per_epoch, "num_envs": args.num_envs}
    plan = [("cpu", s) for s in args.cpu_seeds]
    if torch.cuda.is_available():
        plan += [("cuda", s) for s in args.seeds]
        print(f"GPU: {torch.cuda.get_device_name()}, torch {torch.__version__}", flush=True)
    rows = []
    for algo in args.algos:
        for device, seeds in plan:
            with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
                row = summarise(pool.submit(train_row, algo, device, seeds, settings).result(), args.steps_per_epoch)
            rows.append(row)
            print(f"  {algo} {device} S={seeds}: {row['wall_per_1k_per_seed']:.3f} s wall, "
                  f"{row['cpu_per_1k_per_seed']:.3f} s CPU per 1k steps per seed", flush=True)
    env = args.env_id or "each algorithm's default env"
    print(f"\n{args.steps_per_epoch} steps per seed per epoch from {args.num_envs} simulators per seed on "
          f"{env}; seconds per 1,000 env steps "
          f"per seed (epochs 2..{args.epochs}); passes: update passes (off-policy: gradient steps per epoch)")
    print("| algo | device | S | wall | CPU | collect | update | passes | GPU MiB | per-seed wall speed vs CPU S=1 |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        base = next((r for r in rows if r["algo"] == row["algo"] and r["device"] == "cpu" and r["seeds"] == 1), None)
        speed = f"{base['wall_per_1k_per_seed'] / row['wall_per_1k_per_seed']:.2f}x" if base else "-"
        memory = "-" if row["gpu_mib"] is None else f"{row['gpu_mib']:.0f}"
        print(f"| {row['algo']} | {row['device']} | {row['seeds']} | {row['wall_per_1k_per_seed']:.3f} "
              f"| {row['cpu_per_1k_per_seed']:.3f} | {row['collect_per_1k_per_seed']:.3f} "
              f"| {row['update_per_1k_per_seed']:.3f} | {row['passes']:.1f} | {memory} | {speed} |")
    if args.json:
        from _report import write_json

        write_json(args.json, rows, threads=1)


if __name__ == "__main__":
    main()
