"""Algorithm benchmark: ``sg-train`` over algorithms x envs x seeds, tabulated like the paper.

Each cell is one ``sg-train`` run with the paper's hyper-parameters for its algorithm (override with
extra flags after ``--``); runs go ``--jobs`` at a time as separate processes (one torch thread
each) and a cell whose ``summary.json`` exists is reused, so an interrupted benchmark continues (from
the cell's last checkpoint; Ctrl-C stops the running cells at the end of their epoch under way,
checkpointed). The cells measured so far are kept in ``benchmarks/runs`` (config,
progress and summary of each; ``--report-only`` prints their table), so a later benchmark only
runs the missing cells.

Per (env, algorithm) the table gives, as the Safety-Gymnasium paper's tables do, J^R and J^C (mean
over seeds of the last 10 training episodes' return and cost), the normalised J^R / J^R(PPO) (our
PPO run on the same env and budget, when it is in the benchmark; MAPPO for the multi-agent
algorithms on the multi-agent ids) and J^C / cost limit, the seconds per update of one epoch
(20,000 steps; multi-agent 10,000), and the published numbers from
``sg_torchrl/sweep/paper_results.csv`` (10M steps) with their own normalisation. ``--per-seed``
adds one row per finished run (its figures, evaluation, update seconds and wall minutes).

    python benchmarks/algorithms.py --envs SafetyPointGoal1-v0 --algos ppo ppo_lag cpo --seeds 0 1 2 \\
        --total-steps 1000000 --jobs 2
"""

from __future__ import annotations

import argparse
import csv
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

# The paper's names and published tables live with the sweep report (sg_torchrl.sweep.report).
from sg_torchrl.sweep.report import PAPER_NAMES, baseline, load_paper_results, paper_env_name


def run_dir(output_dir: str, env_id: str, algo: str, seed: int) -> Path:
    return Path(output_dir) / env_id / algo / f"seed-{seed:03d}"


def command(args: argparse.Namespace, env_id: str, algo: str, seed: int) -> list[str]:
    return [sys.executable, "-m", "sg_torchrl.train", "--algo", algo, "--env-id", env_id, "--seed", str(seed),
            "--total-steps", str(args.total_steps), "--output-dir", args.output_dir, "--progress", "false",
            "--wandb", args.wandb, *args.extra]


def run_all(args: argparse.Namespace) -> None:
    """Run every missing cell, ``--jobs`` processes at a time; resume cells that have a checkpoint.

    A cell without a checkpoint (or every cell with ``--force``) starts over with ``--overwrite``:
    sg-train refuses a run directory that already holds a run unless told so, and such a cell's
    directory holds at most what a run killed before its first checkpoint logged (or, with
    ``--force``, the results to be replaced).

    Ctrl-C (or ``SIGTERM``) starts no further cell and asks the running ones to stop after their
    epoch under way, checkpointed (``sg-train``'s own handling, :mod:`sg_torchrl.train.interrupt`);
    running the benchmark again continues them. The cells run in their own sessions, so a Ctrl-C
    at the terminal reaches them once, through this runner, not twice (which would stop them at once).
    """
    pending = [(env, algo, seed) for env in args.envs for algo in args.algos for seed in args.seeds]
    if args.seed_major:  # every cell's first seed before any second seed: a cut-short benchmark covers every cell
        pending.sort(key=lambda cell: args.seeds.index(cell[2]))
    running: list[tuple[str, subprocess.Popen, object]] = []
    previous_sigterm = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        while pending or running:
            while pending and len(running) < args.jobs:
                env_id, algo, seed = pending.pop(0)
                directory = run_dir(args.output_dir, env_id, algo, seed)
                label = f"{env_id} {algo} seed {seed}"
                if (directory / "summary.json").exists() and not args.force:
                    print(f"[skip] {label}: summary.json exists", flush=True)
                    continue
                cmd = command(args, env_id, algo, seed)
                if (directory / "checkpoint.pt").exists() and not args.force:
                    cmd += ["--resume", str(directory)]
                else:  # a new cell, --force, or one killed before its first checkpoint: start it over
                    cmd += ["--overwrite"]
                directory.mkdir(parents=True, exist_ok=True)
                log = open(directory / "stdout.log", "a")
                print(f"[start] {label} -> {directory}", flush=True)
                process = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
                running.append((label, process, log))
            time.sleep(2)
            _reap(running)
    except KeyboardInterrupt:
        print(f"[stopping] {len(running)} running cell(s) finish their epoch and checkpoint; "
              "run the same command again to continue", flush=True)
        for _, process, _ in running:
            process.send_signal(signal.SIGINT)
        while running:
            time.sleep(0.5)
            _reap(running)
        raise
    finally:
        signal.signal(signal.SIGTERM, previous_sigterm)


#: sg-train's exit codes after a Ctrl-C / SIGTERM stop (128 + the signal), checkpointed at an epoch's end.
INTERRUPTED_EXIT_CODES = frozenset({128 + signal.SIGINT, 128 + signal.SIGTERM})


def _reap(running: list[tuple[str, subprocess.Popen, object]]) -> None:
    """Report and drop the finished processes of ``running``."""
    for item in list(running):
        label, proc, log = item
        if proc.poll() is None:
            continue
        log.close()
        running.remove(item)
        if proc.returncode == 0:
            status = "done"
        elif proc.returncode in INTERRUPTED_EXIT_CODES:
            status = "interrupted (checkpointed; the same command continues it)"
        else:
            status = f"FAILED (exit {proc.returncode}, see stdout.log)"
        print(f"[{status}] {label}", flush=True)


def cell_summary(directory: Path) -> dict[str, float] | None:
    """A run's final figures, its mean update seconds per epoch and whether its losses were compiled
    (``--compile true``, which shortens the update), or None if it has not finished."""
    path = directory / "summary.json"
    if not path.exists():
        return None
    summary = json.loads(path.read_text())
    progress = directory / "progress.csv"
    update_seconds = []
    if progress.exists():
        with progress.open() as handle:
            update_seconds = [float(row["Time/Update"]) for row in csv.DictReader(handle) if row.get("Time/Update")]
    summary["update_s"] = sum(update_seconds) / len(update_seconds) if update_seconds else float("nan")
    config = directory / "config.json"
    summary["compiled"] = bool(json.loads(config.read_text()).get("compile", False)) if config.exists() else False
    return summary


def finished_runs(args: argparse.Namespace, env_id: str, algo: str) -> list[tuple[int, dict[str, float]]]:
    """``(seed, cell_summary)`` of each of ``args.seeds`` whose run on (``env_id``, ``algo``) has finished."""
    return [(seed, summary) for seed in args.seeds
            if (summary := cell_summary(run_dir(args.output_dir, env_id, algo, seed)))]


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else float("nan")


def table(args: argparse.Namespace) -> str:
    """The paper-format table of every (env, algorithm) with at least one finished seed."""
    paper = load_paper_results()
    lines = [
        f"Budget {args.total_steps:,} env steps per run; seeds {' '.join(map(str, args.seeds))}; "
        f"cost limit {args.cost_limit:g}. Paper: 10M steps.",
        "",
        "| env | algorithm | seeds | J^R | J^C | J^R / J^R(PPO or MAPPO) | J^C / limit | update s / epoch "
        "| paper J^R | paper J^C | paper J^R / PPO | paper J^C / limit |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for env_id in args.envs:
        cells = {}
        for algo in args.algos:
            runs = [summary for _, summary in finished_runs(args, env_id, algo)]
            if runs:
                cells[algo] = runs
        env_name = paper_env_name(env_id)
        for algo, runs in cells.items():
            ppo_return = _mean([r["Final/EpRetLast10"] for r in cells.get(baseline(algo), [])])
            paper_ppo = paper.get((env_name, PAPER_NAMES[baseline(algo)]), (float("nan"), 0.0))[0]
            reward = _mean([r["Final/EpRetLast10"] for r in runs])
            cost = _mean([r["Final/EpCostLast10"] for r in runs])
            update = _mean([r["update_s"] for r in runs])
            compiled = sum(r["compiled"] for r in runs)
            seeds = f"{len(runs)} ({compiled} compiled)" if compiled else str(len(runs))
            paper_reward, paper_cost = paper.get((env_name, PAPER_NAMES[algo]), (float("nan"), float("nan")))
            lines.append(
                f"| {env_id} | {PAPER_NAMES[algo]} | {seeds} | {reward:.2f} | {cost:.2f} | "
                f"{reward / ppo_return:.2f} | {cost / args.cost_limit:.2f} | {update:.1f} | "
                f"{paper_reward:.2f} | {paper_cost:.2f} | {paper_reward / paper_ppo:.2f} | "
                f"{paper_cost / args.cost_limit:.2f} |".replace("nan", "-")
            )
    return "\n".join(lines)


def seed_table(args: argparse.Namespace) -> str:
    """One row per finished run: its last-10-episode and deterministic-evaluation figures, its update
    seconds per epoch and wall minutes (``*`` marks compiled runs, whose update times are shorter)."""
    lines = [
        "| env | algorithm | seed | EpRet (last 10) | EpCost (last 10) | eval EpRet | eval EpCost "
        "| update s / epoch | wall min |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for env_id in args.envs:
        for algo in args.algos:
            for seed, run in finished_runs(args, env_id, algo):
                lines.append(
                    f"| {env_id} | {PAPER_NAMES[algo]} | {seed}{'*' if run['compiled'] else ''} | "
                    f"{run['Final/EpRetLast10']:.1f} | {run['Final/EpCostLast10']:.1f} | "
                    f"{run.get('Metrics/EvalEpRet', float('nan')):.1f} | {run.get('Metrics/EvalEpCost', float('nan')):.1f} | "
                    f"{run['update_s']:.1f} | {run.get('Time/Total', float('nan')) / 60:.0f} |".replace("nan", "-")
                )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["SafetyPointGoal1-v0"])
    parser.add_argument("--algos", nargs="+", default=["ppo", "ppo_lag", "cpo"], choices=sorted(PAPER_NAMES))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--total-steps", type=int, default=1_000_000)
    parser.add_argument("--cost-limit", type=float, default=25.0, help="for J^C / limit (pass --cost-limit to "
                        "sg-train after -- as well to train with another limit)")
    parser.add_argument("--jobs", type=int, default=2, help="runs in parallel (one per core)")
    parser.add_argument("--output-dir", default="benchmarks/runs", help="one folder per cell; benchmarks/runs keeps "
                        "the finished cells' config, progress and summary in git (checkpoints stay local)")
    parser.add_argument("--wandb", default="disabled", choices=["offline", "online", "disabled"])
    parser.add_argument("--force", action="store_true", help="re-run cells that already have results")
    parser.add_argument("--seed-major", action="store_true", help="run seed 0 of every cell, then seed 1, ...")
    parser.add_argument("--report-only", action="store_true", help="only print the table of existing runs")
    parser.add_argument("--per-seed", action="store_true", help="also print one row per finished run")
    parser.add_argument("extra", nargs="*", help="extra sg-train flags after --, e.g. -- --num-envs 20")
    args = parser.parse_args()
    if not args.report_only:
        try:
            run_all(args)
        except KeyboardInterrupt:
            sys.exit(128 + signal.SIGINT)
    print(table(args))
    if args.per_seed:
        print()
        print(seed_table(args))


if __name__ == "__main__":
    main()
