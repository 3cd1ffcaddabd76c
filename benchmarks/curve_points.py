"""Read learning curves at given step counts: two runs of one task side by side, from their logs alone.

For each seed-group run directory (``sg-train --seeds`` / ``sg-sweep`` output: ``seed-XXX/progress.csv``) and
each step count, the mean over seeds of the episode return and cost averaged over the ``--window`` epochs that
end at that step count. A run that has not reached a step count shows ``-``. This is how a side run (a
non-default setting, ``benchmarks/ablations/``) is compared with its default cell at equal budgets.

    python benchmarks/curve_points.py \\
        benchmarks/sweeps/halfcheetah_10m/SafetyHalfCheetahVelocity-v1/pcpo/seeds-0-1-2 \\
        benchmarks/ablations/pcpo_hx_direction/SafetyHalfCheetahVelocity-v1/pcpo/seeds-0-1-2 \\
        --labels "H^-1 g (default)" "H x (SafePO)" --steps 0.5e6 1e6 2e6 3e6 10e6
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from sg_torchrl.sweep.records import finite_mean, read_progress

RETURN, COST, STEPS = "Metrics/EpRet", "Metrics/EpCost", "Train/TotalSteps"


def seed_curves(run_dir: Path) -> list[list[dict[str, float]]]:
    """Each seed's training rows (those with a step count), in seed order."""
    seeds = sorted(run_dir.glob("seed-*/progress.csv"))
    if not seeds:
        raise SystemExit(f"{run_dir}: no seed-XXX/progress.csv (give a seed-group run directory)")
    return [[row for row in read_progress(path) if math.isfinite(row.get(STEPS, math.nan))] for path in seeds]


def point(curves: list[list[dict[str, float]]], steps: float, window: int) -> tuple[float, float] | None:
    """Mean over seeds of (return, cost) over the ``window`` epochs ending at ``steps``; ``None`` if not reached."""
    means = []
    for rows in curves:
        reached = [row for row in rows if row[STEPS] <= steps]
        if not reached or reached[-1][STEPS] < steps:
            return None
        last = reached[-window:]
        means.append(tuple(finite_mean([row[key] for row in last]) for key in (RETURN, COST)))
    return tuple(sum(values) / len(values) for values in zip(*means))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="seed-group run directories")
    parser.add_argument("--labels", nargs="+", help="a column title per run (default: the directory)")
    parser.add_argument("--steps", nargs="+", type=float, required=True, help="env steps per seed to read at")
    parser.add_argument("--window", type=int, default=10, help="epochs averaged at each point")
    args = parser.parse_args()
    labels = args.labels or [str(run) for run in args.runs]
    if len(labels) != len(args.runs):
        parser.error(f"--labels: {len(labels)} given for {len(args.runs)} runs")
    curves = [seed_curves(run) for run in args.runs]
    print("| env steps per seed | " + " | ".join(f"{label} J^R / J^C" for label in labels) + " |")
    print("|---|" + "---:|" * len(labels))
    for steps in args.steps:
        cells = [point(run, steps, args.window) for run in curves]
        text = ["-" if cell is None else f"{cell[0]:.0f} / {cell[1]:.1f}" for cell in cells]
        print(f"| {steps / 1e6:g}M | " + " | ".join(text) + " |")


if __name__ == "__main__":
    main()
