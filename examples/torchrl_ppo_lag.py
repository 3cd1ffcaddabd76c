"""TorchRL's own PPO recipe, turned into PPO-Lag with sg_torchrl's loss, multiplier and cost bookkeeping.

The loop is TorchRL's ``sota-implementations/ppo/ppo_mujoco.py``: a ``Collector``, a ``ReplayBuffer``
sampling minibatches without replacement, a Gaussian MLP actor and critic, Adam. PPO-Lag (Ray et al.
2019; the Safety-Gymnasium paper's PPO-Lag) needs only this glue on top:

* a cost critic beside the reward critic, and ``PPOLagLoss`` (a ``ClipPPOLoss``) in place of
  ``ClipPPOLoss``, with the ``LagrangeMultiplier`` it reads;
* ``EpisodeSum`` over reward *and* cost (sg_torchrl envs declare ``cost`` in the observation spec,
  where TorchRL's ``RewardSum`` does not look), and one ``multiplier.update`` per batch from the
  mean cost of the episodes finished in it;
* ``loss.estimate_advantages(data)`` in place of the recipe's ``GAE`` module: reward and cost GAE
  on the whole batch, normalised the SafePO way (reward standardised, cost mean-centred). Given a
  whole rollout without advantages the loss would compute the same itself, as TorchRL's losses do;
  the minibatches need them computed once, before the batch is shuffled;
* ``loss_cost_critic`` added to the summed loss.

    python examples/torchrl_ppo_lag.py --env-id SafetyHalfCheetahVelocity-v1 --total-steps 1000000
"""

from __future__ import annotations

import argparse

import torch
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.envs import Compose, TransformedEnv
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator

import sg_torchrl
from sg_torchrl.envs import EpisodeSum
from sg_torchrl.envs.normalization import RunningObservationNorm
from sg_torchrl.objectives import LagrangeMultiplier, PPOLagLoss


def parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="SafetyHalfCheetahVelocity-v1")
    parser.add_argument("--total-steps", type=int, default=1_000_000)
    parser.add_argument("--steps-per-epoch", type=int, default=20_000, help="frames per collected batch")
    parser.add_argument("--num-envs", type=int, default=10)
    parser.add_argument("--update-iters", type=int, default=10, help="passes over each batch (TorchRL's ppo_epochs)")
    parser.add_argument("--minibatch-size", type=int, default=64)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--cost-limit", type=float, default=25.0)
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args()


def make_models(obs_dim: int, action_spec) -> tuple[ProbabilisticActor, ValueOperator, ValueOperator]:
    """TorchRL's PPO MuJoCo networks (tanh MLPs 64 x 64, TanhNormal policy), plus a cost critic."""
    act_dim = action_spec.shape[-1]
    body = torch.nn.Sequential(MLP(in_features=obs_dim, out_features=act_dim, num_cells=[64, 64],
                                   activation_class=torch.nn.Tanh),
                               AddStateIndependentNormalScale(act_dim, scale_lb=1e-8))
    actor = ProbabilisticActor(
        TensorDictModule(body, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"], spec=action_spec, distribution_class=TanhNormal,
        distribution_kwargs={"low": action_spec.space.low, "high": action_spec.space.high, "tanh_loc": False},
        return_log_prob=True, default_interaction_type="random",
    )

    def critic(out_key: str) -> ValueOperator:
        mlp = MLP(in_features=obs_dim, out_features=1, num_cells=[64, 64], activation_class=torch.nn.Tanh)
        return ValueOperator(mlp, in_keys=["observation"], out_keys=[out_key])

    return actor, critic("state_value"), critic("cost_value")


def main() -> None:
    args = parse()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)  # small MLPs: one thread is ~10x faster than two on a small CPU

    base_env = sg_torchrl.make(args.env_id, num_envs=args.num_envs, seed=args.seed)
    env = TransformedEnv(base_env, Compose(
        RunningObservationNorm((base_env.observation_dim,)),
        EpisodeSum(in_keys=["reward", "cost"], out_keys=["episode_reward", "episode_cost"]),
    ))
    actor, critic, cost_critic = make_models(base_env.observation_dim, env.action_spec)

    collector = Collector(env, actor, frames_per_batch=args.steps_per_epoch, total_frames=args.total_steps,
                          auto_register_policy_transforms=False)
    buffer = ReplayBuffer(storage=LazyTensorStorage(args.steps_per_epoch), sampler=SamplerWithoutReplacement(),
                          batch_size=args.minibatch_size)
    multiplier = LagrangeMultiplier(cost_limit=args.cost_limit, init=1e-3, lr=0.035)  # the paper's
    loss_module = PPOLagLoss(actor, critic, cost_critic, multiplier, clip_epsilon=0.2)
    optimizer = torch.optim.Adam(loss_module.parameters(), lr=args.lr)

    ep_ret = ep_cost = float("nan")
    for epoch, data in enumerate(collector, start=1):
        done = data["next", "done"]
        if done.any():  # episodes finished in this batch: their mean cost moves the multiplier
            ep_ret = data["next", "episode_reward"][done].mean().item()
            ep_cost = data["next", "episode_cost"][done].mean().item()
            multiplier.update(ep_cost)

        loss_module.estimate_advantages(data)  # reward and cost GAE, SafePO's normalisation
        buffer.empty()
        buffer.extend(data.reshape(-1))
        for _ in range(args.update_iters):
            for batch in buffer:
                out = loss_module(batch)
                loss = out["loss_objective"] + out["loss_critic"] + out["loss_cost_critic"]
                optimizer.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(loss_module.parameters(), 40.0)
                optimizer.step()
        collector.update_policy_weights_()

        print(f"epoch {epoch}: EpRet {ep_ret:8.2f}  EpCost {ep_cost:7.2f}  lambda {multiplier.value.item():.3f}  "
              f"loss_cost_critic {out['loss_cost_critic'].item():.3f}", flush=True)
    collector.shutdown()


if __name__ == "__main__":
    main()
