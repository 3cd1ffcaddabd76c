"""Ray's overhead on one sweep cell: ``sg-sweep`` (a private local Ray instance) against ``sg-train`` run directly.

The same seed-group cell (default PPO-Lag on SafetyPointGoal1-v0, seeds 0 1 2, 20,000 env steps per
seed: one paper-size epoch, ``--wandb disabled``) runs ``--repeats`` times each way, interleaved (the
order alternates), each run a subprocess:

* **direct**: ``python -m sg_torchrl.train`` with exactly the arguments the sweep's task gives its
  child (:meth:`SweepGrid.train_arguments` plus ``--overwrite --progress false``), so both train the
  same cell with the same flags;
* **sweep**: ``python -m sg_torchrl.sweep ... --num-cpus 1``, which starts its own Ray instance
  (``address="local"``: never the cluster of another sweep on the machine), runs the cell as a Ray task
  (:func:`sg_torchrl.sweep.cell.run_cell`, whose ``sg-train`` child trains), shuts Ray down and writes
  the sweep's report.

Reported per run: wall seconds and CPU seconds, and for the baseline (direct, median over repeats)
the difference and ratio of each. CPU time must include Ray's own processes (gcs_server, raylet, its
agents and monitors, the workers), not only the driver. Two counts:

* ``RUSAGE_CHILDREN`` of this process, which counts every descendant that has exited *and been
  reaped*. Ray's processes are orphaned when Ray shuts down, so this process makes itself a child
  subreaper (``prctl(PR_SET_CHILD_SUBREAPER)``): orphans are re-parented to it, and after each run it
  reaps every descendant (:func:`reap_descendants`, ``wait4(-1)`` until ``ECHILD``; stragglers are
  killed after a timeout). This still misses the Ray workers: the raylet ignores ``SIGCHLD``, so the
  kernel reaps the workers itself and their CPU, with that of the ``sg-train`` child each worker
  reaped, reaches nobody's children's usage (measured: the sweep's count came out *below* its own
  ``sg-train`` child's);
* the CPU of a cgroup v2 of the run's own (:class:`CpuGroup`; every descendant is born in it, however
  it ends). This is the figure the tables use (``RUSAGE_CHILDREN`` where no cgroup2 is writable).

The check: a count must cover the cell's ``sg-train`` child (``cpu_s`` in ``attempts.jsonl``, measured
by the task itself) plus the Ray processes' CPU seen by sampling ``/proc`` every half second
(:class:`CpuSampler`, a lower bound: the last half second of each process is missed). The sampled CPU
per role (driver, gcs_server, raylet, workers, agents, monitors, sg-train) is the table's breakdown.

The sweep's wall time is split into **startup** (the subprocess' start until the attempt's start in
``attempts.jsonl``: interpreter and imports, checking the grid with ``sg-train``'s parser, ``ray.init``,
scheduling, a worker, the cell's lock), the **sg-train child** (the attempt's ``wall_s``) and **after**
(the child's exit until the sweep exits: the driver noticing, ``ray.shutdown`` and the report).

Every run starts in its own session (``start_new_session``), as the task's ``sg-train`` child does: with
the kernel's autogroup scheduling each session is one scheduling group, so the direct run's trainer
and the sweep's get the same share of a busy machine. Wall times on a shared 2-core machine follow
the load beside them; CPU seconds much less so.

    python benchmarks/sweep_overhead.py                                   # 3 repeats of the default cell
    python benchmarks/sweep_overhead.py --repeats 2 --json benchmarks/sweep_figures/overhead.json
    python benchmarks/sweep_overhead.py --algo cpo --total-steps 40000 -- --wandb disabled --eval-episodes 2

Flags after ``--`` go to ``sg-train`` in both runs (default ``--wandb disabled``).
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import resource
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sg_torchrl.sweep.cli import build_parser, grid_from_args
from sg_torchrl.sweep.grid import Cell, SweepGrid
from sg_torchrl.sweep.records import AttemptLog

_PR_SET_CHILD_SUBREAPER = 36
_TICKS = os.sysconf("SC_CLK_TCK")
DEFAULT_EXTRA = ("--wandb", "disabled")
KINDS = ("direct", "sweep", "direct+env")


def become_subreaper() -> None:
    """Make orphaned descendants re-parent to this process, so that reaping them counts their CPU (and no
    zombie or straggler of a run outlives it)."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(_PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER) failed")


def children_cpu() -> float:
    """CPU seconds (user + system) of every reaped descendant of this process so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _stat(pid: int) -> tuple[int, float] | None:
    """``(ppid, CPU seconds)`` of a live process from ``/proc/<pid>/stat`` (None once it is gone)."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2:].split()  # after "pid (comm) ": state ppid ... utime(12) stime(13)
    return int(fields[1]), (int(fields[11]) + int(fields[12])) / _TICKS


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return ""


def descendants(root: int | None = None) -> dict[int, float]:
    """Live descendants of ``root`` (default: this process) and their CPU seconds so far."""
    root = os.getpid() if root is None else root
    table = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit() and (stat := _stat(int(entry))) is not None:
            table[int(entry)] = stat
    found, frontier = {}, [root]
    while frontier:
        parent = frontier.pop()
        for pid, (ppid, cpu) in table.items():
            if ppid == parent and pid not in found:
                found[pid] = cpu
                frontier.append(pid)
    return found


def reap_descendants(timeout: float = 60.0) -> dict[str, int]:
    """Reap every descendant (``wait4(-1)`` until ``ECHILD``); after ``timeout`` s, ``SIGKILL`` what is left.

    Only a process's reaped children count in its ``RUSAGE_CHILDREN``; with this process a subreaper
    the orphans of every run are its children. Returns how many were reaped and killed.
    """
    reaped = killed = 0
    deadline = time.monotonic() + timeout
    while True:
        try:
            pid, _, _ = os.wait4(-1, os.WNOHANG)
        except ChildProcessError:
            return {"reaped": reaped, "killed": killed}
        if pid:
            reaped += 1
            continue
        if time.monotonic() > deadline:
            for straggler in descendants():  # this run's processes only: nothing else descends from us
                try:
                    os.kill(straggler, signal.SIGKILL)
                    killed += 1
                except ProcessLookupError:
                    pass
            deadline = float("inf")
        time.sleep(0.05)


def role(command: str) -> str:
    """Which part of a sweep a process is, from its command line."""
    if "sg_torchrl.train" in command:
        return "sg-train"
    if "sg_torchrl.sweep" in command:
        return "driver"
    for name in ("gcs_server", "raylet"):
        if name in command.split(" ")[0]:
            return name
    if "_worker.py" in command or (command.startswith("ray::") and "Agent" not in command):
        return "workers"
    if "agent" in command.lower() or "dashboard" in command:
        return "agents"
    if "monitor" in command:
        return "monitors"
    return "other"


class CpuGroup:
    """A cgroup v2 of its own for one run: the CPU of every process that ever ran in it, however it was reaped.

    ``RUSAGE_CHILDREN`` misses Ray's workers: the raylet ignores ``SIGCHLD``, so the kernel reaps the
    workers it spawns itself and their CPU (and that of the ``sg-train`` child each worker reaped) is
    added to nobody's children's usage. A cgroup counts them all. The group is created under the
    first writable cgroup2 mount (no controllers are enabled: it only counts, scheduling is unchanged)
    and removed afterwards. :meth:`create` returns None where there is none (the CPU figures are then
    ``RUSAGE_CHILDREN``'s only).
    """

    def __init__(self, path: Path) -> None:
        self.path = path

    @classmethod
    def create(cls, name: str) -> CpuGroup | None:
        mounts = [line.split()[1] for line in Path("/proc/mounts").read_text().splitlines()
                  if line.split()[2] == "cgroup2"]
        for mount in mounts:
            try:
                path = Path(mount) / name
                path.mkdir()
                return cls(path)
            except OSError:
                continue
        return None

    def enter(self) -> None:
        """In the child before ``exec``: join the group (its descendants will be born in it)."""
        (self.path / "cgroup.procs").write_text(str(os.getpid()))

    def cpu_s(self) -> float:
        stat = dict(line.split() for line in (self.path / "cpu.stat").read_text().splitlines())
        return int(stat["usage_usec"]) / 1e6

    def remove(self) -> None:
        try:
            self.path.rmdir()
        except OSError:
            pass


class CpuSampler(threading.Thread):
    """Every ``interval`` s, the CPU seconds of each live descendant; :meth:`by_role` sums the last values.

    A lower bound of what each process used (its last ``interval`` is missed); what it is for is the
    split between roles and the check that ``RUSAGE_CHILDREN`` counted Ray's processes.
    """

    def __init__(self, interval: float = 0.5) -> None:
        super().__init__(daemon=True)
        self.interval, self.stop = interval, threading.Event()
        self.last: dict[int, tuple[str, float]] = {}

    def run(self) -> None:
        while not self.stop.wait(self.interval):
            for pid, cpu in descendants().items():
                # read each time: a process forked but not yet exec'd still shows its parent's command line
                name = role(cmdline(pid))
                if name == "other" and pid in self.last:
                    name = self.last[pid][0]
                self.last[pid] = (name, cpu)

    def by_role(self) -> dict[str, float]:
        totals: dict[str, float] = {}
        for name, cpu in self.last.values():
            totals[name] = totals.get(name, 0.0) + cpu
        return dict(sorted(totals.items()))


@dataclass
class Finished:
    """A finished subprocess: wall seconds, CPU seconds of all its descendants and its timestamped output.

    ``cpu_s`` is the run's cgroup's count where there is one (:class:`CpuGroup`), else ``rusage_cpu_s``,
    the ``RUSAGE_CHILDREN`` delta after reaping every descendant.
    """

    wall_s: float
    cpu_s: float
    rusage_cpu_s: float
    cgroup: bool
    code: int
    start: float  # time.time() at launch
    end: float
    lines: list[tuple[float, str]] = field(default_factory=list)
    reap: dict[str, int] = field(default_factory=dict)
    sampled: dict[str, float] = field(default_factory=dict)


class Launched:
    """A subprocess in its own session (and cgroup) whose output lines are timestamped, and copied to ``log``.

    :meth:`finish` waits for it, reaps every descendant and returns a :class:`Finished`.
    """

    def __init__(self, command: list[str], log: Path, env: dict[str, str] | None = None, sample: bool = False) -> None:
        self.lines: list[tuple[float, str]] = []
        self._log = log.open("w")
        self.sampler = CpuSampler() if sample else None
        self.group = CpuGroup.create(f"sgb-{os.getpid()}-{time.monotonic_ns()}")
        self.cpu_before = children_cpu()
        self.start = time.time()
        self._t0 = time.monotonic()
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                        start_new_session=True, env=env,
                                        preexec_fn=self.group.enter if self.group else None)
        if self.sampler:
            self.sampler.start()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.process.stdout:
            now = time.time()
            self.lines.append((now, line.rstrip("\n")))
            self._log.write(f"{now - self.start:9.2f} {line}")
            self._log.flush()

    def finish(self, timeout: float | None = None) -> Finished:
        try:
            code = self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)
            code = self.process.wait()
        wall, end = time.monotonic() - self._t0, time.time()
        self._reader.join(10)
        self._log.close()
        if self.sampler:
            self.sampler.stop.set()
            self.sampler.join()
        reap = reap_descendants()
        rusage = children_cpu() - self.cpu_before
        cpu = rusage
        if self.group:
            cpu = self.group.cpu_s()
            self.group.remove()
        return Finished(wall, cpu, rusage, self.group is not None, code, self.start, end, self.lines, reap,
                        self.sampler.by_role() if self.sampler else {})


def sweep_command(algo: str, env_id: str, seeds: list[int], total_steps: int, output_dir: Path,
                  extra: list[str], *options: str) -> list[str]:
    """``python -m sg_torchrl.sweep`` for one cell on a private local Ray instance of one CPU."""
    return [sys.executable, "-m", "sg_torchrl.sweep", "--algos", algo, "--envs", env_id, "--seeds", *map(str, seeds),
            "--total-steps", str(total_steps), "--output-dir", str(output_dir), "--num-cpus", "1", *options,
            "--", *extra]


def sweep_cell(command: list[str]) -> tuple[SweepGrid, Cell]:
    """The grid and the (only) cell of a :func:`sweep_command`, as ``sg-sweep`` itself parses it."""
    grid = grid_from_args(build_parser().parse_args(command[3:]))
    return grid, grid.cells[0]


def ray_environment(root: Path) -> dict[str, str]:
    """The environment of a sweep: Ray's session files under ``root`` (not ``/tmp/ray``, which another
    sweep on this machine may be using)."""
    directory = root / "ray-tmp"
    directory.mkdir(parents=True, exist_ok=True)
    return {**os.environ, "RAY_TMPDIR": str(directory)}


def measure_direct(command: list[str], output_dir: Path, cell: Cell,
                   env: dict[str, str] | None = None) -> dict[str, Any]:
    done = Launched(command, output_dir.with_suffix(".log"), {**os.environ, **env} if env else None).finish()
    summary = json.loads((output_dir / cell.run_name / "summary.json").read_text()) if done.code == 0 else {}
    return {"how": "direct+env" if env else "direct", "code": done.code, "wall_s": done.wall_s, "cpu_s": done.cpu_s,
            "rusage_cpu_s": done.rusage_cpu_s, "cgroup": done.cgroup, "train_s": summary.get("Time/Total"),
            "reap": done.reap}


def measure_sweep(command: list[str], grid: SweepGrid, cell: Cell, root: Path) -> dict[str, Any]:
    done = Launched(command, grid.output_dir.with_suffix(".log"), ray_environment(root), sample=True).finish()
    directory = grid.cell_dir(cell)
    attempts = AttemptLog(directory).read()
    row: dict[str, Any] = {"how": "sweep", "code": done.code, "wall_s": done.wall_s, "cpu_s": done.cpu_s,
                           "rusage_cpu_s": done.rusage_cpu_s, "cgroup": done.cgroup, "reap": done.reap,
                           "sampled_cpu_s": done.sampled, "attempts": len(attempts)}
    if done.code != 0 or len(attempts) != 1:
        return row
    attempt = attempts[0]
    summary = json.loads((directory / "summary.json").read_text())
    # The forced status line the driver prints once the last cell is collected, before ray.shutdown.
    last_status = max((t for t, text in done.lines if text.startswith("[sweep ")), default=attempt["end"])
    ray_sampled = sum(cpu for name, cpu in done.sampled.items() if name != "sg-train")
    row.update(train_s=summary.get("Time/Total"), child_wall_s=attempt["wall_s"], child_cpu_s=attempt["cpu_s"],
               startup_s=attempt["start"] - done.start, after_s=done.end - attempt["end"],
               shutdown_report_s=done.end - last_status,
               outside_child_cpu_s=done.cpu_s - attempt["cpu_s"], ray_sampled_cpu_s=ray_sampled,
               # Did a count include Ray's processes, not only the driver? It must cover the child plus what
               # sampling saw the others use (a lower bound of theirs).
               rusage_counts_ray=done.rusage_cpu_s >= attempt["cpu_s"] + ray_sampled,
               cgroup_counts_ray=done.cgroup and done.cpu_s >= attempt["cpu_s"] + ray_sampled)
    return row


def _median(rows: list[dict], key: str) -> float:
    values = [row[key] for row in rows if row.get(key) is not None]
    return statistics.median(values) if values else float("nan")


def summarise(rows: list[dict]) -> dict[str, Any]:
    """Medians per kind of run; each other kind's difference and ratio to ``direct``; the sweep's breakdown."""
    kinds = {how: [r for r in rows if r["how"] == how and r["code"] == 0]
             for how in dict.fromkeys(r["how"] for r in rows)}
    sweep = kinds.get("sweep", [])
    out: dict[str, Any] = {"how": "summary (medians)", "repeats_ok": {how: len(group) for how, group in kinds.items()}}
    for key in ("wall_s", "cpu_s", "rusage_cpu_s", "train_s"):
        out[key] = {how: _median(group, key) for how, group in kinds.items()}
        base = out[key].get("direct", float("nan"))
        for how in kinds:
            if how != "direct":
                out[key][f"{how} - direct"] = out[key][how] - base
                out[key][f"{how} / direct"] = out[key][how] / base
    for key in ("startup_s", "child_wall_s", "after_s", "shutdown_report_s", "child_cpu_s", "outside_child_cpu_s",
                "ray_sampled_cpu_s"):
        out[key] = _median(sweep, key)
    roles = sorted({name for r in sweep for name in r.get("sampled_cpu_s", {})})
    out["sampled_cpu_s_by_role"] = {name: statistics.median(r["sampled_cpu_s"].get(name, 0.0) for r in sweep)
                                    for name in roles}
    out["rusage_counts_ray"] = all(r.get("rusage_counts_ray") for r in sweep)
    out["cgroup_counts_ray"] = all(r.get("cgroup_counts_ray") for r in sweep)
    return out


def markdown(rows: list[dict], summary: dict[str, Any], labels: dict[str, str]) -> str:
    def num(value: Any) -> str:
        return "" if value is None else f"{value:.1f}"

    lines = ["| run | wall s | CPU s (cgroup) | CPU s (RUSAGE_CHILDREN) | sg-train child wall s / CPU s "
             "| Ray startup s | after the child s | CPU s outside sg-train (sampled Ray processes) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        child = (f"{num(row.get('child_wall_s'))} / {num(row.get('child_cpu_s'))}" if row["how"] == "sweep"
                 else f"{num(row['wall_s'])} / {num(row['cpu_s'])}")
        outside = (f"{num(row.get('outside_child_cpu_s'))} ({num(row.get('ray_sampled_cpu_s'))})"
                   if row["how"] == "sweep" else "")
        failed = "" if row["code"] == 0 else f" (exit {row['code']})"
        lines.append(f"| {row['how']} #{row['repeat']}{failed} | {num(row['wall_s'])} | {num(row['cpu_s'])} "
                     f"| {num(row['rusage_cpu_s'])} | {child} "
                     f"| {num(row.get('startup_s'))} | {num(row.get('after_s'))} | {outside} |")
    others = [how for how in summary["repeats_ok"] if how != "direct"]
    lines += ["", "| median | " + " | ".join(labels[how] for how in ["direct", *others]) + " | "
              + " | ".join(f"{how} - direct | {how} / direct" for how in others) + " |",
              "|---|" + "---:|" * (1 + 3 * len(others))]
    for key, name in (("wall_s", "wall s"), ("cpu_s", "CPU s"), ("rusage_cpu_s", "CPU s, RUSAGE_CHILDREN only"),
                      ("train_s", "sg-train's Time/Total s")):
        figures = summary[key]
        lines.append(f"| {name} | " + " | ".join(f"{figures[how]:.1f}" for how in ["direct", *others]) + " | "
                     + " | ".join(f"{figures[f'{how} - direct']:+.1f} | {figures[f'{how} / direct']:.2f}x"
                                  for how in others) + " |")
    if "sweep" in others:
        lines += ["", f"Sweep wall time (medians): Ray startup {summary['startup_s']:.1f} s, sg-train child "
                  f"{summary['child_wall_s']:.1f} s, after the child {summary['after_s']:.1f} s (of which "
                  f"ray.shutdown + report {summary['shutdown_report_s']:.1f} s). CPU outside the child "
                  f"{summary['outside_child_cpu_s']:.1f} s; sampled by role: "
                  + ", ".join(f"{k} {v:.1f}" for k, v in summary["sampled_cpu_s_by_role"].items())
                  + " s. Covered the child plus the sampled Ray processes in every sweep run: the cgroup "
                  f"{summary['cgroup_counts_ray']}, RUSAGE_CHILDREN (subreaper, all reaped) "
                  f"{summary['rusage_counts_ray']}."]
    return "\n".join(lines)


def cell_parser(description: str, total_steps: int) -> argparse.ArgumentParser:
    """A benchmark's command line with the cell's flags: algorithm, env id, seeds and env steps per seed."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", default="ppo_lag")
    parser.add_argument("--env-id", default="SafetyPointGoal1-v0")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--total-steps", type=int, default=total_steps,
                        help=f"env steps per seed (default {total_steps:,})")
    return parser


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = cell_parser(__doc__, 20_000)
    parser.add_argument("--repeats", type=int, default=3, help="runs of each kind, interleaved (default 3)")
    parser.add_argument("--kinds", nargs="+", choices=KINDS, default=["direct", "sweep"],
                        help="which runs (default: direct sweep); direct+env: sg-train directly with --direct-env")
    parser.add_argument("--direct-env", nargs="+", default=["OMP_NUM_THREADS=1"], metavar="KEY=VALUE",
                        help="the environment of the direct+env runs (default OMP_NUM_THREADS=1, which Ray sets for a "
                             "task of one CPU and so for the sweep's sg-train child)")
    parser.add_argument("--workdir", default=None, help="where the runs go (default: a temporary folder, removed)")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    parser.add_argument("extra", nargs="*", help="sg-train flags for both runs, after -- (default --wandb disabled)")
    args = parser.parse_args(argv)
    extra = args.extra or list(DEFAULT_EXTRA)
    if "direct" not in args.kinds:
        parser.error("--kinds must include direct (the baseline)")
    direct_env = dict(item.split("=", 1) for item in args.direct_env)
    labels = {"direct": "direct sg-train", "sweep": "sg-sweep (local Ray, 1 CPU)",
              "direct+env": "direct sg-train, " + " ".join(args.direct_env)}
    become_subreaper()
    root = Path(args.workdir or tempfile.mkdtemp(prefix="sgb-", dir="/tmp")).resolve()
    root.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        for repeat in range(args.repeats):
            shift = repeat % len(args.kinds)
            for how in args.kinds[shift:] + args.kinds[:shift]:  # the order rotates
                output = root / f"{how}-{repeat}"
                command = sweep_command(args.algo, args.env_id, args.seeds, args.total_steps, output, extra)
                grid, cell = sweep_cell(command)
                if how != "sweep":
                    train = [sys.executable, "-m", "sg_torchrl.train", *grid.train_arguments(cell), "--overwrite",
                             "--progress", "false"]  # what run_cell starts for a fresh cell
                    row = measure_direct(train, output, cell, direct_env if how == "direct+env" else None)
                else:
                    row = measure_sweep(command, grid, cell, root)
                row["repeat"] = repeat
                rows.append(row)
                print(f"{how} #{repeat}: exit {row['code']}, wall {row['wall_s']:.1f} s, CPU {row['cpu_s']:.1f} s",
                      flush=True)
    finally:
        if args.workdir is None:
            shutil.rmtree(root, ignore_errors=True)
    summary = summarise(rows)
    print(f"\n{args.algo} on {args.env_id}, seeds {' '.join(map(str, args.seeds))}, {args.total_steps} env steps per "
          f"seed, sg-train flags {' '.join(extra)}; {args.repeats} repeat(s) each, interleaved\n")
    print(markdown(rows, summary, labels))
    result = {"settings": {"algo": args.algo, "env_id": args.env_id, "seeds": args.seeds,
                           "total_steps": args.total_steps, "repeats": args.repeats, "extra": extra,
                           "kinds": args.kinds, "direct_env": direct_env if "direct+env" in args.kinds else None},
              "runs": rows, "summary": summary}
    if args.json:
        from _report import write_json

        write_json(args.json, [result], threads=1)
    return result


if __name__ == "__main__":
    main()
