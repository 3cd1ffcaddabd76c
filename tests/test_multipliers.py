"""Tests of the Lagrange / PID multipliers (sg_torchrl.objectives.multipliers)."""
from __future__ import annotations

import math
from collections import deque

import pytest
import torch

torch.set_num_threads(1)

from sg_torchrl.objectives import LagrangeMultiplier, Multiplier, NoMultiplier, PIDLagrangeMultiplier  # noqa: E402

# Episode costs around the default limit of 25: above, below, far above, exactly at the limit.
COSTS = [40.0, 31.5, 26.0, 12.0, 0.0, 3.0, 60.0, 100.0, 25.0, 24.0, 80.0, 5.0, 0.0, 0.0, 45.0]


# --------------------------------------------------------------------------- reference rules
def adam_reference(costs, *, cost_limit=25.0, init=0.001, lr=0.035, upper_bound=None):
    """SafePO's rule with a real torch.optim.Adam on a torch parameter (the reference sequence)."""
    lam = torch.nn.Parameter(torch.tensor(max(init, 0.0)))
    opt = torch.optim.Adam([lam], lr=lr)
    values = []
    for jc in costs:
        opt.zero_grad()
        loss = -lam * (jc - cost_limit)
        loss.backward()
        opt.step()
        lam.data.clamp_(min=0.0, max=upper_bound)
        values.append(torch.relu(lam.detach()).clone())
    return values


def pid_reference(
    costs,
    *,
    cost_limit=25.0,
    kp=0.1,
    ki=0.01,
    kd=0.01,
    d_delay=10,
    alpha_p=0.95,
    alpha_d=0.95,
    init=0.001,
    penalty_max=100.0,
    sum_norm=True,
    diff_norm=False,
):
    """Pure-Python re-derivation of the PID Lagrangian (Stooke et al. 2020 / SafePO cppo_pid)."""
    integral, p_smooth, cost_smooth = init, 0.0, 0.0
    history = deque([0.0], maxlen=d_delay)  # oldest entry = smoothed cost d_delay updates ago
    values = []
    for jc in costs:
        error = jc - cost_limit
        integral = max(0.0, integral + ki * error)
        if diff_norm:
            integral = max(0.0, min(1.0, integral))
        p_smooth = alpha_p * p_smooth + (1 - alpha_p) * error
        cost_smooth = alpha_d * cost_smooth + (1 - alpha_d) * jc
        rise = max(0.0, cost_smooth - history[0])
        lam = max(0.0, kp * p_smooth + integral + kd * rise)
        if diff_norm:
            lam = min(1.0, lam)
        if not (diff_norm or sum_norm):
            lam = min(lam, penalty_max)
        history.append(cost_smooth)
        values.append(lam)
    return values


# --------------------------------------------------------------------------- tests
class TestMultiplierBase:
    def test_is_abstract(self):
        with pytest.raises(TypeError):
            Multiplier()

    @pytest.mark.parametrize("cls", [LagrangeMultiplier, PIDLagrangeMultiplier])
    def test_common_interface(self, cls):
        m = cls(cost_limit=10.0)
        assert isinstance(m, Multiplier)
        assert isinstance(m.sum_norm, bool) and isinstance(m.diff_norm, bool)
        out = m.update(30.0)
        assert out.shape == torch.Size([]) and not out.requires_grad and out.item() >= 0.0
        assert out.item() == m.value.item() == m().item()


class TestCombine:
    def test_sum_norm_rule(self):
        multiplier = LagrangeMultiplier(init=0.5)
        adv, cost_adv = torch.tensor([[1.0], [2.0]]), torch.tensor([[4.0], [-2.0]])
        torch.testing.assert_close(multiplier.combine(adv, cost_adv), (adv - 0.5 * cost_adv) / 1.5)

    def test_shape_mismatch_is_an_error(self):
        with pytest.raises(ValueError, match="must match"):
            LagrangeMultiplier().combine(torch.zeros(4, 1), torch.zeros(4))

    def test_no_multiplier_is_zero_for_ever(self):
        multiplier = NoMultiplier(cost_limit=10.0)
        adv, cost_adv = torch.randn(5, 1), torch.randn(5, 1)
        for cost in (0.0, 50.0, 1e6):
            assert multiplier.update(cost).item() == 0.0
        torch.testing.assert_close(multiplier.combine(adv, cost_adv), adv)
        assert multiplier.cost_limit.item() == 10.0
        with pytest.raises(ValueError, match="finite"):
            multiplier.update(float("nan"))


class TestLagrangeMultiplier:
    def test_defaults_and_initial_value(self):
        m = LagrangeMultiplier()
        assert isinstance(m, Multiplier)
        assert m.sum_norm and not m.diff_norm
        assert float(m.cost_limit) == 25.0
        assert m.value.item() == pytest.approx(0.001)
        assert not m.value.requires_grad
        assert list(m.parameters()) == []  # nothing for a network optimiser to pick up

    def test_negative_init_is_clamped(self):
        assert LagrangeMultiplier(init=-3.0).value.item() == 0.0

    @pytest.mark.parametrize("upper_bound", [None, 0.08])
    def test_matches_torch_adam(self, upper_bound):
        m = LagrangeMultiplier(cost_limit=25.0, init=0.001, lr=0.035, upper_bound=upper_bound)
        expected = adam_reference(COSTS, upper_bound=upper_bound)
        for jc, ref in zip(COSTS, expected):
            out = m.update(jc)
            torch.testing.assert_close(out, ref, rtol=0, atol=0)
            torch.testing.assert_close(m.value, ref, rtol=0, atol=0)
        assert int(m.step) == len(COSTS)

    def test_clamps_at_zero(self):
        m = LagrangeMultiplier(init=0.05, lr=0.035)
        values = [m.update(0.0).item() for _ in range(5)]
        assert values[0] == pytest.approx(0.05 - 0.035, abs=1e-6)  # first Adam step is ~lr
        assert values[-1] == 0.0
        assert float(m.lambda_raw) == 0.0  # the raw parameter itself is projected
        # Adam's momentum first has to turn around, then the multiplier grows again
        assert max(m.update(100.0).item() for _ in range(5)) > 0.0

    def test_clamps_at_upper_bound(self):
        m = LagrangeMultiplier(init=0.0, lr=0.035, upper_bound=0.1)
        for _ in range(10):
            m.update(1000.0)
        assert m.value.item() == pytest.approx(0.1)
        assert m.lambda_raw <= torch.tensor(0.1)  # float32 bound

    def test_tensor_cost_equals_float_cost(self):
        a, b = LagrangeMultiplier(), LagrangeMultiplier()
        for jc in COSTS[:5]:
            torch.testing.assert_close(a.update(jc), b.update(torch.tensor(jc)), rtol=0, atol=0)

    def test_value_is_a_copy(self):
        m = LagrangeMultiplier(init=0.5)
        v = m.value
        v.add_(10.0)
        assert m.value.item() == pytest.approx(0.5)

    def test_state_dict_round_trip(self):
        m = LagrangeMultiplier(upper_bound=2.0)
        for jc in COSTS[:6]:
            m.update(jc)
        restored = LagrangeMultiplier(upper_bound=2.0)
        restored.load_state_dict(m.state_dict())
        assert set(m.state_dict()) == {"cost_limit", "lambda_raw", "step", "exp_avg", "exp_avg_sq"}
        torch.testing.assert_close(restored.value, m.value, rtol=0, atol=0)
        for jc in COSTS[6:]:
            torch.testing.assert_close(restored.update(jc), m.update(jc), rtol=0, atol=0)

    def test_state_dict_restores_cost_limit(self):
        m = LagrangeMultiplier(cost_limit=10.0)
        restored = LagrangeMultiplier()
        restored.load_state_dict(m.state_dict())
        assert float(restored.cost_limit) == 10.0

    @pytest.mark.parametrize(
        "kwargs, match",
        [
            ({"lr": -0.1}, "lr must be > 0"),
            ({"lr": 0.0}, "lr must be > 0"),
            ({"cost_limit": -1.0}, "cost_limit must be >= 0"),
            ({"cost_limit": float("nan")}, "cost_limit must be finite"),
            ({"upper_bound": -1.0}, "upper_bound must be >= 0"),
            ({"betas": (0.9, 1.0)}, r"betas\[1\] must be in \[0, 1\)"),
            ({"eps": 0.0}, "eps must be > 0"),
            ({"init": float("inf")}, "init must be finite"),
        ],
    )
    def test_bad_config(self, kwargs, match):
        with pytest.raises(ValueError, match=match):
            LagrangeMultiplier(**kwargs)

    @pytest.mark.parametrize(
        "bad", [float("nan"), float("inf"), -float("inf"), torch.tensor(float("nan"))]
    )
    def test_non_finite_cost(self, bad):
        m = LagrangeMultiplier()
        with pytest.raises(ValueError, match="mean_episode_cost must be finite"):
            m.update(bad)
        assert int(m.step) == 0  # nothing was changed

    def test_non_scalar_cost(self):
        with pytest.raises(ValueError, match="must be a scalar"):
            LagrangeMultiplier().update(torch.tensor([1.0, 2.0]))


class TestPIDLagrangeMultiplier:
    def test_initial_value_is_init(self):
        m = PIDLagrangeMultiplier(init=0.25)
        assert isinstance(m, Multiplier)
        assert m.value.item() == 0.25
        assert m.sum_norm and not m.diff_norm
        assert list(m.parameters()) == []

    @pytest.mark.parametrize(
        "kwargs",
        [
            {},  # SafePO cppo_pid defaults (d_delay 10: no sample older than the history)
            {"d_delay": 3},  # derivative delay wraps around the ring buffer several times
            {"d_delay": 1, "kd": 0.5},
            {"d_delay": 4, "kp": 0.3, "ki": 0.05, "kd": 0.2, "ema_alpha_p": 0.5, "ema_alpha_d": 0.7},
            {"d_delay": 3, "sum_norm": False, "penalty_max": 0.4, "ki": 0.05},
            {"d_delay": 3, "diff_norm": True, "ki": 0.05},
        ],
    )
    def test_matches_python_reference(self, kwargs):
        m = PIDLagrangeMultiplier(cost_limit=25.0, **kwargs)
        ref_kwargs = {
            {"ema_alpha_p": "alpha_p", "ema_alpha_d": "alpha_d"}.get(k, k): v for k, v in kwargs.items()
        }
        expected = pid_reference(COSTS, cost_limit=25.0, **ref_kwargs)
        got = [m.update(jc).item() for jc in COSTS]
        assert got == pytest.approx(expected, rel=1e-12, abs=1e-15)
        assert int(m.num_updates) == len(COSTS)

    def test_clamps_exercised(self):
        # the configurations above really hit the clamps they are meant to test
        capped = pid_reference(COSTS, d_delay=3, sum_norm=False, penalty_max=0.4, ki=0.05)
        assert max(capped) == 0.4
        normed = pid_reference(COSTS, d_delay=3, diff_norm=True, ki=0.05)
        assert max(normed) == 1.0

    def test_derivative_uses_delayed_history(self):
        # Only the derivative term, no smoothing: lambda_t = max(0, Jc_t - Jc_{t - d_delay}).
        m = PIDLagrangeMultiplier(kp=0.0, ki=0.0, kd=1.0, d_delay=3, ema_alpha_d=0.0, init=0.0)
        costs = [10.0, 20.0, 30.0, 25.0, 50.0, 10.0, 90.0]
        got = [m.update(c).item() for c in costs]
        delayed = [0.0, 0.0, 0.0] + costs
        assert got == pytest.approx([max(0.0, c - delayed[t]) for t, c in enumerate(costs)])
        assert got == pytest.approx([10.0, 20.0, 30.0, 15.0, 30.0, 0.0, 65.0])

    def test_tensor_cost(self):
        a, b = PIDLagrangeMultiplier(), PIDLagrangeMultiplier()
        for jc in COSTS[:5]:
            assert a.update(jc).item() == b.update(torch.tensor(jc, dtype=torch.float64)).item()

    def test_state_dict_round_trip(self):
        m = PIDLagrangeMultiplier(d_delay=4)
        for jc in COSTS[:6]:  # stop in the middle of the ring buffer
            m.update(jc)
        restored = PIDLagrangeMultiplier(d_delay=4)
        restored.load_state_dict(m.state_dict())
        assert restored.value.item() == m.value.item()
        for jc in COSTS[6:]:
            assert restored.update(jc).item() == m.update(jc).item()
        torch.testing.assert_close(restored.d_history, m.d_history, rtol=0, atol=0)

    def test_state_dict_rejects_other_delay(self):
        with pytest.raises(RuntimeError, match="d_history"):
            other = PIDLagrangeMultiplier(d_delay=4).state_dict()
            PIDLagrangeMultiplier(d_delay=3).load_state_dict(other)

    @pytest.mark.parametrize(
        "kwargs, match",
        [
            ({"d_delay": 0}, "d_delay must be >= 1"),
            ({"cost_limit": -5.0}, "cost_limit must be >= 0"),
            ({"kp": -0.1}, "kp must be >= 0"),
            ({"ki": float("nan")}, "ki must be finite"),
            ({"ema_alpha_p": 1.5}, r"ema_alpha_p must be in \[0, 1\]"),
            ({"ema_alpha_d": -0.1}, r"ema_alpha_d must be in \[0, 1\]"),
            ({"init": -0.1}, "init must be >= 0"),
            ({"penalty_max": 0.0}, "penalty_max must be > 0"),
            ({"diff_norm": True, "init": 2.0}, r"init must be in \[0, 1\] when diff_norm"),
        ],
    )
    def test_bad_config(self, kwargs, match):
        with pytest.raises(ValueError, match=match):
            PIDLagrangeMultiplier(**kwargs)

    def test_d_delay_must_be_int(self):
        with pytest.raises(TypeError, match="d_delay must be an int"):
            PIDLagrangeMultiplier(d_delay=2.5)

    @pytest.mark.parametrize("bad", [float("nan"), math.inf, torch.tensor(-math.inf)])
    def test_non_finite_cost(self, bad):
        m = PIDLagrangeMultiplier()
        with pytest.raises(ValueError, match="mean_episode_cost must be finite"):
            m.update(bad)
        assert int(m.num_updates) == 0


@pytest.mark.parametrize("make", [
    lambda: NoMultiplier(cost_limit=25.0),
    lambda: LagrangeMultiplier(cost_limit=25.0),
    lambda: PIDLagrangeMultiplier(cost_limit=25.0),
])
def test_violation_is_cost_minus_the_limit_the_multiplier_holds(make):
    """The cost limit lives in the multiplier: the trainer and CPO / MACPO read J_c - d from it."""
    multiplier = make()
    assert multiplier.violation(30.0) == pytest.approx(5.0)
    assert multiplier.violation(torch.tensor(10.0)) == pytest.approx(-15.0)
    with pytest.raises(ValueError):
        multiplier.violation(float("nan"))
