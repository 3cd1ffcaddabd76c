"""``benchmarks/algorithms.py``: the paper-format table from finished runs (no training here).

The paper's names and published numbers it uses are :mod:`sg_torchrl.sweep.report`'s, tested in test_sweep_report.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "algorithms.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("benchmark_algorithms", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _finished_run(bench, root: Path, env_id: str, algo: str, seed: int, ret: float, cost: float,
                  compiled: bool | None = None) -> None:
    directory = bench.run_dir(str(root), env_id, algo, seed)
    directory.mkdir(parents=True)
    if compiled is not None:
        (directory / "config.json").write_text(json.dumps({"algo": algo, "compile": compiled}))
    (directory / "summary.json").write_text(json.dumps({"Final/EpRetLast10": ret, "Final/EpCostLast10": cost}))
    (directory / "progress.csv").write_text("Time/Update,Metrics/EpRet\n2.0,1\n4.0,2\n")


def test_table_normalises_by_ppo_or_mappo_and_shows_the_paper(bench, tmp_path, monkeypatch):
    single, multi = "SafetyHalfCheetahVelocity-v1", "Safety2x3HalfCheetahVelocity-v0"
    for seed, (ret, cost) in enumerate([(100.0, 10.0), (300.0, 30.0)]):
        _finished_run(bench, tmp_path, single, "ppo", seed, 2 * ret, 2 * cost)
        _finished_run(bench, tmp_path, single, "ppo_lag", seed, ret, cost)
        _finished_run(bench, tmp_path, multi, "mappo", seed, 4 * ret, 4 * cost)
        _finished_run(bench, tmp_path, multi, "mappo_lag", seed, ret, cost)
    paper = {("HalfCheetahVel", "PPO"): (3000.0, 900.0), ("HalfCheetahVel", "PPO-Lag"): (1500.0, 5.0),
             ("2x3HalfCheetahVel", "MAPPO"): (5000.0, 975.0), ("2x3HalfCheetahVel", "MAPPO-Lag"): (1750.0, 0.5)}
    monkeypatch.setattr(bench, "load_paper_results", lambda: paper)
    args = argparse.Namespace(envs=[single, multi], algos=["ppo", "ppo_lag", "mappo", "mappo_lag"], seeds=[0, 1],
                              total_steps=1_000_000, cost_limit=25.0, output_dir=str(tmp_path))
    rows = {tuple(cell.strip() for cell in line.split("|")[1:3]): [c.strip() for c in line.split("|")[1:-1]]
            for line in bench.table(args).splitlines() if line.startswith("| Safety")}
    # columns: env, algorithm, seeds, J^R, J^C, J^R/base, J^C/limit, update s, paper J^R, paper J^C, paper norm R, C
    assert rows[(single, "PPO-Lag")] == [single, "PPO-Lag", "2", "200.00", "20.00", "0.50", "0.80", "3.0",
                                         "1500.00", "5.00", "0.50", "0.20"]
    assert rows[(multi, "MAPPO-Lag")] == [multi, "MAPPO-Lag", "2", "200.00", "20.00", "0.25", "0.80", "3.0",
                                          "1750.00", "0.50", "0.35", "0.02"]
    assert rows[(multi, "MAPPO")][5] == "1.00"


def test_seeds_column_counts_the_compiled_runs(bench, tmp_path, monkeypatch):
    env_id = "SafetyHalfCheetahVelocity-v1"
    _finished_run(bench, tmp_path, env_id, "ppo_lag", 0, 100.0, 10.0, compiled=False)
    _finished_run(bench, tmp_path, env_id, "ppo_lag", 1, 100.0, 10.0, compiled=True)
    _finished_run(bench, tmp_path, env_id, "cpo", 0, 100.0, 10.0)  # a run from before the option
    monkeypatch.setattr(bench, "load_paper_results", lambda: {})
    args = argparse.Namespace(envs=[env_id], algos=["ppo_lag", "cpo"], seeds=[0, 1], total_steps=1_000_000,
                              cost_limit=25.0, output_dir=str(tmp_path))
    seeds = {line.split("|")[2].strip(): line.split("|")[3].strip()
             for line in bench.table(args).splitlines() if line.startswith("| Safety")}
    assert seeds == {"PPO-Lag": "2 (1 compiled)", "CPO": "1"}


def test_ctrl_c_asks_running_cells_to_checkpoint_and_waits_for_them(bench, tmp_path, monkeypatch, capsys):
    # A stand-in cell that exits like sg-train does on a stop request (130) once it gets SIGINT.
    ready = tmp_path / "ready"
    cell = ("import pathlib, signal, sys, time\n"
            "signal.signal(signal.SIGINT, lambda *_: sys.exit(130))\n"
            f"pathlib.Path({str(ready)!r}).touch()\n"
            "time.sleep(60)\n")
    monkeypatch.setattr(bench, "command", lambda *_: [sys.executable, "-c", cell])
    waited = []
    real_sleep = time.sleep  # bench.time is the time module itself: the patch below replaces time.sleep

    def sleep(seconds: float) -> None:  # Ctrl-C arrives at the runner's first wait, once the cell listens
        waited.append(seconds)
        if len(waited) == 1:
            deadline = time.monotonic() + 30
            while not ready.exists() and time.monotonic() < deadline:
                real_sleep(0.05)
            raise KeyboardInterrupt
        real_sleep(seconds)

    monkeypatch.setattr(bench.time, "sleep", sleep)
    args = argparse.Namespace(envs=["SafetyHalfCheetahVelocity-v1"], algos=["ppo"], seeds=[0, 1], seed_major=False,
                              jobs=1, output_dir=str(tmp_path / "runs"), force=False)
    start = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        bench.run_all(args)
    out = capsys.readouterr().out
    assert "[stopping] 1 running cell(s)" in out
    assert "[interrupted (checkpointed; the same command continues it)] SafetyHalfCheetahVelocity-v1 ppo seed 0" in out
    assert "seed 1" not in out  # no new cell starts after Ctrl-C
    assert time.monotonic() - start < 30  # the cell stopped on the forwarded SIGINT, not at its 60 s sleep


def test_per_seed_table_has_one_row_per_finished_run(bench, tmp_path):
    env_id = "SafetyHalfCheetahVelocity-v1"
    _finished_run(bench, tmp_path, env_id, "cpo", 0, 120.0, 7.5, compiled=False)
    _finished_run(bench, tmp_path, env_id, "cpo", 2, 80.0, 30.0, compiled=True)
    bench.run_dir(str(tmp_path), env_id, "cpo", 1).mkdir(parents=True)  # unfinished: no summary.json
    args = argparse.Namespace(envs=[env_id], algos=["cpo"], seeds=[0, 1, 2], output_dir=str(tmp_path))
    rows = [[cell.strip() for cell in line.split("|")[1:-1]]
            for line in bench.seed_table(args).splitlines() if line.startswith("| Safety")]
    assert [row[2:5] for row in rows] == [["0", "120.0", "7.5"], ["2*", "80.0", "30.0"]]
    assert rows[0][5:] == ["-", "-", "3.0", "-"]  # no evaluation or wall time in the summary: shown as "-"
