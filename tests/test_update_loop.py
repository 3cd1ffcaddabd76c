"""The shared minibatch loop (sg_torchrl.objectives.passes) on a tiny linear model, and a seed group's passes.

What every caller relies on: the whole-batch order draws nothing, any callable is an order (called once
per pass with the generator), ``go_on`` runs after every pass and ends the loop, per-seed metrics are kept
as tensors without a host read per step, and a per-seed stop ends one seed's passes while the others go
on (``seed_passes``).
"""

from __future__ import annotations

import torch

torch.set_num_threads(1)

from tensordict import TensorDict  # noqa: E402
from torch import nn  # noqa: E402

from sg_torchrl.objectives.passes import RowMeans, run_passes, whole_batch  # noqa: E402

SIZE = 10


def make_batch() -> TensorDict:
    gen = torch.Generator().manual_seed(0)
    return TensorDict({"x": torch.randn(SIZE, 3, generator=gen), "y": torch.randn(SIZE, 1, generator=gen),
                       "i": torch.arange(SIZE)}, [SIZE])


class Model(nn.Module):
    """A linear head whose loss is ``a``; records the sample indices of each minibatch."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.a = nn.Linear(3, 1)
        self.seen: list[list[int]] = []

    def forward(self, td: TensorDict) -> dict[str, torch.Tensor]:
        self.seen.append(td["i"].tolist())
        return {"a": (self.a(td["x"]) - td["y"]).pow(2).mean()}


def make_step(model: Model):
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1)

    def step(minibatch):
        out = model(minibatch)
        optimizer.zero_grad()
        out["a"].backward()
        optimizer.step()
        return out, ()

    return step


def means() -> RowMeans:
    return RowMeans({"Loss/a": "a"}, (1,))


class TestGeneralisedLoop:
    def test_whole_batch_draws_nothing_from_the_generator(self):
        gen = torch.Generator().manual_seed(0)
        state = gen.get_state()
        model = Model()
        result = run_passes(make_batch(), make_step(model), passes=3, order=whole_batch, metrics=means(),
                            generator=gen)
        assert torch.equal(gen.get_state(), state) and result.passes == 3
        assert model.seen == [list(range(SIZE))] * 3

    def test_any_callable_is_an_order(self):
        calls = []

        def order(size, generator):
            calls.append((size, generator))
            return (torch.tensor([2, 3]), None, torch.tensor([9]))

        gen = torch.Generator().manual_seed(0)
        model = Model()
        result = run_passes(make_batch(), make_step(model), passes=2, order=order, metrics=means(), generator=gen)
        assert calls == [(SIZE, gen)] * 2 and result.passes == 2
        assert model.seen == [[2, 3], list(range(SIZE)), [9]] * 2

    def test_go_on_runs_after_every_pass_and_ends_the_loop(self):
        events = []

        def go_on() -> bool:
            events.append(len(model.seen))
            return len(events) < 2

        model = Model()
        result = run_passes(make_batch(), make_step(model), passes=5, order=whole_batch, metrics=means(), go_on=go_on)
        assert result.passes == 2 and len(model.seen) == 2 and events == [1, 2]

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
