"""One process at a time per data directory: an exclusive ``flock`` on ``DATA/.randt-store.lock``.

The kernel releases the lock if the process dies, so a store that opens a directory knows no live
writer of another process is in it (and may remove the temporary files of interrupted writes).
Stores of one process share the lock (a service restarted in-process before the old store was
closed); the last of them to close releases it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from randt.core.errors import FormatError, RandtError

try:  # POSIX; elsewhere the store runs without the single-process guard
    import fcntl
except ImportError:  # pragma: no cover - not exercised on Linux
    fcntl = None  # type: ignore[assignment]

__all__ = ["LOCK_FILENAME", "DataDirInUseError", "acquire_lock", "check_data_dir_free", "release_lock"]

logger = logging.getLogger(__name__)

LOCK_FILENAME = ".randt-store.lock"


@dataclass
class _HeldLock:
    """A data directory's flock held by this process: its descriptor and the Stores using it."""

    fd: int | None
    users: int


_HELD_LOCKS: dict[Path, _HeldLock] = {}  # by the data directory's real path
_HELD_LOCKS_GUARD = threading.Lock()
# A Store's finalizer may run from the garbage collector at any allocation, also while this very
# thread is inside the guard (in acquire_lock, say): taking the guard there again would deadlock
# (it is not re-entrant). Such a release is queued here and done at the next entry into the guard.
_PENDING_RELEASES: list[Path] = []
_GUARD_STATE = threading.local()


@contextlib.contextmanager
def _guarded() -> Iterator[None]:
    """Hold the guard (releases queued by finalizers are done first)."""
    with _HELD_LOCKS_GUARD:
        _GUARD_STATE.inside = True
        try:
            while _PENDING_RELEASES:
                _release_held(_PENDING_RELEASES.pop())
            yield
        finally:
            _GUARD_STATE.inside = False


class DataDirInUseError(RandtError):
    """Another process holds the data directory's lock (a service already runs on it)."""


def _in_use(key: Path) -> DataDirInUseError:
    return DataDirInUseError(
        f"data directory {key} is already open in another process (lock {LOCK_FILENAME} is held): "
        "stop that service or choose another --data-dir"
    )


def check_data_dir_free(directory: str | os.PathLike[str]) -> None:
    """Raise :class:`DataDirInUseError` if another process holds ``directory``'s lock.

    Creates nothing: a directory or lock file that does not exist yet is free. The lock is only
    probed (taken and released at once), so ``randt serve`` can say so before starting anything.
    """
    key = Path(directory).resolve()
    path = key / LOCK_FILENAME
    if fcntl is None or not path.is_file():
        return
    with _guarded():
        if key in _HELD_LOCKS:
            return  # this process holds it: its Stores share it
        try:
            fd = os.open(path, os.O_RDWR)
        except OSError:
            return  # unreadable: Store() reports it with its reason
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            raise _in_use(key) from exc
        finally:
            os.close(fd)  # closing the descriptor releases a lock taken here


def acquire_lock(directory: Path) -> tuple[Path, bool]:
    """Hold ``directory``'s lock for one more Store of this process.

    Returns the lock's key and whether this call took the lock (``False``: another Store of this
    process already holds it and shares it).

    Raises
    ------
    DataDirInUseError
        Another process holds the lock.
    FormatError
        The lock file cannot be opened.
    """
    key = directory.resolve()
    path = key / LOCK_FILENAME
    with _guarded():
        held = _HELD_LOCKS.get(key)
        if held is not None:
            held.users += 1
            return key, False
        fd: int | None = None
        if fcntl is None:  # pragma: no cover - not exercised on Linux
            logger.debug("no fcntl: %s is not protected against a second process", key)
        else:
            try:
                fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:
                raise FormatError(f"cannot open the store's lock file {path}: {exc}") from exc
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                os.close(fd)
                raise _in_use(key) from exc
        _HELD_LOCKS[key] = _HeldLock(fd=fd, users=1)
        return key, True


def release_lock(key: Path) -> None:
    """One Store of this process is done with ``key``; the last one releases the flock.

    Called by a Store's finalizer: when that runs inside the guard on this thread (the garbage
    collector), the release is queued for the next entry into the guard instead.
    """
    if getattr(_GUARD_STATE, "inside", False):
        _PENDING_RELEASES.append(key)
        return
    with _guarded():
        _release_held(key)


def _release_held(key: Path) -> None:
    """:func:`release_lock`'s work; the caller holds the guard."""
    held = _HELD_LOCKS.get(key)
    if held is None:
        return
    held.users -= 1
    if held.users > 0:
        return
    del _HELD_LOCKS[key]
    if held.fd is not None:
        with contextlib.suppress(OSError):
            os.close(held.fd)  # closing the descriptor releases the flock
