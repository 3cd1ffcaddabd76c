"""Choosing the physics backend: :func:`make_physics`, the one place envs build their simulators.

``backend="cpu"`` (default): :class:`~sg_torchrl.envs.physics.MujocoBatch`, MuJoCo C, float64, what
the tests and the reference comparisons use. ``backend="warp"``:
:class:`~sg_torchrl.envs.warp_physics.WarpBatch`, MuJoCo Warp (float32) on a CUDA device when one is
visible, else on Warp's CPU device; it needs the optional extra (``pip install 'sg_torchrl[warp]'``).
Envs take ``backend`` and ``warp_device`` as constructor arguments and pass them here, so
``sg_torchrl.make(env_id, backend="warp")`` works for every env that does.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal, Union

import mujoco

from sg_torchrl.envs.physics import MujocoBatch
from sg_torchrl.envs.warp_physics import WarpBatch

__all__ = ["BACKENDS", "Backend", "PhysicsBatch", "make_physics"]

Backend = Literal["cpu", "warp"]
BACKENDS: tuple[str, ...] = ("cpu", "warp")
#: What an env's ``self.physics`` is: both backends implement the same interface.
PhysicsBatch = Union[MujocoBatch, WarpBatch]


def make_physics(
    backend: str,
    model: mujoco.MjModel,
    num_sims: int,
    *,
    post_constraint: bool = False,
    fields: Sequence[str] = (),
    forward_after_step: bool = False,
    threads: int = 1,
    warp_device: str | None = None,
    warp_options: Mapping[str, Any] | None = None,
) -> PhysicsBatch:
    """``num_sims`` simulators of ``model`` on ``backend``.

    Args:
        backend: ``"cpu"`` or ``"warp"`` (module docstring).
        post_constraint / fields / forward_after_step: as for :class:`MujocoBatch`.
        threads: stepping threads (``"cpu"`` only; Warp parallelises over worlds itself).
        warp_device: the Warp device for ``"warp"`` (``"cuda:0"``, ``"cpu"``); ``None``: CUDA when available.
        warp_options: more :class:`WarpBatch` keywords for ``"warp"``: buffer sizes ``nconmax``/``njmax``
            (raise them when it warns of an overflow), ``graph``.

    Raises:
        ValueError: unknown backend, or an option the backend does not take.
        ImportError: ``"warp"`` without MuJoCo Warp installed (the message says how to install it).
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown physics backend {backend!r}; choose from {list(BACKENDS)}")
    common = dict(post_constraint=post_constraint, fields=fields, forward_after_step=forward_after_step)
    if backend == "cpu":
        for name, value in (("warp_device", warp_device), ("warp_options", warp_options)):
            if value is not None:
                raise ValueError(f"{name}={value!r} applies to backend='warp' only")
        return MujocoBatch(model, num_sims, threads=threads, **common)
    if threads != 1:
        raise ValueError(f"physics_threads={threads} applies to backend='cpu' only "
                         "(MuJoCo Warp parallelises over worlds itself); leave it at 1 with backend='warp'")
    return WarpBatch(model, num_sims, device=warp_device, **common, **dict(warp_options or {}))
