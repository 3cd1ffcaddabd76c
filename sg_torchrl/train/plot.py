"""Learning-curve figure: episode return and episode cost with the cost limit."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: never needs a display
import matplotlib.pyplot as plt  # noqa: E402

__all__ = ["plot_curves"]


def plot_curves(history: list[dict[str, float]], path: Path, *, cost_limit: float, title: str) -> Path:
    """Write a two-panel PNG (EpRet, EpCost vs env steps) from ``progress.csv`` rows."""
    steps = [row["Train/TotalSteps"] for row in history]
    fig, (ax_ret, ax_cost) = plt.subplots(1, 2, figsize=(10, 3.8), constrained_layout=True)
    ax_ret.plot(steps, [row.get("Metrics/EpRet", float("nan")) for row in history], color="tab:blue")
    ax_ret.set(title="Episode return", xlabel="env steps", ylabel="EpRet")
    ax_cost.plot(steps, [row.get("Metrics/EpCost", float("nan")) for row in history], color="tab:red")
    ax_cost.axhline(cost_limit, color="black", linestyle="--", linewidth=1, label=f"cost limit {cost_limit:g}")
    ax_cost.set(title="Episode cost", xlabel="env steps", ylabel="EpCost")
    ax_cost.legend(loc="upper right")
    for ax in (ax_ret, ax_cost):
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
