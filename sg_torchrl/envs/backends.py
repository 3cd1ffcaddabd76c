"""Choosing the physics backend: :func:`make_physics`, the one place envs build their simulators.

``backend="cpu"`` (default): :class:`~sg_torchrl.envs.physics.MujocoBatch`, MuJoCo C, float64, what
the tests and the reference comparisons use. ``backend="warp"``:
:class:`~sg_torchrl.envs.warp_physics.WarpBatch`, MuJoCo Warp (float32) on a CUDA device when one is
visible, else on Warp's CPU device; it needs the optional extra (``pip install 'sg_torchrl[warp]'``).
Both implement :class:`~sg_torchrl.envs.physics_protocol.PhysicsBatch`, the interface envs use.
Envs take the fields of :class:`~sg_torchrl.envs.options.SimulatorOptions` (``backend``, ``warp_device``,
...) as constructor arguments and pass the object here, so ``sg_torchrl.make(env_id, backend="warp")``
works for every env that does.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco

from sg_torchrl.envs.options import BACKENDS, Backend, SimulatorOptions
from sg_torchrl.envs.physics import MujocoBatch
from sg_torchrl.envs.physics_protocol import PhysicsBatch
from sg_torchrl.envs.warp_physics import WarpBatch

__all__ = ["BACKENDS", "Backend", "PhysicsBatch", "SimulatorOptions", "make_physics"]


def make_physics(
    model: mujoco.MjModel,
    num_sims: int,
    simulator: SimulatorOptions = SimulatorOptions(),
    *,
    post_constraint: bool = False,
    fields: Sequence[str] = (),
    forward_after_step: bool = False,
) -> PhysicsBatch:
    """``num_sims`` simulators of ``model`` run as ``simulator`` says (its backend, threads, Warp settings).

    Args:
        simulator: the backend and its settings (checked when the object was built).
        post_constraint / fields / forward_after_step: as for :class:`MujocoBatch`.

    Raises:
        ImportError: ``"warp"`` without MuJoCo Warp installed (the message says how to install it).
    """
    common = dict(post_constraint=post_constraint, fields=fields, forward_after_step=forward_after_step)
    if simulator.backend == "cpu":
        return MujocoBatch(model, num_sims, threads=simulator.physics_threads, **common)
    return WarpBatch(model, num_sims, device=simulator.warp_device, **common, **dict(simulator.warp_options or {}))
