"""Tests of the second-order tools: flat views, Fisher-vector product, conjugate gradient, line search."""
from __future__ import annotations

import math

import pytest
import torch

torch.set_num_threads(1)

from tensordict import TensorDict  # noqa: E402
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule  # noqa: E402
from torch import nn  # noqa: E402
from torchrl.modules import IndependentNormal, MLP, ProbabilisticActor  # noqa: E402

from sg_torchrl.objectives import gaussian_kl, TrustRegionLoss  # noqa: E402
from sg_torchrl.objectives.second_order import (  # noqa: E402
    backtracking_line_search,
    conjugate_gradient,
    FisherVectorProduct,
    flat_grad,
    flat_params,
    natural_step_size,
    set_flat_params,
)

OBS_DIM, ACT_DIM, BATCH = 3, 2, 16


# --------------------------------------------------------------------------- helpers
def random_spd(n: int, seed: int, *, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    m = torch.randn(n, n, generator=gen, dtype=dtype)
    return m @ m.T / n + 0.5 * torch.eye(n, dtype=dtype)


def make_tiny_actor(seed: int = 0) -> tuple[ProbabilisticActor, nn.Sequential]:
    """A float64 Gaussian policy (tanh MLP mean, state-independent log-std) and its body."""
    torch.manual_seed(seed)
    body = nn.Sequential(
        MLP(in_features=OBS_DIM, out_features=ACT_DIM, num_cells=[4], activation_class=nn.Tanh),
        AddStateIndependentNormalScale(ACT_DIM, scale_mapping="exp", init_value=0.0),
    ).double()
    with torch.no_grad():  # a non-trivial std so the log-std block of H is not degenerate
        body[1].state_independent_scale.copy_(torch.randn(ACT_DIM, dtype=torch.float64) * 0.3)
    actor = ProbabilisticActor(
        TensorDictModule(body, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=IndependentNormal,
        return_log_prob=True,
    )
    return actor, body


def tiny_batch(actor: ProbabilisticActor, seed: int = 1) -> TensorDict:
    gen = torch.Generator().manual_seed(seed)
    obs = torch.randn(BATCH, OBS_DIM, generator=gen, dtype=torch.float64)
    with torch.no_grad():
        td = actor(TensorDict({"observation": obs}, [BATCH]))
    td.set("advantage", torch.randn(BATCH, 1, generator=gen, dtype=torch.float64))
    return td


# --------------------------------------------------------------------------- flat views
class TestFlatViews:
    def test_round_trip(self):
        actor, _ = make_tiny_actor()
        params = list(actor.parameters())
        theta = flat_params(params)
        assert theta.shape == (sum(p.numel() for p in params),)
        shapes = [p.shape for p in params]
        set_flat_params(params, 2.0 * theta + 1.0)
        assert [p.shape for p in params] == shapes
        torch.testing.assert_close(flat_params(params), 2.0 * theta + 1.0)
        set_flat_params(params, theta)
        torch.testing.assert_close(flat_params(params), theta)

    def test_flat_params_is_a_copy(self):
        actor, _ = make_tiny_actor()
        params = list(actor.parameters())
        theta = flat_params(params)
        theta.add_(1.0)
        assert not torch.equal(flat_params(params), theta)

    def test_wrong_size_raises(self):
        actor, _ = make_tiny_actor()
        params = list(actor.parameters())
        with pytest.raises(ValueError, match="elements"):
            set_flat_params(params, torch.zeros(flat_params(params).numel() + 1, dtype=torch.float64))

    def test_flat_grad_matches_autograd_and_zero_fills_unused(self):
        a = torch.randn(3, requires_grad=True)
        w = torch.randn(2, 2, requires_grad=True)
        unused = torch.randn(4, requires_grad=True)
        out = (a.pow(2).sum() + (w * 3.0).sum())
        g = flat_grad(out, [a, w, unused])
        torch.testing.assert_close(g, torch.cat([2 * a.detach(), torch.full((4,), 3.0), torch.zeros(4)]))
        assert a.grad is None  # does not accumulate into .grad


# --------------------------------------------------------------------------- conjugate gradient
class TestConjugateGradient:
    @pytest.mark.parametrize("n", [2, 5, 20, 60])
    def test_solves_spd_systems(self, n):
        for seed in range(3):
            a = random_spd(n, seed)
            b = torch.randn(n, generator=torch.Generator().manual_seed(100 + seed), dtype=torch.float64)
            x = conjugate_gradient(lambda v: a @ v, b, iters=3 * n, residual_tol=1e-12, eps=0.0)
            assert (a @ x - b).norm() / b.norm() < 1e-8
            torch.testing.assert_close(x, torch.linalg.solve(a, b), rtol=1e-7, atol=1e-9)

    def test_safepo_defaults_converge_on_small_systems(self):
        # SafePO's eps=1e-6 in both denominators caps the attainable accuracy near
        # ||r|| ~ 1e-3 |b|, which is all a trust-region step needs.
        a = random_spd(8, 7)
        b = torch.randn(8, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
        x = conjugate_gradient(lambda v: a @ v, b)  # iters=15, residual_tol=1e-10, eps=1e-6
        assert (a @ x - b).norm() / b.norm() < 1e-3

    def test_stops_at_the_iteration_budget(self):
        calls = []
        a = random_spd(30, 1)

        def avp(v):
            calls.append(1)
            return a @ v

        conjugate_gradient(avp, torch.ones(30, dtype=torch.float64), iters=4)
        assert len(calls) == 4

    def test_zero_rhs_gives_zero(self):
        a = random_spd(4, 2)
        x = conjugate_gradient(lambda v: a @ v, torch.zeros(4, dtype=torch.float64))
        assert torch.equal(x, torch.zeros(4, dtype=torch.float64))


# --------------------------------------------------------------------------- Fisher-vector product
def _explicit_hessian_of_mean_kl(body: nn.Sequential, obs: torch.Tensor, reduction: str) -> torch.Tensor:
    """Hessian of mean KL(pi_theta0 || pi_theta) at theta0 w.r.t. the flat parameters (independent path)."""
    names = [n for n, _ in body.named_parameters()]
    shapes = [p.shape for _, p in body.named_parameters()]
    theta0 = flat_params([p for _, p in body.named_parameters()])
    with torch.no_grad():
        loc0, scale0 = body(obs)

    def mean_kl(theta: torch.Tensor) -> torch.Tensor:
        chunks = torch.split(theta, [math.prod(s) for s in shapes])
        params = {n: c.reshape(s) for n, c, s in zip(names, chunks, shapes)}
        loc, scale = torch.func.functional_call(body, params, (obs,))
        kl = gaussian_kl(loc0, scale0, loc, scale)
        return (kl / ACT_DIM if reduction == "mean" else kl).mean()

    return torch.autograd.functional.hessian(mean_kl, theta0)


class TestFisherVectorProduct:
    @pytest.mark.parametrize("reduction", ["mean", "sum"])
    def test_matches_explicit_hessian_plus_damping(self, reduction):
        actor, body = make_tiny_actor()
        td = tiny_batch(actor)
        params = list(actor.parameters())
        # the anchor (old policy) is the actor itself, detached: KL = 0, H = Fisher matrix
        losses = TrustRegionLoss(actor, kl_action_reduction=reduction)(td)
        assert abs(float(losses["kl"].detach())) < 1e-12
        fvp = FisherVectorProduct(losses["kl"], params, damping=0.1)
        hessian = _explicit_hessian_of_mean_kl(body, td["observation"], reduction)
        gen = torch.Generator().manual_seed(5)
        for _ in range(3):  # reusable for many vectors
            v = torch.randn(hessian.shape[0], generator=gen, dtype=torch.float64)
            torch.testing.assert_close(fvp(v), hessian @ v + 0.1 * v, rtol=1e-8, atol=1e-10)

    def test_fisher_is_positive_semidefinite_and_symmetric(self):
        actor, body = make_tiny_actor(seed=3)
        hessian = _explicit_hessian_of_mean_kl(body, tiny_batch(actor)["observation"], "mean")
        torch.testing.assert_close(hessian, hessian.T)
        assert torch.linalg.eigvalsh(hessian).min() > -1e-10

    def test_damping_only_when_kl_is_linear(self):
        w = torch.randn(3, requires_grad=True)
        fvp = FisherVectorProduct((w * 2.0).sum(), [w], damping=0.5)
        v = torch.tensor([1.0, -2.0, 3.0])
        torch.testing.assert_close(fvp(v), 0.5 * v)

    def test_negative_damping_raises(self):
        w = torch.randn(3, requires_grad=True)
        with pytest.raises(ValueError):
            FisherVectorProduct(w.pow(2).sum(), [w], damping=-1.0)


# --------------------------------------------------------------------------- step size
def test_natural_step_reaches_the_trust_region_boundary():
    h = random_spd(6, 4)
    g = torch.randn(6, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    x = torch.linalg.solve(h, g)
    delta = 0.01
    alpha = natural_step_size(x @ h @ x, delta)
    step = alpha * x
    assert abs(0.5 * float(step @ h @ step) - delta) < 1e-8


# --------------------------------------------------------------------------- line search
class TestLineSearch:
    @staticmethod
    def _params():
        return [torch.nn.Parameter(torch.tensor([1.0, 2.0])), torch.nn.Parameter(torch.tensor([[3.0]]))]

    def test_restores_parameters_when_nothing_is_accepted(self):
        params = self._params()
        theta_old = flat_params(params)
        seen = []

        def reject() -> bool:
            seen.append(flat_params(params))
            return False

        result = backtracking_line_search(params, theta_old, torch.ones(3), reject, max_trials=5, step_fraction=0.5)
        assert (result.step_index, result.step_fraction, result.accepted) == (0, 0.0, False)
        assert len(seen) == 5
        torch.testing.assert_close(seen[-1], theta_old + 0.5**4)  # it did try the candidates
        assert torch.equal(flat_params(params), theta_old)

    def test_accepts_the_first_passing_trial_and_keeps_it(self):
        params = self._params()
        theta_old = flat_params(params)
        direction = torch.tensor([1.0, -1.0, 2.0])
        calls = []

        def third() -> bool:
            calls.append(1)
            return len(calls) == 3

        result = backtracking_line_search(params, theta_old, direction, third, max_trials=15, step_fraction=0.8)
        assert result.step_index == 3 and result.accepted
        assert result.step_fraction == pytest.approx(0.8**2)
        torch.testing.assert_close(flat_params(params), theta_old + 0.8**2 * direction)
        assert len(calls) == 3

    def test_full_step_is_index_one(self):
        params = self._params()
        theta_old = flat_params(params)
        result = backtracking_line_search(params, theta_old, torch.ones(3), lambda: True)
        assert (result.step_index, result.step_fraction) == (1, 1.0)
        torch.testing.assert_close(flat_params(params), theta_old + 1.0)

    def test_predicate_sees_the_candidate(self):
        # accept only once the first coordinate dropped below 1.5: 1 + 0.8^k < 1.5 first at k = 4
        params = self._params()
        theta_old = flat_params(params)
        result = backtracking_line_search(params, theta_old, torch.ones(3), lambda: float(params[0][0]) < 1.5)
        assert result.step_index == 5
