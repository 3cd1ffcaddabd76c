"""``compile=True``: the minibatch losses through ``torch.compile`` give the eager values and gradients,
train without recompiling after the first epoch, and the option is validated like every other."""

from __future__ import annotations

import warnings

import pytest
import torch

torch.set_num_threads(1)

from torch._dynamo.utils import counters  # noqa: E402

from sg_torchrl.objectives import FOCOPSLoss, LagrangeMultiplier, PPOLagLoss  # noqa: E402
from sg_torchrl.train import OnPolicyGroupTrainer, TrainConfig  # noqa: E402
from sg_torchrl.train import compiling  # noqa: E402
from sg_torchrl.train.command_line import parse_args  # noqa: E402
from test_first_order_losses import make_batch, make_modules  # noqa: E402


def _gradients(module: torch.nn.Module) -> list[torch.Tensor]:
    return [p.grad.clone() for p in module.parameters() if p.grad is not None]


def _loss_and_batch(kind: str):
    actor, critic, cost_critic = make_modules()
    multiplier = LagrangeMultiplier(cost_limit=25.0, init=0.5)
    batch = make_batch(actor)
    if kind == "ppo_lag":
        loss = PPOLagLoss(actor, critic, cost_critic, multiplier, functional=False)
    else:
        loss = FOCOPSLoss(actor, critic, cost_critic, multiplier, functional=False)
        batch["loc"] = batch["loc"] + 0.1  # a rollout policy away from the current one
    return loss, batch


# CUP's projection loss is compiled in the training test below (each compile costs 10-40 s on a cold cache).
@pytest.mark.parametrize("kind", ["ppo_lag", "focops"])
def test_compiled_loss_matches_eager_values_and_gradients(kind):
    loss, batch = _loss_and_batch(kind)
    batch = batch.select(*(key for key in loss.in_keys if key in batch.keys()))  # what the loss reads, in order
    terms = [k for k in loss.out_keys if k.startswith("loss_")]

    eager = loss(batch)
    sum(eager[k] for k in terms).backward()
    eager_grads = _gradients(loss)
    loss.zero_grad(set_to_none=True)

    compiled = torch.compile(loss, dynamic=False)(batch)
    sum(compiled[k] for k in terms).backward()
    for key in terms:
        torch.testing.assert_close(compiled[key], eager[key], rtol=1e-5, atol=1e-6)
    compiled_grads = _gradients(loss)
    assert len(compiled_grads) == len(eager_grads) > 0
    for got, want in zip(compiled_grads, eager_grads):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-6)


def _config(tmp_path, **overrides) -> TrainConfig:
    # 2 simulators x 1000 steps: every HalfCheetah episode ends inside the epoch; with a velocity
    # threshold a random policy exceeds, its cost is above the limit of 0 and the multiplier grows, so
    # a graph that read it as a constant would be recompiled.
    values = dict(
        env_id="SafetyHalfCheetahVelocity-v1", env_options={"velocity_threshold": 0.01}, num_envs=2, steps_per_epoch=2000, total_steps=6000, update_iters=2,
        cost_limit=0.0, eval_episodes=0, wandb="disabled", progress=False, output_dir=str(tmp_path),
        run_name="run", checkpoint_every=100, compile=True,
    )
    values.update(overrides)
    return TrainConfig(**values)


# CUP runs the first-order loop (its stage one, as PPO-Lag's) and the projection passes; CPO the critic passes.
@pytest.mark.parametrize("algo", ["cup", "cpo"])
def test_compiled_training_reuses_its_graphs_after_the_first_epoch(tmp_path, algo):
    trainer = OnPolicyGroupTrainer(_config(tmp_path, algo=algo))
    first = trainer.train_epoch()
    graphs = counters["stats"]["unique_graphs"]
    later = [trainer.train_epoch() for _ in range(2)]
    assert counters["stats"]["unique_graphs"] == graphs, "a later epoch recompiled a loss"
    multipliers = [m["Train/LagrangeMultiplier"] for m in (first, *later)]
    if algo != "cpo":
        assert multipliers[2] > multipliers[0] > 0  # the multiplier grew, the graphs stayed
    for metrics in (first, *later):
        assert torch.isfinite(torch.tensor(metrics["Loss/Loss_reward_critic"]))


def test_a_failing_compile_warns_once_and_runs_eagerly(monkeypatch):
    def broken(function, **_):
        def fail(*args, **kwargs):
            raise RuntimeError("no C++ compiler\nmore lines")
        return fail

    monkeypatch.setattr(compiling.torch, "compile", broken)
    calls = []

    def eager(x, *, scale):
        calls.append(x)
        return x * scale

    function = compiling.CompileFallback(eager, owner="Owner", compile=True)
    assert function.compiled and function.compile_error is None
    with pytest.warns(UserWarning, match=r"Owner: torch.compile failed, running eagerly \(RuntimeError: no C\+\+"):
        assert function(2.0, scale=3.0) == 6.0
    assert function.compile_error == "RuntimeError: no C++ compiler" and not function.compiled
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no second warning
        assert function(1.0, scale=2.0) == 2.0 and calls == [2.0, 1.0]  # eagerly from then on


def test_an_eager_function_raises_its_own_errors():
    def eager():
        raise KeyError("a bad batch")

    with pytest.raises(KeyError, match="a bad batch"):
        compiling.CompileFallback(eager, owner="Owner", compile=False)()


class TestCompileOption:
    def test_command_line_flag(self):
        assert parse_args(["--compile", "true"]).compile
        assert not parse_args([]).compile

    def test_multi_agent_algorithms_reject_it(self):
        with pytest.raises(ValueError, match="compile applies to the single-agent"):
            TrainConfig(algo="mappo_lag", compile=True)
