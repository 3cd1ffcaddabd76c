"""Collector factories and cost-aware episode statistics.

On 2-core machines run collection with a single torch thread (``with single_thread(): ...``):
small-MLP policies are about 10x slower with torch's default thread count. :func:`make_collector`
deliberately leaves the global thread setting alone.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase

from sg_torchrl.collectors.episode_stats import EpisodeStats
from sg_torchrl.collectors.onpolicy import RolloutCollector
from sg_torchrl.collectors.threads import single_thread

__all__ = ["EpisodeStats", "RolloutCollector", "make_collector", "single_thread"]


def make_collector(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase] | None,
    *,
    frames_per_batch: int,
    total_frames: int,
    device: torch.device | str = "cpu",
    **collector_kwargs: Any,
) -> Collector:
    """A single-process :class:`torchrl.collectors.Collector` over a batched sg_torchrl env.

    Batches have shape ``[N, frames_per_batch // N]`` for an env with ``batch_size=[N]`` (env
    index first, time last, dim names ``[None, "time"]``), one trajectory stream per env, never
    split into trajectories (``split_trajs=False``): the layout :class:`EpisodeStats` and GAE
    consume. ``frames_per_batch`` must be a multiple of ``N`` (TorchRL would silently round it
    up). ``policy=None`` samples random actions. Policy-required env transforms are not
    auto-registered (``auto_register_policy_transforms=False``: the env is used as given, and
    TorchRL 0.14's FutureWarning is silenced). Extra keyword arguments go to ``Collector``.
    """
    num_envs = env.batch_size.numel()
    if frames_per_batch % num_envs:
        raise ValueError(
            f"frames_per_batch ({frames_per_batch}) must be a multiple of the number of "
            f"batched envs ({num_envs})"
        )
    options: dict[str, Any] = {
        "split_trajs": False,
        "auto_register_policy_transforms": False,
    }
    options.update(collector_kwargs)
    return Collector(
        env,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=total_frames,
        device=device,
        **options,
    )
