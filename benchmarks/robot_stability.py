"""Robot stability under random actions: steps run, non-finite values, MuJoCo warnings, divergences.

For every env id this steps ``N`` simulators with uniform random actions inside the action spec's
bounds (the Racecar's per-actuator ranges, ``[-1, 1]`` elsewhere) for ``--steps`` batched steps,
resetting finished episodes as a collector does, and counts:

* **non-finite**: NaN or inf entries in ``observation``, ``reward`` or ``cost`` (there should be none);
* **MuJoCo warnings**: every warning counter of every ``MjData`` (instability, bad contact, too
  many contacts, ...), read after each step before a reset clears them (there should be none);
* **divergences**: simulators the env itself caught diverging, reset and reported truncated
  (``env.physics_errors``; there should be none);
* **terminations**: episodes that ended by the task's own rule (the Ant's torso falling to 0.08 m),
  which shows the death path ran, and the episodes that ended by time limit.

These figures check that the Racecar, Doggo and Ant robots behave; Point and Car
are included for comparison. A run of 16 simulators x 2,000 steps (32,000 env steps) per robot takes a
few minutes on one core.

Usage::

    python benchmarks/robot_stability.py
    python benchmarks/robot_stability.py --ids SafetyAntGoal2-v0 --num-envs 16 --steps 5000 --json out.json
"""

from __future__ import annotations

import argparse
import time

import torch
from torchrl.envs.utils import step_mdp

import sg_torchrl
from _report import write_json

DEFAULT_IDS = ("SafetyPointGoal1-v0", "SafetyCarGoal1-v0", "SafetyRacecarGoal1-v0", "SafetyDoggoGoal1-v0",
               "SafetyAntGoal1-v0")
CHECKED_KEYS = ("observation", "reward", "cost")


def warning_total(env) -> int:
    """The sum of every MuJoCo warning counter of every simulator since its last reset."""
    return int(sum(int(warning.number) for data in env.physics.datas for warning in data.warning))


def stress(env_id: str, num_envs: int, steps: int, seed: int, max_episode_steps: int) -> dict:
    """Step ``num_envs`` simulators of ``env_id`` with random in-bound actions; count what went wrong."""
    env = sg_torchrl.make(env_id, num_envs=num_envs, seed=seed, max_episode_steps=max_episode_steps,
                          cost_mode="raw")
    generator = torch.Generator().manual_seed(seed)
    low, high = env.action_spec.space.low, env.action_spec.space.high
    non_finite = warnings = terminations = truncations = 0
    td = env.reset()
    start = time.perf_counter()
    for _ in range(steps):
        action = low + (high - low) * torch.rand(low.shape, generator=generator)
        stepped = env.step(td.set("action", action))
        nxt = stepped["next"]
        non_finite += sum(int((~torch.isfinite(nxt[key])).sum()) for key in CHECKED_KEYS)
        warnings += warning_total(env)  # before the reset below clears the finished simulators' counters
        terminations += int(nxt["terminated"].sum())
        truncations += int((nxt["truncated"] & ~nxt["terminated"]).sum())
        td = env.maybe_reset(step_mdp(stepped))
    seconds = time.perf_counter() - start
    row = {
        "env_id": env_id, "num_envs": num_envs, "env_steps": steps * num_envs, "non_finite": non_finite,
        "mujoco_warnings": warnings, "divergences": int(env.physics_errors), "terminations": terminations,
        "time_limit_ends": truncations, "seconds": seconds,
    }
    env.close()
    return row


def markdown_table(rows: list[dict]) -> str:
    lines = [
        "| env id | env steps | non-finite values | MuJoCo warnings | divergences | terminations | time-limit ends "
        "| seconds |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        lines.append(
            f"| {row['env_id']} | {row['env_steps']:,} | {row['non_finite']} | {row['mujoco_warnings']} | "
            f"{row['divergences']} | {row['terminations']} | {row['time_limit_ends']} | {row['seconds']:.0f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ids", nargs="+", default=list(DEFAULT_IDS))
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--steps", type=int, default=2000, help="batched steps per env id")
    parser.add_argument("--max-episode-steps", type=int, default=500, help="short episodes exercise resets")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", help="also write the rows to this JSON file")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for env_id in args.ids:
        rows.append(stress(env_id, args.num_envs, args.steps, args.seed, args.max_episode_steps))
        print(f"{env_id}: {rows[-1]['env_steps']:,} env steps in {rows[-1]['seconds']:.0f} s", flush=True)
    print(markdown_table(rows))
    if args.json:
        write_json(args.json, rows, threads=args.threads)


if __name__ == "__main__":
    main()
