"""``sg-train --seed s`` on the fused engine (a lean hot path for one seed too).

A single-agent run on flat-vector observations runs by default on the seed-group engine with its one
seed (:class:`~sg_torchrl.train.seed_group.SingleSeedGroupTrainer`); ``--engine loss-module`` runs the
:class:`~sg_torchrl.train.trainer.Trainer` (TorchRL ``LossModule`` s), as do pixel observations. Checked here:

* the choice (:func:`~sg_torchrl.train.trainer_class`, the config's filled-in ``engine``) and its refusals,
  exit 2 from the command line;
* the fused run writes the single-seed layout: the same files as a Trainer run, where a Trainer run writes
  them, the same ``progress.csv`` columns and ``summary.json`` keys, the same printout; no ``seed-XXX/``
  level, no group summary;
* a fused ``--seed 0`` run is seed 0 of ``--seeds 0`` exactly: progress rows but their ``Time/*`` columns,
  summary but its time, and the checkpoint's seed entry (networks, Adam rows, multiplier, normaliser,
  generators), bit for bit; and it starts from the Trainer's initial networks (the statistical comparison
  of the group engine with the Trainer is ``tests/test_seed_group.py``'s);
* ``--resume`` continues a fused run bit for bit, and an old Trainer checkpoint (written before
  ``engine`` existed) on the Trainer.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDictBase

torch.set_num_threads(1)

from sg_torchrl.train import (  # noqa: E402
    GroupTrainer,
    SingleSeedGroupTrainer,
    SingleSeedMultiAgentTrainer,
    TrainConfig,
    Trainer,
    main,
    trainer_class,
)
from sg_torchrl.train.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from sg_torchrl.train.config import parse_args  # noqa: E402
from trainer_checks import flat_parameters, tiny_config  # noqa: E402

VISION = "SafetyPointGoal1Vision-v0"
#: Three 200-step epochs of PPO-Lag on HalfCheetah with 100-step episodes and a 0.5 m/s limit (episodes end
#: and cost accrues every epoch, so the multiplier moves), one evaluation episode.
FLAGS = ["--env-id", "SafetyHalfCheetahVelocity-v1", "--env-options", "max_episode_steps=100", "velocity_threshold=0.5",
         "--num-envs", "2", "--steps-per-epoch", "200", "--total-steps", "600", "--update-iters", "2",
         "--cost-limit", "0", "--eval-episodes", "1", "--wandb", "disabled", "--progress", "false",
         "--checkpoint-every", "1"]


def run_cli(argv: list[str]) -> str:
    """``main(argv)``'s stdout; asserts exit status 0."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(argv) == 0
    return out.getvalue()


def progress_rows(run_dir: Path) -> list[dict[str, str]]:
    """``progress.csv``'s epoch rows without their timings (``Time/*``)."""
    with (run_dir / "progress.csv").open() as handle:
        return [{k: v for k, v in row.items() if not k.startswith("Time/")}
                for row in csv.DictReader(handle) if row["Train/Epoch"]]


def assert_same_state(mine, theirs, path="entry"):
    """Two checkpoint entries equal bit for bit (tensors with ``torch.equal``, the rest with ``==``), timings
    (``Time/*`` of the progress rows they carry) aside."""
    if isinstance(mine, TensorDictBase):
        assert_same_state(mine.to_dict(), theirs.to_dict(), path)
    elif isinstance(mine, np.ndarray):
        assert np.array_equal(mine, theirs, equal_nan=mine.dtype.kind == "f"), path
    elif isinstance(mine, dict):
        assert mine.keys() == theirs.keys(), path
        for key in (k for k in mine if not str(k).startswith("Time/")):
            assert_same_state(mine[key], theirs[key], f"{path}[{key!r}]")
    elif isinstance(mine, (list, tuple)):
        assert len(mine) == len(theirs), path
        for i, (a, b) in enumerate(zip(mine, theirs)):
            assert_same_state(a, b, f"{path}[{i}]")
    elif isinstance(mine, torch.Tensor):
        assert torch.equal(mine, theirs), path
    else:
        assert mine == theirs or (mine != mine and theirs != theirs), path


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, tuple[Path, str]]:
    """The same command on each engine, and as a group of one: run directory and printout of each."""
    root = tmp_path_factory.mktemp("engines")
    out = {}
    for name, extra in (("fused", []), ("loss-module", ["--engine", "loss-module"])):
        out[name] = (root / name / "run", run_cli([*FLAGS, "--seed", "0", *extra, "--output-dir", str(root / name),
                                                  "--run-name", "run"]))
    out["group"] = (root / "group" / "run", run_cli([*FLAGS, "--seeds", "0", "--output-dir", str(root / "group"),
                                                     "--run-name", "run"]))
    return out


# --------------------------------------------------------------------------- the choice
def test_the_engine_is_filled_in_and_picks_the_trainer():
    assert TrainConfig().engine == "fused" and trainer_class(TrainConfig()) is SingleSeedGroupTrainer
    reference = TrainConfig(engine="loss-module")
    assert trainer_class(reference) is Trainer
    vision = TrainConfig(env_id=VISION)  # the fused engine reads flat vectors: pixels fall back to the Trainer
    assert vision.engine == "loss-module" and trainer_class(vision) is Trainer
    pixels = TrainConfig(env_id="SafetyCarGoal1-v0", env_options={"obs_mode": "vector+rgb"})
    assert pixels.engine == "loss-module" and trainer_class(pixels) is Trainer
    assert TrainConfig(seeds=[0, 1]).engine == "fused" and trainer_class(TrainConfig(seeds=[0, 1])) is GroupTrainer
    multi = TrainConfig(algo="mappo_lag")
    assert multi.engine is None and trainer_class(multi) is SingleSeedMultiAgentTrainer
    assert parse_args(["--engine", "loss-module"]).engine == "loss-module"


@pytest.mark.parametrize(
    "argv, values, message",
    [
        (["--engine", "fast"], {"engine": "fast"}, "--engine: invalid choice: 'fast'"),
        (["--seeds", "0", "1", "--engine", "loss-module"], {"seeds": [0, 1], "engine": "loss-module"},
         "seed groups (seeds) train on the fused engine"),
        (["--algo", "mappo_lag", "--engine", "fused"], {"algo": "mappo_lag", "engine": "fused"},
         "multi-agent algorithm with its own engine"),
        (["--env-id", VISION, "--engine", "fused"], {"env_id": VISION, "engine": "fused"},
         "engine 'fused' trains on flat-vector observations"),
    ],
)
def test_bad_engines_exit_2_with_a_message(tmp_path, capsys, argv, values, message):
    assert main([*argv, "--output-dir", str(tmp_path)]) == 2
    assert message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # refused before anything was built or written
    with pytest.raises(ValueError, match="config: engine|config: seed groups"):  # the Python API refuses too
        TrainConfig(**values)


def test_help_says_what_each_engine_is(capsys):
    assert main(["--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--engine {fused,loss-module}" in text
    for words in ("seed-group engine with one seed", "LossModules", "loss-module on pixel observations"):
        assert words in text, words


# --------------------------------------------------------------------------- the layout
def test_a_fused_seed_writes_the_single_seed_layout(runs):
    (fused, fused_out), (reference, reference_out) = runs["fused"], runs["loss-module"]
    names = {p.name for p in fused.iterdir()}
    assert names == {p.name for p in reference.iterdir()}
    assert names == {"config.json", "progress.csv", "csv", "summary.json", "curves.png", "checkpoint.pt"}
    assert {str(p.relative_to(fused)) for p in (fused / "csv").rglob("*")} == \
        {str(p.relative_to(reference)) for p in (reference / "csv").rglob("*")}
    fused_summary, reference_summary = (json.loads((d / "summary.json").read_text()) for d in (fused, reference))
    assert fused_summary.keys() == reference_summary.keys()  # no "seeds" / "mean" of a group
    header = [(d / "progress.csv").read_text().splitlines()[0] for d in (fused, reference)]
    assert header[0] == header[1]
    assert [len(progress_rows(d)) for d in (fused, reference)] == [3, 3]
    configs = [json.loads((d / "config.json").read_text()) for d in (fused, reference)]
    assert (configs[0]["engine"], configs[1]["engine"]) == ("fused", "loss-module")
    assert {k: v for k, v in configs[0].items() if k not in ("engine", "output_dir")} == \
        {k: v for k, v in configs[1].items() if k not in ("engine", "output_dir")}
    # What ran: the group engine's checkpoint (one seed entry) and the Trainer's (its loss modules).
    fused_state, reference_state = load_checkpoint(fused), load_checkpoint(reference)
    assert fused_state["seed_group"] == {"seeds": [0]} and [e["seed"] for e in fused_state["seeds"]] == [0]
    assert "loss" in reference_state and "seed_group" not in reference_state

    def shape(text: str, run_dir: Path) -> str:  # the printout with its numbers and directory masked
        return re.sub(r"-?\d+(\.\d+)?|nan", "#", text.replace(str(run_dir), "RUN"))

    assert shape(fused_out, fused) == shape(reference_out, reference)
    assert "seed 0: 600 env steps" in fused_out and "evaluation (1 deterministic episodes)" in fused_out


# --------------------------------------------------------------------------- the same run as a group of one
def test_a_fused_seed_is_seed_0_of_a_group_of_one(runs):
    (single, _), (group, _) = runs["fused"], runs["group"]
    seed_dir = group / "seed-000"
    assert progress_rows(single) == progress_rows(seed_dir)
    summaries = [json.loads((d / "summary.json").read_text()) for d in (single, seed_dir)]
    for summary in summaries:
        summary.pop("Time/Total")
    assert summaries[0] == summaries[1]
    configs = [json.loads((d / "config.json").read_text()) for d in (single, seed_dir)]
    moved = ("output_dir", "run_name")
    assert {k: v for k, v in configs[0].items() if k not in moved} == {k: v for k, v in configs[1].items()
                                                                        if k not in moved}
    mine, theirs = load_checkpoint(single), load_checkpoint(group)
    assert_same_state(mine["seeds"], theirs["seeds"], "seeds")  # networks, Adam rows, multiplier, generators
    for key in ("collector", "torch_rng", "epoch", "total_steps"):
        assert_same_state(mine[key], theirs[key], key)


def test_a_fused_seed_starts_from_the_trainers_networks(tmp_path):
    fused = SingleSeedGroupTrainer(tiny_config(tmp_path / "f", seed=3))
    reference = Trainer(tiny_config(tmp_path / "t", seed=3, engine="loss-module"))
    exported = fused.model.export_seed(0, fused.base_env.action_spec)
    assert torch.equal(torch.cat([p.detach().reshape(-1) for m in exported for p in m.parameters()]),
                       flat_parameters(reference))
    with pytest.raises(ValueError, match="GroupTrainer's"):
        SingleSeedGroupTrainer(tiny_config(tmp_path / "g", seeds=[0, 1], run_name=None))


# --------------------------------------------------------------------------- resume
def test_resume_continues_a_fused_run_bit_for_bit(runs, tmp_path, capsys):
    uninterrupted, _ = runs["fused"]
    cfg = parse_args([*FLAGS, "--seed", "0", "--output-dir", str(tmp_path), "--run-name", "run"])
    SingleSeedGroupTrainer(cfg).run(max_epochs=1)
    run_dir = tmp_path / "run"
    assert load_checkpoint(run_dir)["epoch"] == 1 and len(progress_rows(run_dir)) == 1
    assert main(["--resume", str(run_dir), "--engine", "loss-module"]) == 2  # a run keeps its engine
    assert "keeps the engine that wrote its checkpoint (fused)" in capsys.readouterr().err
    run_cli(["--resume", str(run_dir)])
    assert progress_rows(run_dir) == progress_rows(uninterrupted)
    resumed, whole = load_checkpoint(run_dir), load_checkpoint(uninterrupted)
    assert resumed["epoch"] == 3
    assert_same_state(resumed["seeds"], whole["seeds"], "seeds")
    assert_same_state(resumed["collector"], whole["collector"], "collector")
    summaries = [json.loads((d / "summary.json").read_text()) for d in (run_dir, uninterrupted)]
    for summary in summaries:
        summary.pop("Time/Total")
    assert summaries[0] == summaries[1]


def test_an_old_trainer_checkpoint_resumes_on_the_trainer(tmp_path):
    Trainer(tiny_config(tmp_path, engine="loss-module")).run(max_epochs=1)
    path = tmp_path / "run" / "checkpoint.pt"
    state = load_checkpoint(path)
    del state["config"]["engine"]  # as written before --engine existed
    save_checkpoint(state, path)
    run_cli(["--resume", str(tmp_path / "run")])
    state = load_checkpoint(path)
    assert state["epoch"] == 3 and "loss" in state and state["config"]["engine"] == "loss-module"
