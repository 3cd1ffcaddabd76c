"""``--compile`` for the multi-agent rounds: the agents' losses and the Adam update through ``torch.compile``.

* **compiled against eager**: one epoch of a seed group of two (MAPPO-Lag on the whole batch, HAPPO in two
  minibatches per pass, MACPO's compiled critic passes) trains to the eager run's metrics and parameters
  to float rounding (rtol 1e-4), and a second epoch compiles nothing new (the stages' rows have one shape);
* **fallback**: where compiling fails, the round warns, records the error and trains eagerly, exactly as
  an eager run does;
* the option: accepted for the multi-agent algorithms.

Each compiled run costs tens of seconds of compiling on a small CPU, so each algorithm's pair of runs is
built once (module-scoped) and shared by the assertions.
"""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)

from torch._dynamo.utils import counters  # noqa: E402

from sg_torchrl.train import MultiAgentGroupTrainer, TrainConfig  # noqa: E402
from sg_torchrl.train import compiling  # noqa: E402
from sg_torchrl.train.command_line import parse_args  # noqa: E402
from test_multi_agent_group import config  # noqa: E402

#: Per algorithm, the options of its runs (HAPPO: two minibatches per pass, so a step evaluates the actor itself).
RUNS = {"mappo_lag": {}, "happo": {"minibatch_size": 100}, "macpo": {}}
#: The round's figures compared (means over the seeds; the timings differ, the rollout's figures are one batch's).
ROUND_METRICS = ("Loss/", "Misc/", "Train/")


def _round_metrics(metrics: dict) -> dict[str, float]:
    return {key: value for key, value in metrics.items() if key.startswith(ROUND_METRICS)}


def _parameters(trainer: MultiAgentGroupTrainer) -> list[torch.Tensor]:
    return [p.detach().clone() for team in trainer.teams for p in team.networks.parameters()]


@pytest.fixture(scope="module", params=list(RUNS))
def pair(request, tmp_path_factory):
    """The algorithm's eager and compiled groups after one epoch, the compiled group's graphs and its 2nd epoch."""
    algo, tmp = request.param, tmp_path_factory.mktemp(request.param)
    eager = MultiAgentGroupTrainer(config(tmp / "eager", algo=algo, seeds=[0, 1], **RUNS[algo]))
    compiled = MultiAgentGroupTrainer(config(tmp / "compiled", algo=algo, seeds=[0, 1], compile=True, **RUNS[algo]))
    eager_metrics = eager.train_epoch()
    torch._dynamo.reset()  # the graphs counted are this algorithm's (another's Adam graph would be reused)
    before = counters["stats"]["unique_graphs"]
    compiled_metrics = compiled.train_epoch()
    graphs = counters["stats"]["unique_graphs"] - before
    parameters = _parameters(compiled)
    compiled.train_epoch()
    later = counters["stats"]["unique_graphs"] - before - graphs
    return dict(algo=algo, eager=eager, compiled=compiled, eager_metrics=eager_metrics,
                compiled_metrics=compiled_metrics, parameters=parameters, graphs=graphs, later=later)


def test_compiled_round_trains_as_the_eager_one(pair):
    assert pair["compiled"].round.losses.compiled and pair["compiled"].round.compile_error is None
    eager, compiled = _round_metrics(pair["eager_metrics"]), _round_metrics(pair["compiled_metrics"])
    assert eager.keys() == compiled.keys() and len(eager) > 10
    for key, value in eager.items():
        assert compiled[key] == pytest.approx(value, rel=1e-4, abs=1e-6), key
    mine, theirs = pair["parameters"], _parameters(pair["eager"])
    assert len(mine) == len(theirs) > 0
    for got, want in zip(mine, theirs, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-6)
    assert any(not torch.equal(got, want) for got, want in zip(mine, theirs))  # compiled, not the eager numbers


def test_compiled_round_compiles_a_few_graphs_once(pair):
    # the losses (with their backward) and the Adam update: one graph each, whatever the stage or agent
    assert pair["graphs"] == 2, pair["graphs"]
    assert pair["later"] == 0, "a later epoch recompiled"


def test_a_failing_compile_falls_back_to_the_eager_round(tmp_path, monkeypatch):
    def broken(function, **_):
        def fail(*args, **kwargs):
            raise RuntimeError("no C++ compiler\nmore lines")
        return fail

    monkeypatch.setattr(compiling.torch, "compile", broken)
    compiled = MultiAgentGroupTrainer(config(tmp_path / "compiled", algo="mappo_lag", seeds=[0, 1], compile=True))
    eager = MultiAgentGroupTrainer(config(tmp_path / "eager", algo="mappo_lag", seeds=[0, 1]))
    with pytest.warns(UserWarning, match="torch.compile failed, running eagerly"):
        fallen = compiled.train_epoch()
    assert compiled.round.compile_error == "RuntimeError: no C++ compiler"
    assert not compiled.round.losses.compiled
    assert _round_metrics(fallen) == _round_metrics(eager.train_epoch())  # exactly: the eager round ran
    for got, want in zip(_parameters(compiled), _parameters(eager), strict=True):
        assert torch.equal(got, want)


def test_the_option_is_accepted_for_the_multi_agent_algorithms():
    assert parse_args(["--algo", "mappo_lag", "--compile", "true"]).compile
    for algo in ("mappo", "happo", "mappo_lag", "macpo"):
        assert TrainConfig(algo=algo, compile=True).compile
