"""Tests of the first-order SafePO losses (PPO, PG, FOCOPS, CUP) on synthetic batches."""
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
from torchrl.modules import IndependentNormal, MLP, ProbabilisticActor, ValueOperator  # noqa: E402
from torchrl.objectives import ClipPPOLoss  # noqa: E402

from sg_torchrl.objectives import (  # noqa: E402
    CUPLoss,
    FOCOPSLoss,
    LagrangeMultiplier,
    NoMultiplier,
    PGLoss,
    PPOLagLoss,
)

OBS_DIM, ACT_DIM, BATCH = 5, 2, 32
CRITIC_KEYS = ("loss_critic", "loss_cost_critic")


# --------------------------------------------------------------------------- helpers
def make_actor(seed: int = 0) -> ProbabilisticActor:
    torch.manual_seed(seed)
    net = nn.Sequential(
        MLP(in_features=OBS_DIM, out_features=ACT_DIM, num_cells=[16], activation_class=nn.Tanh),
        AddStateIndependentNormalScale(ACT_DIM, scale_mapping="exp"),
    )
    return ProbabilisticActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=IndependentNormal,
        return_log_prob=True,
    )


def make_critic(out_key: str, seed: int) -> ValueOperator:
    torch.manual_seed(seed)
    mlp = MLP(in_features=OBS_DIM, out_features=1, num_cells=[16], activation_class=nn.Tanh)
    return ValueOperator(mlp, in_keys=["observation"], out_keys=[out_key])


def make_modules():
    return make_actor(), make_critic("state_value", 1), make_critic("cost_value", 2)


def make_batch(actor: ProbabilisticActor, size: int = BATCH, seed: int = 3, noise: float = 0.4) -> TensorDict:
    """Rollout-like batch; ``noise`` perturbs the stored log-probs so that ratios differ from 1."""
    gen = torch.Generator().manual_seed(seed)
    td = TensorDict(observation=torch.randn(size, OBS_DIM, generator=gen), batch_size=[size])
    torch.manual_seed(seed)
    with torch.no_grad(), set_interaction_type(InteractionType.RANDOM):
        td = actor(td)
    td["action_log_prob"] = td["action_log_prob"] + noise * torch.randn(size, generator=gen)
    for key in ("advantage", "value_target", "cost_advantage", "cost_value_target"):
        td[key] = torch.randn(size, 1, generator=gen)
    return td


def current_policy(actor: ProbabilisticActor, data: TensorDict):
    """Differentiable loc, scale and log-prob of the stored actions under the current actor."""
    td = actor[0](data.select("observation").clone())
    loc, scale = td["loc"], td["scale"]
    log_prob = D.Normal(loc, scale).log_prob(data["action"]).sum(-1, keepdim=True)
    return loc, scale, log_prob


def kl_current_to(loc, scale, other_loc, other_scale):
    """Independent reference: torch's KL(N(loc, scale) || N(other)), summed over actions, [B, 1]."""
    kl = D.kl_divergence(D.Normal(loc, scale), D.Normal(other_loc, other_scale))
    return kl.sum(-1, keepdim=True)


def actor_grads(actor: nn.Module, scalar: torch.Tensor) -> list[torch.Tensor]:
    params = list(actor.parameters())
    grads = torch.autograd.grad(scalar, params, allow_unused=True)
    return [torch.zeros_like(p) if g is None else g for p, g in zip(params, grads)]


def assert_grads_close(got, expected, **kw):
    for g, e in zip(got, expected):
        torch.testing.assert_close(g, e, **kw)


def loss_terms(out) -> list[str]:
    return sorted(k for k in out.keys() if k.startswith("loss_"))


def count_actor_calls(loss, data) -> int:
    calls = []
    handle = loss.actor_network[0].module.register_forward_hook(lambda *_: calls.append(1))
    try:
        loss(data)
    finally:
        handle.remove()
    return len(calls)


# --------------------------------------------------------------------------- PPO
class TestPPO:
    def test_no_multiplier_is_lagrangian_ppo_at_zero_and_ignores_cost_advantage(self):
        actor, critic, cost_critic = make_modules()
        data = make_batch(actor)
        ppo = PPOLagLoss(actor, critic, cost_critic, NoMultiplier())
        out = ppo(data)
        ref = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.0))(data)
        for key in ("loss_objective", *CRITIC_KEYS, "clip_fraction"):
            torch.testing.assert_close(out[key], ref[key])
        assert out["lagrange_multiplier"].item() == 0.0
        shifted = data.clone()
        shifted["cost_advantage"] = 100.0 * torch.randn(BATCH, 1)
        torch.testing.assert_close(ppo(shifted)["loss_objective"], out["loss_objective"], rtol=0, atol=0)

    def test_cost_critic_still_learned_and_logged(self):
        actor, critic, cost_critic = make_modules()
        out = PPOLagLoss(actor, critic, cost_critic, NoMultiplier())(make_batch(actor))
        assert torch.isfinite(out["loss_cost_critic"])
        sum(out[k] for k in loss_terms(out)).backward()
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in cost_critic.parameters())

    def test_critic_losses_match_forward(self):
        actor, critic, cost_critic = make_modules()
        loss = PPOLagLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.3))
        data = make_batch(actor)
        out, critics = loss(data), loss.critic_losses(data.exclude("advantage", "cost_advantage"))
        assert loss_terms(critics) == sorted(CRITIC_KEYS)
        for key in CRITIC_KEYS:
            torch.testing.assert_close(critics[key], out[key])


# --------------------------------------------------------------------------- PG
class TestPGLoss:
    def test_keys_shapes_and_gradients(self):
        actor, critic, cost_critic = make_modules()
        loss = PGLoss(actor, critic, cost_critic)
        assert isinstance(loss.multiplier, NoMultiplier)
        out = loss(make_batch(actor))
        assert loss_terms(out) == ["loss_cost_critic", "loss_critic", "loss_objective"]
        assert "clip_fraction" not in out.keys() and "clip_fraction" not in loss.out_keys
        assert set(loss.out_keys) <= set(out.keys())
        for key in loss_terms(out):
            assert out[key].shape == torch.Size([]) and torch.isfinite(out[key])
        sum(out[k] for k in loss_terms(out)).backward()
        for module in (actor, critic, cost_critic):
            for p in module.parameters():
                assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0

    @pytest.mark.parametrize("multiplier", [None, LagrangeMultiplier(init=0.5)], ids=["none", "lagrange"])
    def test_value_is_minus_mean_ratio_times_advantage(self, multiplier):
        actor, critic, cost_critic = make_modules()
        data = make_batch(actor)
        loss = PGLoss(actor, critic, cost_critic, multiplier)
        _, _, log_prob = current_policy(actor, data)
        ratio = (log_prob - data["action_log_prob"].unsqueeze(-1)).exp()
        lam = 0.0 if multiplier is None else multiplier.value.item()
        advantage = (data["advantage"] - lam * data["cost_advantage"]) / (1 + lam)
        torch.testing.assert_close(loss(data)["loss_objective"], -(ratio * advantage).mean())

    def test_gradient_where_the_clipped_objective_has_none(self):
        actor, critic, cost_critic = make_modules()
        data = make_batch(actor, noise=0.0)
        _, _, log_prob = current_policy(actor, data)
        # every ratio is e^0.5 ~ 1.65 > 1 + clip with a positive advantage: PPO's min picks the
        # constant clipped branch, PG keeps the gradient.
        data["action_log_prob"] = log_prob.detach().squeeze(-1) - 0.5
        data["advantage"] = data["advantage"].abs() + 0.1
        ppo = PPOLagLoss(actor, critic, cost_critic, NoMultiplier())
        assert ppo(data)["clip_fraction"].item() == 1.0
        ppo_grads = actor_grads(actor, ppo(data)["loss_objective"])
        assert all(g.abs().sum() == 0 for g in ppo_grads)
        pg_grads = actor_grads(actor, PGLoss(actor, critic, cost_critic)(data)["loss_objective"])
        assert sum(g.abs().sum() for g in pg_grads) > 0

    def test_equals_ppo_while_no_ratio_is_clipped(self):
        actor, critic, cost_critic = make_modules()
        data = make_batch(actor, noise=0.0)
        data["action_log_prob"] = current_policy(actor, data)[2].detach().squeeze(-1)  # ratio 1
        ppo = PPOLagLoss(actor, critic, cost_critic, NoMultiplier())(data)
        pg = PGLoss(actor, critic, cost_critic)(data)
        assert ppo["clip_fraction"].item() == 0.0
        for key in ("loss_objective", *CRITIC_KEYS):
            torch.testing.assert_close(pg[key], ppo[key])
        assert_grads_close(
            actor_grads(actor, pg["loss_objective"]), actor_grads(actor, ppo["loss_objective"])
        )


# --------------------------------------------------------------------------- FOCOPS
def focops_batch(actor: ProbabilisticActor, size: int = 4) -> TensorDict:
    """Tiny batch whose stored (rollout) policy differs from the current one; the last sample's
    stored mean is far away, so its KL exceeds the 0.02 target."""
    data = make_batch(actor, size=size, seed=7)
    offsets = torch.tensor([[0.05, -0.05], [0.1, 0.0], [0.0, 0.08], [1.0, -1.0]])[:size]
    data["loc"] = data["loc"] + offsets
    data["scale"] = data["scale"] * torch.tensor([1.05, 0.97])
    return data


class TestFOCOPSLoss:
    def test_keys_shapes_and_gradients(self):
        actor, critic, cost_critic = make_modules()
        loss = FOCOPSLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.5, upper_bound=2.0))
        data = make_batch(actor)
        data["loc"] = data["loc"] + 0.05
        out = loss(data)
        assert loss_terms(out) == ["loss_cost_critic", "loss_critic", "loss_objective"]
        assert set(loss.out_keys) <= set(out.keys())
        assert {"kl", "kl_mask_fraction"} <= set(out.keys()) and "clip_fraction" not in out.keys()
        assert {"loc", "scale"} <= set(loss.in_keys)
        for key in loss_terms(out):
            assert out[key].shape == torch.Size([]) and torch.isfinite(out[key])
        sum(out[k] for k in loss_terms(out)).backward()
        for module in (actor, critic, cost_critic):
            for p in module.parameters():
                assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
        assert count_actor_calls(loss, data) == 1  # ratio and KL from one actor evaluation

    def test_hand_computed_value(self):
        actor, critic, cost_critic = make_modules()
        multiplier = LagrangeMultiplier(init=0.5, upper_bound=2.0)
        data = focops_batch(actor)
        out = FOCOPSLoss(actor, critic, cost_critic, multiplier)(data)
        loc, scale, log_prob = current_policy(actor, data)
        kl = kl_current_to(loc, scale, data["loc"], data["scale"]).squeeze(-1).tolist()
        ratio = (log_prob.squeeze(-1) - data["action_log_prob"]).exp().tolist()
        nu = multiplier.value.item()
        terms = []
        for i in range(4):
            adv = (data["advantage"][i, 0].item() - nu * data["cost_advantage"][i, 0].item()) / (1 + nu)
            inside = 1.0 if kl[i] <= 0.02 else 0.0
            terms.append((kl[i] - ratio[i] * adv / 1.5) * inside)
        assert [k <= 0.02 for k in kl] == [True, True, True, False]
        assert out["loss_objective"].item() == pytest.approx(sum(terms) / 4, rel=1e-5)
        assert out["kl"].item() == pytest.approx(sum(kl) / 4, rel=1e-5)
        assert out["kl_mask_fraction"].item() == 0.75

    def test_samples_outside_the_trust_region_contribute_nothing(self):
        actor, critic, cost_critic = make_modules()
        loss = FOCOPSLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.5))
        data = focops_batch(actor)
        changed = data.clone()
        changed["advantage"][3] = 50.0
        changed["cost_advantage"][3] = -50.0
        changed["action_log_prob"][3] = -20.0
        out, out_changed = loss(data), loss(changed)
        torch.testing.assert_close(out_changed["loss_objective"], out["loss_objective"])
        assert_grads_close(
            actor_grads(actor, out_changed["loss_objective"]), actor_grads(actor, out["loss_objective"])
        )

    def test_safepo_broadcast_option(self):
        actor, critic, cost_critic = make_modules()
        multiplier = LagrangeMultiplier(init=0.5)
        data = focops_batch(actor)
        quirk = FOCOPSLoss(actor, critic, cost_critic, multiplier, safepo_broadcast=True)(data)
        paper = FOCOPSLoss(actor, critic, cost_critic, multiplier)(data)
        # SafePO's literal expression: KL of shape (B, 1) against ratio * A of shape (B,)
        loc, scale, log_prob = current_policy(actor, data)
        kl = kl_current_to(loc, scale, data["loc"], data["scale"])  # (B, 1)
        ratio = (log_prob.squeeze(-1) - data["action_log_prob"]).exp()  # (B,)
        adv = multiplier.combine(data["advantage"], data["cost_advantage"]).squeeze(-1)
        mask = (kl <= 0.02).float()
        literal = ((kl - ratio * adv / 1.5) * mask).mean()
        torch.testing.assert_close(quirk["loss_objective"], literal)
        closed_form = (kl * mask).mean() - mask.mean() * (ratio * adv).mean() / 1.5
        torch.testing.assert_close(quirk["loss_objective"], closed_form)
        assert_grads_close(
            actor_grads(actor, quirk["loss_objective"]), actor_grads(actor, literal), rtol=1e-4, atol=1e-6
        )
        assert not torch.allclose(quirk["loss_objective"], paper["loss_objective"])

    def test_safepo_broadcast_is_a_config_switch_of_focops_alone(self):
        from sg_torchrl.train import ALGORITHMS, TrainConfig

        actor, critic, cost_critic = make_modules()
        for switch in (False, True):  # the engine builds the loss (and its seed-batched surrogate) from the row
            cfg = TrainConfig(algo="focops", focops_safepo_broadcast=switch)
            loss = ALGORITHMS["focops"].make_loss(actor, critic, cost_critic, LagrangeMultiplier(init=0.5), cfg)
            assert loss.safepo_broadcast is switch and loss.surrogate.safepo_broadcast is switch
        with pytest.raises(ValueError, match="focops_safepo_broadcast is an option of focops, not of 'ppo_lag'"):
            TrainConfig(algo="ppo_lag", focops_safepo_broadcast=True)

    def test_gradient_at_the_old_policy_is_the_scaled_policy_gradient(self):
        actor, critic, cost_critic = make_modules()
        multiplier = LagrangeMultiplier(init=0.5)
        data = make_batch(actor, noise=0.0)
        loc, scale, log_prob = current_policy(actor, data)
        data["loc"], data["scale"] = loc.detach(), scale.detach()
        data["action_log_prob"] = log_prob.detach().squeeze(-1)  # pi_theta == pi_old
        out = FOCOPSLoss(actor, critic, cost_critic, multiplier)(data)
        assert out["kl"].item() == pytest.approx(0.0, abs=1e-7)
        assert out["kl_mask_fraction"].item() == 1.0
        ratio = (log_prob - data["action_log_prob"].unsqueeze(-1)).exp()
        advantage = multiplier.combine(data["advantage"], data["cost_advantage"])
        expected = [-g / 1.5 for g in actor_grads(actor, (ratio * advantage).mean())]
        assert_grads_close(actor_grads(actor, out["loss_objective"]), expected, rtol=1e-4, atol=1e-6)

    def test_set_keys_remaps_the_stored_policy(self):
        actor, critic, cost_critic = make_modules()
        data = focops_batch(actor)
        expected = FOCOPSLoss(actor, critic, cost_critic, LagrangeMultiplier())(data)
        loss = FOCOPSLoss(actor, critic, cost_critic, LagrangeMultiplier())
        loss.set_keys(old_loc="rollout_loc", old_scale="rollout_scale")
        assert {"rollout_loc", "rollout_scale"} <= set(loss.in_keys)
        renamed = data.clone()
        renamed["rollout_loc"], renamed["rollout_scale"] = renamed.pop("loc"), renamed.pop("scale")
        torch.testing.assert_close(loss(renamed)["loss_objective"], expected["loss_objective"])
        with pytest.raises(KeyError, match="rollout_loc"):
            loss(data)

    def test_rejects_bad_hyper_parameters(self):
        actor, critic, cost_critic = make_modules()
        with pytest.raises(ValueError, match="temperature"):
            FOCOPSLoss(actor, critic, cost_critic, LagrangeMultiplier(), temperature=0.0)
        with pytest.raises(ValueError, match="target_kl"):
            FOCOPSLoss(actor, critic, cost_critic, LagrangeMultiplier(), target_kl=-1.0)


# --------------------------------------------------------------------------- CUP
def cup_batch(actor: ProbabilisticActor, size: int = BATCH) -> TensorDict:
    data = make_batch(actor, size=size)
    data["stage1_loc"] = data["loc"] + 0.1 * torch.randn(size, ACT_DIM, generator=torch.Generator().manual_seed(1))
    data["stage1_scale"] = data["scale"] * 0.9
    return data


class TestCUPLoss:
    def test_projection_coefficient(self):
        actor, critic, cost_critic = make_modules()
        assert CUPLoss(actor, critic, cost_critic, LagrangeMultiplier()).cost_coeff.item() == pytest.approx(5.95)
        other = CUPLoss(actor, critic, cost_critic, LagrangeMultiplier(), gamma=0.9, cup_lambda=0.5)
        assert other.cost_coeff.item() == pytest.approx((1 - 0.45) / 0.1)
        with pytest.raises(ValueError, match="gamma"):
            CUPLoss(actor, critic, cost_critic, LagrangeMultiplier(), gamma=1.0)

    def test_stage_two_keys_shapes_and_actor_only_gradient(self):
        actor, critic, cost_critic = make_modules()
        loss = CUPLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.1, upper_bound=0.2))
        data = cup_batch(actor)
        out = loss(data)
        assert loss_terms(out) == ["loss_objective"]
        assert set(loss.out_keys) == set(out.keys())
        assert out["loss_objective"].shape == torch.Size([]) and torch.isfinite(out["loss_objective"])
        assert set(loss.in_keys) == {
            "observation", "action", "action_log_prob", "cost_advantage", "stage1_loc", "stage1_scale"
        }
        out["loss_objective"].backward()
        assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in actor.parameters())
        assert sum(p.grad.abs().sum() for p in actor.parameters()) > 0
        assert all(p.grad is None for m in (critic, cost_critic) for p in m.parameters())
        assert count_actor_calls(loss, data) == 1

    def test_hand_computed_value(self):
        actor, critic, cost_critic = make_modules()
        multiplier = LagrangeMultiplier(init=0.15)
        data = cup_batch(actor, size=4)
        out = CUPLoss(actor, critic, cost_critic, multiplier)(data)
        loc, scale, log_prob = current_policy(actor, data)
        kl = kl_current_to(loc, scale, data["stage1_loc"], data["stage1_scale"]).squeeze(-1).tolist()
        ratio = (log_prob.squeeze(-1) - data["action_log_prob"]).exp().tolist()
        nu, c = multiplier.value.item(), (1 - 0.99 * 0.95) / (1 - 0.99)
        terms = [nu * c * ratio[i] * data["cost_advantage"][i, 0].item() + kl[i] for i in range(4)]
        assert out["loss_objective"].item() == pytest.approx(sum(terms) / 4, rel=1e-5)
        assert out["kl"].item() == pytest.approx(sum(kl) / 4, rel=1e-5)
        assert out["lagrange_multiplier"].item() == pytest.approx(nu)
        # SafePO's (B, 1) + (B,) broadcast has the same mean: no quirk option needed
        literal = (nu * c * torch.tensor(ratio) * data["cost_advantage"].squeeze(-1) + torch.tensor(kl)[:, None]).mean()
        assert out["loss_objective"].item() == pytest.approx(literal.item(), rel=1e-5)

    def test_gradient_pushes_the_cost_surrogate_down(self):
        actor, critic, cost_critic = make_modules()
        loss = CUPLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.2))
        data = make_batch(actor, noise=0.0)
        loc, scale, log_prob = current_policy(actor, data)
        data["stage1_loc"], data["stage1_scale"] = loc.detach(), scale.detach()

        def cost_surrogate() -> float:
            with torch.no_grad():
                lp = current_policy(actor, data)[2]
                return ((lp - data["action_log_prob"].unsqueeze(-1)).exp() * data["cost_advantage"]).mean().item()

        before = cost_surrogate()
        optimizer = torch.optim.SGD(actor.parameters(), lr=0.05)
        for _ in range(5):
            optimizer.zero_grad()
            loss(data)["loss_objective"].backward()
            optimizer.step()
        assert cost_surrogate() < before

    @pytest.mark.parametrize("functional", [True, False])
    def test_reward_stage_is_ppo_sharing_the_networks(self, functional):
        actor, critic, cost_critic = make_modules()
        loss = CUPLoss(actor, critic, cost_critic, LagrangeMultiplier(init=0.1), functional=functional)
        stage = loss.reward_stage
        assert type(stage) is PPOLagLoss and isinstance(stage.multiplier, NoMultiplier)
        module_ids = {id(p) for m in (actor, critic, cost_critic) for p in m.parameters()}
        assert {id(p) for p in stage.parameters()} == module_ids
        assert {id(p) for p in loss.parameters()} == module_ids
        data = cup_batch(actor)
        out = stage(data)
        ref = ClipPPOLoss(actor, critic, entropy_bonus=False, loss_critic_type="l2")(data.clone())
        for key in ("loss_objective", "clip_fraction"):
            torch.testing.assert_close(out[key], ref[key])
        sum(out[k] for k in loss_terms(out)).backward()
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in actor.parameters())

    def test_zero_multiplier_at_the_stage_one_policy_reduces_to_ppo(self):
        # nu = 0 and pi_theta = pi_stage1: the projection loss and its gradient vanish, so CUP's
        # epoch is its PPO stage alone.
        actor, critic, cost_critic = make_modules()
        loss = CUPLoss(actor, critic, cost_critic, NoMultiplier())
        data = make_batch(actor)
        loc, scale, _ = current_policy(actor, data)
        data["stage1_loc"], data["stage1_scale"] = loc.detach(), scale.detach()
        out = loss(data)
        assert out["loss_objective"].item() == pytest.approx(0.0, abs=1e-7)
        assert all(g.abs().max() < 1e-6 for g in actor_grads(actor, out["loss_objective"]))

    def test_missing_stage_one_policy_raises(self):
        actor, critic, cost_critic = make_modules()
        loss = CUPLoss(actor, critic, cost_critic, LagrangeMultiplier())
        with pytest.raises(KeyError, match="stage1_loc"):
            loss(make_batch(actor))
