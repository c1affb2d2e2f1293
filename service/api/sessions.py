"""``/sessions``: the fleet's driving sessions, their trajectories, and closing one.

A session's id is ``<vehicle>/<session>`` and its URL ``/sessions/<vehicle>/<session>`` (both
names are store names: letters, digits, ``_ . -``, so neither holds a ``/``). Sessions that are
running and sessions only in the store (closed, expired, or not resumed since a restart) are
listed together; ``state`` tells which.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Depends, Query
from fastapi.responses import PlainTextResponse

from randt.core.errors import NotFoundError
from randt.core.io import write_kitti_poses, write_tum
from randt.service.api.deps import (
    WRITER_RESPONSES,
    SessionName,
    VehicleName,
    get_manager,
    require_reader,
    require_writer,
)
from randt.service.api.models import (
    ClosedSession,
    ErrorBody,
    SessionDetail,
    SessionSummary,
    TrajectoryJson,
    TrajectoryPose,
)
from randt.service.api.views import find_session, load_trajectory, session_detail, session_summary
from randt.service.sessions import SessionManager

__all__ = ["router"]

router = APIRouter(prefix="/sessions", tags=["sessions"], dependencies=[Depends(require_reader)])
ManagerDep = Annotated[SessionManager, Depends(get_manager)]
_404: dict[int | str, dict[str, Any]] = {404: {"model": ErrorBody, "description": "no such session"}}


@router.get("", response_model=list[SessionSummary])
def list_sessions(
    mgr: ManagerDep,
    state: Annotated[
        Literal["active", "idle", "closed", "expired"] | None, Query(description="only this state")
    ] = None,
) -> list[SessionSummary]:
    """Every running and stored session, sorted by id."""
    depths = mgr.queue_depths()
    running = {(s.vehicle, s.session): s for s in mgr.sessions()}
    records = mgr.records()
    out = [
        session_summary(running.get(key), records.get(key), depths)
        for key in sorted(set(running) | set(records))
    ]
    return [s for s in out if state is None or s.state == state]


@router.get("/{vehicle}/{session}", response_model=SessionDetail, responses=_404)
def get_session(vehicle: VehicleName, session: SessionName, mgr: ManagerDep) -> SessionDetail:
    """One session: vehicle, state, scans, last pose, fitness, drift estimate, lag."""
    return session_detail(mgr, find_session(mgr, vehicle, session))


@router.get(
    "/{vehicle}/{session}/trajectory",
    response_model=TrajectoryJson,
    responses={
        **_404,
        200: {
            "content": {"text/plain": {}},
            "description": "JSON (format=json), or the KITTI / TUM text file (format=kitti|tum)",
        },
    },
)
def get_trajectory(
    vehicle: VehicleName,
    session: SessionName,
    mgr: ManagerDep,
    format: Annotated[
        Literal["json", "kitti", "tum"], Query(description="json, kitti (3x4 rows) or tum")
    ] = "json",
    corrected: Annotated[
        bool,
        Query(description="move the poses with the pose graph's optimized keyframes (docs/mapping.md)"),
    ] = False,
) -> TrajectoryJson | PlainTextResponse:
    """The session's poses (``T_frame_sensor``) in scan order, as JSON, KITTI or TUM text.

    KITTI and TUM are written by the same writers as ``randt map`` (``randt.core.io``); KITTI has no
    stamps, TUM has ``stamp tx ty tz qx qy qz qw`` per line. With ``corrected=true``, each pose is
    moved with the correction of the graph keyframes around it (interpolated); the JSON says
    whether it was (``corrected``: false while the session is not placed in a graph), and for each
    pose whether it lies between keyframes the graph holds (a pose beyond them is served live,
    in the map's frame, ``corrected: false``).
    """
    found = find_session(mgr, vehicle, session)
    stamps, poses = load_trajectory(mgr, found)
    frame = found.info.frame if found.info is not None else found.record.frame  # type: ignore[union-attr]
    map_name = found.info.map_name if found.info is not None else found.record.map  # type: ignore[union-attr]
    was_corrected = False
    marks: list[bool | None] = [None] * len(poses)
    if corrected and mgr.graph is not None:
        poses, graph_map, mask = mgr.graph.corrected_marked(vehicle, session, poses)
        marks = [bool(m) for m in mask]
        if graph_map is not None:
            was_corrected, map_name = True, graph_map
            frame = "map" if graph_map == mgr.settings.default_map else frame
    if format == "json":
        return TrajectoryJson(
            id=found.id,
            frame="map" if frame == "map" else "session",
            map=map_name,
            corrected=was_corrected,
            poses=[
                TrajectoryPose(stamp_s=float(t), pose=p.tolist(), corrected=c)
                for t, p, c in zip(stamps, poses, marks, strict=True)
            ],
        )
    filename = f"{vehicle}.{session}.{'txt' if format == 'kitti' else 'tum'}"
    headers = {"Content-Disposition": f'attachment; filename="{filename}"'}
    if len(poses) == 0:
        return PlainTextResponse("", headers=headers)
    with tempfile.TemporaryDirectory(prefix="randt-traj-") as tmp:
        path = Path(tmp) / filename
        if format == "kitti":
            write_kitti_poses(path, poses)
        else:
            write_tum(path, np.asarray(stamps), poses)
        return PlainTextResponse(path.read_text(), headers=headers)


@router.post(
    "/{vehicle}/{session}/close",
    response_model=ClosedSession,
    dependencies=[Depends(require_writer)],
    responses={
        **_404,
        **WRITER_RESPONSES,
    },
)
def close_session(vehicle: VehicleName, session: SessionName, mgr: ManagerDep) -> ClosedSession:
    """Finish a session: process its queued scans, save it, stop its worker (needs the token).

    Closing a finished session changes nothing (``changed: false``). A later scan with the same
    ids is refused (error ``session_closed``): its saved trajectory is never reopened.
    """
    found = find_session(mgr, vehicle, session)
    key = (vehicle, session)
    if found.info is not None and mgr.close(vehicle, session):
        saved = mgr.records().get(key)  # None only if the save failed (counted in store errors)
        scans = saved.n_scans if saved is not None else found.info.n_scans
        return ClosedSession(id=found.id, state="closed", scans=scans, changed=True)
    current = mgr.records().get(key)
    if current is None:
        raise NotFoundError(resource="session", ident=found.id)
    if current.state == "active":  # stored as active, no worker (not resumed since a restart)
        closed = mgr.close_stored(vehicle, session)
        if closed is not None:
            return ClosedSession(id=found.id, state="closed", scans=closed.n_scans, changed=True)
    state: Literal["closed", "expired"] = "expired" if current.state == "expired" else "closed"
    return ClosedSession(id=found.id, state=state, scans=current.n_scans, changed=False)
