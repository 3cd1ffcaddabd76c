"""A sweep cell's recovery from a killed Ray worker: how long until it trains again, and how much work is redone.

One cell (default PPO-Lag on SafetyPointGoal1-v0, seeds 0 1 2, 1,000 env steps per seed per epoch,
12 epochs: a minute or two on the 2-core machine) runs through ``sg-sweep`` on a private local Ray
instance (a subprocess, as in ``benchmarks/sweep_overhead.py``). This script watches the cell's
``attempts.jsonl`` and its first seed's ``progress.csv`` (every 0.1 s); once ``--kill-after`` epochs
are logged, and half an epoch later (``--kill-into-epoch``: a crash comes mid-epoch), it ``SIGKILL``s
the Ray worker that runs the cell (the attempt's ``pid``), which is what a crashed or OOM-killed
worker looks like to Ray. Two ways to kill (``--scenarios``):

* ``worker``: only the worker. Its ``sg-train`` child gets ``SIGTERM`` (``PR_SET_PDEATHSIG``), finishes
  the epoch under way, checkpoints it and exits (143); Ray retries the task, whose new attempt waits on
  the cell's lock until that orphan is gone, then resumes from the checkpoint;
* ``worker+train``: the worker and its ``sg-train`` child together (a lost node): nothing checkpoints
  on the way out, so the retry resumes from the last periodic checkpoint (``--checkpoint-every``
  epochs, or ``--checkpoint-minutes``; the first epoch a process trains is always saved).

Each under ``sg-train``'s checkpoint defaults (``--checkpoint-every 10 --checkpoint-minutes 1``) and with
``--checkpoint-every 1``. Recorded per run: the kill time; when the orphaned ``sg-train`` exited (its
exit code, epochs logged, checkpoint epoch); the new attempt's start (``attempts.jsonl``) and the first
progress row it writes, as seconds after the kill; epochs logged at the kill against the epoch the new
attempt resumed from (its checkpoint's epoch, read when the attempt starts: ``progress.csv`` is cut back
to it on resume), which gives the epochs and env steps trained twice; for ``worker+train`` also the
seconds of the epoch under way at the kill, lost as well. ``--compare`` first runs the same cell
without a kill and checks that each interrupted cell's ``summary.json`` equals it (timings aside:
``sg-train --resume`` continues bit-identically).

The process is a child subreaper (as in ``sweep_overhead.py``), so the orphaned ``sg-train`` is
re-parented to it where no process in between is one: then its exit code is read by waiting for it.

    python benchmarks/sweep_recovery.py --compare --json benchmarks/sweep_figures/recovery.json
    python benchmarks/sweep_recovery.py --scenarios 10:worker 1:worker+train --kill-after 3
    python benchmarks/sweep_recovery.py --total-steps 20000 -- --wandb disabled --steps-per-epoch 2000

Flags after ``--`` go to ``sg-train`` (default ``--wandb disabled --steps-per-epoch 1000 --eval-episodes 2``);
the scenario adds ``--checkpoint-every`` and ``--checkpoint-minutes``. Timings on a shared machine follow
the load beside them: the script prints the median epoch time next to the recovery times.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from sg_torchrl.sweep.records import AttemptLog
from sg_torchrl.train.checkpoint import load_checkpoint
from sweep_overhead import (Launched, cell_parser, become_subreaper, cmdline, descendants, ray_environment, sweep_cell,
                            sweep_command)

DEFAULT_EXTRA = ("--wandb", "disabled", "--steps-per-epoch", "1000", "--eval-episodes", "2")
SCENARIOS = ("10:worker", "1:worker", "10:worker+train", "1:worker+train")
POLL_S = 0.1


def checkpoint_epoch(directory: Path) -> int | None:
    """The epoch of the cell's checkpoint now (None without one)."""
    try:
        return int(load_checkpoint(directory / "checkpoint.pt")["epoch"])
    except (OSError, ValueError):
        return None


def last_epoch(directory: Path, seed: int) -> int:
    """The epoch of the last complete row of ``seed``'s ``progress.csv`` (0 without one)."""
    try:
        lines = (directory / f"seed-{seed:03d}" / "progress.csv").read_text().splitlines()
    except OSError:
        return 0
    if len(lines) < 2:
        return 0
    header = lines[0].split(",")
    column = header.index("Train/Epoch")
    for line in reversed(lines[1:]):
        values = line.split(",")
        if len(values) == len(header) and values[column]:
            return int(float(values[column]))
    return 0


def train_child(worker: int) -> int | None:
    """The ``sg-train`` process the worker ``worker`` started (None before it exists)."""
    for pid in descendants():
        if "sg_torchrl.train" in cmdline(pid) and _parent(pid) == worker:
            return pid
    return None


def _parent(pid: int) -> int | None:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(text[text.rindex(")") + 2:].split()[1])


def _exited(pid: int) -> tuple[bool, int | None]:
    """Whether ``pid`` has exited, and its exit code where this process could reap it (its subreaper)."""
    try:
        done, status, _ = os.wait4(pid, os.WNOHANG)
        return (True, os.waitstatus_to_exitcode(status)) if done else (False, None)
    except ChildProcessError:  # not (or no longer) our child: look at /proc
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            return True, None
        return state in ("Z", "X"), None


def sweep_once(args: argparse.Namespace, root: Path, name: str, extra: list[str], kill: str | None) -> dict[str, Any]:
    """One sweep of the cell; with ``kill`` (``worker`` / ``worker+train``) the kill after ``--kill-after`` epochs."""
    output = root / name
    command = sweep_command(args.algo, args.env_id, args.seeds, args.total_steps, output, extra,
                            "--progress-every", "5")
    grid, cell = sweep_cell(command)
    directory, seed = grid.cell_dir(cell), cell.seeds[0]
    run = Launched(command, output.with_suffix(".log"), ray_environment(root))
    row: dict[str, Any] = {"name": name, "kill": kill, "extra": extra}
    rows_seen: list[tuple[float, int]] = []  # (time first seen, epoch) of each new last row
    orphan = None
    while run.process.poll() is None:
        time.sleep(POLL_S)
        now, epoch = time.time(), last_epoch(directory, seed)
        if not rows_seen or epoch != rows_seen[-1][1]:
            rows_seen.append((now, epoch))
        attempts = AttemptLog(directory).read()
        if kill and "kill_at" not in row and attempts and attempts[0]["status"] == "running" \
                and epoch >= args.kill_after:  # mid-epoch, as a crash would be: into the next epoch by a fraction
            row["kill_at"] = now + args.kill_into_epoch * (_epoch_seconds(rows_seen, None) or 0.0)
        if "kill_at" in row and "kill_time" not in row and now >= row["kill_at"]:
            worker = attempts[0]["pid"]
            orphan = train_child(worker)
            row.update(checkpoint_epoch_at_kill=checkpoint_epoch(directory), epochs_at_kill=epoch,
                       seconds_since_last_row=now - rows_seen[-1][0])
            if kill == "worker+train" and orphan:
                os.kill(orphan, signal.SIGKILL)
            os.kill(worker, signal.SIGKILL)
            row["kill_time"] = time.time()
            row["last_row_before_kill"] = rows_seen[-1][0]
        if orphan and "orphan_exit_time" not in row:
            gone, code = _exited(orphan)
            if gone:
                row.update(orphan_exit_time=time.time(), orphan_code=code, orphan_epochs=last_epoch(directory, seed),
                           orphan_checkpoint_epoch=checkpoint_epoch(directory))
        if "kill_time" in row and len(attempts) >= 2 and "resumed_from" not in row:
            resumed = checkpoint_epoch(directory) if attempts[1]["resumed"] else 0
            row.update(new_attempt=attempts[1], resumed_from=resumed,
                       logged_before_resume=max(e for t, e in rows_seen if t < attempts[1]["start"] + POLL_S))
        if "resumed_from" in row and "first_new_row_time" not in row and epoch > row["resumed_from"] \
                and rows_seen[-1][0] > row["new_attempt"]["start"]:
            row.update(first_new_row_time=rows_seen[-1][0], first_new_epoch=epoch)
    done = run.finish()
    row.update(code=done.code, wall_s=done.wall_s, cpu_s=done.cpu_s, attempts=AttemptLog(directory).read(),
               epoch_wall_s=_epoch_seconds(rows_seen, row.get("kill_time")))
    summary = directory / "summary.json"
    row["summary"] = json.loads(summary.read_text()) if summary.exists() else None
    if "kill_time" in row:
        _derive(row, args, len(cell.seeds))
    return row


def _epoch_seconds(rows_seen: list[tuple[float, int]], until: float | None) -> float | None:
    """Median seconds between consecutive epoch rows of the first attempt (before any kill)."""
    times = [t for t, e in rows_seen if e > 0 and (until is None or t <= until)]
    gaps = [b - a for a, b in zip(times, times[1:])]
    return statistics.median(gaps) if gaps else None


def _derive(row: dict[str, Any], args: argparse.Namespace, seeds: int) -> None:
    """Seconds after the kill and the work trained twice."""
    kill = row["kill_time"]
    if "orphan_exit_time" in row:
        row["kill_to_orphan_exit_s"] = row["orphan_exit_time"] - kill
    if "new_attempt" in row:
        row["kill_to_new_attempt_s"] = row["new_attempt"]["start"] - kill
        row["redone_epochs"] = max(row["logged_before_resume"] - row["resumed_from"], 0)
        row["redone_env_steps_per_seed"] = row["redone_epochs"] * args.steps_per_epoch
        row["redone_env_steps"] = row["redone_epochs"] * args.steps_per_epoch * seeds
        # the epoch under way when both died was lost too (the orphan of a worker-only kill finishes it)
        row["lost_partial_epoch_s"] = row["seconds_since_last_row"] if row["kill"] == "worker+train" else 0.0
    if "first_new_row_time" in row:
        row["kill_to_new_progress_s"] = row["first_new_row_time"] - kill


def same_summary(a: dict | None, b: dict | None) -> tuple[bool, float]:
    """Whether two ``summary.json`` trees are equal (``Time/*`` entries aside), and their largest difference."""
    def flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
        if isinstance(tree, dict):
            return {k: v for key, value in tree.items() if not str(key).startswith("Time/")
                    for k, v in flatten(value, f"{prefix}/{key}").items()}
        return {prefix: tree}

    if a is None or b is None:
        return False, float("nan")
    fa, fb = flatten(a), flatten(b)
    if fa.keys() != fb.keys():
        return False, float("nan")
    numbers = [k for k in fa if isinstance(fa[k], (int, float)) and isinstance(fb[k], (int, float))]
    equal = all(fa[k] == fb[k] or (k in numbers and fa[k] != fa[k] and fb[k] != fb[k]) for k in fa)  # NaN == NaN
    diffs = [abs(fa[k] - fb[k]) for k in numbers if fa[k] == fa[k] and fb[k] == fb[k]]
    return equal, max(diffs, default=0.0)


def markdown(rows: list[dict]) -> str:
    def num(value: Any, digits: int = 1) -> str:
        return "" if value is None else f"{value:.{digits}f}"

    lines = ["| checkpoints | killed | epochs logged at kill (checkpoint) | orphan sg-train: exit s after kill, code, "
             "checkpoint epoch | kill -> new attempt s | kill -> new progress s | resumed from epoch | redone epochs "
             "(env steps, all seeds) | lost partial epoch s | epoch s (median) | summary = uninterrupted |",
             "|---|---|---|---|---:|---:|---:|---|---:|---:|---|"]
    for row in rows:
        if not row.get("kill"):
            continue
        orphan = (f"{num(row.get('kill_to_orphan_exit_s'))} s, {row.get('orphan_code')}, "
                  f"{row.get('orphan_checkpoint_epoch')}" if "orphan_exit_time" in row else "")
        equal = row.get("summary_equal")
        lines.append(
            f"| {row['checkpoints']} | {row['kill']} "
            f"| {row.get('epochs_at_kill')} ({row.get('checkpoint_epoch_at_kill')}) "
            f"| {orphan} | {num(row.get('kill_to_new_attempt_s'))} | {num(row.get('kill_to_new_progress_s'))} "
            f"| {row.get('resumed_from')} | {row.get('redone_epochs')} ({row.get('redone_env_steps')}) "
            f"| {num(row.get('lost_partial_epoch_s'))} | {num(row.get('epoch_wall_s'))} "
            f"| {'' if equal is None else equal} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = cell_parser(__doc__, 12_000)
    parser.add_argument("--kill-after", type=int, default=5, help="kill once this many epochs are logged (default 5)")
    parser.add_argument("--kill-into-epoch", type=float, default=0.5,
                        help="... and this fraction of an epoch (the median so far) later (default 0.5)")
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), metavar="EVERY:KILL",
                        help="checkpoint-every : worker | worker+train (default: " + " ".join(SCENARIOS) + ")")
    parser.add_argument("--checkpoint-minutes", type=float, default=1.0,
                        help="sg-train --checkpoint-minutes (default 1)")
    parser.add_argument("--compare", action="store_true",
                        help="also run the cell uninterrupted and compare every summary.json with it")
    parser.add_argument("--workdir", default=None, help="where the runs go (default: a temporary folder, removed)")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    parser.add_argument("extra", nargs="*", help="sg-train flags after -- (default: " + " ".join(DEFAULT_EXTRA) + ")")
    args = parser.parse_args(argv)
    extra = args.extra or list(DEFAULT_EXTRA)
    steps = extra[extra.index("--steps-per-epoch") + 1] if "--steps-per-epoch" in extra else "20000"
    args.steps_per_epoch = int(steps)
    become_subreaper()
    root = Path(args.workdir or tempfile.mkdtemp(prefix="sgr-", dir="/tmp")).resolve()
    root.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        if args.compare:
            reference = sweep_once(args, root, "uninterrupted", [*extra, "--checkpoint-every", "10"], None)
            reference["checkpoints"] = "every 10"
            rows.append(reference)
            print(f"uninterrupted: exit {reference['code']}, wall {reference['wall_s']:.1f} s", flush=True)
        for scenario in args.scenarios:
            every, kill = scenario.split(":")
            flags = [*extra, "--checkpoint-every", every, "--checkpoint-minutes", str(args.checkpoint_minutes)]
            row = sweep_once(args, root, f"every-{every}-{kill.replace('+', '-')}", flags, kill)
            row["checkpoints"] = f"every {every} epochs / {args.checkpoint_minutes:g} min"
            if args.compare:
                row["summary_equal"], row["summary_max_abs_diff"] = same_summary(row["summary"], rows[0]["summary"])
            rows.append(row)
            print(f"{scenario}: exit {row['code']}, wall {row['wall_s']:.1f} s, attempts "
                  f"{[a['status'] for a in row['attempts']]}", flush=True)
    finally:
        if args.workdir is None:
            shutil.rmtree(root, ignore_errors=True)
    print(f"\n{args.algo} on {args.env_id}, seeds {' '.join(map(str, args.seeds))}, {args.total_steps} env steps per "
          f"seed, sg-train flags {' '.join(extra)}; killed {args.kill_into_epoch:g} epoch after {args.kill_after} "
          "epochs were logged\n")
    print(markdown(rows))
    if args.json:
        from _report import write_json

        write_json(args.json, rows, threads=1)
    return rows


if __name__ == "__main__":
    main()
