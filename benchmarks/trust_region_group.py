"""Time of one trust-region actor step: S single-seed steps against the stacked seed-group step.

The second-order algorithms (NPG, TRPO, CPO, PCPO) move the actor once per epoch on the whole batch
(SafePO: 20,000 samples on HalfCheetah): two gradients, about 2 x 16 Fisher-vector products (double
backward through the actor) for conjugate gradient, then a few line-search evaluations.
:mod:`sg_torchrl.objectives.stacked_trust_region` does this for S stacked seeds at once. This script
times, interleaved (one repeat of each configuration in turn, so both see the same machine load):

* ``single x S``: the single-seed step classes (``TRPOStep``, ``CPOStep``, ...) run on each seed's
  actor and batch in turn, what S single-seed runs spend;
* ``group``: the :class:`~sg_torchrl.objectives.stacked_trust_region.StackedTrustRegionStep` of the
  same algorithm on the stacked seeds.

The actors are reset to the same parameters before every repeat (not timed), so each repeat takes
the same number of line-search trials. Reported: median ms per step (over repeats after a warm-up)
and the ratio single / group (above 1: the group is faster), and the minor page faults per call.
With glibc's defaults the group step's 5-15 MB temporaries go back to the OS and are faulted in again
on every call (measured on a 2-core CPU at 20,000 samples per seed: 450,000-750,000 minor faults per
call, none for the single-seed steps); ``--keep-freed-memory`` applies
:func:`sg_torchrl.train.memory.keep_freed_memory`, as every ``sg-train`` seed group does.

    python benchmarks/trust_region_group.py                     # HalfCheetah shapes, S = 3, TRPO and CPO
    python benchmarks/trust_region_group.py --seeds 8 --algorithms npg pcpo --samples 5000
"""

from __future__ import annotations

import argparse
import copy
import resource
import statistics
import time

import torch
from tensordict import TensorDict
from torchrl.data import Bounded

from sg_torchrl.algorithms import manifest
from sg_torchrl.train.algorithms import TRUST_REGION_STEPS
from sg_torchrl.train.memory import keep_freed_memory
from sg_torchrl.modules import StackedActorCritic, make_actor_critics
from sg_torchrl.objectives.trust_region import STACKED_STEPS

#: The unconstrained second-order algorithms (NPG, TRPO, CPO, PCPO; the Lagrangian ones step the same classes)
#: and their trust-region step classes, from the algorithm manifest.
STEP_CLASSES = {entry.name: TRUST_REGION_STEPS[entry.update]
                for entry in manifest.rows(agents="single", family="second_order") if entry.multiplier == "none"}


def rollout(actor, obs_dim: int, samples: int, seed: int) -> TensorDict:
    """A synthetic epoch batch of one seed: the actor's own actions, advantages tied to them."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        data = actor(TensorDict(observation=torch.randn(samples, obs_dim, generator=gen), batch_size=[samples]))
    noise = (data["action"] - data["loc"]) / data["scale"]
    adv = noise[:, :1] + 0.3 * torch.randn(samples, 1, generator=gen)
    cost = noise[:, 1:2] + 0.3 * torch.randn(samples, 1, generator=gen)
    data["advantage"] = (adv - adv.mean()) / adv.std()
    data["cost_advantage"] = cost - cost.mean()
    return data.select("observation", "action", "action_log_prob", "advantage", "cost_advantage")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--obs", type=int, default=17)
    parser.add_argument("--act", type=int, default=6)
    parser.add_argument("--samples", type=int, default=20_000)
    parser.add_argument("--algorithms", nargs="+", default=["trpo", "cpo"], choices=sorted(STEP_CLASSES))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--keep-freed-memory", action="store_true",
                        help="glibc: neither trim the heap nor mmap large blocks (sg_torchrl.train.memory, which "
                             "sg-train applies to every seed group)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.keep_freed_memory:
        keep_freed_memory()
    device = torch.device(args.device)
    spec = Bounded(-1.0, 1.0, shape=(args.act,))
    nets = []
    for seed in range(args.seeds):
        torch.manual_seed(seed)
        nets.append(tuple(m.to(device) for m in make_actor_critics(args.obs, spec, [64, 64])))
    batches = [rollout(nets[s][0].cpu(), args.obs, args.samples, 100 + s).to(device) for s in range(args.seeds)]
    nets = [tuple(m.to(device) for m in triple) for triple in nets]
    stacked = {key: torch.stack([b[key] for b in batches]) for key in batches[0].keys()}
    violation = 0.05  # infeasible but recoverable for CPO / PCPO; unused by NPG / TRPO

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize()

    print(f"device {device}, threads {args.threads}, S = {args.seeds}, obs {args.obs}, act {args.act}, "
          f"[64, 64], {args.samples} samples per seed, {args.repeats} repeats after one warm-up")
    for name in args.algorithms:
        actors = [copy.deepcopy(triple[0]) for triple in nets]
        starts = [copy.deepcopy(a.state_dict()) for a in actors]
        singles = [STEP_CLASSES[name](actor) for actor in actors]
        model = StackedActorCritic.from_single(nets, device=device)
        start_flat = model.flat_actor.detach().clone()
        group = STACKED_STEPS[STEP_CLASSES[name]](model)
        violations = torch.full((args.seeds,), violation, dtype=torch.float64)

        def run_single() -> list[float]:
            for actor, state in zip(actors, starts):
                actor.load_state_dict(state)
            return [step.step(b, b["advantage"], b["cost_advantage"], violation)["Misc/AcceptanceStep"]
                    for step, b in zip(singles, batches)]

        def run_group() -> list[float]:
            with torch.no_grad():
                model.flat_actor.copy_(start_flat)
            metrics = group.step(stacked, stacked["advantage"], stacked["cost_advantage"], violations)
            return metrics["Misc/AcceptanceStep"].tolist()

        times, faults, trials = {"single": [], "group": []}, {"single": [], "group": []}, {}
        for repeat in range(args.repeats + 1):
            for key, run in (("single", run_single), ("group", run_group)):
                sync()
                faults0, t0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt, time.perf_counter()
                trials[key] = run()
                sync()
                if repeat:
                    times[key].append(time.perf_counter() - t0)
                    faults[key].append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0)
        ms = {key: 1e3 * statistics.median(values) for key, values in times.items()}
        print(f"{name:5s} single x {args.seeds}: {ms['single']:8.1f} ms   group: {ms['group']:8.1f} ms   "
              f"single / group {ms['single'] / ms['group']:4.2f}   page faults per call "
              f"{statistics.median(faults['single']):.0f} / {statistics.median(faults['group']):.0f}   "
              f"accepted trials {trials['single']} / {trials['group']}")

if __name__ == "__main__":
    main()
