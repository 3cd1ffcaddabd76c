"""sg_torchrl.sweep.report: a sweep's cells read back into the paper table, per-seed rows and figures.

The cells are synthetic run directories in both layouts (seed groups as sg-sweep writes them, single
seeds as the older benchmarks did), with round numbers so every figure in the rows is known exactly.
"""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import matplotlib.image
import pytest

from sg_torchrl.sweep import report
from sg_torchrl.sweep.report import (
    collect, markdown_table, paper_env_name, paper_rows, plot_env_curves, seed_rows, write_csv, write_report,
)
from sweep_dirs import BUDGET, figures, group, single

PROJECT = Path(__file__).resolve().parents[1]
SINGLE, MULTI = "SafetyHalfCheetahVelocity-v1", "Safety2x3HalfCheetahVelocity-v0"
TAG = "lr=0.001,num_envs=20"
PAPER = {("HalfCheetahVel", "PPO"): (3000.0, 900.0), ("HalfCheetahVel", "PPO-Lag"): (1500.0, 5.0),
         ("2x3HalfCheetahVel", "MAPPO"): (5000.0, 975.0), ("2x3HalfCheetahVel", "MAPPO-Lag"): (1750.0, 30.0)}


@pytest.fixture
def sweep(tmp_path: Path) -> Path:
    root = tmp_path / "sweep"
    attempts = [{"attempt": 1, "node": "10.0.0.1", "start": 0.0, "end": 3600.0, "status": "interrupted"},
                {"attempt": 2, "node": "10.0.0.2", "start": 4000.0, "end": 5800.0, "status": "done"}]
    group(root, SINGLE, "ppo", {0: (100.0, 40.0), 1: (300.0, 60.0)}, attempts=attempts)
    # One PPO-Lag experiment in two seed groups (pooled into one row), its own cost limit, a diverged seed.
    group(root, SINGLE, "ppo_lag", {0: (50.0, 10.0), 1: (100.0, 20.0)}, cost_limit=20.0, time_total=7200.0)
    group(root, SINGLE, "ppo_lag", {2: (150.0, 30.0)}, cost_limit=20.0, diverged=(2,))
    group(root, SINGLE, "ppo_lag", {0: (400.0, 30.0)}, tag=TAG)  # grid options: a PPO run with them is missing
    group(root, SINGLE, "cpo", {0: (80.0, 8.0), 1: (80.0, 8.0)}, finished=False,
          attempts=[{"attempt": 1, "node": "10.0.0.1", "start": 10.0, "end": None, "status": "killed"}])
    for seed, scale in enumerate((1.0, 3.0)):
        single(root, MULTI, "mappo", seed, 1000.0 * scale, 100.0 * scale)
        single(root, MULTI, "mappo_lag", seed, 500.0 * scale, 5.0 * scale)
    # sg-sweep's record of its cells (sg_torchrl.sweep.grid): one has not started, so it has no directory.
    listed = [{"env_id": SINGLE, "algo": algo, "seeds": [0], "options": [], "run_name": f"{SINGLE}/{algo}/seeds-0"}
              for algo in ("ppo", "pg")]
    (root / "sweep.json").write_text(json.dumps({"total_steps": BUDGET, "cells": listed}))
    return root


def _by_key(rows):
    return {(row["env"], row["algorithm"], row["options"]): row for row in rows}


@pytest.mark.parametrize("env_id, paper_name", [
    ("SafetyPointGoal1-v0", "PointGoal1"), ("SafetyHalfCheetahVelocity-v1", "HalfCheetahVel"),
    ("Safety2x3HalfCheetahVelocity-v0", "2x3HalfCheetahVel"), ("Safety9|8HumanoidVelocity-v0", "9|8HumanoidVel"),
])
def test_paper_env_names(env_id, paper_name):
    assert paper_env_name(env_id) == paper_name


def test_published_results_ship_with_the_package():
    # The published columns must not depend on files outside the package (an installed wheel has them).
    assert report.PAPER_RESULTS.parent == Path(report.__file__).resolve().parent
    paper = report.load_paper_results()
    assert ("2x3HalfCheetahVel", "MAPPO-Lag") in paper and ("PointGoal1", "PPO-Lag") in paper
    assert len(paper) == 446  # 414 single-agent and 32 multi-agent (env, algorithm) cells
    assert paper[("2x4AntVel", "MAPPO-Lag")] == (2423.47, 0.0)
    assert "paper_results.csv" in (PROJECT / "pyproject.toml").read_text()  # shipped as package data


def test_collect_reads_both_layouts_finished_or_not(sweep):
    cells = {(c.env_id, c.algo, c.tag, c.seeds): c for c in collect(sweep)}
    assert len(cells) == 11  # 9 directories, 2 cells of sweep.json without one
    pending = cells[(SINGLE, "pg", "", (0,))]  # listed in sweep.json only
    assert (pending.finished, pending.steps, pending.attempts, pending.total_steps, pending.status) == (
        False, 0, 0, BUDGET, "not started")
    ppo = cells[(SINGLE, "ppo", "", (0, 1))]
    assert ppo.finished and ppo.group and ppo.directory == Path(SINGLE, "ppo", "seeds-0-1")
    assert ppo.per_seed[1]["Final/EpRetLast10"] == 300.0 and ppo.steps == BUDGET
    assert (ppo.attempts, ppo.wall_s, ppo.status) == (2, 5400.0, "done")  # (3600 - 0) + (5800 - 4000)
    assert ppo.update_s == 2.5 and ppo.compiled and ppo.cost_limit == 25.0  # seeds log 2.0 and 3.0; default limit
    lag = cells[(SINGLE, "ppo_lag", "", (2,))]
    assert (lag.cost_limit, lag.diverged, lag.attempts, lag.wall_s) == (20.0, (2,), 1, 3600.0)  # no attempts log
    assert cells[(SINGLE, "ppo_lag", TAG, (0,))].directory == Path(SINGLE, "ppo_lag", TAG, "seeds-0")
    cpo = cells[(SINGLE, "cpo", "", (0, 1))]
    assert not cpo.finished and cpo.steps == 500 and cpo.per_seed == {}  # two epochs of 250 so far
    # an attempt without an end adds nothing to the attempts' sum; the 200 s of training it logged count instead
    assert (cpo.attempts, cpo.wall_s, cpo.status) == (1, 200.0, "killed")
    mappo = cells[(MULTI, "mappo", "", (1,))]
    assert not mappo.group and mappo.directory == Path(MULTI, "mappo", "seed-001") and mappo.wall_s == 1800.0
    assert mappo.per_seed == {1: {**figures(3000.0, 300.0), "Train/TotalSteps": BUDGET, "Time/Total": 1800.0,
                                  "Final/EpRetLast50": 3000.0, "Final/EpCostLast50": 300.0}}  # progress.csv's end


def test_paper_rows_pool_groups_and_normalise_by_ppo_or_mappo(sweep, monkeypatch):
    monkeypatch.setattr(report, "load_paper_results", lambda: PAPER)
    rows = _by_key(paper_rows(collect(sweep)))
    assert (SINGLE, "CPO", "") not in rows  # unfinished
    lag = rows[(SINGLE, "PPO-Lag", "")]
    assert {key: lag[key] for key in ("budget", "seeds", "compiled", "diverged", "J^R", "J^C", "J^R / base",
                                      "J^C / limit", "cost limit", "wall h", "attempts", "meets_limit")} == {
        "budget": BUDGET, "seeds": 3, "compiled": 3, "diverged": 1, "J^R": 100.0, "J^C": 20.0,
        "J^R / base": 0.5, "J^C / limit": 1.0, "cost limit": 20.0, "wall h": 1.5, "attempts": 2,
        "meets_limit": True}  # J^R: (50+100+150)/3 over PPO's (100+300)/2; wall: cells of 2 h and 1 h
    assert lag["update s / epoch"] == pytest.approx((2.5 + 4.0) / 2)
    # the curves' end: the diverged seed's log stops at epoch 2 of 4, at half its final figures
    assert (lag["J^R (50)"], lag["J^C (50)"]) == ((50.0 + 100.0 + 75.0) / 3, (10.0 + 20.0 + 15.0) / 3)
    assert (lag["paper J^R"], lag["paper J^C"], lag["paper J^R / base"], lag["paper J^C / limit"]) == (
        1500.0, 5.0, 0.5, 0.25)  # the paper's figures over the paper's PPO and this cell's limit
    assert lag["paper_meets_limit"] is True
    ppo = rows[(SINGLE, "PPO", "")]
    assert (ppo["J^R"], ppo["J^C"], ppo["J^R / base"], ppo["J^C / limit"], ppo["meets_limit"]) == (
        200.0, 50.0, 1.0, 2.0, False)
    assert (ppo["wall h"], ppo["paper J^C / limit"], ppo["paper_meets_limit"]) == (1.5, 36.0, False)
    tagged = rows[(SINGLE, "PPO-Lag", TAG)]
    assert tagged["J^R"] == 400.0 and math.isnan(tagged["J^R / base"])  # no PPO with these options
    assert tagged["paper J^R"] == 1500.0  # the paper's row does not depend on our options
    multi = rows[(MULTI, "MAPPO-Lag", "")]
    assert (multi["seeds"], multi["J^R"], multi["J^C"], multi["J^R / base"], multi["J^C / limit"]) == (
        2, 1000.0, 10.0, 0.5, 0.4)  # over MAPPO's 2000, not PPO's
    assert (multi["paper J^R / base"], multi["paper J^C / limit"], multi["paper_meets_limit"]) == (0.35, 1.2, False)
    assert rows[(MULTI, "MAPPO", "")]["J^R / base"] == 1.0
    assert list(rows) == [(MULTI, "MAPPO", ""), (MULTI, "MAPPO-Lag", ""), (SINGLE, "PPO", ""),
                          (SINGLE, "PPO-Lag", ""), (SINGLE, "PPO-Lag", TAG)]  # env, then the paper's algorithm order


def test_paper_columns_are_empty_where_the_paper_has_no_row(sweep, monkeypatch):
    monkeypatch.setattr(report, "load_paper_results", lambda: {})
    row = _by_key(paper_rows(collect(sweep)))[(SINGLE, "PPO-Lag", "")]
    assert math.isnan(row["paper J^R"]) and math.isnan(row["paper J^R / base"]) and row["paper_meets_limit"] is None


def test_seed_rows_one_per_finished_seed(sweep):
    rows = seed_rows(collect(sweep))
    assert len(rows) == 2 + 3 + 1 + 2 + 2
    lag = [row for row in rows if row["algorithm"] == "PPO-Lag" and not row["options"]]
    assert [(r["seed"], r["EpRet (last 10)"], r["EpCost (last 10)"], r["eval EpRet"], r["eval EpCost"],
             r["diverged"], r["steps"]) for r in lag] == [
        (0, 50.0, 10.0, 51.0, 5.0, False, BUDGET), (1, 100.0, 20.0, 101.0, 10.0, False, BUDGET),
        (2, 150.0, 30.0, 151.0, 15.0, True, 500)]  # the diverged seed's own summary: its steps
    assert lag[2]["directory"] == f"{SINGLE}/ppo_lag/seeds-2"
    assert [(r["EpRet (last 50)"], r["EpCost (last 50)"]) for r in lag] == [(50.0, 10.0), (100.0, 20.0), (75.0, 15.0)]


def test_csv_round_trip(sweep, tmp_path, monkeypatch):
    monkeypatch.setattr(report, "load_paper_results", lambda: PAPER)
    for rows in (paper_rows(collect(sweep)), seed_rows(collect(sweep))):
        path = write_csv(rows, tmp_path / "rows.csv")
        with path.open() as handle:
            read = list(csv.DictReader(handle))
        assert len(read) == len(rows)
        for written, back in zip(rows, read):
            assert list(back) == list(written)
            for key, value in written.items():
                if value is None:
                    assert back[key] == ""
                elif isinstance(value, (bool, str)):
                    assert back[key] == str(value)
                elif math.isnan(value):
                    assert back[key] == "nan"
                else:
                    assert float(back[key]) == value  # full precision


def test_markdown_rows(sweep, monkeypatch):
    monkeypatch.setattr(report, "load_paper_results", lambda: PAPER)
    results = collect(sweep)
    lines = markdown_table(paper_rows(results)).splitlines()
    header = [cell.strip() for cell in lines[0].split("|")[1:-1]]
    assert header[:4] == ["env", "algorithm", "options", "budget"]
    assert lines[1].startswith("|---|---|---|---:|")  # text left, numbers right
    rows = {(cells[1], cells[2]): dict(zip(header, cells))
            for cells in ([c.strip() for c in line.split("|")[1:-1]] for line in lines[2:])}
    lag = rows[("PPO-Lag", "")]
    assert [lag[k] for k in ("budget", "seeds", "J^R", "J^C", "J^R / base", "J^C / limit", "cost limit",
                             "update s / epoch", "wall h", "paper J^R", "paper J^R / base", "meets_limit")] == [
        "1,000", "3", "100.00", "20.00", "0.50", "1.00", "20", "3.2", "1.50", "1500.00", "0.50", "yes"]
    assert rows[("PPO-Lag", TAG)]["J^R / base"] == "-"  # NaN
    assert rows[("PPO-Lag", TAG)]["options"] == TAG
    # Without any options the column is left out.
    untagged = [row for row in paper_rows(results) if not row["options"]]
    assert "options" not in markdown_table(untagged).splitlines()[0]
    assert markdown_table([]) == ""


def test_env_figure_draws_each_algorithm_mean_and_band(sweep, tmp_path, monkeypatch):
    from sg_torchrl.train import plot

    drawn = {}
    real_finish = plot.finish_figure

    def finish(fig, axes, path, cost_limit):  # record what was drawn, then write the figure as usual
        drawn["lines"] = {line.get_label(): (list(line.get_xdata()), list(line.get_ydata())) for line in axes[0].lines}
        drawn["bands"] = len(axes[0].collections)
        drawn["extra limits"] = [line.get_ydata()[0] for line in axes[1].lines if line.get_linestyle() == ":"]
        drawn["limit"] = cost_limit
        real_finish(fig, axes, path, cost_limit)

    monkeypatch.setattr(plot, "finish_figure", finish)
    path = plot_env_curves(collect(sweep), SINGLE, tmp_path / "curves.png")
    assert matplotlib.image.imread(path).shape[2] in (3, 4)
    # The cost limits differ between the cells, so the labels name them.
    assert set(drawn["lines"]) == {"PPO limit 25 (2 seeds)", "PPO-Lag limit 20 (3 seeds)",
                                   f"PPO-Lag [{TAG}] limit 25 (1 seed)", "CPO limit 25 (2 seeds)"}
    # The mean of the seeds at each step; the evaluation row dropped.
    assert drawn["lines"]["PPO limit 25 (2 seeds)"] == ([250, 500, 750, 1000], [50.0, 100.0, 150.0, 200.0])
    assert drawn["lines"]["CPO limit 25 (2 seeds)"][0] == [250, 500]  # an unfinished cell as far as it got
    assert drawn["bands"] == 4
    assert (drawn["limit"], drawn["extra limits"]) == (20.0, [25.0])  # one line per cost limit


def test_write_report_works_on_a_copied_directory(sweep, tmp_path, monkeypatch):
    monkeypatch.setattr(report, "load_paper_results", lambda: PAPER)
    copy = tmp_path / "elsewhere" / "sweep-copy"
    shutil.copytree(sweep, copy)
    shutil.rmtree(sweep)
    paths = write_report(copy)
    assert set(paths) == {"table.md", "table.csv", "seeds.csv", f"curves-{SINGLE}.png", f"curves-{MULTI}.png",
                          "analysis.md", "analysis.csv", "analysis.png"}
    assert all(path.parent == copy / "report" and path.is_file() for path in paths.values())
    text = paths["table.md"].read_text()
    assert str(tmp_path) not in text  # names cells relative to the output directory
    assert "| Safety2x3HalfCheetahVelocity-v0 | MAPPO-Lag |  | 1,000 | 2 |" in text
    assert f"- `{SINGLE}/cpo/seeds-0-1`: {SINGLE} CPO, seeds 0 1: 500 / 1,000 (50%) steps, 1 attempt(s), " \
           "0.06 h, last attempt killed" in text
    assert f"- `{SINGLE}/pg/seeds-0`: {SINGLE} PG, seeds 0: 0 / 1,000 (0%) steps, 0 attempt(s), " \
           "last attempt not started" in text  # listed in sweep.json, no directory yet
    with paths["seeds.csv"].open() as handle:
        assert len(list(csv.DictReader(handle))) == 10
    assert write_report(copy) == paths  # again: the report folder is not read as a cell


def test_real_paper_budget_group(tmp_path):
    # The committed 10M-step PPO-Lag group on SafetyHalfCheetahVelocity-v1, alone in a copy of its column.
    cell = Path("SafetyHalfCheetahVelocity-v1") / "ppo_lag"
    copy = tmp_path / "paper_budget"
    shutil.copytree(PROJECT / "benchmarks" / "sweeps" / "halfcheetah_10m" / cell, copy / cell,
                    ignore=shutil.ignore_patterns("*.png", "checkpoint*", "wandb", "csv"))
    paths = write_report(copy)
    with paths["table.csv"].open() as handle:
        (row,) = list(csv.DictReader(handle))
    assert (row["algorithm"], row["seeds"], row["budget"], row["paper J^R"]) == ("PPO-Lag", "3", "10000000", "3025.42")
    assert f"{float(row['J^R']):.2f}" == "2905.82" and f"{float(row['J^C']):.2f}" == "22.33"
    assert "| SafetyHalfCheetahVelocity-v1 | PPO-Lag | 10,000,000 | 3 | 3 | 0 | 2905.82 | 22.33 |" in \
        paths["table.md"].read_text()
