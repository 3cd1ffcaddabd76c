"""Safe multi-agent RL, written out: MAPPO, HAPPO, MAPPO-Lag or MACPO on a MaMuJoCo velocity task.

A recipe in the style of TorchRL's sota-implementations: every piece ``sg-train`` composes is built
here in plain sight. Several agents drive parts of one robot (Safety2x3HalfCheetahVelocity-v0: two
agents, three joints each), share the reward and each pay a cost when the robot runs faster than
the task's threshold (Safety-Gymnasium paper, section 6). Every agent has its own actor (local
observation) and its own centralised reward and cost critics (the global ``"state"``); the
algorithms differ only in the update *round*, which visits the agents one at a time in a random
order:

* MAPPO:     independent clipped PPO per agent                     (Yu et al. 2022)
* HAPPO:     PPO weighted by the earlier agents' ratio product M    (Kuba et al. 2022)
* MAPPO-Lag: HAPPO on A_r - lambda_i A_c, lambda_i per agent        (Gu et al. 2023)
* MACPO:     a CPO step per agent on M-weighted surrogates         (Gu et al. 2023)

Each epoch: collect, per-agent reward and cost GAE, then the round with the mean cost of the
episodes finished in the epoch (MAPPO-Lag steps its multipliers inside the round).

    python examples/multi_agent.py --algo mappo_lag --env-id Safety2x3HalfCheetahVelocity-v0
"""

from __future__ import annotations

import argparse

import torch

import sg_torchrl
from sg_torchrl.collectors import EpisodeStats, RolloutCollector
from sg_torchrl.modules import make_multi_agent_networks
from sg_torchrl.objectives.multi_agent import make_multi_agent_cost_gae, make_multi_agent_gae
from sg_torchrl.train.multi_agent_updates import HAPPOUpdate, MACPOUpdate, MAPPOLagUpdate, MAPPOUpdate

ROUNDS = {"mappo": MAPPOUpdate, "happo": HAPPOUpdate, "mappo_lag": MAPPOLagUpdate, "macpo": MACPOUpdate}


def parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", choices=sorted(ROUNDS), default="mappo_lag")
    parser.add_argument("--env-id", default="Safety2x3HalfCheetahVelocity-v0")
    parser.add_argument("--total-steps", type=int, default=1_000_000)
    parser.add_argument("--steps-per-epoch", type=int, default=10_000)  # episode length 1000 x 10 simulators
    parser.add_argument("--num-envs", type=int, default=10)
    parser.add_argument("--epochs-per-round", type=int, default=5, help="PPO epochs (MACPO: critic epochs)")
    parser.add_argument("--cost-limit", type=float, default=25.0)
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args()


def main() -> None:
    args = parse()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)

    # Env: N simulators of one robot in one process, TorchRL's multi-agent layout (group "agents").
    env = sg_torchrl.make(args.env_id, num_envs=args.num_envs, seed=args.seed)
    print(f"{args.env_id}: {env.num_agents} agents, observation sizes {env.observation_sizes}, "
          f"action sizes {env.action_sizes}, state {env.state_dim}")

    # One actor, one reward critic and one cost critic per agent (no sharing), MLP ReLU [128, 128].
    nets = make_multi_agent_networks(env.observation_dim, env.action_sizes, env.state_dim, hidden_sizes=[128, 128])
    reward_gae = make_multi_agent_gae(nets.reward_critic, gamma=0.99, lmbda=0.95)  # standardised per agent
    cost_gae = make_multi_agent_cost_gae(nets.cost_critic, gamma=0.99, lmbda=0.95)

    # The round: paper defaults (Adam 5e-4, one minibatch, clip 0.2, KL stop 0.016; MACPO: delta 0.01).
    options = dict(cost_limit=args.cost_limit, generator=torch.Generator().manual_seed(args.seed))
    if args.algo == "macpo":
        update = MACPOUpdate(nets, critic_epochs=args.epochs_per_round, **options)
    else:
        update = ROUNDS[args.algo](nets, epochs=args.epochs_per_round, **options)

    collector = RolloutCollector(env, nets.actor, steps=args.steps_per_epoch // args.num_envs)
    stats = EpisodeStats(reward_key=("next", "agents", "reward"), agent_dim=-2)  # team reward, team cost
    episode_cost = 0.0
    for epoch in range(args.total_steps // args.steps_per_epoch):
        batch = collector.collect()  # [num_envs, T], group entries [num_envs, T, n_agents, ...]
        stats.update(batch)
        finished = stats.pop_finished()
        if finished["cost"].numel():
            episode_cost = finished["cost"].mean().item()

        with torch.no_grad():
            reward_gae(batch)
            cost_gae(batch)
        metrics = update(batch, episode_cost)  # team metrics and "<name>/agent<i>"

        window = stats.window(50)
        print(f"epoch {epoch + 1}: EpRet {window.get('return', float('nan')):7.2f}  "
              f"EpCost {window.get('cost', float('nan')):6.2f}  "
              f"lambda {metrics['Train/LagrangeMultiplier']:.3f}  KL {metrics['Train/KL']:.4f}  "
              f"order {[int(metrics[f'Train/AgentOrder/agent{i}']) for i in range(env.num_agents)]}", flush=True)
    env.close()


if __name__ == "__main__":
    main()
