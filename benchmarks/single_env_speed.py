"""Single-env speed: one simulator, random actions, episodes reset as they end.

Where single-env users live (a gymnasium loop, SafePO's single-env scripts, evaluation), the work
around the physics decides the speed, not the physics. For every env id this measures, per CPU
second (``time.process_time``: other jobs on a shared machine do not count), at one simulator:

* **bare**: the floor. A plain loop over one ``mujoco.MjData`` of the env's own compiled model:
  ``data.ctrl[:] = action; mj_step(model, data, frame_skip)``, plus ``mj_forward`` where the env's
  observations describe the state a step ended in (navigation) and ``mj_rnePostConstraint`` where
  they read contact forces (Humanoid), as ``benchmarks/env_throughput.py``'s raw loop. It starts from
  the env's reset state and goes back to it (``mj_setState``) after the very steps at which the
  façade's first timed repeat reset (a time limit, or a fall of Hopper, Walker2d, Ant, Humanoid), so
  both simulate episodes of the same lengths (a fallen robot in contact with the floor steps slower)
  and it pays for resets only what MuJoCo itself pays.
* **bare + driven mocaps** (only for ids whose physics drives mocap bodies, the Button levels'
  gremlins; ``–`` elsewhere): the bare loop, but sub-step by sub-step (``mj_step(model, data)``
  ``frame_skip`` times) writing before each sub-step the mocap positions the env writes there, as
  the env's physics does (``MujocoBatch._step_driven``). The targets come from the env's own
  trajectories (the task's mover objects, ``obj.trajectory`` at ``data.time + k * timestep``, the
  circle centres of the layout the bare loop starts from), computed once before timing, so the loop
  pays for the motion MuJoCo must simulate (the extra ``mj_step`` calls, the moving welds) but not
  for computing the targets. This is the floor for such envs: Safety-Gymnasium moves its gremlins
  the same way, so the plain bare column understates what any implementation has to pay there.
* **façade**: ``sg_torchrl.gym.make(id)``: ``env.step(action)`` with a numpy action, the 6-tuple
  and its info, ``env.reset()`` when an episode ends (what a Safety-Gymnasium user migrates to).
* **torchrl N=1**: ``sg_torchrl.make(id, num_envs=1)`` stepped with ``step_and_maybe_reset`` and a
  new action tensor each step.
* **original** (optional): safety-gymnasium 1.0.0's ``safety_gymnasium.make(id)``, the same loop
  as the façade's, run in a subprocess with the Python of its own virtual environment
  (``--oracle-python``, default ``$SG_ORACLE_PYTHON`` or ``/root/sg_oracle/bin/python``); the
  column is left empty when that interpreter or package is missing. Its navigation resets
  recompile the model, which is part of what its users pay.

Actions are drawn uniformly within the action bounds from a fixed seed (the same sequence for every
column). Each column is timed ``--repeats`` times, interleaved, and the best repeat counts. The
table gives steps per CPU second and each column as a fraction of bare MuJoCo (and the façade as a
fraction of bare + driven mocaps where that column exists); the last column is the façade's speed
over the original's (the targets: façade >= 60% of bare, >= 1.5x the
original). Timings on a shared machine are noisy: compare ratios measured in the same run.

Usage::

    python benchmarks/single_env_speed.py
    python benchmarks/single_env_speed.py --ids SafetyHalfCheetahVelocity-v1 --steps 3000 --json out.json
    python benchmarks/single_env_speed.py --no-oracle
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import time
from typing import Callable

import mujoco
import numpy as np
import torch
from tensordict import TensorDict

import sg_torchrl
import sg_torchrl.gym
from _report import write_json
from env_throughput import start_states

NAVIGATION_IDS = ("SafetyPointGoal1-v0", "SafetyCarGoal1-v0", "SafetyRacecarGoal1-v0", "SafetyDoggoGoal1-v0",
                  "SafetyAntGoal1-v0", "SafetyPointButton1-v0", "SafetyPointPush1-v0")
VELOCITY_IDS = ("SafetyHalfCheetahVelocity-v1", "SafetyHopperVelocity-v1", "SafetySwimmerVelocity-v1",
                "SafetyWalker2dVelocity-v1", "SafetyAntVelocity-v1", "SafetyHumanoidVelocity-v1")
DEFAULT_IDS = NAVIGATION_IDS + VELOCITY_IDS
_STATE = mujoco.mjtState.mjSTATE_INTEGRATION

# Runs in the original's interpreter: the façade's loop on safety_gymnasium.make(id); prints one JSON line.
_ORACLE_SCRIPT = """
import json, sys, time
import numpy as np
import safety_gymnasium
env_id, steps, repeats, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
env = safety_gymnasium.make(env_id)
env.reset(seed=seed)
low, high = env.action_space.low, env.action_space.high
actions = np.random.default_rng(seed).uniform(low, high, size=(steps, *low.shape)).astype(np.float32)
best = float("inf")
for _ in range(repeats):
    start = time.process_time()
    for action in actions:
        _, _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    best = min(best, time.process_time() - start)
print(json.dumps({"steps_per_s": steps / best}))
"""


def random_actions(low: np.ndarray, high: np.ndarray, steps: int, seed: int) -> np.ndarray:
    """``(steps, act_dim)`` float32 actions uniform in ``[low, high]``, the same for every column."""
    return np.random.default_rng(seed).uniform(low, high, size=(steps, len(low))).astype(np.float32)


def bare_simulator(model: mujoco.MjModel, start: np.ndarray) -> tuple[mujoco.MjData, Callable[[], None]]:
    """A fresh ``MjData`` of ``model`` in the state ``start`` (forwarded), and the function that puts it back there
    (the bare loops' reset)."""
    data = mujoco.MjData(model)

    def restart() -> None:
        mujoco.mj_setState(model, data, start, _STATE)
        mujoco.mj_forward(model, data)

    restart()
    return data, restart


def time_bare(physics, start: np.ndarray, actions: np.ndarray, frame_skip: int, resets: np.ndarray) -> float:
    """CPU seconds of the bare loop (module docstring) over ``actions`` from the state ``start``, back to
    ``start`` after each step where ``resets`` (``(steps,)`` bool) is set."""
    model = physics.model
    data, restart = bare_simulator(model, start)
    forward, post = physics.forward_after_step, physics.post_constraint
    ctrl = data.ctrl
    begin = time.process_time()
    for action, reset in zip(actions, resets.tolist()):
        ctrl[:] = action
        mujoco.mj_step(model, data, frame_skip)
        if forward:
            mujoco.mj_forward(model, data)
        if post:
            mujoco.mj_rnePostConstraint(model, data)
        if reset:
            restart()
    return time.process_time() - begin


def mocap_drivers(core) -> list:
    """The mover objects (gremlins) whose mocap bodies ``core``'s physics drives, ``[]`` when none."""
    if not getattr(core.physics, "drives_mocap", False):
        return []
    return [obj for obj in core.task.objects if hasattr(obj, "trajectory") and hasattr(obj, "mocap_ids")]


def driven_targets(core, drivers: list, start: np.ndarray, steps: int) -> list:
    """Per driver, ``(rows of mocap_pos, (steps, frame_skip, K, 3) targets)``: the mocap positions the env
    writes before each sub-step of the first ``steps`` steps of an episode started from ``start``. Computed
    untimed by the env's own ``trajectory`` at the times the env passes it (``data.time`` at the step's
    start plus ``k * timestep``, ``MujocoBatch._mocap_plans``), with the circle centres of the current
    layout, the one ``start`` was taken in: call before the façade steps (its resets move the centres)."""
    model, frame_skip = core.physics.model, core.frame_skip
    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, start, _STATE)
    offsets = np.arange(frame_skip) * model.opt.timestep  # as MujocoBatch._mocap_plans
    plans = []
    for obj in drivers:
        ids = np.asarray(obj.mocap_ids, dtype=np.int64)
        rows = slice(int(ids[0]), int(ids[-1]) + 1) if len(ids) and (np.diff(ids) == 1).all() else ids
        plans.append((rows, np.empty((steps, frame_skip, len(ids), 3))))
    # The clock only (no physics): MuJoCo advances data.time by one timestep per sub-step.
    clock = data.time
    for step in range(steps):
        times = clock + offsets[None]
        for obj, (_, targets) in zip(drivers, plans):
            targets[step] = obj.trajectory(times)[0]
        for _ in range(frame_skip):
            clock += model.opt.timestep
    return plans


def along_episodes(plans: list, resets: np.ndarray) -> list:
    """:func:`driven_targets`' per-episode-step targets laid along the loop's steps: after a step where
    ``resets`` is set the bare loop restarts from ``start`` (the clock too), so the targets start over."""
    since, episode_step = 0, np.empty(len(resets), dtype=np.int64)
    for step, reset in enumerate(resets.tolist()):
        episode_step[step] = since
        since = 0 if reset else since + 1
    return [(rows, np.ascontiguousarray(targets[episode_step])) for rows, targets in plans]


def time_bare_driven(physics, start: np.ndarray, actions: np.ndarray, frame_skip: int, resets: np.ndarray,
                     plans: list) -> float:
    """CPU seconds of the bare + driven mocaps loop (module docstring): :func:`time_bare` one sub-step per
    ``mj_step``, the mocap rows of ``plans`` (:func:`driven_targets`) written before each sub-step."""
    model = physics.model
    data, restart = bare_simulator(model, start)
    forward, post = physics.forward_after_step, physics.post_constraint
    mocap_pos = data.mocap_pos
    ctrl = data.ctrl
    single = len(plans) == 1 and isinstance(plans[0][0], slice)
    driven = mocap_pos[plans[0][0]] if single else None  # a view, as MujocoBatch._step_driven
    begin = time.process_time()
    for step, (action, reset) in enumerate(zip(actions, resets.tolist())):
        ctrl[:] = action
        if single:
            for target in plans[0][1][step]:
                driven[...] = target
                mujoco.mj_step(model, data)
        else:
            for k in range(frame_skip):
                for rows, targets in plans:
                    mocap_pos[rows] = targets[step, k]
                mujoco.mj_step(model, data)
        if forward:
            mujoco.mj_forward(model, data)
        if post:
            mujoco.mj_rnePostConstraint(model, data)
        if reset:
            restart()
    return time.process_time() - begin


def time_facade(env, actions: np.ndarray, resets: np.ndarray | None = None) -> float:
    """CPU seconds of the gymnasium façade's loop over ``actions`` (resetting as episodes end); marks
    in ``resets`` the steps after which it reset."""
    begin = time.process_time()
    for step, action in enumerate(actions):
        _, _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
            if resets is not None:
                resets[step] = True
    return time.process_time() - begin


def time_torchrl(env, td: TensorDict, actions: torch.Tensor) -> tuple[float, TensorDict]:
    """CPU seconds of ``step_and_maybe_reset`` over ``actions`` (``(steps, 1, act_dim)``); returns the last td too."""
    begin = time.process_time()
    for action in actions:
        td.set("action", action)
        _, td = env.step_and_maybe_reset(td)
    return time.process_time() - begin, td


def time_original(oracle_python: str, env_id: str, steps: int, repeats: int, seed: int) -> float | None:
    """Steps per CPU second of safety-gymnasium 1.0.0 (subprocess), or ``None`` when it cannot run."""
    if not oracle_python or not os.path.exists(oracle_python):
        return None
    result = subprocess.run([oracle_python, "-c", _ORACLE_SCRIPT, env_id, str(steps), str(repeats), str(seed)],
                            capture_output=True, text=True, timeout=1800)
    lines = [line for line in result.stdout.splitlines() if line.startswith("{")]
    if result.returncode or not lines:
        print(f"  original unavailable for {env_id}: {result.stderr.strip().splitlines()[-1:]}", flush=True)
        return None
    return float(json.loads(lines[-1])["steps_per_s"])


def measure(env_id: str, steps: int, repeats: int, seed: int, oracle_python: str | None) -> dict:
    facade = sg_torchrl.gym.make(env_id)
    facade.reset(seed=seed)
    single = sg_torchrl.make(env_id, num_envs=1, seed=seed)
    td = single.reset()
    core = facade.torchrl_env
    start = start_states(core)[0]
    actions = random_actions(facade.action_space.low, facade.action_space.high, steps, seed)
    action_tensors = torch.from_numpy(actions).unsqueeze(1)
    drivers = mocap_drivers(core)
    # Targets of the layout start was taken in, per episode step; laid along the loop's steps once the
    # façade's first repeat has told where episodes end.
    episode_plans = driven_targets(core, drivers, start, steps) if drivers else None
    warm = min(steps, 100)
    time_facade(facade, actions[:warm])
    time_torchrl(single, td, action_tensors[:warm])
    bare, driven, ours, torchrl = [], [], [], []
    resets = np.zeros(steps, dtype=bool)
    for repeat in range(repeats):  # interleaved, so machine-load drift hits every column alike
        ours.append(time_facade(facade, actions, resets if repeat == 0 else None))
        bare.append(time_bare(core.physics, start, actions, core.frame_skip, resets))
        if drivers:
            if repeat == 0:
                plans = along_episodes(episode_plans, resets)
            driven.append(time_bare_driven(core.physics, start, actions, core.frame_skip, resets, plans))
        seconds, td = time_torchrl(single, td, action_tensors)
        torchrl.append(seconds)
    facade.close()
    single.close()
    row = {
        "env_id": env_id, "steps": steps, "repeats": repeats, "facade_resets": int(resets.sum()),
        "bare_steps_per_s": steps / min(bare),
        "bare_driven_steps_per_s": steps / min(driven) if driven else None,
        "facade_steps_per_s": steps / min(ours),
        "torchrl_n1_steps_per_s": steps / min(torchrl),
        "original_steps_per_s": time_original(oracle_python, env_id, steps, repeats, seed) if oracle_python else None,
    }
    row["facade_vs_bare"] = row["facade_steps_per_s"] / row["bare_steps_per_s"]
    floor = row["bare_driven_steps_per_s"]
    row["facade_vs_bare_driven"] = None if floor is None else row["facade_steps_per_s"] / floor
    row["torchrl_n1_vs_bare"] = row["torchrl_n1_steps_per_s"] / row["bare_steps_per_s"]
    original = row["original_steps_per_s"]
    row["original_vs_bare"] = None if original is None else original / row["bare_steps_per_s"]
    row["facade_vs_original"] = None if original is None else row["facade_steps_per_s"] / original
    return row


def markdown_table(rows: list[dict]) -> str:
    lines = [
        "| env id | bare MuJoCo (steps/CPU-s) | façade | façade / bare | TorchRL N=1 | TorchRL / bare "
        "| original 1.0.0 | original / bare | façade / original | bare + driven mocaps | façade / bare + driven |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        original = row["original_steps_per_s"]
        extra = ("| – | – | – |" if original is None else
                 f"| {original:,.0f} | {row['original_vs_bare']:.0%} | {row['facade_vs_original']:.2f}x |")
        floor = row["bare_driven_steps_per_s"]
        extra += (" – | – |" if floor is None else f" {floor:,.0f} | {row['facade_vs_bare_driven']:.0%} |")
        lines.append(
            f"| {row['env_id']} | {row['bare_steps_per_s']:,.0f} | {row['facade_steps_per_s']:,.0f} "
            f"| {row['facade_vs_bare']:.0%} | {row['torchrl_n1_steps_per_s']:,.0f} | {row['torchrl_n1_vs_bare']:.0%} "
            + extra
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ids", nargs="+", default=list(DEFAULT_IDS), help="env ids to measure")
    parser.add_argument("--steps", type=int, default=2000, help="steps per timed repeat (episodes reset inside)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats per column; the best counts")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    parser.add_argument("--oracle-python", default=os.environ.get("SG_ORACLE_PYTHON", "/root/sg_oracle/bin/python"),
                        help="Python with safety-gymnasium 1.0.0 installed (the 'original' column)")
    parser.add_argument("--no-oracle", action="store_true", help="skip the original's column")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    oracle = None if args.no_oracle else args.oracle_python
    rows = []
    for env_id in args.ids:
        row = measure(env_id, args.steps, args.repeats, args.seed, oracle)
        rows.append(row)
        original = row["original_steps_per_s"]
        print(f"{env_id}: bare {row['bare_steps_per_s']:,.0f}/s, façade {row['facade_steps_per_s']:,.0f}/s "
              f"({row['facade_vs_bare']:.0%}), torchrl N=1 {row['torchrl_n1_steps_per_s']:,.0f}/s "
              f"({row['torchrl_n1_vs_bare']:.0%})"
              + ("" if original is None else f", original {original:,.0f}/s ({row['facade_vs_original']:.2f}x)")
              + ("" if row["bare_driven_steps_per_s"] is None else
                 f", bare + driven mocaps {row['bare_driven_steps_per_s']:,.0f}/s "
                 f"(façade {row['facade_vs_bare_driven']:.0%} of it)"),
              flush=True)
    print()
    print(markdown_table(rows))
    if args.json:
        write_json(args.json, rows, threads=args.threads)
    return rows


if __name__ == "__main__":
    main()
