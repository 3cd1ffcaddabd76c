"""The seed group's fused minibatch step on a GPU beside the CPU: how many seeds one card steps at once.

The seed-group engine stacks S seeds' networks (SafePO's three [64, 64] tanh MLPs) along a leading
dimension and steps them together (:class:`~sg_torchrl.train.fused.FusedFirstOrderStep`: gather,
PPO-Lag's losses, backward, per-seed clip, masked Adam). On 2 CPU cores that pays off up to S of
about 8; a GPU runs each of those ops as one kernel whatever S is, so the time per step should stay
flat until the seeds fill the card. This script times, in one process:

* ``cuda``: the fused step at each ``--seeds`` (default 1, 8, 64, 256, 1024), eager, with
  ``torch.cuda.synchronize()`` around the timed loops;
* ``cpu``: the same step at ``--cpu-seeds`` (default 1, 8) with one torch thread: the baseline,
  measured on the same machine in the same run.

Reported: ms per step, ms per step per seed, and per-seed speed as a ratio to the CPU step with
S = 1. Minibatch 64 samples per seed, as the paper's PPO-Lag; the batch is synthetic (values do not
change the time). Without CUDA only the CPU rows run (``--allow-cpu``: for trying the script).

    python benchmarks/group_step_device.py
    python benchmarks/group_step_device.py --seeds 1 64 512 --cpu-seeds 1 --steps 50 --json step.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch
from torchrl.data import Bounded

from sg_torchrl.objectives import LagrangeMultiplier
from sg_torchrl.objectives.surrogates import ClipSurrogate, SeedBatchedObjective
from sg_torchrl.train.fused import FusedFirstOrderStep, SeedBatch, SeedShuffler, multiplier_values
from sg_torchrl.modules import StackedActorCritic, make_actor_critics

SHAPES = {"SafetyHalfCheetahVelocity-v1": (17, 6), "SafetyPointGoal1-v0": (60, 2)}
HIDDEN = [64, 64]
SAMPLES = 2048  # per seed; minibatches cycle through shuffled passes of it
LR, CLIP, L2, MAX_NORM = 3e-4, 0.2, 1e-3, 40.0


def build(obs_dim: int, act_dim: int, seeds: int, device: torch.device, minibatch: int):
    """A fused PPO-Lag step for ``seeds`` seeds with its parameters and batch on ``device``; returns ``step()``."""
    with torch.device(device):  # the stacked model allocates its flat buffers where its parameters are
        nets = []
        for seed in range(seeds):
            torch.manual_seed(seed)
            nets.append(make_actor_critics(obs_dim, Bounded(-1.0, 1.0, shape=(act_dim,), device=device), HIDDEN))
        model = StackedActorCritic.from_single(nets)
    optimizer = FusedFirstOrderStep.make_optimizer(model, LR, LR, max_grad_norm=MAX_NORM)
    spec = SeedBatchedObjective(ClipSurrogate(CLIP), combine="sum_norm", critic_l2=L2)
    fused = FusedFirstOrderStep(model, optimizer, spec)
    gen = torch.Generator().manual_seed(0)
    fields = {"observation": torch.randn(seeds, SAMPLES, obs_dim, generator=gen),
              "action": torch.randn(seeds, SAMPLES, act_dim, generator=gen),
              "action_log_prob": -torch.rand(seeds, SAMPLES, 1, generator=gen) * act_dim}
    for key in ("advantage", "cost_advantage", "value_target", "cost_value_target"):
        fields[key] = torch.randn(seeds, SAMPLES, 1, generator=gen)
    batch = SeedBatch.pack({key: fields[key].to(device) for key in spec.fields})
    lam = multiplier_values([LagrangeMultiplier(cost_limit=25.0, init=0.5) for _ in range(seeds)]).to(device)
    active = torch.ones(seeds, dtype=torch.bool, device=device)
    shuffler = SeedShuffler(range(seeds))

    def blocks():
        while True:
            yield from shuffler.minibatches(SAMPLES - SAMPLES % minibatch, minibatch)

    order = blocks()

    def step() -> None:
        fused(batch.gather(next(order).to(device, non_blocking=True)), lam, active)

    return step


def time_step(step, device: torch.device, warmup: int, steps: int, repeats: int) -> float:
    """Median seconds per step over ``repeats`` loops of ``steps`` after ``warmup`` steps."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    for _ in range(warmup):
        step()
    sync()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(steps):
            step()
        sync()
        samples.append((time.perf_counter() - start) / steps)
    return statistics.median(samples)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["SafetyHalfCheetahVelocity-v1"], choices=list(SHAPES))
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 8, 64, 256, 1024], help="S on the GPU")
    parser.add_argument("--cpu-seeds", nargs="+", type=int, default=[1, 8], help="S on the CPU (baseline)")
    parser.add_argument("--minibatch", type=int, default=64)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--allow-cpu", action="store_true", help="run the CPU rows alone when CUDA is missing")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    if not torch.cuda.is_available() and not args.allow_cpu:
        sys.exit("group_step_device.py: no CUDA device (pass --allow-cpu to run the CPU rows alone)")
    torch.set_num_threads(1)
    torch.distributions.Distribution.set_default_validate_args(False)
    plan = [("cpu", s) for s in args.cpu_seeds]
    if torch.cuda.is_available():
        plan += [("cuda", s) for s in args.seeds]
        print(f"GPU: {torch.cuda.get_device_name()}, torch {torch.__version__}", flush=True)
    rows = []
    for env_id in args.envs:
        obs_dim, act_dim = SHAPES[env_id]
        for kind, seeds in plan:
            device = torch.device(kind)
            seconds = time_step(build(obs_dim, act_dim, seeds, device, args.minibatch), device,
                                args.warmup, args.steps, args.repeats)
            rows.append({"env_id": env_id, "device": kind, "seeds": seeds, "ms_per_step": 1e3 * seconds,
                         "ms_per_seed": 1e3 * seconds / seeds})
            print(f"  {env_id} {kind} S={seeds}: {1e3 * seconds:.3f} ms/step, {1e3 * seconds / seeds:.4f} ms/seed",
                  flush=True)
    print("\n| env | device | S | ms / step | ms / step / seed | per-seed speed vs CPU S=1 |")
    print("|---|---|---:|---:|---:|---:|")
    for row in rows:
        base = next(r for r in rows if r["env_id"] == row["env_id"] and r["device"] == "cpu" and r["seeds"] == 1) \
            if any(r["device"] == "cpu" and r["seeds"] == 1 for r in rows) else None
        ratio = f"{base['ms_per_seed'] / row['ms_per_seed']:.1f}x" if base else "-"
        print(f"| {row['env_id']} | {row['device']} | {row['seeds']} | {row['ms_per_step']:.3f} "
              f"| {row['ms_per_seed']:.4f} | {ratio} |")
    if args.json:
        from _report import write_json

        write_json(args.json, rows, threads=1)


if __name__ == "__main__":
    main()
