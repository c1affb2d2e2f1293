"""What the service knows about one running session: its frame and map, its counters, its last
figures, its snapshot's place, its track (read by status, the flusher and the session's stages)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from randt.service.store import SessionFrame
from randt.service.store import SessionState as RecordState

__all__ = ["SessionInfo"]


@dataclass
class SessionInfo:
    """What the service knows about one running session (read by status and the flusher)."""

    vehicle: str
    session: str
    map_name: str
    frame: SessionFrame
    created: float = field(default_factory=time.time)
    last_activity: float = field(default_factory=time.monotonic)
    last_seq: int = -1
    n_scans: int = 0
    n_fallbacks: int = 0
    #: poses answered localizing on the map (docs/mapping.md, "Localizing on the map")
    n_localized: int = 0
    n_errors: int = 0
    stamps_s: list[float] = field(default_factory=list)
    last_fitness: float = float("nan")
    last_status: str = ""
    last_latency_ms: float = float("nan")
    dirty: bool = False
    #: Poses the session's last snapshot covers (all of them on disk: its log holds the later ones).
    saved_scans: int = 0
    #: When (monotonic) and where (position, m; ``None`` before the first) the last snapshot was taken.
    snapshot_at: float = field(default_factory=time.monotonic)
    snapshot_xyz: np.ndarray | None = None
    state: RecordState = "active"
    #: Variance (m^2) of the position accumulated since the last prior pose: the prior's own
    #: variance, plus the trace of each registration's translational covariance (a random walk).
    drift_var_m2: float = 0.0
    #: The shared map the pose graph placed this session (one without priors) into: its points
    #: fold there from then on (service/graph.py); ``None`` otherwise.
    joined_map: str | None = None
    #: The stamp (ns) of the session's last matched (or first) scan in this process; ``None``
    #: before one (a resumed session's first fallback is then beyond any horizon).
    matched_stamp_ns: int | None = None
    #: Lost (the worker's track stage): answered ``lost`` without a pose and folding nothing until
    #: ``VERIFY_MATCHES`` consecutive matches; how many so far; scans answered lost.
    lost: bool = False
    verified_matches: int = 0
    n_lost: int = 0
    #: The last map agreement check's share of points near the map, and whether the session is
    #: lost because its sweeps disagree with it (service/agreement.py).
    map_agreement: float = float("nan")
    map_disagrees: bool = False
    #: The session only localizes on the shared map, never adds to it (its first scan's
    #: ``localize_only``; docs/mapping.md, "A session that only localizes").
    localize_only: bool = False
