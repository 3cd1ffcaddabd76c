"""Tile the frames of several envs into one image (what the vector envs' ``render`` returns)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["tile_images"]


def tile_images(images: Sequence[np.ndarray]) -> np.ndarray:
    """``N`` frames ``(H, W, C)`` as one ``(rows * H, cols * W, C)`` image on a near-square grid
    (``cols = ceil(sqrt(N))``), filled row by row, empty cells black.

    Raises:
        ValueError: no images, or images of different shapes.
    """
    frames = [np.asarray(image) for image in images]
    if not frames:
        raise ValueError("tile_images needs at least one image")
    if any(frame.shape != frames[0].shape for frame in frames):
        raise ValueError(f"images differ in shape: {sorted({frame.shape for frame in frames})}")
    height, width = frames[0].shape[:2]
    rest = frames[0].shape[2:]
    cols = int(np.ceil(np.sqrt(len(frames))))
    rows = int(np.ceil(len(frames) / cols))
    grid = np.zeros((rows * height, cols * width, *rest), dtype=frames[0].dtype)
    for index, frame in enumerate(frames):
        row, col = divmod(index, cols)
        grid[row * height:(row + 1) * height, col * width:(col + 1) * width] = frame
    return grid
