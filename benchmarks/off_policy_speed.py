"""SAC-Lag's training speed on the seed-group engine, S = 1 and S = 3, against a plain-torch SAC-Lag step.

Three rows, measured in one process, one after another, single-threaded (``torch.set_num_threads(1)``):

* ``engine S=1`` and ``engine S=3``: ``sg-train --algo sac_lag`` trainers (OmniSafe's networks and batch:
  ReLU [256, 256] actor, twin reward and twin cost critics, minibatch 256, one gradient step per env step)
  on SafetyHalfCheetahVelocity-v1 from one simulator per seed. A first epoch of ``--steps`` random-action
  warm-up steps fills the buffers; the second, measured, epoch takes ``--steps`` env steps and as many
  gradient steps per seed. Reported: process CPU seconds per 1,000 env steps *per seed* (collection,
  replay, updates) and milliseconds of update per gradient step (``Time/Update`` over the gradient steps);
* ``plain torch``: the floor, a hand-written SAC-Lag gradient step with ``torch.nn`` modules and
  ``torch.optim.Adam`` (the same networks, minibatch, losses, clipping and Polyak update; minibatches drawn
  from a preallocated tensor, no env, no TensorDict): CPU seconds per 1,000 gradient steps.

    python benchmarks/off_policy_speed.py --steps 500
"""

from __future__ import annotations

import argparse
import tempfile
import time

import torch
from torch import nn

from _report import write_json
from sg_torchrl.train import trainer_class
from sg_torchrl.train.command_line import parse_args

OBS, ACT, HIDDEN, BATCH = 17, 6, 256, 256  # SafetyHalfCheetahVelocity-v1, OmniSafe's sizes


def engine_row(seeds: int, steps: int, output_dir: str) -> dict:
    argv = ["--algo", "sac_lag", "--seeds", *map(str, range(seeds)), "--steps-per-epoch", str(steps),
            "--total-steps", str(2 * steps), "--warmup-steps", str(steps), "--eval-episodes", "0",
            "--wandb", "disabled", "--progress", "false", "--output-dir", output_dir]
    cfg = parse_args(argv)
    trainer = trainer_class(cfg)(cfg)
    trainer.train_epoch()  # warm-up: random actions fill the buffers (no checkpoint: outside run())
    start = time.process_time()
    trainer.train_epoch()
    cpu = time.process_time() - start
    row = trainer.runs[0].last_row
    gradient_steps = row["Train/GradientSteps"]
    return {"row": f"engine S={seeds}", "seeds": seeds, "cpu_s_per_1k_steps_per_seed": cpu / steps * 1000 / seeds,
            "update_ms_per_gradient_step": row["Time/Update"] / gradient_steps * 1000,
            "update_ms_per_gradient_step_per_seed": row["Time/Update"] / gradient_steps * 1000 / seeds}


def _mlp(inputs: int, outputs: int) -> nn.Module:
    return nn.Sequential(nn.Linear(inputs, HIDDEN), nn.ReLU(), nn.Linear(HIDDEN, HIDDEN), nn.ReLU(),
                         nn.Linear(HIDDEN, outputs))


def plain_row(steps: int) -> dict:
    """The floor: SAC-Lag's gradient step in plain torch."""
    torch.manual_seed(0)
    actor = _mlp(OBS, 2 * ACT)
    critics, costs = nn.ModuleList([_mlp(OBS + ACT, 1) for _ in range(2)]), nn.ModuleList(
        [_mlp(OBS + ACT, 1) for _ in range(2)])
    targets = [nn.ModuleList([_mlp(OBS + ACT, 1) for _ in range(2)]) for _ in range(2)]
    for target, source in zip(targets, (critics, costs)):
        target.load_state_dict(source.state_dict())
    optimizers = [torch.optim.Adam(m.parameters(), lr=3e-4) for m in (actor, critics, costs)]
    data = torch.randn(100_000, 2 * OBS + ACT + 3)
    alpha, gamma, lam = 0.2, 0.99, 0.5

    def sample(obs):
        loc, raw = actor(obs).chunk(2, -1)
        scale = nn.functional.softplus(raw) + 1e-4
        pre = loc + scale * torch.randn_like(loc)
        log_prob = torch.distributions.Normal(loc, scale).log_prob(pre).sum(-1)
        log_prob = log_prob - (2 * (0.6931471805599453 - pre - nn.functional.softplus(-2 * pre))).sum(-1)
        return torch.tanh(pre), log_prob

    def q(nets, obs, action):
        x = torch.cat([obs, action], -1)
        return torch.stack([net(x).squeeze(-1) for net in nets])

    start = time.process_time()
    for step in range(1, steps + 1):
        batch = data[torch.randint(0, data.shape[0], (BATCH,))]
        obs, action, reward, cost, done, next_obs = batch.split([OBS, ACT, 1, 1, 1, OBS], -1)
        reward, cost, done = reward.squeeze(-1), cost.squeeze(-1), (done.squeeze(-1) > 1)
        with torch.no_grad():
            next_action, next_log_prob = sample(next_obs)
            target = reward + gamma * (~done) * (q(targets[0], next_obs, next_action).min(0).values
                                                 - alpha * next_log_prob)
            cost_target = cost + gamma * (~done) * q(targets[1], next_obs, next_action).max(0).values
        losses = [((q(critics, obs, action) - target) ** 2).mean(1).sum(),
                  ((q(costs, obs, action) - cost_target) ** 2).mean(1).sum()]
        for optimizer in optimizers[1:]:
            optimizer.zero_grad()
        sum(losses).backward()
        for module, optimizer in zip((critics, costs), optimizers[1:]):
            torch.nn.utils.clip_grad_norm_(module.parameters(), 40.0)
            optimizer.step()
        if step % 2 == 0:  # OmniSafe's order: the actor after the critics' step (its gradient reaches them, unused)
            pi, log_prob = sample(obs)
            value = q(critics, obs, pi).min(0).values
            penalty = q(costs, obs, pi).max(0).values
            optimizers[0].zero_grad()
            ((alpha * log_prob - value + lam * penalty) / (1 + lam)).mean().backward()
            torch.nn.utils.clip_grad_norm_(actor.parameters(), 40.0)
            optimizers[0].step()
            with torch.no_grad():
                for target, source in zip(targets, (critics, costs)):
                    for t, s in zip(target.parameters(), source.parameters()):
                        t.lerp_(s, 0.005)
    cpu = time.process_time() - start
    return {"row": "plain torch", "seeds": 1, "cpu_s_per_1k_gradient_steps": cpu / steps * 1000}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=500, help="env steps of the measured epoch (and of the warm-up)")
    parser.add_argument("--json", help="write the rows here")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = [plain_row(args.steps)]
    with tempfile.TemporaryDirectory() as out:
        rows += [engine_row(seeds, args.steps, f"{out}/s{seeds}") for seeds in (1, 3)]
    floor = rows[0]["cpu_s_per_1k_gradient_steps"]
    print(f"SAC-Lag on SafetyHalfCheetahVelocity-v1, {args.steps} measured env steps per seed, 1 thread")
    print("| run | CPU s per 1k env steps per seed | update ms per gradient step, wall (per seed) | x floor (CPU) |")
    print("|---|---:|---:|---:|")
    print(f"| plain-torch SAC-Lag step (floor, no env) | {floor:.2f} (per 1k gradient steps) | — | 1.00 |")
    for row in rows[1:]:
        print(f"| engine S={row['seeds']} | {row['cpu_s_per_1k_steps_per_seed']:.2f} | "
              f"{row['update_ms_per_gradient_step']:.2f} ({row['update_ms_per_gradient_step_per_seed']:.2f}) | "
              f"{row['cpu_s_per_1k_steps_per_seed'] / floor:.2f} |")
    if args.json:
        write_json(args.json, rows, threads=1)


if __name__ == "__main__":
    main()
