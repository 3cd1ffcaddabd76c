"""sg_torchrl.train.plot: the step-axis labels and the single-run and seed-group figures."""

from __future__ import annotations

import math

import matplotlib.image
import pytest

from sg_torchrl.train.plot import format_steps, plot_curves, plot_group_curves, training_rows


@pytest.mark.parametrize("steps, label", [
    (0, "0"), (800, "800"), (1_000, "1k"), (20_000, "20k"), (250_000, "250k"), (1_000_000, "1M"),
    (1_500_000, "1.5M"), (10_000_000, "10M"),
])
def test_step_labels_are_short(steps, label):
    # Plain integer ticks ("200000 400000 ...") overlapped in a half-width panel.
    assert format_steps(steps) == label


def history(epochs: int, *, ret0: float = 0.0, cost0: float = 60.0, evaluation: bool = True) -> list[dict[str, float]]:
    """``progress.csv`` rows of a run: a first epoch without a finished episode (NaN metrics), then a
    rising return and a falling cost, and the evaluation row a finished run appends."""
    rows = [{"Train/TotalSteps": 10_000.0, "Metrics/EpRet": math.nan, "Metrics/EpCost": math.nan}]
    rows += [{"Train/TotalSteps": 10_000.0 * e, "Metrics/EpRet": ret0 + e, "Metrics/EpCost": cost0 - 3 * e}
             for e in range(2, epochs + 1)]
    if evaluation:
        rows.append({"Train/TotalSteps": 10_000.0 * epochs, "Metrics/EvalEpRet": 5.0, "Metrics/EvalEpCost": 1.0})
    return rows


def test_training_rows_drop_unfinished_epochs_and_the_evaluation_row():
    rows = training_rows(history(4))
    assert [row["Train/TotalSteps"] for row in rows] == [20_000.0, 30_000.0, 40_000.0]


def test_single_run_figure(tmp_path):
    path = plot_curves(history(30), tmp_path / "curves.png", cost_limit=25.0, title="PPO-Lag on X (seed 0)")
    assert path.exists() and matplotlib.image.imread(path).shape[2] in (3, 4)


def test_group_figure_takes_seeds_of_different_lengths(tmp_path):
    # Seed 2 diverged after epoch 5: its thin line ends there and the mean goes on over seeds 0 and 1.
    histories = {0: history(30), 1: history(30, ret0=2.0, cost0=70.0), 2: history(5, evaluation=False)}
    path = plot_group_curves(histories, tmp_path / "group.png", cost_limit=25.0, title="PPO-Lag on X (seeds 0 1 2)")
    assert path.exists() and matplotlib.image.imread(path).shape[2] in (3, 4)
