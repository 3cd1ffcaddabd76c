"""Batched MuJoCo simulators that share one compiled model.

:class:`MujocoBatch` is the physics backend behind every MuJoCo-based sg_torchrl env: one
``MjModel`` compiled once, ``N`` ``MjData`` instances stepped in-process, and the state that
tasks read (``qpos``, ``qvel``, body positions, ...) exposed as ``(N, ...)`` numpy arrays.
Tasks never touch ``MjData`` directly, which keeps the door open for an array-native backend
(MuJoCo Warp on a GPU) implementing the same small interface.

Why not one env object per simulator: on a 2-core machine the per-call overhead of TorchRL's
``EnvBase.step`` and of a policy forward dominates small MuJoCo models, so one env stepping N
simulators amortises it N times (Safety-Gymnasium uses one subprocess per simulator instead).
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

__all__ = ["MujocoBatch"]


class MujocoBatch:
    """``num_sims`` MuJoCo simulators stepping one shared model.

    Args:
        model: the compiled model, shared (read-only) by every simulator.
        num_sims: number of simulators.
        post_constraint: also run ``mj_rnePostConstraint`` after stepping, which fills
            ``cfrc_ext``/``cacc`` (needed only by observations that read contact forces,
            e.g. the Humanoid's; gymnasium's MuJoCo envs always run it).
    """

    def __init__(self, model: mujoco.MjModel, num_sims: int, *, post_constraint: bool = False) -> None:
        if num_sims < 1:
            raise ValueError(f"num_sims must be >= 1, got {num_sims}")
        self.model = model
        self.num_sims = num_sims
        self.post_constraint = post_constraint
        self.datas = [mujoco.MjData(model) for _ in range(num_sims)]
        for data in self.datas:
            mujoco.mj_forward(model, data)
        # Preallocated read buffers: gathering state never allocates in the hot path.
        self._qpos = np.zeros((num_sims, model.nq))
        self._qvel = np.zeros((num_sims, model.nv))
        self._ctrl_low = model.actuator_ctrlrange[:, 0].copy()
        self._ctrl_high = model.actuator_ctrlrange[:, 1].copy()

    # ------------------------------------------------------------------ stepping
    def step(self, ctrl: np.ndarray, nstep: int) -> None:
        """Write ``ctrl`` (``(N, nu)``) to every simulator and advance each by ``nstep`` steps."""
        model, post = self.model, self.post_constraint
        for data, row in zip(self.datas, ctrl):
            data.ctrl[:] = row
            mujoco.mj_step(model, data, nstep)
            if post:
                mujoco.mj_rnePostConstraint(model, data)

    def reset(self, indices: Sequence[int], qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Reset simulators ``indices`` to the given joint state (rows of ``qpos``/``qvel``).

        Data is cleared with ``mj_resetData`` first (time, warm-starts, activations), then
        the state is written and ``mj_forward`` recomputes every derived quantity, exactly as
        gymnasium's ``MujocoEnv.reset`` + ``set_state`` do. No model is compiled.
        """
        model = self.model
        for row, index in enumerate(indices):
            data = self.datas[index]
            mujoco.mj_resetData(model, data)
            data.qpos[:] = qpos[row]
            data.qvel[:] = qvel[row]
            mujoco.mj_forward(model, data)
            if self.post_constraint:
                mujoco.mj_rnePostConstraint(model, data)

    # ------------------------------------------------------------------ state views
    @property
    def timestep(self) -> float:
        return float(self.model.opt.timestep)

    @property
    def ctrl_range(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-actuator ``(low, high)`` control limits."""
        return self._ctrl_low, self._ctrl_high

    def qpos(self) -> np.ndarray:
        """Joint positions, ``(N, nq)``; the returned buffer is overwritten by the next call."""
        for i, data in enumerate(self.datas):
            self._qpos[i] = data.qpos
        return self._qpos

    def qvel(self) -> np.ndarray:
        """Joint velocities, ``(N, nv)``; the returned buffer is overwritten by the next call."""
        for i, data in enumerate(self.datas):
            self._qvel[i] = data.qvel
        return self._qvel

    def gather(self, field: str) -> np.ndarray:
        """Stack any ``MjData`` array attribute (``"xpos"``, ``"cinert"``, ...) into ``(N, ...)``."""
        return np.stack([getattr(data, field) for data in self.datas])

    def body_xpos(self, body_id: int) -> np.ndarray:
        """World position of one body in every simulator, ``(N, 3)``."""
        return np.stack([data.xpos[body_id] for data in self.datas])

    def warning_counts(self, warning: mujoco.mjtWarning = mujoco.mjtWarning.mjWARN_BADQACC) -> np.ndarray:
        """How often each simulator raised ``warning`` (MuJoCo resets a diverged simulator itself)."""
        return np.array([data.warning[warning].number for data in self.datas])
