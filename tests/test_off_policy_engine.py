"""The off-policy family on the seed-group engine: ``sg-train --algo sac_lag|td3|ddpg_pid|...``.

* seed k of ``--seeds 0 1`` trains as its ``--seed k`` run (progress rows but their ``Time/*`` columns, and the
  final networks, to the batched matmuls' float rounding);
* ``--resume`` after an interrupted run equals the uninterrupted run bit for bit: rows, networks, targets,
  Adam moments, multipliers, generators and the replay buffers (in the run directory, nowhere else), also
  after a kill between replay writes and the next checkpoint, where the buffer has wrapped over rows the
  checkpoint holds (their undo files);
* a seed whose update failed is put back to its epoch start alone (rows, targets, Adam rows);
* the multiplier moves with the cost (up over the limit, down under it);
* the options the family does not take, and the family's options for the on-policy algorithms, are refused.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
from pathlib import Path

import pytest
import torch

torch.set_num_threads(1)

from sg_torchrl.train import OffPolicyGroupTrainer, main, train, trainer_class  # noqa: E402
from sg_torchrl.train.checkpoint import load_checkpoint  # noqa: E402
from sg_torchrl.train.command_line import parse_args  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

#: Three 200-step epochs from 2 simulators, 50-step episodes, a 0.5 m/s limit (cost accrues), 100 warm-up steps.
FLAGS = ["--env-id", "SafetyHalfCheetahVelocity-v1", "--env-options", "max_episode_steps=50", "velocity_threshold=0.5",
         "--num-envs", "2", "--steps-per-epoch", "200", "--total-steps", "600", "--warmup-steps", "100",
         "--minibatch-size", "16", "--hidden-sizes", "16", "16", "--replay-size", "1000", "--eval-episodes", "1",
         "--wandb", "disabled", "--progress", "false", "--checkpoint-every", "1"]


def _run(argv: list[str]) -> None:
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(argv) == 0


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path) as f:
        return [{k: v for k, v in row.items() if not k.startswith("Time/")} for row in csv.DictReader(f)]


def _floats(rows):
    return torch.tensor([[float(v) if v else float("nan") for v in row.values()] for row in rows], dtype=torch.float64)


def _entry(run_dir: Path, seed: int) -> dict:
    return next(e for e in load_checkpoint(run_dir)["seeds"] if e["seed"] == seed)


def _tensors(tree) -> list[torch.Tensor]:
    if isinstance(tree, torch.Tensor):
        return [tree]
    if isinstance(tree, dict):
        return [t for key in sorted(tree) for t in _tensors(tree[key])]
    if isinstance(tree, (list, tuple)):
        return [t for item in tree for t in _tensors(item)]
    return []


def test_trainer_choice():
    assert trainer_class(parse_args(["--algo", "sac_lag", "--seeds", "0", "1"])) is OffPolicyGroupTrainer
    assert trainer_class(parse_args(["--algo", "td3"])) is OffPolicyGroupTrainer


@pytest.mark.parametrize("algo", ["sac_lag", "td3_pid"])
def test_group_seed_is_its_single_seed_run(tmp_path, algo):
    _run(["--algo", algo, "--seeds", "0", "1", "--output-dir", str(tmp_path / "group"), *FLAGS])
    _run(["--algo", algo, "--seed", "1", "--output-dir", str(tmp_path / "single"), *FLAGS])
    group = tmp_path / "group" / "SafetyHalfCheetahVelocity-v1" / algo / "seeds-0-1"
    single = tmp_path / "single" / "SafetyHalfCheetahVelocity-v1" / algo / "seed-001"
    group_rows, single_rows = _rows(group / "seed-001" / "progress.csv"), _rows(single / "progress.csv")
    assert [list(r) for r in group_rows] == [list(r) for r in single_rows]
    torch.testing.assert_close(_floats(group_rows), _floats(single_rows), rtol=1e-4, atol=1e-5, equal_nan=True)
    for a, b in zip(_tensors(_entry(group, 1)["networks"]), _tensors(_entry(single, 1)["networks"]), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    assert (single / "replay").is_dir() and not (single / "seed-001").exists()


@pytest.mark.parametrize("algo", ["sac_lag", "ddpg"])
def test_resume_equals_the_uninterrupted_run(tmp_path, algo):
    whole = ["--algo", algo, "--seeds", "0", "1", "--output-dir", str(tmp_path / "whole"), *FLAGS]
    _run(whole)
    cfg = parse_args(["--algo", algo, "--seeds", "0", "1", "--output-dir", str(tmp_path / "cut"), *FLAGS])
    first = trainer_class(cfg)(cfg)
    first.run(max_epochs=1)  # the process ends after epoch 1 (past the warm-up: gradient steps were taken)
    first.collector.env.close()
    del first
    cut_dir = cfg.run_dir
    assert _replay_files(cut_dir) == _replay_layout(1)
    train(dataclasses.replace(cfg, resume=str(cut_dir)))
    whole_dir = tmp_path / "whole" / "SafetyHalfCheetahVelocity-v1" / algo / "seeds-0-1"
    for seed in (0, 1):
        assert _rows(cut_dir / f"seed-00{seed}" / "progress.csv") == _rows(whole_dir / f"seed-00{seed}" / "progress.csv")
        a, b = _entry(cut_dir, seed), _entry(whole_dir, seed)
        for name in ("networks", "targets", "optimizer", "multiplier", "action_rng", "replay_rng", "update_rng"):
            for x, y in zip(_tensors(a[name]), _tensors(b[name]), strict=True):
                assert torch.equal(x, y), name
    # everything the runs wrote is inside their directories: the memory maps, the last checkpoint's undo files
    assert _replay_files(cut_dir) == _replay_layout(3)


def _replay_files(run_dir: Path) -> list[str]:
    return sorted(str(p.relative_to(run_dir / "replay")) for p in (run_dir / "replay").rglob("*") if p.is_file())


def _replay_layout(epoch: int, seeds=(0, 1)) -> list[str]:
    return sorted(f"live/seed-{s:03d}/{name}" for s in seeds for name in (
        "storage/meta.json", "storage/row.memmap", "storage/storage_metadata.json", f"undo-{epoch:06d}.bin"))


class _Killed(Exception):
    """A SIGKILL, as far as the run directory can tell: the process stops between two writes."""


def _kill_after(trainer, extends: int) -> None:
    """Stop ``trainer`` after its next ``extends`` replay writes (of every seed), before any later checkpoint."""
    original, count = trainer.replay.extend, [0]

    def extend(*fields):
        original(*fields)
        count[0] += 1
        if count[0] == extends:
            raise _Killed

    trainer.replay.extend = extend


@pytest.mark.parametrize("capacity", [150, 300])
def test_a_run_killed_between_replay_writes_and_checkpoints_resumes_exactly(tmp_path, capacity):
    """Killed inside epoch 2 (replay rows written after checkpoint 1, over rows it holds: the small buffer
    wraps before checkpoint 1 at capacity 150, after it at 300), resumed, killed again inside the resumed
    epoch, resumed to the end: the uninterrupted run's rows, networks, generators, bit for bit."""
    flags = [*FLAGS[: FLAGS.index("--replay-size")], "--replay-size", str(capacity),
             *FLAGS[FLAGS.index("--replay-size") + 2 :]]
    _run(["--algo", "sac_lag", "--seeds", "0", "1", "--output-dir", str(tmp_path / "whole"), *flags])
    cfg = parse_args(["--algo", "sac_lag", "--seeds", "0", "1", "--output-dir", str(tmp_path / "cut"), *flags])
    trainer = trainer_class(cfg)(cfg)
    trainer.run(max_epochs=1)
    for extends in (70, 40):  # 2 simulators: 140 rows per seed after checkpoint 1, then 80
        _kill_after(trainer, extends)
        with pytest.raises(_Killed):
            trainer.run()
        trainer.collector.env.close()
        assert load_checkpoint(cfg.run_dir)["epoch"] == 1
        resumed = dataclasses.replace(cfg, resume=str(cfg.run_dir))
        trainer = trainer_class(resumed)(resumed, load_checkpoint(cfg.run_dir))
    trainer.run()
    trainer.collector.env.close()
    whole_dir = tmp_path / "whole" / "SafetyHalfCheetahVelocity-v1" / "sac_lag" / "seeds-0-1"
    for seed in (0, 1):
        assert _rows(cfg.run_dir / f"seed-00{seed}" / "progress.csv") == _rows(whole_dir / f"seed-00{seed}" / "progress.csv")
        a, b = _entry(cfg.run_dir, seed), _entry(whole_dir, seed)
        for name in ("networks", "targets", "optimizer", "multiplier", "action_rng", "replay_rng", "update_rng"):
            for x, y in zip(_tensors(a[name]), _tensors(b[name]), strict=True):
                assert torch.equal(x, y), name
    assert _replay_files(cfg.run_dir) == _replay_layout(3)


def test_multiplier_moves_with_the_cost(tmp_path):
    over = ["--cost-limit", "0", "--lagrangian-lr", "0.05"]
    _run(["--algo", "sac_lag", "--seed", "0", "--output-dir", str(tmp_path / "over"), *FLAGS, *over])
    rows = _rows(tmp_path / "over" / "SafetyHalfCheetahVelocity-v1" / "sac_lag" / "seed-000" / "progress.csv")
    lam = [float(r["Train/LagrangeMultiplier"]) for r in rows if r["Train/LagrangeMultiplier"]]
    costs = [float(r["Metrics/EpochEpCost"]) for r in rows if r["Metrics/EpochEpCost"]]
    assert all(c > 0 for c in costs) and lam[0] > 1e-3 and lam == sorted(lam) and lam[-1] > lam[0]
    _run(["--algo", "sac_lag", "--seed", "0", "--output-dir", str(tmp_path / "under"), *FLAGS,
          "--cost-limit", "1000", "--lagrangian-lr", "0.05"])
    rows = _rows(tmp_path / "under" / "SafetyHalfCheetahVelocity-v1" / "sac_lag" / "seed-000" / "progress.csv")
    assert [float(r["Train/LagrangeMultiplier"]) for r in rows if r["Train/LagrangeMultiplier"]] == [0.0, 0.0, 0.0]


@pytest.mark.parametrize("argv, message", [
    (["--algo", "ppo_lag", "--polyak", "0.01"], "polyak is an option of the off-policy algorithms"),
    (["--algo", "sac_lag", "--normalize-obs", "true"], "no observation normalisation"),
    (["--algo", "td3", "--compile", "true"], "--compile applies to the on-policy"),
    (["--algo", "sac", "--env-id", "SafetyPointGoal1Vision-v0"], "flat-vector observations only"),
    (["--algo", "sac", "--utd-ratio", "0"], "utd_ratio must be > 0"),
    (["--algo", "ddpg_lag", "--cost-critic-reduction", "median"], "invalid choice"),
])
def test_refused_options(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_a_failed_seed_is_put_back_to_its_epoch_start_alone(tmp_path):
    # A seed whose update diverged gets its epoch-start rows, targets and Adam rows back; the others keep theirs.
    cfg = parse_args(["--algo", "sac_lag", "--seeds", "0", "1", "--output-dir", str(tmp_path), *FLAGS])
    trainer = OffPolicyGroupTrainer(cfg)
    saved = trainer.snapshot
    nets, optimizers = trainer.nets, trainer.optimizers
    rows = {**nets.trained(), **{"target_" + name: t for name, t in nets.targets().items()}}
    with torch.no_grad():
        for tensor in rows.values():
            tensor.add_(1.0)
        for opt in optimizers.values():
            for state in opt.state:
                state["step"].add_(3)
                for moments in (state["exp_avg"], state["exp_avg_sq"]):
                    for tensor in moments:
                        tensor.add_(0.5)
    trainer._restore_seeds(torch.tensor([True, False]))
    for name, tensor in rows.items():
        assert torch.equal(tensor[0], saved["rows"][name][0]), name
        assert torch.equal(tensor[1], saved["rows"][name][1] + 1.0), name
    for name, opt in optimizers.items():
        for state, before in zip(opt.state, saved["moments"][name]["state"], strict=True):
            assert torch.equal(state["step"], before["step"] + torch.tensor([0, 3])), name
            for key in ("exp_avg", "exp_avg_sq"):
                for tensor, old in zip(state[key], before[key], strict=True):
                    assert torch.equal(tensor[0], old[0]) and torch.equal(tensor[1], old[1] + 0.5), (name, key)
