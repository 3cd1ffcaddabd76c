"""Tests of PPOLagLoss (PPO-Lag / CPPO-PID) and gaussian_kl on synthetic batches."""
from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)

from tensordict import TensorDict  # noqa: E402
from tensordict.nn import (  # noqa: E402
    AddStateIndependentNormalScale,
    InteractionType,
    set_interaction_type,
    TensorDictModule,
)
from torch import distributions as D, nn  # noqa: E402
from torchrl.modules import IndependentNormal, MLP, ProbabilisticActor, PopArtValueNorm, ValueOperator  # noqa: E402
from torchrl.objectives import ClipPPOLoss  # noqa: E402

from sg_torchrl.objectives import (  # noqa: E402
    gaussian_kl,
    LagrangeMultiplier,
    Multiplier,
    PIDLagrangeMultiplier,
    PPOLagLoss,
)

OBS_DIM, ACT_DIM, BATCH = 5, 2, 32
LOSS_KEYS = {"loss_objective", "loss_critic", "loss_cost_critic"}


# --------------------------------------------------------------------------- helpers
class SummedNormal(D.Independent):
    """torch's Normal with the log-prob summed over the action dim."""

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor) -> None:
        super().__init__(D.Normal(loc, scale), 1)


DISTRIBUTIONS = {"IndependentNormal": IndependentNormal, "torch_Normal_summed": SummedNormal}


def make_actor(distribution: str = "IndependentNormal", seed: int = 0) -> ProbabilisticActor:
    torch.manual_seed(seed)
    net = nn.Sequential(
        MLP(in_features=OBS_DIM, out_features=ACT_DIM, num_cells=[16, 16], activation_class=nn.Tanh),
        AddStateIndependentNormalScale(ACT_DIM, scale_mapping="exp"),
    )
    return ProbabilisticActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=DISTRIBUTIONS[distribution],
        return_log_prob=True,
    )


def make_critic(out_key: str, seed: int) -> ValueOperator:
    torch.manual_seed(seed)
    mlp = MLP(in_features=OBS_DIM, out_features=1, num_cells=[16, 16], activation_class=nn.Tanh)
    return ValueOperator(mlp, in_keys=["observation"], out_keys=[out_key])


def make_modules(distribution: str = "IndependentNormal"):
    return make_actor(distribution), make_critic("state_value", 1), make_critic("cost_value", 2)


def make_batch(actor: ProbabilisticActor, seed: int = 3) -> TensorDict:
    """A rollout-like batch; stored log-probs differ from the actor's (ratios != 1, some clipped)."""
    gen = torch.Generator().manual_seed(seed)
    td = TensorDict(observation=torch.randn(BATCH, OBS_DIM, generator=gen), batch_size=[BATCH])
    # Sample like a collector does; tensordict's default interaction type returns the mean, where
    # the log-prob has zero gradient w.r.t. the mean and the actor's MLP would learn nothing.
    torch.manual_seed(seed)
    with torch.no_grad(), set_interaction_type(InteractionType.RANDOM):
        td = actor(td)
    td["action_log_prob"] = td["action_log_prob"] + 0.4 * torch.randn(BATCH, generator=gen)
    for key in ("advantage", "value_target", "cost_advantage", "cost_value_target"):
        td[key] = torch.randn(BATCH, 1, generator=gen)
    td["state_value"] = torch.randn(BATCH, 1, generator=gen)
    td["cost_value"] = torch.randn(BATCH, 1, generator=gen)
    return td


def sum_sq(module: nn.Module) -> torch.Tensor:
    return sum(p.pow(2).sum() for p in module.parameters())


def clip_ppo_reference(actor, critic, data, advantage):
    """torchrl's ClipPPOLoss with SafePO's settings, fed a given advantage."""
    ref = ClipPPOLoss(actor, critic, entropy_bonus=False, loss_critic_type="l2")
    data = data.clone()
    data["advantage"] = advantage
    return ref(data)


# --------------------------------------------------------------------------- tests
class TestPPOLagLoss:
    def test_log_prob_key(self):
        actor, critic, cost_critic = make_modules()
        loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier())
        assert loss.tensor_keys.sample_log_prob == "action_log_prob"
        assert "action_log_prob" in make_batch(actor).keys()

    @pytest.mark.parametrize("distribution", sorted(DISTRIBUTIONS))
    def test_output_keys_and_shapes(self, distribution):
        actor, critic, cost_critic = make_modules(distribution)
        multiplier = LagrangeMultiplier(init=0.3)
        loss = PPOLagLoss(actor, critic, cost_critic, multiplier)
        out = loss(make_batch(actor))
        assert {k for k in out.keys() if k.startswith("loss_")} == LOSS_KEYS  # no entropy bonus
        for key in ("lagrange_multiplier", "kl_approx", "clip_fraction", "ESS"):
            assert key in out.keys()
        assert set(loss.out_keys) <= set(out.keys())
        for key in LOSS_KEYS | {"lagrange_multiplier", "kl_approx", "clip_fraction"}:
            assert out[key].shape == torch.Size([]), key
            assert torch.isfinite(out[key]), key
        assert 0.0 < out["clip_fraction"].item() < 1.0  # the batch really exercises the clip
        for key in out.keys():
            if not key.startswith("loss_"):
                assert not out[key].requires_grad, key
        torch.testing.assert_close(out["lagrange_multiplier"], multiplier.value)

    @pytest.mark.parametrize("distribution", sorted(DISTRIBUTIONS))
    def test_backward_reaches_all_networks(self, distribution):
        actor, critic, cost_critic = make_modules(distribution)
        loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.5))
        out = loss(make_batch(actor))
        sum(out[k] for k in out.keys() if k.startswith("loss_")).backward()
        for name, module in (("actor", actor), ("critic", critic), ("cost_critic", cost_critic)):
            for pname, p in module.named_parameters():
                assert p.grad is not None, f"{name}.{pname} got no gradient"
                assert p.grad.abs().sum() > 0, f"{name}.{pname} got a zero gradient"

    def test_in_keys(self):
        actor, critic, cost_critic = make_modules()
        loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier())
        assert set(loss.in_keys) == {
            "observation",
            "action",
            "action_log_prob",
            "advantage",
            "value_target",
            "cost_advantage",
            "cost_value_target",
        }

    def test_parameters_and_state(self):
        actor, critic, cost_critic = make_modules()
        multiplier = LagrangeMultiplier()
        loss = PPOLagLoss(actor, critic, cost_critic, multiplier)
        loss_params = {id(p) for p in loss.parameters()}
        for module in (actor, critic, cost_critic):
            assert {id(p) for p in module.parameters()} <= loss_params
        n_expected = sum(1 for m in (actor, critic, cost_critic) for _ in m.parameters())
        assert len(loss_params) == n_expected  # the multiplier contributes no parameter
        assert "multiplier.lambda_raw" in loss.state_dict()

    def test_zero_multiplier_equals_clip_ppo(self):
        actor, critic, cost_critic = make_modules()
        loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.0))
        data = make_batch(actor)
        out = loss(data)
        ref = clip_ppo_reference(actor, critic, data, data["advantage"])
        for key in ("loss_objective", "clip_fraction", "kl_approx", "ESS"):
            torch.testing.assert_close(out[key], ref[key])
        # SafePO's critic loss = MSE + 0.001 * sum of squared critic parameters
        torch.testing.assert_close(out["loss_critic"], ref["loss_critic"] + 0.001 * sum_sq(critic))
        assert out["lagrange_multiplier"].item() == 0.0

    @pytest.mark.parametrize(
        "multiplier, combine",
        [
            (LagrangeMultiplier(init=0.7), lambda a, c, lam: (a - lam * c) / (1 + lam)),
            (LagrangeMultiplier(init=0.7, sum_norm=False), lambda a, c, lam: a - lam * c),
            (PIDLagrangeMultiplier(init=0.4), lambda a, c, lam: (a - lam * c) / (1 + lam)),
            (PIDLagrangeMultiplier(init=0.4, diff_norm=True), lambda a, c, lam: (1 - lam) * a - lam * c),
        ],
        ids=["lagrange_sum_norm", "lagrange_no_norm", "pid_sum_norm", "pid_diff_norm"],
    )
    def test_positive_multiplier_equals_clip_ppo_on_combined_advantage(self, multiplier, combine):
        actor, critic, cost_critic = make_modules()
        loss = PPOLagLoss(actor, critic, cost_critic, multiplier)
        data = make_batch(actor)
        out = loss(data)
        lam = multiplier.value.float()
        assert lam.item() > 0
        expected_adv = combine(data["advantage"], data["cost_advantage"], lam)
        ref = clip_ppo_reference(actor, critic, data, expected_adv)
        torch.testing.assert_close(out["loss_objective"], ref["loss_objective"])
        torch.testing.assert_close(out["clip_fraction"], ref["clip_fraction"])
        torch.testing.assert_close(out["lagrange_multiplier"], lam)
        # and the multiplier matters: the reward-only objective is different
        plain = clip_ppo_reference(actor, critic, data, data["advantage"])
        assert not torch.allclose(out["loss_objective"], plain["loss_objective"])

    @pytest.mark.parametrize(
        "options",
        [dict(entropy_coeff=0.01), dict(delay_actor=True), dict(max_importance_ratio=1.5),
         dict(clip_epsilon=(0.1, 0.3)), dict(functional=False, entropy_coeff=0.02)],
        ids=["entropy", "delay_actor", "max_importance_ratio", "asymmetric_clip", "not_functional"],
    )
    @pytest.mark.filterwarnings("ignore:No target network updater")  # delay_actor's target stays fixed here
    def test_torchrl_options_give_clip_ppo_numbers(self, options):
        """The ratio, entropy and diagnostics (computed by the loss itself) are ClipPPOLoss's, bit for bit."""
        actor, critic, cost_critic = make_modules()
        loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.0), **options)
        reference = ClipPPOLoss(actor, critic, loss_critic_type="l2", entropy_bonus="entropy_coeff" in options,
                                **options)
        data = make_batch(actor)
        with torch.no_grad():  # the actor moves on from its target (delay_actor's proximal policy)
            for p in actor.parameters():
                p.add_(0.05)
        out, ref = loss(data), reference(data.clone())
        keys = ["loss_objective", "clip_fraction", "kl_approx", "ESS", "max_ratio", "mean_ratio"]
        if "entropy_coeff" in options:
            keys += ["entropy", "loss_entropy"]
        for key in keys:
            torch.testing.assert_close(out[key], ref[key], rtol=0, atol=0, msg=key)

    @pytest.mark.parametrize(
        "options, error",
        [(dict(normalize_advantage=True), ValueError), (dict(advantage_norm=PopArtValueNorm()), ValueError),
         (dict(entropy_coeff={"action": 0.01}), TypeError)],
        ids=["normalize_advantage", "advantage_norm", "per_head_entropy_coeff"],
    )
    def test_refuses_per_minibatch_normalisation_and_per_head_entropy(self, options, error):
        actor, critic, cost_critic = make_modules()
        with pytest.raises(error, match="normalises them once per batch|composite"):
            PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(), **options)

    def test_cost_critic_loss(self):
        actor, critic, cost_critic = make_modules()
        loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier())
        data = make_batch(actor)
        out = loss(data)
        pred = cost_critic(data.clone())["cost_value"]
        expected = (pred - data["cost_value_target"]).pow(2).mean() + 0.001 * sum_sq(cost_critic)
        torch.testing.assert_close(out["loss_cost_critic"], expected)
        no_l2 = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(), critic_l2_coeff=None)(data)
        mse = (pred - data["cost_value_target"]).pow(2).mean()
        torch.testing.assert_close(no_l2["loss_cost_critic"], mse)

    def test_reads_but_never_updates_the_multiplier(self):
        actor, critic, cost_critic = make_modules()
        multiplier = LagrangeMultiplier()
        loss = PPOLagLoss(actor, critic, cost_critic, multiplier)
        data = make_batch(actor)
        before = {k: v.clone() for k, v in multiplier.state_dict().items()}
        out = loss(data)
        sum(out[k] for k in out.keys() if k.startswith("loss_")).backward()
        for key, value in multiplier.state_dict().items():
            torch.testing.assert_close(value, before[key], rtol=0, atol=0)
        for _ in range(3):
            multiplier.update(80.0)  # the trainer's job
        torch.testing.assert_close(loss(data)["lagrange_multiplier"], multiplier.value)

    def test_input_is_not_modified(self):
        actor, critic, cost_critic = make_modules()
        loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.5))
        data = make_batch(actor)
        snapshot = data.clone()
        loss(data)
        assert set(data.keys(True)) == set(snapshot.keys(True))
        for key in snapshot.keys(True, True):
            torch.testing.assert_close(data[key], snapshot[key], rtol=0, atol=0)

    @pytest.mark.parametrize(
        "new_key", ["my_cost_adv", ("agents", "cost_advantage")], ids=["flat", "nested"]
    )
    def test_set_keys_remaps_cost_keys(self, new_key):
        actor, critic, cost_critic = make_modules()
        data = make_batch(actor)
        expected = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.5))(data)
        loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.5))
        loss.set_keys(cost_advantage=new_key, cost_value_target="c_target")
        assert loss.tensor_keys.cost_advantage == new_key
        assert new_key in loss.in_keys
        renamed = data.clone()
        renamed.set(new_key, renamed.pop("cost_advantage"))
        renamed.set("c_target", renamed.pop("cost_value_target"))
        out = loss(renamed)
        for key in LOSS_KEYS:
            torch.testing.assert_close(out[key], expected[key])
        with pytest.raises(KeyError, match="c_target"):
            loss(data.exclude("cost_advantage").set(new_key, data["cost_advantage"]))

    def test_missing_cost_advantage_raises(self):
        actor, critic, cost_critic = make_modules()
        loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier())
        with pytest.raises(KeyError, match="cost_advantage"):
            loss(make_batch(actor).exclude("cost_advantage"))

    def test_advantage_shape_mismatch_raises(self):
        actor, critic, cost_critic = make_modules()
        loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier())
        data = make_batch(actor)
        data["cost_advantage"] = data["cost_advantage"].squeeze(-1)
        with pytest.raises(ValueError, match="must match"):
            loss(data)

    def test_rejects_non_multiplier(self):
        actor, critic, cost_critic = make_modules()
        with pytest.raises(TypeError, match="Multiplier"):
            PPOLagLoss(actor, critic, cost_critic, 0.5)

    def test_cppo_pid_is_ppo_lag_with_pid_multiplier(self):
        actor, critic, cost_critic = make_modules()
        pid = PIDLagrangeMultiplier()
        assert isinstance(pid, Multiplier)
        loss = PPOLagLoss(actor, critic, cost_critic, pid)
        pid.update(60.0)
        out = loss(make_batch(actor))
        assert out["lagrange_multiplier"].item() == pytest.approx(pid.value.item(), rel=1e-6)

    def test_entropy_bonus_and_value_clipping(self):
        actor, critic, cost_critic = make_modules()
        loss = PPOLagLoss(
            actor, critic, cost_critic, LagrangeMultiplier(), entropy_coeff=0.01, clip_value=0.2
        )
        out = loss(make_batch(actor))
        assert "loss_entropy" in out.keys() and "entropy" in out.keys()
        assert 0.0 <= out["cost_value_clip_fraction"].item() <= 1.0
        assert "value_clip_fraction" in out.keys()

    def test_cost_value_estimator_follows_keys(self):
        actor, critic, cost_critic = make_modules()
        loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier())
        loss.set_keys(cost="my_cost", cost_advantage="my_cadv")
        gae = loss.make_cost_value_estimator(gamma=0.9, lmbda=0.8)
        keys = gae.tensor_keys
        assert (keys.reward, keys.value, keys.advantage) == ("my_cost", "cost_value", "my_cadv")
        assert float(gae.gamma) == pytest.approx(0.9)

    def test_cost_value_estimator_with_nested_keys(self):
        """A cost critic writing ``("agents", "cost_value")``, the loss remapped to the group's keys."""
        actor, critic, _ = make_modules()
        torch.manual_seed(4)
        cost_critic = TensorDictModule(nn.Linear(OBS_DIM, 1), in_keys=[("agents", "observation")],
                                       out_keys=[("agents", "cost_value")])
        loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier())
        group = {name: ("agents", name) for name in
                 ("cost", "cost_value", "cost_advantage", "cost_value_target", "done", "terminated")}
        loss.set_keys(**group)
        gae = loss.make_cost_value_estimator(gamma=0.9, lmbda=0.8)
        keys = gae.tensor_keys
        assert (keys.reward, keys.value, keys.advantage, keys.done) == (
            group["cost"], group["cost_value"], group["cost_advantage"], group["done"])
        n, t, agents = 2, 5, 3
        agent_td = TensorDict(observation=torch.randn(n, t, agents, OBS_DIM), batch_size=[n, t, agents])
        next_td = TensorDict(observation=torch.randn(n, t, agents, OBS_DIM), cost=torch.rand(n, t, agents, 1),
                             done=torch.zeros(n, t, agents, 1, dtype=torch.bool),
                             terminated=torch.zeros(n, t, agents, 1, dtype=torch.bool), batch_size=[n, t, agents])
        data = TensorDict({"agents": agent_td, "next": {"agents": next_td}}, batch_size=[n, t])
        with torch.no_grad():
            gae(data)
            loss.cost_value_estimator(data.clone())
        assert data["agents", "cost_advantage"].shape == (n, t, agents, 1)
        assert loss.cost_value_estimator.tensor_keys.value == ("agents", "cost_value")



class TestGaussianKL:
    def test_matches_torch_kl(self):
        gen = torch.Generator().manual_seed(0)
        loc_old, loc_new = torch.randn(2, 10, ACT_DIM, generator=gen)
        scale_old, scale_new = torch.rand(2, 10, ACT_DIM, generator=gen) + 0.2
        expected = D.kl_divergence(D.Normal(loc_old, scale_old), D.Normal(loc_new, scale_new)).sum(-1)
        got = gaussian_kl(loc_old, scale_old, loc_new, scale_new)
        assert got.shape == torch.Size([10])
        torch.testing.assert_close(got, expected)

    def test_zero_for_identical_and_broadcast_scale(self):
        loc = torch.randn(4, ACT_DIM)
        scale = torch.ones(ACT_DIM)  # state-independent scale broadcasts
        torch.testing.assert_close(gaussian_kl(loc, scale, loc, scale), torch.zeros(4))
