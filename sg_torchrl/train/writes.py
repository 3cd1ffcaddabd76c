"""Every file ``sg-train`` and ``sg-sweep`` write goes through here: atomically where a file is replaced, cut
back where one is appended to, and with one clear error when the disk refuses.

A full disk, a quota, ``ulimit -f``, a read-only or vanished directory, or an output directory that is a file
all surface as an ``OSError`` somewhere deep in a write. The helpers below turn it into a
:class:`RunWriteError` whose message is one line naming the file and the cause (``cannot write
runs/x/checkpoint.pt: no space left on device``), and leave nothing behind: a replaced file keeps its
previous contents (the new ones go to ``<name>.tmp``, removed on failure, then renamed over it), an
appended file is cut back to its length before the append. ``sg-train`` prints the message and exits with
:data:`EXIT_WRITE_FAILED`.

Under ``ulimit -f`` the kernel sends ``SIGXFSZ``, which Python ignores from start-up, so the write fails
with ``EFBIG`` ("file too large") like any other write error instead of killing the process.

:func:`check_run_name` keeps a run name (a sweep cell's directory) inside its output directory.
"""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Iterator
from pathlib import Path, PurePath

__all__ = ["EXIT_WRITE_FAILED", "RunWriteError", "append_bytes", "append_text", "check_run_name", "make_dirs",
           "write_atomic", "writing"]

#: ``sg-train``'s exit status when a file of the run could not be written (2 is a bad command line).
EXIT_WRITE_FAILED = 3


class RunWriteError(Exception):
    """A file could not be written; ``str()`` is one line: ``cannot write <path>: <cause>``.

    Attributes:
        path: the file (or directory) being written.
        reason: the cause in words (``"no space left on device"``).
    """

    def __init__(self, path: str | os.PathLike, reason: str) -> None:
        self.path, self.reason = Path(path), reason
        super().__init__(f"cannot write {path}: {reason}")

    def __reduce__(self):  # pickled as (path, reason): Ray sends a task's exception back to the driver
        return type(self), (str(self.path), self.reason)


def reason(error: OSError) -> str:
    """The cause of ``error`` in words, without the errno number or the path: ``"file too large"``."""
    if error.errno == errno.ENOTDIR:
        return "a folder on its path is a file"
    text = error.strerror or (os.strerror(error.errno) if error.errno else str(error) or type(error).__name__)
    return text[:1].lower() + text[1:]


def _remove(path: Path | None) -> None:
    if path is not None:
        with contextlib.suppress(OSError):
            path.unlink()


@contextlib.contextmanager
def writing(path: str | os.PathLike, leftover: Path | None = None) -> Iterator[None]:
    """Turn an ``OSError`` inside the block into :class:`RunWriteError` naming ``path``, after removing
    ``leftover`` (a temporary file) when given."""
    try:
        yield
    except OSError as error:
        _remove(leftover)
        raise RunWriteError(path, reason(error)) from error


def temporary_path(path: Path) -> Path:
    """Where :func:`write_atomic` writes ``path``'s new contents first: ``<name>.tmp`` beside it."""
    return path.with_name(path.name + ".tmp")


def write_atomic(path: str | os.PathLike, data: bytes | str, *chunks: bytes, sync: bool = True) -> Path:
    """Replace ``path`` with ``data`` (then ``chunks``) atomically: readers see the old file or the new one.

    The contents go to ``<name>.tmp``, are flushed (and ``fsync`` ed when ``sync``), then renamed over
    ``path``. On failure the temporary file is removed and ``path`` is as it was.

    Raises:
        RunWriteError: naming ``path`` and the cause.
    """
    path = Path(path)
    tmp = temporary_path(path)
    with writing(path, leftover=tmp):
        with open(tmp, "wb") as handle:
            for chunk in (data.encode() if isinstance(data, str) else data, *chunks):
                handle.write(chunk)
            handle.flush()
            if sync:
                os.fsync(handle.fileno())
        tmp.replace(path)
    return path


def append_text(path: str | os.PathLike, text: str) -> None:
    """Append ``text`` to ``path`` whole or not at all: a failed append is cut back off the file.

    Raises:
        RunWriteError: naming ``path`` and the cause.
    """
    append_bytes(path, text.encode())


def append_bytes(path: str | os.PathLike, data: bytes, *, sync: bool = False) -> None:
    """Append ``data`` to ``path`` whole or not at all (a failed append is cut back off the file), then
    ``fsync`` it when ``sync``.

    Raises:
        RunWriteError: naming ``path`` and the cause.
    """
    view = memoryview(data)
    with writing(path), open(path, "ab", buffering=0) as handle:  # unbuffered: nothing is left to flush later
        start = os.fstat(handle.fileno()).st_size
        try:
            while view:
                view = view[handle.write(view):]
            if sync:
                os.fsync(handle.fileno())
        except OSError:
            with contextlib.suppress(OSError):
                os.ftruncate(handle.fileno(), start)  # shrinking needs no space
            raise


def make_dirs(path: str | os.PathLike) -> Path:
    """``mkdir -p path``.

    Raises:
        RunWriteError: ``path`` or a folder above it is a file, or it cannot be created.
    """
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        blocker = next((p for p in (path, *path.parents) if p.exists() and not p.is_dir()), None)
        raise RunWriteError(path, f"{blocker} is a file, not a directory" if blocker else reason(error)) from error
    return path


def check_run_name(name: str, what: str = "run_name") -> None:
    """Refuse a run name that would leave its output directory: an absolute path, or one with a ``..`` part.

    A relative name with ``/`` names nested folders inside the output directory (the default
    ``<env>/<algo>/seed-000`` does, and so do sweep cells).

    Raises:
        ValueError: naming ``what`` and the refused value.
    """
    text = str(name)
    if not text.strip() or text.strip() == ".":
        raise ValueError(f"config: {what} must name a folder inside output_dir, got {text!r}")
    if PurePath(text).is_absolute():
        raise ValueError(f"config: {what} {text!r} is an absolute path; it must name a folder inside output_dir "
                         f"(give the location with --output-dir)")
    if ".." in PurePath(text).parts:
        raise ValueError(f"config: {what} {text!r} would leave output_dir ('..'); it must name a folder inside "
                         f"output_dir (give the location with --output-dir)")
