"""sg_torchrl.sweep without Ray or training: the grid's cells, its checks, sweep.json merging, the CLI's
refusals and how :func:`~sg_torchrl.sweep.cell.run_cell` maps its ``sg-train`` child's exit to an outcome.

``run_cell`` is exercised with a stand-in interpreter (``sys.executable`` pointed at a shell script that
records its arguments and exits or dies as told), so every exit path runs in milliseconds; the real
``sg-train`` under Ray is tests/test_sweep_cluster.py's.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from sg_torchrl.sweep import cli
from sg_torchrl.sweep.cell import CellFailed, CellInterrupted, CellKilled, SweepStorageError, run_cell
from sg_torchrl.sweep.grid import Cell, SweepGrid, SweepGridError, merge_records, parse_grid_option
from sg_torchrl.sweep.records import AttemptLog
from sg_torchrl.sweep.runner import prepare_output

ENV, OTHER_ENV = "SafetyPointGoal1-v0", "SafetyCarGoal1-v0"
BUDGET = 20_000  # one epoch at sg-train's defaults: the smallest budget its config accepts


def make_grid(tmp_path: Path, **kwargs) -> SweepGrid:
    """A grid under ``tmp_path/out`` (two algorithms on one env, seeds 0 1 2 in one cell unless told)."""
    settings = dict(algos=("ppo", "ppo_lag"), env_ids=(ENV,), total_steps=BUDGET, output_dir=tmp_path / "out")
    settings.update(kwargs)
    seeds, per_cell = settings.pop("seeds", (0, 1, 2)), settings.pop("seeds_per_cell", None)
    return SweepGrid.from_seeds(seeds, per_cell, **settings)


# --- the grid -----------------------------------------------------------------------------------------------


def test_cells_are_every_env_algo_option_combination_and_seed_group(tmp_path):
    grid = make_grid(tmp_path, env_ids=(ENV, OTHER_ENV), seeds=(0, 1, 2, 3), seeds_per_cell=2,
                     grid_options=(("lr", ("0.001", "0.0003")), ("num_envs", ("20",))))
    assert len(grid.cells) == 2 * 2 * 2 * 1 * 2
    assert len(set(grid.cells)) == len(grid.cells)
    first = grid.cells[0]
    assert first == Cell(ENV, "ppo", (0, 1), (("lr", "0.001"), ("num_envs", "20")))
    assert first.tag == "lr=0.001,num_envs=20"
    assert first.run_name == f"{ENV}/ppo/lr=0.001,num_envs=20/seeds-0-1"
    assert first.label == f"{ENV} ppo seeds 0 1 [lr=0.001,num_envs=20]"
    assert grid.cell_dir(first) == (tmp_path / "out").resolve() / first.run_name
    assert {cell.seeds for cell in grid.cells} == {(0, 1), (2, 3)}
    assert {cell.options[0] for cell in grid.cells} == {("lr", "0.001"), ("lr", "0.0003")}
    assert {(cell.env_id, cell.algo) for cell in grid.cells} == {(e, a) for e in (ENV, OTHER_ENV)
                                                                 for a in ("ppo", "ppo_lag")}


def test_a_cell_without_grid_options_has_no_tag_folder(tmp_path):
    (cell,) = make_grid(tmp_path, algos=("cpo",)).cells
    assert cell.tag == "" and cell.run_name == f"{ENV}/cpo/seeds-0-1-2" and cell.label == f"{ENV} cpo seeds 0 1 2"


def test_train_arguments_set_the_cell_and_pass_options_and_extra_flags(tmp_path):
    grid = make_grid(tmp_path, grid_options=(("lagrangian_lr", ("0.01",)),), extra=("--compile", "true"))
    cell = grid.cells[1]
    arguments = grid.train_arguments(cell)
    assert arguments == ["--algo", "ppo_lag", "--env-id", ENV, "--seeds", "0", "1", "2", "--total-steps", str(BUDGET),
                         "--output-dir", str(grid.output_dir), "--run-name", cell.run_name,
                         "--lagrangian-lr", "0.01", "--compile", "true"]


@pytest.mark.parametrize("seeds, per_cell, groups", [
    ((0, 1, 2, 3, 4), 2, [(0, 1), (2, 3), (4,)]),
    ((0, 1, 2), None, [(0, 1, 2)]),
    ((5, 3), 1, [(5,), (3,)]),
    ((0, 1), 5, [(0, 1)]),
])
def test_seeds_per_cell_cuts_the_seeds_into_groups_in_order(tmp_path, seeds, per_cell, groups):
    grid = make_grid(tmp_path, algos=("ppo",), seeds=seeds, seeds_per_cell=per_cell)
    assert [cell.seeds for cell in grid.cells] == groups


@pytest.mark.parametrize("per_cell", [0, -1])
def test_a_seed_group_size_below_one_is_refused(tmp_path, per_cell):
    with pytest.raises(SweepGridError, match="seeds per cell must be >= 1"):
        make_grid(tmp_path, seeds_per_cell=per_cell)


def test_a_seed_listed_twice_is_refused(tmp_path):
    with pytest.raises(SweepGridError, match=r"a seed is listed twice: \[0, 1, 0\]"):
        make_grid(tmp_path, seeds=(0, 1, 0), seeds_per_cell=1)


@pytest.mark.parametrize("extra, grid_options, flag", [
    (("--seed", "3"), (), "--seed"),
    (("--total-steps=5",), (), "--total-steps"),
    (("--overwrite",), (), "--overwrite"),
    ((), (("output_dir", ("a", "b")),), "--output-dir"),
    ((), (("run-name", ("x",)),), "--run-name"),
])
def test_flags_the_sweep_sets_itself_are_refused(tmp_path, extra, grid_options, flag):
    with pytest.raises(SweepGridError, match=f"{flag}: the sweep sets these"):
        make_grid(tmp_path, extra=extra, grid_options=grid_options)


def test_a_listed_twice_axis_or_an_empty_grid_is_refused(tmp_path):
    with pytest.raises(SweepGridError, match="share a directory"):
        make_grid(tmp_path, algos=("ppo", "ppo"))
    with pytest.raises(SweepGridError, match="gridded twice"):
        make_grid(tmp_path, grid_options=(("lr", ("1",)), ("lr", ("2",))))
    with pytest.raises(SweepGridError, match="at least one algorithm"):
        make_grid(tmp_path, algos=())
    with pytest.raises(SweepGridError, match="total steps must be a positive integer"):
        make_grid(tmp_path, total_steps=0)


@pytest.mark.parametrize("text, parsed", [
    ("lr=0.001,0.0003", ("lr", ("0.001", "0.0003"))),
    ("--num-envs=2, 4,", ("num_envs", ("2", "4"))),
])
def test_grid_options_parse_to_an_option_name_and_its_values(text, parsed):
    assert parse_grid_option(text) == parsed


@pytest.mark.parametrize("text", ["lr", "=1,2", "lr=", "lr=,"])
def test_a_malformed_grid_option_is_refused(text):
    with pytest.raises(SweepGridError, match="expected NAME=VALUE"):
        parse_grid_option(text)


@pytest.mark.parametrize("extra, grid_options, bad_cell, complaint", [
    (("--bogus", "1"), (), f"cell {ENV} ppo seeds 0 1 2:", "unrecognized arguments: --bogus 1"),
    ((), (("num_envs", ("2", "abc")),), f"cell {ENV} ppo seeds 0 1 2 [num_envs=abc]:", "invalid int value: 'abc'"),
    ((), (("cost_limit", ("25", "-1")),), f"cell {ENV} ppo seeds 0 1 2 [cost_limit=-1]:", "cost_limit must be >= 0"),
])
def test_validate_names_the_first_bad_cell_and_sg_trains_complaint(tmp_path, extra, grid_options, bad_cell, complaint):
    grid = make_grid(tmp_path, extra=extra, grid_options=grid_options)
    with pytest.raises(SweepGridError) as error:
        grid.validate()
    assert str(error.value).startswith(bad_cell) and complaint in str(error.value)


def test_validate_accepts_a_good_grid(tmp_path):
    make_grid(tmp_path, grid_options=(("num_envs", ("2", "4")),), extra=("--wandb", "disabled")).validate()


# --- sweep.json: one budget and one set of shared options per output directory -------------------------------


def test_a_later_sweep_adds_its_cells_to_the_record(tmp_path):
    first = make_grid(tmp_path, algos=("ppo",), extra=("--wandb", "disabled"))
    second = make_grid(tmp_path, algos=("ppo", "cpo"), extra=("--wandb", "disabled"))
    merged = merge_records(merge_records(None, first), second)
    assert [cell["run_name"] for cell in merged["cells"]] == [f"{ENV}/ppo/seeds-0-1-2", f"{ENV}/cpo/seeds-0-1-2"]
    assert merged["algos"] == ["ppo", "cpo"] and merged["total_steps"] == BUDGET


@pytest.mark.parametrize("change", [{"total_steps": 2 * BUDGET}, {"extra": ("--compile", "true")}])
def test_a_sweep_with_another_budget_or_shared_options_is_refused(tmp_path, change):
    earlier = merge_records(None, make_grid(tmp_path))
    with pytest.raises(SweepGridError, match="Use another --output-dir"):
        merge_records(earlier, make_grid(tmp_path, **change))


def test_prepare_output_keeps_the_storage_token_across_sweeps(tmp_path):
    token = prepare_output(make_grid(tmp_path, algos=("ppo",)))
    assert prepare_output(make_grid(tmp_path, algos=("cpo",))) == token
    record = json.loads((tmp_path / "out" / "sweep.json").read_text())
    assert record["token"] == token and len(record["cells"]) == 2


# --- the command line -----------------------------------------------------------------------------------------


def sweep_command(tmp_path: Path, *arguments: str) -> list[str]:
    return ["--algos", "ppo", "--envs", ENV, "--total-steps", str(BUDGET), "--output-dir", str(tmp_path / "out"),
            *arguments]


@pytest.mark.parametrize("argv, message", [
    (["--envs", ENV], "--algos required"),
    (["--algos", "ppo", "--envs", ENV, "--grid", "lr"], "expected NAME=VALUE"),
    (["--algos", "ppo", "--envs", ENV, "--seeds", "1", "1"], "a seed is listed twice"),
    (["--algos", "ppo", "--envs", ENV, "--", "--seed", "3"], "--seed: the sweep sets these"),
    (["--algos", "ppo", "--envs", ENV, "--total-steps", "20000", "--", "--bogus"], "unrecognized arguments: --bogus"),
    (["--algos", "ppo", "--envs", ENV, "--no-such-flag"], "unrecognized arguments: --no-such-flag"),
])
def test_the_cli_refuses_bad_input_with_exit_status_2_before_any_cell_runs(tmp_path, capsys, argv, message):
    assert cli.main(["--output-dir", str(tmp_path / "out"), *argv]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out" / "sweep.json").exists()


def test_the_cli_refuses_an_output_directory_of_another_budget_and_leaves_it_alone(tmp_path, capsys):
    prepare_output(make_grid(tmp_path, algos=("ppo",), total_steps=2 * BUDGET))
    before = (tmp_path / "out" / "sweep.json").read_text()
    assert cli.main(sweep_command(tmp_path)) == 2
    assert "Use another --output-dir" in capsys.readouterr().err
    assert (tmp_path / "out" / "sweep.json").read_text() == before


def test_report_only_refuses_a_missing_directory(tmp_path, capsys):
    assert cli.main(["--report-only", "--output-dir", str(tmp_path / "nowhere")]) == 2
    assert f"{tmp_path / 'nowhere'} does not exist" in capsys.readouterr().err
    assert not (tmp_path / "nowhere").exists()


def test_report_only_reports_a_sweep_with_no_finished_cell(tmp_path, capsys):
    prepare_output(make_grid(tmp_path, algos=("ppo",)))
    assert cli.main(["--report-only", "--output-dir", str(tmp_path / "out")]) == 0
    table = (tmp_path / "out" / "report" / "table.md").read_text()
    assert "No finished cell yet." in table and f"`{ENV}/ppo/seeds-0-1-2`" in table and "not started" in table
    assert "No finished cell yet." in capsys.readouterr().out


# --- run_cell: the sg-train child's exit -> the task's outcome --------------------------------------------------


@pytest.fixture
def fake_train(tmp_path, monkeypatch):
    """``run_cell``'s interpreter replaced by a shell script: it appends its arguments to ``calls.txt``, then runs
    the body the test wrote to ``behaviour.sh`` (in the cell's directory: ``$CELL``) and exits with its status.

    Returns ``(grid, cell, call)``: ``call()`` runs ``run_cell`` for the cell as a sweep's task would.
    """
    grid = make_grid(tmp_path, algos=("ppo",))
    (cell,) = grid.cells
    token = prepare_output(grid)
    directory = grid.cell_dir(cell)
    script = tmp_path / "fake-python"
    script.write_text(f'#!/bin/sh\nCELL="{directory}"\necho "$@" >> "$CELL/calls.txt"\n. "$CELL/behaviour.sh"\n')
    script.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(script))
    directory.mkdir(parents=True)

    def call():
        return run_cell(str(grid.output_dir), token, cell.run_name, list(cell.seeds), grid.train_arguments(cell))

    return grid, cell, call


def behave(grid: SweepGrid, cell: Cell, body: str) -> None:
    (grid.cell_dir(cell) / "behaviour.sh").write_text(body + "\n")


def calls(grid: SweepGrid, cell: Cell) -> list[str]:
    path = grid.cell_dir(cell) / "calls.txt"
    return path.read_text().splitlines() if path.exists() else []


def test_a_clean_exit_is_a_finished_attempt_of_a_fresh_start(fake_train):
    grid, cell, call = fake_train
    behave(grid, cell, 'echo "{}" > "$CELL/summary.json"; exit 0')
    result = call()
    assert result["status"] == "done" and result["ran"] and result["code"] == 0
    (arguments,) = calls(grid, cell)
    assert arguments.startswith("-m sg_torchrl.train --algo ppo") and arguments.endswith("--overwrite --progress false")
    (attempt,) = AttemptLog(grid.cell_dir(cell)).read()
    assert attempt["status"] == "done" and not attempt["resumed"] and attempt["code"] == 0
    assert attempt["end"] >= attempt["start"] and attempt["node_id"] is None  # no Ray here


def test_a_finished_cell_is_not_run_again(fake_train):
    grid, cell, call = fake_train
    behave(grid, cell, "exit 3")
    (grid.cell_dir(cell) / "summary.json").write_text("{}")
    assert call() == {"status": "done", "ran": False}
    assert calls(grid, cell) == [] and AttemptLog(grid.cell_dir(cell)).read() == []


def test_a_checkpoint_makes_the_attempt_a_resume_and_an_earlier_running_attempt_lost(fake_train):
    grid, cell, call = fake_train
    directory = grid.cell_dir(cell)
    behave(grid, cell, 'echo "{}" > "$CELL/summary.json"; exit 1')  # every seed diverged: finished all the same
    (directory / "checkpoint.pt").write_bytes(b"")
    AttemptLog(directory).begin(node="elsewhere", pid=1, resumed=False)  # a worker that died without a word
    assert call()["ran"]
    assert calls(grid, cell) == [f"-m sg_torchrl.train --resume {directory} --progress false"]
    lost, resumed = AttemptLog(directory).read()
    assert (lost["status"], resumed["status"], resumed["resumed"], resumed["attempt"]) == ("lost", "done", True, 2)


@pytest.mark.parametrize("body, error, status, code", [
    ("kill -9 $$", CellKilled, "killed", -9),
    ("exit 143", CellInterrupted, "interrupted", 143),
    ("exit 130", CellInterrupted, "interrupted", 130),
    ("echo 'sg-train: error: something broke'; exit 1", CellFailed, "failed", 1),
    ("exit 0", None, "done", 0),
])
def test_the_childs_exit_decides_the_outcome(fake_train, body, error, status, code):
    grid, cell, call = fake_train
    behave(grid, cell, body)
    if error is None:
        call()
    else:
        with pytest.raises(error) as raised:
            call()
        if error is CellFailed:  # the log's end is in the message: a failed cell explains itself in the sweep's output
            assert "something broke" in str(raised.value)
    (attempt,) = AttemptLog(grid.cell_dir(cell)).read()
    assert (attempt["status"], attempt["code"]) == (status, code)


def test_a_node_that_cannot_see_the_sweeps_record_refuses_the_cell(fake_train):
    grid, cell, _ = fake_train
    behave(grid, cell, "exit 0")
    with pytest.raises(SweepStorageError, match="storage every node of the cluster shares"):
        run_cell(str(grid.output_dir), "another-sweeps-token", cell.run_name, list(cell.seeds), [])
    assert calls(grid, cell) == []


@pytest.mark.skipif(not Path("/proc/self/autogroup").exists(), reason="no autogroup scheduling on this kernel")
def test_a_cells_session_keeps_the_sweeps_niceness():
    # A cell's sg-train runs in its own session; under autogroup scheduling its nice value would count only
    # inside that session, so `nice sg-sweep` would not yield to the rest of the machine.
    script = (
        "import os, subprocess, sys, time\n"
        "from sg_torchrl.sweep.cell import _keep_niceness\n"
        "child = subprocess.Popen(['sleep', '5'], start_new_session=True)\n"
        "_keep_niceness(child.pid)\n"
        "print(open(f'/proc/{child.pid}/autogroup').read().strip())\n"
        "child.kill()\n"
    )
    result = subprocess.run(["nice", "-n", "7", sys.executable, "-c", script], capture_output=True, text=True,
                            check=True)
    expected = min(os.getpriority(os.PRIO_PROCESS, 0) + 7, 19)  # nice adds to this test's own niceness
    assert result.stdout.strip().endswith(f"nice {expected}"), result.stdout


def test_one_driver_per_output_directory(tmp_path):
    from sg_torchrl.sweep.runner import _driver_lock

    with _driver_lock(tmp_path):
        with pytest.raises(SweepGridError, match=f"another sg-sweep \\(pid {os.getpid()}\\) is running"):
            with _driver_lock(tmp_path):
                pass
    with _driver_lock(tmp_path):  # released with the first driver
        pass


# --- the driver's status line -----------------------------------------------------------------------------------


def test_the_status_line_rates_a_cell_from_when_it_was_first_seen_running(tmp_path, monkeypatch):
    """The first status line after a cell starts (or restarts from a checkpoint with steps already logged)
    gives its rate since it was first seen running, not 0; a line with nothing measured yet says so."""
    from sg_torchrl.sweep import runner

    grid = make_grid(tmp_path, algos=("ppo",))
    (cell,) = grid.cells
    directory = grid.cell_dir(cell)
    (directory / "seed-000").mkdir(parents=True)

    def log_steps(*steps: int) -> None:
        rows = "".join(f"{index},{value}\n" for index, value in enumerate(steps))
        (directory / "seed-000" / "progress.csv").write_text("Train/Epoch,Train/TotalSteps\n" + rows)

    clock = [100.0]
    monkeypatch.setattr(runner.time, "monotonic", lambda: clock[0])
    lines: list[str] = []
    progress = runner._Progress(grid, [cell], every=60.0, out=lines.append)
    log_steps(40_000)  # a resumed cell: two epochs logged by an earlier attempt
    AttemptLog(directory).path.write_text(json.dumps({"attempt": 2, "status": "running", "resumed": True,
                                                     "node": "127.0.0.1", "epochs_before": 2}) + "\n")
    clock[0] = 110.0
    progress.poll([cell], 0, 0)  # seen running: measured at 40k steps per seed
    assert lines == [f"[restart] {cell.label} on 127.0.0.1 from its checkpoint (attempt 2, 2 epochs logged "
                     f"before); log {directory}/sweep.log"]
    log_steps(40_000, 60_000)
    clock[0] = 170.0
    progress.poll([cell], 0, 0)  # the first status line: 20k steps x 3 seeds in 60 s
    assert lines[-1].endswith("0 done, 1 running, 0 failed, 0 waiting; 1,000 env steps/s")
    log_steps(40_000, 60_000, 80_000, 100_000)
    clock[0] = 230.0
    progress.poll([cell], 0, 0)
    assert lines[-1].endswith("; 2,000 env steps/s")

    fresh = runner._Progress(grid, [cell], every=60.0, out=lines.append)
    fresh.poll([cell], 0, 0, force=True)  # first seen at this very line: no interval to rate yet
    assert lines[-1].endswith("0 done, 1 running, 0 failed, 0 waiting; env steps/s from the next line")
    fresh.poll([], 1, 0, force=True)  # nothing running: a plain 0
    assert lines[-1].endswith("1 done, 0 running, 0 failed, 0 waiting; 0 env steps/s")
