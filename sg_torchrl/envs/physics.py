"""Batched MuJoCo simulators that share one compiled model.

:class:`MujocoBatch` is the physics backend behind every MuJoCo-based sg_torchrl env: one
``MjModel`` compiled once, ``N`` ``MjData`` instances stepped in-process, and the state that
tasks read (``qpos``, ``qvel``, body positions, ...) exposed as ``(N, ...)`` numpy arrays.
Tasks never touch ``MjData`` directly, which keeps the door open for an array-native backend
(MuJoCo Warp on a GPU) implementing the same small interface.

Why not one env object per simulator: on a 2-core machine the per-call overhead of TorchRL's
``EnvBase.step`` and of a policy forward dominates small MuJoCo models, so one env stepping N
simulators amortises it N times (Safety-Gymnasium uses one subprocess per simulator instead).

State cache: after stepping, ``qpos``, ``qvel`` and the task's ``fields`` of every simulator are
copied into preallocated ``(N, ...)`` arrays, one ``np.concatenate`` per field over numpy views of
the ``MjData`` buffers that were taken once at construction (no Python loop over the simulators,
no attribute lookups). Tasks then read observations, positions and health checks from those arrays
as often as they like. The cache is refreshed by :meth:`step`, :meth:`reset` and :meth:`set_state`;
code that writes into ``MjData`` directly must call :meth:`refresh`.

One simulator: with ``num_sims == 1`` the state cache arrays are ``(1, ...)`` views of that
simulator's ``MjData`` arrays rather than copies, and :meth:`step` reads its instability counters as
three scalars. A single simulator is where the work around ``mj_step`` decides the speed (the
gymnasium façade), and the values read are the same either way: nothing reads the cache
between a write into ``MjData`` and the :meth:`refresh` that would follow it.

Divergence: when a simulator's state becomes non-finite or huge, MuJoCo raises one of its
``BADQPOS``/``BADQVEL``/``BADQACC`` warnings and silently resets that ``MjData`` to the model's
initial state. :meth:`step` reports which simulators this happened to, so the env can end their
episode instead of presenting the jump as a transition, and clears those counters so that a further
divergence (before the env resets the simulator) is reported too.

Driven mocap bodies: objects that move along a prescribed path (Safety-Gymnasium's gremlins,
placed before every physics sub-step) register a vectorised trajectory with :meth:`drive_mocap`.
:meth:`step` then computes every target of the step for all simulators in one call and runs the
sub-steps one ``mj_step`` at a time; worlds without such objects keep the single
``mj_step(nstep)`` call per simulator.

Threads: MuJoCo's Python bindings release the GIL inside ``mj_step``, so ``threads > 1`` steps
contiguous slices of the simulators on a small persistent thread pool. Each simulator is still
stepped by exactly one thread with its own ``MjData``, so results are bit-identical to one thread.
On 2 idle cores and N = 16-64 simulators, 2 threads step 1.5-1.9x faster for every robot
measured, from the Point (about 5 us per ``mj_step``) to the two hands (about 70 us)
(``benchmarks/threaded_stepping.py``, which also measures ``mujoco.rollout``'s own thread pool: as
fast, but it restarts every simulator from a state array each call, and without the solver
warm-start that is no longer bit-identical). The default stays 1: threads only pay when a core
is idle, which is not the case when several jobs share the machine.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import mujoco
import numpy as np

from sg_torchrl.envs.contacts import ContactCounting
from sg_torchrl.envs.physics_protocol import PhysicsBatch

__all__ = ["MocapTrajectory", "MujocoBatch"]

#: ``times (N, nstep) -> positions (N, nstep, K, 3)``: where driven mocap bodies go before each sub-step
MocapTrajectory = Callable[[np.ndarray], np.ndarray]

# MuJoCo's instability warnings (contiguous in mjtWarning): each comes with an automatic reset.
_UNSTABLE = slice(int(mujoco.mjtWarning.mjWARN_BADQPOS), int(mujoco.mjtWarning.mjWARN_BADQACC) + 1)
assert int(mujoco.mjtWarning.mjWARN_BADQVEL) == _UNSTABLE.start + 1 and _UNSTABLE.stop - _UNSTABLE.start == 3
class MujocoBatch(ContactCounting, PhysicsBatch):
    """``num_sims`` MuJoCo simulators stepping one shared model.

    Args:
        model: the compiled model, shared (read-only) by every simulator.
        num_sims: number of simulators.
        post_constraint: also run ``mj_rnePostConstraint`` after stepping, which fills
            ``cfrc_ext``/``cacc`` (needed only by observations that read contact forces,
            e.g. the Humanoid's; gymnasium's MuJoCo envs always run it).
        fields: ``MjData`` arrays besides ``qpos``/``qvel`` to keep in the state cache
            (``"xpos"``, ``"cinert"``, ...), read with :meth:`field`.
        forward_after_step: run ``mj_forward`` after the ``nstep`` physics steps, so that positions
            derived from ``qpos`` (``xpos``, ``xmat``) and sensor readings describe the state the
            step ended in (``mj_step`` leaves them at the state before its last integration).
            Safety-Gymnasium's navigation tasks do this; gymnasium's MuJoCo envs do not.
        threads: step the simulators on this many threads (at most ``num_sims``; see the module
            docstring for when it pays). ``1``: in the calling thread.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        num_sims: int,
        *,
        post_constraint: bool = False,
        fields: Sequence[str] = (),
        forward_after_step: bool = False,
        threads: int = 1,
    ) -> None:
        if num_sims < 1:
            raise ValueError(f"num_sims must be >= 1, got {num_sims}")
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ValueError(f"threads must be a positive integer, got {threads!r}")
        self.model = model
        self.num_sims = num_sims
        self.post_constraint = post_constraint
        self.forward_after_step = forward_after_step
        self.datas = [mujoco.MjData(model) for _ in range(num_sims)]
        for data in self.datas:
            mujoco.mj_forward(model, data)
        # The state cache (see the module docstring): filled in place, never reallocated. Each entry
        # holds the (N, ...) cache array and the live views of that MjData array in every simulator.
        # MuJoCo's warning counters are cached the same way: they reveal its silent resets.
        self._ctrl_views = [data.ctrl for data in self.datas]
        # One simulator (module docstring, "One simulator"): the cache arrays are (1, ...) views of its
        # MjData arrays, so nothing is copied after a step.
        self._aliased = num_sims == 1
        self._cache: dict[str, tuple[np.ndarray, list[np.ndarray]]] = {}
        for name in ("qpos", "qvel", *fields, "warnings"):
            views = [data.warning.number if name == "warnings" else getattr(data, name) for data in self.datas]
            cache = views[0][None] if self._aliased else np.zeros((num_sims, *views[0].shape), dtype=views[0].dtype)
            self._cache[name] = (cache, views)
        self._qpos, self._qvel, self._warnings = (self._cache[name][0] for name in ("qpos", "qvel", "warnings"))
        # Where np.concatenate of the N views lands: the cache array with the N rows joined (none when aliased).
        self._gather_plan = [] if self._aliased else [
            (views, cache.reshape(-1, *cache.shape[2:])) for cache, views in self._cache.values()]
        self._unstable_counts = np.zeros(num_sims, dtype=np.int64)
        self._unstable_one = self._warnings[0, _UNSTABLE]  # simulator 0's three instability counters (a view)
        self.unstable = np.zeros(num_sims, dtype=bool)  # simulators MuJoCo reset during the last step
        self._ctrl_low = model.actuator_ctrlrange[:, 0].copy()
        self._ctrl_high = model.actuator_ctrlrange[:, 1].copy()
        #: bumped whenever the state cache changes (step, reset, refresh): lets readers cache derived values
        self.version = 0
        # Mocap trajectories (see drive_mocap): (rows of mocap_pos as a slice or index array, trajectory).
        self._mocap_drivers: list[tuple[slice | np.ndarray, MocapTrajectory]] = []
        self._mocap_views = [data.mocap_pos for data in self.datas]
        self._substep_views: tuple[np.ndarray, list[np.ndarray]] | None = None  # see _substeps
        self._substep_offsets: dict[int, np.ndarray] = {}  # nstep -> (1, nstep) sub-step start times after the step's (s)
        # Threads (module docstring): each worker steps one contiguous slice of the simulators.
        self.threads = min(threads, num_sims)
        bounds = np.linspace(0, num_sims, self.threads + 1).round().astype(int)
        self._slices = [range(lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:])]
        self._pool: ThreadPoolExecutor | None = None
        self.refresh()

    # ------------------------------------------------------------------ stepping
    def step(self, ctrl: np.ndarray, nstep: int) -> np.ndarray:
        """Write ``ctrl`` (``(N, nu)``) to every simulator and advance each by ``nstep`` steps.

        Returns:
            ``(N,)`` bool: the simulators MuJoCo found unstable during this step (and reset to
            the model's initial state, see the module docstring).
        """
        if self._aliased:  # one simulator: nothing to gather, three counters to read
            self._ctrl_views[0][:] = ctrl[0]
            self.advance_one(nstep)
            return self.unstable
        if self._mocap_drivers:
            self._for_each_slice(self._step_driven, ctrl, nstep, self._mocap_plans(nstep))
        else:
            self._for_each_slice(self._step_plain, ctrl, nstep)
        self.version += 1
        for views, out in self._gather_plan:
            np.concatenate(views, out=out)
        counts = self._warnings[:, _UNSTABLE].sum(axis=1)
        np.not_equal(counts, self._unstable_counts, out=self.unstable)
        self._unstable_counts[:] = counts
        if np.count_nonzero(self.unstable):
            self._rearm(np.flatnonzero(self.unstable).tolist())
        return self.unstable

    def _rearm(self, rows: Sequence[int]) -> None:
        """Clear the instability counters of simulators just reported unstable (in ``MjData``, the cache and
        the stored counts). MuJoCo's automatic reset zeroes its counters and then counts the one warning, so
        a second divergence before the env resets the simulator would leave the count at 1, unseen;
        from zero, each divergence shows as a change."""
        views = self._cache["warnings"][1]
        for row in rows:
            views[row][_UNSTABLE] = 0
            self._warnings[row, _UNSTABLE] = 0
            self._unstable_counts[row] = 0

    def advance_one(self, nstep: int) -> bool:
        """:meth:`step` of a single simulator whose control is already written into ``datas[0].ctrl``.

        Returns whether MuJoCo found it unstable (also in :attr:`unstable`). Only for one simulator
        (:meth:`step` comes here itself after writing the control); a one-simulator env's single step
        writes the clipped action straight into ``ctrl`` and calls this. The state cache is a
        view of its ``MjData`` (nothing to gather) and its instability warnings are three counters read
        as scalars; driven mocap bodies go sub-step by sub-step as :meth:`step` drives them.
        """
        if self._mocap_drivers:
            self._step_driven(self._slices[0], None, nstep, self._mocap_plans(nstep))
        else:
            data = self.datas[0]
            mujoco.mj_step(self.model, data, nstep)
            if self.forward_after_step:
                mujoco.mj_forward(self.model, data)
            if self.post_constraint:
                mujoco.mj_rnePostConstraint(self.model, data)
        self.version += 1
        return self._check_one()

    def _check_one(self) -> bool:
        """Whether the one simulator turned unstable since the last check (sets :attr:`unstable`), read from
        its three instability counters as Python ints (no ``(N,)`` arrays for one simulator). Python copies of
        its count and flag (kept by this and :meth:`refresh`, their only writers at one simulator) spare the
        arrays' reads and writes on the usual step."""
        first, second, third = self._unstable_one.tolist()
        count = first + second + third
        if count == self._unstable_total_one:  # the usual step: the arrays already say so unless the last was unstable
            if self._unstable_flag_one:
                self.unstable[0] = self._unstable_flag_one = False
            return False
        self.unstable[0] = self._unstable_flag_one = True
        self._rearm((0,))
        self._unstable_total_one = 0
        return True

    def _for_each_slice(self, step_slice: Callable[..., None], *args) -> None:
        """``step_slice(rows, *args)`` for every slice of the simulators: inline, or one per thread."""
        if self.threads == 1:
            step_slice(self._slices[0], *args)
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="mujoco-batch")
        futures = [self._pool.submit(step_slice, rows, *args) for rows in self._slices]
        for future in futures:
            future.result()  # re-raises a worker's exception here

    def _step_plain(self, rows: range, ctrl: np.ndarray, nstep: int) -> None:
        """The fast path: one ``mj_step(nstep)`` call per simulator of ``rows``."""
        model, datas, ctrl_views = self.model, self.datas, self._ctrl_views
        forward, post = self.forward_after_step, self.post_constraint
        for i in rows:
            data = datas[i]
            ctrl_views[i][:] = ctrl[i]
            mujoco.mj_step(model, data, nstep)
            if forward:
                mujoco.mj_forward(model, data)
            if post:
                mujoco.mj_rnePostConstraint(model, data)

    @property
    def supports_aliased_single_step(self) -> bool:
        """Whether the state cache arrays are views of the one simulator's ``MjData`` (``num_sims == 1``):
        then a reader holding :meth:`qpos` / :meth:`qvel` rows sees every step without a copy, and
        :meth:`advance_one` / :meth:`contact_counts_one` apply (:mod:`~sg_torchrl.envs.physics_protocol`)."""
        return self._aliased

    @property
    def drives_mocap(self) -> bool:
        """Whether mocap bodies follow trajectories during steps (:meth:`drive_mocap`)."""
        return bool(self._mocap_drivers)

    def drive_mocap(self, mocap_ids: Sequence[int], trajectory: MocapTrajectory) -> None:
        """Move mocap bodies ``mocap_ids`` along ``trajectory`` before every physics sub-step.

        Args:
            mocap_ids: ``K`` mocap ids (rows of ``mocap_pos``).
            trajectory: called once per :meth:`step` with the simulation times at which its
                sub-steps start, ``(N, nstep)``; returns the positions those mocap bodies take
                before each sub-step, ``(N, nstep, K, 3)``.

        With a trajectory registered, :meth:`step` runs the sub-steps one ``mj_step`` at a time
        (Safety-Gymnasium moves its gremlins this way); without one it keeps the single
        ``mj_step(nstep)`` call per simulator.
        """
        ids = np.asarray(mocap_ids, dtype=np.int64)
        if len(ids) and (np.diff(ids) == 1).all():  # contiguous rows: a slice assignment is cheaper
            rows: slice | np.ndarray = slice(int(ids[0]), int(ids[-1]) + 1)
        else:
            rows = ids
        self._mocap_drivers.append((rows, trajectory))

    def _mocap_plans(self, nstep: int) -> list[tuple[slice | np.ndarray, np.ndarray]]:
        """Every driven mocap target of this step, vectorised: ``(rows, (N, nstep, K, 3) targets)`` per trajectory."""
        offsets = self._substep_offsets.get(nstep)
        if offsets is None:  # computed once per nstep: the same products every step
            offsets = self._substep_offsets[nstep] = (np.arange(nstep) * self.model.opt.timestep)[None]
        if self._aliased:  # one simulator: its clock as a Python float, the same sums
            times = self.datas[0].time + offsets
        else:
            start = np.fromiter((data.time for data in self.datas), dtype=np.float64, count=self.num_sims)
            times = start[:, None] + offsets
        return [(rows, trajectory(times)) for rows, trajectory in self._mocap_drivers]

    def _step_driven(self, sims: range, ctrl: np.ndarray | None, nstep: int,
                     plans: list[tuple[slice | np.ndarray, np.ndarray]]) -> None:
        """:meth:`step` with mocap trajectories (targets from :meth:`_mocap_plans`), sub-step by sub-step
        (``ctrl`` ``None``: the control is already in ``MjData``, :meth:`advance_one`)."""
        model = self.model
        for i in sims:
            data, mocap_pos = self.datas[i], self._mocap_views[i]
            if ctrl is not None:
                self._ctrl_views[i][:] = ctrl[i]
            if len(plans) == 1:  # one trajectory (the gremlins'): its rows of mocap_pos take each sub-step's targets
                rows, targets = plans[0]
                driven = mocap_pos[rows]  # a view when rows is a slice; an index array assigns through mocap_pos
                if isinstance(rows, slice):
                    for target in self._substeps(targets, i):
                        driven[...] = target
                        mujoco.mj_step(model, data)
                else:
                    for target in self._substeps(targets, i):
                        mocap_pos[rows] = target
                        mujoco.mj_step(model, data)
            else:
                paths = [(rows, targets[i]) for rows, targets in plans]  # this simulator's (nstep, K, 3) targets
                for k in range(nstep):
                    for rows, path in paths:
                        mocap_pos[rows] = path[k]
                    mujoco.mj_step(model, data)
            if self.forward_after_step:
                mujoco.mj_forward(model, data)
            if self.post_constraint:
                mujoco.mj_rnePostConstraint(model, data)

    def _substeps(self, targets: np.ndarray, i: int) -> np.ndarray | list[np.ndarray]:
        """Simulator ``i``'s targets ``(nstep, K, 3)`` of a trajectory's ``(N, nstep, K, 3)``, one per sub-step.

        One simulator: a list of views kept while the trajectory returns the very same array (the gremlins'
        rewrites its buffer in place), since making ten views per step costs as much as the ten writes
        they feed; the list holds that array, so no other array can pass the identity test.
        """
        if not self._aliased:
            return targets[i]
        kept = self._substep_views
        if kept is None or kept[0] is not targets:
            kept = self._substep_views = (targets, list(targets[0]))
        return kept[1]

    def reset(
        self,
        indices: Sequence[int],
        qpos: np.ndarray,
        qvel: np.ndarray,
        mocap_pos: np.ndarray | None = None,
        mocap_quat: np.ndarray | None = None,
    ) -> None:
        """Reset simulators ``indices`` to the given joint state (rows of ``qpos``/``qvel``).

        Data is cleared with ``mj_resetData`` first (time, warm-starts, activations), then
        the state is written and ``mj_forward`` recomputes every derived quantity, exactly as
        gymnasium's ``MujocoEnv.reset`` + ``set_state`` do. No model is compiled.
        ``mocap_pos`` / ``mocap_quat`` (rows of ``(nmocap, 3)`` / ``(nmocap, 4)``), when given,
        place the mocap bodies (``mj_resetData`` puts them back at the model's positions).
        """
        model = self.model
        for row, index in enumerate(indices):
            data = self.datas[index]
            mujoco.mj_resetData(model, data)
            data.qpos[:] = qpos[row]
            data.qvel[:] = qvel[row]
            if mocap_pos is not None:
                data.mocap_pos[:] = mocap_pos[row]
            if mocap_quat is not None:
                data.mocap_quat[:] = mocap_quat[row]
            mujoco.mj_forward(model, data)
            if self.post_constraint:
                mujoco.mj_rnePostConstraint(model, data)
        self.refresh(indices)

    def refresh(self, indices: Sequence[int] | None = None) -> None:
        """Re-read the state cache from ``MjData`` (all simulators, or ``indices``).

        Only needed after writing into ``self.datas[i]`` directly.
        """
        rows = range(self.num_sims) if indices is None else [int(i) for i in indices]
        if not self._aliased:  # an aliased cache is the MjData itself
            for cache, views in self._cache.values():
                for i in rows:
                    cache[i] = views[i]
        rows = list(rows)
        self._unstable_counts[rows] = self._warnings[rows, _UNSTABLE].sum(axis=1)
        self.unstable[rows] = False
        if self._aliased:  # _check_one's copies
            self._unstable_total_one, self._unstable_flag_one = self._unstable_counts.item(0), False
        self.version += 1

    def set_mocap_pos(self, index: int, mocap_id: int, pos: np.ndarray) -> None:
        """Move mocap body ``mocap_id`` of simulator ``index`` to ``pos`` (3,), without a forward pass.

        Positions derived from it (``xpos``) follow at the next :meth:`step`; a mocap body without
        collision geoms does not influence the dynamics, so nothing else needs recomputing.
        """
        self.datas[index].mocap_pos[mocap_id] = pos

    def close(self) -> None:
        """Stop the stepping threads (if any); a later :meth:`step` starts them again."""
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True)

    def __getstate__(self) -> dict:
        # Copies and pickles get no thread pool (it belongs to this object); they start their own.
        state = dict(self.__dict__)
        state["_pool"] = None
        state["_substep_views"] = None  # views come back as copies: the copy makes its own
        return state

    # ------------------------------------------------------------------ snapshots
    def get_state(self) -> np.ndarray:
        """Everything the next step depends on, per simulator, ``(N, nstate)`` (``mjSTATE_INTEGRATION``).

        ``mjSTATE_FULLPHYSICS`` is not enough for a bit-exact resume: the constraint solver starts
        from ``qacc_warmstart``, and a restored simulator without it drifts by solver tolerance,
        which chaotic robots amplify within tens of steps.
        """
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        state = np.empty((self.num_sims, mujoco.mj_stateSize(self.model, spec)))
        for row, data in zip(state, self.datas):
            mujoco.mj_getState(self.model, data, row, spec)
        return state

    def set_state(self, state: np.ndarray) -> None:
        """Restore :meth:`get_state` output (checkpoint/resume); derived quantities are recomputed."""
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        for row, data in zip(state, self.datas):
            mujoco.mj_setState(self.model, data, row, spec)
            mujoco.mj_forward(self.model, data)
            if self.post_constraint:
                mujoco.mj_rnePostConstraint(self.model, data)
        self.refresh()

    # ------------------------------------------------------------------ state views
    @property
    def timestep(self) -> float:
        return float(self.model.opt.timestep)

    @property
    def ctrl_range(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-actuator ``(low, high)`` control limits."""
        return self._ctrl_low, self._ctrl_high

    def qpos(self) -> np.ndarray:
        """Joint positions, ``(N, nq)``, from the state cache (updated in place; do not write)."""
        return self._qpos

    def qvel(self) -> np.ndarray:
        """Joint velocities, ``(N, nv)``, from the state cache (updated in place; do not write)."""
        return self._qvel

    def field(self, name: str) -> np.ndarray:
        """A cached ``MjData`` array (one of ``fields``), ``(N, ...)`` (updated in place; do not write)."""
        if name not in self._cache or name == "warnings":
            cached = [key for key in self._cache if key != "warnings"]
            raise KeyError(f"{name!r} is not cached; pass it in `fields` (cached: {cached})")
        return self._cache[name][0]

    def gather(self, field: str) -> np.ndarray:
        """Stack any ``MjData`` array attribute (``"xpos"``, ``"cinert"``, ...) into a new ``(N, ...)`` array."""
        return np.stack([getattr(data, field) for data in self.datas])
