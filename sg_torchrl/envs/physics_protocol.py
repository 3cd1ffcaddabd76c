"""``PhysicsBatch``: the interface every physics backend gives the envs, and its optional capability.

An env holds ``N`` simulators of one compiled model as ``self.physics`` and talks to them only through
this interface: step them, reset rows, read their state as ``(N, ...)`` numpy arrays, snapshot and
restore it, move mocap bodies, count contacts. :class:`~sg_torchrl.envs.physics.MujocoBatch` (MuJoCo C)
and :class:`~sg_torchrl.envs.warp_physics.WarpBatch` (MuJoCo Warp) implement it;
:func:`~sg_torchrl.envs.backends.make_physics` picks one. Both subclass the protocol explicitly, so
they inherit the defaults of the optional capability below; a third backend may too, or just match it
structurally (``isinstance(obj, PhysicsBatch)`` checks the members' presence).

Optional capability, queried, never inferred from the class: **aliased single step**. A backend with one
simulator whose state arrays are views of that simulator's own state (MuJoCo C at ``N = 1``) can step it
without gathering anything: the env writes the clipped control into ``datas[0].ctrl`` and calls
:meth:`PhysicsBatch.advance_one`; :meth:`PhysicsBatch.contact_counts_one` reads its contacts as Python
values. An env's one-simulator fast path (the gymnasium façade's speed) asks
:attr:`PhysicsBatch.supports_aliased_single_step` before taking it; backends without it answer
``False`` and keep the defaults here, which refuse to run.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:
    import mujoco
    import numpy as np

__all__ = ["PhysicsBatch"]


@runtime_checkable
class PhysicsBatch(Protocol):
    """``num_sims`` simulators of one ``model``, stepped together (module docstring).

    Attributes:
        model: the compiled host ``MjModel`` (read-only; the renderer and the tasks read it).
        num_sims: ``N``.
        datas: per simulator an ``MjData`` (for a device backend, host copies made on access).
        unstable: ``(N,)`` bool, the simulators found diverged (and reset) during the last step.
        version: bumped whenever the state changes: readers cache derived values per version.
        threads: stepping threads (1 where the backend parallelises by itself).
    """

    model: mujoco.MjModel
    num_sims: int
    datas: Sequence[mujoco.MjData]
    unstable: np.ndarray
    version: int
    threads: int

    # ------------------------------------------------------------------ stepping and resets
    def step(self, ctrl: np.ndarray, nstep: int) -> np.ndarray:
        """Write ``ctrl`` ``(N, nu)`` and advance every simulator ``nstep`` physics steps; returns :attr:`unstable`."""
        ...

    def reset(self, indices: Sequence[int], qpos: np.ndarray, qvel: np.ndarray,
              mocap_pos: np.ndarray | None = None, mocap_quat: np.ndarray | None = None) -> None:
        """Reset simulators ``indices`` to rows of ``qpos`` / ``qvel`` (and mocap poses), then a forward pass."""
        ...

    def refresh(self, indices: Sequence[int] | None = None) -> None:
        """Re-read the cached state after writing into :attr:`datas` directly."""
        ...

    def set_mocap_pos(self, index: int, mocap_id: int, pos: np.ndarray) -> None:
        """Move one mocap body of simulator ``index``."""
        ...

    @property
    def drives_mocap(self) -> bool:
        """Whether mocap bodies follow a trajectory registered with :meth:`drive_mocap`."""
        ...

    def drive_mocap(self, mocap_ids: Sequence[int], trajectory) -> None:
        """Move mocap bodies ``mocap_ids`` along ``trajectory`` before every physics sub-step."""
        ...

    def close(self) -> None:
        """Release threads or device resources."""
        ...

    # ------------------------------------------------------------------ state
    def qpos(self) -> np.ndarray:
        """Joint positions ``(N, nq)`` (do not write)."""
        ...

    def qvel(self) -> np.ndarray:
        """Joint velocities ``(N, nv)`` (do not write)."""
        ...

    def field(self, name: str) -> np.ndarray:
        """A cached ``MjData`` array named at construction, ``(N, ...)`` (do not write)."""
        ...

    def gather(self, field: str) -> np.ndarray:
        """Any ``MjData`` array stacked into a new ``(N, ...)`` array."""
        ...

    @property
    def timestep(self) -> float:
        """The model's physics timestep (s)."""
        ...

    @property
    def ctrl_range(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-actuator ``(low, high)`` control limits."""
        ...

    def get_state(self) -> np.ndarray:
        """Everything the next step depends on, ``(N, nstate)`` (checkpoints)."""
        ...

    def set_state(self, state: np.ndarray) -> None:
        """Restore :meth:`get_state`'s output."""
        ...

    # ------------------------------------------------------------------ contacts
    def count_contacts(self, geoms_a: np.ndarray, geoms_b: np.ndarray) -> np.ndarray:
        """``(N,)`` number of contacts between a geom of mask A and one of mask B."""
        ...

    def contact_counts(self, geoms: np.ndarray) -> np.ndarray:
        """``(N, ngeom)`` contacts of each geom with a geom of mask ``geoms``."""
        ...

    # ------------------------------------------------------------------ optional: aliased single step
    @property
    def supports_aliased_single_step(self) -> bool:
        """Whether :meth:`advance_one` and :meth:`contact_counts_one` are available (module docstring).
        Default: no."""
        return False

    def advance_one(self, nstep: int) -> bool:
        """Step the one simulator whose control is already in ``datas[0].ctrl``; whether it went unstable.
        Only where :attr:`supports_aliased_single_step`."""
        raise NotImplementedError(f"{type(self).__name__} has no aliased single step "
                                  "(check supports_aliased_single_step first)")

    def contact_counts_one(self, geoms: list[bool]) -> dict[int, float]:
        """:meth:`contact_counts` of simulator 0 as ``{geom: count}``, ``geoms`` a list of bools.
        Only where :attr:`supports_aliased_single_step`."""
        raise NotImplementedError(f"{type(self).__name__} has no aliased single step "
                                  "(check supports_aliased_single_step first)")
