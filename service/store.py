"""The service's durable, embedded store: tiled maps and driving sessions under one data directory.

Layout
------
::

    DATA/.randt-store.lock                       held (flock) while a Store has DATA open
    DATA/maps/<map>/<ix>_<iy>.pcd                Autoware divided map, as randt.core.tiles writes it
    DATA/maps/<map>/pointcloud_map_metadata.yaml
    DATA/maps/<map>/randt_tile_grid.yaml
    DATA/sessions/<vehicle>/<session>/matcher.npz      the last snapshot: matcher state + commit record
    DATA/sessions/<vehicle>/<session>/poses.log        acknowledged poses, appended and fsync'd one by one
    DATA/sessions/<vehicle>/<session>/poses.<i>.log    a closed-off poses.log: poses from the i-th on
    DATA/sessions/<vehicle>/<session>/trajectory.tum   the snapshot's poses: stamp_s tx ty tz qx qy qz qw
    DATA/sessions/<vehicle>/<session>/session.json     the snapshot's record (:class:`SessionRecord`)
    DATA/sessions/<vehicle>/<session>/resume.npz       a recent sweep at its logged pose (resuming)
    DATA/map-versions/<map>                            version floor of a deleted map's name

Map, vehicle and session names are ids (:mod:`randt.wire.ids`: letters, digits, ``_ . -``, at most 64
characters, starting with a letter or digit); every path is built from checked names only.

A session's trajectory
----------------------
The pose log is the trajectory's truth, and no pose in it is written twice: the session worker
appends one fixed-size record per pose (:class:`PoseLogRecord`: the pose's index in the
trajectory, its scan's ``seq`` and stamp, the pose, its status, a CRC-32) and fsyncs it *before*
the pose is published (:meth:`Store.append_pose`). A snapshot (:meth:`Store.save_session`) closes
the log off into a *segment*, ``poses.<index of its first pose, 10 digits>.log``, by one rename,
once it holds :data:`SEGMENT_RECORDS` records; segments are never written again. The trajectory is
the segments one after the other from pose 0, then the log. A snapshot is the matcher state and
the session's record (how many poses it covers, ``n_scans``), written as ``matcher.npz``: its cost
does not grow with the session's length, since the poses are on disk already. Poses handed to
:meth:`Store.save_session` that were never logged (callers other than the service) are kept in
that commit (keys ``_store_first``, ``_store_stamps``, ``_store_poses``) and moved into a segment
by the next snapshot, before the commit that held them is replaced. A commit written before
segments existed held the whole trajectory there, from pose 0; it loads as it did, and the next
snapshot moves those poses into a segment (once).

Crash safety
------------
Every file but the pose log and ``trajectory.tum`` (both appended to) is replaced atomically
(:mod:`randt.core.io.atomic`: temporary file, fsync, rename, fsync of the directory), so a reader, or a
restart after a crash, sees each file whole: its old or its new content. What spans several files
is ordered:

* **maps** (:meth:`TileGrid.write_tiles <randt.core.tiles.TileGrid.write_tiles>`): sidecar, changed
  tiles, metadata last; the metadata never names a tile file that does not exist.
* **sessions**: a pose is in the log before it is acknowledged. A snapshot writes (1) the
  commit's own poses into a segment (fsync'd, renamed into place), if it has any; (2) the log's
  rename into a segment, if due (after a conversion, the records a segment already holds are
  first dropped from the log by an atomic replace); (3) ``matcher.npz``, the *commit*: the matcher
  state (any arrays, whatever the matcher; the service leaves the trajectory out,
  :func:`randt.service.matchers.without_trajectory`) and, under keys starting with ``_store_``, the
  record; (4) the views for people and other tools: ``trajectory.tum`` (the commit's poses; the
  rows since the last snapshot are appended; it appears with the first scan) and
  ``session.json``. Steps 1 and 2 only move poses between files (a crash between leaves them in
  both, the same: loading takes each pose once, by its index), and a commit never covers a pose
  that is not on disk. A crash before step 3 leaves the previous snapshot, whose poses and the
  ones logged after them are all there; after it, the new one. :meth:`Store.load_session` returns
  the commit's matcher state and the trajectory as far as it is on disk (the record brought
  forward over the poses logged after the commit), cuts off a torn last log record (a crash during
  an append fails its CRC), and rewrites views that lag behind or are torn (a crash during step 4).
* **map version floors** (``map-versions/<map>``): :meth:`Store.delete_map` first records the
  highest tile version the map reached, so a new map of that name continues above it and a
  ``(tile, version)`` pair is never reused for other content (:meth:`Store.version_floor`).

A crash can leave the atomic writers' temporary files (``.<name>.<random>.tmp``) behind; opening a
:class:`Store` removes them. One process at a time may open a data directory: the store holds an
exclusive ``flock`` on ``DATA/.randt-store.lock`` (released by the kernel if the process dies), so
the clean-up never deletes the temporary file of a live writer.

Damaged files
-------------
A file that cannot be read (say, a truncated ``matcher.npz`` written by a buggy older version, a
segment cut short, poses missing between segments) fails only its own map or session:
:meth:`Store.list_sessions` and :meth:`Store.load_all` skip it, log an error and report it as a
:class:`StoreProblem`; everything else still loads. Only the log's torn tail is repaired, by
cutting it; a damaged segment is never cut.

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
from scipy.spatial.transform import Rotation

from randt.core.errors import FormatError, InvalidCloudError, NotFoundError, RandtError
from randt.core.io import atomic_write_bytes, read_tum, write_tum
from randt.core.io.atomic import append_durably, atomic_open, fsync_directory
from randt.core.io.autoware import (
    AUTOWARE_METADATA_NAME,
    GRID_SIDECAR_NAME,
    make_directory,
    read_projector_info,
    read_sidecar,
    write_projector_info,
)
from randt.core.tiles import Tile, TileGrid, load_autoware
from randt.wire.ids import legacy_session_map_name, session_map_name, validate_id

try:  # POSIX; elsewhere the store runs without the single-process guard
    import fcntl
except ImportError:  # pragma: no cover - not exercised on Linux
    fcntl = None  # type: ignore[assignment]

__all__ = [
    "LOCK_FILENAME",
    "MAPS_DIRNAME",
    "MATCHER_FILENAME",
    "POSE_LOG_FILENAME",
    "RESUME_FILENAME",
    "SEGMENT_RECORDS",
    "SESSIONS_DIRNAME",
    "SESSION_FILENAME",
    "TRAJECTORY_FILENAME",
    "DataDirInUseError",
    "LoadedSession",
    "PoseLogRecord",
    "ResumeSweep",
    "SessionFrame",
    "SessionRecord",
    "SessionState",
    "Store",
    "StoreContents",
    "StoreProblem",
    "check_data_dir_free",
    "segment_name",
]

logger = logging.getLogger(__name__)

MAPS_DIRNAME = "maps"
SESSIONS_DIRNAME = "sessions"
SESSION_FILENAME = "session.json"
TRAJECTORY_FILENAME = "trajectory.tum"
MATCHER_FILENAME = "matcher.npz"
RESUME_FILENAME = "resume.npz"
LOCK_FILENAME = ".randt-store.lock"
POSE_LOG_FILENAME = "poses.log"
#: A closed-off pose log: ``poses.<index of its first pose, 10 digits>.log`` (:func:`segment_name`).
_SEGMENT_RE = re.compile(r"^poses\.(\d{10})\.log$")
#: A snapshot closes the pose log off into a segment once it holds this many records (5 min at
#: 10 Hz, 516 kB): few files per session, and a torn-tail repair never touches more than that.
SEGMENT_RECORDS = 3000
VERSIONS_DIRNAME = "map-versions"

SessionState = Literal["active", "closed", "expired"]
SessionFrame = Literal["map", "session"]
PoseStatus = Literal["first", "ok", "fallback"]
ProblemKind = Literal["map", "session", "entry"]

# randt.core.io.atomic names its temporary files tempfile.mkstemp(prefix=f".{target}.", suffix=".tmp"),
# in the target's directory. No name the store writes starts with a dot (ids, fixed names).
_TEMP_FILE_RE = re.compile(r"^\..+\.tmp$")
_DELETED_PREFIX = ".deleted-"  # maps/.deleted-<name>-...: a delete_map that did not finish
# Keys of matcher.npz that belong to the store, not to the matcher state.
_RESERVED_PREFIX = "_store_"
_KEY_RECORD = "_store_record"
_KEY_STAMPS = "_store_stamps"
_KEY_POSES = "_store_poses"
_KEY_FIRST = "_store_first"  # index of the commit's own first pose (absent: 0, the whole trajectory)
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
        Names (ids, :mod:`randt.wire.ids`); the session lives in ``sessions/<vehicle>/<session>/``.
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


class ResumeSweep(NamedTuple):
    """A recent sweep of a session (:meth:`Store.save_resume_sweep`): its pose's index in the
    trajectory, that pose (4, 4) and its points (N, 3) float32 in the sensor frame."""

    pose_index: int
    pose: np.ndarray
    points: np.ndarray


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
        :meth:`IncrementalMatcher.load_state_dict <randt.core.odometry.IncrementalMatcher.load_state_dict>`.
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


# The same record as a numpy structured type, to read and write whole segments at once.
_LOG_DTYPE = np.dtype(
    [
        ("magic", "S4"),
        ("index", "<u8"),
        ("seq", "<i8"),
        ("stamp_ns", "<i8"),
        ("stamp_s", "<f8"),
        ("pose", "<f8", (16,)),
        ("status", "u1"),
        ("pad", "V3"),
        ("crc", "<u4"),
    ]
)
assert _LOG_DTYPE.itemsize == POSE_LOG_RECORD_SIZE
_STATUS_FIRST, _STATUS_OK, _STATUS_FALLBACK = range(3)


@dataclass(frozen=True)
class _Poses:
    """Consecutive poses of a session's trajectory, from ``first`` on, as columns: the records of
    a segment or of the log, a commit's own poses, or what a caller saved.

    ``seq`` is -1 where the scan's sequence number is not known (poses given to
    :meth:`Store.save_session` that were never logged); ``status`` indexes ``("first", "ok",
    "fallback")``.
    """

    first: int
    stamps: np.ndarray  # (n,) float64 seconds
    poses: np.ndarray  # (n, 4, 4) float64
    seq: np.ndarray  # (n,) int64
    status: np.ndarray  # (n,) uint8

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    @property
    def end(self) -> int:
        """One past the index of the last pose."""
        return self.first + len(self)

    @classmethod
    def empty(cls, first: int = 0) -> _Poses:
        return cls(
            first, np.zeros(0), np.zeros((0, 4, 4)), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.uint8)
        )

    @classmethod
    def given(cls, first: int, stamps: np.ndarray, poses: np.ndarray) -> _Poses:
        """Poses a caller saved (their sequence numbers and statuses are not known)."""
        n = stamps.shape[0]
        status = np.full(n, _STATUS_OK, dtype=np.uint8)
        if first == 0 and n:
            status[0] = _STATUS_FIRST
        return cls(first, stamps, poses, np.full(n, -1, dtype=np.int64), status)

    @classmethod
    def of_record(cls, r: PoseLogRecord) -> _Poses:
        return cls(
            r.index,
            np.array([r.stamp_s]),
            np.asarray(r.pose, dtype=np.float64).reshape(1, 4, 4),
            np.array([r.seq], dtype=np.int64),
            np.array([_POSE_STATUSES.index(r.status)], dtype=np.uint8),
        )

    def since(self, index: int) -> _Poses:
        """The poses from ``index`` on (all of them if ``index <= first``)."""
        k = min(max(index - self.first, 0), len(self))
        if k == 0:
            return self
        return _Poses(self.first + k, self.stamps[k:], self.poses[k:], self.seq[k:], self.status[k:])

    def until(self, index: int) -> _Poses:
        """The poses before ``index``."""
        k = min(max(index - self.first, 0), len(self))
        return _Poses(self.first, self.stamps[:k], self.poses[:k], self.seq[:k], self.status[:k])

    @classmethod
    def joined(cls, parts: list[_Poses]) -> _Poses | None:
        """``parts`` one after the other, each continuing the previous one (overlaps are skipped);
        ``None`` if one leaves a gap."""
        parts = [p for p in parts if len(p)]
        if not parts:
            return None
        kept = [parts[0]]
        for part in parts[1:]:
            if part.first > kept[-1].end:
                return None
            rest = part.since(kept[-1].end)
            if len(rest):
                kept.append(rest)
        if len(kept) == 1:
            return kept[0]
        return cls(
            kept[0].first,
            np.concatenate([p.stamps for p in kept]),
            np.concatenate([p.poses for p in kept]),
            np.concatenate([p.seq for p in kept]),
            np.concatenate([p.status for p in kept]),
        )

    def to_bytes(self) -> bytes:
        """The poses as pose-log records (:class:`PoseLogRecord`'s layout)."""
        n = len(self)
        table = np.zeros(n, dtype=_LOG_DTYPE)
        table["magic"] = _LOG_MAGIC
        table["index"] = self.first + np.arange(n)
        table["seq"] = self.seq
        table["stamp_ns"] = np.round(self.stamps * 1e9).astype(np.int64)
        table["stamp_s"] = self.stamps
        table["pose"] = self.poses.reshape(n, 16)
        table["status"] = self.status
        body = _LOG_BODY.size
        data = table.tobytes()
        view = memoryview(data)
        size = POSE_LOG_RECORD_SIZE
        table["crc"] = [zlib.crc32(view[o : o + body]) for o in range(0, n * size, size)]
        return table.tobytes()


def _parse_records(data: bytes) -> tuple[_Poses, int]:
    """The whole, intact, consecutive pose-log records at the start of ``data``, and how many
    bytes they take: reading stops at a torn or damaged record (its CRC, magic or status) or at
    one whose index does not follow the previous one's."""
    size = POSE_LOG_RECORD_SIZE
    n = len(data) // size
    if n == 0:
        return _Poses.empty(), 0
    table = np.frombuffer(data, dtype=_LOG_DTYPE, count=n)
    view = memoryview(data)
    body = _LOG_BODY.size
    crc = np.fromiter((zlib.crc32(view[o : o + body]) for o in range(0, n * size, size)), np.uint32, count=n)
    index = table["index"].astype(np.int64)
    good = (crc == table["crc"]) & (table["magic"] == _LOG_MAGIC) & (table["status"] < len(_POSE_STATUSES))
    good &= index == index[0] + np.arange(n)
    k = n if good.all() else int(np.argmin(good))
    if k == 0:
        return _Poses.empty(), 0
    part = _Poses(
        int(index[0]),
        table["stamp_s"][:k].copy(),
        table["pose"][:k].reshape(k, 4, 4).copy(),
        table["seq"][:k].copy(),
        table["status"][:k].copy(),
    )
    return part, k * size


def segment_name(first: int) -> str:
    """The file name of a pose-log segment whose first pose is the trajectory's pose ``first``."""
    return f"poses.{first:010d}.log"


@dataclass
class _Files:
    """What this process knows of one session's trajectory files (kept under the session's lock,
    so that a snapshot neither reads nor rewrites what is already on disk).

    The trajectory on disk is the segments' poses ``[0, segments_end)``, then the commit's own
    poses ``[own_first, commit_n)`` (poses a caller saved that were never logged; the format
    before segments kept the whole trajectory there, from 0), then the active log's
    ``[log_first, log_first + log_count)``; sources may overlap (only with that older format),
    never leave a gap. ``end``: poses ``[0, end)`` are on disk. ``tum_rows``: ``trajectory.tum``
    holds poses ``[0, tum_rows)`` (``None``: not known); ``recent``: poses from ``tum_rows`` on,
    as appended or saved here, for the next append to that view.
    """

    segments_end: int = 0
    commit_n: int = -1  # -1: no commit
    own_first: int = 0
    log_first: int = 0
    log_count: int = 0
    end: int = 0
    tum_rows: int | None = 0
    recent: list[_Poses] = field(default_factory=list)

    def appended(self, part: _Poses) -> None:
        """``part`` (continuing the trajectory) was appended to the active log."""
        if self.log_count == 0:
            self.log_first = part.first
        self.log_count += len(part)
        self.end = part.end
        self.recent.append(part)

    def view_rows(self, start: int, stop: int) -> _Poses | None:
        """Poses ``[start, stop)`` from :attr:`recent`, ``None`` if it does not hold them all."""
        rows = _Poses.joined([p.until(stop) for p in self.recent if p.end > start])
        if rows is None or rows.first > start or rows.end < stop:
            return None
        return rows.since(start)


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
        self._files: dict[tuple[str, str], _Files] = {}  # each session's trajectory files, as known
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
            ``map_name`` is not a valid name (:func:`randt.wire.ids.validate_id`).
        """
        return self._maps / validate_id(map_name, "map")

    def session_dir(self, vehicle: str, session: str) -> Path:
        """``DATA/sessions/<vehicle>/<session>`` (not created).

        Raises
        ------
        ValueError
            ``vehicle`` or ``session`` is not a valid name (:func:`randt.wire.ids.validate_id`).
        """
        return self._sessions / validate_id(vehicle, "vehicle") / validate_id(session, "session")

    # ------------------------------------------------------------------------------ maps

    def save_tiles(
        self, map_name: str, grid: TileGrid, changed_ids: Iterable[str], *, tiles: list[Tile] | None = None
    ) -> list[str]:
        """Persist a map after an update, rewriting only the tiles that changed.

        Uses :meth:`TileGrid.write_tiles <randt.core.tiles.TileGrid.write_tiles>`: sidecar, the changed
        tiles (and any tile whose file is missing), metadata last, each file atomically. An empty
        grid writes nothing.

        Parameters
        ----------
        map_name:
            The map's name (an id, :mod:`randt.wire.ids`).
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

    def save_projection(self, map_name: str, info: dict[str, object]) -> None:
        """Write a map's ``map_projector_info.yaml`` (its geodetic origin, core/geo.py) into its
        folder, atomically and durably (the folder is created if the map has no tile yet): a
        pose answered in the map's frame is only as durable as the origin that defines it."""
        self._check_open()
        directory = make_directory(self.map_dir(map_name))
        fsync_directory(directory.parent)  # (a new map's folder: its name durable too)
        with self._map_lock(map_name):
            write_projector_info(directory, info)

    def load_projection(self, map_name: str) -> dict[str, object] | None:
        """A map's ``map_projector_info.yaml`` (``None``: the map has no geodetic origin).

        Raises
        ------
        FormatError
            The file is there but is not one Autoware's loader would take.
        """
        self._check_open()
        with self._map_lock(map_name):
            return read_projector_info(self.map_dir(map_name))

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
        *,
        first_index: int = 0,
    ) -> SessionRecord:
        """Write a session's snapshot: its matcher state and record (the commit), then the views.

        What a snapshot writes does not grow with the session's length (module docstring,
        Crash safety): poses the store already holds (logged by :meth:`append_pose`, or saved
        before) are not written again, and ``trajectory.tum`` is appended to. Only poses given
        here that the store lacks go into the commit, and an earlier commit's such poses into a
        segment first. A session without scans yet (N = 0) has no ``trajectory.tum``.

        Parameters
        ----------
        meta:
            The session's record; ``n_scans`` is N, the poses this snapshot covers. ``created`` is
            kept from the session's first save (``meta.created`` is used only then); ``updated``
            is set to now.
        poses:
            (N - first_index, 4, 4) ``T_frame_sensor`` of the scans ``first_index .. N - 1``.
        stamps:
            (N - first_index,) their scan times, seconds.
        matcher_state:
            The matcher's state (any name -> numeric array; names must not start with
            ``_store_``), returned as saved by :meth:`load_session`. The service leaves the
            trajectory out of it (:func:`randt.service.matchers.without_trajectory`).
        first_index:
            Index of the first pose given: the store must hold the poses before it already
            (the service gives those since its last snapshot, all of them logged).

        Returns
        -------
        SessionRecord
            The record as written (``meta`` unchanged if the store holds a snapshot of more scans:
            an older snapshot arriving after a newer one is not written).

        Raises
        ------
        ValueError
            Invalid names.
        InvalidCloudError
            ``first_index + len(poses) != meta.n_scans``, poses before ``first_index`` that the
            store does not hold, wrong shapes, non-finite values, or poses that are not
            homogeneous transforms (a ``ValueError`` too).
        FormatError
            An unusable matcher state (reserved or malformed key, object array; a ``ValueError``
            too), damaged trajectory files, or a file could not be written.
        """
        self._check_open()
        key = meta.key
        directory = self.session_dir(*key)
        what = f"session {key[0]}/{key[1]}"
        poses, stamps = _checked_trajectory(poses, stamps, what)
        if first_index < 0 or first_index + poses.shape[0] != meta.n_scans:
            raise InvalidCloudError(
                f"{what}: the record says n_scans={meta.n_scans} but poses {first_index}.."
                f"{first_index + poses.shape[0] - 1} were given"
            )
        arrays = _checked_state(matcher_state)
        with self._session_lock(*key):
            files = self._files_of(*key)
            if meta.n_scans < files.commit_n:
                # An older snapshot arriving after a newer one (a flush racing a close): its
                # matcher state is older than the one on disk.
                logger.warning(
                    "session %s/%s: not saving %d scans over a saved %d", *key, meta.n_scans, files.commit_n
                )
                return meta
            if first_index > files.end:
                raise InvalidCloudError(
                    f"{what}: the store holds poses 0..{files.end - 1}; poses {files.end}.."
                    f"{first_index - 1} were neither logged nor given"
                )
            record = meta.model_copy(update={"created": self._created_time(meta), "updated": _utcnow()})
            new = _Poses.given(first_index, stamps, poses).since(files.end)  # poses the files lack
            try:
                directory.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise FormatError(f"cannot create {directory}: {exc}") from exc
            self._segment_commit_poses(directory, key, files)
            if files.log_count and (len(new) or files.log_count >= SEGMENT_RECORDS):
                self._close_log(directory, files)  # (the commit's own poses follow the segments)
            arrays[_KEY_RECORD] = np.array(record.model_dump_json())
            arrays[_KEY_FIRST] = np.array(new.first if len(new) else record.n_scans, dtype=np.int64)
            arrays[_KEY_STAMPS] = new.stamps
            arrays[_KEY_POSES] = new.poses
            _write_commit(directory / MATCHER_FILENAME, arrays)
            files.commit_n, files.own_first = record.n_scans, int(arrays[_KEY_FIRST])
            if len(new):
                files.end = new.end
                files.recent.append(new)
            self._created[key] = record.created
            try:
                self._extend_view(directory, key, files, record.n_scans)
            except (RandtError, OSError):
                files.tum_rows = None  # rewritten whole by the next snapshot (or load)
                raise
            atomic_write_bytes(directory / SESSION_FILENAME, _record_json(record))
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
        """Restore a session: its last snapshot, and the trajectory as far as it is on disk.

        The trajectory is read from the segments, the commit's own poses and the pose log
        (module docstring); a torn or damaged tail of the log (a crash during an append) is cut
        off. The record is the commit's, brought forward over the poses logged after it
        (``n_scans``, ``n_fallbacks``, ``last_seq``); the matcher state is the commit's.
        ``session.json`` and ``trajectory.tum`` are rewritten when they are missing, unreadable
        or disagree with the commit (a crash between the writes of a snapshot), with a warning.

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
            ``matcher.npz`` is damaged or names another session, a segment is damaged, or poses
            the commit covers are missing.
        """
        self._check_open()
        directory = self.session_dir(vehicle, session)
        what = f"session {vehicle}/{session}"
        with self._session_lock(vehicle, session):
            record, state, own = _read_commit(directory / MATCHER_FILENAME, vehicle, session)
            segments, log = _read_trajectory_files(directory, repair=True)
            trajectory = _assemble(segments, own, log, what)
            if trajectory.end < record.n_scans:
                raise FormatError(
                    f"{what}: its commit covers {record.n_scans} poses, its files hold {trajectory.end}"
                )
            self._repair_views(directory, record, trajectory.until(record.n_scans))
            self._files[(vehicle, session)] = _Files(
                segments_end=segments.end,
                commit_n=record.n_scans,
                own_first=own.first,
                log_first=log.first,
                log_count=len(log),
                end=trajectory.end,
                tum_rows=record.n_scans,
                recent=[trajectory.since(record.n_scans)],
            )
        later = trajectory.since(record.n_scans)
        if len(later):
            record = record.model_copy(
                update={
                    "n_scans": trajectory.end,
                    "n_fallbacks": record.n_fallbacks + int(np.sum(later.status == _STATUS_FALLBACK)),
                    "last_seq": max(record.last_seq, int(later.seq.max())),
                }
            )
        return LoadedSession(record=record, stamps=trajectory.stamps, poses=trajectory.poses, state=state)

    def append_pose(self, vehicle: str, session: str, record: PoseLogRecord) -> None:
        """Append one acknowledged pose to the session's ``poses.log`` and fsync it (module docstring).

        Call it before the pose is published: when it returns, the pose survives a crash.

        Raises
        ------
        ValueError
            Invalid names.
        FormatError
            The record does not continue the stored trajectory (its index is not the number of
            poses on disk), the session's files are damaged, or the record could not be written
            and synced (disk full, read-only...); the file is cut back to its previous length
            where possible, and a torn tail is cut when it is next read.
        """
        self._check_open()
        key = (vehicle, session)
        directory = self.session_dir(vehicle, session)
        path = directory / POSE_LOG_FILENAME
        data = record.to_bytes()
        with self._session_lock(vehicle, session):
            files = self._files_of(vehicle, session)
            if record.index != files.end:
                raise FormatError(
                    f"session {vehicle}/{session}: pose {record.index} does not continue the stored "
                    f"trajectory of {files.end} poses"
                )
            try:  # (a new log's directory entries are synced up to DATA/sessions)
                append_durably(path, data, new_dirs=3)
            except FormatError:
                self._files.pop(key, None)  # read again (and repaired) before the next use
                raise
            files.appended(_Poses.of_record(record))

    def save_resume_sweep(self, vehicle: str, session: str, sweep: ResumeSweep) -> None:
        """Replace the session's ``resume.npz`` (atomically) by ``sweep``, a recent sweep whose
        pose is in the pose log. A snapshot holds the matcher's keyframes as they were when it was
        written, up to ``snapshot_distance_m`` (and a flush) behind the last logged pose; a session
        resumed after a crash adds this sweep to them as its newest keyframe, so its model reaches
        where the vehicle is (service/sessions.py). It is an aid, not the truth: a missing or
        damaged file leaves the snapshot's keyframes alone.

        Raises
        ------
        FormatError
            It could not be written.
        """
        self._check_open()
        directory = self.session_dir(vehicle, session)
        try:
            with self._session_lock(vehicle, session), atomic_open(directory / RESUME_FILENAME, "wb") as fh:
                np.savez(
                    fh,
                    pose_index=np.array(sweep.pose_index, dtype=np.int64),
                    pose=np.asarray(sweep.pose, dtype=np.float64).reshape(4, 4),
                    points=np.asarray(sweep.points, dtype=np.float32).reshape(-1, 3),
                )
        except OSError as exc:
            raise FormatError(f"cannot write {directory / RESUME_FILENAME}: {exc}") from exc

    def load_resume_sweep(self, vehicle: str, session: str) -> ResumeSweep | None:
        """The session's ``resume.npz`` (:meth:`save_resume_sweep`); None when there is none or
        it cannot be read (with a warning)."""
        self._check_open()
        path = self.session_dir(vehicle, session) / RESUME_FILENAME
        try:
            with np.load(path, allow_pickle=False) as z:
                pose, points = np.array(z["pose"], dtype=np.float64), np.array(z["points"])
                sweep = ResumeSweep(int(z["pose_index"]), pose, points)
            if sweep.pose.shape != (4, 4) or sweep.points.ndim != 2 or sweep.points.shape[1] != 3:
                raise ValueError(f"pose {sweep.pose.shape}, points {sweep.points.shape}")
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
            logger.warning("session %s/%s: %s unreadable, not used: %s", vehicle, session, path, exc)
            return None
        return sweep

    def reset_pose_log(self, vehicle: str, session: str) -> None:
        """Remove a session's ``poses.log`` and its segments (a session that starts afresh:
        nothing in them was acknowledged, since a session's first pose is published only after
        its first snapshot, and a session whose snapshot can be read is resumed, not restarted)."""
        self._check_open()
        directory = self.session_dir(vehicle, session)
        with self._session_lock(vehicle, session):
            old = [
                directory / POSE_LOG_FILENAME,
                directory / RESUME_FILENAME,
                *(path for _, path in _segment_files(directory)),
            ]
            old = [path for path in old if path.exists()]
            if old:
                logger.warning(
                    "session %s/%s starts afresh: removing its old %s",
                    vehicle,
                    session,
                    ", ".join(path.name for path in old),
                )
                for path in old:
                    path.unlink()
                fsync_directory(directory)
            self._files[(vehicle, session)] = _Files()
            self._created.pop((vehicle, session), None)

    def _files_of(self, vehicle: str, session: str) -> _Files:
        """What is known of the session's files; read from disk (the log's torn tail cut) when
        this process has not read or written them yet. A commit that cannot be read counts as
        none (a snapshot then replaces it, as before)."""
        files = self._files.get((vehicle, session))
        if files is not None:
            return files
        directory = self.session_dir(vehicle, session)
        what = f"session {vehicle}/{session}"
        commit_n, own = -1, _Poses.empty()
        try:
            record, _, own = _read_commit(directory / MATCHER_FILENAME, vehicle, session)
            commit_n = record.n_scans
        except NotFoundError:
            pass
        except (RandtError, OSError) as exc:
            logger.warning("%s: its commit is unreadable (%s): a snapshot replaces it", what, exc)
        segments, log = _read_trajectory_files(directory, repair=True)
        trajectory = _assemble(segments, own if commit_n >= 0 else None, log, what)
        files = _Files(
            segments_end=segments.end,
            commit_n=commit_n,
            own_first=own.first if commit_n >= 0 else 0,
            log_first=log.first,
            log_count=len(log),
            end=trajectory.end,
            tum_rows=None,  # not compared: the next snapshot writes the view whole
            recent=[trajectory],
        )
        self._files[(vehicle, session)] = files
        return files

    def _segment_commit_poses(self, directory: Path, key: tuple[str, str], files: _Files) -> None:
        """Before a commit is replaced, write its own poses that no segment holds yet into one
        (fsync'd, renamed into place): they stay on disk after the new commit, which does not
        repeat them."""
        if files.commit_n <= max(files.segments_end, files.own_first):
            return
        _, _, own = _read_commit(directory / MATCHER_FILENAME, *key, state=False)
        if own.first > files.segments_end:
            raise FormatError(f"{directory}: poses {files.segments_end}..{own.first - 1} are missing")
        part = own.since(files.segments_end)
        atomic_write_bytes(directory / segment_name(part.first), part.to_bytes())
        files.segments_end = part.end

    def _close_log(self, directory: Path, files: _Files) -> None:
        """Close the active log off into a segment: one rename (and an fsync of the directory).
        Records the segments already hold (only after a commit of the format before segments
        was segmented) are dropped from it first."""
        path = directory / POSE_LOG_FILENAME
        if files.log_first < files.segments_end:
            skip = min(files.segments_end - files.log_first, files.log_count)
            keep = path.read_bytes()[skip * POSE_LOG_RECORD_SIZE : files.log_count * POSE_LOG_RECORD_SIZE]
            files.log_first, files.log_count = files.log_first + skip, files.log_count - skip
            if not keep:
                path.unlink()
                fsync_directory(directory)
                return
            atomic_write_bytes(path, keep)
        if files.log_first != files.segments_end:
            raise FormatError(f"{directory}: poses {files.segments_end}..{files.log_first - 1} are missing")
        try:
            os.replace(path, directory / segment_name(files.log_first))
        except OSError as exc:
            raise FormatError(f"cannot close off {path}: {exc}") from exc
        fsync_directory(directory)
        files.segments_end = files.log_first + files.log_count
        files.log_first, files.log_count = files.segments_end, 0

    def _extend_view(self, directory: Path, key: tuple[str, str], files: _Files, n: int) -> None:
        """Bring ``trajectory.tum`` to the commit's ``n`` poses: append the rows it lacks, or
        write it whole (atomically) when its rows are not known or it does not exist yet."""
        path = directory / TRAJECTORY_FILENAME
        if n == 0:
            _write_trajectory(path, np.zeros(0), np.zeros((0, 4, 4)))
        elif files.tum_rows is not None and 0 < files.tum_rows <= n and path.exists():
            rows = files.view_rows(files.tum_rows, n)
            if rows is None:
                files.tum_rows = None
                self._extend_view(directory, key, files, n)
                return
            if len(rows):
                try:
                    with path.open("a", encoding="utf-8", newline="\n") as fh:
                        fh.write(_tum_rows(rows.stamps, rows.poses))
                except OSError as exc:
                    raise FormatError(f"cannot append to {path}: {exc}") from exc
        else:
            rows = files.view_rows(0, n)
            if rows is None:  # not in memory: read the trajectory (once)
                segments, log = _read_trajectory_files(directory, repair=False)
                _, _, own = _read_commit(directory / MATCHER_FILENAME, *key, state=False)
                rows = _assemble(segments, own, log, f"session {key[0]}/{key[1]}").until(n)
            _write_trajectory(path, rows.stamps, rows.poses)
        files.tum_rows = n
        files.recent = [p.since(n) for p in files.recent if p.end > n]

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
        (:func:`randt.wire.ids.legacy_session_map_name`) moves to :func:`randt.wire.ids.session_map_name`:

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

    def _repair_views(self, directory: Path, record: SessionRecord, trajectory: _Poses) -> None:
        """Rewrite ``session.json`` / ``trajectory.tum`` where they disagree with the commit
        (``record``, and ``trajectory``: the poses it covers)."""
        name = f"{record.vehicle}/{record.session}"
        json_path = directory / SESSION_FILENAME
        try:
            current: SessionRecord | None = SessionRecord.model_validate_json(json_path.read_bytes())
        except (OSError, ValueError) as exc:
            logger.warning("session %s: %s unreadable (%s)", name, SESSION_FILENAME, exc)
            current = None
        if current != record:
            logger.warning("session %s: rewriting %s from %s", name, SESSION_FILENAME, MATCHER_FILENAME)
            atomic_write_bytes(json_path, _record_json(record))

        tum_path = directory / TRAJECTORY_FILENAME
        if len(trajectory) == 0:
            agrees = not tum_path.exists()
        else:
            try:
                stamps, poses = read_tum(tum_path)
                agrees = (
                    stamps.shape == trajectory.stamps.shape
                    and np.allclose(stamps, trajectory.stamps, rtol=0.0, atol=_VIEW_TOLERANCE)
                    and np.allclose(poses, trajectory.poses, rtol=0.0, atol=_VIEW_TOLERANCE)
                )
            except RandtError as exc:
                logger.warning("session %s: %s unreadable (%s)", name, TRAJECTORY_FILENAME, exc)
                agrees = False
        if not agrees:
            logger.warning("session %s: rewriting %s from the stored trajectory", name, TRAJECTORY_FILENAME)
            _write_trajectory(tum_path, trajectory.stamps, trajectory.poses)


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


def _read_commit(
    path: Path, vehicle: str, session: str, *, state: bool = True
) -> tuple[SessionRecord, dict[str, np.ndarray], _Poses]:
    """``matcher.npz``, checked: its record, the matcher state (unless ``state`` is false: then
    ``{}``, and the state's arrays are not read) and the commit's own poses."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {key: npz[key] for key in npz.files if state or key.startswith(_RESERVED_PREFIX)}
    except FileNotFoundError as exc:
        raise NotFoundError(f"session {vehicle}/{session} does not exist") from exc
    except _NPZ_ERRORS as exc:
        raise FormatError(f"{path}: cannot read the session's commit: {exc}") from exc
    missing = [k for k in (_KEY_RECORD, _KEY_STAMPS, _KEY_POSES) if k not in arrays]
    if missing:
        raise FormatError(f"{path}: not a session commit (missing {', '.join(missing)})")
    record = _parse_record(str(arrays.pop(_KEY_RECORD)[()]), path, vehicle, session)
    first_array = arrays.pop(_KEY_FIRST, None)
    try:
        first = 0 if first_array is None else int(first_array)
        poses, stamps = _checked_trajectory(arrays.pop(_KEY_POSES), arrays.pop(_KEY_STAMPS), str(path))
    except (InvalidCloudError, ValueError, TypeError) as exc:
        raise FormatError(f"{path}: invalid trajectory: {exc}") from exc
    if first < 0 or first + poses.shape[0] != record.n_scans:
        raise FormatError(
            f"{path}: record says {record.n_scans} scans, its trajectory has poses {first}.."
            f"{first + poses.shape[0] - 1}"
        )
    matcher_state = {k: v for k, v in arrays.items() if not k.startswith(_RESERVED_PREFIX)}
    return record, matcher_state, _Poses.given(first, stamps, poses)


def _write_commit(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """``matcher.npz``, atomically (written straight into the temporary file)."""
    try:
        with atomic_open(path, "wb") as fh:
            np.savez(fh, **arrays)  # type: ignore[arg-type]  # mypy binds **arrays to allow_pickle: bool too
    except OSError as exc:
        raise FormatError(f"cannot write {path}: {exc}") from exc


def _segment_files(directory: Path) -> list[tuple[int, Path]]:
    """The session's pose-log segments, ``(first pose, path)``, in trajectory order."""
    try:
        names = os.listdir(directory)
    except FileNotFoundError:
        return []
    except OSError as exc:
        raise FormatError(f"cannot list {directory}: {exc}") from exc
    found = [(m, name) for name in names if (m := _SEGMENT_RE.fullmatch(name))]
    return sorted((int(m.group(1)), directory / name) for m, name in found)


def _read_trajectory_files(directory: Path, *, repair: bool) -> tuple[_Poses, _Poses]:
    """The poses of the session's segments (one after the other from pose 0, each whole) and
    of its active log (whole records up to the first torn or damaged one; with ``repair`` what
    follows them is cut off the file, so the next append continues a clean log).

    Raises
    ------
    FormatError
        A segment is damaged or does not continue the previous one.
    """
    parts: list[_Poses] = []
    end = 0
    for first, path in _segment_files(directory):
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise FormatError(f"cannot read {path}: {exc}") from exc
        part, good = _parse_records(data)
        if good != len(data) or len(part) == 0 or part.first != first:
            raise FormatError(
                f"{path}: damaged pose-log segment ({good // POSE_LOG_RECORD_SIZE} intact records "
                f"of {len(data) / POSE_LOG_RECORD_SIZE:g})"
            )
        if first != end:
            raise FormatError(f"{path}: starts at pose {first}, but the segments before it end at {end}")
        parts.append(part)
        end = part.end
    segments = _Poses.joined(parts) or _Poses.empty()
    return segments, _read_log(directory / POSE_LOG_FILENAME, repair=repair)


def _read_log(path: Path, *, repair: bool) -> _Poses:
    """The whole records of a ``poses.log`` up to the first torn or damaged one (none if no file).

    With ``repair``, what follows them (a torn tail: a crash during an append) is cut off the
    file, so the next append continues a clean log.
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return _Poses.empty()
    except OSError as exc:
        raise FormatError(f"cannot read {path}: {exc}") from exc
    log, good = _parse_records(data)
    if good != len(data):
        logger.warning(
            "%s: cutting %d bytes after %d whole records (a torn or damaged tail)",
            path,
            len(data) - good,
            len(log),
        )
        if repair:
            try:
                with open(path, "r+b") as fh:
                    fh.truncate(good)
                    fh.flush()
                    os.fsync(fh.fileno())
            except OSError as exc:
                raise FormatError(f"cannot cut the torn tail of {path}: {exc}") from exc
    return log


def _assemble(segments: _Poses, own: _Poses | None, log: _Poses, what: str) -> _Poses:
    """The trajectory from pose 0: the segments, then the commit's own poses, then the log (each
    may repeat poses of the ones before it, which are the same; none may leave a gap).

    Raises
    ------
    FormatError
        Poses are missing between them.
    """
    end, kept = 0, []
    for name, part in (("segments", segments), ("commit", own), (POSE_LOG_FILENAME, log)):
        if part is None or not len(part):
            continue
        if part.first > end:
            raise FormatError(
                f"{what}: poses {end}..{part.first - 1} are missing ({name} from pose {part.first})"
            )
        kept.append(part)
        end = max(end, part.end)
    return _Poses.joined(kept) or _Poses.empty()


def _tum_rows(stamps: np.ndarray, poses: np.ndarray) -> str:
    """Rows of a TUM trajectory as :func:`randt.core.io.write_tum` writes them (``%.9f`` stamps, 17
    significant digits, canonical quaternions), to append to one."""
    quats = Rotation.from_matrix(poses[:, :3, :3]).as_quat(canonical=True)  # (x, y, z, w)
    buffer = io.StringIO()
    np.savetxt(buffer, np.column_stack([stamps, poses[:, :3, 3], quats]), fmt=["%.9f"] + ["%.17g"] * 7)
    return buffer.getvalue()


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
