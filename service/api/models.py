"""Response models of the HTTP API: the public contract (OpenAPI at ``/docs`` and ``/openapi.json``).

Units and frames follow the rest of the project: metres, seconds, map-frame coordinates; a pose is
the row-major 4x4 ``T_frame_sensor`` where ``frame`` is the session's (``"map"`` or ``"session"``).
Adding a field is compatible; renaming or removing one is not (bump the API then).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

__all__ = [
    "ClosedSession",
    "ErrorBody",
    "Health",
    "Lag",
    "MapExtent",
    "MapIndex",
    "MapSummary",
    "Ready",
    "SessionDetail",
    "SessionSummary",
    "Status",
    "TileBoundsModel",
    "TileIndex",
    "TileInfo",
    "TrajectoryJson",
    "TrajectoryPose",
]


class ErrorBody(BaseModel):
    """Every 4xx/5xx answer of the API (FastAPI's ``detail``, plus what was not found on a 404)."""

    detail: str = Field(description="what went wrong, for a person")
    resource: str | None = Field(default=None, description="on a 404: session, map or tile")
    id: str | None = Field(default=None, description="on a 404: the id that was asked for")


class DeletedMap(BaseModel):
    """The answer to ``DELETE /maps/{map}``."""

    map: str
    tiles: int = Field(description="tiles the map held")
    deleted: bool = True


class Health(BaseModel):
    status: Literal["ok"] = "ok"


class Ready(BaseModel):
    ready: bool
    zenoh: bool = Field(description="the Zenoh session is open (always true when run without Zenoh)")
    store_writable: bool
    workers: bool = Field(description="the session manager and its flusher are running")
    matchers_warm: bool = Field(
        description="the matcher processes have loaded their compiled kernels (longer when numba's "
        "on-disk cache is cold: they are compiled then)"
    )
    graph: bool = Field(
        default=True,
        description="the pose graph process runs (or is not needed yet: no keyframe so far, or the graph "
        "is off) and has taken again every keyframe of its log; false while it is being restarted after "
        "it died, and while it replays its log (its graph lacks keyframes and loops it had until then)",
    )


class GraphStatus(BaseModel):
    enabled: bool = Field(description="the service runs a pose graph (settings.graph)")
    running: bool = Field(description="its process is alive (it starts with the first keyframe)")
    restarts: int = Field(description="times the process died and was started again")
    last_exit: str | None = Field(description="how the process last died ('signal 9', 'exit code 1')")
    pending: int = Field(
        default=0, description="keyframes offered to the graph that it has not processed yet (it lags)"
    )
    replaying: bool = Field(
        default=False,
        description="the process is taking the keyframes of its log again (after a start or a death)",
    )


class CapacityStatus(BaseModel):
    """Admission by measured capacity (service/capacity.py)."""

    cores: float = Field(description="CPUs the matchers run on (this node's, or the Ray cluster's)")
    target: float = Field(description="the share of them admission fills at most (capacity_target)")
    load: float = Field(
        description="the running sessions' measured CPU as a share of cores x target (1: full)"
    )
    used_cores: float = Field(description="the same in cores, matchers and service process together")
    sweep_cpu_ms: float = Field(description="matcher CPU per sweep, mean of the measured sessions")
    service_cpu_ms: float = Field(description="the service process's own CPU per sweep")
    sessions_more: int = Field(description="new sessions that fit, each at session_rate_hz and sweep_cpu_ms")
    measured_sessions: int = Field(description="running sessions counted at their own measured cost")


class MapExtent(BaseModel):
    min_xyz: tuple[float, float, float]
    max_xyz: tuple[float, float, float]


class MapSummary(BaseModel):
    name: str
    tiles: int
    points: int
    tile_size_m: int
    voxel_size_m: float
    extent: MapExtent | None = Field(description="box around every point; null for an empty map")
    sessions: list[str] = Field(description="ids of the running sessions that insert into this map")


class Lag(BaseModel):
    """How far behind a session is."""

    queue_depth: int = Field(description="scans waiting for the matcher")
    last_latency_ms: float | None = Field(description="receive-to-pose time of the last scan")
    idle_s: float | None = Field(description="seconds since the last scan arrived (running sessions)")


class SessionSummary(BaseModel):
    id: str = Field(description="'<vehicle>/<session>'; the URL is /sessions/<vehicle>/<session>")
    vehicle: str
    session: str
    map: str | None
    frame: Literal["map", "session"]
    joined: str | None = Field(
        default=None,
        description="the shared map the pose graph placed this session (one without priors) into: "
        "its points fold there, its corrections name it; its answers stay in its own frame (running "
        "sessions only)",
    )
    state: Literal["active", "idle", "closed", "expired"] = Field(
        description="active: a worker is running; idle: stored as active, resumes with its next "
        "scan (after a restart); closed / expired: finished"
    )
    scans: int
    fallbacks: int
    localized: int | None = Field(
        default=None,
        description="of its scans, those answered localizing on the map (mode localizing); null when idle",
    )
    lost: bool | None = Field(
        default=None,
        description="the session has lost its track (its scans are answered `lost` without a pose "
        "until two consecutive matches) or its sweeps do not agree with its map (until two checks "
        "agree; nothing is folded meanwhile) (running sessions only)",
    )
    map_agreement: float | None = Field(
        default=None,
        description="the last map agreement check: the share of the sweep's points above the ground "
        "within 0.5 m of the map's points where the map has content (below map_agreement_min: "
        "lost); null before a check or where the map had no content (running sessions only)",
    )
    lost_scans: int | None = Field(default=None, description="scans answered `lost` (running sessions only)")
    errors: int | None = Field(description="scans answered with an error (running sessions only)")
    last_seq: int
    last_status: str | None
    queue_depth: int


class SessionDetail(SessionSummary):
    last_pose: list[list[float]] | None = Field(description="4x4 T_frame_sensor of the last scan")
    position: tuple[float, float, float] | None = Field(description="translation of last_pose, metres")
    yaw_deg: float | None = Field(description="heading of the sensor's x axis in the frame's xy plane")
    fitness: float | None = Field(description="the matcher's fitness (NVTL) of the last scan")
    distance_m: float = Field(description="path length of the trajectory")
    drift_m: float | None = Field(
        description="1-sigma position uncertainty since the last prior pose: the prior's, plus each "
        "registration's covariance as a random walk (Hessian covariances are optimistic: a lower "
        "bound). Running sessions only; null after a restart"
    )
    lag: Lag
    created: str | None = Field(description="ISO 8601 time of the first save (stored sessions)")
    updated: str | None = Field(description="ISO 8601 time of the last save (stored sessions)")


class ClosedSession(BaseModel):
    id: str
    state: Literal["closed", "expired"]
    scans: int
    changed: bool = Field(description="false when the session was already finished")


class TrajectoryPose(BaseModel):
    stamp_s: float
    pose: list[list[float]] = Field(description="4x4 T_frame_sensor, row-major")
    corrected: bool | None = Field(
        default=None,
        exclude_if=lambda v: v is None,
        description="with corrected=true: whether this pose was corrected from keyframes the pose "
        "graph holds (between two of them, or one); false: beyond them (before the first, after the "
        "newest, e.g. keyframes the graph dropped under load or has not yet taken), served live "
        "(moved into the map's frame only, for a joined session)",
    )


class TrajectoryJson(BaseModel):
    id: str
    frame: Literal["map", "session"]
    map: str | None
    corrected: bool = Field(
        default=False, description="the poses moved with the pose graph's keyframes (corrected=true)"
    )
    poses: list[TrajectoryPose]


class GraphKeyframe(BaseModel):
    vehicle: str
    session: str
    seq: int = Field(description="the keyframe scan's seq")
    index: int = Field(description="the scan's place in its session (0 = first processed)")
    stamp_s: float
    live: list[list[float]] = Field(description="4x4 pose as answered (the live estimate)")
    pose: list[list[float]] | None = Field(
        description="4x4 optimized T_map_sensor; null while the session is not placed in the graph"
    )


class GraphEdge(BaseModel):
    a: tuple[str, str, int] = Field(description="(vehicle, session, seq) of the source keyframe")
    b: tuple[str, str, int] = Field(description="(vehicle, session, seq) of the target keyframe")
    source: Literal["place", "proximity", "placement"]
    confident: bool = Field(description="global registration passed verification (and the graph's gate)")
    accepted: bool = Field(description="the loop is a factor of the graph")
    reason: str = Field(description="why not accepted; empty when accepted")
    n_inliers: int


class MapGraph(BaseModel):
    map: str
    revision: int = Field(description="increases with every optimization that moved a keyframe")
    sessions: list[str] = Field(description="<vehicle>/<session> of every session with keyframes")
    placed: list[str] = Field(description="sessions placed in the graph's frame")
    keyframes: list[GraphKeyframe]
    loops: list[GraphEdge] = Field(description="every verification, accepted or not")
    refused_keyframes: int
    replaying: bool = Field(
        default=False,
        description="the graph process is still taking the keyframes of its log again (after a restart "
        "or its death): some keyframes and loops it had are not shown yet",
    )
    joined: dict[str, list[list[float]]] = Field(
        default_factory=dict,
        description="sessions without priors the graph placed into this map: <vehicle>/<session> -> "
        "4x4 T_map_session, where their own frame (the frame of their answers) lies in this map",
    )


class TileBoundsModel(BaseModel):
    cell_min_xy: tuple[int, int] = Field(description="lower cell corner, integer metres (Autoware's)")
    cell_max_xy: tuple[int, int]
    min_xyz: tuple[float, float, float] = Field(description="box around the tile's points")
    max_xyz: tuple[float, float, float]


class TileInfo(BaseModel):
    id: str = Field(description="'<ix>_<iy>'")
    ix: int
    iy: int
    version: int = Field(description="incremented on every change; the ETag of a download")
    points: int
    bounds: TileBoundsModel
    pdu: float = Field(description="Point Density Uniformity at pdu_voxel_m (1 = uniform)")
    url: str = Field(description="download path (add ?format=pcd|ply|las)")


class TileIndex(BaseModel):
    map: str
    tile_size_m: int
    voxel_size_m: float
    pdu_voxel_m: float
    query: dict[str, float] | None = Field(description="the bbox or radius filter applied, if any")
    tiles: list[TileInfo]


class MapIndex(BaseModel):
    maps: list[MapSummary]


class Status(BaseModel):
    instance: str
    uptime_s: float
    ready: bool
    sessions: list[SessionSummary] = Field(description="running sessions")
    scans_received: int
    scans_processed: int
    scans_rejected: int
    scans_dropped: int
    queue_depths: dict[str, int] = Field(description="'<vehicle>/<session>' -> scans waiting")
    maps: dict[str, MapSummary]
    graph: GraphStatus = Field(description="the pose graph process (service/graph.py)")
    capacity: CapacityStatus | None = Field(
        default=None, description="what the node can carry, measured; null when admission is by count only"
    )
