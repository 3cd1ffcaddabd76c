"""sg_torchrl.sweep.analysis: the paper's analysis figure (J^R over PPO-Lag's, cost regions) from a sweep.

Synthetic sweeps (:mod:`sweep_dirs`): every seed logs four epochs of 250 steps whose ``Metrics/EpCost``
rises linearly to its final cost C (C/4, C/2, 3C/4, C), so with the default limit d = 25 a final cost of
40 puts one epoch in each region (10, 20, 30, 40), 20 puts two in Strongly Safe and two in Safe, and 50
lands every epoch on a bound (12.5, 25, 37.5, 50: each in the lower region).
"""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import matplotlib.image
import pytest

from sg_torchrl.sweep.analysis import (
    analysis_rows, parse_cost_regions, parse_warmup_share, plot_analysis, region_counts, write_analysis,
)
from sg_torchrl.sweep.cli import main
from sg_torchrl.sweep.report import collect, write_report
from sweep_dirs import group, single

PROJECT = Path(__file__).resolve().parents[1]
CHEETAH, GOAL, BUTTON = "SafetyHalfCheetahVelocity-v1", "SafetyPointGoal1-v0", "SafetyPointButton1-v0"
MULTI = "Safety2x3HalfCheetahVelocity-v0"
REGIONS = ("Strongly Safe", "Safe", "Unsafe", "Strongly Unsafe")


@pytest.fixture
def sweep(tmp_path: Path) -> Path:
    root = tmp_path / "sweep"
    group(root, CHEETAH, "ppo_lag", {0: (100.0, 40.0), 1: (100.0, 40.0)})  # J^R 100; one epoch per region per seed
    group(root, CHEETAH, "cpo", {0: (150.0, 20.0), 1: (250.0, 20.0)})  # J^R 200: 2.0; costs 5 10 15 20
    group(root, GOAL, "ppo_lag", {0: (10.0, 100.0)})  # costs 25 50 75 100
    group(root, GOAL, "cpo", {0: (5.0, 50.0)})  # J^R 5: 0.5; every cost on a bound
    group(root, BUTTON, "cpo", {0: (7.0, 20.0)})  # no PPO-Lag on this env
    group(root, GOAL, "pcpo", {0: (1.0, 1.0)}, finished=False)  # unfinished: not counted
    for seed, scale in enumerate((1.0, 3.0)):
        single(root, MULTI, "mappo", seed, 1000.0 * scale, 40.0)  # J^R 2000
        single(root, MULTI, "mappo_lag", seed, 500.0 * scale, 20.0)  # J^R 1000: MAPPO is at 2.0 of it
    return root


def _rows(results, **options):
    return {(row["scope"], row["env"], row["algorithm"]): row for row in analysis_rows(results, **options)}


def _shares(row):
    return tuple(row[name] for name in REGIONS)


def test_region_counts_put_a_cost_on_a_bound_in_the_lower_region():
    assert region_counts([12.5, 12.6, 25.0, 25.01, 37.5, 37.6, 0.0], 25.0) == (2, 2, 2, 1)
    assert region_counts([10.0, 20.0, 30.0, 40.0], 20.0, (0.25, 1.0, 2.0)) == (0, 2, 2, 0)  # bounds 5, 20, 40
    assert region_counts([], 25.0) == (0, 0, 0, 0)


def test_per_env_ratios_and_region_shares_are_exact(sweep):
    rows = _rows(collect(sweep))
    cpo = rows[("env", CHEETAH, "CPO")]
    assert (cpo["J^R"], cpo["baseline"], cpo["baseline J^R"], cpo["J^R / baseline"]) == (200.0, "PPO-Lag", 100.0, 2.0)
    assert (cpo["evaluations"], _shares(cpo), cpo["seeds"], cpo["note"]) == (8, (0.5, 0.5, 0.0, 0.0), 2, "")
    lag = rows[("env", CHEETAH, "PPO-Lag")]
    assert (lag["J^R / baseline"], lag["evaluations"], _shares(lag)) == (1.0, 8, (0.25, 0.25, 0.25, 0.25))
    on_bounds = rows[("env", GOAL, "CPO")]
    assert (on_bounds["J^R / baseline"], _shares(on_bounds)) == (0.5, (0.25, 0.25, 0.25, 0.25))
    assert _shares(rows[("env", GOAL, "PPO-Lag")]) == (0.0, 0.25, 0.0, 0.75)
    assert ("env", GOAL, "PCPO") not in rows  # unfinished
    assert rows[("env", CHEETAH, "CPO")]["cost regions (x d)"] == "0.5,1,1.5"
    assert rows[("env", CHEETAH, "CPO")]["warm-up share"] == 0.1


def test_env_without_ppo_lag_gets_no_ratio_and_the_mean_leaves_it_out(sweep):
    rows = _rows(collect(sweep))
    button = rows[("env", BUTTON, "CPO")]
    assert math.isnan(button["J^R / baseline"]) and math.isnan(button["baseline J^R"])
    assert button["note"] == "no PPO-Lag cell on this env with these options, budget and cost limit"
    assert (button["J^R"], _shares(button)) == (7.0, (0.5, 0.5, 0.0, 0.0))  # its regions still count
    overall = rows[("all envs", "all", "CPO")]
    assert overall["J^R / baseline"] == (2.0 + 0.5) / 2
    assert overall["note"] == "J^R / baseline over 2 of 3 envs (no PPO-Lag on the others)"
    # the evaluations pooled over envs: (4, 4, 0, 0) + (1, 1, 1, 1) + (2, 2, 0, 0) of 16
    assert (overall["envs"], overall["seeds"], overall["evaluations"]) == (3, 4, 16)
    assert _shares(overall) == (7 / 16, 7 / 16, 1 / 16, 1 / 16)
    assert math.isnan(overall["J^R"])  # returns of different envs are not averaged


def test_multi_agent_algorithms_are_normalised_by_mappo_lag(sweep):
    rows = _rows(collect(sweep))
    mappo = rows[("env", MULTI, "MAPPO")]
    assert (mappo["agents"], mappo["baseline"], mappo["baseline J^R"], mappo["J^R / baseline"]) == (
        "multi", "MAPPO-Lag", 1000.0, 2.0)  # not PPO-Lag's, and not over the single-agent envs
    assert _shares(mappo) == (0.25, 0.25, 0.25, 0.25)  # two single-seed cells, costs 10 20 30 40 each
    assert rows[("all envs", "all", "MAPPO")]["J^R / baseline"] == 2.0
    assert rows[("all envs", "all", "PPO-Lag")]["agents"] == "single"


def test_multi_agent_env_without_mappo_lag(tmp_path):
    root = tmp_path / "sweep"
    single(root, MULTI, "mappo", 0, 1000.0, 40.0)
    group(root, MULTI, "ppo_lag", {0: (500.0, 10.0)})  # a single-agent baseline is not a multi-agent one
    row = _rows(collect(root))[("all envs", "all", "MAPPO")]
    assert math.isnan(row["J^R / baseline"]) and row["note"] == "no MAPPO-Lag on any env"


@pytest.mark.parametrize("share, kept, shares", [
    (0.0, 8, (0.5, 0.5, 0.0, 0.0)),  # the whole run: 5 10 15 20 per seed
    (0.25, 6, (1 / 3, 2 / 3, 0.0, 0.0)),  # epoch 1 ends at 250 steps, not above 0.25 x 1000: 10 15 20
    (0.5, 4, (0.0, 1.0, 0.0, 0.0)),  # 15 20
])
def test_warmup_share_leaves_out_the_first_epochs(sweep, share, kept, shares):
    row = _rows(collect(sweep), warmup_share=share)[("env", CHEETAH, "CPO")]
    assert (row["evaluations"], _shares(row), row["warm-up share"]) == (kept, shares, share)


def test_warmup_of_a_cell_without_a_budget_is_a_share_of_the_steps_it_logged(tmp_path):
    cell = group(tmp_path / "sweep", GOAL, "ppo_lag", {0: (10.0, 40.0)})  # costs 10 20 30 40 at 250 ... 1000 steps
    config = json.loads((cell / "config.json").read_text())
    del config["total_steps"]  # an older run's config
    (cell / "config.json").write_text(json.dumps(config))
    row = _rows(collect(tmp_path / "sweep"), warmup_share=0.5)[("env", GOAL, "PPO-Lag")]
    assert (row["evaluations"], _shares(row)) == (2, (0.0, 0.0, 0.5, 0.5))  # above 500 of the 1000 logged


def test_cost_regions_option_moves_the_bounds(sweep):
    row = _rows(collect(sweep), cost_regions=(0.25, 1.0, 2.0))[("env", GOAL, "PPO-Lag")]  # 25 50 75 100, d 25
    assert _shares(row) == (0.0, 0.25, 0.25, 0.5) and row["cost regions (x d)"] == "0.25,1,2"


def test_cost_limit_comes_from_each_cells_config(tmp_path):
    root = tmp_path / "sweep"
    group(root, GOAL, "ppo_lag", {0: (10.0, 40.0)}, cost_limit=16.0)  # 10 20 30 40 against d = 16, not 25
    row = _rows(collect(root))[("env", GOAL, "PPO-Lag")]
    assert (row["cost limit"], _shares(row)) == (16.0, (0.0, 0.25, 0.25, 0.5))


@pytest.mark.parametrize("text", ["0.5,1", "0.5,1,1.5,2", "1,0.5,2", "0.5,0.5,1", "0,1,2", "-1,1,2", "a,b,c",
                                  "0.5,1,inf", "0.5,1,nan", ""])
def test_bad_cost_regions_are_refused(text):
    with pytest.raises(ValueError, match="three increasing positive fractions"):
        parse_cost_regions(text)


@pytest.mark.parametrize("value", ["-0.1", "1", "1.5", "nan", "x", ""])
def test_bad_warmup_shares_are_refused(value):
    with pytest.raises(ValueError, match="warm-up share"):
        parse_warmup_share(value)


def test_good_options_parse():
    assert parse_cost_regions("0.25, 1 ,2") == (0.25, 1.0, 2.0)
    assert parse_cost_regions([0.5, 1, 1.5]) == (0.5, 1.0, 1.5)
    assert (parse_warmup_share("0"), parse_warmup_share(0.99)) == (0.0, 0.99)


@pytest.mark.parametrize("flag, value, message", [
    ("--cost-regions", "1,0.5,2", "argument --cost-regions: cost regions are three increasing positive fractions"),
    ("--warmup-share", "1", "argument --warmup-share: the warm-up share is a fraction of the budget"),
])
def test_sg_sweep_refuses_bad_options(sweep, capsys, flag, value, message):
    assert main(["--report-only", "--output-dir", str(sweep), flag, value]) == 2
    assert message in capsys.readouterr().err
    assert not (sweep / "report").exists()


def test_sg_sweep_report_only_writes_the_analysis_with_its_options(sweep, capsys):
    assert main(["--report-only", "--output-dir", str(sweep), "--cost-regions", "0.25,1,2",
                 "--warmup-share", "0"]) == 0
    report = sweep / "report"
    with (report / "analysis.csv").open() as handle:
        rows = {(row["scope"], row["env"], row["algorithm"]): row for row in csv.DictReader(handle)}
    goal = rows[("env", GOAL, "PPO-Lag")]
    assert (goal["cost regions (x d)"], goal["warm-up share"], goal["evaluations"]) == ("0.25,1,2", "0.0", "4")
    assert [float(goal[name]) for name in REGIONS] == [0.0, 0.25, 0.25, 0.5]
    assert float(rows[("all envs", "all", "CPO")]["J^R / baseline"]) == 1.25
    assert rows[("env", BUTTON, "CPO")]["J^R / baseline"] == "nan"
    text = (report / "analysis.md").read_text()
    assert "Strongly Safe J_c <= 0.25d, Safe 0.25d < J_c <= d, Unsafe d < J_c <= 2d, Strongly Unsafe J_c > 2d" in text
    assert "every epoch (sg-sweep --warmup-share)" in text
    assert "no PPO-Lag cell on this env" in text
    assert "analysis.md, analysis.png, analysis.csv" in (report / "table.md").read_text()
    assert matplotlib.image.imread(report / "analysis.png").shape[2] in (3, 4)


def test_figure_draws_both_kinds_apart(sweep, tmp_path, monkeypatch):
    from sg_torchrl.train.plot import plt

    drawn = {}
    real_close = plt.close

    def describe(ax):
        return (ax.get_title(), [t.get_text() for t in ax.get_xticklabels()],
                [round(p.get_height(), 6) for p in ax.patches], [t.get_text() for t in ax.texts])

    def close(fig):  # what plot_analysis drew, read before it frees the figure (axes row by row)
        drawn["axes"] = [[describe(ax) for ax in fig.axes[i:i + 2]] for i in range(0, len(fig.axes), 2)]
        real_close(fig)

    monkeypatch.setattr(plt, "close", close)
    rows = analysis_rows(collect(sweep))
    plot_analysis(rows, tmp_path / "analysis.png", "sweep")
    (single_reward, single_cost), (multi_reward, multi_cost) = drawn["axes"]
    assert single_reward[0].startswith("(a) single-agent: $J^R$ / PPO-Lag's, mean over its envs")
    assert single_reward[1] == ["PPO-Lag", "CPO"]
    assert single_reward[2] == [1.0, 1.25]  # PPO-Lag over itself; CPO's mean of 2.0 and 0.5
    assert multi_reward[0].startswith("(a) multi-agent: $J^R$ / MAPPO-Lag's, mean over 1 env")
    assert multi_reward[1] == ["MAPPO", "MAPPO-Lag"] and multi_reward[2] == [2.0, 1.0]
    # stacked regions, one bar per algorithm in each region, lowest cost first
    # PPO-Lag: (2, 2, 2, 2) on HalfCheetah + (0, 1, 0, 3) on PointGoal1; CPO: (7, 7, 1, 1), as above
    assert single_cost[2] == [round(x, 6) for x in (2 / 12, 7 / 16, 3 / 12, 7 / 16, 2 / 12, 1 / 16, 5 / 12, 1 / 16)]
    assert single_cost[3][-2:] == ["n=12", "n=16"] and multi_cost[3][-2:] == ["n=8", "n=8"]


def test_figure_says_where_there_is_no_baseline(tmp_path, monkeypatch):
    root = tmp_path / "sweep"
    group(root, BUTTON, "cpo", {0: (7.0, 20.0)})
    texts = []
    from sg_torchrl.train.plot import plt

    real_close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig: (texts.extend(t.get_text() for t in fig.axes[0].texts),
                                                   real_close(fig)))
    plot_analysis(analysis_rows(collect(root)), tmp_path / "analysis.png")
    assert texts == ["no PPO-Lag"]


def test_empty_sweep_writes_an_empty_analysis(tmp_path):
    paths = write_analysis([], tmp_path)
    assert set(paths) == {"analysis.md", "analysis.csv", "analysis.png"}
    assert "No finished cell yet." in paths["analysis.md"].read_text()
    assert matplotlib.image.imread(paths["analysis.png"]).shape[2] in (3, 4)


def test_committed_pointgoal1_analysis_is_current(tmp_path):
    # The committed 10M-step PointGoal1 sweep: its analysis.csv is what the report writes from it today.
    copy = tmp_path / "pointgoal1_10m"
    shutil.copytree(PROJECT / "benchmarks" / "sweeps" / "pointgoal1_10m", copy)
    write_report(copy)
    committed = (PROJECT / "benchmarks" / "sweeps" / "pointgoal1_10m" / "report" / "analysis.csv").read_text()
    assert (copy / "report" / "analysis.csv").read_text() == committed
    with (copy / "report" / "analysis.csv").open() as handle:
        rows = {(row["scope"], row["algorithm"]): row for row in csv.DictReader(handle)}
    assert f"{float(rows[('all envs', 'CPO')]['J^R / baseline']):.2f}" == "2.64"
    assert rows[("all envs", "PPO")]["Strongly Unsafe"] == "1.0" and rows[("all envs", "PPO")]["evaluations"] == "1350"
