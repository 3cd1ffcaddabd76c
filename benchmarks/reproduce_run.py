"""Does this tree still train a committed run to the same numbers? Re-run its first epochs and compare.

A committed benchmark run (``benchmarks/sweeps/...``, ``benchmarks/runs/...``)
holds its ``config.json`` and each seed's ``progress.csv``. Training is deterministic on one machine
kind (seeded simulators, seeded networks and streams; ``tests/test_golden_equivalence.py``), so a
tree that reproduces the first epochs of a run bit for bit trains the whole run to its committed
figures: a refactor that keeps them needs no new multi-hour run to keep the table.

This script reads the run's config, trains its first ``--epochs`` epochs with the same settings into
a temporary directory (the recorded budget, which sets the learning-rate schedule, stopped after those
epochs; no evaluation, wandb off: they change no training number) and compares every progress column but the timings (``Time/*``), per seed and
epoch, exactly.

    python benchmarks/reproduce_run.py benchmarks/sweeps/halfcheetah_10m/SafetyHalfCheetahVelocity-v1/ppo_lag/seeds-0-1-2 --epochs 2
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import tempfile
from pathlib import Path

import torch

from sg_torchrl.train import TrainConfig, trainer_class

#: Fields of the recorded config that say where and how a run was written, not what it computes.
_WHERE = ("output_dir", "run_name", "wandb", "progress", "overwrite", "resume", "eval_episodes")


def _rows(path: Path, epochs: int) -> list[dict[str, str]]:
    with open(path) as handle:
        return [row for row in csv.DictReader(handle) if row.get("Train/Epoch")][:epochs]


def _same(a: str, b: str) -> bool:
    if a == b:
        return True
    try:
        x, y = float(a), float(b)
    except ValueError:
        return False
    return (math.isnan(x) and math.isnan(y)) or x == y


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a committed run directory (a seed group's or a single seed's)")
    parser.add_argument("--epochs", type=int, default=2)
    args = parser.parse_args()
    recorded = json.loads((args.run / "config.json").read_text())
    seeds = recorded.get("seeds") or [recorded["seed"]]
    grouped = bool(recorded.get("seeds"))
    torch.set_num_threads(int(recorded.get("threads") or 1))
    with tempfile.TemporaryDirectory() as tmp:
        fields = {key: value for key, value in recorded.items() if key not in _WHERE and key in TrainConfig.__dataclass_fields__}
        cfg = TrainConfig(**fields, eval_episodes=0, wandb="disabled", progress=False, output_dir=tmp,
                          run_name="reproduced")
        trainer = trainer_class(cfg)(cfg)
        for _ in range(args.epochs):
            trainer.train_epoch()
        trainer.close() if hasattr(trainer, "close") else None
        out = Path(tmp) / "reproduced"
        differences = 0
        print(f"{args.run}: first {args.epochs} epochs of seeds {seeds} re-trained and compared (Time/* left out)")
        for seed in seeds:
            old_dir = args.run / f"seed-{seed:03d}" if grouped else args.run
            new_dir = out / f"seed-{seed:03d}" if grouped else out
            old, new = _rows(old_dir / "progress.csv", args.epochs), _rows(new_dir / "progress.csv", args.epochs)
            columns = [c for c in old[0] if not c.startswith("Time/")] if old else []
            bad = [(e + 1, c, a[c], b.get(c)) for e, (a, b) in enumerate(zip(old, new)) for c in columns
                   if not _same(a[c], b.get(c, "<missing>"))]
            differences += len(bad) + abs(len(old) - len(new))
            status = "identical" if not bad and len(old) == len(new) else f"{len(bad)} value(s) differ"
            print(f"  seed {seed}: {len(new)} epoch rows, {len(columns)} columns each: {status}")
            for epoch, column, a, b in bad[:5]:
                print(f"    epoch {epoch} {column}: committed {a}, now {b}")
    return 1 if differences else 0


if __name__ == "__main__":
    sys.exit(main())
