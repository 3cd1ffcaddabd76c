"""Write-side faults: a path that would leave the output directory, an output directory that is a file, a full
disk (``RLIMIT_FSIZE``, the kernel's own ``EFBIG``) during a checkpoint and during a progress row, an unwritable
or vanished directory. Each ends in one ``sg-train: error:`` line and exit 3, leaves no temporary file, keeps
the last checkpoint byte for byte, and ``--resume`` continues to the numbers of an uninterrupted run."""

from __future__ import annotations

import csv
import errno
import os
import pickle
import resource
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

torch.set_num_threads(1)

import sg_torchrl  # noqa: E402
from sg_torchrl.sweep import cli as sweep_cli  # noqa: E402
from sg_torchrl.sweep.cell import CellFailed, run_cell  # noqa: E402
from sg_torchrl.sweep.grid import SweepGrid  # noqa: E402
from sg_torchrl.sweep.runner import prepare_output  # noqa: E402
from sg_torchrl.train import SeedGroupTrainer, main  # noqa: E402
from sg_torchrl.train.writes import EXIT_WRITE_FAILED, RunWriteError, append_text  # noqa: E402

ENV = "SafetyHalfCheetahVelocity-v1"


def cli_args(output_dir: Path, run_name: str = "run", *extra: str) -> list[str]:
    """Three 200-step epochs (checkpoints after epochs 1 and 3 unless ``extra`` says otherwise)."""
    return ["--env-id", ENV, "--num-envs", "2", "--steps-per-epoch", "200", "--total-steps", "600",
            "--update-iters", "1", "--eval-episodes", "0", "--wandb", "disabled", "--progress", "false",
            "--output-dir", str(output_dir), "--run-name", run_name, *extra]


def rows_without_timing(run_dir: Path) -> list[dict[str, str]]:
    """``progress.csv``'s rows without the ``Time/`` columns (wall-clock figures differ between runs)."""
    with (run_dir / "progress.csv").open(newline="") as handle:
        return [{k: v for k, v in row.items() if not k.startswith("Time/")} for row in csv.DictReader(handle)]


def leftovers(directory: Path) -> list[str]:
    return sorted(str(path.relative_to(directory)) for path in directory.rglob("*.tmp"))


def error_line(err: str) -> str:
    """The one ``sg-train: error:`` line of ``err``, checking there is exactly one and no traceback."""
    lines = [line for line in err.splitlines() if line.startswith("sg-train: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """An uninterrupted three-epoch run: the numbers a faulted and resumed run must reach."""
    output = tmp_path_factory.mktemp("reference")
    assert main(cli_args(output)) == 0
    return output / "run"


# A wrapper around ``sg-train`` that lowers RLIMIT_FSIZE at a chosen moment of the run, so that the kernel
# refuses a chosen write with EFBIG (Python ignores SIGXFSZ, so the write fails instead of killing the process).
LIMITED_TRAIN = textwrap.dedent("""
    import os, resource, shutil, sys
    from pathlib import Path
    from sg_torchrl.train import checkpoint, logging, main

    when, copy = sys.argv[1], Path(sys.argv[2])

    def limit(size):
        resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))

    save, append, appends = checkpoint.save_checkpoint, logging.append_text, []

    def save_then_limit(state, path):  # after the first checkpoint: later ones fail halfway
        out = save(state, path)
        if when == "checkpoint":
            shutil.copyfile(path, copy)
            limit(path.stat().st_size // 2)
        return out

    def limited_append(path, text):  # the second progress row fails a few bytes in
        appends.append(path)
        if when == "progress" and len(appends) == 2:
            shutil.copyfile(path.parent / "checkpoint.pt", copy)
            limit(path.stat().st_size + 10)
        return append(path, text)

    checkpoint.save_checkpoint, logging.append_text = save_then_limit, limited_append
    sys.exit(main(sys.argv[3:]))
""")


def run_limited(when: str, copy: Path, argv: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", LIMITED_TRAIN, when, str(copy), *argv], capture_output=True,
                          text=True, timeout=300)


# ---------------------------------------------------------------------- paths
@pytest.mark.parametrize("run_name", ["../../elsewhere", "a/../../b", "/tmp/elsewhere"])
def test_a_run_name_leaving_the_output_dir_is_refused_before_anything_runs(tmp_path, monkeypatch, capsys, run_name):
    monkeypatch.chdir(tmp_path)
    victim = tmp_path / "elsewhere" / "progress.csv"  # what --overwrite would have removed
    victim.parent.mkdir()
    victim.write_text("not sg-train's\n")
    monkeypatch.setattr(sg_torchrl, "make", lambda *a, **k: pytest.fail("an env was built"))
    assert main(cli_args(Path("out/runs"), run_name, "--overwrite")) == 2
    assert "it must name a folder inside output_dir" in error_line(capsys.readouterr().err)
    assert victim.read_text() == "not sg-train's\n" and not (tmp_path / "out").exists()


def test_an_output_dir_that_is_a_file_is_refused_before_the_env_is_built(tmp_path, monkeypatch, capsys):
    blocker = tmp_path / "runs"
    blocker.write_text("a file\n")
    monkeypatch.setattr(sg_torchrl, "make", lambda *a, **k: pytest.fail("an env was built"))
    assert main(cli_args(blocker)) == EXIT_WRITE_FAILED
    assert error_line(capsys.readouterr().err) == \
        f"sg-train: error: cannot write {blocker / 'run'}: {blocker} is a file, not a directory"


# ---------------------------------------------------------------------- a full disk
def test_a_full_disk_at_the_first_checkpoint_leaves_nothing_and_the_same_command_starts_over(tmp_path, reference):
    size = (reference / "checkpoint.pt").stat().st_size // 2
    limit = lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))  # noqa: E731
    argv = cli_args(tmp_path)
    done = subprocess.run([sys.executable, "-m", "sg_torchrl.train", *argv], capture_output=True, text=True,
                          preexec_fn=limit, timeout=300)
    assert done.returncode == EXIT_WRITE_FAILED
    run = tmp_path / "run"
    assert error_line(done.stderr) == (f"sg-train: error: cannot write {run / 'checkpoint.pt'}: file too large; {run} "
                                       f"holds no checkpoint to continue from: run the same command again once the "
                                       f"cause is fixed")
    assert leftovers(tmp_path) == [] and not (run / "checkpoint.pt").exists()
    assert main(argv) == 0  # nothing marks a run there: the same command starts it
    assert rows_without_timing(run) == rows_without_timing(reference)


# Checkpointing every epoch, epoch 2's checkpoint fails; by default (epochs 1 and 3) epoch 2's progress row does.
@pytest.mark.parametrize("when, file, flags", [("checkpoint", "checkpoint.pt", ("--checkpoint-minutes", "0")),
                                               ("progress", "progress.csv", ())])
def test_a_full_disk_mid_run_keeps_the_last_checkpoint_and_resume_continues_exactly(tmp_path, reference, when, file,
                                                                                    flags):
    run, copy = tmp_path / "run", tmp_path / "checkpoint-epoch-1.pt"
    done = run_limited(when, copy, cli_args(tmp_path, "run", *flags))
    assert done.returncode == EXIT_WRITE_FAILED, done.stderr
    assert error_line(done.stderr) == (f"sg-train: error: cannot write {run / file}: file too large; the last "
                                       f"checkpoint (epoch 1) is intact, continue with: sg-train --resume {run}")
    assert leftovers(tmp_path) == []
    assert (run / "checkpoint.pt").read_bytes() == copy.read_bytes()  # the previous checkpoint, byte for byte
    assert [row["Train/Epoch"] for row in rows_without_timing(run)] == ["1"]  # no partial row
    assert main(["--resume", str(run)]) == 0
    assert rows_without_timing(run) == rows_without_timing(reference)


# ---------------------------------------------------------------------- unwritable, vanished
@pytest.mark.parametrize("code, words", [(errno.EACCES, "permission denied"), (errno.EROFS, "read-only file system"),
                                         (errno.EDQUOT, "disk quota exceeded")])
def test_an_unwritable_directory_is_one_line_and_exit_3(tmp_path, monkeypatch, capsys, code, words):
    fsync, calls = os.fsync, []

    def failing_fsync(fd):  # the second checkpoint (write_atomic fsyncs it) is refused
        calls.append(fd)
        if len(calls) == 2:
            raise OSError(code, os.strerror(code))
        fsync(fd)

    monkeypatch.setattr(os, "fsync", failing_fsync)
    run = tmp_path / "run"
    assert main(cli_args(tmp_path, "run", "--checkpoint-minutes", "0")) == EXIT_WRITE_FAILED
    assert error_line(capsys.readouterr().err) == (
        f"sg-train: error: cannot write {run / 'checkpoint.pt'}: {words}; the last checkpoint (epoch 1) is intact, "
        f"continue with: sg-train --resume {run}")
    assert leftovers(tmp_path) == [] and SeedGroupTrainer.load_checkpoint(run)["epoch"] == 1


def test_a_run_directory_vanishing_mid_run_is_not_recreated(tmp_path, monkeypatch, capsys):
    train_epoch, run = SeedGroupTrainer.train_epoch, tmp_path / "run"

    def vanish_before_epoch_2(self):
        if self.epoch == 1:
            shutil.rmtree(run)  # an unmounted disk
        return train_epoch(self)

    monkeypatch.setattr(SeedGroupTrainer, "train_epoch", vanish_before_epoch_2)
    assert main(cli_args(tmp_path, "run", "--checkpoint-minutes", "0")) == EXIT_WRITE_FAILED
    assert error_line(capsys.readouterr().err).startswith(
        f"sg-train: error: cannot write {run / 'checkpoint.pt'}: no such file or directory; {run} holds no checkpoint")
    assert not run.exists()


def test_a_failed_append_is_cut_back_off_the_file(tmp_path, monkeypatch):
    path = tmp_path / "progress.csv"
    path.write_text("a,b\r\n1,2\r\n")
    real_open = open

    class HalfWrites:  # writes half of what it is given, then the disk is full
        def __init__(self, handle):
            self.handle = handle

        def __getattr__(self, name):
            return getattr(self.handle, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.handle.close()

        def write(self, data):
            if len(data) < 4:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return self.handle.write(data[:len(data) // 2])

    monkeypatch.setattr("builtins.open", lambda *a, **k: HalfWrites(real_open(*a, **k)))
    with pytest.raises(RunWriteError, match="no space left on device"):
        append_text(path, "3,4\r\n")
    monkeypatch.undo()
    assert path.read_bytes() == b"a,b\r\n1,2\r\n"
    error = RunWriteError(path, "file too large")  # Ray pickles a cell task's exception back to the driver
    assert str(pickle.loads(pickle.dumps(error))) == str(error) == f"cannot write {path}: file too large"


# ---------------------------------------------------------------------- sg-sweep
def test_a_sweep_cell_that_cannot_write_fails_with_sg_trains_line(tmp_path):
    grid = SweepGrid(algos=("ppo",), env_ids=(ENV,), seed_groups=((0,),), total_steps=400, output_dir=tmp_path,
                     extra=("--num-envs", "2", "--steps-per-epoch", "200", "--update-iters", "1",
                            "--eval-episodes", "0", "--wandb", "disabled"))
    (cell,) = grid.cells
    token = prepare_output(grid)
    blocker = grid.cell_dir(cell) / "seed-000"  # where the seed's logs go is a file
    blocker.parent.mkdir(parents=True)
    blocker.write_text("a file\n")
    with pytest.raises(CellFailed) as failed:
        run_cell(str(grid.output_dir), token, cell.run_name, list(cell.seeds), grid.train_arguments(cell))
    first = str(failed.value).splitlines()[0]
    assert first.startswith(f"sg-train: error: cannot write {blocker}: {blocker} is a file, not a directory")
    assert "(exit 3)" in first
    with pytest.raises(ValueError, match="would leave output_dir"):
        run_cell(str(grid.output_dir), token, "../outside", [0], [])


def test_sg_sweep_on_an_output_dir_that_is_a_file_says_so(tmp_path, capsys):
    blocker = tmp_path / "sweep"
    blocker.write_text("a file\n")
    code = sweep_cli.main(["--algos", "ppo", "--envs", ENV, "--seeds", "0", "--output-dir", str(blocker)])
    assert code == EXIT_WRITE_FAILED
    assert capsys.readouterr().err.strip() == \
        f"sg-sweep: error: cannot write {blocker}: {blocker} is a file, not a directory"
