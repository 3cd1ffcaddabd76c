"""Learning-curve figures: episode return and episode cost against env steps, with the cost limit.

* :func:`plot_curves`: one run (``curves.png`` in its run directory);
* :func:`plot_group_curves`: a seed group (``curves.png`` in the group's directory), every seed's
  curves as thin lines and their mean as a thick one, so the spread across seeds is visible next to
  what the group achieves on average.

Both read ``progress.csv`` rows (:meth:`sg_torchrl.train.logging.RunLogger.history`) and share the
panels of :func:`figure_panels` and :func:`finish_figure` (public because a sweep's per-env figure,
:func:`sg_torchrl.sweep.report.plot_env_curves`, draws on the same panels) and their axis formatting:
env steps run to millions, and matplotlib's plain integer ticks ("200000 400000 ...") overlapped in a
half-width panel, so the step axis has at most five ticks written as 250k / 1.5M.
"""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")  # headless: never needs a display
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.ticker import FuncFormatter, MaxNLocator  # noqa: E402

from sg_torchrl.train.writes import write_atomic  # noqa: E402

__all__ = ["figure_panels", "finish_figure", "format_steps", "plot_curves", "plot_group_curves", "training_rows"]

Row = Mapping[str, float]
#: The two panels of every figure: (metric, panel title, y label, colour).
PANELS = (("Metrics/EpRet", "Episode return", "EpRet", "tab:blue"),
          ("Metrics/EpCost", "Episode cost", "EpCost", "tab:red"))


def format_steps(steps: float, _position: object = None) -> str:
    """A step count as a short tick label: ``0``, ``800``, ``250k``, ``1.5M`` (trailing zeros dropped)."""
    for scale, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(steps) >= scale:
            return f"{steps / scale:.3g}{suffix}"
    return f"{steps:.0f}"


def training_rows(history: Sequence[Row]) -> list[Row]:
    """The rows of ``history`` that hold training curves: those with a finite ``Metrics/EpRet``.

    Drops the epochs before the first finished episode (NaN moving averages) and the evaluation row
    a finished run appends to ``progress.csv`` (evaluation metrics, no training episode metrics).
    """
    return [row for row in history if _finite(row.get("Metrics/EpRet", float("nan")))]


def plot_curves(history: Sequence[Row], path: Path, *, cost_limit: float, title: str) -> Path:
    """Write a two-panel PNG (EpRet, EpCost vs env steps) from one run's ``progress.csv`` rows."""
    rows = training_rows(history)
    steps = [row["Train/TotalSteps"] for row in rows]
    fig, axes = figure_panels(title)
    for ax, (metric, _, _, color) in zip(axes, PANELS):
        ax.plot(steps, [row.get(metric, float("nan")) for row in rows], color=color)
    finish_figure(fig, axes, path, cost_limit)
    return path


def plot_group_curves(histories: Mapping[int, Sequence[Row]], path: Path, *, cost_limit: float, title: str) -> Path:
    """Write a seed group's two-panel PNG: each seed's EpRet and EpCost (thin), their mean (thick).

    ``histories`` maps each seed to its ``progress.csv`` rows. The mean at a step is over the seeds
    that logged a finite value there: all of them, unless a seed diverged and stopped logging (its
    thin line ends where it was frozen) or had not finished an episode yet.
    """
    runs = {seed: training_rows(rows) for seed, rows in histories.items()}
    fig, axes = figure_panels(title)
    for ax, (metric, _, _, color) in zip(axes, PANELS):
        by_step: dict[float, list[float]] = {}
        for seed, rows in runs.items():
            steps = [row["Train/TotalSteps"] for row in rows]
            values = [row.get(metric, float("nan")) for row in rows]
            ax.plot(steps, values, color=color, linewidth=0.8, alpha=0.35)
            for step, value in zip(steps, values):
                if _finite(value):
                    by_step.setdefault(step, []).append(value)
        steps = sorted(by_step)
        ax.plot(steps, [sum(by_step[s]) / len(by_step[s]) for s in steps], color=color, linewidth=2.4,
                label=f"mean of {len(runs)} seeds")
        # One legend entry for all the thin lines: they share a style.
        ax.plot([], [], color=color, linewidth=0.8, alpha=0.35, label="each seed")
    finish_figure(fig, axes, path, cost_limit)
    return path


def figure_panels(title: str) -> tuple[plt.Figure, tuple[Axes, Axes]]:
    """The two side-by-side panels with their titles, labels, step axis and grid."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), constrained_layout=True)
    for ax, (_, panel_title, ylabel, _) in zip(axes, PANELS):
        ax.set(title=panel_title, xlabel="env steps", ylabel=ylabel)
        ax.xaxis.set_major_locator(MaxNLocator(nbins=5, steps=[1, 2, 2.5, 5, 10]))  # round ticks: 50k, 100k
        ax.xaxis.set_major_formatter(FuncFormatter(format_steps))
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    return fig, tuple(axes)


def finish_figure(fig: plt.Figure, axes: tuple[Axes, Axes], path: Path, cost_limit: float) -> None:
    """Draw the cost limit on the cost panel, add the legends, write ``path`` and free the figure."""
    ax_ret, ax_cost = axes
    ax_cost.axhline(cost_limit, color="black", linestyle="--", linewidth=1, label=f"cost limit {cost_limit:g}")
    for ax in axes:
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize="small")
    image = io.BytesIO()
    fig.savefig(image, format="png", dpi=110)
    plt.close(fig)
    write_atomic(path, image.getvalue(), sync=False)


def _finite(value: float) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)
