"""Tests of the trust-region steps: the CPO / PCPO step maths against an independent QP solver, and
NPG / TRPO / CPO / PCPO steps on a tiny actor with synthetic data."""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

torch.set_num_threads(1)

from scipy.optimize import minimize  # noqa: E402
from tensordict import TensorDict  # noqa: E402
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule  # noqa: E402
from torch import nn  # noqa: E402
from torchrl.modules import IndependentNormal, MLP, ProbabilisticActor, TanhNormal  # noqa: E402

from sg_torchrl.objectives import (  # noqa: E402
    cpo_direction,
    CPOStep,
    flat_params,
    gaussian_kl,
    linearise,
    NaturalPolicyStep,
    pcpo_direction,
    PCPOStep,
    TRPOStep,
    TrustRegionLoss,
)
from sg_torchrl.objectives.kl import diagonal_gaussian_params, kl_to_stored_gaussian  # noqa: E402

DELTA = 0.01
N = 6  # size of the random QPs
BASE_METRICS = {
    "Misc/Alpha", "Misc/FinalStepNorm", "Misc/xHx", "Misc/gradient_norm", "Misc/H_inv_g",
    "Misc/AcceptanceStep", "Train/KL", "Loss/Loss_actor",
}


# =========================================================================== QP helpers
def random_problem(seed: int, orientation: str = "random") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(H, g, b) in float64: H SPD, b random or (anti-)aligned with g to fix the sign of r."""
    gen = torch.Generator().manual_seed(seed)
    m = torch.randn(N, N, generator=gen, dtype=torch.float64)
    h = m @ m.T / N + 0.3 * torch.eye(N, dtype=torch.float64)
    g = torch.randn(N, generator=gen, dtype=torch.float64)
    noise = 0.5 * torch.randn(N, generator=gen, dtype=torch.float64)
    b = {"random": 2.0 * noise, "aligned": g + noise, "opposed": -g + noise}[orientation]
    return h, g, b


def exact_lin(h: torch.Tensor, g: torch.Tensor, b: torch.Tensor | None):
    # eps=0 and enough iterations: CG is exact on these 6x6 systems, so the test isolates the dual
    return linearise(h, g, b, cg_iters=4 * N, residual_tol=1e-14, eps=0.0)


def c_for(h: torch.Tensor, b: torch.Tensor, k: float) -> float:
    """c = k * sqrt(2 delta s): |k| < 1 means the constraint boundary cuts the trust region."""
    s = float(b @ torch.linalg.solve(h, b))
    return k * math.sqrt(2 * DELTA * s)


def solve_qp_scipy(h: torch.Tensor, g: torch.Tensor, b: torch.Tensor, c: float) -> np.ndarray:
    """max g.d  s.t. 0.5 d'Hd <= delta, c + b.d <= 0, by SLSQP from several starts (independent path)."""
    H, G, Bv = h.numpy(), g.numpy(), b.numpy()
    cons = [
        {"type": "ineq", "fun": lambda d: DELTA - 0.5 * d @ H @ d, "jac": lambda d: -H @ d},
        {"type": "ineq", "fun": lambda d: -(c + Bv @ d), "jac": lambda d: -Bv},
    ]
    best = None
    for start in (np.zeros(N), -0.05 * Bv, 0.05 * G):
        res = minimize(lambda d: -G @ d, start, jac=lambda d: -G, constraints=cons, method="SLSQP",
                       options={"ftol": 1e-12, "maxiter": 1000})
        feasible = DELTA - 0.5 * res.x @ H @ res.x > -1e-9 and c + Bv @ res.x < 1e-9
        if res.success and feasible and (best is None or G @ res.x > G @ best):
            best = res.x
    assert best is not None, "SLSQP found no feasible solution"
    return best


def assert_kkt(h, g, b, c, d, tol=1e-7):
    """d solves the convex QP: feasible, g = lam H d + nu b with lam, nu >= 0, complementary slackness."""
    quad, lin = float(0.5 * d @ h @ d), float(c + b @ d)
    assert quad <= DELTA + tol and lin <= tol
    coeffs = torch.linalg.lstsq(torch.stack([h @ d, b], dim=1), g.unsqueeze(1)).solution.squeeze(1)
    lam, nu = float(coeffs[0]), float(coeffs[1])
    torch.testing.assert_close(lam * (h @ d) + nu * b, g, rtol=1e-6, atol=1e-7)
    assert lam >= -tol and nu >= -tol
    assert abs(lam * (quad - DELTA)) < 1e-6 and abs(nu * lin) < 1e-6


def trpo_direction(h, g):
    x = torch.linalg.solve(h, g)
    return math.sqrt(2 * DELTA / float(x @ h @ x)) * x


# =========================================================================== CPO maths
# (k, orientation, expected case): k sets c = k sqrt(2 delta s); orientations cover r > 0 and
# r < 0, including r / c < 0, where SafePO's projection intervals are empty.
QP_CASES = [
    (-0.9, "random", 2), (-0.5, "random", 2), (-0.1, "random", 2),
    (-0.5, "aligned", 2), (-0.2, "aligned", 2), (-0.5, "opposed", 2),
    (0.0, "random", 1), (0.3, "random", 1), (0.9, "random", 1),
    (0.3, "aligned", 1), (0.5, "opposed", 1), (0.0, "opposed", 1),
]


class TestCPODirection:
    @pytest.mark.parametrize("k,orientation,case", QP_CASES)
    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_dual_solution_equals_the_qp_solution(self, k, orientation, case, seed):
        h, g, b = random_problem(seed, orientation)
        c = c_for(h, b, k)
        sol = cpo_direction(exact_lin(h, g, b), c, DELTA)
        assert sol.case == case
        d = sol.direction
        assert_kkt(h, g, b, c, d)
        reference = torch.from_numpy(solve_qp_scipy(h, g, b, c))
        torch.testing.assert_close(d, reference, rtol=1e-4, atol=1e-5)
        assert float(g @ d) >= float(g @ reference) - 1e-7

    @pytest.mark.parametrize("seed", range(4))
    def test_case_3_inactive_constraint_is_the_trpo_step(self, seed):
        h, g, b = random_problem(seed)
        c = c_for(h, b, -1.5)
        sol = cpo_direction(exact_lin(h, g, b), c, DELTA)
        assert sol.case == 3
        torch.testing.assert_close(sol.direction, trpo_direction(h, g))
        torch.testing.assert_close(sol.direction, torch.from_numpy(solve_qp_scipy(h, g, b, c)), rtol=1e-4, atol=1e-5)

    def test_case_4_no_cost_gradient_is_the_trpo_step(self):
        h, g, _ = random_problem(3)
        b = torch.full((N,), 1e-5, dtype=torch.float64)  # ||b||^2 <= 1e-6
        sol = cpo_direction(exact_lin(h, g, b), -1.0, DELTA)
        assert sol.case == 4
        torch.testing.assert_close(sol.direction, trpo_direction(h, g))

    @pytest.mark.parametrize("seed", range(4))
    def test_case_0_infeasible_recovery(self, seed):
        h, g, b = random_problem(seed)
        c = c_for(h, b, 1.5)
        lin = exact_lin(h, g, b)
        sol = cpo_direction(lin, c, DELTA)
        assert sol.case == 0
        p = torch.linalg.solve(h, b)
        s = float(b @ p)
        # infeasible: even the best point of the trust region violates the linearised constraint
        assert c - math.sqrt(2 * DELTA * s) > 0
        torch.testing.assert_close(sol.direction, -math.sqrt(2 * DELTA / s) * p)
        # ... and the recovery step is that point: on the boundary, minimising b.d
        assert 0.5 * float(sol.direction @ h @ sol.direction) == pytest.approx(DELTA, rel=1e-8)
        assert float(b @ sol.direction) == pytest.approx(-math.sqrt(2 * DELTA * s), rel=1e-8)

    @pytest.mark.parametrize("k,orientation,case", QP_CASES)
    def test_safepo_dual_option_follows_the_reference_formulas(self, k, orientation, case):
        """``safepo_dual=True`` is the reference's transcription of SafePO (r = g.p with the ascent g)."""
        h, g, b = random_problem(0, orientation)
        c = c_for(h, b, k)
        lin = exact_lin(h, g, b)
        q, r, s = lin.q, lin.r, lin.s
        A, B = q - r**2 / (s + 1e-8), 2 * DELTA - c**2 / (s + 1e-8)
        lam_a, lam_b, mid = math.sqrt(A / B), math.sqrt(q / (2 * DELTA)), r / (c + 1e-8)

        def clamp(v, lo, hi):  # torch.clamp: an empty interval gives its upper end
            return min(max(v, lo), hi)

        if c < 0:
            lam_a, lam_b = clamp(lam_a, 0.0, mid), clamp(lam_b, mid, math.inf)
        else:
            lam_a, lam_b = clamp(lam_a, mid, math.inf), clamp(lam_b, 0.0, mid)
        f_a = -0.5 * (A / (lam_a + 1e-8) + B * lam_a) - r * c / (s + 1e-8)
        f_b = -0.5 * (q / (lam_b + 1e-8) + 2 * DELTA * lam_b)
        lam = lam_a if f_a >= f_b else lam_b
        nu = max(lam * c - r, 0.0) / (s + 1e-8)
        expected = (lin.x - nu * lin.p) / (lam + 1e-8)
        sol = cpo_direction(lin, c, DELTA, safepo_dual=True)
        assert sol.case == case
        torch.testing.assert_close(sol.direction, expected, rtol=1e-7, atol=1e-9)

    def test_safepo_dual_does_not_solve_the_qp(self):
        h, g, b = random_problem(0, "aligned")  # r > 0 and an active constraint
        c = c_for(h, b, -0.5)
        lin = exact_lin(h, g, b)
        paper, safepo = cpo_direction(lin, c, DELTA), cpo_direction(lin, c, DELTA, safepo_dual=True)
        assert float(g @ safepo.direction) < float(g @ paper.direction) - 1e-3

    def test_needs_a_cost_gradient(self):
        h, g, _ = random_problem(0)
        with pytest.raises(ValueError, match="cost gradient"):
            cpo_direction(exact_lin(h, g, None), -1.0, DELTA)


# =========================================================================== PCPO maths
class TestPCPODirection:
    @pytest.mark.parametrize("seed", range(4))
    @pytest.mark.parametrize("k", [-0.3, 0.0, 0.5, 2.0])
    def test_projection_satisfies_the_linearised_constraint(self, seed, k):
        h, g, b = random_problem(seed, "aligned")  # r > 0: the reward step raises the cost
        c = c_for(h, b, k)
        lin = exact_lin(h, g, b)
        natural = trpo_direction(h, g)
        assert c + float(b @ natural) > 0, "the natural step must violate the constraint here"
        d = pcpo_direction(lin, c, DELTA)
        assert abs(c + float(b @ d)) < 1e-7  # projected onto the boundary c + b.d = 0
        # KL projection: d - natural is along H^-1 b
        p = torch.linalg.solve(h, b)
        diff = d - natural
        torch.testing.assert_close(diff, float(diff @ p) / float(p @ p) * p)

    @pytest.mark.parametrize("seed", range(4))
    def test_equals_the_natural_step_when_the_constraint_holds(self, seed):
        h, g, b = random_problem(seed, "opposed")
        c = c_for(h, b, -0.2)
        natural = trpo_direction(h, g)
        assert c + float(b @ natural) < 0
        torch.testing.assert_close(pcpo_direction(exact_lin(h, g, b), c, DELTA), natural)

    def test_safepo_hx_option(self):
        h, g, b = random_problem(1, "aligned")
        c = c_for(h, b, 0.5)
        lin = exact_lin(h, g, b)
        alpha = math.sqrt(2 * DELTA / lin.q)
        nu = max((alpha * lin.r + c) / lin.s, 0.0)
        expected = alpha * (h @ lin.x) - nu * lin.p
        torch.testing.assert_close(pcpo_direction(lin, c, DELTA, use_hx=True), expected, rtol=1e-7, atol=1e-9)
        assert not torch.allclose(expected, pcpo_direction(lin, c, DELTA))


# =========================================================================== tiny actor
OBS_DIM, ACT_DIM, BATCH = 4, 2, 256


def make_actor(seed: int = 0) -> ProbabilisticActor:
    torch.manual_seed(seed)
    body = nn.Sequential(
        MLP(in_features=OBS_DIM, out_features=ACT_DIM, num_cells=[16, 16], activation_class=nn.Tanh),
        AddStateIndependentNormalScale(ACT_DIM, scale_mapping="exp", init_value=0.0),
    )
    return ProbabilisticActor(
        TensorDictModule(body, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=IndependentNormal,
        return_log_prob=True,
        default_interaction_type="random",
    )


def synthetic_batch(actor: ProbabilisticActor, seed: int = 1) -> tuple[TensorDict, torch.Tensor, torch.Tensor]:
    """A collected-like batch and advantages that depend on the action (so the surrogates have slopes)."""
    gen = torch.Generator().manual_seed(seed)
    obs = torch.randn(BATCH, OBS_DIM, generator=gen)
    with torch.no_grad():
        data = actor(TensorDict({"observation": obs}, [BATCH]))
    noise = (data["action"] - data["loc"]) / data["scale"]
    adv = noise[:, :1] + 0.3 * torch.randn(BATCH, 1, generator=gen)
    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    cost_adv = noise[:, :1] + noise[:, 1:] + 0.3 * torch.randn(BATCH, 1, generator=gen)
    return data, adv, cost_adv - cost_adv.mean()


@torch.no_grad()
def surrogates_and_kl(actor, data, adv, cost_adv) -> tuple[float, float, float]:
    """Independent evaluation: reward / cost surrogates and KL(old || new) averaged over samples and dims."""
    dist = actor.get_dist(data.select("observation"))
    ratio = (dist.log_prob(data["action"]) - data["action_log_prob"]).exp()
    kl = gaussian_kl(data["loc"], data["scale"], dist.mean, dist.stddev).mean() / ACT_DIM
    return float((ratio * adv.squeeze(-1)).mean()), float((ratio * cost_adv.squeeze(-1)).mean()), float(kl)


class TestTrustRegionLoss:
    def test_values_at_the_behaviour_policy(self):
        actor = make_actor()
        data, adv, cost_adv = synthetic_batch(actor)
        out = TrustRegionLoss(actor)(data.set("advantage", adv).set("cost_advantage", cost_adv))
        assert set(out.keys()) == {"loss_objective", "loss_cost", "kl"}
        torch.testing.assert_close(out["loss_objective"].detach(), -adv.mean(), atol=1e-6, rtol=0)
        torch.testing.assert_close(out["loss_cost"].detach(), cost_adv.mean(), atol=1e-6, rtol=0)
        assert abs(float(out["kl"].detach())) < 1e-7
        assert out["loss_objective"].requires_grad and out["kl"].requires_grad

    def test_kl_reductions_and_key_remapping(self):
        actor = make_actor()
        data, adv, _ = synthetic_batch(actor)
        data.set("my_adv", adv.squeeze(-1))  # per-sample advantages without the trailing dim work too
        with torch.no_grad():
            for p in actor.parameters():
                p.add_(0.05)
        mean_loss, sum_loss = TrustRegionLoss(actor), TrustRegionLoss(actor, kl_action_reduction="sum")
        for loss in (mean_loss, sum_loss):
            loss.set_keys(advantage="my_adv")
        kl_mean, kl_sum = float(mean_loss(data)["kl"].detach()), float(sum_loss(data)["kl"].detach())
        assert kl_mean > 0 and kl_sum == pytest.approx(ACT_DIM * kl_mean, rel=1e-5)
        assert "loss_cost" not in mean_loss(data).keys()  # no cost advantage, no cost surrogate

    def test_mismatched_advantage_shape_raises(self):
        actor = make_actor()
        data, adv, _ = synthetic_batch(actor)
        with pytest.raises(ValueError, match="no silent broadcasting"):
            TrustRegionLoss(actor)(data.set("advantage", adv.expand(BATCH, 3).clone()))


STEP_CLASSES = {
    NaturalPolicyStep: set(),
    TRPOStep: set(),
    CPOStep: {"Misc/cost_gradient_norm", "Misc/CPOCase"},
    PCPOStep: {"Misc/cost_gradient_norm"},
}


class TestSteps:
    @pytest.mark.parametrize("cls", list(STEP_CLASSES))
    @pytest.mark.parametrize("cost_violation", [-20.0, 0.02, 20.0])
    def test_metric_keys_and_finite_values(self, cls, cost_violation):
        actor = make_actor()
        data, adv, cost_adv = synthetic_batch(actor)
        metrics = cls(actor).step(data, adv, cost_adv, cost_violation)
        assert BASE_METRICS | STEP_CLASSES[cls] <= set(metrics)
        assert all(isinstance(v, float) and math.isfinite(v) for v in metrics.values())
        assert metrics["Train/KL"] <= DELTA + 1e-6 or cls is NaturalPolicyStep

    def test_trpo_step_improves_the_surrogate_inside_the_trust_region(self):
        actor = make_actor()
        data, adv, cost_adv = synthetic_batch(actor)
        reference = data.clone()
        before, _, _ = surrogates_and_kl(actor, data, adv, cost_adv)
        metrics = TRPOStep(actor).step(data, adv, cost_adv, 0.0)
        after, _, kl = surrogates_and_kl(actor, data, adv, cost_adv)
        assert metrics["Misc/AcceptanceStep"] >= 1
        assert 0.0 < kl <= DELTA
        assert after > before
        assert metrics["Train/KL"] == pytest.approx(kl, rel=1e-4)
        assert metrics["Loss/Loss_actor"] == pytest.approx(-before, abs=1e-6)
        assert (data == reference).all()  # the caller's batch is not modified

    def test_natural_step_is_always_taken_at_about_delta(self):
        actor = make_actor()
        data, adv, cost_adv = synthetic_batch(actor)
        theta = flat_params(list(actor.parameters()))
        metrics = NaturalPolicyStep(actor).step(data, adv, cost_adv, 0.0)
        _, _, kl = surrogates_and_kl(actor, data, adv, cost_adv)
        step = flat_params(list(actor.parameters())) - theta
        assert metrics["Misc/AcceptanceStep"] == 1.0
        assert float(step.norm()) == pytest.approx(metrics["Misc/FinalStepNorm"], rel=1e-5)
        assert float(step.norm()) == pytest.approx(metrics["Misc/Alpha"] * metrics["Misc/H_inv_g"], rel=1e-5)
        assert 0.2 * DELTA < kl < 2.0 * DELTA  # the quadratic model puts it near the boundary

    def test_cpo_with_a_far_inactive_constraint_is_trpo(self):
        actor = make_actor()
        twin = copy.deepcopy(actor)
        data, adv, cost_adv = synthetic_batch(actor)
        cpo = CPOStep(actor).step(data, adv, cost_adv, -1e3)
        TRPOStep(twin).step(data, adv, cost_adv, -1e3)
        assert cpo["Misc/CPOCase"] == 3.0
        torch.testing.assert_close(flat_params(list(actor.parameters())), flat_params(list(twin.parameters())))

    @pytest.mark.parametrize("cls", [CPOStep, PCPOStep])
    def test_infeasible_policy_does_not_raise_the_cost_surrogate(self, cls):
        actor = make_actor()
        data, adv, cost_adv = synthetic_batch(actor)
        _, cost_before, _ = surrogates_and_kl(actor, data, adv, cost_adv)
        metrics = cls(actor).step(data, adv, cost_adv, 5.0)
        _, cost_after, kl = surrogates_and_kl(actor, data, adv, cost_adv)
        if cls is CPOStep:
            assert metrics["Misc/CPOCase"] in (0.0, 1.0)
        assert metrics["Misc/AcceptanceStep"] >= 1
        assert cost_after < cost_before and kl <= DELTA

    def test_rejected_step_leaves_the_actor_unchanged(self):
        class Never(TRPOStep):
            def acceptable(self, reward, cost, kl, before_reward, before_cost, proposals):
                return torch.zeros_like(kl, dtype=torch.bool)

        actor = make_actor()
        data, adv, cost_adv = synthetic_batch(actor)
        theta = flat_params(list(actor.parameters()))
        metrics = Never(actor, line_search_steps=4).step(data, adv, cost_adv, 0.0)
        assert torch.equal(flat_params(list(actor.parameters())), theta)
        assert (metrics["Misc/AcceptanceStep"], metrics["Misc/FinalStepNorm"], metrics["Train/KL"]) == (0.0, 0.0, 0.0)

    def test_the_actor_keeps_its_parameter_objects(self):
        # the one-seed view writes values into the actor's own parameters (MACPO's agents share
        # them with the team's policy, the trainer's modules with its checkpoints)
        actor = make_actor()
        params = list(actor.parameters())
        data, adv, cost_adv = synthetic_batch(actor)
        theta = flat_params(params)
        CPOStep(actor).step(data, adv, cost_adv, 0.02)
        assert all(a is b for a, b in zip(params, actor.parameters()))
        assert not torch.equal(flat_params(params), theta)

    def test_a_non_gaussian_policy_is_refused(self):
        actor = make_actor()
        tanh = ProbabilisticActor(actor.module[0], in_keys=["loc", "scale"], distribution_class=TanhNormal,
                                  return_log_prob=True)
        data, adv, cost_adv = synthetic_batch(actor)
        with pytest.raises(TypeError, match="diagonal-Gaussian"):
            TRPOStep(tanh).step(data, adv, cost_adv, 0.0)

    def test_the_diagonal_gaussian_check_names_its_user(self):
        loc, scale = torch.zeros(4, 2), torch.ones(4, 2)
        for dist in (torch.distributions.Normal(loc, scale), IndependentNormal(loc, scale)):
            got = diagonal_gaussian_params(dist, "A trust-region step")
            assert torch.equal(got[0], dist.mean) and torch.equal(got[1], dist.stddev)
        over_two_dims = torch.distributions.Independent(torch.distributions.Normal(loc, scale), 2)
        for dist in (over_two_dims, TanhNormal(loc, scale)):
            for user in ("A trust-region step", "The closed-form KL to a stored policy"):
                with pytest.raises(TypeError, match=f"^{user} needs a diagonal-Gaussian policy.*"
                                                    f"distribution is {type(dist).__name__}"):
                    diagonal_gaussian_params(dist, user)
        data = TensorDict(loc=loc, scale=scale, batch_size=[4])
        with pytest.raises(TypeError, match="closed-form KL to a stored policy"):
            kl_to_stored_gaussian(TanhNormal(loc, scale), data, "loc", "scale")

    def test_defaults_and_validation(self):
        actor = make_actor()
        assert NaturalPolicyStep(actor).line_search_steps == 0
        assert TRPOStep(actor).line_search_steps == CPOStep(actor).line_search_steps == 15
        assert PCPOStep(actor).line_search_steps == 200
        assert TRPOStep(actor, line_search_steps=None).line_search_steps == 15
        step = CPOStep(actor)
        assert (step.target_kl, step.cg_iters, step.cg_damping, step.step_fraction) == (0.01, 15, 0.1, 0.8)
        for bad in (dict(target_kl=0.0), dict(step_fraction=1.0), dict(cg_iters=0), dict(line_search_steps=-1)):
            with pytest.raises(ValueError):
                TRPOStep(actor, **bad)
