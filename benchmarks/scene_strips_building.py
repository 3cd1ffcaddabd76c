"""Image strips of the Building and FormulaOne scenes: an overview, the follow camera and the robot's camera.

    PYTHONPATH=. python benchmarks/scene_strips_building.py [--out benchmarks/figures] [--size 192]

Writes one PNG per scene family (``scene_<Task>2.png`` for BuildingGoal2, BuildingButton2,
BuildingPush2 and FormulaOne2, Point robot, seed 0): left an overview of the level from above, middle
the env's default follow camera, right the robot's egocentric ``vision`` camera (what the
``...Vision-v0`` ids observe, drawn at the same size). A few random steps are taken first so moving
objects are mid-motion. Needs an OpenGL backend (EGL or OSMesa; see ``sg_torchrl.envs.rendering``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import mujoco
import numpy as np
import torch
from PIL import Image
from torchrl.envs.utils import step_mdp

import sg_torchrl
from sg_torchrl.envs.rendering import FollowCamera

SCENES = ("BuildingGoal2", "BuildingButton2", "BuildingPush2", "FormulaOne2")


def overview(env, index: int = 0) -> mujoco.MjvCamera:
    """A free camera above the level: the whole placement area (Building) or the whole track (FormulaOne)."""
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.lookat[:] = (0.0, -0.3, 0.0)
    half = max(abs(e) for e in env.task.extents)
    track = getattr(env.task, "track", None)
    span = (track.half_straight + track.radius + 1.5) if track is not None else half + 1.6
    camera.distance, camera.elevation, camera.azimuth = 2.2 * span, -62.0, 90.0
    return camera


def strip(env_id: str, size: int, steps: int = 5) -> np.ndarray:
    """The three views of simulator 0 side by side, ``(size, 3 * size + 8, 3)`` uint8."""
    env = sg_torchrl.make(env_id, num_envs=1, seed=0)
    td = env.reset()
    generator = torch.Generator().manual_seed(0)
    box = env.action_spec.space
    for _ in range(steps):
        action = box.low + (box.high - box.low) * torch.rand(box.low.shape, generator=generator)
        td = step_mdp(env.step(td.set("action", action)))
    views = [env.render(0, size, size, camera=overview(env)),
             env.render(0, size, size, camera=FollowCamera(distance=3.0, elevation=-35.0, heading=True, azimuth=0.0)),
             env.render(0, size, size, camera="vision")]
    env.close()
    gap = np.full((size, 4, 3), 255, dtype=np.uint8)
    return np.concatenate([views[0], gap, views[1], gap, views[2]], axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "figures")
    parser.add_argument("--size", type=int, default=192)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for scene in SCENES:
        path = args.out / f"scene_{scene}.png"
        Image.fromarray(strip(f"SafetyPoint{scene}-v0", args.size)).save(path, optimize=True)
        print(path)


if __name__ == "__main__":
    main()
