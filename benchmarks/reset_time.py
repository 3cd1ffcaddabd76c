"""Reset time of sg_torchrl's envs: one simulator of a batch, and a whole one-simulator env.

For every env id this times, one reset at a time, after a warm-up:

* **one of N**: ``env.reset(TensorDict({"_reset": mask}))`` on an env of ``N`` simulators, the mask
  selecting a single simulator (a different one each time): what a collector pays when one
  episode ends. Everything TorchRL does around the reset is included.
* **full, N=1**: ``env.reset()`` of a one-simulator env: what a gymnasium user pays per episode.
* **env work**: the env's own part of a one-simulator reset (``_reset_sims``: sample a layout with
  its keep-outs, write it into ``MjData``, one forward pass), without TorchRL around it.

It prints median and 90th percentile in milliseconds. Safety-Gymnasium regenerates and recompiles
its model on every navigation reset (about 1.1 s on the 2-core machine kind); sg_torchrl writes a
new layout into the existing ``MjData`` (target: at most 1 ms median for one simulator).
Timings on a shared machine are noisy: the median is the figure to quote.

Usage::

    python benchmarks/reset_time.py
    python benchmarks/reset_time.py --ids SafetyPointGoal2-v0 --num-envs 64 --resets 2000 --json out.json
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from tensordict import TensorDict

import sg_torchrl
from _report import write_json

DEFAULT_IDS = ("SafetyPointGoal1-v0", "SafetyPointGoal2-v0", "SafetyPointButton1-v0", "SafetyPointPush1-v0",
               "SafetyHalfCheetahVelocity-v1")
REFERENCE_RESET_MS = 1100.0  # Safety-Gymnasium navigation reset (recompiles), 2-core machine kind


def _stats(seconds: list[float]) -> dict[str, float]:
    ms = np.asarray(seconds) * 1e3
    return {"median_ms": float(np.median(ms)), "p90_ms": float(np.percentile(ms, 90))}


def time_partial_resets(env, resets: int, warmup: int) -> list[float]:
    """Seconds of each ``env.reset`` of one simulator (rotating) of a batched env."""
    n = env.num_envs
    times = []
    env.reset()
    for k in range(warmup + resets):
        mask = torch.zeros(n, 1, dtype=torch.bool)
        mask[k % n] = True
        td = TensorDict({"_reset": mask}, batch_size=env.batch_size)  # fresh: reset consumes "_reset"
        start = time.perf_counter()
        env.reset(td)
        if k >= warmup:
            times.append(time.perf_counter() - start)
    return times


def time_full_resets(env, resets: int, warmup: int) -> list[float]:
    """Seconds of each ``env.reset()``."""
    times = []
    for k in range(warmup + resets):
        start = time.perf_counter()
        env.reset()
        if k >= warmup:
            times.append(time.perf_counter() - start)
    return times


def time_env_work(env, resets: int, warmup: int) -> list[float]:
    """Seconds of each ``env._reset_sims([0])``: the env's own reset work, no TorchRL around it."""
    index = np.zeros(1, dtype=np.int64)
    times = []
    for k in range(warmup + resets):
        start = time.perf_counter()
        env._reset_sims(index)
        if k >= warmup:
            times.append(time.perf_counter() - start)
    return times


def measure_resets(env_id: str, num_envs: int, resets: int, warmup: int, seed: int) -> dict:
    batched = sg_torchrl.make(env_id, num_envs=num_envs, seed=seed)
    partial = _stats(time_partial_resets(batched, resets, warmup))
    batched.close()
    single = sg_torchrl.make(env_id, num_envs=1, seed=seed)
    full = _stats(time_full_resets(single, resets, warmup))
    work = _stats(time_env_work(single, resets, warmup))
    single.close()
    return {
        "env_id": env_id, "num_envs": num_envs, "resets": resets,
        "one_of_n": partial, "full_n1": full, "env_work": work,
    }


def markdown_table(rows: list[dict]) -> str:
    lines = [
        "| env id | one sim of N: median / p90 (ms) | full reset, N=1: median / p90 (ms) | env work: median (ms) |",
        "|---|---:|---:|---:|",
    ]
    for row in rows:
        one, full, work = row["one_of_n"], row["full_n1"], row["env_work"]
        lines.append(
            f"| {row['env_id']} | N={row['num_envs']}: {one['median_ms']:.3f} / {one['p90_ms']:.3f} | "
            f"{full['median_ms']:.3f} / {full['p90_ms']:.3f} | {work['median_ms']:.3f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ids", nargs="+", default=list(DEFAULT_IDS), help="env ids to measure")
    parser.add_argument("--num-envs", type=int, default=16, help="batch size N for the one-simulator resets")
    parser.add_argument("--resets", type=int, default=500, help="timed resets per measurement")
    parser.add_argument("--warmup", type=int, default=20, help="untimed resets first")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    rows = []
    for env_id in args.ids:
        row = measure_resets(env_id, args.num_envs, args.resets, args.warmup, args.seed)
        rows.append(row)
        print(f"{env_id}: one of N={args.num_envs} {row['one_of_n']['median_ms']:.3f} ms median, "
              f"full N=1 {row['full_n1']['median_ms']:.3f} ms median", flush=True)
    print()
    print(markdown_table(rows))
    print(f"\nReference: Safety-Gymnasium recompiles its navigation model on every reset, about "
          f"{REFERENCE_RESET_MS:.0f} ms on the 2-core machine kind. Bar: one simulator <= 1 ms median.")
    if args.json:
        write_json(args.json, rows, threads=args.threads)
    return rows


if __name__ == "__main__":
    main()
