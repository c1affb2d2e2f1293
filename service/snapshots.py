"""Saving running sessions: their snapshots (when one is due) and their resume sweeps, and the
records the store holds of every session.

A session's truth is its pose log plus its last snapshot; snapshots are rare and their cost does
not grow with the session (``docs/architecture.md``, "The store").
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from randt.core.errors import RandtError
from randt.service.matchers import MatcherProcessDiedError
from randt.service.metrics import ServiceMetrics
from randt.service.settings import ServiceSettings
from randt.service.store import ResumeSweep, SessionRecord, Store
from randt.service.store import SessionState as RecordState

if TYPE_CHECKING:
    from randt.service.worker import SessionWorker

__all__ = ["RESUME_SWEEP_M", "SessionSaver"]

log = logging.getLogger(__name__)

#: A session's resume sweep is saved again once its vehicle is this far (m) from where the saved
#: one was taken: a vehicle that stands still does not rewrite it.
RESUME_SWEEP_M = 2.0


class SessionSaver:
    """Writes sessions' snapshots and resume sweeps to the store and keeps the stored records."""

    def __init__(
        self,
        store: Store,
        settings: ServiceSettings,
        metrics: ServiceMetrics,
        records: dict[tuple[str, str], SessionRecord],
    ) -> None:
        self.store, self.settings, self.metrics = store, settings, metrics
        self._lock = threading.Lock()
        self._records = dict(records)

    def records(self) -> dict[tuple[str, str], SessionRecord]:
        """The stored record of every session known to the store (a copy; running ones as last saved)."""
        with self._lock:
            return dict(self._records)

    def record(self, key: tuple[str, str]) -> SessionRecord | None:
        with self._lock:
            return self._records.get(key)

    def set_record(self, key: tuple[str, str], record: SessionRecord) -> None:
        with self._lock:
            self._records[key] = record

    def due(self, w: SessionWorker, now: float) -> bool:
        """Whether a running session's snapshot is due: it changed, and its last one is
        ``snapshot_interval_s`` old or ``snapshot_distance_m`` away."""
        info = w.info
        if not info.dirty:
            return False
        if now - info.snapshot_at >= self.settings.snapshot_interval_s:
            return True
        reach, poses = self.settings.snapshot_distance_m, w.matcher.poses
        if reach <= 0 or info.snapshot_xyz is None or not poses:
            return False
        return bool(np.linalg.norm(poses[-1][:3, 3] - info.snapshot_xyz) >= reach)

    def save(self, w: SessionWorker, state: RecordState | None = None) -> bool:
        """Write a session's snapshot; whether the store now holds it (False: not saved).

        The matcher state comes without the trajectory, and only the poses since the last snapshot
        are handed to the store (which has them in its log already and appends them to
        ``trajectory.tum``)."""
        with w.lock:
            info = w.info
            if state is not None:
                info.state = state
            record = SessionRecord(
                vehicle=info.vehicle,
                session=info.session,
                map=info.map_name,
                state=info.state,
                last_seq=info.last_seq,
                n_scans=info.n_scans,
                n_fallbacks=info.n_fallbacks,
                frame=info.frame,
                localize_only=info.localize_only,
            )
            if w.broken:
                return False  # its matcher died, or its log failed: the store keeps the truth
            trajectory = w.matcher.poses
            n = len(trajectory)
            first = min(info.saved_scans, n)
            poses = np.array(trajectory[first:n]).reshape(-1, 4, 4)
            stamps = np.array(info.stamps_s[first:n], dtype=float)
            position = np.array(trajectory[-1][:3, 3]) if n else None
            try:
                matcher_state = w.matcher.snapshot_state()
            except MatcherProcessDiedError as exc:
                log.error("session %s/%s: %s; not saved", *w.key, exc)
                w.broken = True
                return False
            info.dirty = False
        try:
            self.store.save_session(record, poses, stamps, matcher_state, first_index=first)
            self.set_record(w.key, record)
            info.saved_scans = max(info.saved_scans, n)
            info.snapshot_at, info.snapshot_xyz = time.monotonic(), position
        except (OSError, ValueError, RandtError):
            self.metrics.store_errors.inc()
            log.exception("saving session %s/%s failed", *w.key)
            info.dirty = True
            return False
        return True

    def save_resume_sweeps(self, running: list[SessionWorker]) -> None:
        """Each running session's newest resume sweep (SessionWorker.resume_sweep), when its
        vehicle moved :data:`RESUME_SWEEP_M` since the saved one (Store.save_resume_sweep)."""
        for w in running:
            sweep, saved = w.resume_sweep, w.resume_saved_xyz
            if sweep is None or w.broken:
                continue
            if saved is not None and np.linalg.norm(sweep.pose[:3, 3] - saved) < RESUME_SWEEP_M:
                continue
            try:
                self.store.save_resume_sweep(*w.key, sweep)
            except (OSError, RandtError):
                self.metrics.store_errors.inc()
                log.exception("saving the resume sweep of session %s/%s failed", *w.key)
                continue
            w.resume_saved_xyz = sweep.pose[:3, 3].copy()

    def resume_sweep(self, key: tuple[str, str], n_snapshot: int, poses: np.ndarray) -> ResumeSweep | None:
        """The session's saved resume sweep when it is newer than its snapshot and its pose is
        the one its log holds (else None: a sweep of an older life of the session id)."""
        sweep = self.store.load_resume_sweep(*key)
        if sweep is None or not n_snapshot <= sweep.pose_index < len(poses):
            return None
        if not np.allclose(sweep.pose, poses[sweep.pose_index], atol=1e-6):
            log.warning("session %s/%s: its resume sweep is not at its logged pose: not used", *key)
            return None
        return sweep
