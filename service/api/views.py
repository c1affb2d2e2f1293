"""Builders of the response models from the service's live state and the store's records.

A session is either **running** (a worker holds its matcher: :class:`randt.service.worker.SessionInfo`)
or only **stored** (:class:`randt.service.store.SessionRecord`: closed, expired, or active but not resumed
since a restart). The routers ask :func:`find_session` for both and build one model from either.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from randt.core.errors import NotFoundError
from randt.core.tiles import TileGrid
from randt.service.api.models import Lag, MapExtent, MapSummary, SessionDetail, SessionSummary
from randt.service.live_maps import DurableMap
from randt.service.session_info import SessionInfo
from randt.service.sessions import SessionManager
from randt.service.store import SessionRecord

__all__ = [
    "FoundSession",
    "find_session",
    "load_trajectory",
    "map_summary",
    "session_detail",
    "session_id",
    "session_summary",
]


def session_id(vehicle: str, session: str) -> str:
    """The API's id of a session, ``<vehicle>/<session>`` (its URL is ``/sessions/<vehicle>/<session>``)."""
    return f"{vehicle}/{session}"


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def session_summary(
    info: SessionInfo | None, record: SessionRecord | None, depths: dict[str, int]
) -> SessionSummary:
    """One session's summary from its running state (preferred) or its stored record."""
    if info is not None:
        sid = session_id(info.vehicle, info.session)
        return SessionSummary(
            id=sid,
            vehicle=info.vehicle,
            session=info.session,
            map=info.map_name,
            frame="map" if info.frame == "map" else "session",
            joined=info.joined_map,
            state="active",
            scans=info.n_scans,
            fallbacks=info.n_fallbacks,
            localized=info.n_localized,
            lost=info.lost or info.map_disagrees,
            map_agreement=None if info.map_agreement != info.map_agreement else info.map_agreement,
            lost_scans=info.n_lost,
            errors=info.n_errors,
            last_seq=info.last_seq,
            last_status=info.last_status or None,
            queue_depth=depths.get(sid, 0),
        )
    if record is None:
        raise ValueError("session_summary needs a running state or a stored record")
    return SessionSummary(
        id=session_id(record.vehicle, record.session),
        vehicle=record.vehicle,
        session=record.session,
        map=record.map,
        frame=record.frame,
        state="idle" if record.state == "active" else record.state,
        scans=record.n_scans,
        fallbacks=record.n_fallbacks,
        errors=None,
        last_seq=record.last_seq,
        last_status=None,
        queue_depth=0,
    )


@dataclass
class FoundSession:
    """A session the API was asked about: its running state and/or its stored record."""

    vehicle: str
    session: str
    info: SessionInfo | None
    record: SessionRecord | None

    @property
    def id(self) -> str:
        return session_id(self.vehicle, self.session)


def find_session(mgr: SessionManager, vehicle: str, session: str) -> FoundSession:
    """The running or stored session ``vehicle/session``; :class:`~randt.core.errors.NotFoundError` if
    neither."""
    worker = mgr.worker(vehicle, session)
    record = mgr.records().get((vehicle, session))
    if worker is None and record is None:
        raise NotFoundError(resource="session", ident=session_id(vehicle, session))
    return FoundSession(vehicle, session, worker.info if worker else None, record)


def load_trajectory(mgr: SessionManager, found: FoundSession) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps_s (N,), poses (N, 4, 4))``: from the running matcher, else from the store."""
    if found.info is not None:
        live = mgr.trajectory(found.vehicle, found.session)
        if live is not None:
            return live
    # Stored (or closed between the two look-ups): the store's commit record is the truth; a
    # session listed but gone or unreadable now is not found.
    return mgr.stored_trajectory(found.vehicle, found.session)


def session_detail(mgr: SessionManager, found: FoundSession) -> SessionDetail:
    """The full view of one session (``GET /sessions/{vehicle}/{session}``)."""
    depths = mgr.queue_depths()
    summary = session_summary(found.info, found.record, depths)
    _, poses = load_trajectory(mgr, found)
    last = poses[-1] if len(poses) else None
    steps = np.diff(poses[:, :3, 3], axis=0) if len(poses) > 1 else np.zeros((0, 3))
    info = found.info
    record = found.record
    return SessionDetail(
        **summary.model_dump(),
        last_pose=last.tolist() if last is not None else None,
        position=tuple(float(v) for v in last[:3, 3]) if last is not None else None,  # type: ignore[arg-type]
        yaw_deg=math.degrees(math.atan2(last[1, 0], last[0, 0])) if last is not None else None,
        fitness=_finite(info.last_fitness) if info is not None else None,
        distance_m=float(np.linalg.norm(steps, axis=1).sum()),
        drift_m=math.sqrt(max(info.drift_var_m2, 0.0)) if info is not None else None,
        lag=Lag(
            queue_depth=summary.queue_depth,
            last_latency_ms=_finite(info.last_latency_ms) if info is not None else None,
            idle_s=time.monotonic() - info.last_activity if info is not None else None,
        ),
        created=record.created.isoformat() if record is not None else None,
        updated=record.updated.isoformat() if record is not None else None,
    )


def map_summary(name: str, grid: TileGrid | DurableMap, running: list[SessionInfo]) -> MapSummary:
    """One map's summary: tiles, points, settings, extent and the running sessions feeding it."""
    tiles = grid.tiles()  # one snapshot: counts and extent agree
    extent = None
    if tiles:
        lo = np.min([t.bounds.min_xyz for t in tiles], axis=0)
        hi = np.max([t.bounds.max_xyz for t in tiles], axis=0)
        extent = MapExtent(min_xyz=tuple(map(float, lo)), max_xyz=tuple(map(float, hi)))  # type: ignore[arg-type]
    return MapSummary(
        name=name,
        tiles=len(tiles),
        points=sum(t.n_points for t in tiles),
        tile_size_m=grid.tile_size_m,
        voxel_size_m=grid.voxel_size_m,
        extent=extent,
        sessions=sorted(
            session_id(s.vehicle, s.session) for s in running if name in (s.map_name, s.joined_map)
        ),
    )
