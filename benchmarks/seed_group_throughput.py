"""CPU cost of training per seed: seed groups of S = 1, 3, 8 against S = 1 of the group.

A seed group (``sg-train --seeds``, :mod:`sg_torchrl.train.seed_group`) steps S seeds' simulators in
one batched env and their networks as one stacked model, so what one seed costs should fall with S.
This script trains each algorithm of ``--algos`` (default PPO-Lag and CPO) at the paper's settings
(20,000 steps per epoch from 10 simulators per seed; the algorithm's own update settings: PPO-Lag 40
passes of minibatch 64 with KL early stop 0.02, CPO one trust-region step then 10 critic passes of
minibatch 128) for ``--epochs`` epochs per configuration, in one run and one after the other:

* ``group S=k``: a seed group of seeds 0..k-1, eager, and with ``--compile true`` (the fused minibatch
  losses and the masked Adam through ``torch.compile``; its first epoch includes the compiling). For
  a second-order algorithm only the critics' passes compile: the stacked trust-region step
  (:mod:`sg_torchrl.objectives.stacked_trust_region`: conjugate gradient, double backward, line search)
  runs eagerly either way, and the table says so.

The baseline of the ratios is the eager ``group S=1`` row: one seed on the seed-group engine, which is
what every single-agent run trains on (``sg-train --seed s`` is that row's code in the single-seed
layout), so the ratios say what stacking more seeds saves per seed. (Earlier versions measured against
the retired single-seed ``LossModule`` trainer; ``benchmarks/RESULTS.md`` keeps those figures.)

Reported per env: CPU seconds (``time.process_time``, every thread of the process) per 1,000 env
steps *per seed*, over all epochs and over the epochs after the first (steady state: no compiling,
warm caches), the ratio of the baseline's steady figure to each configuration's (> 1: cheaper per
seed than one seed alone), the share of wall time spent collecting, and the passes the KL
stop allowed (the mean over seeds: configurations that stop at different passes do different work;
second order: the critic passes, always all of them). Every configuration runs with one torch
thread, as ``sg-train`` does, and with glibc told to keep freed memory
(:func:`~sg_torchrl.train.memory.keep_freed_memory`, which every seed group applies at start-up), so
every row runs under the same allocator settings. Each row runs in a
fresh (spawned) process, which also gives its peak resident memory (``ru_maxrss``: interpreter, torch
and MuJoCo included), reported whole and per seed.

    python benchmarks/seed_group_throughput.py                      # the paper's settings (minutes per row)
    python benchmarks/seed_group_throughput.py --epochs 3 --seeds 1 3 --algos cpo
    python benchmarks/seed_group_throughput.py --quick              # a smoke test: small epochs, S = 1, 3
    python benchmarks/seed_group_throughput.py --multi-agent        # MAPPO-Lag on Safety2x3HalfCheetahVelocity-v0

Multi-agent rows (``--multi-agent``) compare the single-seed run (``sg-train --seed 0``:
:class:`~sg_torchrl.train.multi_agent_group.MultiAgentGroupTrainer` with S = 1 in a single run's
layout, so the ``group S=1`` row is the same code writing the group layout) with
multi-agent seed groups (:class:`~sg_torchrl.train.multi_agent_group.MultiAgentGroupTrainer`: simulators
batched over the seeds, the seeds' networks stacked and acting in one call per step, each seed's round run
after the others'), eager, at the paper's multi-agent settings. ``benchmarks/revision_speed.py`` measures
them against an earlier revision's single-seed trainer.
"""

from __future__ import annotations

import argparse
import multiprocessing
import resource
import tempfile
import time
from dataclasses import dataclass

import torch

from sg_torchrl.train import TrainConfig, trainer_class
from sg_torchrl.train.fused import FusedFirstOrderStep
from sg_torchrl.train.memory import keep_freed_memory

ENVS = ("SafetyHalfCheetahVelocity-v1", "SafetyPointGoal1-v0")
ALGOS = ("ppo_lag", "cpo")
#: Multi-agent rows (``--multi-agent``): MAPPO-Lag on the two-agent HalfCheetah partition.
MULTI_AGENT = (("mappo_lag", "Safety2x3HalfCheetahVelocity-v0"),)
# The update settings (passes, minibatch, KL stop) are each algorithm's paper defaults; --quick cuts the passes.
PAPER = dict(steps_per_epoch=20_000, num_envs=10)
QUICK = dict(steps_per_epoch=1_000, num_envs=4, update_iters=4)
# Multi-agent: the paper's multi-agent settings are TrainConfig's defaults for those algorithms.
MULTI_AGENT_PAPER: dict = {}
MULTI_AGENT_QUICK = dict(steps_per_epoch=1_000, num_envs=4, update_iters=2)


@dataclass
class Row:
    label: str
    seeds: int
    steps_per_epoch: int  # env steps per epoch per seed
    cpu: list[float]  # CPU seconds per epoch
    rollout: float  # wall seconds collecting, all epochs
    wall: float  # wall seconds, all epochs
    passes: float  # mean passes per epoch (mean over seeds)
    compile_error: str | None = None
    peak_mib: float = float("nan")  # the row's process: peak resident memory (ru_maxrss)

    def per_seed_k(self, epochs: list[float]) -> float:
        """CPU seconds per 1,000 env steps per seed over ``epochs``."""
        return sum(epochs) / (len(epochs) * self.seeds * self.steps_per_epoch / 1000)


def measure_in_child(*args) -> Row:
    """:func:`measure` in a fresh process (spawned), so that each row's peak memory is its own and it
    compiles, allocates and warms up as a fresh ``sg-train`` process does."""
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        return pool.apply(measure, args)


def measure(algo: str, env_id: str, seeds: int | None, compile: bool, settings: dict, epochs: int) -> Row:
    """Train ``epochs`` epochs of ``algo``: its single-seed trainer (``seeds`` None: multi-agent) or a group of ``seeds``.

    Compiled graphs of earlier rows are dropped first (``torch._dynamo.reset``), so each row compiles as
    a fresh ``sg-train`` process does: dynamo keys its cache on the loss function's code, and the rows'
    different shapes together would pass its recompile limit, after which it silently runs eagerly.
    """
    torch.set_num_threads(1)
    keep_freed_memory()  # what a group does at start-up: for every row alike
    torch._dynamo.reset()
    with tempfile.TemporaryDirectory() as tmp:
        steps = settings.get("steps_per_epoch", TrainConfig(algo=algo, env_id=env_id).steps_per_epoch)
        common = dict(algo=algo, env_id=env_id, total_steps=epochs * steps, wandb="disabled", eval_episodes=0,
                      progress=False, output_dir=tmp, compile=compile, **settings)
        if seeds is None:  # the multi-agent baseline: sg-train --seed 0's trainer (the engine with S = 1)
            cfg = TrainConfig(seed=0, **common)
            trainer, count = trainer_class(cfg)(cfg), 1
            label = f"{type(trainer).__name__} (single seed)" + (" compiled" if compile else "")
        else:
            cfg = TrainConfig(seeds=list(range(seeds)), **common)
            trainer = trainer_class(cfg)(cfg)
            label, count = f"group S={seeds}", seeds
            if compile:
                label += " compiled" + (" (critic passes only; the trust-region step is eager)"
                                        if trainer.cfg.second_order else "")
        cpu, rows = [], []
        for _ in range(epochs):
            start = time.process_time()
            rows.append(trainer.train_epoch())
            cpu.append(time.process_time() - start)
        error = None
        if seeds is not None and compile and hasattr(trainer, "group_update"):  # fused steps, then the optimiser
            steps = [part for part in vars(trainer.group_update).values() if isinstance(part, FusedFirstOrderStep)]
            errors = [step.compilation.compile_error for step in steps if step.compilation.compile_error]
            error = (errors or [trainer.optimizer.compilation.compile_error])[0]
    return Row(label, count, steps, cpu, sum(r["Time/Rollout"] for r in rows),
               sum(r["Time/Rollout"] + r["Time/Update"] for r in rows),
               sum(r.get("Train/StopIter", float("nan")) for r in rows) / epochs, error,
               resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


def describe(algo: str, env_id: str, settings: dict) -> str:
    """The update settings ``algo`` runs with (its defaults, as ``TrainConfig`` fills them in)."""
    cfg = TrainConfig(algo=algo, env_id=env_id, **settings)
    if cfg.multi_agent:
        return (f"{cfg.steps_per_epoch} steps per epoch from {cfg.num_envs} simulators per seed; per agent "
                f"{cfg.update_iters} epochs, KL stop {cfg.target_kl}")
    if cfg.second_order:
        return (f"one trust-region step (KL {cfg.target_kl}), then {cfg.update_iters} critic passes of minibatch "
                f"{cfg.minibatch_size}")
    return f"{cfg.update_iters} passes of minibatch {cfg.minibatch_size}, KL stop {cfg.target_kl}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=list(ENVS))
    parser.add_argument("--algos", nargs="+", default=list(ALGOS), help="algorithms (default: ppo_lag cpo)")
    parser.add_argument("--seeds", nargs="+", type=int, default=None, help="group sizes S (default 1 3 8; quick 1 3)")
    parser.add_argument("--epochs", type=int, default=2, help="epochs per configuration (the first is reported apart)")
    parser.add_argument("--no-compile", action="store_true", help="skip the compiled groups")
    parser.add_argument("--multi-agent", action="store_true",
                        help="the multi-agent rows instead (MAPPO-Lag on Safety2x3HalfCheetahVelocity-v0, eager: "
                             "multi-agent runs do not compile)")
    parser.add_argument("--quick", action="store_true",
                        help=f"smoke test: {QUICK['steps_per_epoch']}-step epochs from {QUICK['num_envs']} simulators "
                             f"per seed, {QUICK['update_iters']} (critic) passes, S = 1, 3")
    args = parser.parse_args()
    kept = keep_freed_memory()  # each row's process does the same
    pairs = list(MULTI_AGENT) if args.multi_agent else [(algo, env_id) for algo in args.algos for env_id in args.envs]
    if args.multi_agent:
        settings = MULTI_AGENT_QUICK if args.quick else MULTI_AGENT_PAPER
    else:
        settings = QUICK if args.quick else PAPER
    sizes = args.seeds or ([1, 3] if args.quick else [1, 3, 8])
    if not args.multi_agent:  # S = 1 of the group first: the baseline of the ratios
        sizes = [1, *(size for size in sizes if size != 1)]
    steady = slice(1, None) if args.epochs > 1 else slice(None)
    print(f"{args.epochs} epoch(s) per row; CPU s = time.process_time(); glibc keeps freed memory: {kept}\n")
    for algo, env_id in pairs:
        runs = []
        for compile in ([False] if args.no_compile or args.multi_agent else [False, True]):
            if args.multi_agent:
                runs.append(measure_in_child(algo, env_id, None, compile, settings, args.epochs))
            runs += [measure_in_child(algo, env_id, size, compile, settings, args.epochs) for size in sizes]
        base = runs[0].per_seed_k(runs[0].cpu[steady])
        print(f"### {algo} on {env_id}: {describe(algo, env_id, settings)}\n")
        print(f"| configuration | CPU s / 1k steps / seed, all epochs | after the first epoch | speed-up vs {runs[0].label} "
              "| collection share of wall | passes per epoch | peak MiB | peak MiB / seed |")
        print("|---|---|---|---|---|---|---|---|")
        for row in runs:
            after = row.per_seed_k(row.cpu[steady])
            note = f" (compile failed, eager: {row.compile_error})" if row.compile_error else ""
            print(f"| {row.label}{note} | {row.per_seed_k(row.cpu):.3f} | {after:.3f} | {base / after:.2f}x "
                  f"| {row.rollout / row.wall:.0%} | {row.passes:.1f} | {row.peak_mib:.0f} | "
                  f"{row.peak_mib / row.seeds:.0f} |")
        print()


if __name__ == "__main__":
    main()
