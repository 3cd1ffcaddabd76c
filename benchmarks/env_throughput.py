"""Env throughput of sg_torchrl's batched MuJoCo envs against raw MuJoCo stepping.

For every env id and batch size ``N`` this measures, in the same process and interleaved:

* **ours**: ``env.step_and_maybe_reset`` in a loop with one fixed, precomputed action tensor
  (no policy), i.e. everything the env does per step: action validation, physics, observation,
  reward, cost, termination, auto-reset and the TensorDict round trip through TorchRL;
* **raw**: the physical limit, a plain Python loop over ``N`` ``mujoco.MjData`` of the same
  compiled model doing ``data.ctrl[:] = a; mujoco.mj_step(model, data, frame_skip)`` (plus
  ``mj_rnePostConstraint`` for robots whose observation reads contact forces, which the env
  cannot skip either). The raw simulators start from the env's own reset states, so both loops
  integrate the same trajectories (the cost of ``mj_step`` depends on the contacts) until the env
  resets an episode (Hopper, Walker2d, Ant and Humanoid terminate; the raw loop never resets).

Both report env steps per second (``N * steps / seconds``), best of ``--repeats`` runs after a
warm-up, and the table shows their ratio. Timings on a shared 2-core machine are noisy: compare
ratios measured in the same run, not absolute figures across runs.

Usage::

    python benchmarks/env_throughput.py
    python benchmarks/env_throughput.py --ids SafetyAntVelocity-v1 --num-envs 16 --steps 500 --json out.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import mujoco
import numpy as np
import torch

import sg_torchrl
from sg_torchrl.envs import registry_entry
from sg_torchrl.envs.velocity.robots import ROBOTS, load_model

DEFAULT_IDS = ("SafetyHalfCheetahVelocity-v1", "SafetyHopperVelocity-v1", "SafetyAntVelocity-v1")


def _fixed_action(env, seed: int) -> torch.Tensor:
    """One in-bounds random action per simulator, drawn once."""
    generator = torch.Generator().manual_seed(seed)
    low, high = env.action_spec.space.low, env.action_spec.space.high
    return low + (high - low) * torch.rand(low.shape, generator=generator)


def time_ours(env, td, action: torch.Tensor, steps: int, warmup: int) -> float:
    """Seconds for ``steps`` calls of ``env.step_and_maybe_reset``, starting from the reset ``td``."""
    for _ in range(warmup):
        td.set("action", action)
        _, td = env.step_and_maybe_reset(td)
    start = time.perf_counter()
    for _ in range(steps):
        td.set("action", action)
        _, td = env.step_and_maybe_reset(td)
    return time.perf_counter() - start


def time_raw(model: mujoco.MjModel, start: list[tuple[np.ndarray, np.ndarray]], action: np.ndarray,
             frame_skip: int, post_constraint: bool, steps: int, warmup: int) -> float:
    """Seconds for ``steps`` rounds of stepping ``N`` bare ``MjData`` (no env around them) from ``start``."""
    datas = [mujoco.MjData(model) for _ in range(len(action))]
    for data, (qpos, qvel) in zip(datas, start):
        data.qpos[:], data.qvel[:] = qpos, qvel
        mujoco.mj_forward(model, data)

    def run(n: int) -> None:
        for _ in range(n):
            for data, row in zip(datas, action):
                data.ctrl[:] = row
                mujoco.mj_step(model, data, frame_skip)
                if post_constraint:
                    mujoco.mj_rnePostConstraint(model, data)

    run(warmup)
    start = time.perf_counter()
    run(steps)
    return time.perf_counter() - start


def measure(env_id: str, num_envs: int, steps: int, repeats: int, warmup: int, seed: int) -> dict:
    entry = registry_entry(env_id)
    robot = ROBOTS[entry.robot]
    env = sg_torchrl.make(env_id, num_envs=num_envs, seed=seed)
    action = _fixed_action(env, seed)
    raw_action = action.double().numpy()
    model = load_model(robot.xml_file)
    post = "cfrc_ext" in robot.extra_observations
    ours, raw = [], []
    for _ in range(repeats):  # interleaved, so machine-load drift hits both alike
        td = env.reset()
        start = [(data.qpos.copy(), data.qvel.copy()) for data in env.physics.datas]
        ours.append(time_ours(env, td, action, steps, warmup))
        raw.append(time_raw(model, start, raw_action, robot.frame_skip, post, steps, warmup))
    env.close()
    ours_rate = num_envs * steps / min(ours)
    raw_rate = num_envs * steps / min(raw)
    return {
        "env_id": env_id, "num_envs": num_envs, "steps": steps, "repeats": repeats,
        "ours_steps_per_s": ours_rate, "raw_steps_per_s": raw_rate, "ratio": ours_rate / raw_rate,
        "physics_errors": env.physics_errors,
    }


def markdown_table(rows: list[dict]) -> str:
    lines = [
        "| env id | N | ours (env steps/s) | raw MuJoCo (env steps/s) | ours / raw |",
        "|---|---:|---:|---:|---:|",
    ]
    for row in rows:
        lines.append(
            f"| {row['env_id']} | {row['num_envs']} | {row['ours_steps_per_s']:,.0f} | "
            f"{row['raw_steps_per_s']:,.0f} | {row['ratio']:.0%} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ids", nargs="+", default=list(DEFAULT_IDS), help="env ids to measure")
    parser.add_argument("--num-envs", nargs="+", type=int, default=[1, 16, 64], help="batch sizes N")
    parser.add_argument("--steps", type=int, default=200, help="timed env.step calls per repeat")
    parser.add_argument("--repeats", type=int, default=3, help="runs per measurement; the best counts")
    parser.add_argument("--warmup", type=int, default=20, help="untimed steps before each run")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    rows = []
    for env_id in args.ids:
        for num_envs in args.num_envs:
            rows.append(measure(env_id, num_envs, args.steps, args.repeats, args.warmup, args.seed))
            row = rows[-1]
            print(f"{env_id} N={num_envs}: ours {row['ours_steps_per_s']:,.0f}/s, "
                  f"raw {row['raw_steps_per_s']:,.0f}/s ({row['ratio']:.0%})", flush=True)
    print()
    print(markdown_table(rows))
    if args.json:
        meta = {
            "python": platform.python_version(), "torch": torch.__version__, "mujoco": mujoco.__version__,
            "sg_torchrl": sg_torchrl.__version__, "threads": args.threads, "machine": platform.machine(),
        }
        with open(args.json, "w") as f:
            json.dump({"meta": meta, "results": rows}, f, indent=2)
    return rows


if __name__ == "__main__":
    main()
