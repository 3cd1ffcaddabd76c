"""One seed group at the paper's budget: PPO-Lag, seeds 0 1 2, 10M env steps each (the seed-group engine at full scale).

The Safety-Gymnasium paper reports every cell after 10M steps; our 1M-step tables cannot tell a
correct Lagrangian method from a wrong one (PPO-Lag on SafetyHalfCheetahVelocity-v1 is at J^C 143
after 1M steps; the paper's row is 3025.42 / 0.00). This script trains the group in one process
(``sg-train --seeds 0 1 2 --compile true``, the paper's hyper-parameters) and prints each seed's
last-10-episode J^R / J^C beside the published row, with the group's wall time.

The same command starts the run, continues it after a stop (Ctrl-C or SIGTERM checkpoint the epoch
under way; a SIGKILL loses at most the epochs since the last checkpoint, under a minute of work),
and reports it once finished::

    nice python benchmarks/paper_budget.py                # start, or continue from the checkpoint
    python benchmarks/paper_budget.py --report-only       # the table so far (finished or not)

Results go to ``benchmarks/sweeps/halfcheetah_10m/<env>/<algo>/seeds-0-1-2/`` (config, progress and summaries
are committed; checkpoints, wandb and CSV logs stay local, see ``.gitignore``).
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import subprocess
import sys
from pathlib import Path

from sg_torchrl.sweep.report import PAPER_NAMES, load_paper_results, paper_env_name

HERE = Path(__file__).resolve().parent

OUTPUT = HERE / "sweeps" / "halfcheetah_10m"  # its column's sweep: the report draws the cell with the others


def group_dir(args: argparse.Namespace) -> Path:
    return Path(args.output_dir) / args.env_id / args.algo / ("seeds-" + "-".join(map(str, args.seeds)))


def train(args: argparse.Namespace) -> int:
    """Start the group, or continue it when its directory holds a checkpoint."""
    directory = group_dir(args)
    if (directory / "checkpoint.pt").exists():
        cmd = ["--resume", str(directory)]
    else:
        cmd = ["--algo", args.algo, "--env-id", args.env_id, "--seeds", *map(str, args.seeds),
               "--total-steps", str(args.total_steps), "--output-dir", args.output_dir, "--compile", "true",
               "--wandb", "offline", "--overwrite"]  # no checkpoint: at most a run killed before its first epoch
    return subprocess.call([sys.executable, "-m", "sg_torchrl.train", *cmd, *args.extra])


def report(args: argparse.Namespace) -> None:
    """Each seed's last-10-episode J^R / J^C (from its progress.csv) beside the paper's row."""
    directory = group_dir(args)
    paper = load_paper_results().get((paper_env_name(args.env_id), PAPER_NAMES[args.algo]))
    published = f"{paper[0]:.2f} / {paper[1]:.2f}" if paper else "n/a"
    print(f"{PAPER_NAMES[args.algo]} on {args.env_id}, {args.total_steps:,} steps per seed (paper: {published})\n")
    print("| seed | env steps | J^R (last 10) | J^C (last 10) | multiplier | wall h |")
    print("|---:|---:|---:|---:|---:|---:|")
    finals = []
    for seed in args.seeds:
        progress = directory / f"seed-{seed:03d}" / "progress.csv"
        # Training rows only: the final evaluation appends a row that holds the step count alone.
        rows = [row for row in csv.DictReader(progress.open()) if row.get("Metrics/EpRet")] if progress.exists() else []
        if not rows:
            print(f"| {seed} | 0 | | | | |")
            continue
        last = rows[-1]
        summary_path = directory / f"seed-{seed:03d}" / "summary.json"
        summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
        ret = float(summary.get("Final/EpRetLast10", last["Metrics/EpRet"]))
        cost = float(summary.get("Final/EpCostLast10", last["Metrics/EpCost"]))
        finals.append((ret, cost))
        print(f"| {seed} | {float(last['Train/TotalSteps']):,.0f} | {ret:.2f} | {cost:.2f} | "
              f"{float(last['Train/LagrangeMultiplier']):.3f} | {float(last['Time/Total']) / 3600:.2f} |")
    if finals:
        print(f"| mean | | {statistics.mean(r for r, _ in finals):.2f} | {statistics.mean(c for _, c in finals):.2f} "
              f"| | |")
    print("\n(J^R / J^C: the final summary's last 10 episodes once finished, else the last epoch's 50-episode window; "
          "wall h: the group's training time so far, which every seed shares)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", default="ppo_lag")
    parser.add_argument("--env-id", default="SafetyHalfCheetahVelocity-v1")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--total-steps", type=int, default=10_000_000)
    parser.add_argument("--output-dir", default=str(OUTPUT))
    parser.add_argument("--report-only", action="store_true")
    parser.add_argument("extra", nargs="*", help="more sg-train flags (after --)")
    args = parser.parse_args()
    if not args.report_only:
        code = train(args)
        if code not in (0, 130, 143):
            sys.exit(code)
    report(args)


if __name__ == "__main__":
    main()
