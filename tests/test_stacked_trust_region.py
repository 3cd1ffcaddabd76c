"""The seed group's trust-region step moves every seed as the single-seed step moves it alone.

For NPG, TRPO, CPO and PCPO, three seeds' networks (``make_actor_critics`` after
``torch.manual_seed(seed)``) are stacked (:class:`~sg_torchrl.modules.stacked.StackedActorCritic`)
and stepped together by :mod:`sg_torchrl.objectives.stacked_trust_region`; each seed's new actor
parameters and metrics are compared with those of the single-seed step class
(``NaturalPolicyStep``, ``TRPOStep``, ``CPOStep``, ``PCPOStep``, built with the options
:mod:`sg_torchrl.train.algorithms` gives them) applied to that seed's own actor and batch. Both run
the same step code (the single-seed classes are its one-seed case); what differs is the actor's
forward pass: the group's batched matmuls against each seed's ``nn.Linear`` layers.

Tolerances: float32, rtol 1e-4 and atol 1e-6 on parameters and continuous metrics (the stacked
forward pass sums in another order than the single-seed one, and conjugate gradient amplifies
those last-bit differences); float64, rtol 1e-10 and atol 1e-12. Discrete outcomes (the accepted
line-search trial, the CPO case) must be equal.

Timing (not asserted; ``benchmarks/trust_region_group.py``; provisional: one run on a shared 2-core
CPU, one thread, HalfCheetah shapes obs 17 / act 6 / [64, 64], S = 3, median of 5): at 20,000
samples per seed three single-seed TRPO steps took 1.8 s and the group step 2.8 s (0.64x), CPO
3.2 s against 5.2 s (0.62x). The group's 5-15 MB temporaries went back to the OS and were faulted in
again (400,000-650,000 minor page faults per call, none for the single-seed steps); with glibc told
to keep freed memory (``--keep-freed-memory``) TRPO 1.7 s against 2.1 s (0.83x), CPO 3.4 s against
4.0 s (0.86x). At 2,000 samples per seed the two are level, at 500 the group is 1.1-1.2x faster: the
step is compute bound on a CPU; the stacked step pays off where per-op overhead dominates.
"""

from __future__ import annotations

import copy
import math

import pytest
import torch

torch.set_num_threads(1)

from tensordict import TensorDict  # noqa: E402
from torchrl.data import Bounded  # noqa: E402

from sg_torchrl.objectives import CPOStep, NaturalPolicyStep, PCPOStep, TRPOStep  # noqa: E402
from sg_torchrl.objectives.second_order import (  # noqa: E402
    SeedFisherVectorProduct,
    conjugate_gradient,
    seed_conjugate_gradient,
    seed_flat_grad,
    seed_linearise,
)
from sg_torchrl.objectives.stacked_trust_region import SeedSurrogates, StackedCPOStep, StackedTRPOStep  # noqa: E402
from sg_torchrl.objectives.trust_region import STACKED_STEPS  # noqa: E402
from sg_torchrl.train.config import ALGORITHM_DEFAULTS  # noqa: E402
from sg_torchrl.modules import StackedActorCritic, make_actor_critics  # noqa: E402

OBS, ACT, HIDDEN, N = 4, 2, [16, 16], 256
SEEDS = (3, 11, 42)
SPEC = Bounded(-1.0, 1.0, shape=(ACT,))
TOL = {torch.float32: dict(rtol=1e-4, atol=1e-6), torch.float64: dict(rtol=1e-10, atol=1e-12)}
DISCRETE = ("Misc/AcceptanceStep", "Misc/CPOCase")
STEP_CLASSES = {"npg": NaturalPolicyStep, "trpo": TRPOStep, "cpo": CPOStep, "pcpo": PCPOStep}


# --------------------------------------------------------------------------- helpers
def step_options(name: str) -> dict:
    """The options ``algorithms._trust_region`` passes, from the algorithm's config defaults."""
    defaults = ALGORITHM_DEFAULTS[name]
    options = dict(target_kl=defaults["target_kl"], cg_iters=defaults["cg_iters"], cg_damping=0.1)
    if name != "npg":  # NPG (and RCPO) apply the step without a line search
        options.update(line_search_steps=defaults["line_search_steps"], step_fraction=defaults["step_fraction"])
    return options


def networks(seed: int, dtype: torch.dtype = torch.float32):
    torch.manual_seed(seed)
    return tuple(module.to(dtype) for module in make_actor_critics(OBS, SPEC, HIDDEN))


def rollout(seed: int, actor, dtype: torch.dtype = torch.float32, obs_scale: float = 1.0,
            off_policy: float = 0.0) -> TensorDict:
    """A collected-like batch whose advantages depend on the action, so the surrogates have slopes.

    ``obs_scale`` saturates the actor's tanh units; ``off_policy`` adds noise of that size to the
    behaviour log-probabilities (ratios far from 1 make the surrogates far from linear).
    """
    gen = torch.Generator().manual_seed(1000 + seed)
    obs = obs_scale * torch.randn(N, OBS, generator=gen, dtype=dtype)
    with torch.no_grad():
        data = actor(TensorDict(observation=obs, batch_size=[N]))
    noise = (data["action"] - data["loc"]) / data["scale"]
    adv = noise[:, :1] + 0.3 * torch.randn(N, 1, generator=gen, dtype=dtype)
    cost_adv = noise[:, :1] + noise[:, 1:] + 0.3 * torch.randn(N, 1, generator=gen, dtype=dtype)
    data["advantage"] = (adv - adv.mean()) / (adv.std() + 1e-8)
    data["cost_advantage"] = cost_adv - cost_adv.mean()
    if off_policy:
        data["action_log_prob"] = data["action_log_prob"] + off_policy * torch.randn(N, generator=gen, dtype=dtype)
    return data.select("observation", "action", "action_log_prob", "loc", "scale", "advantage", "cost_advantage")


def make_group(dtype: torch.dtype = torch.float32, obs_scales=(1.0, 1.0, 1.0), off_policy=(0.0, 0.0, 0.0)):
    nets = [networks(seed, dtype) for seed in SEEDS]
    batches = [rollout(seed, nets[i][0], dtype, obs_scales[i], off_policy[i]) for i, seed in enumerate(SEEDS)]
    return nets, batches


def stacked_batch(batches) -> dict[str, torch.Tensor]:
    return {key: torch.stack([b[key] for b in batches]) for key in batches[0].keys()}


def single_actor_params(actor) -> list[torch.Tensor]:
    mlp, scale = actor.module[0].module[0], actor.module[0].module[1]
    return [p.detach().clone() for p in (*mlp.parameters(), scale.state_independent_scale)]


def seed_actor_params(model: StackedActorCritic, seed: int) -> list[torch.Tensor]:
    """Seed ``seed``'s actor parameters in the single module's layout (weights transposed back)."""
    out = []
    for weight, bias in zip(model.actor_mean.weights, model.actor_mean.biases):
        out += [weight[seed].detach().T, bias[seed, 0].detach()]
    return [*out, model.log_std[seed].detach()]


def run_single(name: str, nets, batches, violations, **extra):
    """Each seed alone through the single-seed step: (new actor parameters, metrics) per seed."""
    params, metrics = [], []
    for (actor, _, _), batch, c in zip(nets, batches, violations):
        actor = copy.deepcopy(actor)
        step = STEP_CLASSES[name](actor, **step_options(name), **extra)
        metrics.append(step.step(batch, batch["advantage"], batch["cost_advantage"], float(c)))
        params.append(single_actor_params(actor))
    return params, metrics


def run_group(name: str, nets, batches, violations, **extra):
    model = StackedActorCritic.from_single(nets)
    step = STACKED_STEPS[STEP_CLASSES[name]](model, **step_options(name), **extra)
    data = stacked_batch(batches)
    metrics = step.step(data, data["advantage"], data["cost_advantage"], torch.tensor(violations, dtype=torch.float64))
    return model, metrics


def assert_same_as_single(name, nets, batches, violations, dtype=torch.float32, **extra):
    """The group step agrees with the single-seed step seed by seed; returns the group's metrics."""
    before = [single_actor_params(actor) for actor, _, _ in nets]
    single_params, single_metrics = run_single(name, nets, batches, violations, **extra)
    model, metrics = run_group(name, nets, batches, violations, **extra)
    tol = TOL[dtype]
    for seed, (params, expected) in enumerate(zip(single_params, single_metrics)):
        assert set(metrics) == set(expected)
        for key, value in expected.items():
            got = metrics[key][seed].item()
            assert metrics[key].shape == (len(nets),) and metrics[key].dtype == torch.float64
            if key in DISCRETE:
                assert got == value, (key, seed)
            else:
                assert got == pytest.approx(value, rel=tol["rtol"], abs=tol["atol"]), (key, seed)
        for got, want in zip(seed_actor_params(model, seed), params):
            torch.testing.assert_close(got, want, **tol)
        if expected["Misc/AcceptanceStep"] == 0:  # rejected alone, so rejected in the group: bit for bit
            for got, want in zip(seed_actor_params(model, seed), before[seed]):
                assert torch.equal(got, want)
    return metrics


def violation_scale(nets, batches) -> list[float]:
    """Per seed :math:`\\sqrt{2\\delta s}`: violations of that size put CPO's constraint on the trust region's edge."""
    model = StackedActorCritic.from_single(nets)
    data = stacked_batch(batches)
    with torch.no_grad():
        loc, scale = model.dist_params(data["observation"])
    surrogates = SeedSurrogates(data["observation"], data["action"], data["action_log_prob"],
                                data["advantage"].squeeze(-1), data["cost_advantage"].squeeze(-1), loc, scale)
    reward, cost, kl = surrogates(model)
    params = model.actor_parameters()
    grads = [seed_flat_grad(v.sum(), params, len(nets), retain_graph=True) for v in (reward, cost)]
    lin = seed_linearise(SeedFisherVectorProduct(kl, params, 0.1), *grads)
    return [math.sqrt(2 * 0.01 * s) for s in lin.s.tolist()]


# --------------------------------------------------------------------------- pieces
def test_seed_conjugate_gradient_is_row_by_row_conjugate_gradient():
    """Per-seed alpha / beta, and a seed that converges early is frozen where the single loop breaks.

    With ``eps=0`` seed 1 (``A = 2I``) has an exactly zero residual after one iteration; another
    iteration would divide 0 by 0, so only the mask keeps its solution (``b / 2``) finite.
    """
    gen = torch.Generator().manual_seed(0)
    size = 12
    mats = []
    for seed in range(4):
        m = torch.randn(size, size, generator=gen, dtype=torch.float64)
        mats.append(m @ m.T / size + (0.05 + 0.3 * seed) * torch.eye(size, dtype=torch.float64))
    mats[1] = 2.0 * torch.eye(size, dtype=torch.float64)
    A = torch.stack(mats)
    b = torch.randn(4, size, generator=gen, dtype=torch.float64)

    def avp(v):
        return torch.einsum("spq,sq->sp", A, v)

    for iters, eps in ((3, 1e-6), (15, 1e-6), (15, 0.0)):
        rhs = b.clone()
        if eps:
            rhs[3] = 0.0  # converged before the first test
        x = seed_conjugate_gradient(avp, rhs, iters, eps=eps)
        for s in range(4):
            single = conjugate_gradient(lambda v: A[s] @ v, rhs[s], iters, eps=eps)
            # float64; the rows' dot products sum in another order than torch.dot, and CG run to its
            # last iterations (residuals near 1e-10) amplifies that to about 1e-11
            torch.testing.assert_close(x[s], single, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(x[1], b[1] / 2.0, rtol=0, atol=0)


def test_fisher_product_is_block_diagonal():
    """Row s of the group's Hv depends on v's row s only, and equals the single-seed product there."""
    nets, batches = make_group(torch.float64)
    model = StackedActorCritic.from_single(nets)
    data = stacked_batch(batches)
    with torch.no_grad():
        loc, scale = model.dist_params(data["observation"])
    _, _, kl = SeedSurrogates(data["observation"], data["action"], data["action_log_prob"],
                              data["advantage"].squeeze(-1), None, loc, scale)(model)
    fvp = SeedFisherVectorProduct(kl, model.actor_parameters(), 0.1)
    v = torch.randn_like(model.flat_actor)
    hv = fvp(v)
    w = v.clone()
    w[0] = 0.0
    torch.testing.assert_close(fvp(w)[1:], hv[1:], rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(fvp(w)[0], torch.zeros_like(v[0]), rtol=0, atol=0)
    assert (v * hv).sum(1).gt(0).all()  # positive definite with damping


# --------------------------------------------------------------------------- whole steps
@pytest.mark.parametrize("name", ["npg", "trpo"])
def test_natural_and_trpo_steps_match_single_seed(name):
    nets, batches = make_group()
    metrics = assert_same_as_single(name, nets, batches, [0.0, 0.0, 0.0])
    assert (metrics["Misc/AcceptanceStep"] >= 1).all()


@pytest.mark.parametrize("ks, cases", [
    ((-0.5, 0.5, 3.0), (2.0, 1.0, 0.0)),  # mixed: feasible, recoverable, infeasible recovery
    ((-3.0, -0.5, -0.1), (3.0, 2.0, 2.0)),  # all feasible: inactive constraint, then binding ones
    ((3.0, 6.0, 0.5), (0.0, 0.0, 1.0)),  # all infeasible
])
def test_cpo_seeds_take_their_own_cases(ks, cases):
    nets, batches = make_group()
    violations = [k * scale for k, scale in zip(ks, violation_scale(nets, batches))]
    metrics = assert_same_as_single("cpo", nets, batches, violations)
    assert tuple(metrics["Misc/CPOCase"].tolist()) == cases


def test_cpo_without_cost_gradient_is_case_4():
    nets, batches = make_group()
    batches[1]["cost_advantage"] = torch.zeros(N, 1)
    metrics = assert_same_as_single("cpo", nets, batches, [0.01, -1.0, -0.01])
    assert metrics["Misc/CPOCase"][1].item() == 4.0


@pytest.mark.parametrize("ks", [(-0.5, 0.5, 3.0), (0.2, -2.0, 1.0)])
def test_pcpo_step_matches_single_seed(ks):
    nets, batches = make_group()
    violations = [k * scale for k, scale in zip(ks, violation_scale(nets, batches))]
    assert_same_as_single("pcpo", nets, batches, violations)


def test_seeds_stop_at_their_own_trials_and_a_failed_search_keeps_its_seed():
    """Off-policy data (ratios far from 1) and saturated units make CPO's linear cost model wrong.

    Seed 0 backtracks to its 11th trial, seed 1 finds no candidate that lowers the cost surrogate
    (and keeps its parameters), seed 2 takes its first: later trials must not move the seeds that
    stopped earlier.
    """
    nets, batches = make_group(obs_scales=(100.0, 100.0, 1.0), off_policy=(3.0, 3.0, 0.0))
    metrics = assert_same_as_single("cpo", nets, batches, [0.1, 0.1, 0.1])
    assert metrics["Misc/AcceptanceStep"].tolist() == [11.0, 0.0, 1.0]
    assert metrics["Misc/FinalStepNorm"][1] == 0.0 and metrics["Train/KL"][1] == 0.0


def test_a_group_of_one_is_the_single_seed_step():
    nets, batches = make_group(obs_scales=(100.0, 1.0, 1.0), off_policy=(3.0, 0.0, 0.0))
    metrics = assert_same_as_single("cpo", nets[:1], batches[:1], [0.1])
    assert metrics["Misc/AcceptanceStep"].tolist() == [11.0]


def test_non_finite_candidates_are_rejected_per_seed():
    """Seed 1's cost surrogate is infinite: TRPO rejects all its candidates, the others step."""
    nets, batches = make_group()
    batches[1]["cost_advantage"][5] = math.inf
    metrics = assert_same_as_single("trpo", nets, batches, [0.0, 0.0, 0.0])
    assert metrics["Misc/AcceptanceStep"].tolist() == [1.0, 0.0, 1.0]


@pytest.mark.parametrize("name", ["trpo", "cpo"])
def test_float64_agreement(name):
    nets, batches = make_group(torch.float64)
    violations = [k * s for k, s in zip((-0.5, 0.5, 3.0), violation_scale(nets, batches))]
    assert_same_as_single(name, nets, batches, violations, dtype=torch.float64)


def test_options_pass_through():
    """SafePO's CPO dual and PCPO direction, and the papers' joint-distribution KL."""
    nets, batches = make_group()
    violations = [k * s for k, s in zip((-0.5, 0.5, 3.0), violation_scale(nets, batches))]
    assert_same_as_single("cpo", nets, batches, violations, safepo_dual=True)
    assert_same_as_single("pcpo", nets, batches, violations, use_hx_direction=True)
    assert_same_as_single("trpo", nets, batches, violations, kl_action_reduction="sum")


# --------------------------------------------------------------------------- inputs
def test_inputs_are_checked():
    nets, batches = make_group()
    model = StackedActorCritic.from_single(nets)
    data = stacked_batch(batches)
    adv, cost_adv = data["advantage"], data["cost_advantage"]
    with pytest.raises(ValueError, match="cost advantage"):
        StackedCPOStep(model).step(data, adv, None, [0.0] * 3)
    with pytest.raises(ValueError, match="one cost violation per seed"):
        StackedTRPOStep(model).step(data, adv, cost_adv, [0.0, 0.0])
    with pytest.raises(ValueError, match="advantage has shape"):
        StackedTRPOStep(model).step(data, adv.expand(3, N, 2), cost_adv, [0.0] * 3)
    with pytest.raises(ValueError, match="expected"):
        StackedTRPOStep(model).step({k: v[:2] for k, v in data.items()}, adv[:2], cost_adv[:2], [0.0] * 2)
    for bad in (dict(target_kl=0.0), dict(step_fraction=1.0), dict(cg_iters=0), dict(line_search_steps=-1)):
        with pytest.raises(ValueError):
            StackedTRPOStep(model, **bad)
    assert StackedTRPOStep(model).line_search_steps == StackedCPOStep(model).line_search_steps == 15
    assert STACKED_STEPS[PCPOStep](model).line_search_steps == 200
    assert STACKED_STEPS[NaturalPolicyStep](model).line_search_steps == 0
    # (S, N) advantages work as well as (S, N, 1); without a cost advantage TRPO's cost surrogate is 0
    metrics = StackedTRPOStep(model).step(data, adv.squeeze(-1), None, torch.zeros(3))
    assert (metrics["Misc/AcceptanceStep"] >= 1).all()
