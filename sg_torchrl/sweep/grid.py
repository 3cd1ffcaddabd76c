"""The sweep grid: algorithms x env ids x seed groups x ``sg-train`` options, expanded into cells.

A **cell** is one ``sg-train`` run of a seed group (``--seeds 0 1 2``: the seeds train side by side in
one process, :mod:`sg_torchrl.train.seed_group`). Its identity is (env id, algorithm, gridded options,
seeds) and it lives in ``<output>/<env_id>/<algo>/[<tag>/]seeds-0-1-2``, the directory ``sg-train``
itself would choose under ``--output-dir <output>`` (``<tag>`` names the gridded options, for example
``lr=0.001,num_envs=20``). Options given to every cell (``sg-sweep ... -- --compile true``) are not
part of a cell's name; the sweep records them in ``sweep.json`` and refuses to mix cells trained with
other ones into the same output directory.

Everything here is plain data and validation: no Ray, no torch. Each cell's command line is checked
by ``sg-train``'s own parser when the grid is built, so a bad flag fails the sweep before any cell
starts, naming the cell.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

__all__ = ["Cell", "SweepGrid", "SweepGridError", "parse_grid_option"]

#: ``sg-train`` flags that the sweep sets itself for every cell (a grid or extra option may not).
RESERVED_FLAGS = frozenset({"--algo", "--env-id", "--seed", "--seeds", "--output-dir", "--run-name", "--resume",
                            "--overwrite", "--preset", "--total-steps"})


class SweepGridError(ValueError):
    """A sweep that cannot run as asked (a bad option, an empty grid, a clash with an earlier sweep)."""


def _flag(name: str) -> str:
    return "--" + name.strip().lstrip("-").replace("_", "-")


def parse_grid_option(text: str) -> tuple[str, tuple[str, ...]]:
    """``"lr=0.001,0.0003"`` -> ``("lr", ("0.001", "0.0003"))``: one ``sg-train`` option and its values.

    Raises:
        SweepGridError: no ``=``, an empty name or no value.
    """
    name, sep, values = text.partition("=")
    name = name.strip().lstrip("-").replace("-", "_")
    choices = tuple(v.strip() for v in values.split(",") if v.strip())
    if not sep or not name or not choices:
        raise SweepGridError(f"--grid {text!r}: expected NAME=VALUE[,VALUE...], e.g. --grid lr=0.001,0.0003")
    return name, choices


@dataclass(frozen=True)
class Cell:
    """One run of the sweep: a seed group of ``algo`` on ``env_id`` with the gridded ``options``."""

    env_id: str
    algo: str
    seeds: tuple[int, ...]
    #: The gridded options of this cell, ``(name, value)`` pairs in the grid's order (``sg-train`` flag values).
    options: tuple[tuple[str, str], ...] = ()

    @property
    def tag(self) -> str:
        """The folder that names the gridded options (``"lr=0.001,num_envs=20"``); ``""`` without any."""
        return ",".join(f"{name}={value}" for name, value in self.options)

    @property
    def run_name(self) -> str:
        """The cell's directory relative to the sweep's output directory (``sg-train --run-name``)."""
        seeds = "seeds-" + "-".join(map(str, self.seeds))
        return "/".join(part for part in (self.env_id, self.algo, self.tag, seeds) if part)

    @property
    def label(self) -> str:
        """A short human name: ``"SafetyPointGoal1-v0 ppo_lag seeds 0 1 2 [lr=0.001]"``."""
        text = f"{self.env_id} {self.algo} seeds {' '.join(map(str, self.seeds))}"
        return f"{text} [{self.tag}]" if self.tag else text

    def as_dict(self) -> dict[str, Any]:
        return {"env_id": self.env_id, "algo": self.algo, "seeds": list(self.seeds),
                "options": [list(pair) for pair in self.options], "run_name": self.run_name}


@dataclass(frozen=True)
class SweepGrid:
    """The whole sweep: its cells' axes and what every cell shares.

    Attributes:
        algos, env_ids: the algorithms (``sg-train --algo``) and env ids of the grid.
        seed_groups: each a tuple of seeds trained together in one cell.
        grid_options: gridded ``sg-train`` options, ``(name, values)`` in order; every combination is a cell.
        total_steps: env steps per seed of every cell.
        extra: ``sg-train`` arguments given to every cell (``["--compile", "true"]``).
        output_dir: the sweep's root folder.
    """

    algos: tuple[str, ...]
    env_ids: tuple[str, ...]
    seed_groups: tuple[tuple[int, ...], ...]
    total_steps: int
    output_dir: Path
    grid_options: tuple[tuple[str, tuple[str, ...]], ...] = ()
    extra: tuple[str, ...] = ()
    cells: tuple[Cell, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "output_dir", Path(self.output_dir).resolve())
        if not (self.algos and self.env_ids and self.seed_groups):
            raise SweepGridError("a sweep needs at least one algorithm, one env id and one seed")
        if any(not group for group in self.seed_groups):
            raise SweepGridError("every seed group needs at least one seed")
        if not isinstance(self.total_steps, int) or self.total_steps < 1:
            raise SweepGridError(f"total steps must be a positive integer, got {self.total_steps!r}")
        given = {arg.split("=")[0] for arg in self.extra if arg.startswith("--")}
        given |= {_flag(name) for name, _ in self.grid_options}
        if clash := sorted(given & RESERVED_FLAGS):
            raise SweepGridError(f"{', '.join(clash)}: the sweep sets these for each cell itself "
                                 "(use --algos / --envs / --seeds / --total-steps / --output-dir)")
        names = [name for name, _ in self.grid_options]
        if len(set(names)) != len(names):
            raise SweepGridError(f"an option is gridded twice: {names}")
        combos = list(itertools.product(*[[(name, v) for v in values] for name, values in self.grid_options]))
        cells = tuple(Cell(env, algo, tuple(seeds), tuple(combo)) for env in self.env_ids for algo in self.algos
                      for combo in combos for seeds in self.seed_groups)
        if len({cell.run_name for cell in cells}) != len(cells):
            raise SweepGridError("two cells would share a directory: an env, algorithm, option value or seed group "
                                 "is listed twice")
        object.__setattr__(self, "cells", cells)

    @classmethod
    def from_seeds(cls, seeds: Sequence[int], seeds_per_cell: int | None = None, **kwargs: Any) -> SweepGrid:
        """A grid whose seed groups are ``seeds`` cut into groups of ``seeds_per_cell`` (default: one group)."""
        size = len(seeds) if seeds_per_cell is None else seeds_per_cell
        if size < 1:  # 0 included: it is no group size, not "all seeds"
            raise SweepGridError(f"seeds per cell must be >= 1, got {seeds_per_cell}")
        if len(set(seeds)) != len(seeds):
            raise SweepGridError(f"a seed is listed twice: {list(seeds)}")
        groups = tuple(tuple(seeds[i:i + size]) for i in range(0, len(seeds), size))
        return cls(seed_groups=groups, **kwargs)

    def cell_dir(self, cell: Cell) -> Path:
        return self.output_dir / cell.run_name

    def train_arguments(self, cell: Cell) -> list[str]:
        """The ``sg-train`` arguments that start ``cell`` afresh (the runner adds ``--overwrite`` or ``--resume``)."""
        arguments = ["--algo", cell.algo, "--env-id", cell.env_id, "--seeds", *map(str, cell.seeds),
                     "--total-steps", str(self.total_steps), "--output-dir", str(self.output_dir),
                     "--run-name", cell.run_name]
        for name, value in cell.options:
            arguments += [_flag(name), value]
        return arguments + list(self.extra)

    def validate(self) -> None:
        """Check every cell's command line with ``sg-train``'s own parser and config checks.

        Raises:
            SweepGridError: naming the first bad cell and ``sg-train``'s complaint.
        """
        from sg_torchrl.train.command_line import parse_args

        for cell in self.cells:
            errors = io.StringIO()
            try:
                with contextlib.redirect_stderr(errors):
                    parse_args(self.train_arguments(cell))
            except SystemExit:  # argparse: an unknown flag or a bad value, explained on stderr
                message = errors.getvalue().strip().splitlines()
                raise SweepGridError(f"cell {cell.label}: {message[-1] if message else 'bad sg-train arguments'}") \
                    from None
            except ValueError as error:
                raise SweepGridError(f"cell {cell.label}: {error}") from None

    def as_dict(self) -> dict[str, Any]:
        """What ``sweep.json`` records: the axes and the shared options (paths relative to the output dir)."""
        return {"algos": list(self.algos), "env_ids": list(self.env_ids),
                "seed_groups": [list(group) for group in self.seed_groups], "total_steps": self.total_steps,
                "grid_options": [[name, list(values)] for name, values in self.grid_options],
                "extra": list(self.extra), "cells": [cell.as_dict() for cell in self.cells]}

    def shared_settings(self) -> dict[str, Any]:
        """What every cell of an output directory must share: the budget and the options outside the grid."""
        return {"total_steps": self.total_steps, "extra": list(self.extra)}


def merge_records(previous: Mapping[str, Any] | None, grid: SweepGrid) -> dict[str, Any]:
    """The ``sweep.json`` of ``grid`` in an output directory that may hold an earlier sweep's record.

    A later sweep may add algorithms, envs, seeds or option values (its cells join the same table), but
    must share the budget and the options outside the grid: cells trained otherwise would sit in one
    table as if comparable.

    Raises:
        SweepGridError: the earlier record's total steps or shared options differ.
    """
    record = grid.as_dict()
    if previous:
        before = {"total_steps": previous.get("total_steps"), "extra": previous.get("extra", [])}
        if before != grid.shared_settings():
            raise SweepGridError(
                f"{grid.output_dir} holds a sweep with {json.dumps(before)}; this one asks "
                f"{json.dumps(grid.shared_settings())}. Use another --output-dir (cells trained with other "
                "settings would share its table)")
        known = {cell["run_name"]: cell for cell in previous.get("cells", [])}
        known.update({cell["run_name"]: cell for cell in record["cells"]})
        record["cells"] = list(known.values())
    return record
