"""Benchmark scripts that run in seconds: they run, report the rows they promise and refuse what they cannot do."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _run(script: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(BENCHMARKS / script), *args], cwd=BENCHMARKS, capture_output=True,
                          text=True, timeout=300)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message given when CUDA is missing")
def test_group_step_device_needs_cuda_or_allow_cpu():
    result = _run("group_step_device.py")
    assert result.returncode != 0
    assert "no CUDA device" in result.stderr


def test_group_step_device_cpu_rows(tmp_path):
    out = tmp_path / "rows.json"
    result = _run("group_step_device.py", "--allow-cpu", "--seeds", "1", "--cpu-seeds", "1", "2", "--steps", "2",
                  "--repeats", "1", "--warmup", "1", "--json", str(out))
    assert result.returncode == 0, result.stderr
    rows = json.loads(out.read_text())["results"]
    cpu = [row for row in rows if row["device"] == "cpu"]
    assert [row["seeds"] for row in cpu] == [1, 2]
    for row in cpu:
        assert row["ms_per_step"] > 0
        assert row["ms_per_seed"] == pytest.approx(row["ms_per_step"] / row["seeds"])
    assert "| SafetyHalfCheetahVelocity-v1 | cpu | 2 |" in result.stdout


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message given when CUDA is missing")
def test_engine_device_needs_cuda_or_allow_cpu():
    result = _run("engine_device.py")
    assert result.returncode != 0
    assert "no CUDA device" in result.stderr


def _engine_device_rows(tmp_path, *args: str) -> tuple[list[dict], str]:
    """Run ``engine_device.py --allow-cpu`` at a tiny budget; its JSON rows and its printed table."""
    out = tmp_path / "rows.json"
    result = _run("engine_device.py", "--allow-cpu", "--steps-per-epoch", "100", "--num-envs", "2",
                  "--json", str(out), *args)
    assert result.returncode == 0, result.stderr[-2000:]
    return json.loads(out.read_text())["results"], result.stdout


def test_engine_device_cpu_rows(tmp_path):
    rows, stdout = _engine_device_rows(tmp_path, "--algos", "ppo_lag", "--cpu-seeds", "1", "2", "--epochs", "1")
    assert [(row["algo"], row["device"], row["seeds"]) for row in rows] == [("ppo_lag", "cpu", 1), ("ppo_lag", "cpu", 2)]
    for row in rows:
        assert row["wall_per_1k_per_seed"] > 0 and row["cpu_per_1k_per_seed"] > 0 and row["passes"] >= 1
        assert row["collect_per_1k_per_seed"] + row["update_per_1k_per_seed"] <= row["wall_per_1k_per_seed"]
    assert "| ppo_lag | cpu | 2 |" in stdout and "1.00x |" in stdout


def test_engine_device_multi_agent_and_off_policy_rows(tmp_path):
    """A MAPPO-Lag and a SAC-Lag row (the off-policy one's first epoch is its warm-up: the second's gradient steps count)."""
    rows, stdout = _engine_device_rows(tmp_path, "--algos", "mappo_lag", "sac_lag", "--cpu-seeds", "1", "--epochs", "2")
    assert [(row["algo"], row["device"], row["seeds"]) for row in rows] == [("mappo_lag", "cpu", 1), ("sac_lag", "cpu", 1)]
    mappo, sac = rows
    assert mappo["passes"] >= 1 and [epoch["passes"] for epoch in sac["epochs"]] == [0, 100]
    for row in rows:
        assert row["wall_per_1k_per_seed"] > 0 and row["update_per_1k_per_seed"] > 0
    assert "| mappo_lag | cpu | 1 |" in stdout and "| sac_lag | cpu | 1 |" in stdout


def test_revision_speed_compares_a_revision_with_this_tree():
    """Against HEAD itself: one row, both trees trained in their own process, a ratio printed."""
    result = _run("revision_speed.py", "--base", "HEAD", "--rows", "ppo_lag:1:eager", "--steps-per-epoch", "400",
                  "--num-envs", "2", "--epochs", "2")
    assert result.returncode == 0, result.stderr[-2000:]
    row = next(line for line in result.stdout.splitlines() if line.startswith("| ppo_lag S=1 eager |"))
    base, this, ratio, speedup = (cell.strip() for cell in row.strip("|").split("|")[1:])
    base, this, ratio = float(base), float(this), float(ratio)
    assert base > 0 and this > 0 and ratio == pytest.approx(this / base, rel=1e-2)
    assert speedup == ""  # no single-seed row of the base was measured


def test_off_policy_speed_rows(tmp_path):
    out = tmp_path / "rows.json"
    result = _run("off_policy_speed.py", "--steps", "20", "--json", str(out))
    assert result.returncode == 0, result.stderr[-2000:]
    rows = json.loads(out.read_text())["results"]
    assert [row["row"] for row in rows] == ["plain torch", "engine S=1", "engine S=3"]
    assert rows[0]["cpu_s_per_1k_gradient_steps"] > 0 and all(row["cpu_s_per_1k_steps_per_seed"] > 0 for row in rows[1:])
    assert "| engine S=3 |" in result.stdout


def _seed_group(root: Path, returns_per_seed: list[list[float]], steps_per_epoch: int = 100) -> Path:
    """A seed-group run directory whose seeds log the given per-epoch returns (cost: a tenth of the return)."""
    for seed, returns in enumerate(returns_per_seed):
        lines = ["Metrics/EpRet,Metrics/EpCost,Train/Epoch,Train/TotalSteps"]
        lines += [f"{ret},{ret / 10},{epoch},{(epoch + 1) * steps_per_epoch}" for epoch, ret in enumerate(returns)]
        lines.append(f"{999.0},{999.0},,")  # an evaluation row: no step count, not a curve point
        (root / f"seed-{seed:03d}").mkdir(parents=True)
        (root / f"seed-{seed:03d}" / "progress.csv").write_text("\n".join(lines) + "\n")
    return root


def test_curve_points_reads_each_run_at_the_given_steps(tmp_path):
    full = _seed_group(tmp_path / "full", [[10, 20, 30, 40], [30, 40, 50, 60]])
    short = _seed_group(tmp_path / "short", [[1, 3], [3, 5]])
    result = _run("curve_points.py", str(full), str(short), "--labels", "A", "B", "--steps", "200", "400",
                  "--window", "2")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0] == "| env steps per seed | A J^R / J^C | B J^R / J^C |"
    # at 200 steps: A's seeds average (10, 20) and (30, 40) -> 25; B's (1, 3) and (3, 5) -> 3
    assert lines[2] == "| 0.0002M | 25 / 2.5 | 3 / 0.3 |"
    assert lines[3] == "| 0.0004M | 45 / 4.5 | - |"  # B never reached 400 steps


def test_curve_points_refuses_a_directory_without_seed_logs(tmp_path):
    result = _run("curve_points.py", str(tmp_path), "--steps", "100")
    assert result.returncode != 0 and "no seed-XXX/progress.csv" in result.stderr
