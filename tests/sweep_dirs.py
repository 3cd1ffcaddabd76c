"""Synthetic sweep output directories, written the way sg-sweep's cells write them, for the report's tests.

Two layouts of a cell (:mod:`sg_torchrl.sweep.report`): seed groups as sg-sweep writes them (:func:`group`)
and single seeds as the older benchmarks did (:func:`single`). Every seed trains four epochs of 250 env
steps (the budget, :data:`BUDGET`) whose ``Metrics/EpRet`` / ``Metrics/EpCost`` rise linearly to its
final figures (epoch e: e/4 of them), so every number read back is known exactly.
"""

from __future__ import annotations

import json
from pathlib import Path

BUDGET = 1000  # env steps per seed: four epochs of 250


def progress_csv(path: Path, final_ret: float, final_cost: float, *, epochs: int = 4, update_s: float = 2.0,
              evaluation: bool = True) -> None:
    """A progress.csv whose EpRet / EpCost rise linearly to the final figures (epoch e of 4: e/4 of them),
    with the step-count-only evaluation row a finished run appends."""
    path.mkdir(parents=True, exist_ok=True)
    lines = ["Metrics/EpRet,Metrics/EpCost,Train/Epoch,Train/TotalSteps,Time/Update,Time/Total"]
    lines += [f"{final_ret * e / 4},{final_cost * e / 4},{e},{250 * e},{update_s},{100 * e}"
              for e in range(1, epochs + 1)]
    if evaluation:
        lines.append(f",,,{250 * epochs},,")
    (path / "progress.csv").write_text("\n".join(lines) + "\n")


def figures(ret: float, cost: float) -> dict[str, float]:
    return {"Final/EpRetLast10": ret, "Final/EpCostLast10": cost, "Metrics/EvalEpRet": ret + 1,
            "Metrics/EvalEpCost": cost / 2}


def group(root: Path, env_id: str, algo: str, finals: dict[int, tuple[float, float]], *, tag: str = "",
          cost_limit: float | None = None, finished: bool = True, diverged: tuple[int, ...] = (),
          time_total: float = 3600.0, attempts: list[dict] | None = None, update_s: float = 2.0) -> Path:
    """A seed-group cell ``root/env/algo/[tag/]seeds-a-b`` whose seed s ends at ``finals[s] = (J^R, J^C)``."""
    directory = root / env_id / algo / tag / ("seeds-" + "-".join(map(str, finals)))
    directory.mkdir(parents=True)
    config = {"env_id": env_id, "algo": algo, "seeds": list(finals), "total_steps": BUDGET, "compile": True}
    if cost_limit is not None:
        config["cost_limit"] = cost_limit
    (directory / "config.json").write_text(json.dumps(config))
    for seed, (ret, cost) in finals.items():
        seed_dir = directory / f"seed-{seed:03d}"
        progress_csv(seed_dir, ret, cost, epochs=4 if finished and seed not in diverged else 2,
                  update_s=update_s + seed, evaluation=finished)
        if finished:
            steps = 500 if seed in diverged else BUDGET
            (seed_dir / "summary.json").write_text(json.dumps({**figures(ret, cost), "Train/TotalSteps": steps}))
    if finished:
        (directory / "summary.json").write_text(json.dumps({
            "seeds": {str(seed): figures(*final) for seed, final in finals.items()}, "diverged": list(diverged),
            "Train/TotalSteps": BUDGET, "Time/Total": time_total}))
    if attempts is not None:
        (directory / "attempts.jsonl").write_text("".join(json.dumps(a) + "\n" for a in attempts))
    return directory


def single(root: Path, env_id: str, algo: str, seed: int, ret: float, cost: float) -> Path:
    """An older benchmark's single-seed cell ``root/env/algo/seed-00s``."""
    directory = root / env_id / algo / f"seed-{seed:03d}"
    progress_csv(directory, ret, cost, update_s=5.0)
    (directory / "config.json").write_text(json.dumps({"env_id": env_id, "algo": algo, "seed": seed,
                                                       "seeds": [], "total_steps": BUDGET}))
    (directory / "summary.json").write_text(json.dumps({**figures(ret, cost), "Train/TotalSteps": BUDGET,
                                                        "Time/Total": 1800.0}))
    return directory
