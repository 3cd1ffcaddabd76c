"""``sg-sweep``: train a grid of algorithms x env ids x seed groups x ``sg-train`` options on Ray.

Each cell is one ``sg-train --seeds ...`` seed group, run as a Ray task on a local Ray instance (no
setup) or on a running cluster (``--address``). The same command after a Ctrl-C, a crash or a lost
node continues: finished cells are skipped, unfinished ones resume from their checkpoints. Once the
cells are done the report is written to ``<output-dir>/report/`` (the paper-format table as Markdown
and CSV, one row per seed, one curve figure per env); ``--report-only`` writes it from whatever has
finished, also in a copy of the output directory on another machine. The report includes the paper's
analysis figure (``report/analysis.png``, ``.csv``, ``.md``): J^R normalised by PPO-Lag's (MAPPO-Lag's for
the multi-agent algorithms) and the share of training epochs in each cost region around the limit
(``--cost-regions``, after a ``--warmup-share`` of the budget; :mod:`sg_torchrl.sweep.analysis`).

    sg-sweep --algos ppo ppo_lag cppo_pid cpo --envs SafetyPointGoal1-v0 --seeds 0 1 2 \\
        --total-steps 10000000 --output-dir runs/pointgoal1 -- --compile true
    sg-sweep --algos ppo_lag --envs SafetyPointGoal1-v0 --seeds 0 1 2 --grid lagrangian_lr=0.01,0.035
    sg-sweep --report-only --output-dir runs/pointgoal1
    sg-sweep --report-only --output-dir runs/pointgoal1 --cost-regions 0.25,1,2 --warmup-share 0.5
    sg-sweep ... --address auto          # join the cluster started with `ray start --head` on this machine

Flags after ``--`` go to every cell's ``sg-train`` (``sg-train --help`` lists them). Exit status: 0 when
every cell finished, 1 when some failed (or were stopped from outside the sweep), 2 for bad arguments, 3 when the
output directory (its sweep.json, lock or report) cannot be written, 130 after a Ctrl-C. A cell that cannot write
its own files fails ("[failed] ...: sg-train: error: cannot write <file>: <cause>") and the other cells go on.
"""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from sg_torchrl.algorithms import manifest
from sg_torchrl.sweep.analysis import COST_REGIONS, WARMUP_SHARE, parse_cost_regions, parse_warmup_share
from sg_torchrl.sweep.records import SWEEP_RECORD
from sg_torchrl.sweep.grid import SweepGrid, SweepGridError, parse_grid_option
from sg_torchrl.sweep.runner import ClusterUnreachable, run_sweep  # imports Ray only when a sweep runs
from sg_torchrl.train.writes import EXIT_WRITE_FAILED, RunWriteError

__all__ = ["main", "build_parser", "grid_from_args"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sg-sweep", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    grid = parser.add_argument_group("the grid")
    grid.add_argument("--algos", nargs="+", metavar="ALGO", help=f"sg-train --algo values ({' '.join(manifest.names())})")
    grid.add_argument("--envs", nargs="+", metavar="ENV_ID", help="env ids (SafetyPointGoal1-v0 ...)")
    grid.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2], help="seeds of every cell (default 0 1 2)")
    grid.add_argument("--seeds-per-cell", type=int, default=None,
                      help="cut --seeds into groups of this size, one cell each (default: all seeds in one group)")
    grid.add_argument("--total-steps", type=int, default=1_000_000, help="env steps per seed (paper: 10,000,000)")
    grid.add_argument("--grid", action="append", default=[], metavar="NAME=V1,V2",
                      help="an sg-train option to grid over (repeatable): --grid lr=0.001,0.0003")
    grid.add_argument("--output-dir", default="runs/sweep", help="the sweep's folder (default runs/sweep)")
    ray = parser.add_argument_group("Ray")
    ray.add_argument("--address", default=None,
                     help="a running Ray cluster to join ('auto' or HOST:PORT); default: a private local instance")
    ray.add_argument("--num-cpus", type=int, default=None, help="CPUs of the local instance (default: all)")
    ray.add_argument("--cpus-per-cell", type=float, default=1.0, help="CPUs each cell asks for (default 1)")
    ray.add_argument("--gpus-per-cell", type=float, default=0.0, help="GPUs each cell asks for (default 0)")
    ray.add_argument("--max-retries", type=int, default=3,
                     help="resubmissions of a cell whose worker died or whose sg-train was killed (default 3)")
    ray.add_argument("--progress-every", type=float, default=30.0, help="seconds between status lines")
    report = parser.add_argument_group("the report's analysis figure")
    report.add_argument("--cost-regions", type=_option(parse_cost_regions), default=COST_REGIONS, metavar="A,B,C",
                        help="bounds of the cost regions as fractions of the cost limit d: Strongly Safe <= A d < "
                             "Safe <= B d < Unsafe <= C d < Strongly Unsafe (default 0.5,1.0,1.5)")
    report.add_argument("--warmup-share", type=_option(parse_warmup_share), default=WARMUP_SHARE, metavar="SHARE",
                        help="leave out the training epochs of this first share of each cell's budget from the "
                             f"cost regions (default {WARMUP_SHARE:g}; 0: the whole run)")
    parser.add_argument("--report-only", action="store_true", help="only write the report of --output-dir")
    parser.add_argument("extra", nargs="*", help="sg-train flags for every cell, after --")
    return parser


def _option(parse):
    """An argparse ``type`` from a parser that raises ``ValueError``: its message becomes the usage error."""
    def convert(text: str):
        try:
            return parse(text)
        except ValueError as error:
            raise argparse.ArgumentTypeError(str(error)) from None
    convert.__name__ = parse.__name__
    return convert


def grid_from_args(args: argparse.Namespace) -> SweepGrid:
    """The :class:`SweepGrid` of a parsed command line.

    Raises:
        SweepGridError: missing ``--algos`` / ``--envs``, or a bad grid.
    """
    missing = [flag for flag, value in (("--algos", args.algos), ("--envs", args.envs)) if not value]
    if missing:
        raise SweepGridError(f"{' and '.join(missing)} required (or --report-only)")
    return SweepGrid.from_seeds(args.seeds, args.seeds_per_cell, algos=tuple(dict.fromkeys(args.algos)),
                                env_ids=tuple(dict.fromkeys(args.envs)), total_steps=args.total_steps,
                                output_dir=Path(args.output_dir),
                                grid_options=tuple(parse_grid_option(text) for text in args.grid),
                                extra=tuple(args.extra))


def _report(output_dir: Path, args: argparse.Namespace) -> int:
    from sg_torchrl.sweep.report import write_report

    if not output_dir.is_dir():
        print(f"sg-sweep: error: {output_dir} does not exist", file=sys.stderr)
        return 2
    try:
        paths = write_report(output_dir, cost_regions=args.cost_regions, warmup_share=args.warmup_share)
    except RunWriteError as error:
        print(f"sg-sweep: error: {error}", file=sys.stderr)
        return EXIT_WRITE_FAILED
    table = paths.get("table.md") or next((p for p in paths.values() if str(p).endswith(".md")), None)
    if table is not None:
        print(Path(table).read_text())
    print("report: " + ", ".join(str(path) for path in paths.values()))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:
        return stop.code if isinstance(stop.code, int) else 2
    output_dir = Path(args.output_dir)
    if args.report_only:
        return _report(output_dir, args)
    # A cluster scheduler stops a job with SIGTERM: treat it as Ctrl-C (cells checkpoint, then the sweep stops).
    previous_sigterm = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        grid = grid_from_args(args)
        outcome = run_sweep(grid, address=args.address, num_cpus=args.num_cpus, cpus_per_cell=args.cpus_per_cell,
                            gpus_per_cell=args.gpus_per_cell, max_retries=args.max_retries,
                            progress_every=args.progress_every)
    except (SweepGridError, ClusterUnreachable) as error:  # a bad grid, or a bad --address (or no token for it)
        print(f"sg-sweep: error: {error}", file=sys.stderr)
        return 2
    except RunWriteError as error:  # the output directory is a file, read-only or full (a cell's own: [failed])
        print(f"sg-sweep: error: {error}", file=sys.stderr)
        return EXIT_WRITE_FAILED
    except ModuleNotFoundError as error:
        if error.name != "ray":
            raise
        print("sg-sweep: error: running a sweep needs Ray: pip install 'sg_torchrl[sweep]' (--report-only does not)",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"sg-sweep: stopped; the same command continues the sweep in {output_dir}", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous_sigterm)
    if (output_dir / SWEEP_RECORD).exists():
        _report(output_dir, args)
    if outcome.failed:
        print(f"sg-sweep: {len(outcome.failed)} cell(s) failed: "
              + "; ".join(cell.label for cell in outcome.failed), file=sys.stderr)
        return 1
    if outcome.stopped:
        print(f"sg-sweep: {len(outcome.stopped)} cell(s) were stopped from outside the sweep, checkpointed: "
              + "; ".join(cell.label for cell in outcome.stopped) + ". The same command continues them",
              file=sys.stderr)
        return 1
    return 0
