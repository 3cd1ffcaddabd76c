"""Image strips of the vision scenes: a few frames side by side in one PNG per scene family.

Each family is a function that builds its env, stages a short scene and returns the frames; the
script writes ``<out>/scene_<family>.png``. It is a visual check of what a family draws (does the
goal fade? does the road have its houses?), not a benchmark: there is no timing.

* ``fading``: SafetyPointFadingEasy0-v0, the robot idle in front of its goal; frames at steps 0,
  40, 80, 120 and 150 from the follow camera (the goal's alpha falls from 0.25 to 0 over 150 steps).
* ``race``: SafetyPointRace2-v0 (the far start), an overview of the village from above, then the
  follow camera and the robot's own ``vision`` camera at the start.

Add a family by writing a ``(size) -> list[frame]`` function and listing it in :data:`FAMILIES`.

Usage::

    python benchmarks/scene_strips.py                       # every family, 128 px frames
    python benchmarks/scene_strips.py --families race --size 192 --out /tmp/strips
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np
import torch
from tensordict import TensorDict

import sg_torchrl
from sg_torchrl.envs.rendering import FollowCamera

Frame = np.ndarray
CLOSE_CAMERA = FollowCamera(distance=2.5, elevation=-45.0, azimuth=90.0, offset=(0.5, 0.0, 0.0))


def _start_at(env, agent_xy: tuple[float, float], **objects: tuple[float, float]) -> None:
    """Reset simulator 0 with the robot at ``agent_xy`` facing +x and the first instance of each named
    object at the given position (everything else where the sampled layout put it)."""
    env.reset()
    xy, yaw = env.layout[0].copy(), np.zeros(env.layout_sampler.size)
    xy[0] = agent_xy
    for obj in env.task.objects:
        if obj.name in objects:
            xy[env.layout_sampler.slice_of(obj).start] = objects[obj.name]
    env.set_layout([0], xy[None], yaw[None])


def fading(size: int) -> list[Frame]:
    """The goal fading in front of an idle robot (FadingEasy: 150 steps to invisible)."""
    env = sg_torchrl.make("SafetyPointFadingEasy0-v0", num_envs=1, seed=0)
    _start_at(env, (0.0, 0.0), goal=(1.0, 0.0))
    frames, zero = [], np.zeros((1, env.action_dim))
    for step in range(151):
        if step in (0, 40, 80, 120, 150):
            frames.append(env.render(0, size, size, camera=CLOSE_CAMERA))
        _idle(env, zero)
    env.close()
    return frames


def _idle(env, action: np.ndarray) -> None:
    """One step of ``action`` (``(1, action_dim)``)."""
    env.step(TensorDict({"action": torch.as_tensor(action, dtype=torch.float32)}, batch_size=env.batch_size))


def race(size: int) -> list[Frame]:
    """Race level 2: the village from above, then the robot at its start (follow and vision cameras)."""
    env = sg_torchrl.make("SafetyPointRace2-v0", num_envs=1, seed=0)
    env.reset()
    overview = mujoco.MjvCamera()
    overview.type = mujoco.mjtCamera.mjCAMERA_FREE
    overview.lookat[:] = (0.4, -0.6, 0.0)
    overview.distance, overview.elevation, overview.azimuth = 11.0, -80.0, 90.0
    frames = [env.render(0, size, size, camera=overview),
              env.render(0, size, size),
              env.render(0, size, size, camera="vision")]
    env.close()
    return frames


FAMILIES: dict[str, Callable[[int], list[Frame]]] = {"fading": fading, "race": race}


def strip(frames: list[Frame], gap: int = 2) -> Frame:
    """Frames side by side with a white ``gap`` between them."""
    height = frames[0].shape[0]
    spacer = np.full((height, gap, 3), 255, dtype=np.uint8)
    parts = []
    for frame in frames:
        parts += [frame, spacer]
    return np.concatenate(parts[:-1], axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--families", nargs="+", choices=sorted(FAMILIES), default=sorted(FAMILIES))
    parser.add_argument("--size", type=int, default=128, help="side of each square frame, pixels (64-256)")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "figures")
    args = parser.parse_args()
    import imageio.v2 as imageio

    args.out.mkdir(parents=True, exist_ok=True)
    for family in args.families:
        path = args.out / f"scene_{family}.png"
        imageio.imwrite(path, strip(FAMILIES[family](args.size)))
        print(path)


if __name__ == "__main__":
    main()
