"""A seed group's replay buffers: one TorchRL ``ReplayBuffer`` per seed, kept inside the run directory.

Each seed has its own ``ReplayBuffer`` (``LazyMemmapStorage`` + ``RandomSampler``, the seed's own
sampling generator, the ``replay`` stream of :mod:`sg_torchrl.seeding`), so its samples are the same
whatever the group. One buffer per seed rather than one storage with a seed dimension: TorchRL's
samplers draw one index set per buffer, and a seed's draws must not depend on the other seeds (a seed
group trains each seed as its ``--seed`` run). A transition is one float32 row: observation, action,
reward, cost, terminated, next observation (one gather per sample instead of one per field).

**On disk: the live memory map is the store.** Each storage's memory map lives in
``<run dir>/replay/live/seed-XXX/storage/`` (never outside the run directory). A checkpoint costs what was
written since the previous one, not the storage's size (capacity x row bytes: about 180 MB per seed for
SafetyHalfCheetahVelocity-v1 at OmniSafe's 1,000,000):

* :meth:`SeedReplay.checkpoint` flushes each memory map to disk (``fsync``: the pages written since the last
  checkpoint) through TorchRL's in-place ``storage.dumps`` (the storage is already at that path: no copy),
  and returns what the checkpoint records: the storage's metadata (its length), the writer's
  ``state_dict`` (cursor, write count); the sampling generator's state is in the seed's entry;
* after a checkpoint the writer only overwrites rows the checkpoint did not count, until the buffer has
  wrapped: then it overwrites rows the checkpoint holds. Before it does, the old contents of those rows
  are appended to the checkpoint's undo file ``undo-NNNNNN.bin`` beside the memory map (blocks of
  :data:`UNDO_BLOCK` rows, each ``fsync`` ed before the rows are overwritten), so an undo file holds at
  most the rows written since its checkpoint, plus one block;
* ``--resume`` (:meth:`SeedReplay.load`) reopens the memory map in place (``storage.loads`` of its own
  path, with the checkpoint's metadata), writes the undo file's rows back, and loads the writer's state:
  the buffer is what it was at the checkpoint, bit for bit. The rows written after the checkpoint beyond
  its length are never sampled (the length says so) and are overwritten by the resumed run.

A checkpoint's undo file starts empty when the checkpoint is taken and becomes the one written to once
the checkpoint is on disk (:meth:`SeedReplay.commit`, which removes the older ones): a run killed between
a replay write and its checkpoint, or while the checkpoint is written, resumes from the last checkpoint
on disk with that checkpoint's undo file. Nothing is pickled (JSON, raw float32 rows, memory maps). A
write that fails raises :class:`~sg_torchrl.train.writes.RunWriteError`.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torch import Tensor
from torchrl.data import LazyMemmapStorage, ReplayBuffer
from torchrl.data.replay_buffers import RandomSampler

from sg_torchrl.train.writes import RunWriteError, append_bytes, make_dirs, write_atomic, writing

__all__ = ["REPLAY_DIR", "SeedReplay", "UNDO_BLOCK"]

#: The replay buffers' folder in a run directory (removed with the run's files by ``--overwrite``).
REPLAY_DIR = "replay"
#: Rows saved to an undo file at a time (one ``fsync`` each), ahead of the writer.
UNDO_BLOCK = 1024
_METADATA = "storage_metadata.json"  # TorchRL's storage checkpointer's file: the storage's length


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)  # Linux: also the pages written through a memory map of the file
    finally:
        os.close(fd)


class _UndoLog:
    """One buffer's rows that the last checkpoint holds and the writer has overwritten since, saved first.

    The writer writes positions ``(cursor + j) % capacity`` for ``j = 0, 1, ...`` after the checkpoint; those
    below the checkpoint's ``length`` held its rows. Positions ``j < saved`` are covered (saved, or not the
    checkpoint's); a position is saved once (its first overwrite), so ``j >= capacity`` needs nothing.
    """

    def __init__(self, path: Path | None, cursor: int, length: int, capacity: int) -> None:
        self.path, self.cursor, self.length, self.capacity = path, cursor, length, capacity
        self.written = self.saved = 0

    def before_write(self, buffer: ReplayBuffer, rows: int) -> None:
        """Save the old contents of the checkpoint's rows that the next ``rows`` writes overwrite."""
        end = min(self.written + rows, self.capacity)
        self.written += rows
        if self.path is None or end <= self.saved:
            return
        stop = min(self.capacity, max(end, self.saved + UNDO_BLOCK))
        positions = (self.cursor + torch.arange(self.saved, stop)) % self.capacity
        positions = positions[positions < self.length]
        self.saved = stop
        if len(positions):
            old = buffer.storage.get(positions).get("row")
            record = torch.cat([positions.view(-1, 1).view(torch.float32), old], 1)  # the index's bits, the row
            append_bytes(self.path, record.numpy().tobytes(), sync=True)

    @staticmethod
    def read(path: Path, width: int) -> tuple[Tensor, Tensor]:
        """The saved ``(positions, rows)``; a last record cut short by a crash is ignored (its rows were not
        overwritten yet: the write waits for the record's ``fsync``)."""
        data = path.read_bytes()
        whole = len(data) - len(data) % (4 * (width + 2))
        if not whole:
            return torch.zeros(0, dtype=torch.int64), torch.zeros(0, width)
        table = torch.frombuffer(bytearray(data[:whole]), dtype=torch.float32).view(-1, width + 2)
        return table[:, :2].contiguous().view(torch.int64).view(-1), table[:, 2:].clone()


class SeedReplay:
    """S seeds' replay buffers of ``(obs, action, reward, cost, terminated, next obs)`` rows.

    Args:
        run_dir: the run's directory (the group's for a seed group).
        seeds: the seeds, one buffer each.
        generators: each seed's sampling generator.
        capacity, batch_size: per buffer.
        obs_dim, action_dim: the row's layout.
    """

    def __init__(self, run_dir: Path, seeds: Sequence[int], generators: Sequence[torch.Generator], *, capacity: int,
                 batch_size: int, obs_dim: int, action_dim: int) -> None:
        self.run_dir, self.seeds, self.generators = Path(run_dir), list(seeds), list(generators)
        self.capacity, self.batch_size = int(capacity), int(batch_size)
        self.widths = (obs_dim, action_dim, 1, 1, 1, obs_dim)
        self.buffers = [self._buffer(index) for index in range(len(self.seeds))]
        self.undo = [_UndoLog(None, 0, 0, self.capacity) for _ in self.seeds]  # nothing checkpointed yet
        self._pending: list[_UndoLog] | None = None

    @property
    def live(self) -> Path:
        return self.run_dir / REPLAY_DIR / "live"

    def _seed_dir(self, index: int) -> Path:
        return self.live / f"seed-{self.seeds[index]:03d}"

    def _buffer(self, index: int) -> ReplayBuffer:
        # existsok: the memory map of a run killed before its first checkpoint is overwritten, not refused
        storage = LazyMemmapStorage(self.capacity, scratch_dir=self._seed_dir(index) / "storage", existsok=True)
        return ReplayBuffer(storage=storage, sampler=RandomSampler(), batch_size=self.batch_size,
                            generator=self.generators[index])

    def __len__(self) -> int:
        return len(self.buffers[0])

    def extend(self, obs: Tensor, action: Tensor, reward: Tensor, cost: Tensor, terminated: Tensor,
               next_obs: Tensor) -> None:
        """Add one step of every seed's simulators: each field ``(S, N, k)``."""
        rows = torch.cat([obs, action, reward, cost, terminated.to(obs.dtype), next_obs], -1)
        with writing(self.live):
            for buffer, undo, seed_rows in zip(self.buffers, self.undo, rows):
                undo.before_write(buffer, len(seed_rows))
                buffer.extend(TensorDict({"row": seed_rows}, batch_size=seed_rows.shape[:1]))

    def sample(self, device: torch.device | str | None = None) -> tuple[Tensor, ...]:
        """One minibatch per seed: ``obs``, ``action`` ``(S, B, k)``; ``reward``, ``cost`` ``(S, B)``;
        ``terminated`` ``(S, B)`` bool; ``next_obs``.

        The buffers stay on the host; the drawn rows go to ``device`` (default: stay) in one copy, then split there.
        """
        rows = torch.stack([buffer.sample().get("row") for buffer in self.buffers])
        if device is not None:
            rows = rows.to(device, non_blocking=True)
        obs, action, reward, cost, terminated, next_obs = rows.split(self.widths, -1)
        return obs, action, reward.squeeze(-1), cost.squeeze(-1), terminated.squeeze(-1) > 0.5, next_obs

    # ------------------------------------------------------------------ checkpoints
    def checkpoint(self, epoch: int) -> list[dict[str, Any] | None]:
        """Flush every buffer for the checkpoint of ``epoch`` and start its (empty) undo files; returns each
        seed's entry for the checkpoint (``None``: an empty buffer). :meth:`commit` once the checkpoint is on disk."""
        entries, pending = [], []
        with writing(self.live):
            for index, buffer in enumerate(self.buffers):
                storage = buffer.storage
                if not len(buffer):
                    entries.append(None)
                    pending.append(_UndoLog(None, 0, 0, self.capacity))
                    continue
                folder = self._seed_dir(index) / "storage"
                storage.dumps(folder)  # in place: TorchRL writes the metadata only (the storage is at that path)
                for path in (*folder.glob("*.memmap"), folder / _METADATA):
                    _fsync(path)
                writer = buffer.writer.state_dict()
                undo = self._seed_dir(index) / f"undo-{epoch:06d}.bin"
                write_atomic(undo, b"")
                entries.append({"storage": (folder / _METADATA).read_text(), "writer": writer, "undo": undo.name})
                pending.append(_UndoLog(undo, int(writer["_cursor"]), len(storage), self.capacity))
        self._pending = pending
        return entries

    def commit(self) -> None:
        """The checkpoint of the last :meth:`checkpoint` is on disk: its undo files take the overwritten rows
        from now on, and the older undo files (and replay dumps of earlier versions) are removed."""
        if self._pending is None:
            return
        self.undo, self._pending = self._pending, None
        self._prune()

    def _prune(self) -> None:
        keep = {log.path for log in self.undo}
        for path in self.live.glob("seed-*/undo-*.bin"):
            if path not in keep:
                path.unlink(missing_ok=True)
        for path in (self.run_dir / REPLAY_DIR).glob("epoch-*"):  # the full dumps an earlier version wrote
            shutil.rmtree(path, ignore_errors=True)

    def load(self, entries: list[dict[str, Any] | None] | str | None) -> None:
        """Put every buffer back to the checkpoint's state (``entries``: what :meth:`checkpoint` returned).

        Raises:
            RunWriteError: the live memory maps or undo files are missing (the run directory was copied
                without its replay/ folder), or cannot be written.
        """
        self.buffers = [self._buffer(index) for index in range(len(self.seeds))]
        self.undo = [_UndoLog(None, 0, 0, self.capacity) for _ in self.seeds]
        if entries is None or isinstance(entries, str):
            self._load_dump(entries)
            return
        if len(entries) != len(self.seeds):
            raise ValueError(f"the checkpoint holds {len(entries)} replay buffers, this group {len(self.seeds)} seeds")
        for index, (buffer, entry) in enumerate(zip(self.buffers, entries)):
            if entry is None:
                continue
            folder, undo = self._seed_dir(index) / "storage", self._seed_dir(index) / entry["undo"]
            if not (folder / "meta.json").is_file() or not undo.is_file():
                raise RunWriteError(folder.parent, "the replay buffer of this checkpoint is missing (copy the run "
                                                   "directory with its replay/ folder)")
            with writing(folder):
                write_atomic(folder / _METADATA, entry["storage"])
                buffer.storage.loads(folder)  # its own path: the memory map is reopened in place, not copied
                positions, rows = _UndoLog.read(undo, sum(self.widths))
                if len(positions):
                    buffer.storage.set(positions, TensorDict({"row": rows}, batch_size=rows.shape[:1]),
                                       set_cursor=False)
                buffer.writer.load_state_dict(entry["writer"])
                for path in folder.glob("*.memmap"):
                    _fsync(path)  # the rows are back on disk: the undo file can start again
                write_atomic(undo, b"")
            self.undo[index] = _UndoLog(undo, int(entry["writer"]["_cursor"]), len(buffer.storage), self.capacity)

    def _load_dump(self, name: str | None) -> None:
        """A checkpoint of an earlier version names a full dump ``replay/<name>/`` (``None``: empty buffers):
        copied into the live memory maps; the next checkpoint removes it."""
        if name is None:
            return
        root = self.run_dir / REPLAY_DIR / name
        if not root.is_dir():
            raise RunWriteError(root, "the replay buffers of this checkpoint are missing (copy the run directory "
                                      "with its replay/ folder)")
        with writing(self.live):
            for index, buffer in enumerate(self.buffers):
                folder = root / f"seed-{self.seeds[index]:03d}"
                if folder.is_dir():  # the storage, writer and sampler dumps: JSON and memory maps, no pickle
                    make_dirs(self._seed_dir(index))
                    buffer.storage.loads(folder / "storage")
                    buffer.writer.loads(folder / "writer")
                    buffer.sampler.loads(folder / "sampler")
