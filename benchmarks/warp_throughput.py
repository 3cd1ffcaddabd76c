"""Env steps per second with ``backend="warp"`` (MuJoCo Warp on a GPU) beside the CPU backend.

For every env id this times, in one process, full env steps (``env.step`` with one fixed random
action through ``step_and_maybe_reset``: physics, observation, reward, cost, resets, TorchRL's
TensorDict plumbing) and the bare physics (``physics.step`` with zero control), for:

* ``backend="warp"`` at each ``--num-envs`` (default 2048 and 8192) on the CUDA device;
* ``backend="cpu"`` (MuJoCo C) at ``--cpu-num-envs`` (default 64), the batch size CPU training uses.

Rates are env steps per second (``N`` x steps / seconds), best of ``--repeats`` after ``--warmup``
untimed steps (the first Warp steps compile or load the kernels and capture the CUDA graph).

Reference point: Isaac Gym, which the paper's dexterous-hand tasks ran on, reaches about 40,000 env
steps/s on ShadowHandOver at 2,048 envs on one RTX 3090 (the figure to compare against).
The envs here compute observations, rewards and costs in numpy on the host, so the env rate is
bounded by one device-to-host copy of the state per step plus that numpy work; the physics rate
shows what the simulator alone gives.

Without a CUDA device the script stops with a message, unless ``--allow-cpu``: then it runs Warp on
its CPU device with small ``N`` (for trying the script; kernels compile on first use, minutes).

Usage::

    python benchmarks/warp_throughput.py
    python benchmarks/warp_throughput.py --num-envs 2048 8192 --steps 200 --json warp.json
    python benchmarks/warp_throughput.py --allow-cpu --ids SafetyHalfCheetahVelocity-v1 --num-envs 8 --cpu-num-envs 8
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import torch

import sg_torchrl
from _report import write_json

DEFAULT_IDS = ("ShadowHandOverSafeJoint-v0", "SafetyHalfCheetahVelocity-v1")
ISAAC_GYM_REFERENCE = 40_000  # env steps/s, ShadowHandOver at 2,048 envs on an RTX 3090


def _cuda_available() -> bool:
    """Whether Warp and torch both see a CUDA device (what ``backend="warp"`` needs to use one)."""
    try:
        import warp
    except ImportError:
        return False
    return bool(warp.is_cuda_available() and torch.cuda.is_available())


def _best_seconds(run, steps: int, repeats: int, warmup: int) -> float:
    """Shortest wall time of ``repeats`` runs of ``steps`` calls of ``run()``, after ``warmup`` calls."""
    for _ in range(warmup):
        run()
    best = float("inf")
    for _ in range(repeats):
        begin = time.perf_counter()
        for _ in range(steps):
            run()
        best = min(best, time.perf_counter() - begin)
    return best


def measure(env_id: str, backend: str, num_envs: int, warp_device: str | None, steps: int, repeats: int,
            warmup: int, seed: int) -> dict:
    """Env and physics-only steps per second of ``env_id`` on ``backend`` with ``num_envs`` simulators."""
    options = {"warp_device": warp_device} if backend == "warp" else {}
    build = time.perf_counter()
    env = sg_torchrl.make(env_id, num_envs=num_envs, seed=seed, backend=backend, **options)
    td = env.reset()
    build = time.perf_counter() - build
    try:
        generator = torch.Generator().manual_seed(seed)
        box = env.full_action_spec[env.action_key].space
        action = box.low + (box.high - box.low) * torch.rand(box.low.shape, generator=generator)
        state = {"td": td}

        def env_step() -> None:  # episodes end and restart as in training
            state["td"].set(env.action_key, action)
            _, state["td"] = env.step_and_maybe_reset(state["td"])

        physics = env.physics
        ctrl = np.zeros((num_envs, physics.model.nu))  # the bare physics: zero control, no resets

        def physics_step() -> None:
            physics.step(ctrl, env.frame_skip)

        env_seconds = _best_seconds(env_step, steps, repeats, warmup)
        physics_seconds = _best_seconds(physics_step, steps, repeats, warmup)
    finally:
        env.close()
    device = getattr(env.physics, "device", "cpu (MuJoCo C)")
    return {"env_id": env_id, "backend": backend, "device": device, "num_envs": num_envs, "steps": steps,
            "build_and_reset_s": build, "env_steps_per_s": num_envs * steps / env_seconds,
            "physics_steps_per_s": num_envs * steps / physics_seconds}


def markdown_table(rows: list[dict]) -> str:
    lines = ["| env id | backend | device | N | env steps/s | physics steps/s |", "|---|---|---|---:|---:|---:|"]
    for row in rows:
        lines.append(f"| {row['env_id']} | {row['backend']} | {row['device']} | {row['num_envs']} | "
                     f"{row['env_steps_per_s']:,.0f} | {row['physics_steps_per_s']:,.0f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ids", nargs="+", default=list(DEFAULT_IDS), help="env ids to time")
    parser.add_argument("--num-envs", nargs="+", type=int, default=[2048, 8192], help="Warp batch sizes N")
    parser.add_argument("--cpu-num-envs", type=int, default=64, help="CPU backend batch size (0: skip it)")
    parser.add_argument("--steps", type=int, default=100, help="timed env steps per repeat")
    parser.add_argument("--repeats", type=int, default=3, help="runs per measurement; the best counts")
    parser.add_argument("--warmup", type=int, default=5, help="untimed steps before each measurement")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--allow-cpu", action="store_true",
                        help="without CUDA, run Warp on its CPU device (small N: for trying the script)")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    args = parser.parse_args(argv)
    try:
        import mujoco_warp  # noqa: F401
    except ImportError:
        sys.exit("warp_throughput.py: MuJoCo Warp is not installed (pip install 'sg_torchrl[warp]')")
    if _cuda_available():
        warp_device = "cuda:0"
    elif args.allow_cpu:
        warp_device = "cpu"
        print("no CUDA device: running MuJoCo Warp on its CPU device (rates say nothing about GPU throughput)")
    else:
        sys.exit("warp_throughput.py: no CUDA device visible to Warp and torch; this benchmark measures GPU "
                 "throughput. Pass --allow-cpu (with small --num-envs) to try it on Warp's CPU device.")
    torch.set_num_threads(1)
    rows = []
    for env_id in args.ids:
        runs = [("warp", n) for n in args.num_envs] + ([("cpu", args.cpu_num_envs)] if args.cpu_num_envs else [])
        for backend, num_envs in runs:
            row = measure(env_id, backend, num_envs, warp_device, args.steps, args.repeats, args.warmup, args.seed)
            rows.append(row)
            print(f"{env_id} {backend} N={num_envs}: {row['env_steps_per_s']:,.0f} env steps/s, "
                  f"{row['physics_steps_per_s']:,.0f} physics steps/s (built in {row['build_and_reset_s']:.0f} s)",
                  flush=True)
    print()
    print(markdown_table(rows))
    print(f"\nIsaac Gym reference: ~{ISAAC_GYM_REFERENCE:,} env steps/s (ShadowHandOver, 2,048 envs, RTX 3090)")
    if args.json:
        write_json(args.json, rows, threads=1)
    return rows


if __name__ == "__main__":
    main()
