"""Training cost per seed of this tree against an earlier revision, measured in the same run.

A refactor of the algorithm layer must not make training slower. This script exports ``--base`` (a
git revision) into a temporary directory with ``git archive`` and trains the same configurations on
both source trees, alternating, each row in a fresh Python process whose ``PYTHONPATH`` names the
tree (so each process imports only that tree's ``sg_torchrl``). A row builds its trainer the way
``sg-train`` does (``TrainConfig`` and ``trainer_class``, public in both trees), trains ``--epochs``
epochs with one torch thread and reports the CPU seconds (``time.process_time``) of each epoch.

Reported per configuration: CPU seconds per 1,000 env steps per seed over the epochs after the first
(steady state: no compiling, warm caches), for the base and for this tree (the best of
``--repeats``; ``refused`` where a tree's config refuses the row), and their ratio (this tree / base: <= 1
is no slower). A row of mode ``single`` trains one
seed as ``sg-train --seed 0`` does (``TrainConfig(seed=0)``: whatever single-seed trainer the tree has);
with such a row, every row of the same algorithm also gets the base's single-seed figure over this tree's
(the speed-up per seed against one run of the base).

    python benchmarks/revision_speed.py --base bccbadc                     # PPO-Lag S = 1, 3, 8 eager and compiled, CPO S = 3
    python benchmarks/revision_speed.py --base HEAD~3 --rows ppo_lag:1:eager --steps-per-epoch 4000 --epochs 2
    python benchmarks/revision_speed.py --base bccbadc --env-id Safety2x3HalfCheetahVelocity-v0 --steps-per-epoch 10000 \
        --epochs 3 --rows mappo_lag:1:single mappo_lag:1:eager mappo_lag:8:eager   # multi-agent, the paper's epochs
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: algo:S:mode rows measured by default (mode: eager or compiled; single: one seed as ``sg-train --seed 0``).
DEFAULT_ROWS = ("ppo_lag:1:eager", "ppo_lag:3:eager", "ppo_lag:8:eager", "ppo_lag:1:compiled", "ppo_lag:3:compiled",
                "ppo_lag:8:compiled", "cpo:3:eager")

# The row, run in a child process against one tree: only names both trees have (TrainConfig, trainer_class).
_CHILD = """
import json, sys, tempfile, time
import torch
torch.set_num_threads(1)
from sg_torchrl.train import TrainConfig, trainer_class
algo, seeds, mode, env_id, steps, num_envs, epochs = json.loads(sys.argv[1])
with tempfile.TemporaryDirectory() as tmp:
    runs = dict(seed=0) if mode == "single" else dict(seeds=list(range(seeds)))
    cfg = TrainConfig(algo=algo, env_id=env_id, **runs, total_steps=epochs * steps,
                      steps_per_epoch=steps, num_envs=num_envs, wandb="disabled", eval_episodes=0, progress=False,
                      output_dir=tmp, compile=mode == "compiled")
    trainer = trainer_class(cfg)(cfg)
    cpu = []
    for _ in range(epochs):
        start = time.process_time()
        trainer.train_epoch()
        cpu.append(time.process_time() - start)
print(json.dumps(cpu))
"""


@dataclass(frozen=True)
class RowSpec:
    algo: str
    seeds: int
    mode: str

    @classmethod
    def parse(cls, text: str) -> RowSpec:
        algo, seeds, mode = text.split(":")
        if mode not in ("eager", "compiled", "single"):
            raise ValueError(f"row {text!r}: mode must be eager, compiled or single")
        if mode == "single" and int(seeds) != 1:
            raise ValueError(f"row {text!r}: a single-seed run has S = 1")
        return cls(algo, int(seeds), mode)

    def __str__(self) -> str:
        return f"{self.algo} single seed (--seed 0)" if self.mode == "single" else f"{self.algo} S={self.seeds} {self.mode}"


def export(revision: str, into: Path) -> Path:
    """The package of ``revision`` (``git archive``), unpacked under ``into``; returns the tree's root."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision, "sg_torchrl"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


def measure(tree: Path, row: RowSpec, env_id: str, steps: int, num_envs: int, epochs: int) -> list[float] | None:
    """CPU seconds of each epoch of ``row`` trained by the ``sg_torchrl`` of ``tree``; ``None`` when that tree's
    config refuses the row (an option it does not have for the algorithm, e.g. an older tree's ``compile``)."""
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1")
    args = json.dumps([row.algo, row.seeds, row.mode, env_id, steps, num_envs, epochs])
    result = subprocess.run([sys.executable, "-c", _CHILD, args], env=env, cwd=tree, capture_output=True, text=True)
    if result.returncode != 0 and "ValueError: config:" in result.stderr:
        return None
    if result.returncode != 0:
        raise RuntimeError(f"{row} on {tree} failed:\n{result.stderr[-3000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def per_seed_k(cpu: list[float], seeds: int, steps: int) -> float:
    """CPU seconds per 1,000 env steps per seed over the epochs after the first."""
    steady = cpu[1:] or cpu
    return sum(steady) / (len(steady) * seeds * steps / 1000)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--base", required=True, help="the git revision to compare with (e.g. a commit hash)")
    parser.add_argument("--rows", nargs="+", default=list(DEFAULT_ROWS), help="algo:S:eager|compiled|single")
    parser.add_argument("--env-id", default="SafetyHalfCheetahVelocity-v1")
    parser.add_argument("--steps-per-epoch", type=int, default=20_000, help="per seed (the paper's 20,000)")
    parser.add_argument("--num-envs", type=int, default=10, help="simulators per seed (the paper's 10)")
    parser.add_argument("--epochs", type=int, default=2, help="epochs per row; the first is not reported")
    parser.add_argument("--repeats", type=int, default=1, help="rows per tree and configuration (best kept)")
    args = parser.parse_args()
    rows = [RowSpec.parse(text) for text in args.rows]
    with tempfile.TemporaryDirectory() as tmp:
        base = export(args.base, Path(tmp))
        trees = {"base": base, "this tree": ROOT}
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True).stdout.strip()
        print(f"base {args.base} against this tree (HEAD {head}, with its uncommitted changes); {args.env_id}, "
              f"{args.steps_per_epoch} steps per epoch per seed from {args.num_envs} simulators, {args.epochs} "
              f"epochs, best of {args.repeats}; CPU s per 1k env steps per seed after the first epoch")
        single = {}  # algo -> the base's single-seed figure, once measured
        print("| row | base | this tree | this tree / base | base single seed / this tree |\n|---|---:|---:|---:|---:|")
        for row in rows:
            best = {name: float("inf") for name in trees}
            for repeat in range(args.repeats):
                order = list(trees.items()) if repeat % 2 == 0 else list(reversed(trees.items()))
                for name, tree in order:
                    cpu = measure(tree, row, args.env_id, args.steps_per_epoch, args.num_envs, args.epochs)
                    if cpu is not None:
                        best[name] = min(best[name], per_seed_k(cpu, row.seeds, args.steps_per_epoch))
            if row.mode == "single":
                single[row.algo] = best["base"]
            measured = row.algo in single and best["this tree"] < float("inf")
            speedup = f"{single[row.algo] / best['this tree']:.2f}x" if measured else ""
            cells = [f"{best[name]:.3f}" if best[name] < float("inf") else "refused" for name in trees]
            ratio = f"{best['this tree'] / best['base']:.3f}" if max(best.values()) < float("inf") else ""
            print(f"| {row} | {' | '.join(cells)} | {ratio} | {speedup} |", flush=True)


if __name__ == "__main__":
    main()
