"""First-order safe RL, written out: PPO-Lag, CPPO-PID or FOCOPS on a Safety-Gymnasium task.

A recipe in the style of TorchRL's sota-implementations: every piece ``sg-train`` composes is built
here in plain sight, so that you can change one of them. The Lagrangian algorithms differ only in
the loss and the multiplier (Safety-Gymnasium paper, section 5):

* PPO-Lag:  ``PPOLagLoss``  + ``LagrangeMultiplier``   (Ray et al. 2019)
* CPPO-PID: ``PPOLagLoss``  + ``PIDLagrangeMultiplier`` (Stooke et al. 2020)
* FOCOPS:   ``FOCOPSLoss``  + ``LagrangeMultiplier(upper_bound=2.0)`` (Zhang et al. 2020)

Each epoch: collect, update the multiplier from the finished episodes' mean cost, reward and cost
GAE with SafePO's batch normalisation, then minibatch Adam passes with a KL early stop.

    python examples/first_order.py --algo focops --env-id SafetyPointGoal1-v0 --total-steps 200000
"""

from __future__ import annotations

import argparse

import torch
from torchrl.envs import TransformedEnv

import sg_torchrl
from sg_torchrl.collectors import EpisodeStats, RolloutCollector
from sg_torchrl.envs.normalization import RunningObservationNorm
from sg_torchrl.objectives import (
    FOCOPSLoss,
    LagrangeMultiplier,
    PIDLagrangeMultiplier,
    PPOLagLoss,
    gaussian_kl,
    make_cost_gae,
    make_gae,
    normalize_advantages,
)
from sg_torchrl.modules import make_actor_critics


def parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", choices=["ppo_lag", "cppo_pid", "focops"], default="ppo_lag")
    parser.add_argument("--env-id", default="SafetyPointGoal1-v0")
    parser.add_argument("--total-steps", type=int, default=200_000)
    parser.add_argument("--steps-per-epoch", type=int, default=20_000)
    parser.add_argument("--num-envs", type=int, default=10)
    parser.add_argument("--update-iters", type=int, default=40)
    parser.add_argument("--cost-limit", type=float, default=25.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--compile", action="store_true", help="torch.compile the loss (about 2x faster on a CPU)")
    return parser.parse_args()


def main() -> None:
    args = parse()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)

    # Env: N simulators in one process, running observation normalisation (SafePO's default).
    base_env = sg_torchrl.make(args.env_id, num_envs=args.num_envs, seed=args.seed)
    obs_norm = RunningObservationNorm((base_env.observation_dim,))
    env = TransformedEnv(base_env, obs_norm)

    # Networks, multiplier and loss.
    actor, critic, cost_critic = make_actor_critics(base_env.observation_dim, base_env.action_spec, [64, 64])
    if args.algo == "cppo_pid":
        multiplier = PIDLagrangeMultiplier(cost_limit=args.cost_limit, kp=0.1, ki=0.01, kd=0.01)
    else:
        multiplier = LagrangeMultiplier(cost_limit=args.cost_limit, init=1e-3, lr=0.035,
                                        upper_bound=2.0 if args.algo == "focops" else None)
    loss_class = FOCOPSLoss if args.algo == "focops" else PPOLagLoss
    loss = loss_class(actor, critic, cost_critic, multiplier, functional=False)
    reward_gae = make_gae(critic, gamma=0.99, lmbda=0.95)
    cost_gae = make_cost_gae(cost_critic, gamma=0.99, lmbda=0.95)
    optimizer = torch.optim.Adam(loss.parameters(), lr=3e-4)  # actor and both critics
    # 64-sample steps are dispatch-bound on a CPU: a compiled loss fuses them into a few kernels.
    # Static shapes give one graph per minibatch size, reused every epoch.
    step_loss = torch.compile(loss, dynamic=False) if args.compile else loss

    collector = RolloutCollector(env, actor, steps=args.steps_per_epoch // args.num_envs)
    stats = EpisodeStats()
    for epoch in range(args.total_steps // args.steps_per_epoch):
        batch = collector.collect()
        stats.update(batch)
        finished = stats.pop_finished()
        if finished["cost"].numel():
            multiplier.update(finished["cost"].mean())  # before the policy update, as SafePO

        with torch.no_grad():
            reward_gae(batch)
            cost_gae(batch)
        data = batch.reshape(-1)
        normalize_advantages(data)  # reward advantage standardised, cost advantage mean-centred
        old_loc, old_scale = data["loc"].clone(), data["scale"].clone()

        inputs = data.select(*loss.in_keys)  # only what the loss reads, in one key order every epoch
        for passes in range(1, args.update_iters + 1):
            for minibatch in inputs[torch.randperm(inputs.numel())].split(64):
                out = step_loss(minibatch)
                total = out["loss_objective"] + out["loss_critic"] + out["loss_cost_critic"]
                optimizer.zero_grad()
                total.backward()
                torch.nn.utils.clip_grad_norm_(loss.parameters(), 40.0)
                optimizer.step()
            with torch.no_grad():
                current = actor.get_dist_params(data.select("observation"))
                kl = gaussian_kl(old_loc, old_scale, current["loc"], current["scale"]).mean().item()
            if kl > 0.02:  # SafePO's early stop
                break

        window = stats.window(50)
        print(f"epoch {epoch + 1}: EpRet {window.get('return', float('nan')):7.2f}  "
              f"EpCost {window.get('cost', float('nan')):6.2f}  lambda {multiplier.value.item():.3f}  "
              f"passes {passes}  KL {kl:.4f}", flush=True)
    env.close()


if __name__ == "__main__":
    main()
