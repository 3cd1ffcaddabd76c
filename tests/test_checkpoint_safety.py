"""Trustworthy runs: checkpoints that cannot run code and refuse damage, run directories
that are never clobbered, resumes that stay where they are told, and work that survives a SIGKILL."""

from __future__ import annotations

import csv
import hashlib
import io
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict

torch.set_num_threads(1)

from sg_torchrl.train import OnPolicyGroupTrainer, TrainConfig, main  # noqa: E402
from sg_torchrl.train.checkpoint import (  # noqa: E402
    CheckpointError,
    RunDirectoryError,
    check_new_run_dir,
    decode_state,
    encode_state,
    load_checkpoint,
    save_checkpoint,
)
from sg_torchrl.train.trainer import CheckpointSchedule  # noqa: E402
from trainer_checks import tiny_config  # noqa: E402


def cli_args(output_dir: Path, run_name: str = "run", *, total_steps: int = 400,
             steps_per_epoch: int = 200) -> list[str]:
    """``sg-train`` flags of a run of ``total_steps / steps_per_epoch`` tiny HalfCheetah epochs."""
    return ["--env-id", "SafetyHalfCheetahVelocity-v1", "--num-envs", "2", "--steps-per-epoch", str(steps_per_epoch),
            "--total-steps", str(total_steps), "--update-iters", "1", "--eval-episodes", "0", "--wandb", "disabled",
            "--progress", "false", "--output-dir", str(output_dir), "--run-name", run_name]


def snapshot(directory: Path) -> dict[str, bytes]:
    """Every file under ``directory``, by relative path, with its bytes."""
    return {str(path.relative_to(directory)): path.read_bytes() for path in sorted(directory.rglob("*"))
            if path.is_file()}


def progress_epochs(run_dir: Path) -> list[int]:
    with (run_dir / "progress.csv").open() as handle:
        return [int(float(row["Train/Epoch"])) for row in csv.DictReader(handle) if row["Train/Epoch"]]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """The run directory of a two-epoch run (a checkpoint of epoch 2), shared read-only by the tests."""
    output = tmp_path_factory.mktemp("finished")
    assert main(cli_args(output)) == 0
    return output / "run"


@pytest.fixture
def run_copy(finished_run, tmp_path) -> Path:
    copy = tmp_path / "copy"
    shutil.copytree(finished_run, copy)
    return copy


# ---------------------------------------------------------------------- code execution
class Exploit:
    """Unpickling this runs a shell command that writes ``marker``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"echo pwned > '{self.marker}'",)


def with_valid_header(payload: bytes) -> bytes:
    """``payload`` behind a correct sg_torchrl header, as someone who knows the format would write it."""
    digest = hashlib.sha256(payload).hexdigest()
    return b"SG_TORCHRL_CHECKPOINT v1 sha256=%s bytes=%d\n" % (digest.encode(), len(payload)) + payload


def torch_saved(obj) -> bytes:
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return buffer.getvalue()


@pytest.mark.parametrize("framing", ["torch.save", "behind a valid header"])
def test_a_crafted_checkpoint_runs_nothing(tmp_path, framing):
    marker = tmp_path / "marker"
    payload = torch_saved({"config": {}, "epoch": 0, "evil": Exploit(marker)})
    path = tmp_path / "checkpoint.pt"
    path.write_bytes(payload if framing == "torch.save" else with_valid_header(payload))
    with pytest.raises(CheckpointError, match=str(path)):
        load_checkpoint(path)
    assert not marker.exists()


def test_sg_train_resume_refuses_a_crafted_checkpoint(tmp_path, capsys):
    marker = tmp_path / "marker"
    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoint.pt").write_bytes(with_valid_header(torch_saved({"config": {}, "epoch": 0,
                                                                        "evil": Exploit(marker)})))
    assert main(["--resume", str(run)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("sg-train: error: checkpoint ") and str(run / "checkpoint.pt") in err
    assert "refused without running it" in err
    assert not marker.exists()


def test_a_raw_pickle_is_refused(tmp_path):
    import pickle

    marker = tmp_path / "marker"
    path = tmp_path / "checkpoint.pt"
    path.write_bytes(pickle.dumps(Exploit(marker)))
    with pytest.raises(CheckpointError, match="not an sg_torchrl checkpoint"):
        load_checkpoint(path)
    assert not marker.exists()


# ---------------------------------------------------------------------- damaged files
def flipped(data: bytes) -> bytes:
    """64 bytes in the middle of the payload inverted (the finding: a weight moved by 3e4, unnoticed)."""
    middle = len(data) // 2
    return data[:middle] + bytes(b ^ 0xFF for b in data[middle:middle + 64]) + data[middle + 64:]


@pytest.mark.parametrize(
    "damage, message",
    [
        (flipped, "is corrupted"),
        (lambda data: data[: len(data) // 2], "is truncated"),
        (lambda data: data[:-1], "is truncated"),
        (lambda data: data + b"\0", "bytes more than its header says"),
        (lambda data: b"", "is empty"),
        (lambda data: np.random.default_rng(0).bytes(len(data)), "not an sg_torchrl checkpoint"),
        (lambda data: data.replace(b"sha256=", b"sha257=", 1), "damaged header"),
        (lambda data: data.replace(b" v1 ", b" v9 ", 1), "format v9"),
    ],
    ids=["flipped", "half", "one-byte-short", "one-byte-long", "empty", "random", "header", "version"],
)
def test_a_damaged_checkpoint_is_refused(run_copy, damage, message, capsys):
    path = run_copy / "checkpoint.pt"
    load_checkpoint(path)  # intact, it loads
    path.write_bytes(damage(path.read_bytes()))
    with pytest.raises(CheckpointError, match=message) as error:
        load_checkpoint(path)
    assert str(path) in str(error.value)
    before = snapshot(run_copy)
    assert main(["--resume", str(run_copy)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("sg-train: error: checkpoint ") and message in err
    assert snapshot(run_copy) == before


def test_checkpoints_are_weights_only_tensors_and_plain_data(finished_run):
    data = (finished_run / "checkpoint.pt").read_bytes()
    header, payload = data.split(b"\n", 1)
    assert header.startswith(b"SG_TORCHRL_CHECKPOINT v1 sha256=" + hashlib.sha256(payload).hexdigest().encode())
    raw = torch.load(io.BytesIO(payload), weights_only=True)  # PyTorch's own restricted unpickler takes it
    state = decode_state(raw)
    assert isinstance(state["collector"]["carry"], TensorDict)
    assert isinstance(state["collector"]["sims"]["elapsed"], np.ndarray)
    assert state["epoch"] == 2


def test_encoding_round_trips_bit_exactly_and_refuses_other_objects(tmp_path):
    rng = np.random.default_rng(3)
    carry = TensorDict({"obs": torch.randn(2, 5), "group": TensorDict({"x": torch.ones(2, 3, 1)}, [2, 3])}, [2])
    named = TensorDict({"r": torch.arange(6.0).reshape(2, 3)}, [2, 3]).refine_names(None, "time")
    state = {
        "config": {"seed": 1}, "epoch": 4, "rng": rng.bit_generator.state, "carry": carry, "named": named,
        "arrays": [np.arange(5, dtype=np.int16), np.zeros((0, 3)), np.array([True, False]), np.float32(0.1)],
        "scalars": (np.float64(1e-300), np.int64(-7), np.bool_(True)), "nan": float("nan"), "size": torch.Size([2]),
    }
    path = save_checkpoint(state, tmp_path / "state.pt")
    loaded = load_checkpoint(path)
    assert loaded["rng"] == rng.bit_generator.state  # 128-bit integers included
    assert (loaded["carry"] == carry).all() and loaded["carry"]["group"].batch_size == (2, 3)
    assert loaded["named"].names == [None, "time"]
    for got, want in zip([*loaded["arrays"], *loaded["scalars"]], [*state["arrays"], *state["scalars"]]):
        assert type(got) is type(want) and np.asarray(got).dtype == np.asarray(want).dtype
        assert np.array_equal(got, want)
    assert loaded["nan"] != loaded["nan"] and loaded["size"] == torch.Size([2])
    with pytest.raises(TypeError, match=r"state\['bad'\]"):
        encode_state({"bad": object()})
    with pytest.raises(TypeError):
        save_checkpoint({"config": {}, "epoch": 0, "bad": Exploit(tmp_path / "m")}, path)
    assert load_checkpoint(path)["epoch"] == 4  # a failed save leaves the previous checkpoint


# ---------------------------------------------------------------------- where a resumed run writes
@pytest.mark.parametrize("given", ["directory", "checkpoint file"])
def test_a_copied_run_resumes_into_the_copy(finished_run, run_copy, given, capsys):
    original = snapshot(finished_run)
    target = run_copy if given == "directory" else run_copy / "checkpoint.pt"
    assert main(["--resume", str(target), "--total-steps", "600"]) == 0
    assert snapshot(finished_run) == original  # every file of the original, byte for byte
    assert load_checkpoint(run_copy)["epoch"] == 3
    assert progress_epochs(run_copy) == [1, 2, 3]
    saved = load_checkpoint(run_copy)["config"]
    assert Path(saved["output_dir"]) / saved["run_name"] == run_copy
    assert f"--resume {run_copy}" in capsys.readouterr().out


def test_resume_flags_that_would_move_the_run_are_refused(run_copy, tmp_path, capsys):
    assert main(["--resume", str(run_copy), "--output-dir", str(tmp_path / "elsewhere")]) == 2
    assert "cannot move it" in capsys.readouterr().err
    assert main(["--resume", str(run_copy), "--overwrite"]) == 2
    assert main(["--resume", str(run_copy), "--preset", "smoke"]) == 2
    assert not (tmp_path / "elsewhere").exists()
    # Flags that name the run's own directory are fine (the benchmark runner passes --output-dir).
    assert main(["--resume", str(run_copy), "--output-dir", str(tmp_path), "--run-name", "copy",
                 "--total-steps", "600"]) == 0
    assert load_checkpoint(run_copy)["epoch"] == 3


def test_a_sweep_cell_resumes_from_its_checkpoint_or_starts_over(finished_run, tmp_path):
    """sg-sweep's cell task (run here without Ray): a cell with a checkpoint continues it (``--resume``);
    one killed before its first checkpoint starts over (``--overwrite``); a finished one is never run again."""
    import json

    from sg_torchrl.sweep.cell import run_cell
    from sg_torchrl.sweep.records import AttemptLog

    root = tmp_path / "sweep"
    root.mkdir()
    (root / "sweep.json").write_text(json.dumps({"token": "t"}))
    unfinished = root / "unfinished"
    shutil.copytree(finished_run, unfinished)
    (unfinished / "summary.json").unlink()  # checkpointed at its last epoch, summary not written yet
    killed = root / "killed"
    killed.mkdir()
    (killed / "progress.csv").write_text("Train/Epoch\n")  # killed before its first checkpoint

    assert run_cell(str(root), "t", "unfinished", [0], ["--never-used-when-resuming"])["ran"]
    assert "sg-train --resume " + str(unfinished) in (unfinished / "sweep.log").read_text()
    assert (unfinished / "summary.json").exists() and AttemptLog(unfinished).read()[-1]["resumed"] is True

    assert run_cell(str(root), "t", "killed", [0], cli_args(root, "killed"))["ran"]
    header = next(line for line in (killed / "sweep.log").read_text().splitlines() if line.startswith("=== attempt"))
    assert "--overwrite" in header and "--resume" not in header and (killed / "summary.json").exists()

    before = snapshot(unfinished)
    assert run_cell(str(root), "t", "unfinished", [0], [])["ran"] is False  # finished: skipped
    assert snapshot(unfinished) == before
    assert [a["status"] for a in AttemptLog(killed).read()] == ["done"]



def test_resume_validates_new_options_against_the_saved_config(tmp_path):
    # 1000-step epochs: --total-steps 3000 is three epochs of this run, not less than one default (20,000) epoch.
    assert main(cli_args(tmp_path, total_steps=2000, steps_per_epoch=1000)) == 0
    assert main(["--resume", str(tmp_path / "run"), "--total-steps", "3000"]) == 0
    checkpoint = load_checkpoint(tmp_path / "run")
    assert checkpoint["epoch"] == 3 and checkpoint["config"]["total_steps"] == 3000
    assert checkpoint["config"]["steps_per_epoch"] == 1000


# ---------------------------------------------------------------------- never clobbered
def test_rerunning_over_a_run_is_refused_and_overwrite_starts_over(finished_run, run_copy, tmp_path, capsys):
    args = cli_args(tmp_path, "copy")
    before = snapshot(run_copy)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.strip() == (f"sg-train: error: run directory {run_copy} already holds a run (checkpoint.pt, "
                           f"progress.csv, summary.json); pass --resume {run_copy} to continue it or --overwrite "
                           f"to start over")
    assert snapshot(run_copy) == before
    (run_copy / "notes.txt").write_text("mine")
    assert main([*args, "--overwrite"]) == 0
    assert progress_epochs(run_copy) == [1, 2]  # a new log, not appended to the old one
    assert (run_copy / "notes.txt").read_text() == "mine"  # only the run's own files were replaced
    with pytest.raises(RunDirectoryError, match="already holds a run"):
        OnPolicyGroupTrainer(tiny_config(tmp_path, run_name="copy"))  # the library refuses the same way
    check_new_run_dir(tmp_path / "new")  # an empty or missing directory is fine


# ---------------------------------------------------------------------- work lost
@pytest.mark.parametrize("flag, value", [("--checkpoint-every", "0"), ("--checkpoint-minutes", "-1")])
def test_bad_checkpoint_intervals_are_refused(tmp_path, flag, value, capsys):
    assert main([*cli_args(tmp_path), flag, value]) == 2
    assert flag[2:].replace("-", "_") in capsys.readouterr().err
    with pytest.raises(ValueError, match="checkpoint_every"):
        TrainConfig(checkpoint_every=0)


def test_checkpoint_schedule(monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(time, "monotonic", lambda: clock[0])
    schedule = CheckpointSchedule(every=10, minutes=1.0, last_epoch=25)
    assert schedule.due(3)  # the first epoch of a run() call, whatever its number
    schedule.saved(3)
    clock[0] = 59.0
    assert not schedule.due(4)
    assert schedule.due(10) and schedule.due(25)  # every 10th and the last
    clock[0] = 63.0
    assert schedule.due(5)  # a minute after the last checkpoint


def test_a_checkpoint_carries_its_progress_row(tmp_path):
    # Killed between writing epoch 1's checkpoint and logging it: the resumed run writes the row.
    first = OnPolicyGroupTrainer(tiny_config(tmp_path))
    first.run(max_epochs=1)
    progress = tmp_path / "run" / "progress.csv"
    progress.write_text(progress.read_text().splitlines()[0] + "\n")
    OnPolicyGroupTrainer(tiny_config(tmp_path), OnPolicyGroupTrainer.load_checkpoint(tmp_path / "run")).run()
    assert progress_epochs(tmp_path / "run") == [1, 2, 3]


def test_sigkill_after_the_first_epoch_leaves_a_resumable_checkpoint(tmp_path):
    run_dir = tmp_path / "run"
    command = [sys.executable, "-m", "sg_torchrl.train",
               *cli_args(tmp_path, total_steps=6000, steps_per_epoch=2000)]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 180
    try:
        while not (run_dir / "progress.csv").exists() or len((run_dir / "progress.csv").read_text().splitlines()) < 2:
            assert process.poll() is None, process.stderr.read().decode()
            assert time.monotonic() < deadline, "no epoch finished in time"
            time.sleep(0.01)
        process.send_signal(signal.SIGKILL)
    finally:
        process.kill()
        process.wait()
    assert process.returncode == -signal.SIGKILL
    assert load_checkpoint(run_dir)["epoch"] >= 1
    assert main(["--resume", str(run_dir)]) == 0
    assert progress_epochs(run_dir) == [1, 2, 3]
    assert load_checkpoint(run_dir)["epoch"] == 3 and (run_dir / "summary.json").exists()
