"""Second-order safe RL, written out: TRPO-Lag, CPO or PCPO on a Safety-Gymnasium task.

A recipe in the style of TorchRL's sota-implementations. The actor moves once per epoch by a
trust-region step on the whole batch (:mod:`sg_torchrl.objectives.trust_region`: Fisher-vector
products of the mean KL, conjugate gradient, then the algorithm's own step and line search); the
critics then take minibatch Adam passes (Safety-Gymnasium paper appendix: delta 0.01, 15 CG
iterations, critics at 1e-3 for 10 passes of 128).

* TRPO-Lag: ``TRPOStep`` on ``LagrangeMultiplier.combine(A_r, A_c)`` (Ray et al. 2019)
* CPO:      ``CPOStep`` on ``A_r`` with the constraint ``J_c - d`` (Achiam et al. 2017)
* PCPO:     ``PCPOStep``, projection onto the linearised constraint (Yang et al. 2020)

    python examples/second_order.py --algo cpo --env-id SafetyPointGoal1-v0 --total-steps 200000
"""

from __future__ import annotations

import argparse

import torch
from torchrl.envs import TransformedEnv

import sg_torchrl
from sg_torchrl.collectors import EpisodeStats, RolloutCollector
from sg_torchrl.envs.normalization import RunningObservationNorm
from sg_torchrl.objectives import (
    CPOStep,
    LagrangeMultiplier,
    NoMultiplier,
    PCPOStep,
    PPOLagLoss,
    TRPOStep,
    make_cost_gae,
    make_gae,
    normalize_advantages,
)
from sg_torchrl.modules import make_actor_critics

STEPS = {"trpo_lag": TRPOStep, "cpo": CPOStep, "pcpo": PCPOStep}


def parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", choices=sorted(STEPS), default="cpo")
    parser.add_argument("--env-id", default="SafetyPointGoal1-v0")
    parser.add_argument("--total-steps", type=int, default=200_000)
    parser.add_argument("--steps-per-epoch", type=int, default=20_000)
    parser.add_argument("--num-envs", type=int, default=10)
    parser.add_argument("--critic-iters", type=int, default=10)
    parser.add_argument("--cost-limit", type=float, default=25.0)
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args()


def main() -> None:
    args = parse()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)

    base_env = sg_torchrl.make(args.env_id, num_envs=args.num_envs, seed=args.seed)
    obs_norm = RunningObservationNorm((base_env.observation_dim,))
    env = TransformedEnv(base_env, obs_norm)

    actor, critic, cost_critic = make_actor_critics(base_env.observation_dim, base_env.action_spec, [64, 64])
    # TRPO-Lag folds the cost into the advantage; CPO and PCPO keep lambda = 0 and use J_c - d.
    if args.algo == "trpo_lag":
        multiplier = LagrangeMultiplier(cost_limit=args.cost_limit, init=1e-3, lr=0.035)
    else:
        multiplier = NoMultiplier(cost_limit=args.cost_limit)
    policy_step = STEPS[args.algo](actor, target_kl=0.01, cg_iters=15, cg_damping=0.1)
    critic_loss = PPOLagLoss(actor, critic, cost_critic, multiplier, functional=False)  # critic terms only
    critic_params = [*critic.parameters(), *cost_critic.parameters()]
    critic_optimizer = torch.optim.Adam(critic_params, lr=1e-3)
    reward_gae = make_gae(critic, gamma=0.99, lmbda=0.95)
    cost_gae = make_cost_gae(cost_critic, gamma=0.99, lmbda=0.95)

    collector = RolloutCollector(env, actor, steps=args.steps_per_epoch // args.num_envs)
    stats = EpisodeStats()
    mean_cost = 0.0
    for epoch in range(args.total_steps // args.steps_per_epoch):
        batch = collector.collect()
        stats.update(batch)
        finished = stats.pop_finished()
        if finished["cost"].numel():
            mean_cost = finished["cost"].mean().item()
        multiplier.update(mean_cost)

        with torch.no_grad():
            reward_gae(batch)
            cost_gae(batch)
        data = batch.reshape(-1)
        normalize_advantages(data)

        # The actor: one trust-region step on the whole batch.
        advantage = multiplier.combine(data["advantage"], data["cost_advantage"])
        info = policy_step.step(data, advantage, data["cost_advantage"], multiplier.violation(mean_cost))

        # The critics: minibatch regression to the GAE targets.
        for _ in range(args.critic_iters):
            for minibatch in data[torch.randperm(data.numel())].split(128):
                out = critic_loss.critic_losses(minibatch)
                critic_optimizer.zero_grad()
                (out["loss_critic"] + out["loss_cost_critic"]).backward()
                torch.nn.utils.clip_grad_norm_(critic_params, 40.0)
                critic_optimizer.step()

        window = stats.window(50)
        case = f"  case {info['Misc/CPOCase']:.0f}" if "Misc/CPOCase" in info else ""
        print(f"epoch {epoch + 1}: EpRet {window.get('return', float('nan')):7.2f}  "
              f"EpCost {window.get('cost', float('nan')):6.2f}  KL {info['Train/KL']:.4f}  "
              f"accepted step {info['Misc/AcceptanceStep']:.0f}{case}", flush=True)
    env.close()


if __name__ == "__main__":
    main()
