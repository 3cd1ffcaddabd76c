"""Env throughput of sg_torchrl's batched MuJoCo envs against raw MuJoCo stepping.

For every env id and batch size ``N`` this measures, in the same process and interleaved:

* **ours**: ``env.step_and_maybe_reset`` in a loop with one fixed, precomputed action tensor
  (no policy), i.e. everything the env does per step: action validation, physics, observation,
  reward, cost, termination, auto-reset and the TensorDict round trip through TorchRL;
* **raw**: the physical limit, a plain Python loop over ``N`` ``mujoco.MjData`` of the env's own
  compiled model (``env.physics.model``) doing ``data.ctrl[:] = a; mujoco.mj_step(model, data,
  frame_skip)`` with the env's frame skip, plus what the env's physics runs after the sub-steps and
  cannot skip: ``mj_forward`` where observations must describe the state the step ended in (the
  navigation tasks, as in Safety-Gymnasium) and ``mj_rnePostConstraint`` for robots whose
  observation reads contact forces (``--raw-step-only`` drops both). The raw simulators start from
  the env's own reset states (joints, mocap bodies such as goals and hazards, time), so both loops
  integrate the same trajectories (the cost of ``mj_step`` depends on the contacts) until the env
  resets an episode (Hopper, Walker2d, Ant and Humanoid terminate, a navigation goal moves when
  reached; the raw loop never resets). Objects the env moves before every sub-step (gremlins)
  stand still in the raw loop, which keeps MuJoCo's single ``mj_step(frame_skip)`` call.

Works for any registered id (navigation, velocity and multi-agent velocity alike: a multi-agent env's
group action is mapped to the robot's actuators for the raw loop; ``benchmarks/multi_agent_throughput.py``
sets the multi-agent envs beside their single-agent robots). ``benchmarks/reset_time.py`` measures
reset times; ``--reset-time`` adds its one-simulator reset median to this table.

Both report env steps per second (``N * steps / seconds``), best of ``--repeats`` runs after a
warm-up, and the table shows their ratio. Timings on a shared 2-core machine are noisy: compare
ratios measured in the same run, not absolute figures across runs.

Usage::

    python benchmarks/env_throughput.py
    python benchmarks/env_throughput.py --ids SafetyAntVelocity-v1 --num-envs 16 --steps 500 --json out.json
    python benchmarks/env_throughput.py --ids SafetyPointGoal1-v0 --num-envs 1 64 --steps 1000 --reset-time
    python benchmarks/env_throughput.py --ids ShadowHandOverSafeJoint-v0 --num-envs 16 64 --physics-threads 1 2
"""

from __future__ import annotations

import argparse
import itertools
import time

import mujoco
import numpy as np
import torch

import sg_torchrl
from _report import write_json

DEFAULT_IDS = ("SafetyPointGoal1-v0", "SafetyCarGoal1-v0", "SafetyRacecarGoal1-v0", "SafetyDoggoGoal1-v0",
               "SafetyAntGoal1-v0", "SafetyPointButton1-v0", "SafetyPointPush1-v0", "SafetyHalfCheetahVelocity-v1",
               "SafetyHopperVelocity-v1", "SafetyAntVelocity-v1")
_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # joints, mocap bodies, time, warm-start: a full restart point


def _fixed_action(env, seed: int) -> torch.Tensor:
    """One in-bounds random action per simulator (per agent for multi-agent envs), drawn once."""
    generator = torch.Generator().manual_seed(seed)
    box = env.full_action_spec[env.action_key].space
    low, high = box.low, box.high
    return low + (high - low) * torch.rand(low.shape, generator=generator)


def _robot_control(env, action: torch.Tensor) -> np.ndarray:
    """The ``(N, nu)`` control the raw loop writes: the action itself, or a multi-agent env's group
    action mapped to the robot's actuators."""
    if hasattr(env, "robot_control"):
        return env.robot_control(action)
    return action.double().numpy()


def time_ours(env, td, action: torch.Tensor, steps: int, warmup: int) -> float:
    """Seconds for ``steps`` calls of ``env.step_and_maybe_reset``, starting from the reset ``td``."""
    key = env.action_key  # ("agents", "action") for multi-agent envs
    for _ in range(warmup):
        td.set(key, action)
        _, td = env.step_and_maybe_reset(td)
    start = time.perf_counter()
    for _ in range(steps):
        td.set(key, action)
        _, td = env.step_and_maybe_reset(td)
    return time.perf_counter() - start


def start_states(env) -> np.ndarray:
    """Every simulator's state as MuJoCo saves it (``mjSTATE_INTEGRATION``), ``(N, nstate)``."""
    model = env.physics.model
    states = np.empty((env.num_envs, mujoco.mj_stateSize(model, _STATE)))
    for row, data in zip(states, env.physics.datas):
        mujoco.mj_getState(model, data, row, _STATE)
    return states


def time_raw(model: mujoco.MjModel, start: np.ndarray, action: np.ndarray, frame_skip: int,
             post_constraint: bool, steps: int, warmup: int, forward: bool = False) -> float:
    """Seconds for ``steps`` rounds of stepping ``N`` bare ``MjData`` (no env around them) from ``start``."""
    datas = [mujoco.MjData(model) for _ in range(len(action))]
    for data, state in zip(datas, start):
        mujoco.mj_setState(model, data, state, _STATE)
        mujoco.mj_forward(model, data)

    def run(n: int) -> None:
        for _ in range(n):
            for data, row in zip(datas, action):
                data.ctrl[:] = row
                mujoco.mj_step(model, data, frame_skip)
                if forward:
                    mujoco.mj_forward(model, data)
                if post_constraint:
                    mujoco.mj_rnePostConstraint(model, data)

    run(warmup)
    start = time.perf_counter()
    run(steps)
    return time.perf_counter() - start


def measure(env_id: str, num_envs: int, steps: int, repeats: int, warmup: int, seed: int,
            raw_step_only: bool = False, reset_time: bool = False, physics_threads: int = 1) -> dict:
    env = sg_torchrl.make(env_id, num_envs=num_envs, seed=seed, physics_threads=physics_threads)
    action = _fixed_action(env, seed)
    raw_action = _robot_control(env, action)
    physics = env.physics  # the env's own compiled model and post-step work
    post = physics.post_constraint and not raw_step_only
    forward = physics.forward_after_step and not raw_step_only
    ours, raw = [], []
    for _ in range(repeats):  # interleaved, so machine-load drift hits both alike
        td = env.reset()
        start = start_states(env)
        ours.append(time_ours(env, td, action, steps, warmup))
        raw.append(time_raw(physics.model, start, raw_action, env.frame_skip, post, steps, warmup, forward))
    ours_rate = num_envs * steps / min(ours)
    raw_rate = num_envs * steps / min(raw)
    row = {
        "env_id": env_id, "num_envs": num_envs, "physics_threads": physics_threads, "steps": steps, "repeats": repeats,
        "ours_steps_per_s": ours_rate, "raw_steps_per_s": raw_rate, "ratio": ours_rate / raw_rate,
        "raw_includes": [name for name, on in (("mj_forward", forward), ("mj_rnePostConstraint", post)) if on],
        "physics_errors": env.physics_errors,
    }
    if reset_time:
        from reset_time import time_partial_resets

        row["reset_one_sim_median_ms"] = float(np.median(time_partial_resets(env, 200, 10)) * 1e3)
    env.close()
    return row


def markdown_table(rows: list[dict]) -> str:
    resets = any("reset_one_sim_median_ms" in row for row in rows)
    lines = [
        "| env id | N | physics threads | ours (env steps/s) | raw MuJoCo, 1 thread (env steps/s) | ours / raw |"
        + (" reset 1 sim, median (ms) |" if resets else ""),
        "|---|---:|---:|---:|---:|---:|" + ("---:|" if resets else ""),
    ]
    for row in rows:
        reset = ""
        if resets:
            value = row.get("reset_one_sim_median_ms")
            reset = " |" if value is None else f" {value:.3f} |"
        lines.append(
            f"| {row['env_id']} | {row['num_envs']} | {row['physics_threads']} | {row['ours_steps_per_s']:,.0f} | "
            f"{row['raw_steps_per_s']:,.0f} | {row['ratio']:.0%} |" + reset
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ids", nargs="+", default=list(DEFAULT_IDS), help="env ids to measure")
    parser.add_argument("--num-envs", nargs="+", type=int, default=[1, 16, 64], help="batch sizes N")
    parser.add_argument("--steps", type=int, default=200, help="timed env.step calls per repeat")
    parser.add_argument("--repeats", type=int, default=3, help="runs per measurement; the best counts")
    parser.add_argument("--warmup", type=int, default=20, help="untimed steps before each run")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    parser.add_argument("--physics-threads", nargs="+", type=int, default=[1],
                        help="the envs' physics_threads to measure (the raw loop always runs on one thread)")
    parser.add_argument("--raw-step-only", action="store_true",
                        help="raw loop: mj_step only (no mj_forward / mj_rnePostConstraint the env runs)")
    parser.add_argument("--reset-time", action="store_true",
                        help="also time resets of one simulator (median ms, see benchmarks/reset_time.py)")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    rows = []
    for env_id, num_envs, physics_threads in itertools.product(args.ids, args.num_envs, args.physics_threads):
        row = measure(env_id, num_envs, args.steps, args.repeats, args.warmup, args.seed,
                      raw_step_only=args.raw_step_only, reset_time=args.reset_time, physics_threads=physics_threads)
        rows.append(row)
        print(f"{env_id} N={num_envs} physics_threads={physics_threads}: ours {row['ours_steps_per_s']:,.0f}/s, "
              f"raw {row['raw_steps_per_s']:,.0f}/s ({row['ratio']:.0%})", flush=True)
    print()
    print(markdown_table(rows))
    if args.json:
        write_json(args.json, rows, threads=args.threads)
    return rows


if __name__ == "__main__":
    main()
