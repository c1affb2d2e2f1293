"""The sessions of the store: ``DATA/sessions/<vehicle>/<session>/``.

:class:`SessionStore` writes a session's snapshots (the commit, then its views), appends its
acknowledged poses to the pose log, closes the log off into segments, and loads a session back
from its last snapshot and the poses logged after it. What it knows of each session's files is
kept per session (``_Files``), under the session's lock, so that a snapshot neither reads nor
rewrites what is already on disk. The files' formats are :mod:`randt.service.pose_log`'s and
:mod:`randt.service.session_files`'; the order of the writes, and why, is
:mod:`randt.service.store`'s module docstring (A session's trajectory, Crash safety).
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from randt.core.errors import FormatError, InvalidCloudError, NotFoundError, RandtError
from randt.core.io import atomic_write_bytes
from randt.core.io.atomic import append_durably, fsync_directory
from randt.service.pose_log import (
    POSE_LOG_FILENAME,
    POSE_LOG_RECORD_SIZE,
    STATUS_FALLBACK,
    PoseLogRecord,
    Poses,
    assemble,
    read_trajectory_files,
    segment_files,
    segment_name,
)
from randt.service.session_files import (
    KEY_FIRST,
    KEY_POSES,
    KEY_RECORD,
    KEY_STAMPS,
    MATCHER_FILENAME,
    RESUME_FILENAME,
    SESSION_FILENAME,
    TRAJECTORY_FILENAME,
    checked_state,
    checked_trajectory,
    read_commit,
    read_record,
    read_resume_sweep,
    record_json,
    repair_views,
    tum_rows,
    write_commit,
    write_resume_sweep,
    write_trajectory,
)
from randt.service.session_record import LoadedSession, ResumeSweep, SessionRecord, utcnow
from randt.service.store_files import StoreProblem, report_problem
from randt.wire.ids import validate_id

__all__ = ["SEGMENT_RECORDS", "SESSIONS_DIRNAME", "SessionStore", "scan_sessions"]

logger = logging.getLogger(__name__)

SESSIONS_DIRNAME = "sessions"
#: A snapshot closes the pose log off into a segment once it holds this many records (5 min at
#: 10 Hz, 516 kB): few files per session, and a torn-tail repair never touches more than that.
SEGMENT_RECORDS = 3000


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
    recent: list[Poses] = field(default_factory=list)

    def appended(self, part: Poses) -> None:
        """``part`` (continuing the trajectory) was appended to the active log."""
        if self.log_count == 0:
            self.log_first = part.first
        self.log_count += len(part)
        self.end = part.end
        self.recent.append(part)

    def view_rows(self, start: int, stop: int) -> Poses | None:
        """Poses ``[start, stop)`` from :attr:`recent`, ``None`` if it does not hold them all."""
        rows = Poses.joined([p.until(stop) for p in self.recent if p.end > start])
        if rows is None or rows.first > start or rows.end < stop:
            return None
        return rows.since(start)


class SessionStore:
    """The sessions under ``sessions``: snapshots, the pose log, resume sweeps.

    ``check_open`` raises when the store that owns the directory is closed; every read and write
    calls it first. Writes to one session are serialized by the session's (re-entrant) lock.
    """

    def __init__(self, sessions: Path, check_open: Callable[[], None]) -> None:
        self._sessions = sessions
        self._check_open = check_open
        self._guard = threading.Lock()
        self._session_locks: dict[tuple[str, str], threading.RLock] = {}
        self._created: dict[tuple[str, str], datetime] = {}
        self._files: dict[tuple[str, str], _Files] = {}  # each session's trajectory files, as known

    def session_lock(self, vehicle: str, session: str) -> threading.RLock:
        """The lock that serializes writes to the session (re-entrant)."""
        with self._guard:
            return self._session_locks.setdefault((vehicle, session), threading.RLock())

    def session_dir(self, vehicle: str, session: str) -> Path:
        """``DATA/sessions/<vehicle>/<session>`` (not created).

        Raises
        ------
        ValueError
            ``vehicle`` or ``session`` is not a valid name (:func:`randt.wire.ids.validate_id`).
        """
        return self._sessions / validate_id(vehicle, "vehicle") / validate_id(session, "session")

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

        What a snapshot writes does not grow with the session's length (:mod:`randt.service.store`,
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
        poses, stamps = checked_trajectory(poses, stamps, what)
        if first_index < 0 or first_index + poses.shape[0] != meta.n_scans:
            raise InvalidCloudError(
                f"{what}: the record says n_scans={meta.n_scans} but poses {first_index}.."
                f"{first_index + poses.shape[0] - 1} were given"
            )
        arrays = checked_state(matcher_state)
        with self.session_lock(*key):
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
            record = meta.model_copy(update={"created": self._created_time(meta), "updated": utcnow()})
            new = Poses.given(first_index, stamps, poses).since(files.end)  # poses the files lack
            try:
                directory.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise FormatError(f"cannot create {directory}: {exc}") from exc
            _segment_commit_poses(directory, key, files)
            if files.log_count and (len(new) or files.log_count >= SEGMENT_RECORDS):
                _close_log(directory, files)  # (the commit's own poses follow the segments)
            arrays[KEY_RECORD] = np.array(record.model_dump_json())
            arrays[KEY_FIRST] = np.array(new.first if len(new) else record.n_scans, dtype=np.int64)
            arrays[KEY_STAMPS] = new.stamps
            arrays[KEY_POSES] = new.poses
            write_commit(directory / MATCHER_FILENAME, arrays)
            files.commit_n, files.own_first = record.n_scans, int(arrays[KEY_FIRST])
            if len(new):
                files.end = new.end
                files.recent.append(new)
            self._created[key] = record.created
            try:
                self._extend_view(directory, key, files, record.n_scans)
            except (RandtError, OSError):
                files.tum_rows = None  # rewritten whole by the next snapshot (or load)
                raise
            atomic_write_bytes(directory / SESSION_FILENAME, record_json(record))
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
            return read_record(self.session_dir(*meta.key) / MATCHER_FILENAME, *meta.key).created
        except NotFoundError:
            return meta.created
        except (RandtError, OSError) as exc:
            logger.warning("session %s/%s: overwriting an unreadable commit (%s)", *meta.key, exc)
            return meta.created

    def load_session(self, vehicle: str, session: str) -> LoadedSession:
        """Restore a session: its last snapshot, and the trajectory as far as it is on disk.

        The trajectory is read from the segments, the commit's own poses and the pose log
        (:mod:`randt.service.store`); a torn or damaged tail of the log (a crash during an append) is cut
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
        with self.session_lock(vehicle, session):
            record, state, own = read_commit(directory / MATCHER_FILENAME, vehicle, session)
            segments, log = read_trajectory_files(directory, repair=True)
            trajectory = assemble(segments, own, log, what)
            if trajectory.end < record.n_scans:
                raise FormatError(
                    f"{what}: its commit covers {record.n_scans} poses, its files hold {trajectory.end}"
                )
            repair_views(directory, record, trajectory.until(record.n_scans))
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
                    "n_fallbacks": record.n_fallbacks + int(np.sum(later.status == STATUS_FALLBACK)),
                    "last_seq": max(record.last_seq, int(later.seq.max())),
                }
            )
        return LoadedSession(record=record, stamps=trajectory.stamps, poses=trajectory.poses, state=state)

    def append_pose(self, vehicle: str, session: str, record: PoseLogRecord) -> None:
        """Append one acknowledged pose to the session's ``poses.log`` and fsync it
        (:mod:`randt.service.store`).

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
        with self.session_lock(vehicle, session):
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
            files.appended(Poses.of_record(record))

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
        with self.session_lock(vehicle, session):
            write_resume_sweep(directory, sweep)

    def load_resume_sweep(self, vehicle: str, session: str) -> ResumeSweep | None:
        """The session's ``resume.npz`` (:meth:`save_resume_sweep`); None when there is none or
        it cannot be read (with a warning)."""
        self._check_open()
        path = self.session_dir(vehicle, session) / RESUME_FILENAME
        return read_resume_sweep(path, vehicle, session)

    def reset_pose_log(self, vehicle: str, session: str) -> None:
        """Remove a session's ``poses.log`` and its segments (a session that starts afresh:
        nothing in them was acknowledged, since a session's first pose is published only after
        its first snapshot, and a session whose snapshot can be read is resumed, not restarted)."""
        self._check_open()
        directory = self.session_dir(vehicle, session)
        with self.session_lock(vehicle, session):
            old = [
                directory / POSE_LOG_FILENAME,
                directory / RESUME_FILENAME,
                *(path for _, path in segment_files(directory)),
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
        commit_n, own = -1, Poses.empty()
        try:
            record, _, own = read_commit(directory / MATCHER_FILENAME, vehicle, session)
            commit_n = record.n_scans
        except NotFoundError:
            pass
        except (RandtError, OSError) as exc:
            logger.warning("%s: its commit is unreadable (%s): a snapshot replaces it", what, exc)
        segments, log = read_trajectory_files(directory, repair=True)
        trajectory = assemble(segments, own if commit_n >= 0 else None, log, what)
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

    def _extend_view(self, directory: Path, key: tuple[str, str], files: _Files, n: int) -> None:
        """Bring ``trajectory.tum`` to the commit's ``n`` poses: append the rows it lacks, or
        write it whole (atomically) when its rows are not known or it does not exist yet."""
        path = directory / TRAJECTORY_FILENAME
        if n == 0:
            write_trajectory(path, np.zeros(0), np.zeros((0, 4, 4)))
        elif files.tum_rows is not None and 0 < files.tum_rows <= n and path.exists():
            rows = files.view_rows(files.tum_rows, n)
            if rows is None:
                files.tum_rows = None
                self._extend_view(directory, key, files, n)
                return
            if len(rows):
                try:
                    with path.open("a", encoding="utf-8", newline="\n") as fh:
                        fh.write(tum_rows(rows.stamps, rows.poses))
                except OSError as exc:
                    raise FormatError(f"cannot append to {path}: {exc}") from exc
        else:
            rows = files.view_rows(0, n)
            if rows is None:  # not in memory: read the trajectory (once)
                segments, log = read_trajectory_files(directory, repair=False)
                _, _, own = read_commit(directory / MATCHER_FILENAME, *key, state=False)
                rows = assemble(segments, own, log, f"session {key[0]}/{key[1]}").until(n)
            write_trajectory(path, rows.stamps, rows.poses)
        files.tum_rows = n
        files.recent = [p.since(n) for p in files.recent if p.end > n]


def _segment_commit_poses(directory: Path, key: tuple[str, str], files: _Files) -> None:
    """Before a commit is replaced, write its own poses that no segment holds yet into one
    (fsync'd, renamed into place): they stay on disk after the new commit, which does not
    repeat them."""
    if files.commit_n <= max(files.segments_end, files.own_first):
        return
    _, _, own = read_commit(directory / MATCHER_FILENAME, *key, state=False)
    if own.first > files.segments_end:
        raise FormatError(f"{directory}: poses {files.segments_end}..{own.first - 1} are missing")
    part = own.since(files.segments_end)
    atomic_write_bytes(directory / segment_name(part.first), part.to_bytes())
    files.segments_end = part.end


def _close_log(directory: Path, files: _Files) -> None:
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


def scan_sessions(root: Path, sessions: Path) -> tuple[list[SessionRecord], list[StoreProblem]]:
    """The records of the sessions under ``sessions`` (read from each commit), sorted by
    ``(vehicle, session)``, and what could not be read (paths of entries relative to the data
    directory ``root``)."""
    records: list[SessionRecord] = []
    problems: list[StoreProblem] = []
    for vehicle_dir in sorted(sessions.iterdir()):
        if not _valid_entry(root, vehicle_dir, "vehicle", problems):
            continue
        for session_dir in sorted(vehicle_dir.iterdir()):
            if not _valid_entry(root, session_dir, "session", problems):
                continue
            name = f"{vehicle_dir.name}/{session_dir.name}"
            commit = session_dir / MATCHER_FILENAME
            if not commit.is_file():
                if (session_dir / SESSION_FILENAME).exists():
                    report_problem(problems, "session", name, commit, f"{MATCHER_FILENAME} is missing")
                else:  # an empty directory: the first save never completed
                    logger.debug("ignoring %s: no save completed", session_dir)
                continue
            try:
                records.append(read_record(commit, vehicle_dir.name, session_dir.name))
            except (RandtError, OSError) as exc:
                report_problem(problems, "session", name, commit, str(exc))
    return records, problems


def _valid_entry(root: Path, path: Path, what: str, problems: list[StoreProblem]) -> bool:
    rel = str(path.relative_to(root))
    if not path.is_dir() or path.is_symlink():
        report_problem(problems, "entry", rel, path, f"not a {what} directory")
        return False
    try:
        validate_id(path.name, what)
    except ValueError as exc:
        report_problem(problems, "entry", rel, path, str(exc))
        return False
    return True
