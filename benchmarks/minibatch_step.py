"""Time of one first-order minibatch gradient step: hand-written PyTorch, today's trainer, the fused seed group.

On SafePO's networks (three [64, 64] tanh MLPs) and minibatches (64 samples) a gradient
step is per-op overhead, so S seeds stacked along a leading dimension and stepped together
(:mod:`sg_torchrl.train.fused`) should cost little more than one. This script times, in one run and
interleaved (every configuration runs one repeat in turn, so all see the same machine load):

* ``hand-written``: the floor. Three ``nn.Sequential`` MLPs, the Gaussian log-prob written out,
  PPO-Lag's clipped surrogate + both critics' MSE + L2, ``backward``, ``clip_grad_norm_``,
  ``torch.optim.Adam(fused=True)``; also with its loss ``torch.compile``\\ d;
* ``trainer``: what ``minibatch_passes`` does today: ``PPOLagLoss(functional=False)`` on the
  gathered TensorDict minibatch, the sum of its terms, ``zero_grad``, ``backward``,
  ``clip_grad_norm_``, fused Adam, three ``.item()`` (eager, and with the loss compiled as
  ``compile=True`` does);
* ``fused S=..``: :class:`~sg_torchrl.train.fused.FusedFirstOrderStep` for S seeds (gather,
  losses, backward, per-seed clip, masked Adam), eager and compiled (losses and the Adam update).

Every step includes gathering its minibatch. Reported per env shape: ms per step, ms per step per
seed, each as a ratio to the hand-written eager step of the same run (median over repeats after a
warm-up), and the aten ops one eager step dispatches. When ``torch.compile`` fails (say, no C++
compiler) the compiled rows say so and show the eager fallback's time.

    python benchmarks/minibatch_step.py                 # both env shapes, S = 1, 3, 8
    python benchmarks/minibatch_step.py --seeds 1 3 --repeats 5 --steps 100 --no-compile
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections.abc import Callable

import torch
from tensordict import TensorDict
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode
from torchrl.data import Bounded

from sg_torchrl.objectives import LagrangeMultiplier, PPOLagLoss
from sg_torchrl.objectives.surrogates import ClipSurrogate, SeedBatchedObjective
from sg_torchrl.train.fused import FusedFirstOrderStep, SeedBatch, SeedShuffler, multiplier_values
from sg_torchrl.modules import StackedActorCritic, make_actor_critics

SHAPES = {"SafetyHalfCheetahVelocity-v1": (17, 6), "SafetyPointGoal1-v0": (60, 2)}
HIDDEN = [64, 64]
SAMPLES = 2048  # per seed; minibatches cycle through shuffled passes of it
LR, CLIP, L2, MAX_NORM = 3e-4, 0.2, 1e-3, 40.0
Step = Callable[[], object]


def rollout(obs_dim: int, act_dim: int, seed: int) -> dict[str, torch.Tensor]:
    """A synthetic epoch batch of one seed (the losses' inputs; values do not matter for timing)."""
    gen = torch.Generator().manual_seed(seed)
    data = {"observation": torch.randn(SAMPLES, obs_dim, generator=gen),
            "action": torch.randn(SAMPLES, act_dim, generator=gen),
            "action_log_prob": -torch.rand(SAMPLES, generator=gen) * act_dim}
    for key in ("advantage", "cost_advantage", "value_target", "cost_value_target"):
        data[key] = torch.randn(SAMPLES, 1, generator=gen)
    return data


def orders(seed: int, minibatch: int):
    """Endless minibatch index blocks of shuffled passes."""
    gen = torch.Generator().manual_seed(seed)
    while True:
        order = torch.randperm(SAMPLES, generator=gen)
        for start in range(0, SAMPLES - minibatch + 1, minibatch):
            yield order[start : start + minibatch]


# ---------------------------------------------------------------------------- hand-written floor
def mlp(inputs: int, outputs: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inputs, 64), nn.Tanh(), nn.Linear(64, 64), nn.Tanh(), nn.Linear(64, outputs))


def hand_written(obs_dim: int, act_dim: int, minibatch: int, compile: bool) -> tuple[Step, str | None]:
    torch.manual_seed(0)
    actor, critic, cost_critic = mlp(obs_dim, act_dim), mlp(obs_dim, 1), mlp(obs_dim, 1)
    log_std = nn.Parameter(torch.zeros(act_dim))
    actor_params = [*actor.parameters(), log_std]
    critic_params = [*critic.parameters(), *cost_critic.parameters()]
    optimizer = torch.optim.Adam([{"params": actor_params, "lr": LR}, {"params": critic_params, "lr": LR}],
                                 fused=True)
    data, order, lam = rollout(obs_dim, act_dim, 0), orders(0, minibatch), torch.tensor(0.5)
    half_log_2pi = 0.5 * math.log(2 * math.pi)

    def loss(obs, action, old_log_prob, adv, cost_adv, target, cost_target):
        loc, scale = actor(obs), log_std.exp()
        log_prob = (-((action - loc) ** 2) / (2 * scale**2) - log_std - half_log_2pi).sum(-1, keepdim=True)
        ratio = (log_prob - old_log_prob.unsqueeze(-1)).exp()
        advantage = (adv - lam * cost_adv) / (1 + lam)
        surrogate = -torch.minimum(ratio * advantage, ratio.clamp(1 - CLIP, 1 + CLIP) * advantage).mean()
        critic_loss = ((critic(obs) - target) ** 2).mean() + L2 * sum(p.pow(2).sum() for p in critic.parameters())
        cost_loss = ((cost_critic(obs) - cost_target) ** 2).mean() + L2 * sum(
            p.pow(2).sum() for p in cost_critic.parameters())
        return surrogate + critic_loss + cost_loss

    keys = ("observation", "action", "action_log_prob", "advantage", "cost_advantage", "value_target",
            "cost_value_target")
    loss_fn = torch.compile(loss, dynamic=False) if compile else loss
    params = actor_params + critic_params
    error: list[str] = []

    def step():
        nonlocal loss_fn
        index = next(order)
        inputs = [data[key][index] for key in keys]
        try:
            total = loss_fn(*inputs)
        except Exception as exc:  # noqa: BLE001 -- report and time the eager loss instead
            error.append(f"{type(exc).__name__}: {exc}".splitlines()[0])
            loss_fn = loss
            total = loss_fn(*inputs)
        optimizer.zero_grad(set_to_none=True)
        total.backward()
        torch.nn.utils.clip_grad_norm_(params, MAX_NORM, foreach=True)
        optimizer.step()

    return step, (lambda: error[0] if error else None)


# ---------------------------------------------------------------------------- today's trainer
def trainer_step(obs_dim: int, act_dim: int, minibatch: int, compile: bool) -> tuple[Step, Callable]:
    torch.manual_seed(0)
    actor, critic, cost_critic = make_actor_critics(obs_dim, Bounded(-1.0, 1.0, shape=(act_dim,)), HIDDEN)
    multiplier = LagrangeMultiplier(cost_limit=25.0)
    loss = PPOLagLoss(actor, critic, cost_critic, multiplier, clip_epsilon=CLIP, critic_l2_coeff=L2, functional=False)
    critic_params = [*critic.parameters(), *cost_critic.parameters()]
    optimizer = torch.optim.Adam([{"params": list(actor.parameters()), "lr": LR}, {"params": critic_params, "lr": LR}],
                                 fused=True)
    params = [*actor.parameters(), *critic_params]
    data = TensorDict(rollout(obs_dim, act_dim, 0), batch_size=[SAMPLES]).select(*loss.in_keys)
    order = orders(0, minibatch)
    terms = ("loss_objective", "loss_critic", "loss_cost_critic")
    loss.in_keys, loss.out_keys  # noqa: B018 -- filled before compiling, as UpdateParts.loss_step does
    loss_fn = torch.compile(loss, dynamic=False) if compile else loss
    error: list[str] = []

    def step():
        nonlocal loss_fn
        mini = data[next(order)]
        try:
            out = loss_fn(mini)
        except Exception as exc:  # noqa: BLE001
            error.append(f"{type(exc).__name__}: {exc}".splitlines()[0])
            loss_fn = loss
            out = loss_fn(mini)
        total = sum(out[name] for name in terms)
        optimizer.zero_grad(set_to_none=True)
        total.backward()
        torch.nn.utils.clip_grad_norm_(params, MAX_NORM, foreach=True)
        optimizer.step()
        for name in terms:
            out[name].item()

    return step, (lambda: error[0] if error else None)


# ---------------------------------------------------------------------------- fused seed group
def fused_step(obs_dim: int, act_dim: int, minibatch: int, seeds: int, compile: bool) -> tuple[Step, Callable]:
    nets = []
    for seed in range(seeds):
        torch.manual_seed(seed)
        nets.append(make_actor_critics(obs_dim, Bounded(-1.0, 1.0, shape=(act_dim,)), HIDDEN))
    model = StackedActorCritic.from_single(nets)
    optimizer = FusedFirstOrderStep.make_optimizer(model, LR, LR, max_grad_norm=MAX_NORM, compile=compile)
    spec = SeedBatchedObjective(ClipSurrogate(CLIP), combine="sum_norm", critic_l2=L2)
    fused = FusedFirstOrderStep(model, optimizer, spec, compile=compile)
    rollouts = [rollout(obs_dim, act_dim, seed) for seed in range(seeds)]
    batch = SeedBatch.pack({key: torch.stack([r[key] for r in rollouts]) for key in spec.fields})
    lam = multiplier_values([LagrangeMultiplier(cost_limit=25.0, init=0.5) for _ in range(seeds)])
    shuffler = SeedShuffler(range(seeds))
    active = torch.ones(seeds, dtype=torch.bool)

    def blocks():
        while True:
            yield from shuffler.minibatches(SAMPLES - SAMPLES % minibatch, minibatch)

    order = blocks()

    def step():
        fused(batch.gather(next(order)), lam, active)

    def error():
        return fused.compilation.compile_error or optimizer.compilation.compile_error

    return step, error


# ---------------------------------------------------------------------------- measuring
class _CountOps(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.count += 1
        return func(*args, **(kwargs or {}))


def count_ops(step: Step) -> int:
    """Aten ops one step dispatches (forward, backward and optimiser)."""
    with _CountOps() as counter:
        step()
    return counter.count


def measure(configs: dict[str, Step], warmup: int, steps: int, repeats: int) -> dict[str, float]:
    """Median seconds per step of each configuration, repeats interleaved across configurations."""
    for name, step in configs.items():
        start = time.perf_counter()
        for _ in range(warmup):
            step()
        print(f"    warm-up {name}: {time.perf_counter() - start:.1f} s", flush=True)
    samples: dict[str, list[float]] = {name: [] for name in configs}
    for _ in range(repeats):
        for name, step in configs.items():
            start = time.perf_counter()
            for _ in range(steps):
                step()
            samples[name].append((time.perf_counter() - start) / steps)
    return {name: statistics.median(values) for name, values in samples.items()}


def run_shape(env_id: str, args: argparse.Namespace) -> list[dict]:
    obs_dim, act_dim = SHAPES[env_id]
    mb = args.minibatch
    rows: list[tuple[str, int, bool, Step, Callable]] = []
    modes = [False] if args.no_compile else [False, True]
    for compile in modes:
        rows.append(("hand-written", 1, compile, *hand_written(obs_dim, act_dim, mb, compile)))
    for compile in modes:
        rows.append(("trainer (PPOLagLoss)", 1, compile, *trainer_step(obs_dim, act_dim, mb, compile)))
    for seeds in args.seeds:
        for compile in modes:
            rows.append((f"fused S={seeds}", seeds, compile, *fused_step(obs_dim, act_dim, mb, seeds, compile)))
    configs = {f"{name} {'compiled' if compile else 'eager'}": step for name, _, compile, step, _ in rows}
    print(f"\n{env_id} (obs {obs_dim}, action {act_dim}, minibatch {mb})", flush=True)
    seconds = measure(configs, args.warmup, args.steps, args.repeats)
    floor = seconds["hand-written eager"]
    table = []
    for (name, seeds, compile, step, error), label in zip(rows, configs):
        ops = None if compile else count_ops(step)
        table.append({"env_id": env_id, "config": name, "seeds": seeds, "compiled": compile,
                      "ms_per_step": 1e3 * seconds[label], "ms_per_seed": 1e3 * seconds[label] / seeds,
                      "ratio": seconds[label] / floor, "ratio_per_seed": seconds[label] / seeds / floor,
                      "aten_ops": ops, "compile_error": error() if compile else None})
    print(f"\n{env_id}: ms per minibatch step (median of {args.repeats} x {args.steps} steps; one torch thread; "
          f"ratios to the hand-written eager step of this run)")
    print("| step | mode | ms / step | ms / step / seed | ratio | ratio per seed | aten ops |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for row in table:
        mode = "compiled" if row["compiled"] else "eager"
        if row["compile_error"]:
            mode = f"eager fallback (compile failed: {row['compile_error'][:80]})"
        print(f"| {row['config']} | {mode} | {row['ms_per_step']:.3f} | {row['ms_per_seed']:.3f} | {row['ratio']:.2f} "
              f"| {row['ratio_per_seed']:.2f} | {row['aten_ops'] if row['aten_ops'] is not None else '-'} |")
    return table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=list(SHAPES), choices=list(SHAPES))
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 3, 8], help="group sizes S of the fused step")
    parser.add_argument("--minibatch", type=int, default=64)
    parser.add_argument("--warmup", type=int, default=30, help="steps per configuration before timing")
    parser.add_argument("--steps", type=int, default=100, help="steps per timed repeat")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--no-compile", action="store_true", help="eager configurations only")
    parser.add_argument("--json", default=None, help="also write the rows here")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.distributions.Distribution.set_default_validate_args(False)  # as the trainer runs its updates
    rows = [row for env_id in args.envs for row in run_shape(env_id, args)]
    if args.json:
        from _report import write_json

        write_json(args.json, rows, threads=1)


if __name__ == "__main__":
    main()
