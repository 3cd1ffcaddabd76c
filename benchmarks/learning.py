"""Learning benchmark: train algorithms x seeds with ``sg-train`` and print a results table.

Each cell is one ``sg-train`` run (paper hyper-parameters unless overridden); runs go ``--jobs``
at a time as separate processes (one torch thread each). The table reports, per algorithm, the
mean and per-seed EpRet / EpCost over the last 10 training episodes, the deterministic evaluation,
and the published SafePO numbers from ``reference/paper_results.csv`` where available.

    python benchmarks/learning.py --algos ppo_lag cppo_pid --seeds 0 1 2 --total-steps 1000000 --jobs 2
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

PAPER_RESULTS = Path(__file__).resolve().parents[1].parent / "shared" / "reference" / "paper_results.csv"
PAPER_NAMES = {"ppo_lag": "PPO-Lag", "cppo_pid": "CPPO-PID"}
PAPER_ENVS = {"SafetyHalfCheetahVelocity-v1": "HalfCheetahVel"}


def run_all(args: argparse.Namespace) -> list[tuple[str, int, Path]]:
    cells = [(algo, seed) for algo in args.algos for seed in args.seeds]
    pending, running, done = list(cells), [], []
    while pending or running:
        while pending and len(running) < args.jobs:
            algo, seed = pending.pop(0)
            run_dir = Path(args.output_dir) / args.env_id / algo / f"seed-{seed:03d}"
            cmd = [sys.executable, "-m", "sg_torchrl.train", "--algo", algo, "--env-id", args.env_id,
                   "--seed", str(seed), "--total-steps", str(args.total_steps), "--output-dir", args.output_dir,
                   "--progress", "false", "--wandb", args.wandb, *args.extra]
            if (run_dir / "summary.json").exists() and not args.force:
                print(f"[skip] {algo} seed {seed}: {run_dir}/summary.json exists", flush=True)
                done.append((algo, seed, run_dir))
                continue
            if (run_dir / "checkpoint.pt").exists() and not args.force:
                cmd += ["--resume", str(run_dir)]
            run_dir.mkdir(parents=True, exist_ok=True)
            log = open(run_dir / "stdout.log", "a")
            print(f"[start] {algo} seed {seed} -> {run_dir}", flush=True)
            running.append((algo, seed, run_dir, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), log))
        time.sleep(5)
        for item in list(running):
            algo, seed, run_dir, proc, log = item
            if proc.poll() is not None:
                log.close()
                running.remove(item)
                status = "done" if proc.returncode == 0 else f"FAILED (exit {proc.returncode}, see stdout.log)"
                print(f"[{status}] {algo} seed {seed}", flush=True)
                done.append((algo, seed, run_dir))
    return done


def paper_value(env_id: str, algo: str) -> tuple[str, str]:
    if not PAPER_RESULTS.exists() or env_id not in PAPER_ENVS:
        return "-", "-"
    with PAPER_RESULTS.open() as handle:
        for row in csv.DictReader(handle):
            if row["table"] == "single_agent_raw" and row["env"] == PAPER_ENVS[env_id] and row["algorithm"] == PAPER_NAMES.get(algo):
                return row["reward"], row["cost"]
    return "-", "-"


def table(results: list[tuple[str, int, Path]], env_id: str) -> str:
    lines = ["| algorithm | seed | EpRet (last 10) | EpCost (last 10) | eval EpRet | eval EpCost | env steps | wall s |",
             "|---|---|---|---|---|---|---|---|"]
    by_algo: dict[str, list[dict]] = {}
    for algo, seed, run_dir in results:
        path = run_dir / "summary.json"
        if not path.exists():
            lines.append(f"| {algo} | {seed} | (no summary) | | | | | |")
            continue
        s = json.loads(path.read_text())
        by_algo.setdefault(algo, []).append(s)
        lines.append(f"| {algo} | {seed} | {s['Final/EpRetLast10']:.1f} | {s['Final/EpCostLast10']:.2f} | "
                     f"{s.get('Metrics/EvalEpRet', float('nan')):.1f} | {s.get('Metrics/EvalEpCost', float('nan')):.2f} | "
                     f"{s['Train/TotalSteps']:.0f} | {s['Time/Total']:.0f} |")
    lines += ["", "| algorithm | seeds | mean EpRet | mean EpCost | max seed EpCost | paper EpRet | paper EpCost |",
              "|---|---|---|---|---|---|---|"]
    for algo, rows in by_algo.items():
        rets = [r["Final/EpRetLast10"] for r in rows]
        costs = [r["Final/EpCostLast10"] for r in rows]
        paper_ret, paper_cost = paper_value(env_id, algo)
        lines.append(f"| {algo} | {len(rows)} | {sum(rets)/len(rets):.1f} | {sum(costs)/len(costs):.2f} | "
                     f"{max(costs):.2f} | {paper_ret} | {paper_cost} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="SafetyHalfCheetahVelocity-v1")
    parser.add_argument("--algos", nargs="+", default=["ppo_lag", "cppo_pid"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--total-steps", type=int, default=1_000_000)
    parser.add_argument("--jobs", type=int, default=2, help="runs in parallel (one per core)")
    parser.add_argument("--output-dir", default="runs/benchmark")
    parser.add_argument("--wandb", default="disabled", choices=["offline", "online", "disabled"])
    parser.add_argument("--force", action="store_true", help="re-run cells that already have results")
    parser.add_argument("--report-only", action="store_true", help="only print the table of existing runs")
    parser.add_argument("extra", nargs="*", help="extra sg-train flags after --, e.g. -- --num-envs 20")
    args = parser.parse_args()
    if args.report_only:
        results = [(a, s, Path(args.output_dir) / args.env_id / a / f"seed-{s:03d}") for a in args.algos for s in args.seeds]
    else:
        results = run_all(args)
    print(table(results, args.env_id))


if __name__ == "__main__":
    main()
