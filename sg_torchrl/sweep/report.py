"""A sweep's results: its cells gathered into the paper-format table, per-seed rows and curve figures.

``sg-sweep`` runs every cell (one env id, one algorithm, one seed group, one set of grid options) as a
Ray task that writes an ``sg-train`` run directory under the sweep's output directory ``OUT``. This
module reads those directories back, and nothing else: no Ray, no torch, no absolute path, so a
report can be written on any machine from a copy of ``OUT`` (:func:`write_report`).

Two layouts of a cell are read (:func:`collect`):

* a seed group, as ``sg-sweep`` runs it: ``OUT/<env_id>/<algo>/[<tag>/]seeds-0-1-2/`` with the
  group's ``config.json`` and, once finished, ``summary.json`` (``"seeds"``: each seed's final
  figures; ``"diverged"``; ``"Train/TotalSteps"``; ``"Time/Total"``), and one ``seed-000/`` per seed
  with its ``progress.csv``;
* a single seed, as the older benchmarks ran it: ``OUT/<env_id>/<algo>/seed-000/`` with
  ``config.json``, ``summary.json`` (that seed's figures) and ``progress.csv``.

``<tag>`` is the folder of a cell's grid options (``lr=0.001,num_envs=20``); cells that differ only
by it are different experiments, so it is part of every row's key (the ``options`` column). The
runner appends one JSON line per attempt to a cell's ``attempts.jsonl``; where it is present, a
cell's wall time is the sum of its ended attempts' durations or the ``Time/Total`` it logged (training
time over all its resumes), whichever is larger (an attempt lost with its worker has no end).

The paper table (:func:`paper_rows`) gives, as the Safety-Gymnasium paper's tables do (Ji et al.
2023), J^R and J^C (mean over seeds of the last 10 training episodes' return and cost), J^R
normalised by PPO's (MAPPO's for the multi-agent algorithms) on the same env, options and budget in
the same sweep, and J^C over the cell's own cost limit (its ``config.json``), beside the published
numbers (``paper_results.csv`` in this package, 10M steps) normalised the same way.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from sg_torchrl.algorithms import manifest
from sg_torchrl.sweep.records import (
    AttemptLog, finite_mean, finite_ratio, is_finite_number, latest, parse_float, read_progress,
)
from sg_torchrl.train.writes import make_dirs, write_atomic

__all__ = [
    "CellResult", "MULTI_AGENT", "PAPER_NAMES", "PAPER_RESULTS", "baseline", "cell_histories", "collect",
    "load_paper_results", "markdown_table", "paper_env_name", "paper_rows", "plot_env_curves", "pool_cells",
    "read_progress", "seed_rows", "write_csv", "write_report",
]

#: The Safety-Gymnasium paper's published J^R / J^C tables (Ji et al. 2023), shipped as package data.
PAPER_RESULTS = Path(__file__).resolve().parent / "paper_results.csv"
#: Our algorithm ids -> the paper's names (its tables' rows), in the paper's order (the algorithm manifest's).
PAPER_NAMES = {entry.name: entry.paper for entry in manifest.rows()}
#: The multi-agent algorithms: their J^R is normalised by MAPPO's, the others' by PPO's (the paper's tables).
MULTI_AGENT = frozenset(manifest.names(agents="multi"))
PAPER_TABLES = ("single_agent_raw", "multi_agent_raw")
#: The cost limit of a cell whose config.json does not say (sg-train's default, the paper's).
DEFAULT_COST_LIMIT = 25.0
#: The folder under the output directory that :func:`write_report` writes (never read as a cell).
REPORT_DIR = "report"
NAN = float("nan")

_GROUP_DIR = re.compile(r"seeds-\d+(?:-\d+)*")
_SEED_DIR = re.compile(r"seed-(\d+)")


def baseline(algo: str) -> str:
    """The algorithm the paper normalises ``algo``'s J^R by: MAPPO for the multi-agent algorithms, else PPO."""
    return manifest.baseline(algo)


def paper_env_name(env_id: str) -> str:
    """``SafetyPointGoal1-v0`` -> ``PointGoal1``; ``SafetyHalfCheetahVelocity-v1`` -> ``HalfCheetahVel``;
    ``Safety2x3HalfCheetahVelocity-v0`` -> ``2x3HalfCheetahVel``."""
    name = re.sub(r"^Safety|-v\d+$", "", env_id)
    return re.sub(r"Velocity$", "Vel", name)


def load_paper_results(path: Path = PAPER_RESULTS) -> dict[tuple[str, str], tuple[float, float]]:
    """``{(paper env, paper algorithm): (reward, cost)}`` of the single- and multi-agent tables (empty if absent)."""
    if not path.exists():
        return {}
    with path.open() as handle:
        return {(row["env"], row["algorithm"]): (float(row["reward"]), float(row["cost"]))
                for row in csv.DictReader(handle) if row["table"] in PAPER_TABLES}


@dataclass
class CellResult:
    """One cell of a sweep as its directory holds it, finished or not.

    ``directory`` is relative to ``root`` (the output directory :func:`collect` read), so rows and
    reports name a cell the same way wherever the output directory was copied to. ``steps`` is the
    latest ``Train/TotalSteps`` seen (per seed), ``total_steps`` the budget the cell was started with,
    ``update_s`` the mean ``Time/Update`` of its epochs, ``wall_s`` its wall time (the ended attempts
    of ``attempts.jsonl`` or the ``Time/Total`` it logged, whichever is larger) and ``status`` its last attempt's status.
    """

    env_id: str
    algo: str
    tag: str
    seeds: tuple[int, ...]
    directory: Path
    finished: bool
    per_seed: dict[int, dict[str, float]]
    steps: int
    wall_s: float
    attempts: int
    cost_limit: float
    compiled: bool
    update_s: float
    total_steps: int = 0
    diverged: tuple[int, ...] = ()
    group: bool = True
    status: str = ""
    root: Path = field(default=Path("."), repr=False)

    @property
    def path(self) -> Path:
        """The cell's directory as found (``root / directory``)."""
        return self.root / self.directory

    def seed_dir(self, seed: int) -> Path:
        """The directory of ``seed``'s ``progress.csv``: ``seed-000/`` in a group, the cell itself for a single seed."""
        return self.path / f"seed-{seed:03d}" if self.group else self.path

    @property
    def name(self) -> str:
        """The algorithm's name in the paper's tables (our id when the paper has none)."""
        return PAPER_NAMES.get(self.algo, self.algo)


def cell_histories(cell: CellResult) -> dict[int, list[dict[str, float]]]:
    """Each seed's ``progress.csv`` rows (all of them: training and evaluation rows)."""
    return {seed: read_progress(cell.seed_dir(seed) / "progress.csv") for seed in cell.seeds}


def collect(output_dir: str | os.PathLike) -> list[CellResult]:
    """Every cell under ``output_dir``, finished or not, sorted by directory.

    A cell is a directory with a ``config.json``, or named like one (``seeds-0-1-2``, ``seed-000``:
    a cell whose run has not written its config yet); nothing below a cell is searched, so a group's
    ``seed-000/`` folders are part of it, not cells. Cells are found by walking the directory, so an
    older benchmark directory without a ``sweep.json`` reads the same way; where the sweep's
    ``sweep.json`` lists cells (``"cells"``: ``env_id``, ``algo``, ``seeds``, ``run_name``, the
    directory), those without a directory yet are added as not started (no steps, no attempts).
    """
    root = Path(output_dir)
    cells = []
    for dirpath, dirnames, filenames in os.walk(root):
        here = Path(dirpath)
        if here == root and REPORT_DIR in dirnames:
            dirnames.remove(REPORT_DIR)
        if "config.json" in filenames or _GROUP_DIR.fullmatch(here.name) or _SEED_DIR.fullmatch(here.name):
            dirnames.clear()
            cells.append(_read_cell(root, here))
    record = _read_json(root / "sweep.json")
    found = {cell.directory.as_posix() for cell in cells}
    for listed in record.get("cells", []):
        if isinstance(listed, dict) and listed.get("run_name") and listed["run_name"] not in found:
            cells.append(_pending_cell(root, listed, int(record.get("total_steps") or 0)))
    return sorted(cells, key=lambda cell: cell.directory.as_posix())


def _pending_cell(root: Path, listed: Mapping[str, Any], total_steps: int) -> CellResult:
    """A cell that ``sweep.json`` lists but that has no directory yet."""
    directory = Path(listed["run_name"])
    env_id, algo, tag = _cell_key(directory, listed)
    return CellResult(env_id=env_id, algo=algo, tag=tag, seeds=tuple(int(s) for s in listed.get("seeds", ())),
                      directory=directory, finished=False, per_seed={}, steps=0, wall_s=NAN, attempts=0,
                      cost_limit=DEFAULT_COST_LIMIT, compiled=False, update_s=NAN, total_steps=total_steps,
                      root=root, status="not started")


def _read_cell(root: Path, path: Path) -> CellResult:
    """A :class:`CellResult` from one cell directory (see :func:`collect`)."""
    config = _read_json(path / "config.json")
    relative = path.relative_to(root)
    env_id, algo, tag = _cell_key(relative, config)
    group, seeds = _cell_seeds(path.name, config)
    summary = _read_json(path / "summary.json")
    if group:  # a seed's own summary.json adds its steps (fewer if it diverged) to the group's figures of it
        per_seed = {int(seed): {**_read_json(path / f"seed-{int(seed):03d}" / "summary.json"), **figures}
                    for seed, figures in summary.get("seeds", {}).items()}
    else:
        per_seed = {seeds[0]: summary} if summary and seeds else {}
    cell = CellResult(
        env_id=env_id, algo=algo, tag=tag, seeds=seeds, directory=relative, finished=bool(summary),
        per_seed=per_seed, steps=0, wall_s=NAN, attempts=0, update_s=NAN,
        cost_limit=float(config.get("cost_limit") if config.get("cost_limit") is not None else DEFAULT_COST_LIMIT),
        compiled=bool(config.get("compile", False)), total_steps=int(config.get("total_steps") or 0),
        diverged=tuple(int(seed) for seed in summary.get("diverged", ())), group=group, root=root,
    )
    histories = cell_histories(cell)
    for seed, figures in per_seed.items():  # the curve's end: its last 50-episode moving averages
        figures["Final/EpRetLast50"] = latest(histories.get(seed, []), "Metrics/EpRet")
        figures["Final/EpCostLast50"] = latest(histories.get(seed, []), "Metrics/EpCost")
    rows = [row for rows in histories.values() for row in rows]
    steps = [row["Train/TotalSteps"] for row in rows if is_finite_number(row.get("Train/TotalSteps"))]
    steps += [summary["Train/TotalSteps"]] if is_finite_number(summary.get("Train/TotalSteps")) else []
    cell.steps = int(max(steps, default=0))
    cell.update_s = finite_mean(row.get("Time/Update", NAN) for row in rows)
    logged_s = summary.get("Time/Total") if is_finite_number(summary.get("Time/Total")) else max(
        (row["Time/Total"] for row in rows if is_finite_number(row.get("Time/Total"))), default=NAN)
    attempts = AttemptLog(path).read()
    if attempts:
        cell.attempts, cell.status = len(attempts), str(attempts[-1].get("status", ""))
        ended = sum(float(a["end"]) - float(a["start"]) for a in attempts
                    if is_finite_number(a.get("end")) and is_finite_number(a.get("start")))
        # An attempt lost with its worker has no end: its time is then only in the training time sg-train logged
        # (accumulated over resumes), which in turn leaves out start-ups. The larger is the closer to the truth.
        cell.wall_s = max(ended, logged_s) if is_finite_number(logged_s) else ended
    else:  # no runner log (an older benchmark cell): one attempt as far as we know, its logged training time
        cell.attempts, cell.wall_s = int(cell.finished or bool(rows)), logged_s
    return cell


def _cell_key(relative: Path, config: Mapping[str, Any]) -> tuple[str, str, str]:
    """``(env_id, algo, tag)`` of a cell: env and algorithm from its config (its path where it has none
    yet), the tag from the folders between the algorithm's and the cell's.

    A folder under the env's that is not the algorithm's own (``ppo_lag-hands-preset/seed-000``: an
    older benchmark's name for a preset) stays in the tag, so such a cell is not pooled with plain ones.
    """
    parts = list(relative.parts[:-1])
    env_id = str(config.get("env_id") or (parts[0] if parts else ""))
    middle = parts[parts.index(env_id) + 1:] if env_id in parts else parts
    algo = str(config.get("algo") or (middle[0] if middle else ""))
    if middle and middle[0] == algo:
        middle = middle[1:]
    return env_id, algo, "/".join(middle)


def _cell_seeds(name: str, config: Mapping[str, Any]) -> tuple[bool, tuple[int, ...]]:
    """``(is a seed group, its seeds)`` from the config's ``seeds`` / ``seed``, else the folder's name."""
    if config.get("seeds"):
        return True, tuple(int(seed) for seed in config["seeds"])
    if _GROUP_DIR.fullmatch(name):
        return True, tuple(int(seed) for seed in name.split("-")[1:])
    if config.get("seed") is not None:
        return False, (int(config["seed"]),)
    match = _SEED_DIR.fullmatch(name)
    return False, (int(match.group(1)),) if match else ()


def paper_rows(results: Iterable[CellResult]) -> list[dict[str, Any]]:
    """The paper-format table: one row per (env, algorithm, options, budget, cost limit) over finished cells.

    A row pools every finished cell of its key (several seed groups of one experiment): ``seeds`` is
    the number of seeds, ``J^R`` / ``J^C`` their mean ``Final/EpRetLast10`` / ``Final/EpCostLast10``.
    ``J^R / base`` divides by the J^R of PPO (MAPPO for the multi-agent algorithms) on the same env,
    options and budget in these results (NaN when that baseline did not run); ``J^C / limit`` by the
    cell's cost limit; ``J^R (50)`` / ``J^C (50)`` are the seeds' mean of their last 50-episode moving
    averages (the end of their curves, ``progress.csv``'s last ``Metrics/EpRet`` / ``EpCost``), steadier
    than 10 episodes. ``update s / epoch`` and ``wall h`` are means over the pooled cells (wall time
    per cell). The ``paper`` columns are the published 10M-step numbers, normalised by the paper's
    PPO / MAPPO on that env and by the same limit; ``meets_limit`` / ``paper_meets_limit`` say whether
    J^C <= limit (``None`` where the paper has no number).
    """
    paper = load_paper_results()
    groups = pool_cells(cell for cell in results if cell.finished)
    rows = []
    for (env_id, algo, tag, budget, limit), cells in groups.items():
        base = [cell for (e, a, t, b, _), pooled in groups.items()
                if (e, a, t, b) == (env_id, baseline(algo), tag, budget) for cell in pooled]
        reward, cost = _seed_mean(cells, "Final/EpRetLast10"), _seed_mean(cells, "Final/EpCostLast10")
        env_name, name = paper_env_name(env_id), PAPER_NAMES.get(algo, algo)
        paper_reward, paper_cost = paper.get((env_name, name), (NAN, NAN))
        paper_base = paper.get((env_name, PAPER_NAMES[baseline(algo)]), (NAN, NAN))[0]
        rows.append({
            "env": env_id, "algorithm": name, "options": tag, "budget": budget,
            "seeds": sum(len(cell.per_seed) for cell in cells),
            "compiled": sum(len(cell.per_seed) for cell in cells if cell.compiled),
            "diverged": sum(len(cell.diverged) for cell in cells),
            "J^R": reward, "J^C": cost, "J^R / base": finite_ratio(reward, _seed_mean(base, "Final/EpRetLast10")),
            "J^C / limit": finite_ratio(cost, limit), "cost limit": limit,
            "J^R (50)": _seed_mean(cells, "Final/EpRetLast50"), "J^C (50)": _seed_mean(cells, "Final/EpCostLast50"),
            "update s / epoch": finite_mean(cell.update_s for cell in cells),
            "wall h": finite_mean(cell.wall_s / 3600 for cell in cells),
            "attempts": sum(cell.attempts for cell in cells),
            "paper J^R": paper_reward, "paper J^C": paper_cost,
            "paper J^R / base": finite_ratio(paper_reward, paper_base),
            "paper J^C / limit": finite_ratio(paper_cost, limit),
            "meets_limit": bool(cost <= limit),
            "paper_meets_limit": bool(paper_cost <= limit) if is_finite_number(paper_cost) else None,
        })
    return rows


def seed_rows(results: Iterable[CellResult]) -> list[dict[str, Any]]:
    """One row per finished seed: its last-10- and last-50-episode and evaluation figures, whether it diverged
    (stopped early with non-finite losses, as its group's summary lists) and its env steps."""
    rows = []
    for cell in sorted((cell for cell in results if cell.finished), key=_order):
        for seed, figures in sorted(cell.per_seed.items()):
            rows.append({
                "env": cell.env_id, "algorithm": cell.name, "options": cell.tag, "seed": seed,
                "EpRet (last 10)": parse_float(figures.get("Final/EpRetLast10")),
                "EpCost (last 10)": parse_float(figures.get("Final/EpCostLast10")),
                "EpRet (last 50)": parse_float(figures.get("Final/EpRetLast50")),
                "EpCost (last 50)": parse_float(figures.get("Final/EpCostLast50")),
                "eval EpRet": parse_float(figures.get("Metrics/EvalEpRet")),
                "eval EpCost": parse_float(figures.get("Metrics/EvalEpCost")),
                "diverged": seed in cell.diverged,
                "steps": (int(figures["Train/TotalSteps"]) if is_finite_number(figures.get("Train/TotalSteps"))
                          else cell.steps),
                "compiled": cell.compiled, "directory": cell.directory.as_posix(),
            })
    return rows


#: Markdown number formats by column (other floats: two decimals).
_FORMATS = {"update s / epoch": "{:.1f}", "cost limit": "{:g}", "budget": "{:,}", "steps": "{:,}"}


def markdown_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """``rows`` as a Markdown table, one column per key (numbers right-aligned, NaN and None as ``-``,
    booleans as yes / no); the ``options`` column only when a row has options."""
    if not rows:
        return ""
    columns = list(dict.fromkeys(key for row in rows for key in row))
    if not any(row.get("options") for row in rows):
        columns = [column for column in columns if column != "options"]
    numeric = {column: all(isinstance(row.get(column), (int, float)) and not isinstance(row.get(column), bool)
                           for row in rows) for column in columns}
    lines = ["| " + " | ".join(columns) + " |",
             "|" + "|".join("---:" if numeric[column] else "---" for column in columns) + "|"]
    lines += ["| " + " | ".join(_cell_text(column, row.get(column)) for column in columns) + " |" for row in rows]
    return "\n".join(lines)


def _cell_text(column: str, value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, float)):
        return _FORMATS.get(column, "{:.2f}" if isinstance(value, float) else "{}").format(value)
    return str(value).replace("|", "\\|")


def write_csv(rows: Sequence[Mapping[str, Any]], path: str | os.PathLike) -> Path:
    """Write ``rows`` as CSV (every key a column; floats in full precision, NaN as ``nan``, None empty)."""
    path = Path(path)
    columns = list(dict.fromkeys(key for row in rows for key in row))
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=columns)
    writer.writeheader()
    writer.writerows({key: "" if value is None else value for key, value in row.items()} for row in rows)
    return write_atomic(path, text.getvalue(), sync=False)


def plot_env_curves(results: Iterable[CellResult], env_id: str, path: str | os.PathLike) -> Path:
    """One figure for ``env_id``: episode return and cost against env steps, one line per algorithm
    (and options, budget and cost limit where they differ), the mean over its seeds with a min-max
    band, and the cost limit on the cost panel. Unfinished cells are drawn as far as they got; the
    legend counts the seeds with a finished episode."""
    from matplotlib import colormaps  # matplotlib only for figures: the tables are read without it

    from sg_torchrl.train.plot import PANELS, figure_panels, finish_figure, training_rows

    path = Path(path)
    groups = pool_cells(cell for cell in results if cell.env_id == env_id)
    varies = [len({key[i] for key in groups}) > 1 for i in range(5)]
    palette = colormaps["tab10" if len(groups) <= 10 else "tab20"]
    fig, axes = figure_panels(f"{env_id}: mean over seeds, band from min to max")
    for index, (key, cells) in enumerate(groups.items()):
        runs = [rows for cell in cells for rows in map(training_rows, cell_histories(cell).values()) if rows]
        if not runs:  # not started, or no episode finished yet
            continue
        label = " ".join([PAPER_NAMES.get(key[1], key[1])] + [f"[{key[2]}]"] * bool(key[2])
                         + [f"{key[3]:,} steps"] * varies[3] + [f"limit {key[4]:g}"] * varies[4])
        for ax, (metric, *_) in zip(axes, PANELS):
            by_step: dict[float, list[float]] = {}
            for rows in runs:
                for row in rows:
                    if is_finite_number(row.get(metric)):
                        by_step.setdefault(row["Train/TotalSteps"], []).append(row[metric])
            steps = sorted(by_step)
            color = palette(index % palette.N)
            ax.plot(steps, [sum(by_step[s]) / len(by_step[s]) for s in steps], color=color, linewidth=1.6,
                    label=f"{label} ({len(runs)} seed{'s' * (len(runs) != 1)})" if ax is axes[0] else None)
            ax.fill_between(steps, [min(by_step[s]) for s in steps], [max(by_step[s]) for s in steps],
                            color=color, alpha=0.2, linewidth=0)
    limits = sorted({key[4] for key in groups}) or [DEFAULT_COST_LIMIT]
    for limit in limits[1:]:  # finish_figure draws the first
        axes[1].axhline(limit, color="black", linestyle=":", linewidth=1, label=f"cost limit {limit:g}")
    finish_figure(fig, axes, path, limits[0])
    return path


def write_report(output_dir: str | os.PathLike, *, cost_regions: Sequence[float] | None = None,
                 warmup_share: float | None = None) -> dict[str, Path]:
    """Collect ``output_dir``'s cells and write ``output_dir/report/``: ``table.md`` (the paper table,
    the per-seed table and one line per unfinished cell with its progress), ``table.csv``,
    ``seeds.csv``, ``curves-<env_id>.png`` per env (characters other than letters, digits, ``.``,
    ``-`` and ``_`` in the id become ``_``) and the analysis figure with its numbers
    (:func:`sg_torchrl.sweep.analysis.write_analysis`, given ``cost_regions`` and ``warmup_share``; ``None``:
    its defaults). Returns ``{file name: path}``."""
    from sg_torchrl.sweep.analysis import write_analysis  # it reads cells through this module

    root = Path(output_dir)
    report = root / REPORT_DIR
    make_dirs(report)
    results = collect(root)
    table, seeds = paper_rows(results), seed_rows(results)
    unfinished = [cell for cell in sorted(results, key=_order) if not cell.finished]
    text = [
        f"# Sweep report: {root.resolve().name}", "",
        f"{len(results)} cells, {len(results) - len(unfinished)} finished.", "",
        "## Paper table", "",
        "J^R, J^C: mean over seeds of the last 10 training episodes' return and cost. J^R / base: over the J^R of "
        "PPO (MAPPO for the multi-agent algorithms) on the same env, options and budget in this sweep. J^C / limit: "
        "over the cell's cost limit. J^R (50), J^C (50): the same over the last 50 episodes (the curves' end, "
        "steadier than 10 episodes). wall h: per cell. paper: Ji et al. 2023 at 10M steps, normalised the same way.",
        "", markdown_table(table) or "No finished cell yet.", "",
        "Normalised reward (by PPO-Lag / MAPPO-Lag) and cost regions: analysis.md, analysis.png, analysis.csv.", "",
        "## Per seed", "", markdown_table(seeds) or "No finished seed yet.", "",
        "## Unfinished cells", "",
    ]
    text += [_progress_line(cell) for cell in unfinished] or ["None."]
    paths = {"table.md": report / "table.md"}
    write_atomic(paths["table.md"], "\n".join(text) + "\n", sync=False)
    paths["table.csv"] = write_csv(table, report / "table.csv")
    paths["seeds.csv"] = write_csv(seeds, report / "seeds.csv")
    for env_id in sorted({cell.env_id for cell in results}):
        name = f"curves-{re.sub(r'[^A-Za-z0-9._-]', '_', env_id)}.png"
        paths[name] = plot_env_curves(results, env_id, report / name)
    paths.update(write_analysis(results, report, cost_regions, warmup_share, title=root.resolve().name))
    return paths


def _progress_line(cell: CellResult) -> str:
    """``- `dir`: env algorithm [options], seeds 0 1 2: steps / budget (percent), attempts, wall h, status``."""
    budget = f" / {cell.total_steps:,} ({100 * cell.steps / cell.total_steps:.0f}%)" if cell.total_steps else ""
    tag = f" [{cell.tag}]" if cell.tag else ""
    wall = f", {cell.wall_s / 3600:.2f} h" if is_finite_number(cell.wall_s) else ""
    status = f", last attempt {cell.status}" if cell.status else ""
    return (f"- `{cell.directory.as_posix()}`: {cell.env_id} {cell.name}{tag}, seeds {' '.join(map(str, cell.seeds))}: "
            f"{cell.steps:,}{budget} steps, {cell.attempts} attempt(s){wall}{status}")


def pool_cells(cells: Iterable[CellResult]) -> dict[tuple[str, str, str, int, float], list[CellResult]]:
    """Cells by (env, algo, tag, budget, cost limit), in table order (env, the paper's algorithm order, tag)."""
    groups: dict[tuple[str, str, str, int, float], list[CellResult]] = {}
    for cell in sorted(cells, key=_order):
        groups.setdefault((cell.env_id, cell.algo, cell.tag, cell.total_steps, cell.cost_limit), []).append(cell)
    return groups


def _order(cell: CellResult) -> tuple:
    algos = list(PAPER_NAMES)
    rank = algos.index(cell.algo) if cell.algo in algos else len(algos)
    return cell.env_id, rank, cell.algo, cell.tag, cell.total_steps, cell.cost_limit, cell.seeds


def _seed_mean(cells: Iterable[CellResult], metric: str) -> float:
    return finite_mean(figures.get(metric, NAN) for cell in cells for figures in cell.per_seed.values())


def _read_json(path: Path) -> dict[str, Any]:
    """A JSON object file's content; ``{}`` if absent or not (yet) complete."""
    try:
        content = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return content if isinstance(content, dict) else {}
