"""A seed group's replay buffers: one TorchRL ``ReplayBuffer`` per seed, kept inside the run directory.

Each seed has its own ``ReplayBuffer`` (``LazyMemmapStorage`` + ``RandomSampler``, the seed's own
sampling generator, the ``replay`` stream of :mod:`sg_torchrl.seeding`), so its samples are the same
whatever the group. One buffer per seed rather than one storage with a seed dimension: TorchRL's
samplers draw one index set per buffer, and a seed's draws must not depend on the other seeds (a seed
group trains each seed as its ``--seed`` run). A transition is one float32 row: observation, action,
reward, cost, terminated, next observation (one gather per sample instead of one per field).

**On disk.** The storage's memory map lives in ``<run dir>/replay/live/seed-XXX/`` (never outside the run
directory). Each checkpoint dumps every buffer with TorchRL's ``ReplayBuffer.dumps`` (storage, sampler,
writer cursor; the sampling generator's state goes into the checkpoint) to ``<run dir>/replay/epoch-NNNNNN/seed-XXX/``, written as ``...tmp`` and renamed
when complete; the checkpoint names that directory, and the dumps of older epochs are removed once the
checkpoint is on disk. Loading reads the storage, writer and sampler dumps through their own ``loads``
(JSON and memory maps); ``ReplayBuffer.loads`` would also unpickle a ``prefetch.pkl``, which ``dump``
removes, so reading a run directory never runs code from it. So ``--resume`` loads the buffers exactly as they were at the checkpoint, and a run
killed between the dump and the checkpoint leaves a newer dump that the next checkpoint removes. A dump
writes the whole storage (capacity x row bytes per seed: about 180 MB for SafetyHalfCheetahVelocity-v1 at
OmniSafe's 1,000,000). A write that fails raises :class:`~sg_torchrl.train.writes.RunWriteError`.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from pathlib import Path

import torch
from tensordict import TensorDict
from torch import Tensor
from torchrl.data import LazyMemmapStorage, ReplayBuffer
from torchrl.data.replay_buffers import RandomSampler

from sg_torchrl.train.writes import RunWriteError, writing

__all__ = ["REPLAY_DIR", "SeedReplay"]

#: The replay buffers' folder in a run directory (removed with the run's files by ``--overwrite``).
REPLAY_DIR = "replay"


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

    def _seed_dir(self, root: Path, index: int) -> Path:
        return root / f"seed-{self.seeds[index]:03d}"

    def _buffer(self, index: int) -> ReplayBuffer:
        # existsok: the memory map of a run killed before its first checkpoint is overwritten, not refused
        storage = LazyMemmapStorage(self.capacity, scratch_dir=self._seed_dir(self.run_dir / REPLAY_DIR / "live", index),
                                    existsok=True)
        return ReplayBuffer(storage=storage, sampler=RandomSampler(), batch_size=self.batch_size,
                            generator=self.generators[index])

    def __len__(self) -> int:
        return len(self.buffers[0])

    def extend(self, obs: Tensor, action: Tensor, reward: Tensor, cost: Tensor, terminated: Tensor,
               next_obs: Tensor) -> None:
        """Add one step of every seed's simulators: each field ``(S, N, k)``."""
        rows = torch.cat([obs, action, reward, cost, terminated.to(obs.dtype), next_obs], -1)
        with writing(self.run_dir / REPLAY_DIR / "live"):
            for buffer, seed_rows in zip(self.buffers, rows):
                buffer.extend(TensorDict({"row": seed_rows}, batch_size=seed_rows.shape[:1]))

    def sample(self) -> tuple[Tensor, ...]:
        """One minibatch per seed: ``obs``, ``action`` ``(S, B, k)``; ``reward``, ``cost`` ``(S, B)``;
        ``terminated`` ``(S, B)`` bool; ``next_obs``."""
        rows = torch.stack([buffer.sample().get("row") for buffer in self.buffers])
        obs, action, reward, cost, terminated, next_obs = rows.split(self.widths, -1)
        return obs, action, reward.squeeze(-1), cost.squeeze(-1), terminated.squeeze(-1) > 0.5, next_obs

    # ------------------------------------------------------------------ checkpoints
    def dump(self, epoch: int) -> str:
        """Dump every buffer for the checkpoint of ``epoch``; returns the dump's folder name (in ``replay/``)."""
        name = f"epoch-{epoch:06d}"
        final = self.run_dir / REPLAY_DIR / name
        partial = final.with_name(name + ".tmp")
        with writing(partial):
            shutil.rmtree(partial, ignore_errors=True)
            partial.mkdir(parents=True)
            for index, buffer in enumerate(self.buffers):
                if len(buffer):
                    folder = self._seed_dir(partial, index)
                    buffer.dumps(folder)
                    (folder / "prefetch.pkl").unlink(missing_ok=True)  # a pickle; nothing here is ever unpickled
            shutil.rmtree(final, ignore_errors=True)
            partial.rename(final)
        return name

    def prune(self, keep: str) -> None:
        """Remove the dumps other than ``keep`` (after the checkpoint naming ``keep`` is on disk)."""
        root = self.run_dir / REPLAY_DIR
        for path in root.glob("epoch-*"):
            if path.name != keep:
                shutil.rmtree(path, ignore_errors=True)

    def load(self, name: str | None) -> None:
        """Load the dump ``name`` (the checkpoint's); ``None``: the buffers were empty at the checkpoint.

        Raises:
            RunWriteError: the dump is missing (the run directory was copied without ``replay/``).
        """
        self.remove_live()
        self.buffers = [self._buffer(index) for index in range(len(self.seeds))]
        if name is None:
            return
        root = self.run_dir / REPLAY_DIR / name
        if not root.is_dir():
            raise RunWriteError(root, "the replay buffers of this checkpoint are missing (copy the run directory "
                                      "with its replay/ folder)")
        for index, buffer in enumerate(self.buffers):
            folder = self._seed_dir(root, index)
            if folder.is_dir():  # the storage, writer and sampler dumps: JSON and memory maps, no pickle
                buffer.storage.loads(folder / "storage")
                buffer.writer.loads(folder / "writer")
                buffer.sampler.loads(folder / "sampler")

    def remove_live(self) -> None:
        """Remove the live memory maps (at the end of a run: the last dump holds what ``--resume`` needs)."""
        shutil.rmtree(self.run_dir / REPLAY_DIR / "live", ignore_errors=True)
