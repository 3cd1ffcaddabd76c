"""Multi-agent velocity envs: env steps/s beside the single-agent env and raw MuJoCo of the same robot.

For every multi-agent id (``Safety2x4AntVelocity-v0``, ...) and batch size ``N`` this measures, in
one process, with ``benchmarks/env_throughput.py``'s ``measure`` (interleaved repeats, best of
``--repeats``, fixed random actions, auto-resets inside ``step_and_maybe_reset``):

* **multi-agent**: the batched :class:`~sg_torchrl.envs.multi_agent.MultiAgentVelocityEnv`
  (group action in, per-agent observations, rewards, costs and flags plus ``state`` out);
* **single-agent**: the same robot's ``Safety<Robot>Velocity-v0`` (:class:`VelocityEnv`, the same
  physics, reward and cost code behind a single-agent interface);
* **raw**: the physical limit, bare ``mujoco.mj_step`` over ``N`` ``MjData`` of the robot's model
  with its frame skip (and ``mj_rnePostConstraint`` where the observation reads contact forces).

The table reports each as env steps per second and as a ratio to the raw loop. As in
``env_throughput.py`` the raw loop never resets while the envs reset terminated episodes: with random
actions the Humanoid falls within about 20 steps, and a fallen Humanoid (about 5 contacts instead of
1) steps about 20% slower, so its env can outrun its raw loop (ratios above 100%). The difference
between the first two is the price of the multi-agent layout (two numpy gathers and a nested
TensorDict per step); MaMuJoCo through TorchRL's ``PettingZooWrapper`` runs about 15x slower than
its raw PettingZoo loop (``reference/stack_notes.md``). Timings on a shared 2-core machine are noisy:
compare ratios measured in the same run.

Usage::

    python benchmarks/multi_agent_throughput.py
    python benchmarks/multi_agent_throughput.py --ids Safety2x4AntVelocity-v0 --num-envs 16 64 --json out.json
"""

from __future__ import annotations

import argparse

import torch

import sg_torchrl
from _report import write_json
from env_throughput import measure
from sg_torchrl.envs import registry_entry


def single_agent_id(env_id: str) -> str:
    """The single-agent velocity id of a multi-agent id's robot (v0, like the multi-agent ids)."""
    return f"Safety{registry_entry(env_id).robot}Velocity-v0"


def markdown_table(rows: list[dict]) -> str:
    lines = [
        "| env id | N | multi-agent (env steps/s) | single-agent (env steps/s) | raw MuJoCo (env steps/s) "
        "| multi-agent / raw | single-agent / raw |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        lines.append(
            f"| {row['env_id']} | {row['num_envs']} | {row['multi_agent_steps_per_s']:,.0f} | "
            f"{row['single_agent_steps_per_s']:,.0f} | {row['raw_steps_per_s']:,.0f} | "
            f"{row['multi_agent_ratio']:.0%} | {row['single_agent_ratio']:.0%} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ids", nargs="+", default=sg_torchrl.list_envs(family="multi_agent_velocity"))
    parser.add_argument("--num-envs", nargs="+", type=int, default=[16], help="batch sizes N")
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
            multi = measure(env_id, num_envs, args.steps, args.repeats, args.warmup, args.seed)
            single = measure(single_agent_id(env_id), num_envs, args.steps, args.repeats, args.warmup, args.seed)
            # Both raw loops step the same model; the faster of the two is the physical limit.
            raw = max(multi["raw_steps_per_s"], single["raw_steps_per_s"])
            rows.append({
                "env_id": env_id, "single_agent_id": single["env_id"], "num_envs": num_envs, "steps": args.steps,
                "repeats": args.repeats, "multi_agent_steps_per_s": multi["ours_steps_per_s"],
                "single_agent_steps_per_s": single["ours_steps_per_s"], "raw_steps_per_s": raw,
                "multi_agent_ratio": multi["ours_steps_per_s"] / raw,
                "single_agent_ratio": single["ours_steps_per_s"] / raw,
                "raw_includes": multi["raw_includes"],
            })
            row = rows[-1]
            print(f"{env_id} N={num_envs}: multi-agent {row['multi_agent_steps_per_s']:,.0f}/s, single-agent "
                  f"{row['single_agent_steps_per_s']:,.0f}/s, raw {raw:,.0f}/s", flush=True)
    print()
    print(markdown_table(rows))
    if args.json:
        write_json(args.json, rows, threads=args.threads)
    return rows


if __name__ == "__main__":
    main()
