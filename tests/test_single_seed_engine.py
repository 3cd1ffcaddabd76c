"""``sg-train --seed s``: the seed-group engine with its one seed (a lean hot path for one seed too).

Every single-agent run trains on the seed-group engine; one seed is
:class:`~sg_torchrl.train.seed_group.OnPolicyGroupTrainer` with S = 1, in a single run's layout
(:class:`~sg_torchrl.train.seed_runs.SingleRunLayout`, which the config picks). Checked here:

* the choice (:func:`~sg_torchrl.train.trainer_class`: the family only, pixel ids included), the layout the
  config picks, the deprecated ``GroupTrainer`` name, and that ``--engine`` is gone;
* a ``--seed`` run writes the single-seed layout: a single run's files in its run directory, no
  ``seed-XXX/`` level, no group summary, the single-seed printout;
* ``--seed 0`` is seed 0 of ``--seeds 0`` exactly: progress rows but their ``Time/*`` columns, summary
  but its time, and the checkpoint's seed entry (networks, Adam rows, multiplier, normaliser,
  generators), bit for bit; and it starts from ``make_actor_critics``' networks;
* ``--resume`` continues a run bit for bit (also from a checkpoint whose config still names
  ``engine: fused``, as written before the option was retired), and a checkpoint of the retired
  ``LossModule`` trainer is refused with exit 2 and what to do instead.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import dataclasses
from pathlib import Path

import pytest
import torch

torch.set_num_threads(1)

from sg_torchrl import seeding  # noqa: E402
from sg_torchrl.train import (  # noqa: E402
    MultiAgentGroupTrainer,
    OnPolicyGroupTrainer,
    TrainConfig,
    main,
    train,
    trainer_class,
)
from sg_torchrl.train.checkpoint import CheckpointError, load_checkpoint, save_checkpoint  # noqa: E402
from sg_torchrl.train.command_line import parse_args  # noqa: E402
from sg_torchrl.train.seed_runs import GroupLayout, SingleRunLayout, run_layout  # noqa: E402
from sg_torchrl.modules.mlp import make_actor_critics  # noqa: E402
from trainer_checks import assert_same_state, tiny_config  # noqa: E402

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


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, tuple[Path, str]]:
    """The same command as one seed and as a group of one: run directory and printout of each."""
    root = tmp_path_factory.mktemp("engines")
    out = {"single": (root / "single" / "run", run_cli([*FLAGS, "--seed", "0", "--output-dir", str(root / "single"),
                                                        "--run-name", "run"]))}
    out["group"] = (root / "group" / "run", run_cli([*FLAGS, "--seeds", "0", "--output-dir", str(root / "group"),
                                                     "--run-name", "run"]))
    return out


# --------------------------------------------------------------------------- the choice
def test_every_single_agent_run_trains_on_the_seed_group_engine():
    assert trainer_class(TrainConfig()) is OnPolicyGroupTrainer
    assert trainer_class(TrainConfig(env_id=VISION)) is OnPolicyGroupTrainer  # stacked CNN encoders
    pixels = TrainConfig(env_id="SafetyCarGoal1-v0", env_options={"obs_mode": "vector+rgb"})
    assert trainer_class(pixels) is OnPolicyGroupTrainer
    assert trainer_class(TrainConfig(seeds=[0, 1])) is OnPolicyGroupTrainer
    assert trainer_class(TrainConfig(algo="mappo_lag")) is MultiAgentGroupTrainer
    assert "engine" not in TrainConfig().to_dict()


def test_the_layout_is_the_configs_choice(tmp_path):
    single, group = tiny_config(tmp_path / "s"), tiny_config(tmp_path / "g", seeds=[0, 1], run_name=None)
    one, two = run_layout(single), run_layout(group)
    assert isinstance(one, SingleRunLayout) and one.seeds == [0] and one.seed_config(0) is single
    assert isinstance(two, GroupLayout) and two.seeds == [0, 1]
    assert two.seed_config(1).run_dir == group.run_dir / "seed-001" and not two.seed_config(1).group
    with pytest.raises(ValueError, match="group's"):
        SingleRunLayout(group)
    with pytest.raises(ValueError, match="cfg.seeds"):
        GroupLayout(single)
    trainer = OnPolicyGroupTrainer(group)  # the family class that trains one seed trains the group too
    assert isinstance(trainer.layout, GroupLayout) and trainer.seeds == [0, 1]
    with pytest.raises(AttributeError, match=r"runs\[i\]\.stats"):
        trainer.stats  # a group has no one run's statistics


def test_group_trainer_is_a_deprecated_name():
    with pytest.warns(DeprecationWarning, match="OnPolicyGroupTrainer"):
        from sg_torchrl.train import GroupTrainer
    assert GroupTrainer is OnPolicyGroupTrainer


def test_the_engine_option_is_gone(tmp_path, capsys):
    assert main(["--engine", "loss-module", "--output-dir", str(tmp_path)]) == 2
    assert "unrecognized arguments: --engine loss-module" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
    with pytest.raises(TypeError, match="engine"):
        TrainConfig(engine="fused")
    assert main(["--help"]) == 0
    assert "--engine" not in capsys.readouterr().out


# --------------------------------------------------------------------------- the layout
def test_a_seed_writes_the_single_seed_layout(runs):
    (single, out), (group, _) = runs["single"], runs["group"]
    names = {p.name for p in single.iterdir()}
    assert names == {"config.json", "progress.csv", "csv", "summary.json", "curves.png", "checkpoint.pt"}
    assert {p.name for p in (single / "csv").iterdir()} == {p.name for p in (group / "seed-000" / "csv").iterdir()}
    summary = json.loads((single / "summary.json").read_text())
    assert "seeds" not in summary and "mean" not in summary and "Metrics/EvalEpRet" in summary
    header = [(d / "progress.csv").read_text().splitlines()[0] for d in (single, group / "seed-000")]
    assert header[0] == header[1] and len(progress_rows(single)) == 3
    state = load_checkpoint(single)
    assert state["seed_group"] == {"seeds": [0]} and [e["seed"] for e in state["seeds"]] == [0]
    assert "engine" not in json.loads((single / "config.json").read_text())
    assert "seed 0: 600 env steps" in out and "evaluation (1 deterministic episodes)" in out
    assert f"continue with: sg-train --resume {single}" in out and "seed-XXX" not in out


# --------------------------------------------------------------------------- the same run as a group of one
def test_a_seed_is_seed_0_of_a_group_of_one(runs):
    (single, _), (group, _) = runs["single"], runs["group"]
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


def test_a_seed_starts_from_make_actor_critics_networks(tmp_path):
    fused = OnPolicyGroupTrainer(tiny_config(tmp_path / "f", seed=3))
    env = fused.base_env
    seeding.seed_torch(3)  # as a user's single-seed code builds them
    reference = make_actor_critics(env.observation_spec, env.action_spec, fused.cfg.network_sizes)
    exported = fused.model.export_seed(0, env.action_spec)
    assert torch.equal(torch.cat([p.detach().reshape(-1) for m in exported for p in m.parameters()]),
                       torch.cat([p.detach().reshape(-1) for m in reference for p in m.parameters()]))
    assert isinstance(fused.layout, SingleRunLayout) and fused.stats is fused.runs[0].stats


# --------------------------------------------------------------------------- resume
def test_resume_continues_a_run_bit_for_bit(runs, tmp_path):
    uninterrupted, _ = runs["single"]
    cfg = parse_args([*FLAGS, "--seed", "0", "--output-dir", str(tmp_path), "--run-name", "run"])
    OnPolicyGroupTrainer(cfg).run(max_epochs=1)
    run_dir = tmp_path / "run"
    assert load_checkpoint(run_dir)["epoch"] == 1 and len(progress_rows(run_dir)) == 1
    state = load_checkpoint(run_dir)
    state["config"]["engine"] = "fused"  # as written before the option was retired: read past
    save_checkpoint(state, run_dir / "checkpoint.pt")
    run_cli(["--resume", str(run_dir)])
    assert progress_rows(run_dir) == progress_rows(uninterrupted)
    resumed, whole = load_checkpoint(run_dir), load_checkpoint(uninterrupted)
    assert resumed["epoch"] == 3 and "engine" not in resumed["config"]
    assert_same_state(resumed["seeds"], whole["seeds"], "seeds")
    assert_same_state(resumed["collector"], whole["collector"], "collector")
    summaries = [json.loads((d / "summary.json").read_text()) for d in (run_dir, uninterrupted)]
    for summary in summaries:
        summary.pop("Time/Total")
    assert summaries[0] == summaries[1]


def retired_trainer_checkpoint(runs, run_dir: Path, engine: str | None) -> None:
    """A checkpoint as the retired ``LossModule`` trainer wrote it (``engine`` in its config, or none before
    the option existed): its networks under ``"loss"``, no ``"seed_group"`` / ``"seeds"`` entries."""
    state = load_checkpoint(runs["single"][0])
    for name in ("seed_group", "seeds"):
        del state[name]
    state["loss"] = {}
    state["config"] = {k: v for k, v in state["config"].items() if k != "engine"}
    if engine is not None:
        state["config"]["engine"] = engine
    run_dir.mkdir(parents=True)
    save_checkpoint(state, run_dir / "checkpoint.pt")


@pytest.mark.parametrize("engine", ["loss-module", None])
def test_a_retired_trainer_checkpoint_is_refused_with_what_to_do(runs, tmp_path, capsys, engine):
    run_dir = tmp_path / "old"
    retired_trainer_checkpoint(runs, run_dir, engine)
    assert main(["--resume", str(run_dir)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("sg-train: error: ") and "written by the LossModule trainer" in err
    assert "fresh --run-name" in err and "earlier sg_torchrl release" in err
    assert list(run_dir.iterdir()) == [run_dir / "checkpoint.pt"]  # nothing written next to it
    cfg = dataclasses.replace(parse_args([*FLAGS, "--seed", "0"]), resume=str(run_dir), output_dir=str(tmp_path),
                              run_name="old")
    with pytest.raises(CheckpointError, match="LossModule trainer"):  # the Python API refuses too
        train(cfg)
