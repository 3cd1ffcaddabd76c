"""SAC-Lag, TD3-Lag and DDPG-Lag: the objective against hand computations, the losses against TorchRL's own.

* without a multiplier each loss is TorchRL's ``SACLoss`` / ``TD3Loss`` / ``DDPGLoss`` on the same batch and
  parameters (the same random draws), so SAC, TD3 and DDPG are these classes, not copies;
* the reward and cost critics' targets (discount, termination masking, the twin reduction, SAC's entropy
  term in the reward target only), the critic losses and the Lagrangian actor loss against numbers worked
  out by hand on a tiny batch;
* the seed-batched form (``seed_dims=1``) is each seed's one-batch form;
* bad options are refused.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.objectives import DDPGLoss, SACLoss, TD3Loss, ValueEstimators

from sg_torchrl.modules.off_policy import make_off_policy_networks
from sg_torchrl.objectives import LagrangeMultiplier, PIDLagrangeMultiplier
from sg_torchrl.objectives.off_policy import DDPGLagLoss, OffPolicyObjective, SACLagLoss, TD3LagLoss

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")
SPEC = Bounded(-torch.ones(2), torch.ones(2), (2,))


def _batch(n: int = 6, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    terminated = torch.zeros(n, 1, dtype=torch.bool)
    terminated[1] = True
    return TensorDict({
        "observation": torch.randn(n, 3, generator=g), "action": torch.rand(n, 2, generator=g) * 2 - 1,
        "next": {"observation": torch.randn(n, 3, generator=g), "reward": torch.randn(n, 1, generator=g),
                 "cost": torch.rand(n, 1, generator=g), "terminated": terminated, "done": terminated.clone()},
    }, [n])


def _networks(stochastic: bool, k: int, constrained: bool = False):
    torch.manual_seed(1)
    return make_off_policy_networks(3, SPEC, [8, 8], stochastic=stochastic, num_critics=k, constrained=constrained)


@pytest.mark.parametrize("name", ["sac", "td3", "ddpg"])
def test_without_a_multiplier_the_loss_is_torchrls(name):
    stochastic, k = name == "sac", 1 if name == "ddpg" else 2
    actor, critics, _ = _networks(stochastic, k)
    if name == "sac":
        ours = SACLagLoss(actor, critics, alpha_init=0.2)
        stock = SACLoss(actor, critics, alpha_init=0.2, fixed_alpha=True, loss_function="l2")
    elif name == "td3":
        ours = TD3LagLoss(actor, critics, action_spec=SPEC)
        stock = TD3Loss(actor, critics, action_spec=SPEC, loss_function="l2")
    else:
        ours = DDPGLagLoss(actor, critics[0])
        stock = DDPGLoss(actor, critics[0], loss_function="l2", delay_actor=True)
    for loss in (ours, stock):
        loss.make_value_estimator(ValueEstimators.TD0, gamma=0.9)
    torch.manual_seed(5)
    got = ours(_batch())
    torch.manual_seed(5)
    want = stock(_batch())
    value_key = "loss_value" if name == "ddpg" else "loss_qvalue"
    torch.testing.assert_close(got["loss_qvalue"], want[value_key])
    torch.testing.assert_close(got["loss_actor"], want["loss_actor"])
    assert "loss_cost_qvalue" not in got.keys()


def test_hand_computed_targets_losses_and_actor_term():
    """gamma 0.5; two samples (the second terminated); twin critics; alpha 0.1; lambda 1."""
    objective = OffPolicyObjective(gamma=0.5, alpha=0.1, actor_q="min", cost_reduction="max")
    q = torch.tensor([[1.0, 2.0], [3.0, 0.0]])  # (K=2, B=2)
    next_q = torch.tensor([[4.0, 10.0], [2.0, 20.0]])
    next_log_prob = torch.tensor([-1.0, 3.0])
    cost_q = torch.tensor([[0.5, 1.0], [1.5, 2.0]])
    next_cost_q = torch.tensor([[2.0, 7.0], [6.0, 9.0]])
    reward, cost = torch.tensor([1.0, 2.0]), torch.tensor([1.0, 0.0])
    terminated = torch.tensor([False, True])
    out = objective.losses(q=q, next_q=next_q, reward=reward, terminated=terminated, seed_dims=0,
                           next_log_prob=next_log_prob, cost_q=cost_q, next_cost_q=next_cost_q, cost=cost,
                           actor_q=torch.tensor([[2.0, 1.0], [1.0, 5.0]]), actor_log_prob=torch.tensor([0.5, -0.5]),
                           actor_cost_q=torch.tensor([[1.0, 4.0], [3.0, 2.0]]), lam=torch.tensor(1.0))
    # reward: min_k(Q' - 0.1 logp') = min(4.1, 2.1) = 2.1 -> 1 + 0.5 * 2.1 = 2.05; terminated -> 2.0
    torch.testing.assert_close(out["target_value"], torch.tensor([2.05, 2.0]))
    # cost: max_k Q_c' = 6 -> 1 + 0.5 * 6 = 4.0 (no entropy term); terminated -> 0.0
    torch.testing.assert_close(out["target_cost_value"], torch.tensor([4.0, 0.0]))
    # critic losses: squared errors summed over the twins, averaged over the samples
    want_q = (((1 - 2.05) ** 2 + (3 - 2.05) ** 2) + ((2 - 2.0) ** 2 + (0 - 2.0) ** 2)) / 2
    want_c = (((0.5 - 4) ** 2 + (1.5 - 4) ** 2) + ((1 - 0) ** 2 + (2 - 0) ** 2)) / 2
    torch.testing.assert_close(out["loss_qvalue"], torch.tensor(want_q))
    torch.testing.assert_close(out["loss_cost_qvalue"], torch.tensor(want_c))
    # actor: (0.1 logp - min Q + lambda max Q_c) / (1 + lambda)
    want_actor = ((0.05 - 1.0 + 3.0) / 2 + (-0.05 - 1.0 + 4.0) / 2) / 2
    torch.testing.assert_close(out["loss_actor"], torch.tensor(want_actor))


@pytest.mark.parametrize("reduction, want", [("mean", [1 + 0.5 * 4.0, 0.0]), ("min", [1 + 0.5 * 2.0, 0.0])])
def test_cost_target_reductions(reduction, want):
    objective = OffPolicyObjective(gamma=0.5, cost_reduction=reduction)
    next_cost_q = torch.tensor([[2.0, 7.0], [6.0, 9.0]])
    target = objective.bootstrap(torch.tensor([1.0, 0.0]), torch.tensor([False, True]),
                                 objective.reduce_cost(next_cost_q, 0))
    torch.testing.assert_close(target, torch.tensor(want))


def test_unconstrained_actor_terms():
    q = torch.tensor([[2.0, 1.0], [1.0, 5.0]])
    td3 = OffPolicyObjective(gamma=0.9, actor_q="first", constrained=False)
    torch.testing.assert_close(td3.actor_loss(q, None, None, None, 0), torch.tensor(-1.5))  # -mean(Q_1)
    sac = OffPolicyObjective(gamma=0.9, alpha=0.2, constrained=False)
    torch.testing.assert_close(sac.actor_loss(q, torch.tensor([1.0, 2.0]), None, None, 0),
                               torch.tensor(((0.2 - 1.0) + (0.4 - 1.0)) / 2))


def test_td3_smoothing_is_clipped_and_bounded():
    objective = OffPolicyObjective(gamma=0.9, policy_noise=0.2, noise_clip=0.5, actor_q="first")
    action = torch.tensor([0.9, 0.0, -0.2])
    noise = torch.tensor([1.0, 10.0, -1.0])  # scaled: 0.2, 2.0 -> clipped 0.5, -0.2
    got = objective.smoothed_action(action, noise, torch.tensor(-1.0), torch.tensor(1.0))
    torch.testing.assert_close(got, torch.tensor([1.0, 0.5, -0.4]))


def test_seed_batched_form_is_each_seeds_form():
    g = torch.Generator().manual_seed(3)
    objective = OffPolicyObjective(gamma=0.99, alpha=0.2, cost_reduction="max")
    S, K, B = 3, 2, 5

    def r(*shape):
        return torch.randn(*shape, generator=g)

    fields = dict(q=r(S, K, B), next_q=r(S, K, B), reward=r(S, B), terminated=torch.rand(S, B, generator=g) > 0.7,
                  next_log_prob=r(S, B), cost_q=r(S, K, B), next_cost_q=r(S, K, B), cost=r(S, B).abs(),
                  actor_q=r(S, K, B), actor_log_prob=r(S, B), actor_cost_q=r(S, K, B))
    lam = torch.tensor([0.0, 0.5, 3.0])
    stacked = objective.losses(seed_dims=1, lam=lam, **fields)
    for s in range(S):
        single = objective.losses(seed_dims=0, lam=lam[s], **{k: v[s] for k, v in fields.items()})
        for name in ("loss_qvalue", "loss_cost_qvalue", "loss_actor", "target_value", "target_cost_value"):
            torch.testing.assert_close(stacked[name][s], single[name])


@pytest.mark.parametrize("name", ["sac", "td3", "ddpg"])
def test_constrained_loss_evaluates_the_objective(name):
    """Lambda moves the actor loss as (l_r + lambda Q_c) / (1 + lambda), and the actor's gradient reaches no critic."""
    stochastic, k = name == "sac", 1 if name == "ddpg" else 2
    actor, critics, costs = _networks(stochastic, k, constrained=True)
    multiplier = LagrangeMultiplier(cost_limit=0.0, init=0.0, lr=0.1)
    cls = {"sac": SACLagLoss, "td3": TD3LagLoss, "ddpg": DDPGLagLoss}[name]
    kw = {"action_spec": SPEC} if name == "td3" else {}
    if k == 1:
        critics, costs = critics[0], costs[0]
    loss = cls(actor, critics, costs, multiplier, **kw)
    outs = {}
    for lam in (0.0, 2.0, 5.0):  # the same draws each time: only lambda changes
        multiplier.lambda_raw.fill_(lam)
        torch.manual_seed(2)
        outs[lam] = loss(_batch())
        torch.testing.assert_close(outs[lam]["lagrangian"], torch.tensor(lam))
    # (1 + lambda) * loss_actor = L_r + lambda * C: linear in lambda, L_r the unconstrained loss
    reward_term = outs[0.0]["loss_actor"]
    cost_term = (3 * outs[2.0]["loss_actor"] - reward_term) / 2
    torch.testing.assert_close(6 * outs[5.0]["loss_actor"], reward_term + 5 * cost_term)
    out = outs[5.0]
    loss.zero_grad()
    out["loss_actor"].backward()
    for params in (loss.cost_qvalue_network_params, loss._critic_params):
        assert all(p.grad is None or not p.grad.any() for p in params.values(True, True))
    assert any(p.grad is not None and p.grad.any() for p in loss.actor_network_params.values(True, True))


def test_pid_variant_is_the_same_class():
    actor, critics, costs = _networks(True, 2, constrained=True)
    loss = SACLagLoss(actor, critics, costs, PIDLagrangeMultiplier(cost_limit=25.0, kp=0.1, ki=0.01, kd=0.01))
    assert type(loss) is SACLagLoss and loss.seed_batched_objective().constrained


def test_refusals():
    actor, critics, costs = _networks(True, 2, constrained=True)
    multiplier = LagrangeMultiplier(cost_limit=25.0)
    with pytest.raises(TypeError):
        SACLagLoss(actor, critics, costs, multiplier, no_such_option=1)
    with pytest.raises(ValueError, match="fixed alpha"):
        SACLagLoss(actor, critics, costs, multiplier, fixed_alpha=False)
    with pytest.raises(ValueError, match="cost_reduction"):
        SACLagLoss(actor, critics, costs, multiplier, cost_reduction="median")
    with pytest.raises(ValueError, match="together"):
        SACLagLoss(actor, critics, None, multiplier)
    with pytest.raises(ValueError, match="reduction"):
        SACLagLoss(actor, critics, costs, multiplier, reduction="sum")
    with pytest.raises(ValueError, match="TD\\(0\\)"):
        SACLagLoss(actor, critics, costs, multiplier).make_value_estimator(ValueEstimators.TDLambda)
    with pytest.raises(TypeError, match="Multiplier"):
        SACLagLoss(actor, critics, costs, object())
