"""Opening a session: a new one, or one the store holds (resumed after a restart or an idle
expiry, from its snapshot, the poses logged since and its newest resume sweep), with its matcher
started where the matchers run."""

from __future__ import annotations

import logging

import numpy as np

from randt.core.errors import BadMessageError
from randt.core.odometry import extend_state_dict, with_keyframe
from randt.service.matchers import LocalMatcher, MatcherExecutor, SessionMatcher, with_trajectory
from randt.service.session_info import SessionInfo
from randt.service.session_record import SessionFrame
from randt.service.snapshots import SessionSaver
from randt.service.store import SessionRecord
from randt.service.worker import SessionWorker, WorkerServices
from randt.wire.codes import ErrorCode
from randt.wire.ids import session_map_name
from randt.wire.messages import ScanHeader

__all__ = ["SessionOpener", "open_session"]

log = logging.getLogger(__name__)


class SessionOpener:
    """Opens sessions with the service's collaborators and matcher executor."""

    def __init__(self, services: WorkerServices, saver: SessionSaver, pool: MatcherExecutor | None) -> None:
        self.services, self.saver, self.pool = services, saver, pool

    def open(self, scan: ScanHeader) -> SessionWorker:
        """The worker of a new or stored session (an opener thread's call, no lock held)."""
        record = self.saver.record((scan.vehicle, scan.session))
        return open_session(scan, record, self.services, self.saver, self.pool)


def open_session(
    scan: ScanHeader,
    record: SessionRecord | None,
    services: WorkerServices,
    saver: SessionSaver,
    pool: MatcherExecutor | None,
) -> SessionWorker:
    """The worker of the session ``scan`` opens (on an opener thread, no manager lock held)."""
    key = (scan.vehicle, scan.session)
    if record is not None and record.state == "closed":
        # Its trajectory and state are on disk; reopening would overwrite them.
        raise BadMessageError(
            f"session {scan.session!r} of vehicle {scan.vehicle!r} was closed: "
            "publish under a new session id",
            code=ErrorCode.SESSION_CLOSED,
        )
    state: dict[str, np.ndarray] | None = None
    if record is not None and record.state in ("active", "expired"):
        # Active: the service restarted. Expired: the vehicle paused longer than the idle expiry
        # and came back. Either way the session resumes where it stopped.
        info, state = _resumed(scan, record, services, saver)
    else:
        # A new session (or one whose first save never completed: nothing was acknowledged).
        services.store.reset_pose_log(*key)
        in_map = scan.prior_pose() is not None or scan.geo_prior is not None
        map_name = services.settings.default_map if in_map else session_map_name(scan.vehicle, scan.session)
        frame: SessionFrame = "map" if in_map else "session"
        info = SessionInfo(scan.vehicle, scan.session, map_name, frame, localize_only=scan.localize_only)
    grid = services.maps.grid(info.map_name)
    settings = services.settings
    matcher: SessionMatcher
    if pool is not None:
        matcher = pool.open(key, state or None, grid, settings.session_matcher(), settings.registration)
    else:
        local = LocalMatcher(settings.session_matcher(), settings.registration)
        if state:
            local.load_state_dict(state)
        matcher = local
    return SessionWorker(info, matcher, grid, services)


def _resumed(
    scan: ScanHeader, record: SessionRecord, services: WorkerServices, saver: SessionSaver
) -> tuple[SessionInfo, dict[str, np.ndarray]]:
    """A stored session's state and figures: the snapshot plus the poses logged since (every pose
    published), the matcher brought to the last of them (extend_state_dict: poses, velocity and
    stamp; the keyframes stay the snapshot's), and a sweep saved since the snapshot, at its logged
    pose, joining its keyframes: the model then reaches where the vehicle is."""
    key = (scan.vehicle, scan.session)
    stored, stamps, poses, state = services.store.load_session(*key)
    assert record.map is not None  # the service saves every session with its map
    state = with_trajectory(state, poses)
    sweep = saver.resume_sweep(key, len(state.get("poses", ())), poses)
    state = extend_state_dict(state, poses, stamps, settings=services.settings.session_matcher())
    if sweep is not None:
        state = with_keyframe(state, sweep.pose, sweep.points)
        log.info("session %s/%s: sweep %d joins its snapshot's keyframes", *key, sweep.pose_index)
    info = SessionInfo(
        scan.vehicle,
        scan.session,
        record.map,
        record.frame,
        last_seq=max(record.last_seq, stored.last_seq),
        n_scans=stored.n_scans,
        n_fallbacks=stored.n_fallbacks,
        stamps_s=list(np.asarray(stamps, dtype=float)),
        saved_scans=len(poses),  # every one of them on disk
        snapshot_xyz=np.array(poses[-1][:3, 3]) if len(poses) else None,
        localize_only=record.localize_only,
    )
    log.info("session %s/%s resumed at seq %d (%d poses)", *key, info.last_seq, len(poses))
    return info, state
