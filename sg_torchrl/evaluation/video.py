"""Watch evaluation episodes: their frames, with each episode's running return and cost drawn on them.

:class:`EvaluationVideo` is a step callback of :func:`~sg_torchrl.train.evaluate.evaluate_episodes`:
after every step it renders the first ``episodes`` simulators of the evaluation env (the env's public
``render``; rendering only reads the simulators, so the evaluated figures are those of a run without a
video), draws each one's episode, step, return and cost so far on its frame, tiles the frames side by
side (a grid for more than one episode) and appends the picture to an MP4 (``imageio-ffmpeg``) or
GIF. A simulator's tile stops at its episode's last step before the end (after the final step TorchRL
has already reset it) and keeps its last picture, marked ``done``, until every recorded episode has
ended. The file is written beside its target and renamed over it when complete
(:mod:`sg_torchrl.train.writes`); :meth:`EvaluationVideo.close` must be called (``with`` does it).
"""

from __future__ import annotations

import importlib.util
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from tensordict import TensorDictBase

from sg_torchrl.train.writes import RunWriteError, make_dirs, writing

__all__ = ["VIDEO_SUFFIXES", "EvaluationVideo", "check_video_path", "record_evaluation"]

#: The video formats written, by file suffix.
VIDEO_SUFFIXES = (".mp4", ".gif")
_BAND = 14  # pixels of the text band at the top of a tile


def check_video_path(path: str | os.PathLike) -> Path:
    """``path`` if a video can be written there in its format, else ``ValueError`` saying why (the suffix,
    or an MP4 without ``imageio-ffmpeg``)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in VIDEO_SUFFIXES:
        raise ValueError(f"video {path}: give a .mp4 or .gif file name")
    if suffix == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise ValueError(f"video {path}: writing MP4 needs imageio-ffmpeg (pip install imageio-ffmpeg, which "
                         f"ships its own ffmpeg binary); without it give a .gif file name")
    return path


def _frame_rate(env: Any) -> float:
    """Real time: one frame per env step of ``frame_skip * timestep`` seconds (30 where the env does not say)."""
    try:
        dt = float(env.frame_skip * env.physics.model.opt.timestep)
    except AttributeError:
        return 30.0
    return 1.0 / dt if dt > 0 else 30.0


def _draw_text(frame: np.ndarray, text: str) -> np.ndarray:
    """``frame`` with a dark band on top holding ``text`` (PIL's built-in font)."""
    from PIL import Image, ImageDraw

    image = Image.fromarray(frame)
    draw = ImageDraw.Draw(image)
    draw.rectangle((0, 0, image.width, _BAND), fill=(0, 0, 0))
    draw.text((3, 2), text, fill=(255, 255, 255))
    return np.asarray(image)


class EvaluationVideo:
    """Record the first ``episodes`` evaluation episodes to ``path`` (a step callback; see the module docstring).

    Args:
        path: ``.mp4`` or ``.gif`` (:func:`check_video_path`).
        episodes: how many simulators to show, tiled (at most the number evaluated).
        width, height: one tile's size in pixels.
        fps: frame rate (default: real time).
        camera: the env's camera name (``None``: its default, following the robot).
    """

    def __init__(self, path: str | os.PathLike, episodes: int = 1, *, width: int = 256, height: int = 256,
                 fps: float | None = None, camera: Any = None) -> None:
        self.path = check_video_path(path)
        if episodes < 1:
            raise ValueError(f"video episodes must be >= 1, got {episodes}")
        self.episodes, self.width, self.height, self.fps, self.camera = episodes, width, height, fps, camera
        self.columns = math.ceil(math.sqrt(episodes))
        self.rows = math.ceil(episodes / self.columns)
        self.frames = 0
        self._writer = None
        self._tmp = self.path.with_name(f".{self.path.stem}.tmp{self.path.suffix}")  # keeps its format's suffix
        self._tiles: list[np.ndarray | None] = [None] * episodes
        self._returns = np.zeros(episodes)
        self._costs = np.zeros(episodes)
        self._steps = np.zeros(episodes, dtype=int)
        self._ended = np.zeros(episodes, dtype=bool)

    def _open(self, env: Any) -> None:
        import imageio.v2 as imageio

        fps = float(self.fps if self.fps is not None else _frame_rate(env))
        make_dirs(self.path.parent)
        with writing(self.path, leftover=self._tmp):
            if self.path.suffix.lower() == ".gif":
                self._writer = imageio.get_writer(self._tmp, mode="I", duration=1000.0 / fps, loop=0)
            else:  # macro_block_size=1: keep the frame size as is
                self._writer = imageio.get_writer(self._tmp, fps=fps, macro_block_size=1)

    def __call__(self, base: Any, env: Any, tensordict: TensorDictBase) -> None:
        if self._ended.all():
            return
        if self.episodes > base.batch_size[0]:
            raise ValueError(f"the video shows {self.episodes} episodes of an evaluation of {base.batch_size[0]}")
        if self._writer is None:
            self._open(base)
        shown = slice(0, self.episodes)
        reward = tensordict.get(("next", base.reward_key))[shown].reshape(self.episodes, -1).mean(-1)
        cost = tensordict.get(("next", "cost"))[shown].reshape(self.episodes, -1).mean(-1)
        done = tensordict.get(("next", "done"))[shown].reshape(self.episodes, -1).any(-1)
        for k in range(self.episodes):
            if self._ended[k]:
                continue
            self._returns[k] += float(reward[k])
            self._costs[k] += float(cost[k])
            self._steps[k] += 1
            if bool(done[k]):  # already reset by TorchRL: keep the last picture of the episode
                self._ended[k] = True
                if self._tiles[k] is not None:
                    self._tiles[k] = _draw_text(self._tiles[k], self._caption(k) + "  done")
                continue
            frame = base.render(k, self.width, self.height, self.camera)
            self._tiles[k] = _draw_text(frame, self._caption(k))
        self._append()

    def _caption(self, k: int) -> str:
        return f"ep {k}  t {self._steps[k]}  ret {self._returns[k]:.1f}  cost {self._costs[k]:.0f}"

    def _append(self) -> None:
        blank = np.zeros((self.height, self.width, 3), dtype=np.uint8)
        tiles = [tile if tile is not None else blank for tile in self._tiles]
        tiles += [blank] * (self.rows * self.columns - len(tiles))
        grid = np.concatenate([np.concatenate(tiles[r * self.columns:(r + 1) * self.columns], axis=1)
                               for r in range(self.rows)], axis=0)
        with writing(self.path, leftover=self._tmp):
            self._writer.append_data(grid)
        self.frames += 1

    def close(self) -> Path | None:
        """Finish the file and move it to :attr:`path`; returns it (``None`` when no frame was recorded).

        Raises:
            RunWriteError: the video could not be written.
        """
        if self._writer is None:
            return None
        writer, self._writer = self._writer, None
        with writing(self.path, leftover=self._tmp):
            writer.close()
            self._tmp.replace(self.path)
        return self.path

    def discard(self) -> None:
        """Drop a video left unfinished (an error during the evaluation): nothing is written."""
        if self._writer is not None:
            writer, self._writer = self._writer, None
            try:
                writer.close()
            except (OSError, RuntimeError):
                pass
        if self._tmp.exists():
            self._tmp.unlink()

    def __enter__(self) -> EvaluationVideo:
        return self

    def __exit__(self, kind, error, traceback) -> None:
        if kind is None:
            self.close()
        else:
            self.discard()


def record_evaluation(policy, path: str | os.PathLike, episodes: int = 1, *, seed: int,
                      env_options: dict[str, Any] | None = None, env_id: str | None = None,
                      **video_options: Any) -> tuple[Path, dict[str, Any]]:
    """Evaluate a :class:`~sg_torchrl.evaluation.policy.TrainedPolicy` on ``episodes`` episodes (env seed
    ``seed``) and record them all; returns the video's path and the episodes' figures
    (:func:`~sg_torchrl.train.evaluate.evaluate_episodes`).

    Raises:
        RenderingUnavailable: no OpenGL backend can render here.
        RunWriteError: the video could not be written.
    """
    from sg_torchrl.train.evaluate import evaluate_episodes

    cfg = policy.config
    options = {**cfg.env_options, **(env_options or {})}
    with EvaluationVideo(path, episodes, **video_options) as video:
        figures = evaluate_episodes(env_id or cfg.env_id, policy, episodes, seed=seed, env_options=options,
                                    callback=video)
    if video.frames == 0:
        raise RunWriteError(path, "no frame was recorded (the episodes ended at once)")
    return video.path, figures
