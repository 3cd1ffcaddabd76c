"""The engine trains each loss through the loss object's own seed-batched form, and refuses what has none.

* every built-in first-order loss hands the engine its own :class:`Surrogate` (the one definition);
* a new algorithm written as one Surrogate plus one loss subclass (``objectives/pessimistic.py``)
  trains on the engine with the LossModule's exact gradients, and its penalty changes the update;
* a loss without a seed-batched form (a stock TorchRL loss, a subclass that overrides the math
  hooks) is refused with an error naming the problem, never trained as another algorithm.
"""
from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.objectives import ClipPPOLoss

from sg_torchrl.objectives import (
    CUPLoss,
    FOCOPSLoss,
    LagrangeMultiplier,
    NoMultiplier,
    PessimisticPPOLagLoss,
    PGLoss,
    PPOLagLoss,
)
from sg_torchrl.objectives.multi_agent.loss import AgentPPOLoss
from sg_torchrl.objectives.pessimistic import PessimisticCostSurrogate
from sg_torchrl.objectives.surrogates import (
    ClipSurrogate,
    CUPProjectionSurrogate,
    FOCOPSSurrogate,
    PGSurrogate,
    SeedBatchedObjective,
)
from sg_torchrl.train.fused import FusedFirstOrderStep, SeedBatch, multiplier_values, objective_of
from sg_torchrl.modules import StackedActorCritic, make_actor_critics

OBS, ACT, N = 7, 3, 64
SPEC = Bounded(-1.0, 1.0, shape=(ACT,))
SEEDS = (0, 5)


def _example():
    path = Path(__file__).resolve().parents[1] / "examples" / "add_an_algorithm.py"
    spec = importlib.util.spec_from_file_location("add_an_algorithm", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _networks(seed: int):
    torch.manual_seed(seed)
    return make_actor_critics(OBS, SPEC, [16, 16])


def _batch(seed: int, actor) -> TensorDict:
    gen = torch.Generator().manual_seed(100 + seed)
    with torch.no_grad():
        data = actor(TensorDict(observation=torch.randn(N, OBS, generator=gen), batch_size=[N]))
    data["action_log_prob"] = data["action_log_prob"] + 0.5 * torch.randn(N, generator=gen)  # ratios leave the clip
    for key in ("advantage", "cost_advantage", "value_target", "cost_value_target"):
        data[key] = torch.randn(N, 1, generator=gen)
    return data


def _f32(value: float) -> float:
    """``value`` as the loss stores it (a float32 buffer)."""
    return float(torch.tensor(value))


@pytest.mark.parametrize("loss_class, options, expected", [
    (PPOLagLoss, {"clip_epsilon": 0.1}, ClipSurrogate(_f32(0.1))),
    (PGLoss, {}, PGSurrogate()),
    (FOCOPSLoss, {"temperature": 2.0, "target_kl": 0.05, "safepo_broadcast": True},
     FOCOPSSurrogate(2.0, _f32(0.05), True)),
    (CUPLoss, {"gamma": 0.9, "cup_lambda": 0.5}, CUPProjectionSurrogate(_f32((1 - 0.45) / 0.1))),
])
def test_the_engine_trains_the_loss_objects_own_surrogate(loss_class, options, expected):
    loss = loss_class(*_networks(0), LagrangeMultiplier(cost_limit=25.0, sum_norm=False), functional=False, **options)
    objective = objective_of(loss)
    assert objective.surrogate == loss.surrogate == expected
    assert objective.combine == "plain" and objective.critic_l2 == pytest.approx(1e-3)
    assert objective_of(loss, critics_only=True).critics_only


def test_a_new_algorithm_is_one_surrogate_and_one_loss_and_its_penalty_changes_the_update():
    nets = [_networks(seed) for seed in SEEDS]
    batches = [_batch(seed, net[0]) for seed, net in zip(SEEDS, nets)]
    multipliers = [LagrangeMultiplier(cost_limit=25.0, init=value) for value in (0.5, 2.0)]
    losses = [PessimisticPPOLagLoss(*net, m, functional=False) for net, m in zip(nets, multipliers)]
    objective = objective_of(losses[0])
    assert isinstance(objective.surrogate, PessimisticCostSurrogate)

    model = StackedActorCritic.from_single(nets)
    step = FusedFirstOrderStep(model, FusedFirstOrderStep.make_optimizer(model, 3e-4, 3e-4), objective)
    packed = SeedBatch.pack({key: torch.stack([b[key] for b in batches]) for key in objective.fields})
    returned = step.backward(packed, multiplier_values(multipliers))
    engine_grad = model.flat_actor.grad.clone()

    for s, (net, loss, batch) in enumerate(zip(nets, losses, batches)):
        net[0].zero_grad()
        out = loss(batch.select(*loss.in_keys))
        out["loss_objective"].backward()
        torch.testing.assert_close(returned[0][s], out["loss_objective"].detach(), rtol=1e-5, atol=1e-6)
        single = torch.cat([p.grad.flatten() for p in net[0].parameters()])
        assert torch.allclose(single.sort().values, engine_grad[s].sort().values, rtol=1e-4, atol=1e-6)

        # the same batch and multiplier through PPO-Lag: the pessimistic cost clip moves the policy otherwise
        net[0].zero_grad()
        PPOLagLoss(*net, multipliers[s], functional=False)(batch.select(*loss.in_keys))["loss_objective"].backward()
        ppo_lag = torch.cat([p.grad.flatten() for p in net[0].parameters()])
        assert not torch.allclose(ppo_lag, single, rtol=1e-3, atol=1e-5)


def test_a_stock_torchrl_loss_is_refused_not_trained_as_another_algorithm():
    actor, critic, _ = _networks(0)
    with pytest.raises(TypeError, match="ClipPPOLoss has no seed_batched_objective"):
        objective_of(ClipPPOLoss(actor, critic))


def test_a_subclass_that_overrides_the_math_hooks_is_refused():
    class HalvedSurrogateLoss(PPOLagLoss):
        def _surrogate(self, log_weight, advantage, dist, tensordict, *, log_is_weight=None):
            loss, diagnostics = super()._surrogate(log_weight, advantage, dist, tensordict, log_is_weight=log_is_weight)
            return 0.5 * loss, diagnostics

    class OwnAdvantageLoss(PGLoss):
        def _combined_advantage(self, tensordict):
            return 2 * super()._combined_advantage(tensordict)

    for loss_class, hook in ((HalvedSurrogateLoss, "_surrogate"), (OwnAdvantageLoss, "_combined_advantage")):
        loss = loss_class(*_networks(0), NoMultiplier(), functional=False)
        with pytest.raises(TypeError, match=f"overrides {loss_class.__name__}.{hook} but not seed_batched_objective"):
            objective_of(loss)
    # the multi-agent loss weights its advantage by the sequential factor: its seed-batched form is the multi-agent
    # rounds' objective, which the single-agent engine refuses
    actor, critic, cost_critic = _networks(0)
    with pytest.raises(TypeError, match="returned AgentObjective, not a SeedBatchedObjective"):
        objective_of(AgentPPOLoss(actor, critic, cost_critic, NoMultiplier(), functional=False))


def test_a_seed_batched_objective_checks_what_it_is_given():
    with pytest.raises(TypeError, match="Surrogate"):
        SeedBatchedObjective("ppo")
    with pytest.raises(ValueError, match="combine rule"):
        SeedBatchedObjective(ClipSurrogate(0.2), combine="sum")
    assert SeedBatchedObjective(None).fields == ("observation", "value_target", "cost_value_target")
    assert SeedBatchedObjective(CUPProjectionSurrogate()).groups == (0,)


def test_the_add_an_algorithm_example_runs_and_shows_a_different_gradient(capsys):
    _example().main()
    lines = [line for line in capsys.readouterr().out.splitlines() if "|policy gradient|" in line]
    assert len(lines) == 2 and lines[0].split("=")[1] != lines[1].split("=")[1]


def test_the_new_algorithm_trains_through_sg_train_seeds(tmp_path):
    """One manifest row and the loss: ``sg-train --algo ppo_lag_pessimistic --seeds 0 1`` trains both seeds."""
    from sg_torchrl.train import main

    code = main(["--algo", "ppo_lag_pessimistic", "--env-id", "SafetyPointGoal1-v0", "--seeds", "0", "1",
                 "--num-envs", "2", "--steps-per-epoch", "400", "--total-steps", "800", "--update-iters", "2",
                 "--output-dir", str(tmp_path), "--run-name", "pessimistic", "--wandb", "disabled",
                 "--eval-episodes", "1"])
    assert code in (0, None)
    for seed in (0, 1):
        with open(tmp_path / "pessimistic" / f"seed-00{seed}" / "progress.csv") as handle:
            epochs = [row for row in csv.DictReader(handle) if row["Train/Epoch"]]
        assert [row["Train/Epoch"] for row in epochs] == ["1", "2"] and all(row["Loss/Loss_actor"] for row in epochs)
