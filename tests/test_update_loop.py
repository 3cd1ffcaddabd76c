"""The shared minibatch loop (sg_torchrl.objectives.passes) on a tiny linear model.

What every caller relies on: the KL stop ends the passes, the orders draw from the generator only
when they shuffle (chunks and slices of the same permutation agree), each clip group is clipped on
its own, and the after-step hook runs once per optimiser step.
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


def test_multi_agent_steps_clip_each_network_separately():
    from sg_torchrl.objectives.multi_agent import MAPPOLagUpdate, make_multi_agent_networks

    torch.manual_seed(0)
    nets = make_multi_agent_networks(4, [2, 1], 5, hidden_sizes=(8,))
    update = MAPPOLagUpdate(nets)
    loss = update.losses[1]
    step = update._gradient_step(1, loss, ("loss_objective",), actor=True)
    networks = (nets.agent_actor(1), nets.agent_critic(1), nets.agent_cost_critic(1))
    assert [list(group.parameters) for group in step.clip_groups] == [list(m.parameters()) for m in networks]
    assert [group.norm_metric for group in step.clip_groups] == [None, "Misc/Reward_critic_norm", "Misc/Cost_critic_norm"]
    critics = update._gradient_step(1, loss.critic_losses, ("loss_critic",), actor=False)
    assert len(critics.clip_groups) == 2 and critics.optimizer is update.optimizers[1]
