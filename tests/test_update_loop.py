"""The shared minibatch loop (sg_torchrl.objectives.passes) on a tiny linear model, and a seed group's passes.

What every caller relies on: the KL stop ends the passes, the orders draw from the generator only
when they shuffle (chunks and slices of the same permutation agree), each clip group is clipped on
its own, and the after-step hook runs once per optimiser step. What the seed group adds through the
same loop: any callable order, a ``go_on`` decision after each pass, per-seed metrics kept as
tensors without a host read per step, and a per-seed stop that ends one seed's passes while the
others go on (``seed_passes``).
"""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)

from tensordict import TensorDict  # noqa: E402
from torch import nn  # noqa: E402

from sg_torchrl.objectives.passes import (  # noqa: E402
    ClipGroup,
    GradientStep,
    RowMeans,
    StepMeans,
    run_passes,
    shuffled_chunks,
    shuffled_slices,
    whole_batch,
)

SIZE = 10


def make_batch() -> TensorDict:
    gen = torch.Generator().manual_seed(0)
    return TensorDict({"x": torch.randn(SIZE, 3, generator=gen), "y": torch.randn(SIZE, 1, generator=gen),
                       "i": torch.arange(SIZE)}, [SIZE])


class Model(nn.Module):
    """Two linear heads whose losses are ``a`` and ``b``; records the sample indices of each minibatch."""

    def __init__(self, scale_b: float = 1.0) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.a, self.b = nn.Linear(3, 1), nn.Linear(3, 1)
        self.scale_b = scale_b
        self.seen: list[list[int]] = []

    def forward(self, td: TensorDict) -> dict[str, torch.Tensor]:
        self.seen.append(td["i"].tolist())
        loss_a = (self.a(td["x"]) - td["y"]).pow(2).mean()
        loss_b = self.scale_b * (self.b(td["x"]) - td["y"]).pow(2).mean()
        return {"a": loss_a, "b": loss_b, "ratio": torch.tensor(1.0)}


def make_step(model: Model, *, max_grad_norm: float = 1e6, groups=None, after_step=None, lr: float = 0.0):
    groups = groups if groups is not None else (ClipGroup(list(model.parameters())),)
    optimizer = torch.optim.SGD(model.parameters(), lr=lr)
    return GradientStep(model, optimizer, ("a", "b"), groups, max_grad_norm, after_step=after_step)


class TestOrders:
    def test_whole_batch_draws_nothing_from_the_generator(self):
        gen = torch.Generator().manual_seed(3)
        state = gen.get_state()
        model = Model()
        run_passes(make_batch(), make_step(model), passes=3, order=whole_batch, generator=gen)
        assert torch.equal(gen.get_state(), state)
        assert model.seen == [list(range(SIZE))] * 3
        assert shuffled_chunks(1) is whole_batch

    def test_slices_draw_one_permutation_per_pass(self):
        gen, reference = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
        model = Model()
        result = run_passes(make_batch(), make_step(model), passes=2, order=shuffled_slices(4), generator=gen)
        expected = []
        for _ in range(2):
            perm = torch.randperm(SIZE, generator=reference).tolist()
            expected += [perm[0:4], perm[4:8], perm[8:10]]
        assert model.seen == expected and result.passes == 2
        assert torch.equal(gen.get_state(), reference.get_state())
        # one slice covering the batch still shuffles it (the single-agent trainer's draws)
        model = Model()
        run_passes(make_batch(), make_step(model), passes=1, order=shuffled_slices(64), generator=gen)
        assert model.seen == [torch.randperm(SIZE, generator=reference).tolist()]

    def test_chunks_are_the_slices_of_ceil_size_over_k(self):
        seen = []
        for order in (shuffled_chunks(3), shuffled_slices(4)):  # ceil(10 / 3) = 4
            model = Model()
            run_passes(make_batch(), make_step(model), passes=2, order=order, generator=torch.Generator().manual_seed(5))
            seen.append(model.seen)
        assert seen[0] == seen[1] and [len(s) for s in seen[0]] == [4, 4, 2] * 2

    def test_bad_sizes_are_errors(self):
        with pytest.raises(ValueError):
            shuffled_slices(0)
        with pytest.raises(ValueError):
            shuffled_chunks(0)


class TestStop:
    def test_kl_over_target_ends_the_passes(self):
        kls = iter([0.001, 0.05, 0.0])
        calls = []

        def stop() -> float:
            calls.append(1)
            return next(kls)

        model = Model()
        result = run_passes(make_batch(), make_step(model), passes=5, order=whole_batch, stop=stop, target_kl=0.02)
        assert (result.passes, result.kl, len(calls), len(model.seen)) == (2, 0.05, 2, 2)

    def test_without_target_the_stop_runs_after_the_last_pass_only(self):
        calls = []
        model = Model()
        result = run_passes(make_batch(), make_step(model), passes=3, order=whole_batch,
                            stop=lambda: calls.append(1) or 0.5)
        assert (result.passes, result.kl, len(calls), len(model.seen)) == (3, 0.5, 1, 3)

    def test_no_stop_reports_zero_kl(self):
        result = run_passes(make_batch(), make_step(Model()), passes=2, order=whole_batch, target_kl=0.01)
        assert (result.passes, result.kl) == (2, 0.0)


class TestStep:
    def test_each_group_is_clipped_on_its_own(self):
        model = Model(scale_b=100.0)  # b's gradient is far larger than a's
        groups = (ClipGroup(list(model.a.parameters()), "norm_a"), ClipGroup(list(model.b.parameters()), "norm_b"))
        step = make_step(model, max_grad_norm=1.0, groups=groups)
        out, norms = step(make_batch())
        grad_norm = lambda m: torch.linalg.vector_norm(torch.cat([p.grad.reshape(-1) for p in m.parameters()]))  # noqa: E731
        assert norms[0] < 1.0 < norms[1]  # a under the threshold: untouched; b over it: clipped to 1
        assert grad_norm(model.a) == pytest.approx(float(norms[0]))
        assert grad_norm(model.b) == pytest.approx(1.0)
        # one group over both: b's norm dominates and a's gradient is scaled down with it
        model = Model(scale_b=100.0)
        make_step(model, max_grad_norm=1.0)(make_batch())
        assert grad_norm(model.a) < float(norms[0])

    def test_terms_are_summed_and_metrics_averaged(self):
        model = Model()
        batch = make_batch()
        expected = {key: value.item() for key, value in model(batch).items()}
        model.seen.clear()
        groups = (ClipGroup(list(model.a.parameters()), "norm_a"), ClipGroup(list(model.b.parameters())))
        result = run_passes(batch, make_step(model, groups=groups), passes=2, order=whole_batch,
                            metrics={"Loss/a": "a", "Loss/b": "b"})
        assert list(result.means) == ["Loss/a", "Loss/b", "norm_a"]  # the named group's norm follows
        assert result.means["Loss/a"] == pytest.approx(expected["a"])  # lr 0: the same loss at both steps
        assert result.means["Loss/b"] == pytest.approx(expected["b"])
        assert run_passes(batch, make_step(model), passes=1, order=whole_batch, metrics=("a",)).means.keys() == {"a"}

    def test_after_step_hook_runs_once_per_minibatch_after_the_optimiser_step(self):
        model = Model()
        before = model.a.weight.detach().clone()
        seen = []

        def hook(out) -> None:
            seen.append((sorted(out), torch.equal(model.a.weight, before)))

        step = make_step(model, after_step=hook, lr=0.1)
        run_passes(make_batch(), step, passes=2, order=shuffled_chunks(3), generator=torch.Generator().manual_seed(0))
        assert len(seen) == len(model.seen) == 6
        assert seen[0] == (["a", "b", "ratio"], False)  # the parameters had already moved

    def test_a_step_needs_a_term(self):
        model = Model()
        with pytest.raises(ValueError):
            GradientStep(model, torch.optim.SGD(model.parameters(), lr=0.1), (), (), 1.0)


class TestGeneralisedLoop:
    def test_any_callable_is_an_order(self):
        calls = []

        def order(size, generator):
            calls.append((size, generator))
            return (torch.tensor([2, 3]), None, torch.tensor([9]))

        gen = torch.Generator().manual_seed(0)
        model = Model()
        result = run_passes(make_batch(), make_step(model), passes=2, order=order, generator=gen)
        assert calls == [(SIZE, gen)] * 2 and result.passes == 2
        assert model.seen == [[2, 3], list(range(SIZE)), [9]] * 2

    def test_go_on_runs_after_every_pass_after_the_stop_and_ends_the_loop(self):
        events = []

        def stop() -> float:
            events.append("stop")
            return 0.0

        def go_on() -> bool:
            events.append("go_on")
            return len(events) < 4

        model = Model()
        result = run_passes(make_batch(), make_step(model), passes=5, order=whole_batch, stop=stop, target_kl=1.0,
                            go_on=go_on)
        assert result.passes == 2 and len(model.seen) == 2
        assert events == ["stop", "go_on", "stop", "go_on"]

    def test_step_means_are_the_default_metrics(self):
        batch, model = make_batch(), Model()
        means = StepMeans({"Loss/a": "a"})
        result = run_passes(batch, make_step(model), passes=2, order=whole_batch, metrics=means)
        expected = run_passes(batch, make_step(Model()), passes=2, order=whole_batch, metrics={"Loss/a": "a"})
        assert result.means == expected.means and means.steps == 2

    def test_row_means_average_each_row_over_its_own_steps_without_reading_them_back(self, monkeypatch):
        """Three rows (seeds); row r stops after pass r + 1: its mean is over its own steps only."""
        weights, values = [], iter(torch.arange(1.0, 19.0).view(6, 3))  # 2 steps per pass, 3 passes

        means = RowMeans({"Loss/x": "x"}, (3,))

        def step(minibatch):
            weights.append(means.weight.clone())
            return {"x": next(values).to(torch.float32)}, ()

        passes = iter(range(1, 10))

        def go_on() -> bool:
            done = next(passes)
            means.weight = (torch.arange(3) >= done).to(torch.float64)  # row `done - 1` stops now
            return bool(means.weight.any())

        def no_reads(self):
            raise AssertionError("a per-seed metric was read back during the passes")

        order = lambda size, generator: (torch.tensor([0]), torch.tensor([1]))  # noqa: E731
        with monkeypatch.context() as patch:
            patch.setattr(torch.Tensor, "item", no_reads)
            patch.setattr(torch.Tensor, "tolist", no_reads)
            result = run_passes(make_batch(), step, passes=5, order=order, metrics=means, go_on=go_on)
        assert result.passes == 3
        rows = torch.arange(1.0, 19.0, dtype=torch.float64).view(6, 3)
        expected = torch.stack([rows[:2, 0].mean(), rows[:4, 1].mean(), rows[:, 2].mean()])
        assert torch.equal(result.means["Loss/x"], expected)
        assert result.means["Loss/x"].dtype == torch.float64
        assert torch.equal(means.steps, torch.tensor([2.0, 4.0, 6.0], dtype=torch.float64))
        assert [w.tolist() for w in weights] == [[1.0] * 3] * 2 + [[0.0, 1.0, 1.0]] * 2 + [[0.0, 0.0, 1.0]] * 2


def synthetic_group(passes: int, target_kl: float):
    """A two-seed PPO-Lag group on synthetic data: seed 0's advantages are large (its KL stop fires
    after its first pass), seed 1's are zero (its actor never moves: KL 0, it runs every pass)."""
    import sg_torchrl
    from sg_torchrl.objectives.surrogates import ClipSurrogate, SeedBatchedObjective
    from sg_torchrl.train.fused import FusedFirstOrderStep, SeedShuffler
    from sg_torchrl.train.group_updates import GroupParts
    from sg_torchrl.modules import StackedActorCritic, make_actor_critics

    seeds, obs_dim, size = (3, 11), 6, 128
    action_spec = sg_torchrl.make("SafetyHalfCheetahVelocity-v1").action_spec
    nets = []
    for seed in seeds:
        torch.manual_seed(seed)
        nets.append(make_actor_critics(obs_dim, action_spec, [16, 16]))
    model = StackedActorCritic.from_single(nets)
    optimizer = FusedFirstOrderStep.make_optimizer(model, 1e-3, 1e-3, max_grad_norm=40.0)
    parts = GroupParts(model, optimizer, SeedShuffler(seeds), passes=passes, minibatch_size=32, target_kl=target_kl)
    step = FusedFirstOrderStep(model, optimizer, SeedBatchedObjective(ClipSurrogate(0.2), critic_l2=1e-3))
    generator = torch.Generator().manual_seed(0)
    obs = torch.randn(2, size, obs_dim, generator=generator)
    with torch.no_grad():
        action, log_prob, loc, scale = model.sample(obs, [torch.Generator().manual_seed(s) for s in seeds])
    data = {"observation": obs, "action": action, "action_log_prob": log_prob.unsqueeze(-1), "loc": loc,
            "scale": scale.expand_as(loc).clone()}
    for key in ("advantage", "cost_advantage", "value_target", "cost_value_target"):
        data[key] = torch.randn(2, size, 1, generator=generator)
    data["advantage"][0] *= 100.0
    data["advantage"][1] = 0.0
    data["cost_advantage"][1] = 0.0
    return parts, step, data


def test_a_seed_whose_kl_stop_fires_stops_while_the_other_goes_on():
    from sg_torchrl.train.group_updates import seed_passes

    lam, active = torch.zeros(2), torch.ones(2, dtype=torch.bool)
    parts, step, data = synthetic_group(passes=4, target_kl=1e-6)
    result = seed_passes(parts, step, data, lam, active, (data["loc"], data["scale"]))
    assert result.passes.tolist() == [1.0, 4.0] and not result.diverged.any()
    assert result.kl[0] > 1e-6 and result.kl[1] == 0.0
    # Adam counted 4 steps (128 / 32) for seed 0, 16 for seed 1; seed 0's generator drew one order
    assert parts.optimizer.state[0]["step"].tolist() == [4.0, 16.0]
    drawn = torch.Generator().manual_seed(3)
    torch.randperm(128, generator=drawn)
    assert torch.equal(parts.shuffler.generators[0].get_state(), drawn.get_state())
    # seed 0 ends where a single pass leaves it, bit for bit, while seed 1 went on
    once, step_once, data_once = synthetic_group(passes=1, target_kl=1e-6)
    alone = seed_passes(once, step_once, data_once, lam, active, (data_once["loc"], data_once["scale"]))
    for mine, single in zip(parts.model.flat_groups, once.model.flat_groups):
        assert torch.equal(mine[0], single[0])
    assert not torch.equal(parts.model.flat_critics[1], once.model.flat_critics[1])
    assert torch.equal(result.means[:, 0], alone.means[:, 0])
    # no seed left: nothing runs and nothing is drawn
    state = parts.shuffler.generators[1].get_state()
    none = seed_passes(parts, step, data, lam, torch.zeros(2, dtype=torch.bool), (data["loc"], data["scale"]))
    assert none.passes.tolist() == [0.0, 0.0] and torch.equal(parts.shuffler.generators[1].get_state(), state)
