"""Seed-stacked networks and the fused first-order step agree with the single-seed code, seed by seed.

A seed group must train each seed exactly as its single-seed run would (DESIGN.md, "Many seeds in
one process"). These tests compare, on synthetic rollout batches, the stacked networks
(:mod:`sg_torchrl.modules.stacked`), the fused losses and step (:mod:`sg_torchrl.train.fused`) and
the masked Adam (:mod:`sg_torchrl.train.seed_adam`) with the modules, losses and optimiser the
single-seed trainer uses (``make_actor_critics``, ``PPOLagLoss`` & co. with ``functional=False``,
``clip_grad_norm_``, ``torch.optim.Adam``), seed slice by seed slice.

Tolerances: network outputs 1e-6 (absolute; batched matmuls sum in another order than ``addmm``);
losses and gradients 1e-5 relative (plus 1e-6 absolute for entries near zero); Adam and the clip
1e-6 relative; a masked seed's state is compared bit for bit; a seed's trajectory in a group of
three against a group of one over nine steps, 1e-5 relative and 1e-6 absolute (the actor's is
identical; the critics' last layer, one output column, takes another matmul kernel for one seed
than for three); S = 1 against the trainer's own loop over six steps, 1e-5 relative.
"""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)

from tensordict import TensorDict  # noqa: E402
from torchrl.data import Bounded  # noqa: E402

from sg_torchrl.objectives import (  # noqa: E402
    CUPLoss,
    FOCOPSLoss,
    LagrangeMultiplier,
    NoMultiplier,
    PGLoss,
    PIDLagrangeMultiplier,
    PPOLagLoss,
    gaussian_kl,
)
from sg_torchrl.objectives.surrogates import ClipSurrogate, SeedBatchedObjective  # noqa: E402
from sg_torchrl.train.fused import (  # noqa: E402
    FusedFirstOrderStep,
    SeedBatch,
    SeedShuffler,
    batch_kl,
    multiplier_values,
)
from sg_torchrl.modules import StackedActorCritic, StackedMLP, gaussian_log_prob, make_actor_critics  # noqa: E402
from sg_torchrl.train.seed_adam import SeedMaskedAdam, clip_grad_norm_per_seed_  # noqa: E402

OBS, ACT, HIDDEN, N = 17, 6, [64, 64], 96
SEEDS = (3, 11, 42)
SPEC = Bounded(-1.0, 1.0, shape=(ACT,))
LOSS_RTOL, LOSS_ATOL = 1e-5, 1e-6


# --------------------------------------------------------------------------- helpers
def single_networks(seed: int):
    """What the trainer builds for ``seed``: ``torch.manual_seed(seed)`` then ``make_actor_critics``."""
    torch.manual_seed(seed)
    return make_actor_critics(OBS, SPEC, HIDDEN)


def rollout_batch(seed: int, actor, size: int = N) -> TensorDict:
    """A rollout-like flat batch of the actor (log-probs perturbed so ratios differ from 1)."""
    gen = torch.Generator().manual_seed(1000 + seed)
    obs = torch.randn(size, OBS, generator=gen)
    with torch.no_grad():
        data = actor(TensorDict(observation=obs, batch_size=[size]))
    data["action_log_prob"] = data["action_log_prob"] + 0.3 * torch.randn(size, generator=gen)
    for key in ("advantage", "cost_advantage", "value_target", "cost_value_target"):
        data[key] = torch.randn(size, 1, generator=gen)
    # The stored rollout loc drifts from the current policy's, so that FOCOPS's per-sample trust
    # region keeps some samples and drops others.
    data["loc"] = data["loc"] + 0.08 * torch.randn(size, ACT, generator=gen)
    data["stage1_loc"] = data["loc"] + 0.1 * torch.randn(size, ACT, generator=gen)
    data["stage1_scale"] = data["scale"] * 1.1
    return data


def stack_batches(batches, keys) -> SeedBatch:
    return SeedBatch.pack({key: torch.stack([b[key] for b in batches]) for key in keys})


def single_parameters(actor, critic, cost_critic, which: str):
    """The single modules' parameters in the stacked model's flat order (``which``: actor / critics)."""
    if which == "actor":
        mlp = actor.module[0].module[0]
        return [*mlp.parameters(), actor.module[0].module[1].state_independent_scale]
    return [*critic.module.parameters(), *cost_critic.module.parameters()]


def stacked_slices(model: StackedActorCritic, seed: int, which: str, grad: bool = False):
    """Seed ``seed``'s parameters (or gradients) of ``model`` in the single modules' layout."""
    def pick(p):
        return p.grad if grad else p

    def mlp(net):
        out = []
        for w, b in zip(net.weights, net.biases):
            out += [pick(w)[seed].T, pick(b)[seed, 0]]
        return out

    if which == "actor":
        return [*mlp(model.actor_mean), pick(model.log_std)[seed]]
    return [*mlp(model.critic), *mlp(model.cost_critic)]


def assert_all_close(actual, expected, rtol, atol=0.0):
    assert len(actual) == len(expected)
    for a, e in zip(actual, expected):
        torch.testing.assert_close(a, e, rtol=rtol, atol=atol)


@pytest.fixture(scope="module")
def group():
    """Three seeds' single networks, their stacked group and their rollout batches."""
    nets = [single_networks(seed) for seed in SEEDS]
    batches = [rollout_batch(seed, nets[i][0]) for i, seed in enumerate(SEEDS)]
    return nets, batches


# --------------------------------------------------------------------------- (a) outputs
def test_stacked_mlp_matches_each_module():
    modules = [single_networks(seed)[1].module for seed in SEEDS]
    stacked = StackedMLP.from_modules(modules)
    x = torch.randn(len(SEEDS), 32, OBS)
    out = stacked(x)
    for s, module in enumerate(modules):
        torch.testing.assert_close(out[s], module(x[s]), rtol=0, atol=1e-6)
        torch.testing.assert_close(stacked.export(s)(x[s]), module(x[s]), rtol=0, atol=0)
        assert stacked.export(s).state_dict().keys() == module.state_dict().keys()


def test_actor_critic_matches_single_modules(group):
    nets, _ = group
    model = StackedActorCritic.from_single(nets)
    x = torch.randn(len(SEEDS), 32, OBS)
    action = torch.randn(len(SEEDS), 32, ACT)
    loc, scale = model.dist_params(x)
    log_prob = gaussian_log_prob(action, loc, scale)
    value, cost_value = model.values(x)
    for s, (actor, critic, cost_critic) in enumerate(nets):
        td = TensorDict(observation=x[s], action=action[s], batch_size=[32])
        dist = actor.get_dist(td)
        torch.testing.assert_close(loc[s], dist.base_dist.loc, rtol=0, atol=1e-6)
        torch.testing.assert_close(scale[s].expand(32, ACT), dist.base_dist.scale, rtol=0, atol=1e-6)
        torch.testing.assert_close(log_prob[s], dist.log_prob(action[s]), rtol=0, atol=1e-5)
        torch.testing.assert_close(value[s], critic(td)["state_value"].squeeze(-1), rtol=0, atol=1e-6)
        torch.testing.assert_close(cost_value[s], cost_critic(td)["cost_value"].squeeze(-1), rtol=0, atol=1e-6)


def test_export_and_reload_round_trip(group):
    nets, _ = group
    model = StackedActorCritic.from_single(nets)
    for s, triple in enumerate(nets):
        exported = model.export_seed(s, SPEC)
        for mine, theirs in zip(exported, triple):
            assert mine.state_dict().keys() == theirs.state_dict().keys()
            for key, value in theirs.state_dict().items():
                torch.testing.assert_close(mine.state_dict()[key], value, rtol=0, atol=0)
    fresh = StackedActorCritic(len(SEEDS), OBS, ACT, HIDDEN)
    fresh.load_seed(1, *nets[1])
    assert_all_close(stacked_slices(fresh, 1, "actor"), single_parameters(*nets[1], "actor"), rtol=0)
    assert_all_close(stacked_slices(fresh, 1, "critics"), single_parameters(*nets[1], "critics"), rtol=0)


def test_parameters_are_views_of_the_flat_buffers(group):
    model = StackedActorCritic.from_single(group[0])
    for which, flat in (("actor", model.flat_actor), ("critics", model.flat_critics)):
        params = model.actor_parameters() if which == "actor" else [*model.critic.parameters(),
                                                                     *model.cost_critic.parameters()]
        assert sum(p[0].numel() for p in params) == flat.shape[1]
        assert all(p.untyped_storage().data_ptr() == flat.untyped_storage().data_ptr() for p in params)
        assert all(p.grad.untyped_storage().data_ptr() == flat.grad.untyped_storage().data_ptr() for p in params)
    with torch.no_grad():
        model.flat_actor.add_(1.0)
    torch.testing.assert_close(model.log_std, torch.ones_like(model.log_std) + torch.stack(
        [t[0].module[0].module[1].state_independent_scale for t in group[0]]))
    model.flat_critics.grad.fill_(1.0)
    model.zero_grad()  # in place: set_to_none would cut the parameters from the flat gradients
    assert all(p.grad is not None for p in model.parameters()) and not model.flat_critics.grad.any()
    double = StackedActorCritic.from_single(group[0]).double()
    assert double.flat_critics.dtype == torch.float64
    assert double.critic.weights[0].untyped_storage().data_ptr() == double.flat_critics.untyped_storage().data_ptr()


# --------------------------------------------------------------------------- (b) losses and gradients
def _multipliers(kind: str):
    """One multiplier per seed, moved to different values."""
    out = []
    for i, _ in enumerate(SEEDS):
        if kind == "lagrange":
            m = LagrangeMultiplier(cost_limit=25.0)
        elif kind == "lagrange_capped":
            m = LagrangeMultiplier(cost_limit=25.0, upper_bound=2.0)
        elif kind == "pid":
            m = PIDLagrangeMultiplier(cost_limit=25.0)
        elif kind == "pid_diff":
            m = PIDLagrangeMultiplier(cost_limit=25.0, diff_norm=True, sum_norm=False)
        elif kind == "plain":
            m = LagrangeMultiplier(cost_limit=25.0, sum_norm=False)
        else:
            m = NoMultiplier(cost_limit=25.0)
        for _ in range(3 + 4 * i):
            m.update(25.0 + 20.0 * (i + 1))
        out.append(m)
    return out


CASES = {
    "ppo_lag": (PPOLagLoss, "lagrange", {}),
    "ppo_lag_plain": (PPOLagLoss, "plain", {}),
    "cppo_pid": (PPOLagLoss, "pid", {}),
    "cppo_pid_diff_norm": (PPOLagLoss, "pid_diff", {}),
    "ppo": (PPOLagLoss, "none", {}),
    "pg": (PGLoss, "none", {}),
    "pg_lagrangian": (PGLoss, "lagrange", {}),
    "focops": (FOCOPSLoss, "lagrange_capped", {"temperature": 1.5, "target_kl": 0.02}),
    "focops_safepo_broadcast": (FOCOPSLoss, "lagrange_capped", {"target_kl": 0.02, "safepo_broadcast": True}),
    "cup_projection": (CUPLoss, "lagrange_capped", {"gamma": 0.99, "cup_lambda": 0.95}),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_fused_losses_and_gradients_match_single_seed_losses(group, case):
    loss_class, kind, options = CASES[case]
    nets, batches = group
    multipliers = _multipliers(kind)
    # As sg_torchrl.train.algorithms builds them: critic_l2 as the trainer sets it, functional=False.
    losses = [loss_class(*triple, m, critic_l2_coeff=1e-3, functional=False, **options)
              for triple, m in zip(nets, multipliers)]
    spec = losses[0].seed_batched_objective()
    model = StackedActorCritic.from_single(nets)
    step = FusedFirstOrderStep(model, FusedFirstOrderStep.make_optimizer(model, 3e-4, 3e-4), spec)
    batch = stack_batches(batches, spec.fields)
    lam = multiplier_values(multipliers)
    returned = step.backward(batch, lam)
    diagnostics = spec.diagnostics(model, batch.fields(), lam)
    for s, (triple, loss, data) in enumerate(zip(nets, losses, batches)):
        for p in [*triple[0].parameters(), *triple[1].parameters(), *triple[2].parameters()]:
            p.grad = None
        out = loss(data.select(*loss.in_keys))
        terms = ["loss_objective"] if spec.actor_only else ["loss_objective", "loss_critic", "loss_cost_critic"]
        sum(out[t] for t in terms).backward()
        for t in terms:
            torch.testing.assert_close(diagnostics[t][s], out[t].detach(), rtol=LOSS_RTOL, atol=LOSS_ATOL)
        torch.testing.assert_close(returned[0][s], out["loss_objective"].detach(), rtol=LOSS_RTOL, atol=LOSS_ATOL)
        groups = ["actor"] if spec.actor_only else ["actor", "critics"]
        for which in groups:
            expected = [p.grad for p in single_parameters(*triple, which)]
            assert_all_close(stacked_slices(model, s, which, grad=True), expected, LOSS_RTOL, LOSS_ATOL)
        if "clip_fraction" in out.keys():
            torch.testing.assert_close(diagnostics["clip_fraction"][s], out["clip_fraction"], rtol=0, atol=0)
        if "kl_mask_fraction" in out.keys():  # the trust region keeps some samples and drops others
            assert 0.0 < float(out["kl_mask_fraction"]) < 1.0
            torch.testing.assert_close(diagnostics["kl_mask_fraction"][s], out["kl_mask_fraction"], rtol=0, atol=0)


def test_seed_batched_objective_rejects_what_the_fused_step_lacks(group):
    triple = group[0][0]
    with pytest.raises(ValueError, match="clip_value"):
        PPOLagLoss(*triple, NoMultiplier(), clip_value=0.2, functional=False).seed_batched_objective()
    with pytest.raises(ValueError, match="entropy_bonus"):
        PPOLagLoss(*triple, NoMultiplier(), entropy_coeff=0.01, functional=False).seed_batched_objective()


# --------------------------------------------------------------------------- (c, d) Adam and clip
def _stacked_tensors(seeds: int, gen: torch.Generator):
    return [torch.randn(seeds, 4, 5, generator=gen), torch.randn(seeds, 1, 5, generator=gen),
            torch.randn(seeds, 6, generator=gen)]


@pytest.mark.parametrize("fused", [False, True])
def test_seed_masked_adam_tracks_torch_adam(fused):
    gen = torch.Generator().manual_seed(0)
    seeds = 3
    group_a, group_b = _stacked_tensors(seeds, gen), _stacked_tensors(seeds, gen)[:2]
    adam = SeedMaskedAdam([{"params": group_a, "lr": 3e-4}, {"params": group_b, "lr": 1e-3}])
    singles = []
    for s in range(seeds):
        a = [t[s].clone().requires_grad_() for t in group_a]
        b = [t[s].clone().requires_grad_() for t in group_b]
        singles.append((a, b, torch.optim.Adam([{"params": a, "lr": 3e-4}, {"params": b, "lr": 1e-3}],
                                               fused=fused or None)))
    for step in range(6):
        for t in group_a + group_b:
            t.grad = torch.randn(t.shape, generator=gen) * (10.0 ** (step % 3 - 1))
        for s, (a, b, opt) in enumerate(singles):
            for mine, theirs in zip(group_a + group_b, a + b):
                theirs.grad = mine.grad[s].clone()
        if step == 3:  # the actor's learning rate is annealed between epochs
            adam.param_groups[0]["lr"] = 2e-4
            for _, _, opt in singles:
                opt.param_groups[0]["lr"] = 2e-4
        adam.step()
        for s, (a, b, opt) in enumerate(singles):
            opt.step()
            moments = [opt.state[p] for p in a + b]
            mine = adam.state[0]["exp_avg_sq"] + adam.state[1]["exp_avg_sq"]
            if fused:  # the fused kernel rounds its own way
                assert_all_close([t[s] for t in group_a + group_b], [t.detach() for t in a + b], rtol=1e-6, atol=1e-7)
                assert_all_close([t[s] for t in mine], [m["exp_avg_sq"] for m in moments], rtol=1e-6, atol=1e-12)
            else:  # the CPU default (single-tensor) implementation: the same arithmetic, bit for bit
                for got, want in zip([t[s] for t in group_a + group_b] + [t[s] for t in mine],
                                     [t.detach() for t in a + b] + [m["exp_avg_sq"] for m in moments], strict=True):
                    assert torch.equal(got, want)
    assert adam.state[0]["step"].tolist() == [6.0] * seeds


def test_masked_seed_does_not_move_while_others_track_adam():
    gen = torch.Generator().manual_seed(1)
    seeds = 3
    params = _stacked_tensors(seeds, gen)
    adam = SeedMaskedAdam([{"params": params, "lr": 1e-2}], max_grad_norm=1.0)
    reference = [t.clone() for t in params]
    ref_adam = SeedMaskedAdam([{"params": reference, "lr": 1e-2}], max_grad_norm=1.0)
    frozen = None
    for step in range(5):
        for t, r in zip(params, reference):
            t.grad = torch.randn(t.shape, generator=gen)
            r.grad = t.grad.clone()
        active = torch.tensor([True, step < 2, True])
        if step == 2:
            state = adam.state[0]
            frozen = ([t[1].clone() for t in params], [t[1].clone() for t in state["exp_avg"]],
                      [t[1].clone() for t in state["exp_avg_sq"]], state["step"][1].clone())
        adam.step(active)
        ref_adam.step()
        for s in (0, 2):  # active seeds: exactly as without a mask
            assert_all_close([t[s] for t in params], [r[s] for r in reference], rtol=1e-6, atol=1e-7)
    state = adam.state[0]
    after = ([t[1] for t in params], [t[1] for t in state["exp_avg"]], [t[1] for t in state["exp_avg_sq"]],
             state["step"][1])
    for before_part, after_part in zip(frozen[:3], after[:3]):
        assert all(torch.equal(x, y) for x, y in zip(before_part, after_part))
    assert torch.equal(frozen[3], after[3]) and float(after[3]) == 2.0


def test_adam_groups_argument_leaves_other_groups_alone():
    gen = torch.Generator().manual_seed(2)
    a, b = _stacked_tensors(2, gen)[:1], _stacked_tensors(2, gen)[:1]
    adam = SeedMaskedAdam([{"params": a, "lr": 1e-2}, {"params": b, "lr": 1e-2}])
    a[0].grad, b[0].grad = torch.randn(a[0].shape, generator=gen), torch.randn(b[0].shape, generator=gen)
    before = b[0].clone()
    adam.step(groups=[0])
    assert torch.equal(b[0], before) and adam.state[1]["step"].tolist() == [0.0, 0.0]
    assert adam.state[0]["step"].tolist() == [1.0, 1.0]


def test_adam_seed_rows_read_write_and_restore_touch_one_seed():
    gen = torch.Generator().manual_seed(4)

    def stepped(seeds: int, steps: int) -> SeedMaskedAdam:
        adam = SeedMaskedAdam([{"params": _stacked_tensors(seeds, gen), "lr": 1e-2},
                               {"params": _stacked_tensors(seeds, gen)[:1], "lr": 1e-3}])
        for _ in range(steps):
            for group in adam.param_groups:
                for t in group["params"]:
                    t.grad = torch.randn(t.shape, generator=gen)
            adam.step(torch.tensor([True] * (seeds - 1) + [False]))
        return adam

    def rows(adam: SeedMaskedAdam, seed: int) -> list[torch.Tensor]:
        return [t[seed] for state in adam.state for t in [state["step"], *state["exp_avg"], *state["exp_avg_sq"]]]

    source, target = stepped(3, 3), stepped(2, 1)
    saved = source.seed_state_dict(1)
    assert all(t.device.type == "cpu" for group in saved for t in [group["step"], *group["exp_avg"]])
    other = [t.clone() for t in rows(target, 1)]
    target.load_seed_state_dict(0, saved)
    assert all(torch.equal(x, y) for x, y in zip(rows(target, 0), rows(source, 1)))
    assert all(torch.equal(x, y) for x, y in zip(rows(target, 1), other))  # the other seed is untouched
    with pytest.raises(ValueError):  # a state of another group count is refused
        target.load_seed_state_dict(0, saved[:1])

    snapshot = source.state_dict()
    before = [[t.clone() for t in rows(source, s)] for s in range(3)]
    for group in source.param_groups:
        for t in group["params"]:
            t.grad = torch.randn(t.shape, generator=gen)
    source.step()
    moved = [[t.clone() for t in rows(source, s)] for s in range(3)]
    source.restore_seeds(torch.tensor([False, True, False]), snapshot)
    assert all(torch.equal(x, y) for x, y in zip(rows(source, 1), before[1]))
    for s in (0, 2):
        assert all(torch.equal(x, y) for x, y in zip(rows(source, s), moved[s]))


def test_per_seed_clip_matches_clip_grad_norm():
    gen = torch.Generator().manual_seed(3)
    grads = [torch.randn(4, 8, 3, generator=gen), torch.randn(4, 1, 3, generator=gen), torch.randn(4, 5, generator=gen)]
    grads[0][1] *= 100.0  # seed 1 far above the limit, seed 3 below it
    for g in grads:
        g[3] *= 1e-3
    expected_norms, expected = [], []
    for s in range(4):
        params = [torch.zeros(g.shape[1:], requires_grad=True) for g in grads]
        for p, g in zip(params, grads):
            p.grad = g[s].clone()
        expected_norms.append(torch.nn.utils.clip_grad_norm_(params, 5.0, foreach=True))
        expected.append([p.grad for p in params])
    norms = clip_grad_norm_per_seed_(grads, 5.0)
    torch.testing.assert_close(norms, torch.stack(expected_norms), rtol=1e-6, atol=0)
    for s in range(4):
        assert_all_close([g[s] for g in grads], expected[s], rtol=1e-6, atol=1e-9)


# --------------------------------------------------------------------------- (e) trajectories
def _run_group(seed_ids, nets, batches, steps_per_pass: int, passes: int, spec: SeedBatchedObjective, lam_of):
    """A seed group's minibatch passes with per-seed KL stops; returns each step's parameters of every seed."""
    model = StackedActorCritic.from_single([nets[i] for i in seed_ids])
    optimizer = FusedFirstOrderStep.make_optimizer(model, 3e-4, 3e-4, max_grad_norm=40.0)
    step = FusedFirstOrderStep(model, optimizer, spec)
    batch = stack_batches([batches[i] for i in seed_ids], (*spec.fields, "loc", "scale"))
    shuffler = SeedShuffler([SEEDS[i] for i in seed_ids])
    lam = torch.stack([lam_of[i] for i in seed_ids])
    obs, old_loc, old_scale = batch["observation"], batch["loc"], batch["scale"]
    active = torch.ones(len(seed_ids), dtype=torch.bool)
    history = []
    for pass_index in range(passes):
        for index in list(shuffler.minibatches(N, N // steps_per_pass)):
            step(batch.gather(index), lam, active)
            history.append([model.flat_actor.clone(), model.flat_critics.clone()])
        optimizer.param_groups[0]["lr"] *= 0.5
        kl = batch_kl(model, obs, old_loc, old_scale)
        # A seed-dependent stop, as the KL threshold gives: SEEDS[0] stops after its second pass.
        active &= torch.tensor([SEEDS[i] != SEEDS[0] or pass_index < 1 for i in seed_ids]) & (kl >= 0)
    return history


def test_seed_in_a_group_of_three_moves_as_in_a_group_of_one(group):
    nets, batches = group
    spec = SeedBatchedObjective(ClipSurrogate(0.2), combine="sum_norm")
    lam_of = [torch.tensor(v) for v in (0.2, 0.5, 1.5)]
    batches = [b.clone().set("advantage", b["advantage"] * 50) for b in batches]  # big steps: ratios leave the clip range
    three = _run_group([0, 1, 2], nets, batches, 3, 3, spec, lam_of)
    one = _run_group([1], nets, batches, 3, 3, spec, lam_of)
    first = _run_group([0], nets, batches, 3, 3, spec, lam_of)
    for group_step, single_step, first_step in zip(three, one, first):
        for flat3, flat1, flat_first in zip(group_step, single_step, first_step):
            # Not bit-identical: a batched matmul with one output column (the critics' last layer)
            # takes another kernel for one seed than for three (last-bit differences, then Adam).
            torch.testing.assert_close(flat3[1], flat1[0], rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(flat3[0], flat_first[0], rtol=1e-5, atol=1e-6)
    # SEEDS[0] stopped after two passes (6 steps) while the others went on
    assert not torch.equal(three[4][0][0], three[5][0][0])
    assert torch.equal(three[5][0][0], three[-1][0][0]) and not torch.equal(three[5][0][1], three[-1][0][1])


def test_group_of_one_tracks_the_trainer_loop(group):
    """S = 1 against what ``minibatch_passes`` does: PPOLagLoss, clip_grad_norm_, fused torch Adam."""
    nets, batches = group
    seed_index = 2
    actor, critic, cost_critic = single_networks(SEEDS[seed_index])
    multiplier = _multipliers("lagrange")[seed_index]
    loss = PPOLagLoss(actor, critic, cost_critic, multiplier, clip_epsilon=0.2, critic_l2_coeff=1e-3, functional=False)
    critic_params = [*critic.parameters(), *cost_critic.parameters()]
    optimizer = torch.optim.Adam([{"params": list(actor.parameters()), "lr": 3e-4},
                                  {"params": critic_params, "lr": 1e-3}], fused=True)
    parameters = [*actor.parameters(), *critic_params]
    rng = torch.Generator().manual_seed(SEEDS[seed_index])
    data = batches[seed_index].select(*loss.in_keys)

    model = StackedActorCritic.from_single([nets[seed_index]])
    spec = loss.seed_batched_objective()
    step = FusedFirstOrderStep(model, FusedFirstOrderStep.make_optimizer(model, 3e-4, 1e-3, max_grad_norm=40.0), spec)
    stacked = stack_batches([batches[seed_index]], spec.fields)
    shuffler = SeedShuffler([SEEDS[seed_index]])
    lam = multiplier_values([multiplier])
    for _ in range(2):
        order = torch.randperm(N, generator=rng)
        group_order = shuffler.permutation(N)
        assert torch.equal(order, group_order[0])
        for start in range(0, N, 32):
            out = loss(data[order[start : start + 32]])
            optimizer.zero_grad(set_to_none=True)
            (out["loss_objective"] + out["loss_critic"] + out["loss_cost_critic"]).backward()
            torch.nn.utils.clip_grad_norm_(parameters, 40.0, foreach=True)
            optimizer.step()
            step(stacked.gather(group_order[:, start : start + 32]), lam)
            for which in ("actor", "critics"):
                assert_all_close(stacked_slices(model, 0, which), single_parameters(actor, critic, cost_critic, which),
                                 rtol=1e-5, atol=1e-6)


# --------------------------------------------------------------------------- (f) sampling, order, KL
def test_seed_draws_the_same_actions_whatever_the_group_size(group):
    nets, _ = group
    obs = torch.randn(len(SEEDS), 8, OBS)
    three = StackedActorCritic.from_single(nets)
    one = StackedActorCritic.from_single([nets[1]])
    gens3 = [torch.Generator().manual_seed(100 + seed) for seed in SEEDS]
    gens1 = [torch.Generator().manual_seed(100 + SEEDS[1])]
    for _ in range(3):
        action3, log_prob3, _, _ = three.sample(obs, gens3)
        action1, log_prob1, _, _ = one.sample(obs[1:2], gens1)
        assert torch.equal(action3[1], action1[0]) and torch.equal(log_prob3[1], log_prob1[0])
    actor = nets[1][0]
    dist = actor.get_dist(TensorDict(observation=obs[1], batch_size=[8]))
    torch.testing.assert_close(log_prob3[1], dist.log_prob(action3[1]), rtol=0, atol=1e-5)
    mean, _, _, _ = three.sample(obs, gens3, deterministic=True)
    torch.testing.assert_close(mean[1], dist.base_dist.loc, rtol=0, atol=1e-6)


def test_minibatch_order_and_gather():
    shuffler = SeedShuffler(SEEDS)
    order = shuffler.permutation(50)
    for s, seed in enumerate(SEEDS):
        assert torch.equal(order[s], torch.randperm(50, generator=torch.Generator().manual_seed(seed)))
    data = torch.arange(len(SEEDS) * 50 * 2, dtype=torch.float32).view(len(SEEDS), 50, 2)
    batch = SeedBatch.pack({"x": data[..., 0], "y": data})
    index = order[:, :7]
    mini = batch.gather(index)
    for s in range(len(SEEDS)):
        assert torch.equal(mini["y"][s], data[s, index[s]]) and torch.equal(mini["x"][s, :, 0], data[s, index[s], 0])
    blocks = list(SeedShuffler(SEEDS).minibatches(50, 16))
    assert [b.shape for b in blocks] == [(3, 16)] * 3 + [(3, 2)]
    state = shuffler.state_dict()
    again = shuffler.permutation(10)
    shuffler.load_state_dict(state)
    assert torch.equal(shuffler.permutation(10), again)


def test_batch_kl_matches_the_trainer_statistic(group):
    nets, batches = group
    model = StackedActorCritic.from_single(nets)
    with torch.no_grad():
        model.log_std.add_(0.1)
        model.actor_mean.biases[-1].add_(0.05)
    obs = torch.stack([b["observation"] for b in batches])
    loc = torch.stack([b["loc"] for b in batches])
    scale = torch.stack([b["scale"] for b in batches])
    kl = batch_kl(model, obs, loc, scale)
    chunked = batch_kl(model, obs, loc, scale, chunk_size=40)
    current_loc, current_scale = model.dist_params(obs)
    for s in range(len(SEEDS)):
        expected = gaussian_kl(loc[s], scale[s], current_loc[s].detach(), current_scale[s].detach().expand_as(loc[s]))
        torch.testing.assert_close(kl[s], expected.mean(), rtol=1e-6, atol=0)
        torch.testing.assert_close(chunked[s], expected.mean(), rtol=1e-5, atol=0)
    assert (kl > 0).all()
