"""Shared check of sampled navigation layouts: keep-outs, extents, and that the physics holds them."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def assert_layouts_respect_keepouts(
    env,
    *,
    resets: int,
    extents: float,
    expected_positions: Callable[[object, np.ndarray], np.ndarray] = lambda obj, where: where,
) -> np.ndarray:
    """Reset ``env`` ``resets`` times and check every sampled layout; returns them ``(L, items, 2)``.

    After each reset the robot and every object stand where the layout put them
    (``expected_positions(obj, layout_rows)`` adjusts objects that move off their layout point);
    over all layouts, every pair of items keeps the sum of their keep-outs, each item lies inside
    the extents shrunk by its own keep-out, and no two layouts share a robot position.
    """
    sampler = env.layout_sampler
    keepouts = sampler.keepouts
    layouts = []
    for _ in range(resets):
        env.reset()
        layouts.append(env.layout.copy())
        np.testing.assert_allclose(env.scene.agent_xy(), env.layout[:, 0], atol=1e-9)
        for obj in env.task.objects:
            where = expected_positions(obj, env.layout[:, sampler.slice_of(obj)])
            np.testing.assert_allclose(obj.positions(env.scene), where, atol=1e-9, err_msg=obj.name)
    layouts = np.concatenate(layouts)
    assert layouts.shape == (resets * env.num_envs, sampler.size, 2)
    minimum = keepouts[:, None] + keepouts[None, :]
    off_diagonal = ~np.eye(sampler.size, dtype=bool)
    distance = np.linalg.norm(layouts[:, :, None] - layouts[:, None, :], axis=-1)
    assert (distance[:, off_diagonal] >= np.broadcast_to(minimum, distance.shape)[:, off_diagonal]).all()
    assert (np.abs(layouts) <= extents - keepouts[None, :, None] + 1e-12).all()
    assert len(np.unique(layouts[:, 0], axis=0)) == len(layouts)  # layouts differ
    return layouts
