"""The service's durable, embedded store: tiled maps and driving sessions under one data directory.

Layout
------
::

    DATA/.randt-store.lock                       held (flock) while a Store has DATA open
    DATA/maps/<map>/<ix>_<iy>.pcd                Autoware divided map, as core.tiles writes it
    DATA/maps/<map>/pointcloud_map_metadata.yaml
    DATA/maps/<map>/randt_tile_grid.yaml
    DATA/sessions/<vehicle>/<session>/matcher.npz      matcher state + the session's commit record
    DATA/sessions/<vehicle>/<session>/trajectory.tum   stamp_s tx ty tz qx qy qz qw, a line per scan
    DATA/sessions/<vehicle>/<session>/session.json     the session's record (:class:`SessionRecord`)
    DATA/sessions/<vehicle>/<session>/poses.log        poses acknowledged since matcher.npz (appended)
    DATA/map-versions/<map>                            version floor of a deleted map's name

Map, vehicle and session names are ids (:mod:`wire.ids`: letters, digits, ``_ . -``, at most 64
characters, starting with a letter or digit); every path is built from checked names only.

Crash safety
------------
Every file is replaced atomically (:mod:`core.io.atomic`: temporary file, fsync, rename, fsync of
the directory), so a reader, or a restart after a crash, sees each file whole: its old or its new
content. What spans several files is ordered:

* **maps** (:meth:`TileGrid.write_tiles <core.tiles.TileGrid.write_tiles>`): sidecar, changed
  tiles, metadata last; the metadata never names a tile file that does not exist.
* **sessions**: three files cannot be replaced in one step, so ``matcher.npz`` is the *commit
  record*. Besides the arrays of :meth:`IncrementalMatcher.state_dict
  <core.odometry.IncrementalMatcher.state_dict>` it holds the session's stamps, poses and record
  (keys starting with ``_store_``; :meth:`~core.odometry.IncrementalMatcher.load_state_dict`
  ignores them). It is written first, then ``trajectory.tum`` and ``session.json``, which are
  views of it for people and other tools (``trajectory.tum`` appears with the first scan). A crash
  between the writes leaves the matcher state and its ``last_seq`` consistent (they are in one
  file); :meth:`Store.load_session` notices views that lag behind and rewrites them.

* **the pose log** (``poses.log``): the session worker appends one fixed-size record per pose
  (:class:`PoseLogRecord`, with a CRC-32) and fsyncs it *before* the pose is published, so every
  pose a vehicle received survives a crash (:meth:`Store.append_pose`). :meth:`Store.save_session`
  drops from it the records its snapshot now holds (records are indexed by their pose's place in
  the trajectory, not by ``seq``), by an atomic replace after the snapshot is written: a crash in
  between leaves records the snapshot also holds, which loading skips. :meth:`Store.load_session`
  returns the snapshot plus the logged poses beyond it; a torn last record (a crash during an
  append) fails its CRC and is cut off.
* **map version floors** (``map-versions/<map>``): :meth:`Store.delete_map` first records the
  highest tile version the map reached, so a new map of that name continues above it and a
  ``(tile, version)`` pair is never reused for other content (:meth:`Store.version_floor`).

A crash can leave the atomic writers' temporary files (``.<name>.<random>.tmp``) behind; opening a
:class:`Store` removes them. One process at a time may open a data directory: the store holds an
exclusive ``flock`` on ``DATA/.randt-store.lock`` (released by the kernel if the process dies), so
the clean-up never deletes the temporary file of a live writer.

Damaged files
-------------
A file that cannot be read (say, a truncated ``matcher.npz`` written by a buggy older version)
fails only its own map or session: :meth:`Store.list_sessions` and :meth:`Store.load_all` skip it,
log an error and report it as a :class:`StoreProblem`; everything else still loads.

Thread safety
-------------
Writes to one map, or to one session, are serialized by a lock per map and per session; different
maps and sessions are written concurrently.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import re
import shutil
import struct
import threading
import time
import weakref
import zipfile
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Literal, NamedTuple, Self

import numpy as np
from pydantic import (
    AwareDatetime,
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from core.errors import FormatError, InvalidCloudError, NotFoundError, RandtError
from core.io import atomic_write_bytes, read_tum, write_tum
from core.io.atomic import fsync_directory
from core.io.autoware import AUTOWARE_METADATA_NAME, GRID_SIDECAR_NAME, read_sidecar
from core.tiles import Tile, TileGrid, load_autoware
from wire.ids import legacy_session_map_name, session_map_name, validate_id

try:  # POSIX; elsewhere the store runs without the single-process guard
    import fcntl
except ImportError:  # pragma: no cover - not exercised on Linux
    fcntl = None  # type: ignore[assignment]

__all__ = [
    "LOCK_FILENAME",
    "MAPS_DIRNAME",
    "MATCHER_FILENAME",
    "POSE_LOG_FILENAME",
    "SESSIONS_DIRNAME",
    "SESSION_FILENAME",
    "TRAJECTORY_FILENAME",
    "DataDirInUseError",
    "LoadedSession",
    "PoseLogRecord",
    "SessionFrame",
    "SessionRecord",
    "SessionState",
    "Store",
    "StoreContents",
    "StoreProblem",
    "check_data_dir_free",
]

logger = logging.getLogger(__name__)

MAPS_DIRNAME = "maps"
SESSIONS_DIRNAME = "sessions"
SESSION_FILENAME = "session.json"
TRAJECTORY_FILENAME = "trajectory.tum"
MATCHER_FILENAME = "matcher.npz"
LOCK_FILENAME = ".randt-store.lock"
POSE_LOG_FILENAME = "poses.log"
VERSIONS_DIRNAME = "map-versions"

SessionState = Literal["active", "closed", "expired"]
SessionFrame = Literal["map", "session"]
PoseStatus = Literal["first", "ok", "fallback"]
ProblemKind = Literal["map", "session", "entry"]

# core.io.atomic names its temporary files tempfile.mkstemp(prefix=f".{target}.", suffix=".tmp"),
# in the target's directory. No name the store writes starts with a dot (ids, fixed names).
_TEMP_FILE_RE = re.compile(r"^\..+\.tmp$")
_DELETED_PREFIX = ".deleted-"  # maps/.deleted-<name>-...: a delete_map that did not finish
# Keys of matcher.npz that belong to the store, not to the matcher state.
_RESERVED_PREFIX = "_store_"
_KEY_RECORD = "_store_record"
_KEY_STAMPS = "_store_stamps"
_KEY_POSES = "_store_poses"
_STATE_KEY_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
# Views (trajectory.tum) agree with the commit record within this (TUM rounds stamps to 1 ns).
_VIEW_TOLERANCE = 1e-6
_BOTTOM_ROW = np.array([0.0, 0.0, 0.0, 1.0])
# What np.load / zipfile raise on a damaged archive.
_NPZ_ERRORS = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile)


def _utcnow() -> datetime:
    return datetime.now(UTC)


class SessionRecord(BaseModel):
    """What the store keeps about one driving session (``session.json``).

    Attributes
    ----------
    vehicle, session:
        Names (ids, :mod:`wire.ids`); the session lives in ``sessions/<vehicle>/<session>/``.
    map:
        The map the session's scans go into, or ``None``.
    state:
        ``"active"`` (scans may still arrive), ``"closed"`` (ended by the vehicle) or
        ``"expired"`` (timed out by the service).
    created, updated:
        Timezone-aware times (ISO 8601 in the file). :meth:`Store.save_session` keeps ``created``
        from the session's first save and sets ``updated`` to the time of the save.
    last_seq:
        Sequence number of the last scan processed; -1 before any.
    n_scans:
        Scans in the trajectory (one pose each, fallbacks included).
    n_fallbacks:
        Scans whose pose fell back to the prediction or a prior (<= ``n_scans``).
    frame:
        ``"map"`` if the poses are in the map's frame, ``"session"`` if in the session's own
        (its first scan's) frame.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    vehicle: str
    session: str
    map: str | None = None
    state: SessionState = "active"
    created: AwareDatetime = Field(default_factory=_utcnow)
    updated: AwareDatetime = Field(default_factory=_utcnow)
    last_seq: int = Field(default=-1, ge=-1)
    n_scans: int = Field(default=0, ge=0)
    n_fallbacks: int = Field(default=0, ge=0)
    frame: SessionFrame = "session"

    @property
    def key(self) -> tuple[str, str]:
        """``(vehicle, session)``."""
        return self.vehicle, self.session

    @field_validator("vehicle", "session", "map")
    @classmethod
    def _safe_name(cls, value: str | None, info: ValidationInfo) -> str | None:
        assert info.field_name is not None  # a field validator's, always set
        return None if value is None else validate_id(value, info.field_name)

    @model_validator(mode="after")
    def _fallbacks_within_scans(self) -> SessionRecord:
        if self.n_fallbacks > self.n_scans:
            raise ValueError(f"n_fallbacks ({self.n_fallbacks}) exceeds n_scans ({self.n_scans})")
        return self


class LoadedSession(NamedTuple):
    """A session as :meth:`Store.load_session` restores it.

    Attributes
    ----------
    record:
        The session's record.
    stamps:
        (N,) float64 scan times, seconds.
    poses:
        (N, 4, 4) float64 ``T_frame_sensor`` (``record.frame`` names the frame).
    state:
        The matcher state as saved (name -> array), for
        :meth:`IncrementalMatcher.load_state_dict <core.odometry.IncrementalMatcher.load_state_dict>`.
    """

    record: SessionRecord
    stamps: np.ndarray
    poses: np.ndarray
    state: dict[str, np.ndarray]


_POSE_STATUSES: tuple[PoseStatus, ...] = ("first", "ok", "fallback")
# One pose-log record: magic, pose index, seq, stamp_ns, stamp_s, the 4x4 pose (row-major),
# status, padding; then a CRC-32 of those bytes. Little-endian, fixed size.
_LOG_MAGIC = b"RPL1"
_LOG_BODY = struct.Struct("<4sQqqd16dB3x")
_LOG_CRC = struct.Struct("<I")
POSE_LOG_RECORD_SIZE = _LOG_BODY.size + _LOG_CRC.size


@dataclass(frozen=True)
class PoseLogRecord:
    """One acknowledged pose in a session's ``poses.log`` (:meth:`Store.append_pose`).

    Attributes
    ----------
    index:
        The pose's place in the session's trajectory (0 for its first scan).
    seq, stamp_ns:
        The scan's sequence number and time stamp (ns), as the vehicle sent them.
    stamp_s:
        The stamp in seconds exactly as the trajectory keeps it (``stamp_ns * 1e-9``).
    pose:
        (4, 4) float64 ``T_frame_sensor``, the pose published.
    status:
        ``"first"``, ``"ok"`` or ``"fallback"``.
    """

    index: int
    seq: int
    stamp_ns: int
    stamp_s: float
    pose: np.ndarray
    status: PoseStatus

    def to_bytes(self) -> bytes:
        pose = np.asarray(self.pose, dtype=np.float64).reshape(16)
        body = _LOG_BODY.pack(
            _LOG_MAGIC,
            self.index,
            self.seq,
            self.stamp_ns,
            self.stamp_s,
            *pose.tolist(),
            _POSE_STATUSES.index(self.status),
        )
        return body + _LOG_CRC.pack(zlib.crc32(body))

    @classmethod
    def from_bytes(cls, data: bytes) -> PoseLogRecord | None:
        """The record in ``data`` (:data:`POSE_LOG_RECORD_SIZE` bytes), ``None`` if torn or damaged."""
        body, crc = data[: _LOG_BODY.size], data[_LOG_BODY.size :]
        if len(crc) != _LOG_CRC.size or _LOG_CRC.unpack(crc)[0] != zlib.crc32(body):
            return None
        magic, index, seq, stamp_ns, stamp_s, *rest = _LOG_BODY.unpack(body)
        status = int(rest[16])
        if magic != _LOG_MAGIC or status >= len(_POSE_STATUSES):
            return None
        pose = np.array(rest[:16], dtype=np.float64).reshape(4, 4)
        return cls(index, seq, stamp_ns, stamp_s, pose, _POSE_STATUSES[status])


@dataclass(frozen=True)
class StoreProblem:
    """A map, session or directory entry that was skipped because it could not be read.

    Attributes
    ----------
    kind:
        ``"map"``, ``"session"`` or ``"entry"`` (an unexpected directory entry).
    name:
        The map name, ``"<vehicle>/<session>"``, or the entry's relative path.
    path:
        The file or directory at fault.
    message:
        Why it was skipped.
    """

    kind: ProblemKind
    name: str
    path: Path
    message: str


@dataclass
class StoreContents:
    """Everything :meth:`Store.load_all` could restore, and what it had to skip.

    Attributes
    ----------
    maps:
        Map name -> grid.
    sessions:
        ``(vehicle, session)`` -> the loaded session.
    problems:
        What was skipped, and why.
    """

    maps: dict[str, TileGrid] = field(default_factory=dict)
    sessions: dict[tuple[str, str], LoadedSession] = field(default_factory=dict)
    problems: list[StoreProblem] = field(default_factory=list)


@dataclass
class _HeldLock:
    """A data directory's flock held by this process: its descriptor and the Stores using it."""

    fd: int | None
    users: int


_HELD_LOCKS: dict[Path, _HeldLock] = {}  # by the data directory's real path
_HELD_LOCKS_GUARD = threading.Lock()
# A Store's finalizer may run from the garbage collector at any allocation, also while this very
# thread is inside the guard (in _acquire_lock, say): taking the guard there again deadlocked a
# test run. Such a release is queued here and done at the next entry into the guard.
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


def _acquire_lock(directory: Path) -> tuple[Path, bool]:
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


def _release_lock(key: Path) -> None:
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
    """:func:`_release_lock`'s work; the caller holds the guard."""
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


class Store:
    """The durable store of maps and sessions under ``data_dir`` (see the module docstring).

    Opening creates ``maps/`` and ``sessions/``, takes the directory's lock and removes temporary
    files left by interrupted atomic writes (their number is logged and kept in
    :attr:`removed_temp_files`). Close the store (or use it as a context manager) to release the
    lock. Stores of one process share the lock (say, a service restarted in-process before the
    old store was closed); only the first of them removes temporary files, since the others
    might delete a live writer's. Use one open Store per directory and process at a time.

    Parameters
    ----------
    data_dir:
        The data directory; created if missing.

    Raises
    ------
    RandtError
        Another process has ``data_dir`` open.
    FormatError
        The directories or the lock file cannot be created.

    Examples
    --------
    >>> with Store(tmp_dir) as store:  # doctest: +SKIP
    ...     store.save_tiles("town", grid, changed_ids=grid.insert(points))
    ...     contents = store.load_all()
    """

    def __init__(self, data_dir: str | os.PathLike[str]) -> None:
        self._root = Path(data_dir).absolute()
        self._maps = self._root / MAPS_DIRNAME
        self._sessions = self._root / SESSIONS_DIRNAME
        try:
            for directory in (self._root, self._maps, self._sessions):
                directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise FormatError(f"cannot create the data directory {self._root}: {exc}") from exc
        lock_key, first = _acquire_lock(self._root)
        self._finalizer = weakref.finalize(self, _release_lock, lock_key)
        self._guard = threading.Lock()
        self._map_locks: dict[str, threading.Lock] = {}
        self._session_locks: dict[tuple[str, str], threading.RLock] = {}
        self._created: dict[tuple[str, str], datetime] = {}
        self._saved_scans: dict[tuple[str, str], int] = {}  # n_scans of each session's last save
        self._versions = self._root / VERSIONS_DIRNAME
        self._problems: list[StoreProblem] = []
        if first:
            self.removed_temp_files = self._remove_temp_files()
        else:
            logger.warning("%s is already open in this process: temporary files are left alone", self._root)
            self.removed_temp_files = 0
        logger.info("store opened at %s", self._root)

    def __repr__(self) -> str:
        return f"Store({str(self._root)!r}{'' if self.is_open else ', closed'})"

    # ------------------------------------------------------------------------------ lifecycle

    @property
    def data_dir(self) -> Path:
        """The (absolute) data directory."""
        return self._root

    @property
    def is_open(self) -> bool:
        """Whether the store still holds its data directory."""
        return self._finalizer.alive

    def writable(self) -> bool:
        """Whether the store is open and its directories accept writes (a readiness check).

        Checks permissions only (``os.access``); a full disk shows up as a :class:`FormatError`
        from the next save.
        """
        return self.is_open and all(os.access(d, os.W_OK | os.X_OK) for d in (self._maps, self._sessions))

    @property
    def problems(self) -> list[StoreProblem]:
        """What the last :meth:`list_sessions` or :meth:`load_all` skipped (a copy)."""
        return list(self._problems)

    def close(self) -> None:
        """Release the data directory's lock; the store cannot be used afterwards."""
        if self._finalizer.alive:
            self._finalizer()
            logger.info("store closed at %s", self._root)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _check_open(self) -> None:
        if not self._finalizer.alive:
            raise RandtError(f"the store at {self._root} is closed")

    def _remove_temp_files(self) -> int:
        """Delete leftover ``.<name>.<random>.tmp`` files in ``DATA`` (``counters.json``) and under
        ``maps/``, ``sessions/`` and ``map-versions/``, and the ``maps/.deleted-*`` directories of
        an interrupted :meth:`delete_map` (or map-name migration)."""
        removed = 0
        for entry in self._maps.iterdir():
            if entry.name.startswith(_DELETED_PREFIX) and entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
                removed += 1
        # The data directory's own file (counters.json) is written atomically too: its leftovers
        # sit in DATA itself, among files that may not be ours (only its own are removed).
        ours = f".{COUNTERS_FILENAME}."
        top_level = [(str(self._root), [e.name for e in self._root.iterdir() if e.name.startswith(ours)])]
        walks = [(d, f) for top in (self._maps, self._sessions, self._versions) for d, _, f in os.walk(top)]
        for dirpath, filenames in top_level + walks:  # os.walk does not follow symlinks
            for name in filenames:
                path = Path(dirpath) / name
                if not _TEMP_FILE_RE.match(name) or path.is_symlink() or not path.is_file():
                    continue
                try:
                    path.unlink()
                except OSError as exc:
                    logger.warning("cannot remove leftover temporary file %s: %s", path, exc)
                    continue
                logger.debug("removed leftover temporary file %s", path)
                removed += 1
        if removed:
            logger.warning("removed %d temporary files left by interrupted writes in %s", removed, self._root)
        else:
            logger.info("no temporary files left by interrupted writes in %s", self._root)
        return removed

    def _map_lock(self, map_name: str) -> threading.Lock:
        with self._guard:
            return self._map_locks.setdefault(map_name, threading.Lock())

    def _session_lock(self, vehicle: str, session: str) -> threading.RLock:
        with self._guard:
            return self._session_locks.setdefault((vehicle, session), threading.RLock())

    # ------------------------------------------------------------------------------ paths

    def map_dir(self, map_name: str) -> Path:
        """``DATA/maps/<map_name>`` (not created).

        Raises
        ------
        ValueError
            ``map_name`` is not a valid name (:func:`wire.ids.validate_id`).
        """
        return self._maps / validate_id(map_name, "map")

    def session_dir(self, vehicle: str, session: str) -> Path:
        """``DATA/sessions/<vehicle>/<session>`` (not created).

        Raises
        ------
        ValueError
            ``vehicle`` or ``session`` is not a valid name (:func:`wire.ids.validate_id`).
        """
        return self._sessions / validate_id(vehicle, "vehicle") / validate_id(session, "session")

    # ------------------------------------------------------------------------------ maps

    def save_tiles(
        self, map_name: str, grid: TileGrid, changed_ids: Iterable[str], *, tiles: list[Tile] | None = None
    ) -> list[str]:
        """Persist a map after an update, rewriting only the tiles that changed.

        Uses :meth:`TileGrid.write_tiles <core.tiles.TileGrid.write_tiles>`: sidecar, the changed
        tiles (and any tile whose file is missing), metadata last, each file atomically. An empty
        grid writes nothing.

        Parameters
        ----------
        map_name:
            The map's name (an id, :mod:`wire.ids`).
        grid:
            The map.
        changed_ids:
            Ids of the tiles changed since the last save (what :meth:`TileGrid.insert` returned).
        tiles:
            The snapshot of ``grid`` to write (:meth:`TileGrid.tiles`); ``None``: the current one.

        Returns
        -------
        list[str]
            Ids of the tiles whose files were written.

        Raises
        ------
        ValueError
            Invalid ``map_name``.
        NotFoundError
            A changed id is not a tile of ``grid``.
        FormatError
            A file could not be written.
        """
        self._check_open()
        directory = self.map_dir(map_name)
        if len(grid) == 0 or tiles == []:
            logger.debug("map %s is empty: nothing to save", map_name)
            return []
        with self._map_lock(map_name):
            written = grid.write_tiles(directory, changed_ids, tiles=tiles)
        logger.debug("saved map %s: %d tiles written, %d in the map", map_name, len(written), len(grid))
        return written

    def load_map(self, map_name: str) -> TileGrid | None:
        """Restore a map saved by :meth:`save_tiles`, or ``None`` if there is none.

        Raises
        ------
        ValueError
            Invalid ``map_name``.
        FormatError
            The map's files are damaged (unreadable metadata or sidecar, a listed tile file that is
            missing or unreadable).
        """
        self._check_open()
        directory = self.map_dir(map_name)
        if not (directory / AUTOWARE_METADATA_NAME).is_file():
            return None
        with self._map_lock(map_name):
            try:
                return load_autoware(directory)
            except NotFoundError as exc:  # the metadata exists, so a missing tile is damage
                raise FormatError(f"map {map_name} is incomplete: {exc}") from exc

    def version_floor(self, map_name: str) -> int:
        """The highest tile version a deleted map of this name reached (0 if none was deleted):
        a new map of the name numbers its tiles above it (:meth:`delete_map`).

        Raises
        ------
        ValueError
            Invalid ``map_name``.
        FormatError
            The floor's file is unreadable.
        """
        self._check_open()
        path = self._versions / validate_id(map_name, "map")
        try:
            text = path.read_text(encoding="ascii").strip()
        except FileNotFoundError:
            return 0
        except OSError as exc:
            raise FormatError(f"cannot read {path}: {exc}") from exc
        if not text.isdigit():
            raise FormatError(f"{path}: not a version number: {text[:40]!r}")
        return int(text)

    def delete_map(self, map_name: str, *, version_floor: int = 0) -> bool:
        """Remove a saved map's directory; False if there was none.

        First the highest tile version the map reached (the larger of ``version_floor``, the
        versions on disk and an earlier floor) is recorded in ``map-versions/<map>``
        (:meth:`version_floor`), so that versions of a later map of the same name never repeat
        one served for this map's content.

        The directory is first renamed to ``maps/.deleted-<name>-<pid>-<ns>`` (one atomic step, so
        after a crash the map is either whole or gone) and then removed; a leftover ``.deleted-*``
        directory is removed when the store next opens.

        Raises
        ------
        ValueError
            Invalid ``map_name``.
        """
        self._check_open()
        directory = self.map_dir(map_name)
        with self._map_lock(map_name):
            floor = max(version_floor, self.version_floor(map_name))
            if directory.is_dir():
                with contextlib.suppress(RandtError, OSError):
                    saved = read_sidecar(directory, _sidecar_tile_size(directory))[1]
                    floor = max(floor, *saved.values(), 0)
            if floor > 0:
                self._versions.mkdir(exist_ok=True)
                atomic_write_bytes(self._versions / map_name, f"{floor}\n".encode("ascii"))
            if not directory.is_dir():
                return False
            trash = self._maps / f"{_DELETED_PREFIX}{map_name}-{os.getpid()}-{time.time_ns()}"
            os.replace(directory, trash)
            fsync_directory(self._maps)
        shutil.rmtree(trash, ignore_errors=True)
        logger.info("deleted map %s", map_name)
        return True

    def list_maps(self) -> list[str]:
        """Names of the saved maps (those with a metadata file), sorted."""
        self._check_open()
        names = []
        for entry in sorted(self._maps.iterdir()):
            if not entry.is_dir():
                continue
            try:
                validate_id(entry.name, "map")
            except ValueError:
                logger.warning("ignoring %s: not a valid map directory name", entry)
                continue
            if (entry / AUTOWARE_METADATA_NAME).is_file():
                names.append(entry.name)
            else:
                logger.debug("ignoring %s: no %s (no save completed)", entry, AUTOWARE_METADATA_NAME)
        return names

    # ------------------------------------------------------------------------------ sessions

    def save_session(
        self,
        meta: SessionRecord,
        poses: np.ndarray,
        stamps: np.ndarray,
        matcher_state: dict[str, np.ndarray],
    ) -> SessionRecord:
        """Persist a session: its matcher state (with the commit record), trajectory and record.

        Writes ``matcher.npz`` (the commit), then ``trajectory.tum`` and ``session.json``, each
        atomically. A session without scans yet (N = 0) has no ``trajectory.tum``.

        Parameters
        ----------
        meta:
            The session's record; ``n_scans`` must equal ``N``. ``created`` is kept from the
            session's first save (``meta.created`` is used only then); ``updated`` is set to now.
        poses:
            (N, 4, 4) ``T_frame_sensor`` of every scan so far.
        stamps:
            (N,) scan times, seconds.
        matcher_state:
            :meth:`IncrementalMatcher.state_dict <core.odometry.IncrementalMatcher.state_dict>`
            (any name -> numeric array; names must not start with ``_store_``).

        Returns
        -------
        SessionRecord
            The record as written.

        Raises
        ------
        ValueError
            Invalid names.
        InvalidCloudError
            ``meta.n_scans != N``, wrong shapes, non-finite values, or poses that are not
            homogeneous transforms (a ``ValueError`` too).
        FormatError
            An unusable matcher state (reserved or malformed key, object array; a ``ValueError``
            too), or a file could not be written.
        """
        self._check_open()
        key = meta.key
        directory = self.session_dir(*key)
        what = f"session {key[0]}/{key[1]}"
        poses, stamps = _checked_trajectory(poses, stamps, what)
        if meta.n_scans != poses.shape[0]:
            raise InvalidCloudError(
                f"{what}: the record says n_scans={meta.n_scans} but {poses.shape[0]} poses were given"
            )
        arrays = _checked_state(matcher_state)
        with self._session_lock(*key):
            saved_n = self._saved_scans.get(key, -1)
            if meta.n_scans < saved_n:
                # An older snapshot arriving after a newer one (a flush racing a close): writing it
                # would drop poses the newer one holds and the pose log no longer has.
                logger.warning(
                    "session %s/%s: not saving %d scans over a saved %d", *key, meta.n_scans, saved_n
                )
                return meta
            record = meta.model_copy(update={"created": self._created_time(meta), "updated": _utcnow()})
            arrays[_KEY_RECORD] = np.array(record.model_dump_json())
            arrays[_KEY_STAMPS] = stamps
            arrays[_KEY_POSES] = poses
            buffer = io.BytesIO()
            np.savez(buffer, **arrays)  # type: ignore[arg-type]  # mypy binds **arrays to allow_pickle: bool too
            try:
                directory.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise FormatError(f"cannot create {directory}: {exc}") from exc
            atomic_write_bytes(directory / MATCHER_FILENAME, buffer.getvalue())
            _write_trajectory(directory / TRAJECTORY_FILENAME, stamps, poses)
            atomic_write_bytes(directory / SESSION_FILENAME, _record_json(record))
            self._created[key] = record.created
            self._saved_scans[key] = record.n_scans
            self._compact_pose_log(directory, record.n_scans)
        logger.debug(
            "saved session %s/%s: %d scans, last_seq %d",
            record.vehicle,
            record.session,
            record.n_scans,
            record.last_seq,
        )
        return record

    def _created_time(self, meta: SessionRecord) -> datetime:
        """``created`` of the session's first save (from memory, else from its commit, else ``meta``)."""
        created = self._created.get(meta.key)
        if created is not None:
            return created
        try:
            return _read_record(self.session_dir(*meta.key) / MATCHER_FILENAME, *meta.key).created
        except NotFoundError:
            return meta.created
        except (RandtError, OSError) as exc:
            logger.warning("session %s/%s: overwriting an unreadable commit (%s)", *meta.key, exc)
            return meta.created

    def load_session(self, vehicle: str, session: str) -> LoadedSession:
        """Restore a session saved by :meth:`save_session`.

        The commit record in ``matcher.npz`` is the truth; ``session.json`` and ``trajectory.tum``
        are rewritten from it when they are missing, unreadable or lag behind (a crash between
        the writes of one save), with a warning.

        Returns
        -------
        LoadedSession
            ``(record, stamps, poses, state)``: stamps (N,), poses (N, 4, 4), the matcher state.

        Raises
        ------
        ValueError
            Invalid names.
        NotFoundError
            No such session.
        FormatError
            ``matcher.npz`` is damaged, or its record names another session.
        """
        self._check_open()
        directory = self.session_dir(vehicle, session)
        with self._session_lock(vehicle, session):
            loaded = _read_commit(directory / MATCHER_FILENAME, vehicle, session)
            self._repair_views(directory, loaded)
            self._saved_scans.setdefault((vehicle, session), loaded.record.n_scans)
            records = _read_pose_log(directory / POSE_LOG_FILENAME, repair=True)
        return _with_logged(loaded, records)

    def append_pose(self, vehicle: str, session: str, record: PoseLogRecord) -> None:
        """Append one acknowledged pose to the session's ``poses.log`` and fsync it (module docstring).

        Call it before the pose is published: when it returns, the pose survives a crash.

        Raises
        ------
        ValueError
            Invalid names.
        FormatError
            The record could not be written and synced (disk full, read-only...); the file is cut
            back to its previous length where possible, and a torn tail is cut when it is next read.
        """
        self._check_open()
        directory = self.session_dir(vehicle, session)
        path = directory / POSE_LOG_FILENAME
        data = record.to_bytes()
        with self._session_lock(vehicle, session):
            try:
                created = not path.exists()
                if created:
                    directory.mkdir(parents=True, exist_ok=True)
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
            if created:  # the new file's directory entries must be durable too
                try:
                    for d in (directory, directory.parent, directory.parent.parent):
                        fsync_directory(d)
                except OSError as exc:
                    raise FormatError(f"cannot sync {directory}: {exc}") from exc

    def reset_pose_log(self, vehicle: str, session: str) -> None:
        """Remove a session's ``poses.log`` (a session that starts afresh: nothing in it was
        acknowledged, since a session's first pose is published only after its first save)."""
        self._check_open()
        path = self.session_dir(vehicle, session) / POSE_LOG_FILENAME
        with self._session_lock(vehicle, session):
            if path.exists():
                logger.warning(
                    "session %s/%s starts afresh: removing its old %s", vehicle, session, path.name
                )
                path.unlink()
                fsync_directory(path.parent)

    def _compact_pose_log(self, directory: Path, n_saved: int) -> None:
        """Drop the records of poses ``< n_saved`` (now in the snapshot) by an atomic replace."""
        path = directory / POSE_LOG_FILENAME
        records = _read_pose_log(path, repair=False)
        if not records and not path.exists():
            return
        keep = [r for r in records if r.index >= n_saved]
        if len(keep) == len(records) and path.stat().st_size == len(records) * POSE_LOG_RECORD_SIZE:
            return
        if keep:
            atomic_write_bytes(path, b"".join(r.to_bytes() for r in keep))
        elif path.exists():
            path.unlink()
            fsync_directory(directory)

    def list_sessions(self) -> list[SessionRecord]:
        """The records of every saved session, sorted by ``(vehicle, session)``.

        Records are read from each session's commit (``matcher.npz``). A session that cannot be
        read is skipped with a logged error and reported in :attr:`problems`.
        """
        self._check_open()
        records, problems = self._scan_sessions()
        self._problems = problems
        return records

    def mark_session(self, vehicle: str, session: str, state: SessionState) -> SessionRecord:
        """Set a session's state (``"active"``, ``"closed"`` or ``"expired"``) and save it.

        Returns
        -------
        SessionRecord
            The record as written.

        Raises
        ------
        ValueError
            Invalid names or state.
        NotFoundError
            No such session.
        FormatError
            The session's files are damaged or cannot be written.
        """
        self._check_open()
        if state not in ("active", "closed", "expired"):
            raise ValueError(f"session state must be 'active', 'closed' or 'expired', got {state!r}")
        self.session_dir(vehicle, session)  # validates the names before they key a lock
        with self._session_lock(vehicle, session):  # re-entrant: no save slips in between
            record, stamps, poses, arrays = self.load_session(vehicle, session)
            saved = self.save_session(record.model_copy(update={"state": state}), poses, stamps, arrays)
        logger.info("session %s/%s is now %s", vehicle, session, state)
        return saved

    # ------------------------------------------------------------------------------ everything

    def migrate_map_names(self) -> list[tuple[str, str, str]]:
        """Rename the maps of sessions without priors to their injective names (run by :meth:`load_all`).

        Before, a session's own map was ``<vehicle>.<session>``, which collided (vehicle ``col.a``
        + session ``b`` and vehicle ``col`` + session ``a.b`` shared ``col.a.b``). Each stored
        session in its own frame whose record names that legacy map
        (:func:`wire.ids.legacy_session_map_name`) moves to :func:`wire.ids.session_map_name`:

        1. the map directory is renamed (one atomic step) when this session is its only user,
           else copied (into a temporary directory, fsync'd, renamed): a map two sessions were
           fused into stays fused, and each of them keeps a copy;
        2. the session's record is saved with the new name;
        3. a legacy map no record names any more is deleted.

        Every step can be interrupted: the next open redoes what is left (an interrupted copy is
        a ``.deleted-*`` directory, removed on open). Names that need no change (ids of letters,
        digits and dashes) are untouched, so usually there is nothing to do.

        Returns
        -------
        list[tuple[str, str, str]]
            ``("<vehicle>/<session>", old map, new map)`` for each session moved.
        """
        self._check_open()
        records, _ = self._scan_sessions()
        moves = [
            (r, session_map_name(r.vehicle, r.session))
            for r in records
            if r.frame == "session"
            and r.map is not None
            and r.map == legacy_session_map_name(r.vehicle, r.session)
            and r.map != session_map_name(r.vehicle, r.session)
        ]
        done: list[tuple[str, str, str]] = []
        for record, new in moves:
            old = record.map
            assert old is not None  # filtered above
            users = sum(r.map == old for r in records)
            old_dir, new_dir = self.map_dir(old), self.map_dir(new)
            try:
                with self._map_lock(old), self._map_lock(new):
                    if old_dir.is_dir() and not new_dir.exists():
                        if users == 1:
                            os.replace(old_dir, new_dir)
                        else:
                            _copy_tree_durably(old_dir, new_dir, self._maps)
                        fsync_directory(self._maps)
                with self._session_lock(record.vehicle, record.session):
                    loaded = self.load_session(record.vehicle, record.session)
                    self.save_session(
                        loaded.record.model_copy(update={"map": new}),
                        loaded.poses,
                        loaded.stamps,
                        loaded.state,
                    )
            except (RandtError, OSError, ValueError) as exc:
                logger.error(
                    "store: could not move map %s of session %s/%s to %s: %s",
                    old,
                    record.vehicle,
                    record.session,
                    new,
                    exc,
                )
                continue
            records = [r for r in records if r.key != record.key] + [record.model_copy(update={"map": new})]
            done.append((f"{record.vehicle}/{record.session}", old, new))
            logger.warning(
                "store: session %s/%s's map %s is now %s (injective session-map names)%s",
                record.vehicle,
                record.session,
                old,
                new,
                "" if users == 1 else f"; {users} sessions were fused in {old}: each keeps a copy",
            )
        named = {r.map for r in records}
        for old in {old for _, old, _ in done} - named:
            self.delete_map(old)
        return done

    def load_all(self) -> StoreContents:
        """Restore every map and session; skip (and report) what cannot be read.

        Returns
        -------
        StoreContents
            The maps, the sessions and the problems (also kept in :attr:`problems`).
        """
        self._check_open()
        contents = StoreContents()
        self.migrate_map_names()
        for name in self.list_maps():
            try:
                grid = self.load_map(name)
            except (RandtError, OSError) as exc:
                self._report(contents.problems, "map", name, self.map_dir(name), str(exc))
                continue
            if grid is not None:
                contents.maps[name] = grid
        records, problems = self._scan_sessions()
        contents.problems.extend(problems)
        for record in records:
            key = (record.vehicle, record.session)
            try:
                contents.sessions[key] = self.load_session(*key)
            except (RandtError, OSError) as exc:
                path = self.session_dir(*key)
                self._report(contents.problems, "session", f"{key[0]}/{key[1]}", path, str(exc))
        self._problems = list(contents.problems)
        logger.info(
            "restored %d maps and %d sessions from %s (%d skipped)",
            len(contents.maps),
            len(contents.sessions),
            self._root,
            len(contents.problems),
        )
        return contents

    # ------------------------------------------------------------------------------ internals

    @staticmethod
    def _report(problems: list[StoreProblem], kind: ProblemKind, name: str, path: Path, msg: str) -> None:
        logger.error("skipping %s %s: %s", kind, name, msg)
        problems.append(StoreProblem(kind=kind, name=name, path=path, message=msg))

    def _scan_sessions(self) -> tuple[list[SessionRecord], list[StoreProblem]]:
        records: list[SessionRecord] = []
        problems: list[StoreProblem] = []
        for vehicle_dir in sorted(self._sessions.iterdir()):
            if not self._valid_entry(vehicle_dir, "vehicle", problems):
                continue
            for session_dir in sorted(vehicle_dir.iterdir()):
                if not self._valid_entry(session_dir, "session", problems):
                    continue
                name = f"{vehicle_dir.name}/{session_dir.name}"
                commit = session_dir / MATCHER_FILENAME
                if not commit.is_file():
                    if (session_dir / SESSION_FILENAME).exists():
                        self._report(problems, "session", name, commit, f"{MATCHER_FILENAME} is missing")
                    else:  # an empty directory: the first save never completed
                        logger.debug("ignoring %s: no save completed", session_dir)
                    continue
                try:
                    records.append(_read_record(commit, vehicle_dir.name, session_dir.name))
                except (RandtError, OSError) as exc:
                    self._report(problems, "session", name, commit, str(exc))
        return records, problems

    def _valid_entry(self, path: Path, what: str, problems: list[StoreProblem]) -> bool:
        rel = str(path.relative_to(self._root))
        if not path.is_dir() or path.is_symlink():
            self._report(problems, "entry", rel, path, f"not a {what} directory")
            return False
        try:
            validate_id(path.name, what)
        except ValueError as exc:
            self._report(problems, "entry", rel, path, str(exc))
            return False
        return True

    def _repair_views(self, directory: Path, loaded: LoadedSession) -> None:
        """Rewrite ``session.json`` / ``trajectory.tum`` where they disagree with the commit."""
        name = f"{loaded.record.vehicle}/{loaded.record.session}"
        json_path = directory / SESSION_FILENAME
        try:
            current: SessionRecord | None = SessionRecord.model_validate_json(json_path.read_bytes())
        except (OSError, ValueError) as exc:
            logger.warning("session %s: %s unreadable (%s)", name, SESSION_FILENAME, exc)
            current = None
        if current != loaded.record:
            logger.warning("session %s: rewriting %s from %s", name, SESSION_FILENAME, MATCHER_FILENAME)
            atomic_write_bytes(json_path, _record_json(loaded.record))

        tum_path = directory / TRAJECTORY_FILENAME
        if loaded.stamps.size == 0:
            agrees = not tum_path.exists()
        else:
            try:
                stamps, poses = read_tum(tum_path)
                agrees = (
                    stamps.shape == loaded.stamps.shape
                    and np.allclose(stamps, loaded.stamps, rtol=0.0, atol=_VIEW_TOLERANCE)
                    and np.allclose(poses, loaded.poses, rtol=0.0, atol=_VIEW_TOLERANCE)
                )
            except RandtError as exc:
                logger.warning("session %s: %s unreadable (%s)", name, TRAJECTORY_FILENAME, exc)
                agrees = False
        if not agrees:
            logger.warning("session %s: rewriting %s from %s", name, TRAJECTORY_FILENAME, MATCHER_FILENAME)
            _write_trajectory(tum_path, loaded.stamps, loaded.poses)


# ---------------------------------------------------------------------------------- helpers


def _record_json(record: SessionRecord) -> bytes:
    return (record.model_dump_json(indent=2) + "\n").encode("utf-8")


def _write_trajectory(path: Path, stamps: np.ndarray, poses: np.ndarray) -> None:
    """``write_tum``, or no file at all for an empty trajectory (a TUM file needs a row)."""
    if stamps.size:
        write_tum(path, stamps, poses)
    elif path.exists():
        try:
            path.unlink()
        except OSError as exc:
            raise FormatError(f"cannot remove {path}: {exc}") from exc


def _checked_trajectory(poses: np.ndarray, stamps: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4, 4) and (N,) float64 copies, finite, homogeneous (N may be 0)."""
    poses = np.array(poses, dtype=np.float64)
    stamps = np.array(stamps, dtype=np.float64)
    if poses.size == 0 and poses.ndim < 3:
        poses = poses.reshape(0, 4, 4)  # np.array([]) for "no poses yet"
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise InvalidCloudError(f"{what}: poses must be (N, 4, 4), got {poses.shape}")
    if stamps.shape != (poses.shape[0],):
        raise InvalidCloudError(
            f"{what}: stamps must be ({poses.shape[0]},) to match poses, got {stamps.shape}"
        )
    if not (np.isfinite(poses).all() and np.isfinite(stamps).all()):
        raise InvalidCloudError(f"{what}: poses and stamps must be finite")
    if poses.size and np.abs(poses[:, 3, :] - _BOTTOM_ROW).max() > 1e-9:
        raise InvalidCloudError(f"{what}: poses are not homogeneous (bottom row != [0 0 0 1])")
    return poses, stamps


def _checked_state(matcher_state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The matcher state as arrays that ``np.load(allow_pickle=False)`` can read back."""
    arrays: dict[str, np.ndarray] = {}
    for key, value in matcher_state.items():
        if not isinstance(key, str) or not _STATE_KEY_RE.fullmatch(key) or key.startswith(_RESERVED_PREFIX):
            raise FormatError(
                f"matcher state key {key!r} is not usable: keys are names from A-Z a-z 0-9 _ . - and "
                f"must not start with {_RESERVED_PREFIX!r}"
            )
        array = np.asarray(value)
        if array.dtype.hasobject:
            raise FormatError(f"matcher state {key!r} is an object array; only plain arrays can be saved")
        arrays[key] = array
    return arrays


def _read_record(path: Path, vehicle: str, session: str) -> SessionRecord:
    """Only the commit record of ``matcher.npz`` (the archive's other members are not read)."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            text = str(npz[_KEY_RECORD][()])
    except FileNotFoundError as exc:
        raise NotFoundError(f"session {vehicle}/{session} does not exist") from exc
    except _NPZ_ERRORS as exc:
        raise FormatError(f"{path}: cannot read the session's commit: {exc}") from exc
    return _parse_record(text, path, vehicle, session)


def _parse_record(text: str, path: Path, vehicle: str, session: str) -> SessionRecord:
    try:
        record = SessionRecord.model_validate_json(text)
    except ValueError as exc:
        raise FormatError(f"{path}: invalid session record: {exc}") from exc
    if (record.vehicle, record.session) != (vehicle, session):
        raise FormatError(f"{path}: holds session {record.vehicle}/{record.session}, not {vehicle}/{session}")
    return record


def _read_commit(path: Path, vehicle: str, session: str) -> LoadedSession:
    """Everything in ``matcher.npz``, checked for consistency."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {key: npz[key] for key in npz.files}
    except FileNotFoundError as exc:
        raise NotFoundError(f"session {vehicle}/{session} does not exist") from exc
    except _NPZ_ERRORS as exc:
        raise FormatError(f"{path}: cannot read the session's commit: {exc}") from exc
    missing = [k for k in (_KEY_RECORD, _KEY_STAMPS, _KEY_POSES) if k not in arrays]
    if missing:
        raise FormatError(f"{path}: not a session commit (missing {', '.join(missing)})")
    record = _parse_record(str(arrays.pop(_KEY_RECORD)[()]), path, vehicle, session)
    try:
        poses, stamps = _checked_trajectory(arrays.pop(_KEY_POSES), arrays.pop(_KEY_STAMPS), str(path))
    except (InvalidCloudError, ValueError) as exc:
        raise FormatError(f"{path}: invalid trajectory: {exc}") from exc
    if record.n_scans != poses.shape[0]:
        raise FormatError(f"{path}: record says {record.n_scans} scans, trajectory has {poses.shape[0]}")
    state = {k: v for k, v in arrays.items() if not k.startswith(_RESERVED_PREFIX)}
    return LoadedSession(record=record, stamps=stamps, poses=poses, state=state)


def _copy_tree_durably(source: Path, target: Path, parent: Path) -> None:
    """Copy the directory ``source`` to ``target`` (in ``parent``) in one visible step: copy into
    ``parent/.deleted-copy-*`` (removed on the next open if this is interrupted), fsync every file
    and the directory, then rename it to ``target``."""
    scratch = parent / f"{_DELETED_PREFIX}copy-{target.name}-{os.getpid()}-{time.time_ns()}"
    shutil.copytree(source, scratch)
    for path in scratch.rglob("*"):
        if path.is_file():
            with path.open("rb+") as fh:
                os.fsync(fh.fileno())
    fsync_directory(scratch)
    os.replace(scratch, target)


# --------------------------------------------------------------------------------------------
# counters (service/metrics.py): DATA/counters.json, written by the flusher
# --------------------------------------------------------------------------------------------

#: The counters' totals, so ``/status`` and ``/metrics`` go on counting across restarts.
COUNTERS_FILENAME = "counters.json"

#: ``{counter name: {label value ("" when unlabelled): total}}``.
CounterTotals = dict[str, dict[str, float]]


def save_counters(data_dir: Path, totals: CounterTotals) -> None:
    """Write the counters' totals to ``data_dir/counters.json`` atomically (temp file, fsync, rename).

    A crash loses at most the counts since the previous write (one flush interval).
    """
    import json

    body = json.dumps({"version": 1, "counters": totals}, sort_keys=True, indent=1) + "\n"
    atomic_write_bytes(Path(data_dir) / COUNTERS_FILENAME, body.encode())


def load_counters(data_dir: Path) -> CounterTotals:
    """The totals :func:`save_counters` wrote; ``{}`` when there is no file. A damaged file is
    logged and read as ``{}`` (counting restarts from zero; the maps and sessions are unaffected);
    entries that are not non-negative finite numbers are skipped."""
    import json
    import math

    path = Path(data_dir) / COUNTERS_FILENAME
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as exc:
        logger.error("store: %s is unreadable (%s); counters start from zero", path, exc)
        return {}
    counters = doc.get("counters") if isinstance(doc, dict) else None
    if not isinstance(counters, dict):
        logger.error("store: %s holds no counters; counters start from zero", path)
        return {}
    out: CounterTotals = {}
    for name, values in counters.items():
        if not isinstance(name, str) or not isinstance(values, dict):
            continue
        kept = {
            str(label): float(v)
            for label, v in values.items()
            if isinstance(label, str)
            and len(label) <= 64
            and isinstance(v, int | float)
            and not isinstance(v, bool)
            and math.isfinite(v)
            and v >= 0
        }
        if kept:
            out[name] = kept
    return out


def _sidecar_tile_size(directory: Path) -> int:
    """The tile size a map's sidecar states (so :func:`read_sidecar` accepts it)."""
    import yaml

    doc = yaml.safe_load((directory / GRID_SIDECAR_NAME).read_text(encoding="utf-8"))
    if not isinstance(doc, dict) or not isinstance(doc.get("tile_size_m"), int):
        raise FormatError(f"{directory / GRID_SIDECAR_NAME}: no tile_size_m")
    return int(doc["tile_size_m"])


def _read_pose_log(path: Path, *, repair: bool) -> list[PoseLogRecord]:
    """The whole records of a ``poses.log`` up to the first torn or damaged one (none if no file).

    With ``repair``, what follows them (a torn tail: a crash during an append) is cut off the
    file, so the next append continues a clean log.
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return []
    except OSError as exc:
        raise FormatError(f"cannot read {path}: {exc}") from exc
    records: list[PoseLogRecord] = []
    size = POSE_LOG_RECORD_SIZE
    for start in range(0, len(data) - size + 1, size):
        record = PoseLogRecord.from_bytes(data[start : start + size])
        if record is None:
            break
        records.append(record)
    good = len(records) * size
    if good != len(data):
        logger.warning(
            "%s: cutting %d bytes after %d whole records (a torn or damaged tail)",
            path,
            len(data) - good,
            len(records),
        )
        if repair:
            try:
                with open(path, "r+b") as fh:
                    fh.truncate(good)
                    fh.flush()
                    os.fsync(fh.fileno())
            except OSError as exc:
                raise FormatError(f"cannot cut the torn tail of {path}: {exc}") from exc
    return records


def _with_logged(loaded: LoadedSession, records: list[PoseLogRecord]) -> LoadedSession:
    """The snapshot ``loaded`` extended by the logged poses beyond it (contiguous from its end)."""
    n = loaded.poses.shape[0]
    extra: list[PoseLogRecord] = []
    for r in records:
        if r.index < n:
            continue  # the snapshot holds it already (a crash before the log was compacted)
        if r.index != n + len(extra):
            logger.error(
                "session %s/%s: %s jumps from pose %d to %d; the rest is ignored",
                loaded.record.vehicle,
                loaded.record.session,
                POSE_LOG_FILENAME,
                n + len(extra),
                r.index,
            )
            break
        extra.append(r)
    if not extra:
        return loaded
    poses = np.concatenate([loaded.poses, np.stack([r.pose for r in extra])])
    stamps = np.concatenate([loaded.stamps, np.array([r.stamp_s for r in extra], dtype=np.float64)])
    record = loaded.record.model_copy(
        update={
            "n_scans": poses.shape[0],
            "n_fallbacks": loaded.record.n_fallbacks + sum(r.status == "fallback" for r in extra),
            "last_seq": max(loaded.record.last_seq, extra[-1].seq),
        }
    )
    return LoadedSession(record=record, stamps=stamps, poses=poses, state=loaded.state)
