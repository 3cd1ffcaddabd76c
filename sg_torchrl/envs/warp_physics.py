"""Batched simulators on MuJoCo Warp: :class:`WarpBatch`, the array-native physics backend.

:class:`WarpBatch` implements :class:`~sg_torchrl.envs.physics_protocol.PhysicsBatch` (``step``,
``reset``, ``qpos()``, ``field()``, ``get_state``/``set_state``, ``unstable``, ``version``, ...)
over `MuJoCo Warp <https://github.com/google-deepmind/mujoco_warp>`_: one ``mjw.Model`` put on the
device once, one ``mjw.Data`` holding all ``N`` worlds as ``(N, ...)`` device arrays, every kernel
launched once for the whole batch. On a CUDA device this is how thousands of simulators step at
GPU throughput; on Warp's ``"cpu"`` device the same code runs (slowly, but it lets CI check the
backend without a GPU).

Zero-copy to torch: at construction every ``Data`` array the backend touches is wrapped once with
``wp.to_torch`` (a tensor aliasing the Warp buffer, no copy); :meth:`torch_view` hands them out, so
GPU-side consumers can read the state without leaving the device. The numpy accessors the envs use
(:meth:`qpos`, :meth:`qvel`, :meth:`field`) return float64 host copies, made lazily, at most once
per :attr:`version` (one device-to-host transfer per field and step, only for fields read).

Precision: MuJoCo Warp computes in float32, MuJoCo C in float64; trajectories agree to float32
rounding at first and drift apart like any two float implementations of chaotic dynamics.

Divergence: MuJoCo C resets a simulator whose ``qpos``/``qvel``/``qacc`` becomes non-finite or
larger than ``mjMAXVAL`` (1e10) and raises a warning; MuJoCo Warp does neither. :meth:`step` checks
the same condition per world after the ``nstep`` physics steps, reports the offenders in
:attr:`unstable` and resets them to the model's initial state, so one bad world never takes down
the others (a diverged world stays diverged until the end of the step; C MuJoCo resets it within
the sub-step).

Sizes: contacts and constraint rows live in preallocated buffers (``nconmax`` contacts and
``njmax`` rows per world). A world that needs more silently drops them; :meth:`step` warns once when
Warp reports such an overflow, naming the keyword to raise. MuJoCo Warp's own default
(``njmax=64`` for these models) is too small for the two-hand scene: with random actions it uses up
to 95 rows (``nefc``) and 11 contacts per world, hence the defaults below.

Partial resets: MuJoCo Warp's ``forward`` runs on every world (there is no per-world mask), so
:meth:`reset` saves the cached ``fields`` of the worlds it does not reset and puts them back after
the forward pass: those worlds are left exactly as they were.

Checkpoints (:meth:`get_state`): per world, the concatenation of :data:`STATE_FIELDS` (flattened, in
that order) as float64, ``(N, nstate)``; this is not MuJoCo's ``mjSTATE_INTEGRATION`` layout, so a
checkpoint resumes only on the backend that wrote it.

Rendering: :attr:`datas` is a sequence whose item ``i`` copies world ``i`` into a host ``MjData``
(``mujoco_warp.get_data_into``) on access, so :class:`~sg_torchrl.envs.rendering.RenderMixin` works
unchanged. Those copies are read-only snapshots: writing into them does not reach the device.

Not ported: contact counting (``count_contacts``/``contact_counts``) and driven mocap bodies
(``drive_mocap``), which only Safety-Gymnasium's navigation tasks need.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np
import torch

from sg_torchrl.envs.physics_protocol import PhysicsBatch

__all__ = ["STATE_FIELDS", "WarpBatch", "default_warp_device", "import_warp"]

INSTALL_HINT = "pip install 'sg_torchrl[warp]'"
#: ``Data`` arrays that make up one world's checkpoint (:meth:`WarpBatch.get_state`), in this order.
STATE_FIELDS = ("time", "qpos", "qvel", "act", "qacc_warmstart", "ctrl", "qfrc_applied", "xfrc_applied",
                "mocap_pos", "mocap_quat")
#: What MuJoCo's ``mj_resetData`` zeroes besides the state written by :meth:`WarpBatch.reset`.
_ZEROED_ON_RESET = ("time", "act", "act_dot", "qacc_warmstart", "qacc", "qfrc_applied", "xfrc_applied", "ctrl")
#: Zeroed too, as ``mujoco_warp.reset_data`` does: Warp's per-world buffer-overflow flags (they are sticky).
_CLEARED_ON_RESET = ("overflow",)
_MAXVAL = 1e10  # MuJoCo's mjMAXVAL: larger |qpos|, |qvel|, |qacc| count as diverged, as in mj_checkPos & co.
DEFAULT_NCONMAX = 64
DEFAULT_NJMAX = 256


def import_warp() -> tuple[Any, Any]:
    """``(warp, mujoco_warp)``, imported on first use; an ``ImportError`` with the install hint otherwise."""
    try:
        import mujoco_warp
        import warp
    except ImportError as error:
        raise ImportError(f"backend='warp' needs MuJoCo Warp, which is not installed: {INSTALL_HINT} "
                          f"({error})") from error
    return warp, mujoco_warp


def default_warp_device() -> str:
    """``"cuda:0"`` when both Warp and torch see a CUDA device, else ``"cpu"``.

    Both, because the zero-copy views need a CUDA build of torch to alias Warp's CUDA buffers.
    """
    wp, _ = import_warp()
    return "cuda:0" if wp.is_cuda_available() and torch.cuda.is_available() else "cpu"


class _HostDatas(Sequence[mujoco.MjData]):
    """``datas[i]``: world ``i`` copied into a host ``MjData`` on access (refreshed once per version)."""

    def __init__(self, batch: WarpBatch) -> None:
        self._batch = batch
        self._copies: dict[int, tuple[int, mujoco.MjData]] = {}

    def __len__(self) -> int:
        return self._batch.num_sims

    def __getitem__(self, index):  # type: ignore[override]
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        index = int(index)
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(f"world {index} out of range for {len(self)} worlds")
        batch = self._batch
        version, data = self._copies.get(index, (-1, None))
        if data is None:
            data = mujoco.MjData(batch.model)
        if version != batch.version:
            batch.mjw.get_data_into(data, batch.model, batch.warp_data, index)
            self._copies[index] = (batch.version, data)
        return data


class WarpBatch(PhysicsBatch):
    """``num_sims`` worlds of one model stepped by MuJoCo Warp (see the module docstring).

    Args:
        model: the compiled host model (kept as :attr:`model` for the renderer and the tasks).
        num_sims: number of worlds ``N``.
        post_constraint / fields / forward_after_step: as for :class:`~sg_torchrl.envs.physics.MujocoBatch`.
        device: Warp device (``"cuda:0"``, ``"cpu"``, ...); ``None``: :func:`default_warp_device`.
        nconmax: contacts per world to allocate room for.
        njmax: constraint rows per world to allocate room for.
        graph: capture the ``nstep`` loop of :meth:`step` in a CUDA graph (CUDA devices only;
            ``None``: whenever the device is a CUDA device).
    """

    threads = 1  # MuJoCo Warp parallelises over worlds itself

    def __init__(
        self,
        model: mujoco.MjModel,
        num_sims: int,
        *,
        post_constraint: bool = False,
        fields: Sequence[str] = (),
        forward_after_step: bool = False,
        device: str | None = None,
        nconmax: int = DEFAULT_NCONMAX,
        njmax: int = DEFAULT_NJMAX,
        graph: bool | None = None,
    ) -> None:
        if isinstance(num_sims, bool) or not isinstance(num_sims, int) or num_sims < 1:
            raise ValueError(f"num_sims must be a positive integer, got {num_sims!r}")
        self.wp, self.mjw = import_warp()
        self.device = default_warp_device() if device is None else str(device)
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise RuntimeError(f"Warp device {self.device!r} needs a CUDA build of torch for the zero-copy views "
                               f"(this torch {torch.__version__} sees no CUDA); use warp_device='cpu'")
        self.model = model
        self.num_sims = num_sims
        self.post_constraint = post_constraint
        self.forward_after_step = forward_after_step
        self._fields = tuple(fields)
        with self.wp.ScopedDevice(self.device):
            self.warp_model = self.mjw.put_model(model)
            self.warp_data = self.mjw.make_data(model, nworld=num_sims, nconmax=nconmax, njmax=njmax)
        self._on_cuda = self.wp.get_device(self.device).is_cuda
        self._use_graph = self._on_cuda if graph is None else bool(graph) and self._on_cuda
        self._graphs: dict[int, Any] = {}
        self._warmed: set[int] = set()
        # Zero-copy torch views of every Data array used here (module docstring).
        names = {"qpos", "qvel", "qacc", "mocap_pos", "mocap_quat", "act_dot", "overflow", *STATE_FIELDS, *self._fields}
        missing = [name for name in names if not hasattr(self.warp_data, name)]
        if missing:
            raise ValueError(f"MuJoCo Warp's Data has no {missing}")
        self._views: dict[str, torch.Tensor] = {name: self.wp.to_torch(getattr(self.warp_data, name)) for name in names}
        self.torch_device = self._views["qpos"].device
        # The model's initial state, for diverged worlds: qpos0, qvel 0, mocap bodies where the model puts them.
        mocap_bodies = np.flatnonzero(model.body_mocapid >= 0)
        mocap_bodies = mocap_bodies[np.argsort(model.body_mocapid[mocap_bodies])]
        self._mocap_pos0 = model.body_pos[mocap_bodies].copy()
        self._mocap_quat0 = model.body_quat[mocap_bodies].copy()
        self._host: dict[str, tuple[int, np.ndarray]] = {}
        self.unstable = np.zeros(num_sims, dtype=bool)  # worlds reset during the last step after diverging
        self._ctrl_low = model.actuator_ctrlrange[:, 0].copy()
        self._ctrl_high = model.actuator_ctrlrange[:, 1].copy()
        self._overflow_warned = False
        ignored = int(self.mjw.OverflowType.ITERATIONS)  # hitting the iteration cap drops nothing
        self._overflow_mask = ~ignored
        #: bumped whenever the state changes (step, reset, set_state): lets readers cache derived values
        self.version = 0
        self.datas: Sequence[mujoco.MjData] = _HostDatas(self)
        self._forward()

    # ------------------------------------------------------------------ device calls
    def _on_device(self, work, *args) -> None:
        """Run Warp ``work(*args)`` between torch's pending writes and torch's next reads.

        On CUDA, torch and Warp launch on different streams: the torch views (``ctrl``, reset rows)
        must be written before Warp's kernels read them, and Warp's results complete before torch
        reads them. Two device synchronisations per call (tens of microseconds) buy that; when
        :meth:`step` returns, the device state and :meth:`torch_view` tensors are final.
        """
        if self._on_cuda:
            torch.cuda.synchronize(self.torch_device)
        with self.wp.ScopedDevice(self.device):
            work(*args)
        if self._on_cuda:
            self.wp.synchronize_device(self.device)

    def _forward(self) -> None:
        """Recompute every derived quantity of every world from its state."""
        def forward() -> None:
            self.mjw.forward(self.warp_model, self.warp_data)
            if self.post_constraint:
                self.mjw.rne_postconstraint(self.warp_model, self.warp_data)

        self._on_device(forward)

    def _advance(self, nstep: int) -> None:
        """``nstep`` physics steps, then the optional forward/post-constraint passes (device work only)."""
        model, data = self.warp_model, self.warp_data
        for _ in range(nstep):
            self.mjw.step(model, data)
        if self.forward_after_step:
            self.mjw.forward(model, data)
        if self.post_constraint:
            self.mjw.rne_postconstraint(model, data)

    def _launch(self, nstep: int) -> None:
        """:meth:`_advance`, replayed from a CUDA graph (captured on the second call per ``nstep``) on CUDA devices."""
        if not self._use_graph:
            self._advance(nstep)
            return
        graph = self._graphs.get(nstep)
        if graph is None:
            if nstep not in self._warmed:  # first call: load the kernels outside any capture
                self._warmed.add(nstep)
                self._advance(nstep)
                return
            try:
                with self.wp.ScopedCapture() as capture:
                    self._advance(nstep)
            except Exception as error:  # e.g. a host synchronisation inside a kernel sequence
                warnings.warn(f"CUDA graph capture failed ({error}); stepping without graphs", RuntimeWarning,
                              stacklevel=5)
                self._use_graph = False
                self._advance(nstep)
                return
            graph = self._graphs[nstep] = capture.graph
        self.wp.capture_launch(graph)

    # ------------------------------------------------------------------ stepping
    def step(self, ctrl: np.ndarray, nstep: int) -> np.ndarray:
        """Write ``ctrl`` (``(N, nu)``) to every world and advance each by ``nstep`` steps.

        Returns:
            ``(N,)`` bool: the worlds that diverged during this step and were reset to the model's
            initial state (module docstring).
        """
        self._views["ctrl"].copy_(torch.as_tensor(np.asarray(ctrl)))
        self._on_device(self._launch, nstep)
        self._reset_diverged()
        self._check_overflow()
        self.version += 1
        return self.unstable

    def _reset_diverged(self) -> None:
        """Fill :attr:`unstable` and reset the worlds it names (module docstring)."""
        views = self._views
        state = torch.cat([views["qpos"], views["qvel"], views["qacc"]], dim=1)
        bad = ~(state.abs() <= _MAXVAL).all(dim=1)  # NaN compares False
        self.unstable[:] = bad.cpu().numpy()
        if self.unstable.any():
            rows = np.flatnonzero(self.unstable)
            n = len(rows)
            self._write_reset(rows, np.tile(self.model.qpos0, (n, 1)), np.zeros((n, self.model.nv)),
                              np.tile(self._mocap_pos0, (n, 1, 1)), np.tile(self._mocap_quat0, (n, 1, 1)))

    def _check_overflow(self) -> None:
        """Warn once when a world ran out of contact or constraint buffer (module docstring)."""
        if self._overflow_warned:
            return
        overflow = self._views["overflow"] & self._overflow_mask
        if bool(overflow.any()):
            self._overflow_warned = True
            flags = sorted(set(overflow.cpu().tolist()) - {0})
            nconmax, njmax = self.warp_data.naconmax // self.num_sims, self.warp_data.njmax
            warnings.warn(f"MuJoCo Warp ran out of contact or constraint buffer in some worlds (OverflowType flags "
                          f"{flags}) and dropped contacts or constraint rows: raise nconmax (now {nconmax}) or njmax "
                          f"(now {njmax}), e.g. warp_options={{'njmax': {2 * njmax}}}", RuntimeWarning, stacklevel=3)

    def reset(
        self,
        indices: Sequence[int],
        qpos: np.ndarray,
        qvel: np.ndarray,
        mocap_pos: np.ndarray | None = None,
        mocap_quat: np.ndarray | None = None,
    ) -> None:
        """Reset worlds ``indices`` to the given joint state (rows of ``qpos``/``qvel``).

        As :meth:`MujocoBatch.reset <sg_torchrl.envs.physics.MujocoBatch.reset>`: time, activations,
        warm-starts, controls and applied forces are cleared, mocap bodies go back to the model's
        positions unless ``mocap_pos``/``mocap_quat`` are given, then a forward pass recomputes the
        derived quantities. The other worlds are left untouched (module docstring).
        """
        rows = np.asarray(indices, dtype=np.int64).reshape(-1)
        if len(rows):
            self._write_reset(rows, qpos, qvel, mocap_pos, mocap_quat)
            self.unstable[rows] = False
        self.version += 1

    def _write_reset(self, rows: np.ndarray, qpos: np.ndarray, qvel: np.ndarray,
                     mocap_pos: np.ndarray | None, mocap_quat: np.ndarray | None) -> None:
        views, n = self._views, len(rows)
        index = torch.as_tensor(rows, device=self.torch_device)
        for name in _ZEROED_ON_RESET + _CLEARED_ON_RESET:
            views[name][index] = 0
        if mocap_pos is None:
            mocap_pos = np.tile(self._mocap_pos0, (n, 1, 1))
        if mocap_quat is None:
            mocap_quat = np.tile(self._mocap_quat0, (n, 1, 1))
        for name, values in (("qpos", qpos), ("qvel", qvel), ("mocap_pos", mocap_pos), ("mocap_quat", mocap_quat)):
            view = views[name]
            view[index] = torch.as_tensor(np.asarray(values), dtype=view.dtype).reshape(n, *view.shape[1:]).to(view.device)
        keep = torch.ones(self.num_sims, dtype=torch.bool, device=self.torch_device)
        keep[index] = False
        saved = {name: views[name][keep] for name in self._fields}  # advanced indexing: copies
        self._forward()
        for name, values in saved.items():
            views[name][keep] = values

    def refresh(self, indices: Sequence[int] | None = None) -> None:
        """Invalidate the host copies (the device arrays are the state; nothing else to re-read)."""
        self.version += 1

    def set_mocap_pos(self, index: int, mocap_id: int, pos: np.ndarray) -> None:
        """Move mocap body ``mocap_id`` of world ``index`` to ``pos`` (3,), without a forward pass."""
        view = self._views["mocap_pos"]
        view[index, mocap_id] = torch.as_tensor(np.asarray(pos), dtype=view.dtype).to(view.device)

    @property
    def drives_mocap(self) -> bool:
        return False  # drive_mocap refuses: no trajectory is ever registered

    def drive_mocap(self, mocap_ids: Sequence[int], trajectory) -> None:
        raise NotImplementedError("driven mocap bodies (navigation's gremlins) are not ported to backend='warp'")

    def count_contacts(self, geoms_a: np.ndarray, geoms_b: np.ndarray) -> np.ndarray:
        raise NotImplementedError("contact counting (navigation tasks) is not ported to backend='warp'; "
                                  "use backend='cpu'")

    def contact_counts(self, geoms: np.ndarray) -> np.ndarray:
        raise NotImplementedError("contact counting (navigation tasks) is not ported to backend='warp'; "
                                  "use backend='cpu'")

    def close(self) -> None:
        """Drop the captured CUDA graphs (device memory is freed with the object)."""
        self._graphs.clear()

    def __reduce__(self):
        raise TypeError("WarpBatch holds device memory and cannot be pickled or copied; build a new env and "
                        "move the state with get_state()/set_state()")

    # ------------------------------------------------------------------ snapshots
    def get_state(self) -> np.ndarray:
        """Per world, :data:`STATE_FIELDS` flattened and concatenated, float64, ``(N, nstate)``."""
        parts = [self._views[name].reshape(self.num_sims, -1).to(torch.float64) for name in STATE_FIELDS]
        return torch.cat(parts, dim=1).cpu().numpy()

    def set_state(self, state: np.ndarray) -> None:
        """Restore :meth:`get_state` output; derived quantities are recomputed."""
        state = torch.as_tensor(np.asarray(state))
        views = [self._views[name] for name in STATE_FIELDS]
        widths = [int(np.prod(view.shape[1:], dtype=np.int64)) for view in views]
        if tuple(state.shape) != (self.num_sims, sum(widths)):
            raise ValueError(f"state has shape {tuple(state.shape)}, expected {(self.num_sims, sum(widths))} "
                             f"columns (a WarpBatch checkpoint of this model and batch size?)")
        for view, part in zip(views, torch.split(state, widths, dim=1)):
            view.copy_(part.reshape(view.shape))
        self._forward()
        self.unstable[:] = False
        self.version += 1

    # ------------------------------------------------------------------ state views
    @property
    def timestep(self) -> float:
        return float(self.model.opt.timestep)

    @property
    def ctrl_range(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-actuator ``(low, high)`` control limits."""
        return self._ctrl_low, self._ctrl_high

    def torch_view(self, name: str) -> torch.Tensor:
        """The ``(N, ...)`` device tensor aliasing ``Data.<name>`` (zero-copy; writing into it writes the state)."""
        view = self._views.get(name)
        if view is None:
            if not hasattr(self.warp_data, name):
                raise KeyError(f"MuJoCo Warp's Data has no {name!r}")
            view = self._views[name] = self.wp.to_torch(getattr(self.warp_data, name))
        return view

    def _host_copy(self, name: str) -> np.ndarray:
        """A float64 host copy of ``Data.<name>``, refreshed at most once per :attr:`version`."""
        version, array = self._host.get(name, (-1, None))
        if version != self.version:
            values = self.torch_view(name).detach().cpu().numpy()
            if array is None:
                array = np.empty(values.shape, dtype=np.float64)
            np.copyto(array, values)
            self._host[name] = (self.version, array)
        return array

    def qpos(self) -> np.ndarray:
        """Joint positions, ``(N, nq)``, float64 host copy (do not write)."""
        return self._host_copy("qpos")

    def qvel(self) -> np.ndarray:
        """Joint velocities, ``(N, nv)``, float64 host copy (do not write)."""
        return self._host_copy("qvel")

    def field(self, name: str) -> np.ndarray:
        """A ``Data`` array named in ``fields``, ``(N, ...)`` float64 host copy (do not write)."""
        if name not in self._fields:
            raise KeyError(f"{name!r} is not cached; pass it in `fields` (cached: {list(self._fields)})")
        return self._host_copy(name)

    def gather(self, field: str) -> np.ndarray:
        """Any ``Data`` array (``"xpos"``, ``"cinert"``, ...) as a new ``(N, ...)`` host array."""
        return self.torch_view(field).detach().cpu().numpy().copy()
