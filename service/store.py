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

The parts
---------
:class:`Store` owns the data directory: its lock (:mod:`randt.service.data_dir_lock`) and the
clean-up on opening (:mod:`randt.service.store_files`). Maps go to
:class:`~randt.service.tile_store.TileStore`, sessions to
:class:`~randt.service.session_store.SessionStore` (their files' formats:
:mod:`randt.service.pose_log`, :mod:`randt.service.session_files`; the record:
:mod:`randt.service.session_record`); :meth:`Store.load_all` spans both, and moves legacy
session-map names first (:mod:`randt.service.legacy_map_names`). The counters' totals have a
file of their own (:mod:`randt.service.counter_totals`). All their names are importable from here.
"""

from __future__ import annotations

import logging
import os
import weakref
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Self

import numpy as np

from randt.core.errors import FormatError, RandtError
from randt.core.tiles import Tile, TileGrid
from randt.service.counter_totals import COUNTERS_FILENAME, CounterTotals, load_counters, save_counters
from randt.service.data_dir_lock import (
    LOCK_FILENAME,
    DataDirInUseError,
    acquire_lock,
    check_data_dir_free,
    release_lock,
)
from randt.service.legacy_map_names import migrate_map_names
from randt.service.pose_log import (
    POSE_LOG_FILENAME,
    POSE_LOG_RECORD_SIZE,
    PoseLogRecord,
    PoseStatus,
    segment_name,
)
from randt.service.session_files import (
    MATCHER_FILENAME,
    RESUME_FILENAME,
    SESSION_FILENAME,
    TRAJECTORY_FILENAME,
)
from randt.service.session_record import (
    LoadedSession,
    ResumeSweep,
    SessionFrame,
    SessionRecord,
    SessionState,
)
from randt.service.session_store import SEGMENT_RECORDS, SESSIONS_DIRNAME, SessionStore, scan_sessions
from randt.service.store_files import OpenCheck, ProblemKind, StoreProblem, remove_temp_files, report_problem
from randt.service.tile_store import MAPS_DIRNAME, VERSIONS_DIRNAME, TileStore

__all__ = [
    "COUNTERS_FILENAME",
    "LOCK_FILENAME",
    "MAPS_DIRNAME",
    "MATCHER_FILENAME",
    "POSE_LOG_FILENAME",
    "POSE_LOG_RECORD_SIZE",
    "RESUME_FILENAME",
    "SEGMENT_RECORDS",
    "SESSIONS_DIRNAME",
    "SESSION_FILENAME",
    "TRAJECTORY_FILENAME",
    "VERSIONS_DIRNAME",
    "CounterTotals",
    "DataDirInUseError",
    "LoadedSession",
    "PoseLogRecord",
    "PoseStatus",
    "ProblemKind",
    "ResumeSweep",
    "SessionFrame",
    "SessionRecord",
    "SessionState",
    "Store",
    "StoreContents",
    "StoreProblem",
    "check_data_dir_free",
    "load_counters",
    "save_counters",
    "segment_name",
]

logger = logging.getLogger(__name__)


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


class Store:
    """The durable store of maps and sessions under ``data_dir`` (see the module docstring).

    Opening creates ``maps/`` and ``sessions/``, takes the directory's lock and removes temporary
    files left by interrupted atomic writes (their number is logged and kept in
    :attr:`removed_temp_files`). Close the store (or use it as a context manager) to release the
    lock. Stores of one process share the lock (say, a service restarted in-process before the
    old store was closed); only the first of them removes temporary files, since the others
    might delete a live writer's. Use one open Store per directory and process at a time.

    Maps are :class:`~randt.service.tile_store.TileStore`'s, sessions
    :class:`~randt.service.session_store.SessionStore`'s: the methods below hand each call to
    the part that holds it (their docstrings say more), except those that span both.

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
        lock_key, first = acquire_lock(self._root)
        self._finalizer = weakref.finalize(self, release_lock, lock_key)
        self._check_open = OpenCheck(self._finalizer, self._root)
        self._versions = self._root / VERSIONS_DIRNAME
        self._tiles = TileStore(self._maps, self._versions, self._check_open)
        self._session_store = SessionStore(self._sessions, self._check_open)
        self._problems: list[StoreProblem] = []
        if first:
            trees = (self._maps, self._sessions, self._versions)
            self.removed_temp_files = removed = remove_temp_files(self._root, self._maps, trees)
            if removed:
                logger.warning(
                    "removed %d temporary files left by interrupted writes in %s", removed, self._root
                )
            else:
                logger.info("no temporary files left by interrupted writes in %s", self._root)
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

    # ------------------------------------------------------------------------------ paths

    def map_dir(self, map_name: str) -> Path:
        """``DATA/maps/<map_name>`` (not created; :meth:`TileStore.map_dir`)."""
        return self._tiles.map_dir(map_name)

    def session_dir(self, vehicle: str, session: str) -> Path:
        """``DATA/sessions/<vehicle>/<session>`` (not created; :meth:`SessionStore.session_dir`)."""
        return self._session_store.session_dir(vehicle, session)

    # ------------------------------------------------------------------------------ maps

    def save_tiles(
        self, map_name: str, grid: TileGrid, changed_ids: Iterable[str], *, tiles: list[Tile] | None = None
    ) -> list[str]:
        """Persist a map after an update, rewriting only the tiles that changed
        (:meth:`TileStore.save_tiles`)."""
        return self._tiles.save_tiles(map_name, grid, changed_ids, tiles=tiles)

    def load_map(self, map_name: str) -> TileGrid | None:
        """A map saved by :meth:`save_tiles`, or ``None`` (:meth:`TileStore.load_map`)."""
        return self._tiles.load_map(map_name)

    def save_projection(self, map_name: str, info: dict[str, object]) -> None:
        """Write a map's ``map_projector_info.yaml`` (:meth:`TileStore.save_projection`)."""
        self._tiles.save_projection(map_name, info)

    def load_projection(self, map_name: str) -> dict[str, object] | None:
        """A map's ``map_projector_info.yaml`` (:meth:`TileStore.load_projection`)."""
        return self._tiles.load_projection(map_name)

    def version_floor(self, map_name: str) -> int:
        """The highest tile version a deleted map of this name reached (:meth:`TileStore.version_floor`)."""
        return self._tiles.version_floor(map_name)

    def delete_map(self, map_name: str, *, version_floor: int = 0) -> bool:
        """Remove a saved map, recording its version floor first (:meth:`TileStore.delete_map`)."""
        return self._tiles.delete_map(map_name, version_floor=version_floor)

    def list_maps(self) -> list[str]:
        """Names of the saved maps, sorted (:meth:`TileStore.list_maps`)."""
        return self._tiles.list_maps()

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
        """Write a session's snapshot: the commit, then the views (:meth:`SessionStore.save_session`)."""
        return self._session_store.save_session(meta, poses, stamps, matcher_state, first_index=first_index)

    def load_session(self, vehicle: str, session: str) -> LoadedSession:
        """A session's last snapshot and its trajectory as far as it is on disk
        (:meth:`SessionStore.load_session`)."""
        return self._session_store.load_session(vehicle, session)

    def append_pose(self, vehicle: str, session: str, record: PoseLogRecord) -> None:
        """Append one acknowledged pose to the session's ``poses.log`` and fsync it, before it is
        published (:meth:`SessionStore.append_pose`)."""
        self._session_store.append_pose(vehicle, session, record)

    def save_resume_sweep(self, vehicle: str, session: str, sweep: ResumeSweep) -> None:
        """Replace the session's ``resume.npz`` (:meth:`SessionStore.save_resume_sweep`)."""
        self._session_store.save_resume_sweep(vehicle, session, sweep)

    def load_resume_sweep(self, vehicle: str, session: str) -> ResumeSweep | None:
        """The session's ``resume.npz``, or None (:meth:`SessionStore.load_resume_sweep`)."""
        return self._session_store.load_resume_sweep(vehicle, session)

    def reset_pose_log(self, vehicle: str, session: str) -> None:
        """Remove a session's pose log and segments: it starts afresh
        (:meth:`SessionStore.reset_pose_log`)."""
        self._session_store.reset_pose_log(vehicle, session)

    def list_sessions(self) -> list[SessionRecord]:
        """The records of every saved session, sorted by ``(vehicle, session)``.

        Records are read from each session's commit (``matcher.npz``). A session that cannot be
        read is skipped with a logged error and reported in :attr:`problems`.
        """
        self._check_open()
        records, problems = scan_sessions(self._root, self._sessions)
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
        with self._session_store.session_lock(vehicle, session):  # re-entrant: no save slips in between
            record, stamps, poses, arrays = self.load_session(vehicle, session)
            saved = self.save_session(record.model_copy(update={"state": state}), poses, stamps, arrays)
        logger.info("session %s/%s is now %s", vehicle, session, state)
        return saved

    # ------------------------------------------------------------------------------ everything

    def migrate_map_names(self) -> list[tuple[str, str, str]]:
        """Rename the maps of sessions without priors to their injective names (run by :meth:`load_all`;
        :func:`randt.service.legacy_map_names.migrate_map_names`).

        Returns
        -------
        list[tuple[str, str, str]]
            ``("<vehicle>/<session>", old map, new map)`` for each session moved.
        """
        self._check_open()
        records, _ = scan_sessions(self._root, self._sessions)
        return migrate_map_names(self._tiles, self._session_store, records)

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
                report_problem(contents.problems, "map", name, self.map_dir(name), str(exc))
                continue
            if grid is not None:
                contents.maps[name] = grid
        records, problems = scan_sessions(self._root, self._sessions)
        contents.problems.extend(problems)
        for record in records:
            key = (record.vehicle, record.session)
            try:
                contents.sessions[key] = self.load_session(*key)
            except (RandtError, OSError) as exc:
                path = self.session_dir(*key)
                report_problem(contents.problems, "session", f"{key[0]}/{key[1]}", path, str(exc))
        self._problems = list(contents.problems)
        logger.info(
            "restored %d maps and %d sessions from %s (%d skipped)",
            len(contents.maps),
            len(contents.sessions),
            self._root,
            len(contents.problems),
        )
        return contents
