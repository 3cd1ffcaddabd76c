"""PPO-Lag from pixels, written out: CNN actor and critics on a Safety-Gymnasium Vision task.

A recipe in the style of TorchRL's sota-implementations, the pixel twin of ``first_order.py``. A
``...Vision-v0`` id emits what the robot's camera sees, ``"pixels"`` ``(N, H, W, 3)`` uint8, channels
last as TorchRL's raw pixels, next to the flat ``"observation"``: Safety-Gymnasium's layout, 256 x 256
by default. This recipe asks for 64 x 64 images (``--image-size``; 16 times cheaper to render and
convolve on a CPU) and pixels only (``--obs-mode rgb``; ``rgbd`` adds ``"depth"`` ``(N, 64, 64, 1)`` in
metres, ``vector+rgb`` / ``vector+rgbd`` keep the flat vector too).
``make_actor_critics`` reads the env's observation spec and gives each of the actor and the two
critics its own small CNN encoder (TorchRL's ``ConvNet``) before the usual tanh MLP; images stay
uint8 and channels last in the batch and are scaled and turned channels first inside the networks. Only a flat vector, if
any, gets the running normaliser. Passes over the whole batch without gradient (the critics' values
for GAE, the KL early stop) run in chunks, so an epoch of frames is never converted to float at once.

Epochs are sized for a CPU (see ``sg-train --preset vision``): rendering the 10 cameras dominates
collection and three CNNs the update, so 4 passes of minibatch 64 instead of the paper's 40.

    python examples/vision.py --env-id SafetyPointGoal1Vision-v0 --total-steps 80000
"""

from __future__ import annotations

import argparse
import time

import torch
from torchrl.envs import TransformedEnv

import sg_torchrl
from sg_torchrl.collectors import EpisodeStats, RolloutCollector
from sg_torchrl.envs.normalization import RunningObservationNorm
from sg_torchrl.objectives import (
    LagrangeMultiplier,
    PPOLagLoss,
    gaussian_kl,
    make_cost_gae,
    make_gae,
    normalize_advantages,
)
from sg_torchrl.modules.mlp import ObservationLayout, forward_in_chunks, make_actor_critics, write_values


def parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="SafetyPointGoal1Vision-v0")
    parser.add_argument("--obs-mode", choices=["rgb", "rgbd", "vector+rgb", "vector+rgbd"], default="rgb")
    parser.add_argument("--image-size", type=int, default=64, help="image side in pixels (the ids' default: 256)")
    parser.add_argument("--max-episode-steps", type=int, default=None, help="shorter episodes (default: the task's)")
    parser.add_argument("--total-steps", type=int, default=80_000)
    parser.add_argument("--steps-per-epoch", type=int, default=10_000)
    parser.add_argument("--num-envs", type=int, default=10)
    parser.add_argument("--update-iters", type=int, default=4)
    parser.add_argument("--minibatch-size", type=int, default=64)
    parser.add_argument("--cost-limit", type=float, default=25.0)
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args()


def main() -> None:
    args = parse()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)

    # Env: N simulators rendering their robot cameras in one process.
    options = {"obs_mode": args.obs_mode, "image_size": args.image_size}
    if args.max_episode_steps:
        options["max_episode_steps"] = args.max_episode_steps
    base_env = sg_torchrl.make(args.env_id, num_envs=args.num_envs, seed=args.seed, **options)
    layout = ObservationLayout.from_spec(base_env.observation_spec)  # pixels / depth / observation
    obs_norm = RunningObservationNorm((layout.vector_dim,)) if layout.vector_dim else None
    env = TransformedEnv(base_env, obs_norm) if obs_norm else base_env

    # Networks (a CNN encoder each), multiplier and loss: the vector recipe's, unchanged.
    actor, critic, cost_critic = make_actor_critics(layout, base_env.action_spec, [64, 64])
    multiplier = LagrangeMultiplier(cost_limit=args.cost_limit, init=1e-3, lr=0.035)
    loss = PPOLagLoss(actor, critic, cost_critic, multiplier, functional=False)
    reward_gae = make_gae(None, gamma=0.99, lmbda=0.95)  # values come from write_values below
    cost_gae = make_cost_gae(None, gamma=0.99, lmbda=0.95)
    optimizer = torch.optim.Adam(loss.parameters(), lr=3e-4)

    collector = RolloutCollector(env, actor, steps=args.steps_per_epoch // args.num_envs)
    stats = EpisodeStats()
    for epoch in range(args.total_steps // args.steps_per_epoch):
        start = time.perf_counter()
        batch = collector.collect()
        collected = time.perf_counter()
        stats.update(batch)
        finished = stats.pop_finished()
        if finished["cost"].numel():
            multiplier.update(finished["cost"].mean())  # before the policy update, as SafePO

        with torch.no_grad():
            write_values(batch, (critic, cost_critic), layout.chunk_size)  # chunked: images stay uint8
            reward_gae(batch)
            cost_gae(batch)
        data = batch.reshape(-1)
        normalize_advantages(data)
        old_loc, old_scale = data["loc"].clone(), data["scale"].clone()

        for passes in range(1, args.update_iters + 1):
            for indices in torch.randperm(data.numel()).split(args.minibatch_size):
                out = loss(data[indices])  # only this minibatch's frames are gathered and scaled
                total = out["loss_objective"] + out["loss_critic"] + out["loss_cost_critic"]
                optimizer.zero_grad()
                total.backward()
                torch.nn.utils.clip_grad_norm_(loss.parameters(), 40.0)
                optimizer.step()
            current = forward_in_chunks(actor.get_dist_params, data, actor.in_keys, ("loc", "scale"),
                                        layout.chunk_size)
            kl = gaussian_kl(old_loc, old_scale, current["loc"], current["scale"]).mean().item()
            if kl > 0.02:  # SafePO's early stop
                break

        window = stats.window(50)
        print(f"epoch {epoch + 1}: EpRet {window.get('return', float('nan')):7.2f}  "
              f"EpCost {window.get('cost', float('nan')):6.2f}  lambda {multiplier.value.item():.3f}  "
              f"passes {passes}  KL {kl:.4f}  collect {collected - start:.1f}s  "
              f"update {time.perf_counter() - collected:.1f}s", flush=True)
    env.close()


if __name__ == "__main__":
    main()
