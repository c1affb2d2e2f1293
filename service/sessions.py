"""Session management: one incremental matcher and one worker thread per (vehicle, session).

Flow of a scan::

    transport callback --> SessionManager.submit --> Intake (service/intake.py): bounded queue per
          (only enqueues bytes)                      vehicle, drained round-robin by intake workers
    intake worker --> SessionManager.handle: decode (bounded cost) --> admission --> seq check -->
          SessionWorker queue (bounded, shed evenly), or the queue of an _Opening placeholder
          while an opener thread opens the session (store read, matcher start) outside the lock
    SessionWorker thread --> matcher (a worker process, service/matchers.py: float32 points in,
        the map's candidate points in the map frame out) --> the pose appended to the session's
        pose log and fsync'd (Store.append_pose) --> map tiles (shared TileGrid) --> pose to the
        outbox (held until the session's first snapshot is on disk)
    flusher thread (every flush_interval_s) --> the snapshots that are due (a session's matcher
        state and record, every snapshot_interval_s or snapshot_distance_m; its poses are in its
        log already); every tile_save_interval_s, dirty tiles too, then the saved tiles' updates
        to the outbox; idle sessions expired; counters to DATA/counters.json

**Durable before acknowledged**: a pose goes out only once it is in the session's fsync'd log (a
session's first poses also wait for its first snapshot, which fixes its frame and holds its first
keyframe: it is written on a thread of its own while the session goes on matching, and the poses
that come meanwhile go out in order once it is on disk, or are answered ``storage_error`` if it
could not be written; a crash before it leaves nothing acknowledged, so the session starts
afresh). If the log cannot be written, the scan is answered ``storage_error`` and the session is
dropped from memory, to resume from the store with its next scan.

**Snapshots, rarely**: the log is the trajectory's truth, so a running session's snapshot (its
matcher state without the trajectory, :meth:`SessionMatcher.snapshot_state
<randt.service.matchers.SessionMatcher.snapshot_state>`, and its record) is written when the session
opens, closes, expires, gives up its slot or the service stops, and in between only when one is
due: ``snapshot_interval_s`` after the last (30 s), or once the vehicle is ``snapshot_distance_m``
(20 m) from where the last was taken, so that a session resumed after a crash still matches
against the snapshot's keyframes; with them, its newest sweep that came with points, saved by the
flusher (``resume.npz``, :meth:`Store.save_resume_sweep`), reaches where the vehicle is. A
snapshot costs the same at any length of the session: the store writes no pose it already holds
(:meth:`Store.save_session`). Everything the API shows of a running session comes from memory;
the stored record (``session.json``, ``updated``) lags by up to a snapshot interval.

**Saved before seen**: tiles are served (HTTP, the queryable, tile updates, listings) as last saved
(:class:`DurableMap`), so a version seen outside is on disk and never goes back or repeats with
other content after a crash.

**Map folding**: a scan's map points (the matcher process sends only those the map can keep, in
the map frame) wait with the session, and the points of ``fold_scans`` scans (10) are inserted
into the map's tiles together, by the scan that makes them that many, by the flusher before it
saves tiles, or when the session closes. An insert pays per point and per tile touched (about 60
tiles of 20 m per sweep, each copied: a tile is an immutable version), and a vehicle's
consecutive sweeps touch the same tiles, so a tile is copied once per fold instead of once per
sweep. Tiles are served as saved (every ``tile_save_interval_s``, before which every session
folds), so nothing outside sees the difference; ``fold_scans=1`` folds every scan before its pose
goes out. Tiles are saved less often than sessions: a vehicle's sweeps touch the same ~60 tiles
for seconds, and each save writes a tile whole (PCD, fsync) and publishes it whole, so the
service process's cost of saving falls with the interval (3 s by default).

**Locking**: the manager lock (``_lock``) guards the dictionaries of sessions only and is never held
across a store read, a matcher call or a matcher warm-up: ``/status``, ``/sessions`` and other
vehicles' scans never wait for one. Opening a session (reading its saved state, starting its
matcher, which may wait ~10 s for a cold matcher process) runs on an opener thread; meanwhile an
``_Opening`` placeholder holds the session's slot, and its later scans queue behind it (bounded
by ``queue_size`` with the overload policy below) and are seq-checked once it is open.

**Admission**: a scan that would open a session is refused ``sessions_full`` at ``max_sessions``
running (and opening) sessions, ``vehicle_sessions_full`` at ``max_sessions_per_vehicle`` of its
vehicle, unless a running session has been idle for ``slot_idle_s`` (nothing queued, not
matching), or, for the per-vehicle limit, one of that vehicle's sessions for
``vehicle_slot_idle_s`` (a vehicle that starts a new session has moved on from the one it stopped
feeding a second ago): the idlest such session then gives up its slot,
saved as ``expired`` like an idle expiry, and resumes from the store with its next scan. So
sessions that sent one scan and went quiet cannot squat the service.

Every scan a vehicle sends gets exactly one answer on its keys: a pose, or an error whose ``code``
says why (bad message, duplicate or out-of-order sequence number, dropped by overload, failed
registration). One session's failure never touches another's worker, queue or map data.

**Overload policy**: each session queue holds ``queue_size`` scans; when a new scan arrives at a
full queue, a waiting scan is dropped, counted in ``randt_scans_dropped`` and answered with error
code ``dropped``: the one whose removal leaves the shortest gap (by the scans' stamps) between the
scans around it (:func:`drop_index`). A session that falls behind so sheds evenly (every second
scan, then every third) and never loses the newest, and the gaps its matcher predicts over stay
short: dropping the oldest instead left one gap as long as the stall that filled the queue,
past the fallback horizon (the session was then lost). One exception: a
young session (fewer than ``YOUNG_SESSION_SCANS`` processed) keeps its oldest waiting scans and
loses the newest waiting one instead: its first scan anchors it (a prior pose places it in the map
frame) and its first sweeps must be consecutive for the matcher to learn its velocity (with none,
a 2.4 s gap at 8 vehicles could not be bridged). After that the matcher extrapolates over the
gaps from the stamps.

**Frames**: a session whose first processed scan carries a prior pose (GNSS/INS) lives in the map
frame and folds into the shared map (``default``). A session without priors has its own frame,
starting at its first sweep, and its own map ``<vehicle>.<session>``
(:func:`randt.wire.ids.session_map_name`: the vehicle escaped so that no two sessions share a map) until
it can be placed;
status reports which (``frame``: ``"map"`` or ``"session"``). The frame is fixed by the first scan
the matcher *processes* (the first one received may be rejected), never by an earlier one.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from randt.core.errors import BadMessageError, ConflictError, NotFoundError, RandtError, UnavailableError
from randt.core.geo import GeoOrigin
from randt.core.odometry import (
    MAP_SEED_MIN_POINTS,
    RELOCALIZED,
    PosePrior,
    ScanResult,
    extend_state_dict,
    with_keyframe,
)
from randt.core.tiles import Tile, TileGrid
from randt.service.agreement import AgreementGate, Held
from randt.service.capacity import Capacity, CapacityFigures
from randt.service.georef import MapProjections
from randt.service.graph import MapGeometry, ServiceGraph
from randt.service.graph_log import GRAPH_DIRNAME
from randt.service.intake import Intake
from randt.service.matchers import (
    LocalMatcher,
    MapFrame,
    MatcherExecutor,
    MatcherPool,
    MatcherProcessDiedError,
    MatcherProcessError,
    Registered,
    SessionMatcher,
    prior_of,
    with_trajectory,
)
from randt.service.metrics import ServiceMetrics
from randt.service.settings import ServiceSettings
from randt.service.store import (
    PoseLogRecord,
    ResumeSweep,
    SessionFrame,
    SessionRecord,
    Store,
    load_counters,
    save_counters,
)
from randt.service.store import SessionState as RecordState
from randt.wire.codes import ErrorCode
from randt.wire.ids import UNKNOWN_ID, session_map_name
from randt.wire.messages import (
    SCAN_V2,
    ErrorMessage,
    PoseMessage,
    ScanHeader,
    TileUpdateMessage,
    WireLimits,
    WireMessage,
    decode_scan,
    decode_scan_header,
    peek_ids,
    peek_seq,
    points_digest,
    tile_update_from_arrays,
    tile_update_from_table,
)
from randt.wire.ros2 import Ros2Scan
from randt.wire.ros2 import scan_header as ros2_scan_header
from randt.wire.ros2 import sweep_arrays as ros2_sweep_arrays

__all__ = [
    "DurableMap",
    "MapInUseError",
    "Outbox",
    "SessionManager",
    "SessionWorker",
    "tile_digest",
    "tile_message",
]

log = logging.getLogger(__name__)

#: ``max_sessions=-1``: this many running sessions per core (ServiceSettings.max_sessions).
SESSIONS_PER_CORE = 4
#: A lost session answers poses again after this many consecutive matches (SessionWorker._track).
VERIFY_MATCHES = 2

#: A session's resume sweep (Store.save_resume_sweep) is saved again once its vehicle is this far
#: (m) from where the saved one was taken: a vehicle that stands still does not rewrite it.
RESUME_SWEEP_M = 2.0
#: A session's first sweep with a prior is placed against its map's points within this many
#: metres (x and y) of the prior (:meth:`SessionWorker._map_seed`), beyond the matcher's reach.
MAP_SEED_REACH_M = 60.0
#: A sweep with fewer points than this is no resume sweep (it would not make a keyframe).
MIN_RESUME_POINTS = 100
#: A session whose queue holds at least this many scans is behind: on a node past its capacity
#: (:meth:`SessionManager.saturated`) its matcher lets the keyframe model lag one keyframe rather
#: than delay them (IncrementalMatcher.update_model). A shorter backlog is a transient that clears
#: within a sweep or two; on a node within capacity so is a longer one (a session's first sweeps
#: take 0.5-0.7 s in all, which queues 5-7 scans; a corner's sweeps up to 120 ms): lagging there
#: changed one vehicle's trajectory (the same 600 sweeps: 11.3 and 11.7 cm max error against 8.4 cm
#: offline, no lag gives 8.4 exactly; with lag only at depth 3, 5.7 to 10.8 cm against 5.8 cm).
BEHIND_DEPTH = 3

#: Where results go: the transport (Zenoh) or, in tests, a list. Must not block for long.
Outbox = Callable[[WireMessage], None]


class MapInUseError(ConflictError):
    """A map cannot be deleted while running sessions fold scans into it."""


@dataclass
class _Job:
    """A scan as the service process holds it: its header, and the payload's bytes, which only
    the session's matcher decodes (randt.wire.messages.decode_scan_header)."""

    scan: ScanHeader
    received_ns: int
    payload: bytes | Ros2Scan = b""


@dataclass
class _Opening:
    """A session being opened by an opener thread: holds its slot; its scans wait here meanwhile."""

    first: ScanHeader
    jobs: deque[_Job] = field(default_factory=deque)
    #: A running session that gave up its slot (admission): saved and closed before the open.
    evict: SessionWorker | None = None
    done: threading.Event = field(default_factory=threading.Event)


@dataclass
class SessionState:
    """What the service knows about one session (read by status and the flusher)."""

    vehicle: str
    session: str
    map_name: str
    frame: SessionFrame
    created: float = field(default_factory=time.time)
    last_activity: float = field(default_factory=time.monotonic)
    last_seq: int = -1
    n_scans: int = 0
    n_fallbacks: int = 0
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
    #: Lost (:meth:`SessionWorker._track`): answered ``lost`` without a pose and folding nothing
    #: until :data:`VERIFY_MATCHES` consecutive matches; how many so far; scans answered lost.
    lost: bool = False
    verified_matches: int = 0
    n_lost: int = 0
    #: The last map agreement check's share of points near the map, and whether the session is
    #: lost because its sweeps disagree with it (service/agreement.py).
    map_agreement: float = float("nan")
    map_disagrees: bool = False


class SessionWorker:
    """One session's bounded queue, worker thread and matcher (module docstring)."""

    def __init__(
        self,
        info: SessionState,
        matcher: SessionMatcher,
        grid: TileGrid,
        manager: SessionManager,
    ) -> None:
        self.info = info
        self.matcher = matcher
        self.grid = grid
        self._manager = manager
        self._queue: deque[_Job] = deque()
        self._taken_ns: int | None = None  # the stamp of the scan taken from the queue last
        self._cond = threading.Condition()
        self._stopping = False
        # Its matcher process died, or a pose could not be made durable: abandon (not save) and
        # resume from the store. The code and reason answer the scans still queued.
        self.broken = False
        self.broken_answer: tuple[str, str] = (
            ErrorCode.INTERNAL_ERROR,
            "the matcher process died; the session resumes from its last saved state",
        )
        self.lock = threading.Lock()  # held while the matcher runs; the flusher takes it to save
        # A new session's poses are held until its first snapshot is written (_save_first):
        # _first_saved is None meanwhile, then whether it was saved (a resumed session has one).
        self._held_lock = threading.Lock()
        self._held: list[tuple[PoseMessage, int]] = []
        self._first_saved: bool | None = True
        self._first_save: threading.Thread | None = None
        # Map points of scans processed while behind, waiting to be folded in together (_fold).
        self._unfolded: list[Held] = []  # map, xyz, intensity
        # ... after the map agreement check let them through (service/agreement.py)
        s = manager.settings
        self.gate = AgreementGate(s.map_agreement_min, s.map_agreement_every, s.map_agreement_min_points)
        self._fold_lock = threading.Lock()
        self._keyframe_wanted = False  # the graph asked for the sweep being matched as a keyframe
        self._fix_refused = False  # a NavSatFix could not be placed in the shared map (logged once)
        # The newest matched sweep that came with its points, and where the saved one is: the
        # flusher saves it for a resume after a crash (SessionManager._save_resume_sweeps).
        self.resume_sweep: ResumeSweep | None = None
        self.resume_saved_xyz: np.ndarray | None = None
        self._thread = threading.Thread(
            target=self._run, name=f"session-{info.vehicle}-{info.session}", daemon=True
        )
        self._thread.start()

    @property
    def key(self) -> tuple[str, str]:
        return self.info.vehicle, self.info.session

    def depth(self) -> int:
        return len(self._queue)

    def submit(self, job: _Job) -> _Job | None:
        """Enqueue ``job``; returns the job dropped to make room, if the queue was full."""
        with self._cond:
            dropped = None
            if len(self._queue) >= self._manager.settings.queue_size:
                k = drop_index(
                    self._queue,
                    n_processed=self.info.n_scans,
                    arriving_ns=job.scan.stamp_ns,
                    taken_ns=self._taken_ns,
                )
                dropped = self._queue[k]
                del self._queue[k]
            self._queue.append(job)
            self._cond.notify()
            return dropped

    def stop(self, *, drain: bool = True, timeout: float = 30.0) -> None:
        """Stop the worker, after processing what is queued when ``drain``."""
        with self._cond:
            if not drain:
                self._queue.clear()
            self._stopping = True
            self._cond.notify()
        self._thread.join(timeout)
        self.wait_first_save(timeout)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._stopping and not self.broken:
                    self._cond.wait()
                if self.broken:  # its first snapshot failed on the first-save thread
                    break
                if not self._queue and self._stopping:
                    return
                job = self._queue.popleft()
                self._taken_ns = job.scan.stamp_ns
                self._manager.metrics.queue_depth.labels(queue_label(*self.key)).set(len(self._queue))
            graph = self._manager.graph
            try:
                # the graph process yields the cores while a sweep is matched (YieldGate)
                with contextlib.nullcontext() if graph is None else graph.matching():
                    self._process(job)
                if self.broken:
                    self._abandon()
                    return
            except Exception:  # a bug in one scan must not kill the session or the service
                log.exception("session %s/%s: scan %d failed", *self.key, job.scan.seq)
                self._manager.reject(
                    job.scan.vehicle,
                    job.scan.session,
                    job.scan.seq,
                    ErrorCode.INTERNAL_ERROR,
                    "internal error while registering this scan (logged by the service)",
                )
        self._abandon()

    def _abandon(self) -> None:
        """Leave the manager after the matcher process died or a pose could not be made durable:
        queued scans are answered with ``broken_answer``, nothing is saved (the store's last state
        stays the truth), and the session's next scan resumes it from the store on a live process."""
        m = self._manager
        with m._lock:
            if m._workers.get(self.key) is self:
                del m._workers[self.key]
                m.metrics.sessions_active.set(len(m._workers))
        with self._cond:
            pending = list(self._queue)
            self._queue.clear()
            self._stopping = True
        for job in pending:
            m.reject(job.scan.vehicle, job.scan.session, job.scan.seq, *self.broken_answer)
        self.wait_first_save()  # (it answers the poses it holds) before the matcher goes
        self.fold(release=True)  # the poses of these points went out: their points belong to the map
        self.matcher.close()

    def _fix_frame(self, has_prior: bool) -> None:
        """Set the session's frame from its first processed scan (module docstring, Frames)."""
        info = self.info
        frame: SessionFrame = "map" if has_prior else "session"
        if info.frame == frame:
            return
        old = info.map_name
        name = (
            self._manager.settings.default_map if has_prior else session_map_name(info.vehicle, info.session)
        )
        log.info(
            "session %s/%s: its first processed scan %s a prior pose: %s frame, map %s",
            info.vehicle,
            info.session,
            "carries" if has_prior else "has no",
            frame,
            name,
        )
        self.grid = self._manager.map_grid(name)
        info.frame, info.map_name = frame, name
        self._manager.forget_empty_map(old)

    def _process(self, job: _Job) -> None:
        """One scan, in stages: match it where the matcher runs, make its pose durable, queue its
        map points, account for it, answer it, offer it to the pose graph. A stage that answers
        the scan with an error ends it (``None``/``False``)."""
        scan = job.scan
        try:
            prior = self._manager.prior_in_map(scan)
        except BadMessageError as exc:  # a WGS84 prior its map cannot place (service/georef.py)
            self._manager.reject(scan.vehicle, scan.session, scan.seq, exc.code, str(exc))
            return
        # Several more of this session's scans wait and the node is past its capacity: the
        # keyframe model may lag one keyframe rather than delay them (IncrementalMatcher.update_model).
        behind = self.depth() >= BEHIND_DEPTH and self._manager.saturated()
        with self.lock:
            registered = self._match(job, prior, behind)
            if registered is not None and self._manager.capacity is not None:
                self._manager.capacity.matched(
                    self.key, registered.cpu_s, in_process=self._manager.pool is None
                )
            if registered is None or not self._log_pose(scan, registered.result):
                return
            lost = self._track(scan, registered.result)
            if lost is None:
                lost = self._queue_map_points(registered)
            if lost is None:
                self._keep_resume_sweep(registered)
            self._account(scan, registered.result, prior, lost is not None)
        if len(self._unfolded) >= self._manager.settings.fold_scans:  # (module docstring, Map folding)
            self.fold()
        if lost is None:
            self._answer(job, registered.result)
            self._offer_keyframe(scan, registered, prior)
        else:
            self._manager.reject(scan.vehicle, scan.session, scan.seq, ErrorCode.LOST, lost)
        if not behind:
            with self.lock:
                self.matcher.update_model()  # in-process matchers; a matcher process does it itself

    # -- the stages of one scan (SessionWorker._process, under the session lock up to _account) --
    def _match(self, job: _Job, prior: PosePrior | None, behind: bool) -> Registered | None:
        """The scan's payload to the matcher, which decodes and matches it; ``None`` when it was
        answered with an error instead (the matcher process died: the session is then broken)."""
        scan, m, graph = job.scan, self._manager, self._manager.graph
        if self.info.n_scans == 0:
            self._fix_frame(prior is not None)
        # The pose graph's next keyframe: the matcher returns its points (service/graph.py), at
        # the map's voxel (they also re-fold the map's tiles; the graph thins them).
        keyframe_voxel_m = None
        self._keyframe_wanted = graph is not None and graph.wants_keyframe(
            scan.vehicle, scan.session, self.matcher.poses
        )
        if self._keyframe_wanted:
            assert graph is not None
            keyframe_voxel_m = min(graph.settings.keyframe_voxel_m, m.settings.map_voxel_m)
        elif self.gate.due() or (
            self.gate.enabled and (self.info.lost or self.info.last_status == "fallback")
        ):
            # the map agreement check wants the sweep's points too (and a lost session's track
            # is found again only where its sweep agrees with the map; a match after fallbacks
            # passed only the matcher's loose gate: service/agreement.py)
            keyframe_voxel_m = m.settings.map_voxel_m
        try:
            # the keyframe model is rebuilt after the pose is out
            return self.matcher.register_payload(
                job.payload,
                limits=m.limits,
                behind=behind,
                keyframe_voxel_m=keyframe_voxel_m,
                frame=self._map_frame(
                    self._map_seed(prior) if self.info.n_scans == 0 else None,
                    prior if scan.geo_prior is not None else None,  # (placed here: the payload has none)
                ),
            )
        except MatcherProcessDiedError as exc:  # (a RandtError too: caught first)
            log.error("session %s/%s: %s; it resumes from its last saved state", *self.key, exc)
            m.reject(
                scan.vehicle,
                scan.session,
                scan.seq,
                ErrorCode.INTERNAL_ERROR,
                "the matcher process died; the session resumes from its last saved state",
            )
            self.broken = True
        except MatcherProcessError:
            raise  # a bug, not bad input: logged and answered internal_error by the worker loop
        except BadMessageError as exc:  # its bodies did not decode (v2: decompressed there)
            m.reject(scan.vehicle, scan.session, scan.seq, exc.code, str(exc))
        except RandtError as exc:
            m.reject(scan.vehicle, scan.session, scan.seq, ErrorCode.REGISTRATION_FAILED, str(exc))
        return None

    def _track(self, scan: ScanHeader, result: ScanResult) -> str | None:
        """Whether the scan's pose may be answered (``None``) or the session is lost (why).

        A fallback's pose is the motion prediction, right only over a short gap: it is answered
        while the last match is at most ``fallback_horizon_s`` old (scan stamps). Past that the
        session is lost: no pose, nothing folded or offered to the graph, until
        :data:`VERIFY_MATCHES` consecutive scans match (the second matched from the first's
        prediction, within the matcher's correction gate: two agreeing registrations). A match
        the matcher found by relocalization (one global registration, :data:`RELOCALIZED`) is
        the first of those, never answered by itself: in a place that merely looks alike it can be
        tens of metres off (18 m, with 30 % inliers, where the map's town was swapped for
        another). The sweep that finds the track again is also checked against the map
        (service/agreement.py)."""
        info, horizon = self.info, self._manager.settings.fallback_horizon_s
        if result.status == "ok" and result.message == RELOCALIZED and not info.lost:
            log.warning("session %s/%s relocalized at scan %d: to be verified", *self.key, scan.seq)
            info.lost, info.verified_matches = True, 0
        if result.status == "fallback":
            info.verified_matches = 0
            since_ns = None if info.matched_stamp_ns is None else scan.stamp_ns - info.matched_stamp_ns
            if not info.lost and since_ns is not None and since_ns <= horizon * 1e9:
                return None
            if not info.lost:
                log.warning("session %s/%s lost its track at scan %d", *self.key, scan.seq)
            info.lost = True
            gap = "since it resumed" if since_ns is None else f"for {since_ns * 1e-9:.2f} s"
            return (
                f"lost: no match {gap} (a prediction is answered for {horizon:g} s at most); "
                f"poses resume after {VERIFY_MATCHES} consecutive matches"
            )
        info.matched_stamp_ns = scan.stamp_ns
        if not info.lost:
            return None
        info.verified_matches += 1
        if info.verified_matches < VERIFY_MATCHES:
            return f"lost: relocalizing, {info.verified_matches} of {VERIFY_MATCHES} consecutive matches"
        log.info("session %s/%s found its track again at scan %d", *self.key, scan.seq)
        info.lost, info.verified_matches = False, 0
        return None

    def _keep_resume_sweep(self, registered: Registered) -> None:
        """A matched sweep the matcher returned points of (for the graph or the map agreement
        check, every few sweeps) becomes the session's resume sweep, which the flusher saves
        (a reference: nothing is copied on this path)."""
        result, points = registered.result, registered.keyframe_xyz
        if points is None or result.status == "fallback" or len(points) < MIN_RESUME_POINTS:
            return
        self.resume_sweep = ResumeSweep(result.index, result.T_world_sensor, points)

    def _log_pose(self, scan: ScanHeader, result: ScanResult) -> bool:
        """Durable before acknowledged: the pose into the session's fsync'd log before it is
        published (and before the map holds its points); False when that failed (answered
        ``storage_error``, the session dropped to resume from the store)."""
        try:
            self._manager.store.append_pose(
                scan.vehicle,
                scan.session,
                PoseLogRecord(
                    index=result.index,
                    seq=scan.seq,
                    stamp_ns=scan.stamp_ns,
                    stamp_s=scan.stamp_ns * 1e-9,
                    pose=result.T_world_sensor,
                    status=result.status,
                ),
            )
        except (OSError, RandtError) as exc:
            self._storage_failed(scan, exc)
            return False
        return True

    def _fold_target(self) -> tuple[np.ndarray | None, str]:
        """``(correction, map)`` for the session's new map points: the pose graph's newest
        correction of the session (None: none) and the map they are folded into."""
        graph, info = self._manager.graph, self.info
        if graph is None:
            return None, info.map_name
        return graph.fold_target(info.vehicle, info.session, info.map_name)

    def _map_frame(self, seed_xyz: np.ndarray | None = None, prior: PosePrior | None = None) -> MapFrame:
        """Where this sweep's map points go (:class:`~randt.service.matchers.MapFrame`): the matcher
        moves them by the correction and sends only voxels it has not sent to this map's content
        (``seed_xyz``: :meth:`_map_seed`; ``prior``: a WGS84 prior placed in the map)."""
        C, fold_map = self._fold_target()
        grid = self.grid if fold_map == self.info.map_name else self._manager.map_grid(fold_map)
        return MapFrame((fold_map, *grid.content_token), C, seed_xyz, prior)

    def _map_seed(self, prior: PosePrior | None) -> np.ndarray | None:
        """For a session's first sweep with a prior: its map's points within
        :data:`MAP_SEED_REACH_M` of the prior, which the matcher places the sweep against
        (``None`` without a prior or when the map has too few there: the sweep goes at its prior)."""
        if prior is None:
            return None
        xy = np.asarray(prior.T_world_sensor, dtype=np.float64)[:2, 3]
        cloud = self.grid.points_in_bbox(xy - MAP_SEED_REACH_M, xy + MAP_SEED_REACH_M)
        return cloud.xyz.astype(np.float32) if len(cloud.xyz) >= MAP_SEED_MIN_POINTS else None

    def _queue_map_points(self, registered: Registered) -> str | None:
        """The scan's map points (none for a fallback) wait to be folded, into the map they go to
        and moved by the session's newest correction: the map follows the pose graph. The matcher
        moved them by the correction of when the sweep was sent; if the graph has corrected the
        session since, they are moved on by the difference.

        They wait first for the map agreement check (service/agreement.py): a sweep the matcher
        returned thinned points for is checked, and its verdict folds or drops the points held
        since the last check, its own included. Returns why the session is lost when its sweeps
        do not agree with its map (nothing is then held), else ``None``."""
        gate = self.gate
        C, fold_map = self._fold_target()
        checked = gate.enabled and registered.keyframe_xyz is not None
        if gate.disagreeing and not checked:
            gate.matched()
            return gate.lost_reason(self.info.map_name)
        if registered.map_xyz.shape[0]:
            points = (fold_map, registered.map_points_under(C), registered.map_intensity)
            self._unfolded.extend(gate.hold(points))
        if not gate.enabled:
            return None
        if not checked:
            gate.matched()
            return None
        assert registered.keyframe_xyz is not None
        grid = self.grid if fold_map == self.info.map_name else self._manager.map_grid(fold_map)
        T = registered.result.T_world_sensor if C is None else C @ registered.result.T_world_sensor
        was_lost = gate.disagreeing
        self._unfolded.extend(gate.check(grid, T, registered.keyframe_xyz))
        last = gate.last
        assert last is not None
        self.info.map_agreement, self.info.map_disagrees = last.share, gate.disagreeing
        if gate.disagreeing and not was_lost:
            self._manager.metrics.map_disagreements.inc()
            log.warning(
                "session %s/%s: scan %d disagrees with map %s (%.0f%% of %d points near it): lost",
                *self.key, registered.result.index, fold_map, 100 * last.share, last.checked,
            )  # fmt: skip
        elif was_lost and not gate.disagreeing:
            log.info("session %s/%s agrees with map %s again", *self.key, fold_map)
        return gate.lost_reason(self.info.map_name) if gate.disagreeing else None

    def _account(self, scan: ScanHeader, result: ScanResult, prior: PosePrior | None, lost: bool) -> None:
        """The session's counters, last figures and drift variance after a processed scan."""
        info = self.info
        info.n_scans += 1
        info.n_fallbacks += result.status == "fallback"
        info.n_lost += lost
        info.stamps_s.append(scan.stamp_ns * 1e-9)
        info.last_fitness = result.fitness
        info.last_status = result.status
        info.last_activity = time.monotonic()
        info.dirty = True
        if prior is not None:
            info.drift_var_m2 = float(np.trace(np.asarray(prior.covariance)[:3, :3]))
        elif np.all(np.isfinite(result.covariance[:3, :3])):
            info.drift_var_m2 += float(np.trace(result.covariance[:3, :3]))

    def _answer(self, job: _Job, result: ScanResult) -> None:
        """The pose message, published, or held until the session's first snapshot is on disk:
        a session's first save holds its frame, map and first keyframe, and its later logged poses
        are resumable only on top of it. It is written on its own thread while this one goes on
        matching (module docstring, Durable)."""
        scan, cov = job.scan, result.covariance
        answer = PoseMessage(
            vehicle=scan.vehicle,
            session=scan.session,
            seq=scan.seq,
            stamp_ns=scan.stamp_ns,
            pose=tuple(result.T_world_sensor.ravel().tolist()),
            fitness=float(result.fitness),
            inlier_ratio=float(result.inlier_ratio),
            converged=bool(result.converged),
            status=result.status,
            covariance=None if not np.all(np.isfinite(cov)) else tuple(cov.ravel().tolist()),
            latency_ms=0.0,  # set when it goes out
            map=self.info.map_name,
        )
        self._manager.metrics.registration_seconds.observe(result.time_s)
        if result.index != 0:
            self._publish(answer, job.received_ns)
            return
        with self._held_lock:
            self._first_saved = None
            self._held.append((answer, job.received_ns))
        self._first_save = threading.Thread(
            target=self._save_first, name=f"first-save-{scan.vehicle}-{scan.session}", daemon=True
        )
        self._first_save.start()

    def _offer_keyframe(self, scan: ScanHeader, registered: Registered, prior: PosePrior | None) -> None:
        """A keyframe's points (when the matcher returned some) to the pose graph of the session's
        map, with its prior's position as GNSS; a session without priors may join the shared map."""
        graph, kf = self._manager.graph, registered.keyframe_xyz
        if graph is None or not self._keyframe_wanted or kf is None or len(kf) < 10:
            return
        info, result = self.info, registered.result
        graph.offer(
            scan.vehicle,
            scan.session,
            map_name=info.map_name,
            seq=scan.seq,
            index=result.index,
            stamp_s=scan.stamp_ns * 1e-9,
            T_live=result.T_world_sensor,
            points=kf,
            intensity=registered.keyframe_intensity,
            gnss=self._gnss(scan, prior),
            join=self._manager.settings.default_map if info.frame == "session" else None,
        )

    def _gnss(self, scan: ScanHeader, prior: PosePrior | None) -> tuple[np.ndarray, np.ndarray] | None:
        """A keyframe's GNSS for the pose graph: its prior's position (in the session's map), or
        a ROS 2 robot's NavSatFix in the shared map's frame, which the session may join (the graph
        places it there by its fixes); ``None`` when the fix cannot be placed (logged once)."""
        if prior is not None:
            return prior.T_world_sensor[:3, 3], prior.covariance[:3, :3]
        if scan.gnss_fix is None:
            return None
        m = self._manager
        name = m.settings.default_map
        try:
            return m.projections.fix_in_map(name, m.map_grid(name), scan.gnss_fix)
        except BadMessageError as exc:
            if not self._fix_refused:
                log.warning("session %s/%s: its GNSS fixes are not used: %s", *self.key, exc)
            self._fix_refused = True
            return None

    def fold(self, *, release: bool = False) -> None:
        """Insert the map points waiting to be folded into the session's map, and mark the tiles
        that changed for the next save (the session thread, and the flusher before it saves).
        ``release`` (the session ends or merges its map): the points the map agreement check
        holds too, unless its last check disagreed (service/agreement.py).

        Folds are serialized (``_fold_lock``), so points enter the map in arrival order; the
        session's :attr:`lock` is held only to take the waiting points, not during the insert,
        so a fold by the flusher does not hold up the session's matching."""
        with self._fold_lock:
            with self.lock:
                batch, self._unfolded = self._unfolded + (self.gate.release() if release else []), []
                own_grid, own_map = self.grid, self.info.map_name
            # (a session without priors folds into the shared map once it joined it)
            for map_name in dict.fromkeys(name for name, _, _ in batch):
                part = [(x, i) for name, x, i in batch if name == map_name]
                grid = own_grid if map_name == own_map else self._manager.map_grid(map_name)
                xyz = np.concatenate([x for x, _ in part]) if len(part) > 1 else part[0][0]
                inten = None
                if any(i is not None for _, i in part):
                    inten = np.concatenate(
                        [np.zeros(len(x), np.float32) if i is None else i for x, i in part]
                    )
                changed = grid.insert(xyz, inten)
                if changed:
                    self._manager.mark_tiles_dirty(map_name, changed)

    def _publish(self, pose: PoseMessage, received_ns: int) -> None:
        """Send a durable pose, or hold it while the session's first snapshot is being written
        (:meth:`_save_first` sends it then, or answers ``storage_error`` if that save failed)."""
        with self._held_lock:
            if self._first_saved is None:
                self._held.append((pose, received_ns))
                return
            if self._first_saved:
                self._send(pose, received_ns)
                return
        self._refuse_not_durable(pose, "its first snapshot could not be saved")

    def _send(self, pose: PoseMessage, received_ns: int) -> None:
        m = self._manager
        latency_ms = (time.time_ns() - received_ns) * 1e-6
        self.info.last_latency_ms = latency_ms
        m.metrics.latency_seconds.observe(latency_ms * 1e-3)
        m.metrics.scans_processed.labels(pose.status).inc()
        m.outbox(pose.model_copy(update={"latency_ms": latency_ms}))

    def _save_first(self) -> None:
        """The first-save thread: write the session's first snapshot, then send the poses held
        meanwhile in order, or answer them ``storage_error`` (and abandon the session) if it
        could not be written."""
        saved = False
        try:
            saved = self._manager._save_session(self)
        finally:
            with self._held_lock:
                held, self._held = self._held, []
                self._first_saved = saved
                if saved:
                    for pose, received_ns in held:
                        self._send(pose, received_ns)
        if not saved:
            for pose, _ in held:
                self._refuse_not_durable(pose, "its first snapshot could not be saved")
            self.broken = True
            with self._cond:  # an idle worker wakes up to abandon the session
                self._cond.notify()

    def wait_first_save(self, timeout: float | None = None) -> bool:
        """Wait for the session's first snapshot (if it is being written); whether it is done."""
        thread = self._first_save
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)
            return not thread.is_alive()
        return True

    def _refuse_not_durable(self, pose: PoseMessage, why: str) -> None:
        """Answer a pose's scan ``storage_error`` instead (the session is abandoned)."""
        log.error("session %s/%s: scan %d not durable: %s", *self.key, pose.seq, why)
        self._manager.metrics.store_errors.inc()
        self.broken_answer = (
            ErrorCode.STORAGE_ERROR,
            "the service could not store this session's poses; it resumes from its stored state",
        )
        self._manager.reject(
            pose.vehicle,
            pose.session,
            pose.seq,
            ErrorCode.STORAGE_ERROR,
            f"the pose could not be made durable ({why}): not acknowledged",
        )
        self.broken = True

    def _storage_failed(self, scan: ScanHeader, exc: Exception) -> None:
        """A pose could not be made durable: answer ``storage_error`` (no pose) and abandon the
        session, so that its next scan resumes it from what the store holds."""
        log.error("session %s/%s: scan %d not durable: %s", *self.key, scan.seq, exc)
        self._manager.metrics.store_errors.inc()
        self.broken_answer = (
            ErrorCode.STORAGE_ERROR,
            "the service could not store this session's poses; it resumes from its stored state",
        )
        self._manager.reject(
            scan.vehicle,
            scan.session,
            scan.seq,
            ErrorCode.STORAGE_ERROR,
            f"the pose could not be made durable ({exc}): not acknowledged",
        )
        self.broken = True


@dataclass(frozen=True)
class DurableMap:
    """What the outside may see of a map: the tiles as last saved (every version in it is on
    disk, so it never goes back after a crash), with the live grid for its settings and cell
    geometry only (bbox and radius queries)."""

    name: str
    grid: TileGrid
    by_id: dict[str, Tile]

    @property
    def tile_size_m(self) -> int:
        return self.grid.tile_size_m

    @property
    def voxel_size_m(self) -> float:
        return self.grid.voxel_size_m

    def tiles(self) -> list[Tile]:
        """The saved tiles sorted by ``(ix, iy)``."""
        return sorted(self.by_id.values(), key=lambda t: (t.ix, t.iy))


class SessionManager:
    """Routes scans to session workers; owns the maps; saves to the store (module docstring)."""

    def __init__(
        self,
        settings: ServiceSettings,
        store: Store,
        outbox: Outbox,
        metrics: ServiceMetrics | None = None,
        executor: MatcherExecutor | None = None,
    ) -> None:
        self.settings = settings
        self.store = store
        if settings.map_origin is not None:  # before anything starts: a wrong one stops it, saying why
            name = settings.default_map
            MapProjections(store).give(name, name in store.list_maps(), GeoOrigin(*settings.map_origin))
        self.outbox = outbox
        self.metrics = metrics or ServiceMetrics()
        self.limits = WireLimits(max_points=settings.max_points, max_payload_bytes=settings.max_payload_bytes)
        self._lock = threading.RLock()
        self._flush_lock = threading.Lock()  # one flush at a time; map deletion waits for it
        self._workers: dict[tuple[str, str], SessionWorker] = {}
        # Sessions between leaving _workers and their final save: a scan for one is refused
        # (session_busy) rather than reopening it from an older saved state.
        self._closing: set[tuple[str, str]] = set()
        # Sessions an opener thread is opening (module docstring, Locking).
        self._opening: dict[tuple[str, str], _Opening] = {}
        self._openers: set[threading.Thread] = set()
        #: Running sessions at most (0: no limit); see ServiceSettings.max_sessions.
        self.max_sessions = settings.max_sessions
        if self.max_sessions < 0:
            self.max_sessions = SESSIONS_PER_CORE * (os.cpu_count() or 1)
        n_procs = settings.matcher_processes
        if n_procs < 0:
            cores = os.cpu_count() or 1
            n_procs = cores if cores > 1 else 0
        # (an executor given: e.g. bench/main_process.py's stand-in that answers at once)
        self.pool: MatcherExecutor | None = executor
        if executor is None and settings.executor == "ray":
            from randt.service.ray_executor import RayMatcherPool  # the ray extra

            self.pool = RayMatcherPool(settings.ray_address, settings.ray_transport)
        elif executor is None and n_procs > 0:
            self.pool = MatcherPool(n_procs)
        #: Admission by measured capacity (service/capacity.py); None: by max_sessions only.
        self.capacity: Capacity | None = None
        if settings.capacity_target > 0:
            # a Ray cluster's CPUs (they change); else this node's, or one core for in-process matchers
            cpus = getattr(self.pool, "cpus", None)
            matcher_cores: float | Callable[[], float] = (
                cpus if callable(cpus) else float(os.cpu_count() or 1) if self.pool is not None else 1.0
            )
            self.capacity = Capacity(
                cores=matcher_cores,
                shares_cores=cpus is None,
                target=settings.capacity_target,
                rate_hz=settings.session_rate_hz,
                sweep_cpu_s=settings.sweep_cpu_estimate_s,
                retry_after_s=settings.admission_retry_s,
            )
        #: The shared map's pose graph (service/graph.py); its process starts with the first keyframe.
        self.graph: ServiceGraph | None = (
            ServiceGraph(
                settings.fleet_map,
                outbox,
                self.metrics,
                geometry=MapGeometry(settings.tile_size_m, settings.map_voxel_m, 1),
                on_refold=self.refold_tiles,
                on_join=self._joined,
                keyframe_m=settings.graph_keyframe_m,
                queue_size=settings.graph_queue,
                refold_s=settings.graph_refold_s,
                yield_to_matchers=settings.executor == "local"
                if settings.graph_yield is None
                else settings.graph_yield,
                on_restart=self._graph_restarted,
                log_dir=Path(settings.data_dir) / GRAPH_DIRNAME,
            )
            if settings.graph
            else None
        )
        contents = store.load_all()  # a damaged map or session is reported and skipped, not fatal
        for problem in contents.problems:
            log.error("store: skipped %s %s: %s", problem.kind, problem.name, problem.message)
        self._records: dict[tuple[str, str], SessionRecord] = {
            key: loaded.record for key, loaded in contents.sessions.items()
        }
        self.maps: dict[str, TileGrid] = dict(contents.maps)
        #: Each map's geodetic origin, if it has one (service/georef.py).
        self.projections = MapProjections(store)
        #: Per map, the tiles as last saved: what HTTP, the queryable and tile updates serve.
        self._durable: dict[str, dict[str, Tile]] = {}
        self._digests: dict[tuple[str, str, int], str] = {}
        for name, grid in self.maps.items():
            tiles = grid.tiles()
            try:
                grid.version_floor = self._version_floor(name)
            except RandtError as exc:  # damaged: continue above every version the map holds
                log.error("%s", exc)
                grid.version_floor = max((t.version for t in tiles), default=0)
            self._durable[name] = {t.id: t for t in tiles}
        #: Tiles the store held at start (and when the graph process was last restarted): points of
        #: sessions the (in-memory) pose graph never saw, so it never re-folds them (refold_tiles).
        self._tiles_before_graph: dict[str, set[str]] = {
            name: set(g.tile_ids()) for name, g in self.maps.items()
        }
        self._dirty_tiles: dict[str, set[str]] = {}
        self._tiles_saved_at = time.monotonic()  # the flusher saves tiles every tile_save_interval_s
        #: Own maps of sessions that joined another map, merged into it: name -> (map, session).
        self._merged: dict[str, tuple[str, str]] = {}
        self._restore_counters()
        self.intake = Intake(
            self.handle,
            self._answer_intake_drop,
            workers=settings.intake_workers,
            max_scans=settings.intake_queue_scans,
            max_bytes=settings.intake_queue_bytes,
            total_bytes=settings.intake_total_bytes,
        )
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_loop, name="store-flusher", daemon=True)
        self._flusher.start()

    # -- intake (transport callback thread: enqueue only; service/intake.py) -----------------------
    def submit(self, key_vehicle: str, payload: bytes | Ros2Scan, received_ns: int | None = None) -> None:
        """Queue one scan payload published on ``randt/fleet/<key_vehicle>/scan`` (never blocks).

        The payload waits in ``key_vehicle``'s intake queue until an intake worker calls
        :meth:`handle` (service/intake.py). A ``key_vehicle`` that is not an id has no key to
        answer on: the scan is counted as rejected (``invalid_id``) and logged, not queued.
        """
        received_ns = time.time_ns() if received_ns is None else received_ns
        self.metrics.scans_received.inc()
        if not self.limits.id_ok(key_vehicle):
            self.reject(key_vehicle, UNKNOWN_ID, None, ErrorCode.INVALID_ID, "the key's vehicle is not an id")
            return
        if len(payload) > self.limits.max_payload_bytes:  # refused before queuing: O(1) and a bounded peek
            self.handle(key_vehicle, payload, received_ns)
            return
        self.intake.put(key_vehicle, payload, received_ns)

    def _answer_intake_drop(self, vehicle: str, payload: bytes | Ros2Scan, reason: str) -> None:
        """Answer a payload the intake dropped unread: ``dropped``, addressed by a bounded peek."""
        session, seq = self._peek(payload)
        self.metrics.scans_dropped.inc()
        self.reject(vehicle, session, seq, ErrorCode.DROPPED, reason, count=False)

    def _peek(self, payload: bytes | Ros2Scan) -> tuple[str, int | None]:
        """``(session, seq)`` of a payload that may not decode, to answer it on (never raises):
        a ROS 2 scan's are its publisher's; ours are read by a bounded peek."""
        if isinstance(payload, Ros2Scan):
            return payload.session, payload.seq
        _, session = peek_ids(payload, self.limits)
        return session or UNKNOWN_ID, peek_seq(payload)

    def _header(self, payload: bytes | Ros2Scan) -> ScanHeader:
        """A scan's header, its bodies not decoded (raises BadMessageError)."""
        if isinstance(payload, Ros2Scan):
            return ros2_scan_header(payload, self.limits)
        return decode_scan_header(payload, self.limits)

    def handle(self, key_vehicle: str, payload: bytes | Ros2Scan, received_ns: int) -> None:
        """Decode, validate and admit one scan (an intake worker's call; flow in the module docstring).

        Never waits for a store read or a matcher: a scan that opens a session is queued behind
        an ``_Opening`` placeholder and an opener thread does the opening.
        """
        try:
            scan = self._header(payload)  # the bodies: the matcher's
            if self._refused_for_capacity(scan, key_vehicle):  # (before its body costs anything)
                return
            if (scan.vehicle, scan.session) not in self._workers:
                # A scan that may open a session is decoded whole first (rare: once a session):
                # a body that does not decode never takes a slot, opens a session or reads the store.
                if isinstance(payload, Ros2Scan):
                    ros2_sweep_arrays(payload)
                elif scan.v == SCAN_V2:
                    decode_scan(payload, self.limits)
            if scan.vehicle != key_vehicle:
                raise BadMessageError(
                    f"vehicle: message says {scan.vehicle!r} but was published on {key_vehicle!r}'s key",
                    code=ErrorCode.INVALID_FIELD,
                )
        except BadMessageError as exc:
            session, seq = self._peek(payload)
            self.reject(key_vehicle, session, seq, exc.code, str(exc))
            return
        key = (scan.vehicle, scan.session)
        job = _Job(scan, received_ns, payload)
        dropped: _Job | None = None
        refusal: tuple[str, str] | tuple[str, str, float] | None = None
        if self.capacity is not None:
            self.capacity.arrived(key)
        with self._lock:
            worker = self._workers.get(key)
            opening = self._opening.get(key)
            record = self._records.get(key)
            if worker is not None:
                dropped = self._enqueue(worker, job)
            elif opening is not None:
                # The first scan opens the session (like a scan being processed); the others wait
                # as in a session queue, with a young session's overload policy.
                waiting = len(opening.jobs) - 1
                if waiting >= self.settings.queue_size:
                    k = 1 + drop_index(deque(list(opening.jobs)[1:]), n_processed=0)
                    dropped = opening.jobs[k]
                    del opening.jobs[k]
                opening.jobs.append(job)
            elif key in self._closing:
                refusal = (
                    ErrorCode.SESSION_BUSY,
                    "the session is being saved (closed or expired a moment ago): send the scan again",
                )
            elif record is not None and record.state == "closed":
                refusal = (
                    ErrorCode.SESSION_CLOSED,
                    f"session {scan.session!r} of vehicle {scan.vehicle!r} was closed: "
                    "publish under a new session id",
                )
            else:
                admitted = self._admit(key)
                if isinstance(admitted, tuple):
                    refusal = admitted
                else:
                    opening = self._opening[key] = _Opening(scan, deque([job]), evict=admitted)
                    opener = threading.Thread(
                        target=self._open, args=(key, opening), name=f"open-{key[0]}-{key[1]}", daemon=True
                    )
                    self._openers.add(opener)
                    opener.start()
        if refusal is not None:
            self.reject(scan.vehicle, scan.session, scan.seq, *refusal)
        if dropped is not None:
            self._answer_dropped(dropped)

    def _refused_for_capacity(self, scan: ScanHeader, key_vehicle: str) -> bool:
        """A scan that would open a session the node cannot carry is refused on its header alone
        (answered ``sessions_full`` with ``retry_after_s``): a vehicle refused at 10 Hz must cost
        no body decoding. :meth:`_admit` checks again under the lock."""
        key = (scan.vehicle, scan.session)
        if (
            self.capacity is None
            or scan.vehicle != key_vehicle
            or key in self._workers
            or key in self._opening
        ):
            return False
        why = self.capacity.refusal([*self._workers, *self._opening])
        if why is None:
            return False
        self.reject(
            scan.vehicle, scan.session, scan.seq, ErrorCode.SESSIONS_FULL, why, self.capacity.retry_after_s
        )
        return True

    def _enqueue(self, worker: SessionWorker, job: _Job) -> _Job | None:
        """Seq check and enqueue on a running session (under the manager lock); the job dropped."""
        scan, info = job.scan, worker.info
        if scan.seq == info.last_seq:
            self.reject(
                scan.vehicle,
                scan.session,
                scan.seq,
                ErrorCode.DUPLICATE_SEQ,
                f"seq {scan.seq} was already received for this session",
            )
            return None
        if scan.seq < info.last_seq:
            self.reject(
                scan.vehicle,
                scan.session,
                scan.seq,
                ErrorCode.OUT_OF_ORDER,
                f"seq {scan.seq} arrived after seq {info.last_seq}: scans must come in order",
            )
            return None
        info.last_seq = scan.seq
        info.last_activity = time.monotonic()
        dropped = worker.submit(job)
        self.metrics.queue_depth.labels(queue_label(scan.vehicle, scan.session)).set(worker.depth())
        return dropped

    def _answer_dropped(self, dropped: _Job) -> None:
        self.metrics.scans_dropped.inc()
        self.reject(
            dropped.scan.vehicle,
            dropped.scan.session,
            dropped.scan.seq,
            ErrorCode.DROPPED,
            f"dropped: the session's queue was full ({self.settings.queue_size} scans waiting): the "
            "service is behind and sheds this session's scans evenly until it catches up",
            count=False,
        )

    # -- admission (under the manager lock; module docstring, Admission) ---------------------------
    def _admit(self, key: tuple[str, str]) -> SessionWorker | tuple[str, str, float] | None:
        """May ``key`` open a session? ``None``: yes; a worker: yes, after that idle session gives
        up its slot (already out of the running set); ``(code, reason, retry_after_s)``: refused."""
        vehicle = key[0]
        evict: SessionWorker | None = None
        per_vehicle = self.settings.max_sessions_per_vehicle
        if per_vehicle > 0:
            mine = [w for k, w in self._workers.items() if k[0] == vehicle]
            n_mine = len(mine) + sum(1 for k in self._opening if k[0] == vehicle)
            if n_mine >= per_vehicle:
                evict = self._idlest(mine, self.settings.vehicle_slot_idle_s)
                if evict is None:
                    return (
                        ErrorCode.VEHICLE_SESSIONS_FULL,
                        f"vehicle {vehicle!r} runs its maximum of {per_vehicle} sessions "
                        "(RANDT_MAX_SESSIONS_PER_VEHICLE), none idle for "
                        f"{self.settings.vehicle_slot_idle_s:g} s: close one or send again later",
                        self.settings.vehicle_slot_idle_s,
                    )
        if evict is None and 0 < self.max_sessions <= len(self._workers) + len(self._opening):
            evict = self._idlest(list(self._workers.values()), self.settings.slot_idle_s)
            if evict is None:
                return (
                    ErrorCode.SESSIONS_FULL,
                    f"the service runs its maximum of {self.max_sessions} sessions (RANDT_MAX_SESSIONS), "
                    f"none idle for {self.settings.slot_idle_s:g} s: send again later, close a session "
                    "or add capacity",
                    self.settings.slot_idle_s,
                )
        if self.capacity is not None:  # before the session costs anything (module docstring)
            why = self.capacity.refusal(
                [*self._workers, *self._opening], exclude=() if evict is None else (evict.key,)
            )
            if why is not None:
                return (ErrorCode.SESSIONS_FULL, why, self.capacity.retry_after_s)
        if evict is not None:
            log.info(
                "session %s/%s gives its slot to %s/%s (idle %.1f s): saved as expired",
                *evict.key,
                *key,
                time.monotonic() - evict.info.last_activity,
            )
            self._detach(evict.key)
        return evict

    def _idlest(self, candidates: list[SessionWorker], idle_s: float) -> SessionWorker | None:
        """The running session idle longest, if one has been idle for ``idle_s``: nothing
        queued, not matching, no scan received for that long."""
        limit = time.monotonic() - idle_s
        idle = [
            w
            for w in candidates
            if w.depth() == 0
            and not w.lock.locked()
            and w.info.last_activity <= limit
            and w.key not in self._closing
        ]
        return min(idle, key=lambda w: w.info.last_activity, default=None)

    def _open(self, key: tuple[str, str], opening: _Opening) -> None:
        """Opener thread: free an evicted slot, open the session outside the lock, then hand it the
        scans that waited behind the placeholder (seq-checked now that its last seq is known)."""
        try:
            if opening.evict is not None:
                self._finish_close(opening.evict, "expired")
            worker: SessionWorker | None = None
            error: tuple[str, str] | None = None
            try:
                worker = self._open_session(opening.first)
            except BadMessageError as exc:
                error = (exc.code, str(exc))
            except RandtError as exc:
                error = (ErrorCode.SESSION_ERROR, str(exc))
            except Exception:  # a bug: the scans still get their answer
                log.exception("opening session %s/%s failed", *key)
                error = (ErrorCode.INTERNAL_ERROR, "internal error while opening the session (logged)")
            dropped: list[_Job] = []
            with self._lock:
                del self._opening[key]
                jobs = list(opening.jobs)
                opening.jobs.clear()
                if worker is not None:
                    self._workers[key] = worker
                    self.metrics.sessions_active.set(len(self._workers))
                    worker.info.last_activity = time.monotonic()
                    for job in jobs:
                        gone = self._enqueue(worker, job)
                        if gone is not None:
                            dropped.append(gone)
            if error is not None:
                for job in jobs:
                    self.reject(job.scan.vehicle, job.scan.session, job.scan.seq, *error)
            for job in dropped:
                self._answer_dropped(job)
        finally:
            opening.done.set()
            with self._lock:
                self._openers.discard(threading.current_thread())

    def reject(
        self,
        vehicle: str,
        session: str,
        seq: int | None,
        code: str,
        reason: str,
        retry_after_s: float | None = None,
        *,
        count: bool = True,
    ) -> None:
        """Answer one scan with an error (``code``: an :class:`~randt.wire.codes.ErrorCode`; a refusal
        that passes says when to send again, ``retry_after_s``) on its vehicle's error key and
        count it."""
        if count:
            self.metrics.scans_rejected.labels(code).inc()
        if not self.limits.id_ok(vehicle):
            # No valid key to answer on (randt/fleet/<vehicle>/error): counted and logged only.
            log.warning(
                "rejected a scan from an unaddressable vehicle id %r: %s: %s", vehicle[:40], code, reason
            )
            return
        if not self.limits.id_ok(session):
            session = UNKNOWN_ID
        w = self._workers.get((vehicle, session))  # no lock: reject runs on the callback's thread too
        if w is not None:
            w.info.n_errors += 1
        self.outbox(
            ErrorMessage(
                vehicle=vehicle,
                session=session,
                seq=seq,
                code=code,
                reason=reason,
                retry_after_s=retry_after_s,
            )
        )

    def _open_session(self, scan: ScanHeader) -> SessionWorker:
        key = (scan.vehicle, scan.session)
        state: dict[str, np.ndarray] | None = None
        record = self._records.get(key)
        if record is not None and record.state == "closed":
            # Its trajectory and state are on disk; reopening would overwrite them.
            raise BadMessageError(
                f"session {scan.session!r} of vehicle {scan.vehicle!r} was closed: "
                "publish under a new session id",
                code=ErrorCode.SESSION_CLOSED,
            )
        if record is not None and record.state in ("active", "expired"):
            # Active: the service restarted. Expired: the vehicle paused longer than the idle
            # expiry and came back. Either way the session resumes where it stopped.
            # The snapshot plus the poses logged since (Store.load_session): every pose published.
            stored, stamps, poses, state = self.store.load_session(*key)
            assert record.map is not None  # the service saves every session with its map
            # The matcher resumes from its snapshot (its trajectory from the store's), brought to
            # the last published pose (extend_state_dict: poses, velocity and stamp; the keyframes
            # stay the snapshot's).
            # A sweep saved since the snapshot, at its logged pose, joins its keyframes: the model
            # then reaches where the vehicle is (the snapshot's may end 30 m behind, too far to match).
            state = with_trajectory(state, poses)
            n_snapshot = len(state.get("poses", ()))
            sweep = self._resume_sweep(key, n_snapshot, poses)
            state = extend_state_dict(state, poses, stamps, settings=self.settings.session_matcher())
            if sweep is not None:
                state = with_keyframe(state, sweep.pose, sweep.points)
                log.info("session %s/%s: sweep %d joins its snapshot's keyframes", *key, sweep.pose_index)
            info = SessionState(
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
            )
            log.info("session %s/%s resumed at seq %d (%d poses)", *key, info.last_seq, len(poses))
        else:
            # A new session (or one whose first save never completed: nothing was acknowledged).
            self.store.reset_pose_log(*key)
            in_map = scan.prior_pose() is not None or scan.geo_prior is not None
            map_name = self.settings.default_map if in_map else session_map_name(scan.vehicle, scan.session)
            info = SessionState(scan.vehicle, scan.session, map_name, "map" if in_map else "session")
        grid = self.map_grid(info.map_name)
        matcher: SessionMatcher
        settings = self.settings
        session_matcher = settings.session_matcher()
        if self.pool is not None:
            matcher = self.pool.open(key, state or None, grid, session_matcher, settings.registration)
        else:
            local = LocalMatcher(session_matcher, settings.registration)
            if state:
                local.load_state_dict(state)
            matcher = local
        # Called on an opener thread without the manager lock; _open installs the worker.
        return SessionWorker(info, matcher, grid, self)

    # -- maps and persistence -----------------------------------------------------------------
    def prior_in_map(self, scan: ScanHeader) -> PosePrior | None:
        """The scan's prior in the map frame: its ``prior``, or its ``geo_prior`` placed in the
        shared map through that map's geodetic origin (service/georef.py; raises
        :class:`~randt.core.errors.BadMessageError` ``invalid_prior`` when it cannot be)."""
        if scan.geo_prior is None:
            return prior_of(scan)
        name = self.settings.default_map
        return self.projections.prior_in_map(name, self.map_grid(name), scan.geo_prior)

    def map_grid(self, map_name: str) -> TileGrid:
        """The tiles of ``map_name``, an empty map with the settings' sizes if it is new."""
        with self._lock:
            grid = self.maps.get(map_name)
            if grid is None:
                grid = self.maps[map_name] = TileGrid(
                    tile_size_m=self.settings.tile_size_m, voxel_size_m=self.settings.map_voxel_m
                )
                grid.version_floor = self._version_floor(map_name)
                self._durable[map_name] = {}
            return grid

    def _version_floor(self, map_name: str) -> int:
        """The store's version floor of ``map_name`` (a deleted map's highest version)."""
        try:
            return self.store.version_floor(map_name)
        except (OSError, RandtError) as exc:
            # Unreadable: versions from 1 could repeat a deleted map's; refuse rather than lie.
            raise RandtError(f"map {map_name}: cannot read its version floor: {exc}") from exc

    def fold_map(self, vehicle: str, session: str) -> str | None:
        """The map a running session's points go into (the shared map it joined, or its own);
        ``None`` when the session is not running."""
        with self._lock:
            w = self._workers.get((vehicle, session))
            return None if w is None else (w.info.joined_map or w.info.map_name)

    def durable_map(self, map_name: str) -> DurableMap | None:
        """The map as last saved (:class:`DurableMap`), ``None`` if there is no such map."""
        with self._lock:
            grid = self.maps.get(map_name)
            if grid is None:
                return None
            return DurableMap(map_name, grid, dict(self._durable.get(map_name, {})))

    def durable_maps(self) -> dict[str, DurableMap]:
        """Every map as last saved, by name."""
        with self._lock:
            return {n: DurableMap(n, g, dict(self._durable.get(n, {}))) for n, g in self.maps.items()}

    def tile_digest(self, map_name: str, tile: Tile) -> str:
        """:func:`tile_digest` of a tile, cached by ``(map, tile, version)`` (versions never repeat)."""
        digest = self._cached_digest(map_name, tile)
        if digest is None:
            digest = tile_digest(tile)
            self._remember_digest(map_name, tile, digest)
        return digest

    def _cached_digest(self, map_name: str, tile: Tile) -> str | None:
        with self._lock:
            return self._digests.get((map_name, tile.id, tile.version))

    def _remember_digest(self, map_name: str, tile: Tile, digest: str) -> None:
        with self._lock:
            if len(self._digests) > 100_000:
                self._digests.clear()
            self._digests[(map_name, tile.id, tile.version)] = digest

    def forget_empty_map(self, map_name: str) -> None:
        """Drop ``map_name`` if it holds no tile and no session uses it (a frame left unused)."""
        with self._lock:
            grid = self.maps.get(map_name)
            in_use = any(w.info.map_name == map_name for w in self._workers.values())
            if (
                grid is not None
                and not grid.tile_ids()
                and not in_use
                and map_name != self.settings.default_map
            ):
                del self.maps[map_name]

    def refold_tiles(
        self, map_name: str, tile_ids: list[str], xyz: np.ndarray, intensity: np.ndarray
    ) -> None:
        """Replace tiles of ``map_name`` by the pose graph's re-fold of them (its keyframes'
        points at their optimized poses, equalized in the graph process: service/graph.py);
        saved and published by the next flush like any change. Tiles the store held when the
        service started are left as they are (the graph never saw their points)."""
        with self._lock:
            grid = self.maps.get(map_name)
            frozen = self._tiles_before_graph.get(map_name, set())
        if grid is None:
            return
        wanted = [t for t in tile_ids if t not in frozen]
        changed = grid.refold(wanted, xyz, intensity)
        if changed:
            self.metrics.graph_tiles_refolded.inc(len(changed))
            self.mark_tiles_dirty(map_name, changed)

    def _graph_restarted(self) -> None:
        """The pose graph process was started again with an empty graph (service/graph.py): the
        tiles made so far hold points of keyframes it never saw, so it no longer re-folds them,
        as after a restart of the service."""
        with self._lock:
            for name, grid in self.maps.items():
                self._tiles_before_graph.setdefault(name, set()).update(grid.tile_ids())

    def _joined(self, vehicle: str, session: str, map_name: str, T_map_session: np.ndarray) -> None:
        """The pose graph placed a session without priors into ``map_name`` (service/graph.py):
        from now on its points fold there, and its own map is merged in and removed."""
        with self._lock:
            w = self._workers.get((vehicle, session))
            own = session_map_name(vehicle, session)
            if w is None and own not in self.maps:  # the graph's log taken again after a restart:
                self._merged.setdefault(own, (map_name, f"{vehicle}/{session}"))  # merged before it
        if w is not None:
            w.info.joined_map = map_name
        log.info(
            "session %s/%s joined map %s at x %.2f y %.2f z %.2f m",
            vehicle,
            session,
            map_name,
            *T_map_session[:3, 3],
        )
        if w is not None and w.info.map_name != map_name:
            try:
                self._merge_map(w, map_name, T_map_session)
            except (OSError, RandtError):  # the own map stays; nothing is lost
                self.metrics.store_errors.inc()
                log.exception("merging map %s into %s failed", w.info.map_name, map_name)

    def _merge_map(self, w: SessionWorker, into: str, T_into_own: np.ndarray) -> None:
        """Merge the session's own map into the map it joined, and remove it.

        Its tiles' points, moved by ``T_into_own``, are inserted into ``into`` (equalized like
        any insert: where ``into`` already holds a voxel, its point stays); the graph's next
        re-fold then replaces the tiles its keyframes touch by their points at their optimized
        poses. The own map is deleted from memory and the store, its highest version kept as
        the floor of any later map of that name (a restarted session recreates it until it joins
        again); ``GET /maps/<own>`` says where it went (:meth:`merged_into`). A map another
        running session also uses is left alone."""
        own = w.info.map_name
        w.fold(release=True)  # its points still waiting for the own map go in first
        with self._flush_lock:  # no flush saves the own map while it goes
            with self._lock:
                grid = self.maps.get(own)
                shared = any(
                    x is not w and own in (x.info.map_name, x.info.joined_map) for x in self._workers.values()
                )
            if grid is None or shared or own == self.settings.default_map:
                return
            tiles = grid.tiles()
            if tiles:
                xyz = np.concatenate([t.points for t in tiles]).astype(np.float64)
                moved = (xyz @ T_into_own[:3, :3].T + T_into_own[:3, 3]).astype(np.float32)
                changed = self.map_grid(into).insert(moved, np.concatenate([t.intensity for t in tiles]))
                if changed:
                    self.mark_tiles_dirty(into, changed)
            floor = max([grid.version_floor, *(t.version for t in tiles)])
            self.store.delete_map(own, version_floor=floor)
            with self._lock:
                if self.maps.get(own) is grid:
                    del self.maps[own]
                self._durable.pop(own, None)
                self._dirty_tiles.pop(own, None)
                self._merged[own] = (into, f"{w.info.vehicle}/{w.info.session}")
        log.info("map %s merged into %s (%d tiles) and removed", own, into, len(tiles))

    def merged_into(self, map_name: str) -> tuple[str, str] | None:
        """``(map, session)`` when ``map_name`` was merged into ``map`` as ``session`` joined it
        (since this service started), else None."""
        with self._lock:
            return self._merged.get(map_name)

    def mark_tiles_dirty(self, map_name: str, tile_ids: list[str]) -> None:
        with self._lock:
            self._dirty_tiles.setdefault(map_name, set()).update(tile_ids)

    def flush(self, *, tiles: bool = True) -> None:
        """Save changed sessions (and, with ``tiles``, dirty tiles, publishing their updates),
        expire idle sessions."""
        with self._flush_lock:
            self._flush(tiles=tiles)
            self._save_counters()

    def _flush(self, *, tiles: bool = True) -> None:
        with self._lock:
            workers = list(self._workers.values())
        self._save_resume_sweeps(workers)  # first: small, and what a resume after a crash needs
        if tiles:
            self._save_tiles(workers)
        now = time.monotonic()
        for w in workers:
            if self._snapshot_due(w, now):
                self._save_session(w)
            if w.depth() == 0 and now - w.info.last_activity > self.settings.idle_expiry_s:
                self.close(*w.key, state="expired")

    def _save_resume_sweeps(self, running: list[SessionWorker]) -> None:
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

    def _resume_sweep(self, key: tuple[str, str], n_snapshot: int, poses: np.ndarray) -> ResumeSweep | None:
        """The session's saved resume sweep when it is newer than its snapshot and its pose is
        the one its log holds (else None: a sweep of an older life of the session id)."""
        sweep = self.store.load_resume_sweep(*key)
        if sweep is None or not n_snapshot <= sweep.pose_index < len(poses):
            return None
        if not np.allclose(sweep.pose, poses[sweep.pose_index], atol=1e-6):
            log.warning("session %s/%s: its resume sweep is not at its logged pose: not used", *key)
            return None
        return sweep

    def _save_tiles(self, running: list[SessionWorker]) -> None:
        """Save every dirty tile (after the sessions fold what they hold) and publish it."""
        self._tiles_saved_at = time.monotonic()
        for w in running:  # what sessions that were behind processed goes into this save
            w.fold()
        with self._lock:
            dirty, self._dirty_tiles = self._dirty_tiles, {}
        for map_name, ids in dirty.items():
            grid = self.maps.get(map_name)
            if grid is None:  # deleted since its tiles changed
                continue
            snapshot = grid.tiles()  # what is written, then served: one consistent set
            try:
                written = self.store.save_tiles(map_name, grid, sorted(ids), tiles=snapshot)
                self.metrics.tiles_written.inc(len(ids))
            except (OSError, ValueError, RandtError):
                self.metrics.store_errors.inc()
                log.exception("saving %d tiles of map %s failed", len(ids), map_name)
                with self._lock:
                    self._dirty_tiles.setdefault(map_name, set()).update(ids)
                continue  # nothing of it is served before it is on disk
            on_disk = set(written)
            saved = [t for t in snapshot if t.id in on_disk]
            with self._lock:
                if self.maps.get(map_name) is grid:  # not deleted meanwhile
                    durable = self._durable.setdefault(map_name, {})
                    # A tile changed after this flush took its dirty set but before the snapshot
                    # is dirty again: the next flush saves the same version once more. Publish
                    # each version once (a client sees every tile's versions strictly increase).
                    saved = [t for t in saved if t.id not in durable or t.version > durable[t.id].version]
                    durable.update({t.id: t for t in saved})
            for tile in saved:
                self.outbox(self.tile_message(map_name, tile))

    def tile_message(self, map_name: str, tile: Tile) -> TileUpdateMessage:
        """The :class:`~randt.wire.messages.TileUpdateMessage` of a saved tile, with its digest (which
        its ETag names too: computed once, cached). The grid checked its points when they were
        inserted, so the message is built from its table without checking them again."""
        message = tile_update_from_table(
            map_name,
            tile.ix,
            tile.iy,
            tile.version,
            tile.xyzi,
            (tile.bounds.min_xyz, tile.bounds.max_xyz),
            self._cached_digest(map_name, tile),
        )
        if message.digest is not None:
            self._remember_digest(map_name, tile, message.digest)
        return message

    def _snapshot_due(self, w: SessionWorker, now: float) -> bool:
        """Whether a running session's snapshot is due (module docstring, Snapshots): it changed,
        and its last one is ``snapshot_interval_s`` old or ``snapshot_distance_m`` away."""
        info = w.info
        if not info.dirty:
            return False
        if now - info.snapshot_at >= self.settings.snapshot_interval_s:
            return True
        reach, poses = self.settings.snapshot_distance_m, w.matcher.poses
        if reach <= 0 or info.snapshot_xyz is None or not poses:
            return False
        return bool(np.linalg.norm(poses[-1][:3, 3] - info.snapshot_xyz) >= reach)

    def _save_session(self, w: SessionWorker, state: RecordState | None = None) -> bool:
        """Write a session's snapshot; whether the store now holds it (False: not saved).

        Its cost does not grow with the session's length: the matcher state comes without the
        trajectory, and only the poses since the last snapshot are handed to the store (which has
        them in its log already and appends them to ``trajectory.tum``)."""
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
            with self._lock:
                self._records[w.key] = record
            info.saved_scans = max(info.saved_scans, n)
            info.snapshot_at, info.snapshot_xyz = time.monotonic(), position
        except (OSError, ValueError, RandtError):
            self.metrics.store_errors.inc()
            log.exception("saving session %s/%s failed", *w.key)
            info.dirty = True
            return False
        return True

    def delete_map(self, map_name: str) -> int:
        """Delete a map from memory and the store; returns how many tiles it held.

        Raises
        ------
        NotFoundError
            No map of that name is loaded.
        MapInUseError
            A running session folds its scans into the map (close those sessions first).
        UnavailableError
            Its pose graph's log could not be rewritten (nothing was deleted).
        """
        with self._flush_lock, self._lock:
            users = sorted(
                f"{w.info.vehicle}/{w.info.session}"
                for w in self._workers.values()
                if map_name in (w.info.map_name, w.info.joined_map)
            )
            if users:
                raise MapInUseError(
                    f"map {map_name!r} is in use by {len(users)} running session(s) "
                    f"({', '.join(users[:5])}): close them first"
                )
            grid = self.maps.get(map_name)
            if grid is None:
                raise NotFoundError(f"map {map_name!r} not found", resource="map", ident=map_name)
            n_tiles = len(grid)
            if self.graph is not None:  # its pose graph first: a restart must not bring it back
                try:
                    self.graph.forget_map(map_name)
                except RandtError as exc:
                    raise UnavailableError(f"map {map_name!r} not deleted: its pose graph: {exc}") from exc
            # Its highest version becomes the floor of a later map of the same name (first).
            floor = max([grid.version_floor, *(t.version for t in grid.tiles())])
            self.store.delete_map(map_name, version_floor=floor)
            del self.maps[map_name]
            self._durable.pop(map_name, None)
            self._dirty_tiles.pop(map_name, None)
            self.projections.forget(map_name)
        log.info("map %s deleted (%d tiles)", map_name, n_tiles)
        return n_tiles

    def close(self, vehicle: str, session: str, *, state: RecordState = "closed") -> bool:
        """Finish a session: process what is queued, save it, stop its worker. False if unknown.

        A session being opened is closed once open (this waits for the opening)."""
        with self._lock:
            opening = self._opening.get((vehicle, session))
        if opening is not None:
            opening.done.wait(120)
        with self._lock:
            w = self._detach((vehicle, session))
        if w is None:
            return False
        self._finish_close(w, state)
        return True

    def _detach(self, key: tuple[str, str]) -> SessionWorker | None:
        """Take a session out of the running set into ``_closing`` (under the manager lock)."""
        w = self._workers.pop(key, None)
        self.metrics.sessions_active.set(len(self._workers))
        if w is not None:
            self._closing.add(w.key)
        return w

    def _finish_close(self, w: SessionWorker, state: RecordState) -> None:
        """Drain, save and stop a detached session (no manager lock held: it waits on the worker)."""
        vehicle, session = w.key
        try:
            w.stop(drain=True)
            w.fold(release=True)
            self._save_session(w, state=state)
        finally:
            with self._lock:
                self._closing.discard(w.key)
        w.matcher.close()
        with contextlib.suppress(KeyError):  # a closed session's queue is no longer a time series
            self.metrics.queue_depth.remove(queue_label(vehicle, session))

    def _flush_loop(self) -> None:
        while not self._stop.wait(self.settings.flush_interval_s):
            due = time.monotonic() - self._tiles_saved_at >= self.settings.tile_save_s - 1e-3
            try:
                self.flush(tiles=due)
                self._measure_capacity()
            except Exception:  # keep flushing whatever one failure was
                log.exception("flush failed")

    def _measure_capacity(self) -> None:
        """The service process's own CPU per sweep sampled, ended sessions forgotten, and the
        capacity's figures to ``/metrics`` (the flusher, every flush)."""
        if self.capacity is None:
            return
        self.capacity.service_sample(graph_cpu_s=0.0 if self.graph is None else self.graph.cpu_s())
        with self._lock:
            running = [*self._workers, *self._opening]
        self.capacity.forget(running)
        f, m = self.capacity.figures(running), self.metrics
        m.capacity_cores.set(f.cores)
        m.capacity_load.set(f.load)
        m.capacity_sessions_more.set(f.sessions_more)
        m.capacity_sweep_cpu_seconds.set(f.sweep_cpu_s)
        m.capacity_service_cpu_seconds.set(f.service_cpu_s)

    def saturated(self) -> bool:
        """Whether the node is past what admission may fill (the running sessions' measured load
        above 1, :class:`~randt.service.capacity.CapacityFigures`; always without capacity admission):
        only then does a session that is behind let its keyframe model lag (:data:`BEHIND_DEPTH`).
        Within capacity a backlog clears by itself, and a session whose model never lags gets the
        offline matcher's poses to the digit."""
        f = self.capacity_figures()
        return f is None or f.load > 1.0

    def capacity_figures(self) -> CapacityFigures | None:
        """The node's capacity as measured now (``/status``), or None without capacity admission."""
        if self.capacity is None:
            return None
        with self._lock:
            running = [*self._workers, *self._opening]
        return self.capacity.figures(running)

    def stop(self) -> None:
        """Drain the intake and every session, save everything, stop the flusher (SIGTERM path)."""
        self._stop.set()
        self.intake.stop()
        self.wait_openings(60)
        self._flusher.join(10)
        with self._lock:
            workers = list(self._workers.values())
        for w in workers:
            w.stop(drain=True)
        self.flush()
        for w in workers:
            self._save_session(w)
        if self.pool is not None:
            self.pool.close()
        if self.graph is not None:
            self.graph.close()

    # -- status ---------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        """Whether the manager accepts scans and its flusher thread is alive (a readiness check)."""
        return not self._stop.is_set() and self._flusher.is_alive()

    @property
    def matchers_warm(self) -> bool:
        """Whether the matcher processes have loaded their compiled kernels (always, without a
        pool). Scans are accepted before: the first ones wait for the warm-up."""
        return self.pool is None or self.pool.ready

    def wait_matchers(self, timeout: float | None = None) -> bool:
        """Wait until :attr:`matchers_warm` (None: as long as it takes); whether it became so."""
        return self.pool is None or self.pool.wait_ready(timeout)

    def wait_openings(self, timeout: float | None = None) -> bool:
        """Wait until no session is being opened; whether that happened in time."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            with self._lock:
                pending = list(self._opening.values())
            if not pending:
                return True
            for opening in pending:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                opening.done.wait(left)

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Wait until the intake is empty and no session is being opened (tests, shutdown)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if not self.intake.wait_idle(deadline - time.monotonic()):
                return False
            if not self.wait_openings(max(0.0, deadline - time.monotonic())):
                return False
            if not self.intake.depths():
                return True
        return False

    def opening(self) -> list[tuple[str, str]]:
        """Sessions being opened right now (``(vehicle, session)``)."""
        with self._lock:
            return list(self._opening)

    def sessions(self) -> list[SessionState]:
        with self._lock:
            return [w.info for w in self._workers.values()]

    def worker(self, vehicle: str, session: str) -> SessionWorker | None:
        with self._lock:
            return self._workers.get((vehicle, session))

    def queue_depths(self) -> dict[str, int]:
        with self._lock:
            return {f"{k[0]}/{k[1]}": w.depth() for k, w in self._workers.items()}

    def records(self) -> dict[tuple[str, str], SessionRecord]:
        """The stored record of every session known to the store (a copy; running ones as last saved)."""
        with self._lock:
            return dict(self._records)

    def trajectory(self, vehicle: str, session: str) -> tuple[np.ndarray, np.ndarray] | None:
        """``(stamps_s (N,), poses (N, 4, 4))`` of a running session, or ``None`` if it is not running.

        Read without the worker's lock (which is held while the matcher runs, up to a matcher
        warm-up): both lists only grow, one entry per scan in the same order, so their common
        prefix belongs to the same scans.
        """
        w = self.worker(vehicle, session)
        if w is None:
            return None
        pose_list = list(w.matcher.poses)  # copies of append-only lists (atomic under the GIL)
        stamp_list = list(w.info.stamps_s)
        n = min(len(pose_list), len(stamp_list))
        poses = np.array(pose_list[:n], dtype=np.float64).reshape(-1, 4, 4)
        stamps = np.array(stamp_list[:n], dtype=np.float64)
        return stamps, poses

    def stored_trajectory(self, vehicle: str, session: str) -> tuple[np.ndarray, np.ndarray]:
        """``(stamps_s (N,), poses (N, 4, 4))`` of a session as the store's commit record holds them.

        Raises
        ------
        NotFoundError
            The store holds no readable trajectory of it (never saved, deleted, damaged);
            ``resource`` is ``"session"``, ``ident`` ``"<vehicle>/<session>"``.
        """
        try:
            loaded = self.store.load_session(vehicle, session)
        except (RandtError, OSError, ValueError) as exc:
            sid = f"{vehicle}/{session}"
            raise NotFoundError(
                f"session {sid!r} has no readable trajectory: {exc}", resource="session", ident=sid
            ) from exc
        return np.asarray(loaded.stamps, dtype=float), np.asarray(loaded.poses, dtype=float).reshape(-1, 4, 4)

    def close_stored(self, vehicle: str, session: str) -> SessionRecord | None:
        """Mark a stored session that has no running worker ``closed``; ``None`` if it is not stored.

        A session restored as ``active`` after a restart has no worker until its next scan; this
        closes it without loading its matcher.
        """
        with self._lock:
            if (vehicle, session) in self._workers or (vehicle, session) not in self._records:
                return None
        record = self.store.mark_session(vehicle, session, "closed")  # file I/O: outside the lock
        with self._lock:
            self._records[(vehicle, session)] = record
        return record

    # -- counters that outlive a restart (DATA/counters.json) -------------------------------------
    def _restore_counters(self) -> None:
        """Start the scan counters from the totals the store kept (a missing file: from zero)."""
        totals = load_counters(self.store.data_dir)
        if totals:
            self.metrics.restore(totals)
            received = int(totals.get("scans_received", {}).get("", 0))
            log.info("counters restored: %d scans received so far", received)
        self._saved_counters = self.metrics.totals()

    def _save_counters(self) -> None:
        """Write the counters' totals when they changed (the flusher, and the last flush at stop)."""
        totals = self.metrics.totals()
        if totals == self._saved_counters:
            return
        try:
            save_counters(self.store.data_dir, totals)
            self._saved_counters = totals
        except OSError:
            self.metrics.store_errors.inc()
            log.exception("saving the counters failed")


def queue_label(vehicle: str, session: str) -> str:
    """The ``session`` label of a session's queue-depth gauge: ``<vehicle>/<session>``."""
    return f"{vehicle}/{session}"


def tile_message(map_name: str, grid: TileGrid, tile_id: str) -> TileUpdateMessage:
    """The current :class:`~randt.wire.messages.TileUpdateMessage` of one tile of a grid (offline use;
    the service publishes saved tiles only: :meth:`SessionManager.tile_message`)."""
    tile = grid.get(tile_id)
    return tile_update_from_arrays(map_name, tile.ix, tile.iy, tile.version, tile.points, tile.intensity)


def tile_digest(tile: Tile) -> str:
    """The digest of a tile's content: :func:`randt.wire.messages.points_digest` of its float32
    ``x y z intensity`` table, as its tile update carries it and its ETag names it."""
    return points_digest(np.ascontiguousarray(tile.xyzi, dtype="<f4").tobytes())


#: Until a session has processed this many scans, overload drops its newest waiting scan rather
#: than shedding evenly (module docstring, Overload policy).
YOUNG_SESSION_SCANS = 3


def drop_index(
    queue: deque[_Job], *, n_processed: int, arriving_ns: int | None = None, taken_ns: int | None = None
) -> int:
    """Which waiting job the overload policy drops to make room for one arriving (module
    docstring, Overload policy): while the session has processed fewer than
    :data:`YOUNG_SESSION_SCANS` scans, the newest waiting one; after that, the one whose removal
    leaves the shortest gap between the scans around it (the scan taken last for matching,
    ``taken_ns``, before the first; the arriving one, ``arriving_ns``, after the last), the
    oldest of equals. Repeated, this sheds evenly (every second scan, then every third...), so
    the gaps the matcher predicts over stay as short as the session's share of the cores allows,
    where dropping the oldest left one gap as long as the stall that filled the queue."""
    n = len(queue)
    if n_processed < YOUNG_SESSION_SCANS:
        return n - 1
    stamps = [job.scan.stamp_ns for job in queue]
    left = [stamps[0] if taken_ns is None else taken_ns, *stamps[:-1]]
    right = [*stamps[1:], stamps[-1] if arriving_ns is None else arriving_ns]
    gaps = [r - lo for lo, r in zip(left, right, strict=True)]  # (at most queue_size of them)
    return gaps.index(min(gaps))
