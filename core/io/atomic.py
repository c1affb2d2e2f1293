"""Atomic file writes: a reader sees either the old file or the complete new one, never a torn one.

The recipe (the one used by ``git`` and most databases):

1. write into a temporary file created with :func:`tempfile.mkstemp` in the *same directory*
   as the target (so the final rename stays on one file system and is atomic);
2. ``flush`` and ``fsync`` the temporary file, so its bytes are on disk before it gets a name;
3. :func:`os.replace` it onto the target (atomic on POSIX and on Windows);
4. ``fsync`` the directory, so the rename itself survives a power cut.

If anything raises before step 3 the temporary file is removed and the target is untouched.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from randt.core.errors import FormatError

__all__ = ["append_durably", "atomic_open", "atomic_write_bytes", "fsync_directory"]

logger = logging.getLogger(__name__)

_TEXT_MODES = ("w", "wt")
_BINARY_MODES = ("wb",)


def _default_file_mode() -> int:
    """Return the permission bits a plain ``open(path, "w")`` would give a new file.

    :func:`tempfile.mkstemp` creates files with mode ``0o600``; without this the atomic writers
    would silently produce owner-only files. The umask can only be read by setting it, so it is
    read once, at import time.
    """
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


_NEW_FILE_MODE = _default_file_mode()


def fsync_directory(directory: Path) -> None:
    """``fsync`` a directory so a rename inside it is durable (best effort, POSIX only)."""
    if not hasattr(os, "O_DIRECTORY"):
        return
    try:
        fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    except OSError as exc:
        logger.debug("cannot open directory %s to fsync it: %s", directory, exc)
        return
    try:
        os.fsync(fd)
    except OSError as exc:  # some file systems (e.g. some network mounts) refuse this
        logger.debug("fsync of directory %s failed: %s", directory, exc)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary file that atomically replaces ``path`` when the block exits cleanly.

    Parameters
    ----------
    path:
        The file to create or replace. Its directory must exist.
    mode:
        ``"wb"`` (binary, the default) or ``"w"`` / ``"wt"`` (UTF-8 text with ``"\\n"`` newlines).

    Yields
    ------
    IO
        A writable file object for the temporary file.

    Raises
    ------
    FormatError
        The temporary file could not be created, synced or renamed onto ``path``.
    ValueError
        ``mode`` is not one of the write modes above.

    Notes
    -----
    An exception raised inside the ``with`` block propagates unchanged; the temporary file is
    deleted and ``path`` keeps its previous content (or keeps not existing). A replaced file keeps
    its permission bits; a new file gets the usual ``0o666 & ~umask``.

    Examples
    --------
    >>> with atomic_open("poses.txt", "w") as fh:  # doctest: +SKIP
    ...     fh.write("1 0 0 0 0 1 0 0 0 0 1 0\\n")
    """
    if mode not in _TEXT_MODES + _BINARY_MODES:
        raise ValueError(f"atomic_open supports modes 'wb', 'w' and 'wt', not {mode!r}")
    target = Path(path)
    directory = target.parent
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=directory)
    except OSError as exc:
        raise FormatError(f"cannot write {target}: cannot create a temporary file: {exc}") from exc
    tmp = Path(tmp_name)
    committed = False
    try:
        if mode in _TEXT_MODES:
            fh: IO[Any] = os.fdopen(fd, "w", encoding="utf-8", newline="\n")
        else:
            fh = os.fdopen(fd, "wb")
        with fh:
            yield fh
            try:
                fh.flush()
                os.fsync(fh.fileno())
            except OSError as exc:
                raise FormatError(f"cannot write {target}: {exc}") from exc
        try:
            try:
                file_mode = target.stat().st_mode & 0o7777
            except FileNotFoundError:
                file_mode = _NEW_FILE_MODE
            os.chmod(tmp, file_mode)
            os.replace(tmp, target)
        except OSError as exc:
            raise FormatError(f"cannot write {target}: {exc}") from exc
        committed = True
    finally:
        if not committed:
            with contextlib.suppress(OSError):
                tmp.unlink()
    fsync_directory(directory)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Atomically replace (or create) ``path`` with ``data``.

    Parameters
    ----------
    path:
        Target file; its directory must exist.
    data:
        The complete new content.

    Raises
    ------
    FormatError
        The file could not be written.
    """
    with atomic_open(path, "wb") as fh:
        fh.write(data)


def append_durably(path: str | os.PathLike[str], data: bytes, *, new_dirs: int = 1) -> None:
    """Append ``data`` to ``path`` and fsync it: when this returns, the bytes survive a crash
    (the fsync'd logs: a session's poses, the pose graph's keyframes).

    The file (and its directory) is created when missing; a new file's directory entry is made
    durable too, in its directory and the ``new_dirs - 1`` above it (those that may have been
    created with it). A write or sync that fails cuts the file back to its previous length where
    possible (a torn tail left by a crash is the reader's to cut: records carry their own check).

    Raises
    ------
    FormatError
        It could not be opened, written or synced (disk full, read-only...).
    """
    path = Path(path)
    try:
        created = not path.exists()
        if created:
            path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    except OSError as exc:
        raise FormatError(f"cannot open {path}: {exc}") from exc
    try:
        size = os.fstat(fd).st_size
        try:
            if os.write(fd, data) != len(data):
                raise OSError(f"short write to {path}")
            os.fsync(fd)
        except OSError as exc:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, size)
            raise FormatError(f"cannot append to {path}: {exc}") from exc
    finally:
        os.close(fd)
    if created:
        try:
            for directory in [path.parent, *path.parent.parents][:new_dirs]:
                fsync_directory(directory)
        except OSError as exc:
            raise FormatError(f"cannot sync {path.parent}: {exc}") from exc
