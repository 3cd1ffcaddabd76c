"""sg-sweep on a real two-node Ray cluster: cells spread over the nodes, the report's table, a finished sweep
skipped, and a cell whose Ray worker (or whose sg-train) is SIGKILLed ending bit-identical to an uninterrupted one.

The cluster is started here with the ``ray`` CLI, as a user would start one, on 127.0.0.1: a head node and a
worker node with one CPU each (so two cells run on two nodes), their own ``--temp-dir``, their own ports and
their own authentication token. The test stops exactly the two ``ray start --block`` process groups it started
(never ``ray stop``, which stops every Ray instance of the machine, other users' included).

Cells are tiny (two seeds, 2 envs, 200 env steps per epoch, 100-step episodes, a checkpoint every epoch);
``sg-train --resume`` continues bit-identically, so an interrupted cell must end with the same numbers.
"""

from __future__ import annotations

import contextlib
import importlib.util
import csv
import io
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from sg_torchrl.sweep import cli
from sg_torchrl.sweep.grid import Cell, SweepGrid
from sg_torchrl.sweep.records import AttemptLog, epochs_logged
from sg_torchrl.sweep.runner import run_sweep

ENV = "SafetyPointGoal1-v0"
SEEDS = (0, 1)
TOTAL_STEPS = 3000  # 15 epochs of 200 env steps per seed
CELL_OPTIONS = ("--num-envs", "2", "--steps-per-epoch", "200", "--update-iters", "2", "--eval-episodes", "1",
                "--checkpoint-every", "1", "--checkpoint-minutes", "0", "--wandb", "disabled",
                "--env-options", "max_episode_steps=100")
#: Epochs a cell has logged (and checkpointed) before a test kills it.
KILL_AFTER_EPOCHS = 3
#: Ports of its own each node listens on besides the head's GCS and client server (see :func:`_node_ports`).
NODE_PORTS = 6


# --- the cluster ----------------------------------------------------------------------------------------------


@dataclass
class RayCluster:
    """A running two-node cluster: the address a driver joins and each node's Ray node id."""

    address: str
    head_id: str
    worker_id: str


def _free_ports(count: int) -> list[int]:
    """``count`` distinct TCP ports free on 127.0.0.1 right now."""
    sockets = [socket.socket() for _ in range(count)]
    try:
        for sock in sockets:
            sock.bind(("127.0.0.1", 0))
        return [sock.getsockname()[1] for sock in sockets]
    finally:
        for sock in sockets:
            sock.close()


def _node_ports(ports: list[int]) -> list[str]:
    """``ray start`` flags giving a node ports of its own: two nodes on one machine (and any other Ray
    instance there) must not share the fixed defaults (the dashboard agent's 52365, for one). Its workers
    take ports the system picks (0) rather than the default range 10002-19999 another instance also draws from.

    ``ports``: :data:`NODE_PORTS` free ports."""
    flags = ("--node-manager-port", "--object-manager-port", "--dashboard-agent-listen-port",
             "--dashboard-agent-grpc-port", "--metrics-export-port", "--runtime-env-agent-port")
    assert len(ports) == NODE_PORTS == len(flags)
    return [text for flag, port in zip(flags, ports) for text in (flag, str(port))] + [
        "--min-worker-port", "0", "--max-worker-port", "0"]


def _start_node(arguments: list[str], log: Path, env: dict[str, str]) -> subprocess.Popen:
    """``ray start --block ...`` in a process group of its own (so that stopping it reaches all it started)."""
    command = [str(Path(sys.executable).with_name("ray")), "start", "--block", "--node-ip-address", "127.0.0.1",
               "--num-cpus", "1", "--disable-usage-stats", *arguments]
    with open(log, "wb") as handle:
        return subprocess.Popen(command, env=env, stdout=handle, stderr=subprocess.STDOUT, start_new_session=True)


def _wait_for_log(process: subprocess.Popen, log: Path, text: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while text not in log.read_text(errors="replace"):
        if process.poll() is not None or time.monotonic() > deadline:
            tail = "\n".join(log.read_text(errors="replace").splitlines()[-20:])
            state = "timed out" if process.poll() is None else f"exited {process.returncode}"
            pytest.fail(f"ray start did not come up ({state}):\n{tail}")
        time.sleep(0.5)


def _stop_node(process: subprocess.Popen) -> None:
    """SIGTERM the node's process group (``ray start --block`` stops what it started), SIGKILL it if it lingers."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGTERM)
    try:
        process.wait(timeout=45)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
        process.wait(timeout=30)


def _reload_ray_auth() -> None:
    """Make this process's Ray client read ``RAY_AUTH_MODE`` / ``RAY_AUTH_TOKEN`` again: Ray caches both per
    process, and an earlier Ray user in this process may have cached others."""
    from ray._raylet import AuthenticationTokenLoader, Config

    Config.initialize("")
    AuthenticationTokenLoader.instance().reset_cache()


@pytest.fixture(scope="module")
def ray_cluster():
    """A head node and a worker node on 127.0.0.1 (one CPU each), token-authenticated; stopped afterwards."""
    ray = pytest.importorskip("ray")
    temp_dir = Path(tempfile.mkdtemp(prefix="sgray-", dir="/tmp"))  # Unix socket paths must stay under 108 chars
    token = secrets.token_hex(32)
    auth = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token}
    env = {key: value for key, value in os.environ.items() if key not in ("RAY_ADDRESS", "RAY_AUTH_TOKEN_PATH")}
    env.update(auth, RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S="0")  # stopping a node: no 30 s wait for its tasks
    gcs_port, client_port, *ports = _free_ports(2 + 2 * NODE_PORTS)
    address = f"127.0.0.1:{gcs_port}"
    nodes = []
    with pytest.MonkeyPatch.context() as patch:
        for key, value in auth.items():
            patch.setenv(key, value)
        patch.delenv("RAY_ADDRESS", raising=False)
        try:
            head_ports, worker_ports = _node_ports(ports[:NODE_PORTS]), _node_ports(ports[NODE_PORTS:])
            # Ray's client server exists only where ray[client] (grpcio) is installed; there it would take the
            # fixed default port 10001, so it gets a free one. Without grpcio, `ray start` refuses the option.
            client = ["--ray-client-server-port", str(client_port)] if importlib.util.find_spec("grpc") else []
            nodes.append(_start_node(["--head", "--port", str(gcs_port), "--include-dashboard", "false", *client,
                                      "--temp-dir", str(temp_dir), *head_ports], temp_dir / "head.log", env))
            _wait_for_log(nodes[0], temp_dir / "head.log", "Ray runtime started", timeout=180)
            nodes.append(_start_node(["--address", address, "--temp-dir", str(temp_dir), *worker_ports],
                                     temp_dir / "worker.log", env))
            _wait_for_log(nodes[1], temp_dir / "worker.log", "Ray runtime started", timeout=180)
            _reload_ray_auth()
            ray.init(address=address, logging_level="warning", log_to_driver=False)
            try:
                deadline = time.monotonic() + 60
                while len(alive := [node for node in ray.nodes() if node["Alive"]]) < 2:
                    assert time.monotonic() < deadline, f"the worker node did not join: {alive}"
                    time.sleep(0.5)
                by_port = {str(node["NodeManagerPort"]): node["NodeID"] for node in alive}
            finally:
                ray.shutdown()
            port = "--node-manager-port"
            yield RayCluster(address, by_port[head_ports[head_ports.index(port) + 1]],
                             by_port[worker_ports[worker_ports.index(port) + 1]])
        finally:
            for node in reversed(nodes):  # the worker first, while the head it reports to is still up
                _stop_node(node)
            shutil.rmtree(temp_dir, ignore_errors=True)
    _reload_ray_auth()


# --- sweeps on it ---------------------------------------------------------------------------------------------


def tiny_grid(output_dir: Path, algos: tuple[str, ...]) -> SweepGrid:
    return SweepGrid(algos=algos, env_ids=(ENV,), seed_groups=(SEEDS,), total_steps=TOTAL_STEPS,
                     output_dir=output_dir, extra=CELL_OPTIONS)


def sweep_arguments(grid: SweepGrid, address: str) -> list[str]:
    """The ``sg-sweep`` command line of ``grid`` joining ``address``."""
    return ["--algos", *grid.algos, "--envs", *grid.env_ids, "--seeds", *map(str, SEEDS),
            "--total-steps", str(grid.total_steps), "--output-dir", str(grid.output_dir), "--address", address,
            "--progress-every", "5", "--", *grid.extra]


@dataclass
class FinishedSweep:
    grid: SweepGrid
    code: int
    output: str


@pytest.fixture(scope="module")
def finished_sweep(ray_cluster, tmp_path_factory):
    """PPO and PPO-Lag cells run to the end by ``sg-sweep --address`` on the cluster (both at once, one per node)."""
    grid = tiny_grid(tmp_path_factory.mktemp("sweep") / "out", ("ppo", "ppo_lag"))
    output = io.StringIO()
    with contextlib.redirect_stdout(output), contextlib.redirect_stderr(output):
        code = cli.main(sweep_arguments(grid, ray_cluster.address))
    return FinishedSweep(grid, code, output.getvalue())


def cell_of(grid: SweepGrid, algo: str) -> Cell:
    return next(cell for cell in grid.cells if cell.algo == algo)


def final_results(directory: Path) -> dict:
    """What a cell's training produced, timings aside: its summaries and every seed's progress rows."""
    def untimed(row: dict) -> dict:
        return {key: value for key, value in row.items() if not key.startswith("Time/")}

    results = {"summary": untimed(json.loads((directory / "summary.json").read_text()))}
    for seed in SEEDS:
        seed_dir = directory / f"seed-{seed:03d}"
        results[f"{seed} summary"] = untimed(json.loads((seed_dir / "summary.json").read_text()))
        with open(seed_dir / "progress.csv") as handle:
            results[f"{seed} progress"] = [untimed(row) for row in csv.DictReader(handle)]
    return results


@pytest.mark.timeout(900)
def test_a_sweep_runs_its_cells_on_both_nodes_and_reports_them(ray_cluster, finished_sweep):
    grid = finished_sweep.grid
    assert finished_sweep.code == 0, finished_sweep.output
    assert f"[done] {cell_of(grid, 'ppo').label}" in finished_sweep.output
    nodes = set()
    for cell in grid.cells:
        (attempt,) = AttemptLog(grid.cell_dir(cell)).read()
        assert (attempt["status"], attempt["resumed"], attempt["code"]) == ("done", False, 0)
        nodes.add(attempt["node_id"])
    assert nodes == {ray_cluster.head_id, ray_cluster.worker_id}

    with open(grid.output_dir / "report" / "table.csv") as handle:
        rows = {row["algorithm"]: row for row in csv.DictReader(handle)}
    assert set(rows) == {"PPO", "PPO-Lag"}
    expected = {}
    for cell in grid.cells:
        seeds = json.loads((grid.cell_dir(cell) / "summary.json").read_text())["seeds"]
        expected[cell.algo] = [sum(figures[key] for figures in seeds.values()) / len(seeds)
                               for key in ("Final/EpRetLast10", "Final/EpCostLast10")]
    for algo, name in (("ppo", "PPO"), ("ppo_lag", "PPO-Lag")):
        row = rows[name]
        assert (int(row["seeds"]), int(row["budget"]), int(row["attempts"])) == (len(SEEDS), TOTAL_STEPS, 1)
        assert [float(row["J^R"]), float(row["J^C"])] == pytest.approx(expected[algo], rel=1e-12)
    assert float(rows["PPO-Lag"]["J^R / base"]) == pytest.approx(expected["ppo_lag"][0] / expected["ppo"][0],
                                                                 rel=1e-12)
    assert float(rows["PPO"]["J^R / base"]) == pytest.approx(1.0)


@pytest.mark.timeout(300)
def test_running_a_finished_sweep_again_skips_every_cell(ray_cluster, finished_sweep):
    grid = finished_sweep.grid
    before = {cell: (grid.cell_dir(cell) / "attempts.jsonl").read_bytes() for cell in grid.cells}
    lines: list[str] = []
    outcome = run_sweep(tiny_grid(grid.output_dir, grid.algos), address=ray_cluster.address, out=lines.append)
    assert outcome.skipped == list(grid.cells) and not outcome.finished and outcome.ok
    assert all(line.startswith("[skip]") for line in lines), lines
    assert {cell: (grid.cell_dir(cell) / "attempts.jsonl").read_bytes() for cell in grid.cells} == before


@pytest.mark.timeout(300)
def test_a_driver_without_the_clusters_token_is_told_how_to_give_it(ray_cluster, tmp_path):
    without_token = {key: value for key, value in os.environ.items() if not key.startswith("RAY_AUTH")}
    without_token["RAY_gcs_server_port_wait_time_s"] = "2"  # tries to connect twice, not for 20 s
    grid = tiny_grid(tmp_path / "out", ("ppo",))
    result = subprocess.run([sys.executable, "-m", "sg_torchrl.sweep", *sweep_arguments(grid, ray_cluster.address)],
                            env=without_token, capture_output=True, text=True, timeout=240)
    assert result.returncode == 2, result.stderr[-3000:]
    assert "refused this driver's authentication token" in result.stderr, result.stderr[-3000:]
    assert "RAY_AUTH_MODE=token" in result.stderr and "Traceback" not in result.stderr
    assert not grid.cell_dir(grid.cells[0]).exists()


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid``."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError):
                stat = (entry / "stat").read_text()
                if int(stat[stat.rindex(")") + 2:].split()[1]) == pid:
                    found.append(int(entry.name))
    return found


def _kill_when_trained(directory: Path, victim: str, record: dict, timeout: float = 300) -> None:
    """Once attempt 1 of the cell in ``directory`` has logged :data:`KILL_AFTER_EPOCHS` epochs, SIGKILL its Ray
    worker (``victim="worker"``) or the worker's sg-train child (``"sg-train"``); ``record`` gets what was killed."""
    attempts = AttemptLog(directory)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        logged = attempts.read()
        if len(logged) == 1 and logged[0]["status"] == "running":
            epochs = epochs_logged(directory, list(SEEDS))
            if epochs >= KILL_AFTER_EPOCHS:
                worker = logged[0]["pid"]
                targets = [worker] if victim == "worker" else _children(worker)
                record.update(epochs=epochs, worker=worker, targets=targets)
                for pid in targets:
                    os.kill(pid, signal.SIGKILL)
                return
        elif logged and logged[0]["status"] != "running":
            break
        time.sleep(0.1)
    record["missed"] = attempts.read()


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.parametrize("victim, first_status", [("worker", "lost"), ("sg-train", "killed")])
def test_a_cell_whose_process_is_killed_is_retried_and_ends_as_if_never_interrupted(
        ray_cluster, finished_sweep, tmp_path, victim, first_status):
    grid = tiny_grid(tmp_path / "out", ("ppo_lag",))
    (cell,) = grid.cells
    directory = grid.cell_dir(cell)
    killed: dict = {}
    watcher = threading.Thread(target=_kill_when_trained, args=(directory, victim, killed), daemon=True)
    watcher.start()
    lines: list[str] = []
    outcome = run_sweep(grid, address=ray_cluster.address, progress_every=5, out=lines.append)
    watcher.join(timeout=10)
    assert "missed" not in killed and killed.get("targets"), f"nothing was killed: {killed}\n" + "\n".join(lines)
    assert outcome.finished == [cell] and outcome.ok, "\n".join(lines)
    assert any(line.startswith(f"[restart] {cell.label}") for line in lines), lines

    first, second = AttemptLog(directory).read()
    assert (first["status"], first["pid"]) == (first_status, killed["worker"])
    assert (second["status"], second["resumed"]) == ("done", True)
    # the retry went on from a checkpoint of at least the epochs logged at the kill: an orphaned sg-train (its
    # worker killed) finished the epoch under way and checkpointed it; a killed one had checkpointed each epoch
    assert second["epochs_before"] >= killed["epochs"] - (victim == "sg-train")
    if victim == "worker":
        assert second["pid"] != killed["worker"]
    assert final_results(directory) == final_results(finished_sweep.grid.cell_dir(cell_of(finished_sweep.grid,
                                                                                            "ppo_lag")))


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_a_stopped_sweep_checkpoints_its_cell_and_the_same_command_finishes_it(ray_cluster, finished_sweep, tmp_path):
    """``sg-sweep`` stopped with SIGTERM (a cluster scheduler's stop; Ctrl-C is the same path) cancels its cell's
    task, which has ``sg-train`` finish the epoch under way, checkpoint and exit; running it again continues."""
    grid = tiny_grid(tmp_path / "out", ("ppo_lag",))
    (cell,) = grid.cells
    directory = grid.cell_dir(cell)
    log = tmp_path / "sg-sweep.log"
    with open(log, "wb") as handle:
        sweep = subprocess.Popen([sys.executable, "-m", "sg_torchrl.sweep",
                                  *sweep_arguments(grid, ray_cluster.address)], stdout=handle, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 300
        while epochs_logged(directory, list(SEEDS)) < KILL_AFTER_EPOCHS:
            assert sweep.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
            time.sleep(0.1)
        stopped_at = epochs_logged(directory, list(SEEDS))
        sweep.send_signal(signal.SIGTERM)
        sweep.wait(timeout=300)
    finally:
        if sweep.poll() is None:
            sweep.kill()
            sweep.wait()
    output = log.read_text()
    assert sweep.returncode == 130, output[-3000:]
    assert "the same command continues the sweep" in output
    (attempt,) = AttemptLog(directory).read()
    assert (attempt["status"], attempt["code"]) == ("interrupted", 128 + signal.SIGINT), output[-3000:]
    assert not (directory / "summary.json").exists()

    outcome = run_sweep(tiny_grid(grid.output_dir, grid.algos), address=ray_cluster.address, out=lambda line: None)
    assert outcome.finished == [cell] and outcome.ok
    first, second = AttemptLog(directory).read()
    assert (second["status"], second["resumed"]) == ("done", True) and second["epochs_before"] >= stopped_at
    assert final_results(directory) == final_results(finished_sweep.grid.cell_dir(cell_of(finished_sweep.grid,
                                                                                            "ppo_lag")))


def test_a_cell_task_takes_rays_cancel_where_sigint_is_ignored():
    """A sweep started in the background (``sg-sweep ... &``, ``nohup``) ignores SIGINT, and so do the local Ray
    workers it starts. Ray cancels a running task with a simulated SIGINT (``_thread.interrupt_main``), which
    does nothing where SIGINT is ignored, so the sweep's stop never reached its cells; the cell task takes SIGINT
    back first (``accept_cancel``)."""
    script = "\n".join([
        "import _thread, signal, time",
        "from sg_torchrl.sweep.cell import accept_cancel",
        "signal.signal(signal.SIGINT, signal.SIG_IGN)",
        "_thread.interrupt_main()",  # ignored, as Ray's cancel was
        "time.sleep(0.2)",
        "accept_cancel()",
        "try:",
        "    _thread.interrupt_main()",
        "    time.sleep(10)",
        "    print('not cancelled')",
        "except KeyboardInterrupt:",
        "    print('cancelled')",
    ])
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert (result.returncode, result.stdout.strip()) == (0, "cancelled"), result.stderr[-2000:]
