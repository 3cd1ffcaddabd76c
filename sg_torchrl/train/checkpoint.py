"""Checkpoint files and run directories of ``sg-train``: safe to load, verified, never clobbered.

**File format.** A checkpoint is one header line followed by a payload::

    SG_TORCHRL_CHECKPOINT v1 sha256=<64 hex digits of the payload> bytes=<payload length>\\n
    <payload: torch.save of the encoded state tree>

Loading reads the whole file, checks the header, the payload length (a truncated or extended file
is refused) and its sha256 (a flipped byte anywhere in the payload is refused), and only then
unpickles it with ``torch.load(..., weights_only=True)``: PyTorch's restricted unpickler, which
builds tensors and plain containers and calls nothing else, so a crafted file (a pickle whose
``__reduce__`` runs a shell command) is refused instead of executed. The checksum catches
accidents (disk or copy errors); ``weights_only`` is what makes a hostile file harmless, since
anyone who can write a file can also write a matching checksum. Every failure is a
:class:`CheckpointError` naming the file and what is wrong.

**Encoding.** The trainers' state (networks, optimisers, schedulers, multipliers, normalisers,
simulator states with numpy arrays and numpy bit-generator states, torch generator states, the
collector's TensorDict carry, episode statistics, the config) is mostly tensors and plain data;
what ``weights_only`` would reject is turned into tagged plain dicts on save and back on load
(:func:`encode_state` / :func:`decode_state`), so the envs and the collector keep returning numpy
arrays and TensorDicts from their ``state_dict`` methods:

* a numpy array or scalar -> ``{TAG: "numpy", "dtype": "<f8", "shape": [...], "data": uint8 tensor}``
  (its raw bytes: bit-exact for every dtype, including the big integers of bit-generator states,
  which are plain Python ints and load as they are);
* a TensorDict -> ``{TAG: "tensordict", "batch_size": [...], "device": ..., "names": ...,
  "entries": {...}}``, its entries encoded in turn (nested TensorDicts keep their own batch size).

Anything else that is not a tensor or plain data (``None``, ``bool``, ``int``, ``float``, ``str``,
lists, tuples, dicts, ``torch.Size``, ``torch.dtype``, ``torch.device``) makes saving fail with a
``TypeError`` naming where it sits in the tree, so a checkpoint that could not be loaded is never
written. Writing is atomic (a temporary file in the same folder, flushed to disk, then renamed over
the old checkpoint): a crash while saving leaves the previous checkpoint intact.

**Run directories.** :func:`check_new_run_dir` refuses to start a new run in a directory that
already holds one (a checkpoint, ``progress.csv`` or ``summary.json``) unless asked to start over
(``--overwrite``), and :func:`clear_run_dir` then removes exactly the files and folders a run
writes, nothing else. A seed group's directory (``sg-train --seeds``) holds its own checkpoint and
config plus one run directory per seed, ``seed-XXX/`` (:data:`SEED_DIR_PATTERN`): both functions
look into those too. :func:`resume_run_dir` says where a resumed run continues: the directory given
to ``--resume`` (or the folder of the checkpoint file given), whatever the saved config says, so a
copied run continues in the copy.
"""

from __future__ import annotations

import hashlib
import io
import os
import re
import shutil
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from sg_torchrl.train.writes import write_atomic, writing

__all__ = [
    "CHECKPOINT_NAME", "CheckpointError", "RUN_FILES", "RunDirectoryError", "SEED_DIR_PATTERN", "check_new_run_dir",
    "checkpoint_file", "clear_run_dir", "decode_state", "encode_state", "existing_run_files", "host_copy", "load_checkpoint",
    "resume_run_dir", "save_checkpoint",
]


#: File name of a run's checkpoint inside its run directory.
CHECKPOINT_NAME = "checkpoint.pt"
#: What a run writes into its directory; a new run with ``--overwrite`` removes these, and nothing else.
RUN_FILES = (CHECKPOINT_NAME, CHECKPOINT_NAME + ".tmp", "config.json", "progress.csv", "summary.json", "curves.png",
             "csv", "tb", "wandb", "replay")
#: The per-seed run directories inside a seed group's directory (``seed-000``, ``seed-001``, ...).
SEED_DIR_PATTERN = "seed-[0-9]*"
#: The files whose presence means a directory already holds a run.
_RUN_MARKERS = (CHECKPOINT_NAME, "progress.csv", "summary.json")

FORMAT_VERSION = 1
_MAGIC = b"SG_TORCHRL_CHECKPOINT"
_HEADER = re.compile(rb"SG_TORCHRL_CHECKPOINT v(\d+) sha256=([0-9a-f]{64}) bytes=(\d+)\n")
_MAX_HEADER = 256
#: Key of the tagged dicts that stand for numpy arrays and TensorDicts in a saved state tree.
TAG = "__sg_torchrl__"
_PLAIN = (type(None), bool, int, float, str, torch.dtype, torch.device)


class CheckpointError(ValueError):
    """A checkpoint file that cannot be trusted or read: its message names the file and the problem."""


class RunDirectoryError(ValueError):
    """A new run would overwrite a run directory that already holds a run."""


# ---------------------------------------------------------------------- encoding
def host_copy(value: Any) -> Any:
    """``value`` (a tensor, or nested dicts, lists, tuples of them) with every tensor a detached CPU copy.

    What a trainer puts in a checkpoint whatever its device: the file loads, and the run continues, anywhere.
    """
    if isinstance(value, torch.Tensor):
        return value.detach().to("cpu", copy=True)
    if isinstance(value, dict):
        return type(value)((key, host_copy(item)) for key, item in value.items())
    if isinstance(value, (list, tuple)):
        return type(value)(host_copy(item) for item in value)
    return value


def encode_state(tree: Any, where: str = "state") -> Any:
    """``tree`` with numpy arrays / scalars and TensorDicts replaced by tagged plain dicts.

    Raises:
        TypeError: for anything that is neither a tensor nor plain data (``where`` names its place).
    """
    if isinstance(tree, (np.ndarray, np.generic)):  # first: np.float64 is also a float
        return _encode_numpy(tree, where)
    if isinstance(tree, _PLAIN):
        return tree
    if isinstance(tree, torch.Tensor):
        if type(tree) not in (torch.Tensor, torch.nn.Parameter):
            raise TypeError(f"checkpoint: {where} is a {type(tree).__name__}, not a plain tensor")
        return tree.detach()
    if isinstance(tree, TensorDictBase):
        return _encode_tensordict(tree, where)
    if type(tree) is torch.Size:
        return tree
    if isinstance(tree, (list, tuple)) and type(tree) in (list, tuple):
        return type(tree)(encode_state(item, f"{where}[{i}]") for i, item in enumerate(tree))
    if type(tree) in (dict, OrderedDict):
        if TAG in tree:
            raise TypeError(f"checkpoint: {where} holds the reserved key {TAG!r}")
        encoded = type(tree)()
        for key, value in tree.items():
            if not isinstance(key, (str, int, float, bool, type(None), tuple)):
                raise TypeError(f"checkpoint: {where} has a key of type {type(key).__name__}")
            encoded[key] = encode_state(value, f"{where}[{key!r}]")
        metadata = getattr(tree, "_metadata", None)  # a module state dict's version numbers
        if metadata is not None:
            encoded._metadata = encode_state(dict(metadata), f"{where}._metadata")
        return encoded
    raise TypeError(f"checkpoint: {where} is a {type(tree).__module__}.{type(tree).__qualname__}, which a "
                    f"weights-only checkpoint cannot hold (tensors and plain data only)")


def _encode_numpy(value: np.ndarray | np.generic, where: str) -> dict[str, Any]:
    array = np.asarray(value)
    if array.dtype.hasobject or array.dtype.fields is not None or np.dtype(array.dtype.str) != array.dtype:
        raise TypeError(f"checkpoint: {where} is a numpy array of dtype {array.dtype}, which has no raw-byte form")
    raw = np.frombuffer(np.ascontiguousarray(array).tobytes(), dtype=np.uint8).copy()
    return {TAG: "numpy", "dtype": array.dtype.str, "shape": list(array.shape),
            "scalar": isinstance(value, np.generic), "data": torch.from_numpy(raw)}


def _encode_tensordict(td: TensorDictBase, where: str) -> dict[str, Any]:
    names = list(td.names) if any(name is not None for name in td.names) else None
    entries = {key: encode_state(value, f"{where}[{key!r}]") for key, value in td.items()}
    return {TAG: "tensordict", "batch_size": list(td.batch_size), "names": names,
            "device": None if td.device is None else str(td.device), "entries": entries}


def decode_state(tree: Any) -> Any:
    """Invert :func:`encode_state`: tagged dicts back to numpy arrays / scalars and TensorDicts."""
    if isinstance(tree, Mapping):
        if TAG in tree:
            return _decode_tagged(tree)
        decoded = type(tree)() if type(tree) in (dict, OrderedDict) else {}
        for key, value in tree.items():
            decoded[key] = decode_state(value)
        metadata = getattr(tree, "_metadata", None)
        if metadata is not None:
            decoded._metadata = metadata
        return decoded
    if type(tree) in (list, tuple):
        return type(tree)(decode_state(item) for item in tree)
    return tree


def _decode_tagged(tree: Mapping[str, Any]) -> Any:
    kind = tree[TAG]
    if kind == "numpy":
        dtype = np.dtype(tree["dtype"])
        array = np.frombuffer(tree["data"].numpy().tobytes(), dtype=dtype).reshape(tree["shape"]).copy()
        return array[()] if tree["scalar"] else array
    if kind == "tensordict":
        entries = {key: decode_state(value) for key, value in tree["entries"].items()}
        td = TensorDict(entries, batch_size=tree["batch_size"], device=tree["device"])
        if tree["names"] is not None:
            td.refine_names(*tree["names"])
        return td
    raise ValueError(f"unknown entry kind {kind!r}")


# ---------------------------------------------------------------------- files
def checkpoint_file(path: str | Path) -> Path:
    """``path`` itself, or ``<path>/checkpoint.pt`` when ``path`` is a directory."""
    path = Path(path)
    return path / CHECKPOINT_NAME if path.is_dir() else path


def save_checkpoint(state: Mapping[str, Any], path: str | Path) -> Path:
    """Write ``state`` to ``path`` (header, checksum, weights-only payload), atomically; returns ``path``.

    Raises:
        RunWriteError: the file could not be written (its temporary file is removed, ``path`` is untouched).
    """
    path = Path(path)
    buffer = io.BytesIO()
    torch.save(encode_state(dict(state)), buffer)
    payload = buffer.getvalue()
    header = b"%s v%d sha256=%s bytes=%d\n" % (_MAGIC, FORMAT_VERSION, hashlib.sha256(payload).hexdigest().encode(),
                                               len(payload))
    # Atomic: a save that fails (a full disk) or is interrupted leaves the previous checkpoint as it was.
    return write_atomic(path, header, payload)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint file (or ``<dir>/checkpoint.pt``), verified and without running any code.

    Raises:
        FileNotFoundError: no file there.
        CheckpointError: an empty, truncated, corrupted, foreign or unsafe file.
    """
    path = checkpoint_file(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    data = path.read_bytes()
    payload = _verified_payload(path, data)
    try:
        tree = torch.load(io.BytesIO(payload), weights_only=True, map_location="cpu")  # whatever wrote it
    except Exception as error:  # noqa: BLE001 - any unpickling failure means: refuse the file
        first_line = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise CheckpointError(
            f"checkpoint {path} holds something other than tensors and plain data, which sg_torchrl never "
            f"writes; refused without running it ({first_line})"
        ) from None
    try:
        state = decode_state(tree)
    except Exception as error:  # noqa: BLE001
        raise CheckpointError(f"checkpoint {path} has contents sg_torchrl cannot read ({error})") from None
    if not isinstance(state, dict) or not isinstance(state.get("config"), dict) or "epoch" not in state:
        raise CheckpointError(f"checkpoint {path} is not a training checkpoint (no 'config' and 'epoch' entries)")
    return state


def _verified_payload(path: Path, data: bytes) -> bytes:
    """The payload of ``data`` after checking its header, length and sha256."""
    if not data:
        raise CheckpointError(f"checkpoint {path} is empty (0 bytes)")
    if not data.startswith(_MAGIC):
        raise CheckpointError(
            f"checkpoint {path} is not an sg_torchrl checkpoint (it does not start with the "
            f"{_MAGIC.decode()} header: another program's file, one written before sg_torchrl verified "
            f"checkpoints, or a damaged one)"
        )
    end = data.find(b"\n", 0, _MAX_HEADER)
    match = _HEADER.fullmatch(data[:end + 1]) if end >= 0 else None
    if match is None:
        raise CheckpointError(f"checkpoint {path} has a damaged header")
    version, digest, size = int(match[1]), match[2].decode(), int(match[3])
    if version != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {path} has format v{version}; this sg_torchrl reads v{FORMAT_VERSION}")
    payload = data[end + 1:]
    if len(payload) < size:
        raise CheckpointError(f"checkpoint {path} is truncated: {len(payload)} of its {size} payload bytes are there")
    if len(payload) > size:
        raise CheckpointError(f"checkpoint {path} has {len(payload) - size} bytes more than its header says")
    if hashlib.sha256(payload).hexdigest() != digest:
        raise CheckpointError(
            f"checkpoint {path} is corrupted: the sha256 of its contents does not match the one saved with it "
            f"(bytes changed after it was written)"
        )
    return payload


# ---------------------------------------------------------------------- run directories
def _seed_dirs(run_dir: Path) -> list[Path]:
    """The ``seed-XXX`` run directories of a seed group's directory (none in a single run's)."""
    return sorted(path for path in run_dir.glob(SEED_DIR_PATTERN) if path.is_dir() and not path.is_symlink())


def existing_run_files(run_dir: str | Path) -> list[str]:
    """The names among ``checkpoint.pt``, ``progress.csv``, ``summary.json`` present in ``run_dir``,
    and in its ``seed-XXX/`` directories (as ``seed-000/progress.csv``) when it is a seed group's."""
    run_dir = Path(run_dir)
    found = [name for name in _RUN_MARKERS if (run_dir / name).exists()]
    for seed_dir in _seed_dirs(run_dir):
        found += [f"{seed_dir.name}/{name}" for name in _RUN_MARKERS if (seed_dir / name).exists()]
    return found


def check_new_run_dir(run_dir: str | Path, overwrite: bool = False) -> None:
    """Refuse to start a new run in ``run_dir`` when it already holds one, unless ``overwrite``.

    Raises:
        RunDirectoryError: saying how to continue the run (``--resume``) or start over (``--overwrite``).
    """
    found = existing_run_files(run_dir)
    if found and not overwrite:
        raise RunDirectoryError(
            f"run directory {run_dir} already holds a run ({', '.join(found)}); pass --resume {run_dir} to "
            f"continue it or --overwrite to start over"
        )


def clear_run_dir(run_dir: str | Path) -> list[str]:
    """Remove what a run writes (:data:`RUN_FILES`) from ``run_dir``; returns the names removed.

    In a seed group's directory, also from each ``seed-XXX/`` run directory, which is then removed
    when nothing else is left in it.

    Raises:
        RunWriteError: a file could not be removed (a read-only directory).
    """
    run_dir = Path(run_dir)
    with writing(run_dir):
        return _clear(run_dir)


def _clear(run_dir: Path) -> list[str]:
    removed = []
    for seed_dir in _seed_dirs(run_dir):
        removed += [f"{seed_dir.name}/{name}" for name in _clear(seed_dir)]
        if not any(seed_dir.iterdir()):
            seed_dir.rmdir()
    for name in RUN_FILES:
        target = run_dir / name
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        elif target.exists() or target.is_symlink():
            target.unlink()
        else:
            continue
        removed.append(name)
    return removed


def resume_run_dir(resume: str | Path) -> Path:
    """Where a run resumed from ``resume`` continues: that directory, or the checkpoint file's folder.

    Absolute, so that ``output_dir`` / ``run_name`` rebuilt from it name it whatever the current
    directory (``--resume .`` included).
    """
    path = Path(resume)
    return Path(os.path.abspath(path if path.is_dir() else path.parent))
