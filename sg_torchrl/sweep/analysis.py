"""A sweep's analysis figure, as in the Safety-Gymnasium paper's "Experiments and Analysis" (Ji et al. 2023).

Two panels per kind of algorithm (single agent, multi agent), written by :func:`write_analysis` (which
:func:`sg_torchrl.sweep.report.write_report` calls) to ``report/analysis.png``, with the numbers behind
them in ``report/analysis.csv`` and their definitions in ``report/analysis.md``:

(a) **Normalised reward.** Each algorithm's J^R over PPO-Lag's on the same env (MAPPO-Lag's for the
    multi-agent algorithms MAPPO, HAPPO, MAPPO-Lag and MACPO), aggregated over the sweep's envs as the
    mean of the per-env ratios. J^R is the report table's own (:func:`~sg_torchrl.sweep.report.paper_rows`:
    mean over seeds of the last 10 training episodes' return). The baseline is the PPO-Lag (MAPPO-Lag)
    row with the same env, grid options, budget and cost limit; an env without one gets no ratio (the
    row's ``note`` says so) and the mean is over the envs that have one. (The report's table normalises
    by PPO / MAPPO, as the paper's tables do; the paper's analysis figure normalises by the Lagrangian
    baseline, as here.)

(b) **Cost regions.** The share of an algorithm's training evaluations whose episodic cost J_c falls in
    each region around its cost limit d (each cell's ``config.json`` ``cost_limit``): Strongly Safe
    J_c <= 0.5 d, Safe 0.5 d < J_c <= d, Unsafe d < J_c <= 1.5 d, Strongly Unsafe J_c > 1.5 d.
    ``sg-sweep --cost-regions A,B,C`` moves the three bounds (fractions of d, increasing).

Which evaluations count: every training epoch's row of each seed's ``progress.csv`` (rows with a
``Train/Epoch``; the final evaluation row has none) whose ``Metrics/EpCost`` is finite (an epoch
before the first finished episode has none), after a warm-up: an epoch counts when its
``Train/TotalSteps`` exceeds ``--warmup-share`` (default 0.1; 0 = the whole run) of the cell's
budget. ``Metrics/EpCost`` is SafePO's logged episode cost, the moving average of the last 50
finished episodes at the epoch's end (the value the paper's runs logged), so neighbouring epochs
share episodes. The evaluations are pooled over seeds and seed groups of one experiment (env,
algorithm, options, budget, cost limit), and over envs for the aggregate. Only finished cells count,
as in the report's table.
"""

from __future__ import annotations

import bisect
import io
import math
import os
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from sg_torchrl.sweep.records import finite_ratio, is_finite_number
from sg_torchrl.sweep.report import (
    MULTI_AGENT, PAPER_NAMES, CellResult, cell_histories, markdown_table, paper_rows, pool_cells, write_csv,
)
from sg_torchrl.train.writes import write_atomic

__all__ = [
    "COST_REGIONS", "REGION_NAMES", "WARMUP_SHARE", "analysis_rows", "counted_costs", "parse_cost_regions",
    "parse_warmup_share", "plot_analysis", "region_counts", "safe_baseline", "write_analysis",
]

#: The default bounds of the cost regions, as fractions of the cost limit d (the paper's).
COST_REGIONS = (0.5, 1.0, 1.5)
#: The regions, from the lowest cost up.
REGION_NAMES = ("Strongly Safe", "Safe", "Unsafe", "Strongly Unsafe")
#: The default share of a cell's budget whose epochs are left out as warm-up.
WARMUP_SHARE = 0.1
#: The Lagrangian baselines of panel (a), by kind of algorithm.
SAFE_BASELINES = {"single": "ppo_lag", "multi": "mappo_lag"}
_COLOURS = ("#1a9641", "#a6d96a", "#fdae61", "#d7191c")
NAN = float("nan")


def safe_baseline(algo: str) -> str:
    """The algorithm panel (a) normalises ``algo``'s J^R by: MAPPO-Lag for a multi-agent one, else PPO-Lag."""
    return SAFE_BASELINES["multi" if algo in MULTI_AGENT else "single"]


def parse_cost_regions(text: str | Sequence[float]) -> tuple[float, float, float]:
    """``"0.5,1.0,1.5"`` (or three numbers) -> the region bounds as fractions of the cost limit.

    Raises:
        ValueError: not three finite, positive, strictly increasing numbers.
    """
    parts = text.split(",") if isinstance(text, str) else list(text)
    try:
        bounds = tuple(float(part) for part in parts)
    except (TypeError, ValueError):
        bounds = ()
    if len(bounds) != 3 or not all(math.isfinite(b) and b > 0 for b in bounds) or not bounds[0] < bounds[1] < bounds[2]:
        raise ValueError(f"cost regions are three increasing positive fractions of the cost limit, "
                         f"like 0.5,1.0,1.5; got {text!r}")
    return bounds  # type: ignore[return-value]


def parse_warmup_share(value: str | float) -> float:
    """The warm-up share of the budget: a number from 0 (count the whole run) up to, not including, 1.

    Raises:
        ValueError: not a number in [0, 1).
    """
    try:
        share = float(value)
    except (TypeError, ValueError):
        share = NAN
    if not 0.0 <= share < 1.0:
        raise ValueError(f"the warm-up share is a fraction of the budget from 0 (the whole run) to below 1; "
                         f"got {value!r}")
    return share


def counted_costs(cell: CellResult, warmup_share: float = WARMUP_SHARE) -> list[float]:
    """The ``Metrics/EpCost`` of every training epoch of every seed of ``cell`` after the warm-up.

    An epoch counts when its ``Train/TotalSteps`` exceeds ``warmup_share`` of the cell's budget (its
    ``total_steps``; the most steps it logged when its config does not say).
    """
    histories = cell_histories(cell)
    rows = [row for rows in histories.values() for row in rows
            if is_finite_number(row.get("Train/Epoch")) and is_finite_number(row.get("Metrics/EpCost"))]
    budget = cell.total_steps or max((row["Train/TotalSteps"] for row in rows
                                      if is_finite_number(row.get("Train/TotalSteps"))),
                                     default=0.0)
    return [row["Metrics/EpCost"] for row in rows if row.get("Train/TotalSteps", NAN) > warmup_share * budget]


def region_counts(costs: Iterable[float], cost_limit: float,
                  cost_regions: Sequence[float] = COST_REGIONS) -> tuple[int, int, int, int]:
    """How many of ``costs`` fall in each region of :data:`REGION_NAMES`; a cost on a bound is in the lower region."""
    bounds = [fraction * cost_limit for fraction in cost_regions]
    counts = [0, 0, 0, 0]
    for cost in costs:
        counts[bisect.bisect_left(bounds, cost)] += 1
    return tuple(counts)  # type: ignore[return-value]


def analysis_rows(results: Sequence[CellResult], cost_regions: Sequence[float] = COST_REGIONS,
                  warmup_share: float = WARMUP_SHARE) -> list[dict[str, Any]]:
    """The numbers behind the figure: one row per experiment (env, algorithm, options, budget, cost limit)
    of the finished cells (``scope`` "env"), then one per experiment over all envs (``scope`` "all envs":
    ``J^R / baseline`` the mean of the envs' ratios, the regions over the pooled evaluations)."""
    cost_regions = parse_cost_regions(cost_regions)
    warmup_share = parse_warmup_share(warmup_share)
    table = {(row["env"], row["algorithm"], row["options"], row["budget"], row["cost limit"]): row
             for row in paper_rows(results)}
    per_env, pooled = [], {}
    for (env_id, algo, tag, budget, limit), cells in pool_cells(cell for cell in results if cell.finished).items():
        row = table[(env_id, PAPER_NAMES.get(algo, algo), tag, budget, limit)]
        base_name = PAPER_NAMES[safe_baseline(algo)]
        base = table.get((env_id, base_name, tag, budget, limit))
        counts = region_counts((cost for cell in cells for cost in counted_costs(cell, warmup_share)),
                               limit, cost_regions)
        ratio = finite_ratio(row["J^R"], base["J^R"]) if base else NAN
        notes = [] if base else [f"no {base_name} cell on this env with these options, budget and cost limit"]
        notes += [] if sum(counts) else ["no training evaluation after the warm-up"]
        per_env.append(_row("env", env_id, algo, tag, budget, limit, row["seeds"], 1, row["J^R"], base_name,
                            base["J^R"] if base else NAN, ratio, counts, "; ".join(notes)))
        entry = pooled.setdefault((algo, tag, budget, limit), {"envs": [], "ratios": [], "counts": [0] * 4, "seeds": 0})
        entry["envs"].append(env_id)
        entry["ratios"] += [ratio] if is_finite_number(ratio) else []
        entry["counts"] = [a + b for a, b in zip(entry["counts"], counts)]
        entry["seeds"] += row["seeds"]
    overall = []
    order = list(PAPER_NAMES)
    for (algo, tag, budget, limit), entry in sorted(pooled.items(), key=lambda item: (
            order.index(item[0][0]) if item[0][0] in order else len(order), *item[0])):
        ratios, envs = entry["ratios"], len(entry["envs"])
        base_name = PAPER_NAMES[safe_baseline(algo)]
        note = "" if len(ratios) == envs else (f"J^R / baseline over {len(ratios)} of {envs} envs (no {base_name} "
                                              "on the others)" if ratios else f"no {base_name} on any env")
        overall.append(_row("all envs", "all", algo, tag, budget, limit, entry["seeds"], envs, NAN, base_name, NAN,
                            sum(ratios) / len(ratios) if ratios else NAN, entry["counts"], note))
    for row in per_env + overall:
        row.update({"cost regions (x d)": ",".join(f"{b:g}" for b in cost_regions), "warm-up share": warmup_share})
    return per_env + overall


def _row(scope: str, env: str, algo: str, tag: str, budget: int, limit: float, seeds: int, envs: int,
         reward: float, base_name: str, base_reward: float, ratio: float, counts: Sequence[int],
         note: str) -> dict[str, Any]:
    total = sum(counts)
    return {
        "scope": scope, "env": env, "algorithm": PAPER_NAMES.get(algo, algo),
        "agents": "multi" if algo in MULTI_AGENT else "single", "options": tag, "budget": budget,
        "cost limit": limit, "seeds": seeds, "envs": envs, "J^R": reward, "baseline": base_name,
        "baseline J^R": base_reward, "J^R / baseline": ratio, "evaluations": total,
        **{name: count / total if total else NAN for name, count in zip(REGION_NAMES, counts)},
        "note": note,
    }


def plot_analysis(rows: Sequence[Mapping[str, Any]], path: str | os.PathLike, title: str = "") -> Path:
    """The figure of :func:`analysis_rows`' ``all envs`` rows: per kind of algorithm present (single, multi
    agent), (a) the normalised J^R as bars with each env's ratio as a dot, and (b) the cost regions as
    stacked bars. An algorithm without a baseline gets a note in place of its bar."""
    from sg_torchrl.train.plot import plt  # headless matplotlib, only for figures

    path = Path(path)
    overall = [row for row in rows if row["scope"] == "all envs"]
    kinds = [kind for kind in ("single", "multi") if any(row["agents"] == kind for row in overall)]
    varies = {key: len({row[key] for row in overall}) > 1 for key in ("budget", "cost limit")}
    fig, axes = plt.subplots(max(len(kinds), 1), 2, figsize=(12, 4.4 * max(len(kinds), 1)), squeeze=False,
                             constrained_layout=True, gridspec_kw={"width_ratios": [1, 1.25]})
    if not kinds:
        for ax in axes[0]:
            ax.text(0.5, 0.5, "No finished cell yet", ha="center", va="center", transform=ax.transAxes)
            ax.set_axis_off()
    for (ax_reward, ax_cost), kind in zip(axes, kinds):
        group = [row for row in overall if row["agents"] == kind]
        labels = [" ".join([row["algorithm"]] + [f"[{row['options']}]"] * bool(row["options"])
                           + [f"{row['budget']:,} steps"] * varies["budget"]
                           + [f"limit {row['cost limit']:g}"] * varies["cost limit"]) for row in group]
        counts = {row["envs"] for row in group}
        envs = max(counts)
        over = f"mean over {envs} env{'s' * (envs != 1)}" if len(counts) == 1 else "mean over its envs"
        _reward_panel(ax_reward, group, [row for row in rows if row["scope"] == "env" and row["agents"] == kind],
                      labels, envs)
        _cost_panel(ax_cost, group, labels, rows[0]["cost regions (x d)"], rows[0]["warm-up share"])
        who = "single-agent" if kind == "single" else "multi-agent"
        ax_reward.set_title(f"(a) {who}: $J^R$ / {group[0]['baseline']}'s, {over}",
                            fontsize=11)
    fig.suptitle(f"{title + ': ' if title else ''}normalised reward and cost regions")
    image = io.BytesIO()
    fig.savefig(image, format="png", dpi=110)
    plt.close(fig)
    write_atomic(path, image.getvalue(), sync=False)
    return path


def _reward_panel(ax, group, env_rows, labels, envs) -> None:
    x = range(len(group))
    heights = [row["J^R / baseline"] for row in group]
    bars = ax.bar(x, [h if is_finite_number(h) else 0.0 for h in heights], color="tab:blue", alpha=0.8, width=0.6)
    top = max([h for h in heights if is_finite_number(h)]
              + [r["J^R / baseline"] for r in env_rows if is_finite_number(r["J^R / baseline"])] + [1.0])
    for index, (bar, row, height) in enumerate(zip(bars, group, heights)):
        if is_finite_number(height):
            ax.annotate(f"{height:.2f}", (bar.get_x() + bar.get_width() / 2, height), xytext=(0, 2),
                        textcoords="offset points", ha="center", va="bottom", fontsize=9)
        else:
            ax.text(index, 0.02 * top, f"no {row['baseline']}", rotation=90, ha="center", va="bottom", fontsize=8)
        if envs > 1:  # each env's own ratio
            ratios = [r["J^R / baseline"] for r in env_rows
                      if _same_experiment(r, row) and is_finite_number(r["J^R / baseline"])]
            ax.scatter([index] * len(ratios), ratios, color="black", s=12, zorder=3,
                       label="one env" if index == 0 else None)
    ax.axhline(1.0, color="black", linestyle="--", linewidth=1, label=f"{group[0]['baseline']} = 1")
    ax.set_ylim(0, top * 1.15)
    ax.set_ylabel("normalised $J^R$ (last 10 episodes)")
    _algorithm_axis(ax, labels)
    ax.legend(loc="best", fontsize="small")
    ax.grid(axis="y", alpha=0.3)


def _cost_panel(ax, group, labels, regions: str, warmup_share: float) -> None:
    x = range(len(group))
    bottom = [0.0] * len(group)
    texts = _region_texts([float(b) for b in regions.split(",")], tex=True)
    for name, text, colour in zip(REGION_NAMES, texts, _COLOURS):
        shares = [row[name] if is_finite_number(row[name]) else 0.0 for row in group]
        ax.bar(x, shares, bottom=bottom, color=colour, width=0.6, label=f"{name}: {text}")
        for index, share in enumerate(shares):
            if share >= 0.06:
                ax.text(index, bottom[index] + share / 2, f"{100 * share:.0f}%", ha="center", va="center", fontsize=8)
        bottom = [b + s for b, s in zip(bottom, shares)]
    for index, row in enumerate(group):
        ax.annotate(f"n={row['evaluations']}", (index, 1.0), xytext=(0, 2), textcoords="offset points",
                    ha="center", va="bottom", fontsize=8)
    warmup = f"after the first {100 * warmup_share:g}% of the budget" if warmup_share else "the whole run"
    ax.set_title(f"(b) training epochs by episode cost $J_c$, {warmup}", fontsize=11)
    ax.set_ylim(0, 1.08)
    ax.set_ylabel("share of epochs ($d$ = cost limit)")
    _algorithm_axis(ax, labels)
    handles, names = ax.get_legend_handles_labels()  # top region first, as the bars stack
    ax.legend(handles[::-1], names[::-1], loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize="small")


def _region_texts(bounds: Sequence[float], tex: bool = False) -> list[str]:
    """The regions' conditions: ``J_c <= 0.5d``, ``0.5d < J_c <= d``, ... (``d``: the cost limit), as
    matplotlib mathtext with ``tex``."""
    a, b, c = ("d" if bound == 1 else f"{bound:g}d" for bound in bounds)
    cost, le = (r"J_c", r" \leq ") if tex else ("J_c", " <= ")
    texts = [f"{cost}{le}{a}", f"{a} < {cost}{le}{b}", f"{b} < {cost}{le}{c}", f"{cost} > {c}"]
    return [f"${text}$" for text in texts] if tex else texts


def _algorithm_axis(ax, labels: Sequence[str]) -> None:
    long = len(labels) > 5 or any(len(label) > 10 for label in labels)
    ax.set_xticks(range(len(labels)), labels, rotation=30 if long else 0, ha="right" if long else "center")


def _same_experiment(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    return all(a[key] == b[key] for key in ("algorithm", "options", "budget", "cost limit"))


def write_analysis(results: Sequence[CellResult], report_dir: str | os.PathLike,
                   cost_regions: Sequence[float] | None = None, warmup_share: float | None = None,
                   title: str = "") -> dict[str, Path]:
    """Write ``analysis.csv`` (:func:`analysis_rows`), ``analysis.md`` (the definitions and both tables) and
    ``analysis.png`` (:func:`plot_analysis`) into ``report_dir``; ``None`` options take the defaults.
    Returns ``{file name: path}``."""
    report = Path(report_dir)
    regions = parse_cost_regions(COST_REGIONS if cost_regions is None else cost_regions)
    share = parse_warmup_share(WARMUP_SHARE if warmup_share is None else warmup_share)
    rows = analysis_rows(results, regions, share)
    hidden = {"all envs": ("scope", "env", "J^R", "baseline J^R", "cost regions (x d)", "warm-up share"),
              "env": ("scope", "envs", "cost regions (x d)", "warm-up share")}
    shown = {scope: [{key: value for key, value in row.items() if key not in hidden[scope]}
                     for row in rows if row["scope"] == scope] for scope in hidden}
    warmup = (f"epochs after the first {100 * share:g}% of each cell's budget (Train/TotalSteps above "
              f"{share:g} x budget)" if share else "every epoch")
    text = [
        f"# Analysis{': ' + title if title else ''}", "",
        "![normalised reward and cost regions](analysis.png)", "",
        "J^R / baseline: J^R (the table's: mean over seeds of the last 10 training episodes' return) over the "
        "J^R of PPO-Lag (MAPPO-Lag for the multi-agent algorithms) on the same env, options, budget and cost "
        "limit; over all envs, the mean of the envs' ratios (envs without the baseline left out, as the note says).",
        "",
        "Cost regions, with d the cell's cost limit (config.json): "
        + ", ".join(f"{name} {text}" for name, text in zip(REGION_NAMES, _region_texts(regions)))
        + " (sg-sweep --cost-regions). Each evaluation is one training epoch's "
        f"Metrics/EpCost (the mean cost of the last 50 finished episodes at the epoch's end) of one seed: "
        f"{warmup} (sg-sweep --warmup-share), pooled over seeds (and over envs for all envs); "
        "the region columns are shares of the evaluations. Finished cells only.", "",
        "## All envs", "", markdown_table(shown["all envs"]) or "No finished cell yet.", "",
        "## Per env", "", markdown_table(shown["env"]) or "No finished cell yet.",
    ]
    paths = {"analysis.md": write_atomic(report / "analysis.md", "\n".join(text) + "\n", sync=False),
             "analysis.csv": write_csv(rows, report / "analysis.csv"),
             "analysis.png": plot_analysis(rows, report / "analysis.png", title)}
    return paths
