"""Three ways to step N simulators of one model on several CPU threads, on the bare physics.

For every env id and batch size ``N``, from the env's own reset states and with one fixed random
control, this times ``--steps`` env steps (``frame_skip`` calls of ``mj_step`` each, nothing else:
no ``mj_forward``, no observation) three ways, interleaved in one process:

* **serial**: a Python loop over ``N`` ``MjData`` (``env_throughput.py``'s raw loop);
* **MujocoBatch, k threads**: :class:`sg_torchrl.envs.physics.MujocoBatch` with ``threads=k``, what
  ``physics_threads=k`` gives an env: each thread steps a fixed slice of the simulators in place
  (MuJoCo's bindings release the GIL inside ``mj_step``);
* **mujoco.rollout, k threads**: MuJoCo's own C++ thread pool (``mujoco.rollout.Rollout(nthread=k)``)
  used as a stepping engine: each env step rolls every simulator ``frame_skip`` steps from the
  previous step's state array (``mjSTATE_FULLPHYSICS``) and keeps the last state.

The question it answers ("threads through mujoco.rollout where it pays"): how much do
threads buy for heavy (two Shadow Hands) and light (Point, HalfCheetah) models, and does
``mujoco.rollout`` beat plain threads over the env's own ``MjData``. Rates are env steps per second,
best of ``--repeats``; on a shared machine compare columns of one run only.

Usage::

    python benchmarks/threaded_stepping.py
    python benchmarks/threaded_stepping.py --ids ShadowHandOverSafeJoint-v0 --num-envs 16 64 --threads 2 4
"""

from __future__ import annotations

import argparse
import itertools
import time

import mujoco
import numpy as np
import torch
from mujoco import rollout

import sg_torchrl
from _report import write_json
from env_throughput import _fixed_action, _robot_control, start_states, time_raw
from sg_torchrl.envs.physics import MujocoBatch

DEFAULT_IDS = ("ShadowHandOverSafeJoint-v0", "SafetyAntGoal1-v0", "SafetyHalfCheetahVelocity-v1", "SafetyPointGoal1-v0")
_INTEGRATION = mujoco.mjtState.mjSTATE_INTEGRATION
_FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS


def time_batch(model: mujoco.MjModel, start: np.ndarray, ctrl: np.ndarray, frame_skip: int, threads: int,
               steps: int, warmup: int) -> float:
    """Seconds for ``steps`` calls of ``MujocoBatch(threads=threads).step`` from ``start``."""
    batch = MujocoBatch(model, len(ctrl), threads=threads)
    for data, state in zip(batch.datas, start):
        mujoco.mj_setState(model, data, state, _INTEGRATION)
    try:
        for _ in range(warmup):
            batch.step(ctrl, frame_skip)
        begin = time.perf_counter()
        for _ in range(steps):
            batch.step(ctrl, frame_skip)
        return time.perf_counter() - begin
    finally:
        batch.close()


def time_rollout(model: mujoco.MjModel, start: np.ndarray, ctrl: np.ndarray, frame_skip: int, threads: int,
                 steps: int, warmup: int) -> float:
    """Seconds for ``steps`` env steps through ``mujoco.rollout`` (state array in, last state out)."""
    datas = [mujoco.MjData(model) for _ in range(threads)]
    state = np.empty((len(ctrl), mujoco.mj_stateSize(model, _FULL)))
    scratch = mujoco.MjData(model)
    for row, source in zip(state, start):
        mujoco.mj_setState(model, scratch, source, _INTEGRATION)
        mujoco.mj_getState(model, scratch, row, _FULL)
    control = np.repeat(ctrl[:, None, :], frame_skip, axis=1)
    with rollout.Rollout(nthread=threads) as runner:
        def run(n: int, state: np.ndarray) -> np.ndarray:
            for _ in range(n):
                states, _ = runner.rollout(model, datas, state, control, nstep=frame_skip)
                state = states[:, -1]
            return state

        state = run(warmup, state)
        begin = time.perf_counter()
        run(steps, state)
        return time.perf_counter() - begin


def measure(env_id: str, num_envs: int, threads: int, steps: int, repeats: int, warmup: int, seed: int) -> dict:
    env = sg_torchrl.make(env_id, num_envs=num_envs, seed=seed)
    env.reset()
    model, frame_skip = env.physics.model, env.frame_skip
    ctrl = _robot_control(env, _fixed_action(env, seed))
    start = start_states(env)
    env.close()
    times: dict[str, list[float]] = {"serial": [], "batch": [], "rollout": []}
    for _ in range(repeats):  # interleaved, so machine-load drift hits all three alike
        times["serial"].append(time_raw(model, start, ctrl, frame_skip, False, steps, warmup))
        times["batch"].append(time_batch(model, start, ctrl, frame_skip, threads, steps, warmup))
        times["rollout"].append(time_rollout(model, start, ctrl, frame_skip, threads, steps, warmup))
    rates = {name: num_envs * steps / min(values) for name, values in times.items()}
    return {"env_id": env_id, "num_envs": num_envs, "threads": threads, "frame_skip": frame_skip,
            **{f"{name}_steps_per_s": rate for name, rate in rates.items()},
            "batch_speedup": rates["batch"] / rates["serial"], "rollout_speedup": rates["rollout"] / rates["serial"]}


def markdown_table(rows: list[dict]) -> str:
    lines = ["| env id | N | threads | serial (env steps/s) | MujocoBatch threads | mujoco.rollout |",
             "|---|---:|---:|---:|---:|---:|"]
    for row in rows:
        lines.append(f"| {row['env_id']} | {row['num_envs']} | {row['threads']} | {row['serial_steps_per_s']:,.0f} | "
                     f"{row['batch_steps_per_s']:,.0f} ({row['batch_speedup']:.2f}x) | "
                     f"{row['rollout_steps_per_s']:,.0f} ({row['rollout_speedup']:.2f}x) |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ids", nargs="+", default=list(DEFAULT_IDS), help="env ids whose models to step")
    parser.add_argument("--num-envs", nargs="+", type=int, default=[16, 64], help="batch sizes N")
    parser.add_argument("--threads", nargs="+", type=int, default=[2], help="thread counts k")
    parser.add_argument("--steps", type=int, default=100, help="timed env steps per repeat")
    parser.add_argument("--repeats", type=int, default=3, help="runs per measurement; the best counts")
    parser.add_argument("--warmup", type=int, default=10, help="untimed steps before each run")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    for env_id, num_envs, threads in itertools.product(args.ids, args.num_envs, args.threads):
        row = measure(env_id, num_envs, threads, args.steps, args.repeats, args.warmup, args.seed)
        rows.append(row)
        print(f"{env_id} N={num_envs} k={threads}: serial {row['serial_steps_per_s']:,.0f}/s, "
              f"MujocoBatch {row['batch_speedup']:.2f}x, mujoco.rollout {row['rollout_speedup']:.2f}x", flush=True)
    print()
    print(markdown_table(rows))
    if args.json:
        write_json(args.json, rows, threads=1)
    return rows


if __name__ == "__main__":
    main()
