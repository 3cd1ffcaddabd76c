"""Pixel-observation throughput of a Vision env against the bare renderer and the vector env.

For one env id (``SafetyPointGoal1Vision-v0`` by default), every image size and batch size ``N``,
this measures in the same process, interleaved (best of ``--repeats`` after a warm-up):

* **vision env**: ``env.step_and_maybe_reset`` with one fixed action, i.e. everything a step of
  the pixel env does (physics, vector observation, reward, cost, rendering all ``N`` robot cameras,
  copying the frames into the TensorDict, auto-resets). Each step yields ``N`` frames, so its
  observation frames/s equal its env steps/s;
* **bare renderer**: the physical limit of the rendering part, MuJoCo's own ``mujoco.Renderer``
  doing ``update_scene(data, camera="vision")`` + ``render()`` of the same ``N`` ``MjData`` (the
  vision env's simulators, frozen) with the same settings (no shadows, reflections, skybox or
  multisampling), nothing else;
* **vector env**: the same task without pixels (the plain id, ``obs_mode="vector"``), stepped the
  same way.

The markdown table gives the frame rates and the ratios vision env / bare renderer (overhead of the
env around rendering) and vision env / vector env (what pixels cost a step). Rendering runs on the
CPU (Mesa's llvmpipe) unless the OpenGL backend has a GPU; timings on a shared 2-core machine are
noisy, so compare ratios measured in the same run.

``mujoco.Renderer`` picks its OpenGL backend from ``MUJOCO_GL`` when ``mujoco`` is imported: when
it is unset, the script finds the backend sg_torchrl would use (:func:`gl_backend`) and re-runs
itself with ``MUJOCO_GL`` set to it, so that both renderers use the same backend.

Usage::

    python benchmarks/vision_throughput.py
    python benchmarks/vision_throughput.py --sizes 64 --num-envs 1 16 64 --steps 100 --json out.json
    python benchmarks/vision_throughput.py --id SafetyCarGoal2Vision-v0 --obs-mode rgbd
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import mujoco
import numpy as np
import torch

import sg_torchrl
from _report import write_json
from sg_torchrl.envs.rendering import gl_backend

DEFAULT_ID = "SafetyPointGoal1Vision-v0"


def time_env(env, steps: int, warmup: int, seed: int) -> float:
    """Seconds for ``steps`` calls of ``env.step_and_maybe_reset`` with one fixed in-bounds action."""
    generator = torch.Generator().manual_seed(seed)
    box = env.action_spec.space
    action = box.low + (box.high - box.low) * torch.rand(box.low.shape, generator=generator)
    td = env.reset()
    for _ in range(warmup):
        td.set("action", action)
        _, td = env.step_and_maybe_reset(td)
    start = time.perf_counter()
    for _ in range(steps):
        td.set("action", action)
        _, td = env.step_and_maybe_reset(td)
    return time.perf_counter() - start


class BareRenderer:
    """``mujoco.Renderer`` of a model's ``vision`` camera with the settings of sg_torchrl's fast frames."""

    def __init__(self, model: mujoco.MjModel, size: int) -> None:
        quality = model.vis.quality
        saved = quality.offsamples
        quality.offsamples = 0  # no multisampling, as sg_torchrl's renderer (read when the context is made)
        try:
            self.renderer = mujoco.Renderer(model, size, size)
        finally:
            quality.offsamples = saved
        self.frame = np.empty((size, size, 3), dtype=np.uint8)

    def draw(self, data: mujoco.MjData) -> None:
        renderer = self.renderer
        renderer.update_scene(data, camera="vision")
        flags = renderer.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = 0
        renderer.render(out=self.frame)

    def time(self, datas: list[mujoco.MjData], steps: int, warmup: int) -> float:
        """Seconds for ``steps`` rounds of drawing every one of ``datas``."""
        for _ in range(warmup):
            for data in datas:
                self.draw(data)
        start = time.perf_counter()
        for _ in range(steps):
            for data in datas:
                self.draw(data)
        return time.perf_counter() - start

    def close(self) -> None:
        self.renderer.close()


def measure(env_id: str, size: int, num_envs: int, obs_mode: str, steps: int, repeats: int, warmup: int,
            seed: int) -> dict:
    vision = sg_torchrl.make(env_id, num_envs=num_envs, seed=seed, obs_mode=obs_mode, image_size=size)
    vector = sg_torchrl.make(env_id, num_envs=num_envs, seed=seed, obs_mode="vector")
    bare = BareRenderer(vision.physics.model, size)
    ours, raw, plain = [], [], []
    for _ in range(repeats):  # interleaved, so machine-load drift hits all three alike
        ours.append(time_env(vision, steps, warmup, seed))
        raw.append(bare.time(vision.physics.datas, steps, warmup))
        plain.append(time_env(vector, steps, warmup, seed))
    bare.close()
    vision.close()
    vector.close()
    frames = num_envs * steps
    row = {
        "env_id": env_id, "obs_mode": obs_mode, "image_size": size, "num_envs": num_envs, "steps": steps,
        "repeats": repeats, "vision_frames_per_s": frames / min(ours), "bare_frames_per_s": frames / min(raw),
        "vector_steps_per_s": frames / min(plain),
    }
    row["vision_over_bare"] = row["vision_frames_per_s"] / row["bare_frames_per_s"]
    row["vision_over_vector"] = row["vision_frames_per_s"] / row["vector_steps_per_s"]
    return row


def markdown_table(rows: list[dict]) -> str:
    lines = [
        "| env id | obs_mode | image | N | vision env (frames/s = env steps/s) | bare mujoco.Renderer (frames/s) "
        "| vision env / bare renderer | vector env (env steps/s) | vision env / vector env |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        size = row["image_size"]
        lines.append(
            f"| {row['env_id']} | {row['obs_mode']} | {size}x{size} | {row['num_envs']} | "
            f"{row['vision_frames_per_s']:,.0f} | {row['bare_frames_per_s']:,.0f} | {row['vision_over_bare']:.0%} | "
            f"{row['vector_steps_per_s']:,.0f} | {row['vision_over_vector']:.1%} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--id", default=DEFAULT_ID, help="a Vision env id (or any navigation id)")
    parser.add_argument("--obs-mode", default="rgb", help="obs_mode of the vision env (rgb, rgbd, vector+rgb, ...)")
    parser.add_argument("--sizes", nargs="+", type=int, default=[64, 256], help="image sizes (square)")
    parser.add_argument("--num-envs", nargs="+", type=int, default=[1, 16], help="batch sizes N")
    parser.add_argument("--steps", type=int, default=50, help="timed env steps (rendering rounds) per repeat")
    parser.add_argument("--repeats", type=int, default=3, help="runs per measurement; the best counts")
    parser.add_argument("--warmup", type=int, default=5, help="untimed steps before each run")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    rows = []
    for size in args.sizes:
        for num_envs in args.num_envs:
            row = measure(args.id, size, num_envs, args.obs_mode, args.steps, args.repeats, args.warmup, args.seed)
            rows.append(row)
            print(f"{args.id} {size}x{size} N={num_envs}: vision env {row['vision_frames_per_s']:,.0f} frames/s, "
                  f"bare renderer {row['bare_frames_per_s']:,.0f} frames/s, "
                  f"vector env {row['vector_steps_per_s']:,.0f} steps/s", flush=True)
    print()
    print(f"OpenGL backend: {os.environ['MUJOCO_GL']}, torch threads: {args.threads}")
    print()
    print(markdown_table(rows))
    if args.json:
        write_json(args.json, rows, threads=args.threads)
    return rows


if __name__ == "__main__":
    if not os.environ.get("MUJOCO_GL"):
        # mujoco.Renderer reads MUJOCO_GL at `import mujoco`: re-run with the backend sg_torchrl uses.
        os.environ["MUJOCO_GL"] = gl_backend()
        os.execv(sys.executable, [sys.executable, *sys.argv])
    main()
