"""SAC-Lag written out: TorchRL's Collector, ReplayBuffer and SoftUpdate around sg_torchrl's SACLagLoss.

The loop is TorchRL's SAC recipe (``sota-implementations/sac``): a ``Collector`` with random actions for
the first frames, a ``ReplayBuffer`` the transitions go into, gradient steps on sampled minibatches, Polyak
target updates with ``SoftUpdate``. SAC-Lag (OmniSafe's) needs only this on top:

* a twin cost critic beside the twin reward critic, and ``SACLagLoss`` (a ``SACLoss``) in place of
  ``SACLoss``, with the ``LagrangeMultiplier`` whose value weighs the actor's cost term:
  ``(alpha log pi - min Q_r + lambda max Q_c) / (1 + lambda)``;
* ``EpisodeSum`` over reward *and* cost, and one ``multiplier.update`` per epoch from the mean cost of
  the episodes finished in it;
* ``loss_cost_qvalue`` added to the summed loss.

``sg-train --algo sac_lag`` trains the same loss (its seed-batched form) on the seed-group engine.

    python examples/sac_lag.py --env-id SafetyHalfCheetahVelocity-v1 --total-steps 1000000
"""

from __future__ import annotations

import argparse

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import TransformedEnv
from torchrl.objectives import SoftUpdate

import sg_torchrl
from sg_torchrl.envs import EpisodeSum
from sg_torchrl.modules.off_policy import make_off_policy_networks
from sg_torchrl.objectives import LagrangeMultiplier
from sg_torchrl.objectives.off_policy import SACLagLoss


def parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="SafetyHalfCheetahVelocity-v1")
    parser.add_argument("--total-steps", type=int, default=1_000_000)
    parser.add_argument("--steps-per-epoch", type=int, default=2_000, help="frames between multiplier updates")
    parser.add_argument("--num-envs", type=int, default=1)
    parser.add_argument("--warmup-steps", type=int, default=10_000, help="frames of random actions first")
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--hidden", type=int, nargs="+", default=[256, 256])
    parser.add_argument("--cost-limit", type=float, default=25.0)
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args()


def main() -> None:
    args = parse()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)

    base_env = sg_torchrl.make(args.env_id, num_envs=args.num_envs, seed=args.seed)
    env = TransformedEnv(base_env, EpisodeSum(in_keys=["reward", "cost"], out_keys=["episode_reward", "episode_cost"]))
    action_spec = base_env.action_spec[0]
    actor, critics, cost_critics = make_off_policy_networks(base_env.observation_dim, action_spec, args.hidden,
                                                            stochastic=True, num_critics=2, constrained=True)
    multiplier = LagrangeMultiplier(cost_limit=args.cost_limit, init=1e-3, lr=1e-3)  # OmniSafe's
    loss_module = SACLagLoss(actor, critics, cost_critics, multiplier, alpha_init=0.2)
    loss_module.make_value_estimator(gamma=0.99)
    target_updater = SoftUpdate(loss_module, tau=0.005)
    optimizers = [torch.optim.Adam(params.values(True, True), lr=3e-4) for params in (
        loss_module.actor_network_params, loss_module.qvalue_network_params, loss_module.cost_qvalue_network_params)]

    frames = args.num_envs * 10  # ten env steps, then ten gradient steps per simulator
    collector = Collector(env, actor, frames_per_batch=frames, total_frames=args.total_steps,
                          init_random_frames=args.warmup_steps, auto_register_policy_transforms=False)
    buffer = ReplayBuffer(storage=LazyTensorStorage(min(args.total_steps, 1_000_000)), batch_size=args.batch_size)

    seen, epoch, costs, returns, updates = 0, 0, [], [], 0
    for data in collector:
        buffer.extend(data.reshape(-1))
        seen += data.numel()
        done = data["next", "done"]
        costs += data["next", "episode_cost"][done].tolist()
        returns += data["next", "episode_reward"][done].tolist()
        if seen > args.warmup_steps:
            for _ in range(data.numel()):  # one gradient step per env step
                out = loss_module(buffer.sample())
                loss = out["loss_actor"] + out["loss_qvalue"] + out["loss_cost_qvalue"]
                for optimizer in optimizers:
                    optimizer.zero_grad()
                loss.backward()
                for params in (loss_module.actor_network_params, loss_module.qvalue_network_params,
                               loss_module.cost_qvalue_network_params):
                    torch.nn.utils.clip_grad_norm_(list(params.values(True, True)), 40.0)
                for optimizer in optimizers:
                    optimizer.step()
                updates += 1
                if updates % 2 == 0:  # OmniSafe's policy delay: the targets follow every second step
                    target_updater.step()
        if seen // args.steps_per_epoch > epoch:  # an epoch ended: the multiplier follows its episodes' cost
            epoch = seen // args.steps_per_epoch
            ep_cost = sum(costs) / len(costs) if costs else float("nan")
            ep_ret = sum(returns) / len(returns) if returns else float("nan")
            if costs:
                multiplier.update(ep_cost)
            print(f"epoch {epoch}: EpRet {ep_ret:8.2f}  EpCost {ep_cost:7.2f}  lambda {multiplier.value.item():.4f}  "
                  f"gradient steps {updates}", flush=True)
            costs, returns = [], []
    collector.shutdown()


if __name__ == "__main__":
    main()
