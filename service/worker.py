"""One session's worker: its bounded queue, its thread, its matcher, and the stages one scan
passes through, each answered exactly once (``docs/architecture.md``, "One scan, through the
service").

The worker sees only the collaborators it uses (:class:`WorkerServices`): the live maps, the
store's pose log, the answers, the pose graph, the capacity; never the session manager.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from randt.core.errors import BadMessageError, NotRelocalizedError, RandtError
from randt.core.odometry import MAP_SEED_MIN_POINTS, MATCHED_TO_MAP, PosePrior, ScanResult
from randt.core.tiles import TileGrid
from randt.service.agreement import AgreementGate
from randt.service.answers import Answers
from randt.service.capacity import Capacity
from randt.service.folding import MapPoints
from randt.service.georef import MapProjections
from randt.service.graph import ServiceGraph
from randt.service.live_maps import LiveMaps
from randt.service.localizing import MapPieces, SessionLocalizer
from randt.service.matchers import (
    MapFrame,
    MatcherProcessDiedError,
    MatcherProcessError,
    Registered,
    SessionMatcher,
    decoded_sweep,
    prior_of,
)
from randt.service.metrics import ServiceMetrics
from randt.service.publishing import SessionOutbox, not_durable
from randt.service.queueing import Job, drop_index, queue_label
from randt.service.session_info import SessionInfo
from randt.service.settings import ServiceSettings
from randt.service.store import PoseLogRecord, ResumeSweep, SessionFrame, Store
from randt.service.tracking import VERIFY_MATCHES, track
from randt.wire.codes import ErrorCode
from randt.wire.ids import session_map_name
from randt.wire.messages import PoseMessage, ScanHeader

__all__ = [
    "BEHIND_DEPTH",
    "MAP_SEED_REACH_M",
    "VERIFY_MATCHES",
    "Refusal",
    "SessionInfo",
    "SessionWorker",
    "WorkerServices",
]

log = logging.getLogger(__name__)

#: A session's first sweep with a prior is placed against its map's points within this many
#: metres (x and y) of the prior (:meth:`SessionWorker._map_seed`), beyond the matcher's reach.
MAP_SEED_REACH_M = 60.0
#: The covariance a keyframe placed on the map enters the pose graph with (``_on_map_fix``): 5 cm
#: and 0.2 deg, what a match on the map is good to (docs/mapping.md, "In the service").
ON_MAP_FIX_COVARIANCE = np.diag([0.05**2] * 3 + [np.radians(0.2) ** 2] * 3)
#: The message of a first sweep of a session that only localizes which did not match the map.
NOT_MATCHED_FIRST = "the first sweep did not match the map around its prior"
#: A session that only localizes, without a prior, tries to relocalize at most this often (its
#: scans' stamps): each try decodes the sweep here and matches it on the map at each place guessed.
RELOCALIZE_EVERY_S = 1.0
#: What its scans between two tries are answered.
NOT_RELOCALIZED_YET = (
    "this session only localizes (localize_only), its scans carry no prior pose and it was not "
    f"relocalized on the map yet (it tries again at most every {RELOCALIZE_EVERY_S:g} s)"
)
#: A sweep with fewer points than this is no resume sweep (it would not make a keyframe).
MIN_RESUME_POINTS = 100
#: A session whose queue holds at least this many scans is behind: on a node past its capacity its
#: matcher lets the keyframe model lag one keyframe rather than delay them. Within capacity a
#: backlog clears by itself, and lagging would change the poses (docs/architecture.md, "Overload").
BEHIND_DEPTH = 3
#: What the scans of a session whose matcher process died are answered.
MATCHER_DIED = (
    ErrorCode.INTERNAL_ERROR,
    "the matcher process died; the session resumes from its last saved state",
)
#: What the scans of a session whose poses could not be stored are answered.
NOT_STORED = (
    ErrorCode.STORAGE_ERROR,
    "the service could not store this session's poses; it resumes from its stored state",
)


@dataclass(frozen=True)
class Refusal:
    """A scan's answer when it gets no pose: an :class:`~randt.wire.codes.ErrorCode` and why."""

    code: str
    reason: str


@dataclass(frozen=True)
class WorkerServices:
    """What a session worker uses of the service, and nothing more."""

    settings: ServiceSettings
    metrics: ServiceMetrics
    answers: Answers
    maps: LiveMaps
    store: Store  # the pose log
    projections: MapProjections
    graph: ServiceGraph | None
    capacity: Capacity | None
    #: Matchers run in the service process (no executor): their CPU is the service's.
    in_process: bool
    #: Whether the node is past what admission may fill (only then may a session behind lag).
    saturated: Callable[[], bool]
    #: Whether a running session other than the caller uses a map.
    map_in_use: Callable[[str], bool]
    #: Write a session's snapshot (its first, here); whether it is on disk.
    save: Callable[[SessionWorker], bool]
    #: Take a broken session out of the running set.
    leave: Callable[[SessionWorker], None]
    #: The map's tiles prepared for every session's windows (None: each matcher prepares them).
    pieces: MapPieces | None = None


class SessionWorker:
    """One session's bounded queue, worker thread and matcher."""

    def __init__(
        self, info: SessionInfo, matcher: SessionMatcher, grid: TileGrid, services: WorkerServices
    ) -> None:
        self.info = info
        self.matcher = matcher
        self.grid = grid
        self.services = services
        self._queue: deque[Job] = deque()
        self._taken_ns: int | None = None  # the stamp of the scan taken from the queue last
        self._cond = threading.Condition()
        self._stopping = False
        # Its matcher process died, or a pose could not be made durable: abandon (not save) and
        # resume from the store.
        self._broken = False
        self._not_stored = False  # a pose log append failed
        self.lock = threading.Lock()  # held while the matcher runs; the flusher takes it to save
        self.out = SessionOutbox(info, services.answers, self._cond)
        s = services.settings
        gate = AgreementGate(s.map_agreement_min, s.map_agreement_every, s.map_agreement_min_points)
        self.points = MapPoints(self, gate, self.lock, services.maps, services.metrics)
        # (localizing or mapping, sweep by sweep; or only localizing)
        self.localizer = SessionLocalizer(s, services.pieces, only=info.localize_only)
        self._fix_refused = False  # a NavSatFix could not be placed in the shared map (logged once)
        # A pose was answered (a resumed session's were): the first waits for the first snapshot.
        self._posed = info.n_scans > 0
        self._relocalize_after_ns = 0  # (a session that only localizes, without a prior: next try)
        # The newest matched sweep that came with its points, and where the saved one is: the
        # flusher saves it for a resume after a crash (SessionSaver.save_resume_sweeps).
        self.resume_sweep: ResumeSweep | None = None
        self.resume_saved_xyz: np.ndarray | None = None
        self._thread = threading.Thread(
            target=self._run, name=f"session-{info.vehicle}-{info.session}", daemon=True
        )
        self._thread.start()

    @property
    def key(self) -> tuple[str, str]:
        return self.info.vehicle, self.info.session

    @property
    def broken(self) -> bool:
        """The session is to be abandoned: its matcher process died, or a pose could not be made
        durable (its log, or its first snapshot)."""
        return self._broken or self.out.failed

    @broken.setter
    def broken(self, value: bool) -> None:
        self._broken = value

    @property
    def broken_answer(self) -> tuple[str, str]:
        """What the scans still queued in a broken session are answered."""
        return NOT_STORED if self._not_stored or self.out.failed else MATCHER_DIED

    def wait_first_save(self, timeout: float | None = None) -> bool:
        """Wait for the session's first snapshot (if it is being written); whether it is done."""
        return self.out.wait_first_save(timeout)

    @property
    def gate(self) -> AgreementGate:
        return self.points.gate

    def depth(self) -> int:
        return len(self._queue)

    def submit(self, job: Job) -> Job | None:
        """Enqueue ``job``; returns the job dropped to make room, if the queue was full."""
        with self._cond:
            dropped = None
            if len(self._queue) >= self.services.settings.queue_size:
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
        while (job := self._next()) is not None:
            graph = self.services.graph
            try:
                # the graph process yields the cores while a sweep is matched (YieldGate)
                with contextlib.nullcontext() if graph is None else graph.matching():
                    self._process(job)
                if self.broken:
                    break
            except Exception:  # a bug in one scan must not kill the session or the service
                log.exception("session %s/%s: scan %d failed", *self.key, job.scan.seq)
                self._answer(
                    job,
                    Refusal(
                        ErrorCode.INTERNAL_ERROR,
                        "internal error while registering this scan (logged by the service)",
                    ),
                )
        if self.broken:
            self._abandon()

    def _next(self) -> Job | None:
        """The next scan to process; ``None`` when the worker stops or the session broke."""
        with self._cond:
            while not self._queue and not self._stopping and not self.broken:
                self._cond.wait()
            if self.broken or not self._queue:  # broken: its first snapshot failed meanwhile
                return None
            job = self._queue.popleft()
            self._taken_ns = job.scan.stamp_ns
            self.services.metrics.queue_depth.labels(queue_label(*self.key)).set(len(self._queue))
            return job

    def _abandon(self) -> None:
        """Leave the running set after the matcher process died or a pose could not be made
        durable: queued scans are answered with ``broken_answer``, nothing is saved (the store's
        last state stays the truth), and the session's next scan resumes it from the store."""
        self.services.leave(self)
        with self._cond:
            pending = list(self._queue)
            self._queue.clear()
            self._stopping = True
        for job in pending:
            self._answer(job, Refusal(*self.broken_answer))
        self.wait_first_save()  # (it answers the poses it holds) before the matcher goes
        self.fold(release=True)  # the poses of these points went out: their points belong to the map
        self.matcher.close()

    # -- one scan -------------------------------------------------------------------------------
    def _process(self, job: Job) -> None:
        """One scan through its stages: its prior -> the matcher -> the pose log -> the track and
        the map agreement -> the session's figures -> the fold -> its one answer -> the pose graph
        -> the keyframe model. A stage that refuses the scan returns a :class:`Refusal`, which
        :meth:`_answer` sends instead of the pose. (Localizing on the map, relocalizing and only
        localizing are choices of :meth:`_register`'s frame; every other stage stays.)"""
        scan = job.scan
        prior = self._prior(scan)
        if isinstance(prior, Refusal):
            return self._answer(job, prior)
        behind = self.depth() >= BEHIND_DEPTH and self.services.saturated()
        with self.lock:
            for_graph, points_voxel_m = self._points_wanted(scan, prior)
            registered = self._register(job, prior, behind, points_voxel_m)
            if isinstance(registered, Refusal):
                return self._answer(job, registered)
            not_logged = self._log_pose(scan, registered.result)
            if not_logged is not None:
                return self._answer(job, not_logged)
            lost = self._track(scan, registered.result) or self._hold_map_points(registered)
            if lost is None:
                self._keep_resume_sweep(registered)
            self._account(scan, registered.result, prior, lost is not None)
        if len(self.points) >= self.services.settings.fold_scans:
            self.fold()
        self._answer(job, registered if lost is None else lost)
        if lost is None and for_graph:
            self._offer_keyframe(scan, registered, prior)
        if not behind:
            with self.lock:
                self.matcher.update_model()  # in-process matchers; a matcher process does it itself
        return None

    def _prior(self, scan: ScanHeader) -> PosePrior | Refusal | None:
        """The scan's prior in the map frame: its ``prior``, or its ``geo_prior`` placed in the
        shared map through that map's geodetic origin (service/georef.py); ``invalid_prior``
        when it cannot be."""
        if scan.geo_prior is None:
            return prior_of(scan)
        s = self.services
        name = s.settings.default_map
        try:
            return s.projections.prior_in_map(name, s.maps.grid(name), scan.geo_prior)
        except BadMessageError as exc:
            return Refusal(exc.code, str(exc))

    def _points_wanted(self, scan: ScanHeader, prior: PosePrior | None) -> tuple[bool, float | None]:
        """``(for the pose graph, voxel)``: whether the graph wants this sweep as its next keyframe,
        and at which voxel the matcher returns the sweep's points (``None``: none are wanted). The
        map agreement check wants them too when it is due, and for a lost session or a match after
        fallbacks (service/agreement.py). A new session's frame is fixed first."""
        s, info = self.services, self.info
        if info.n_scans == 0:
            self._fix_frame(prior is not None)
        if info.localize_only:  # (nothing of its sweeps goes to the map or the graph)
            return False, None
        graph, poses = s.graph, self.matcher.poses
        # a localizing session: no points for a keyframe the graph would not add, nor for the
        # agreement check (its match on the map is the check: service/folding.py)
        localizing = self.localizer.localizing and not info.lost and info.last_status != "fallback"
        # (a first sweep in the map's frame goes with a window: its place is judged at its prior)
        first = info.n_scans == 0 and prior is not None and self.localizer.enabled and info.frame == "map"
        if graph is not None and graph.wants_keyframe(scan.vehicle, scan.session, poses):
            here = poses[-1] if poses else None if prior is None else prior.T_world_sensor
            known = (
                (localizing or first)
                and here is not None
                and graph.passes_known_place(scan.vehicle, scan.session, info.map_name, here)
            )
            if not known:
                return True, min(graph.settings.keyframe_voxel_m, s.settings.map_voxel_m)
        if localizing:
            return False, None
        if self.gate.due() or (self.gate.enabled and (info.lost or info.last_status == "fallback")):
            return False, s.settings.map_voxel_m
        return False, None

    def _fix_frame(self, has_prior: bool) -> None:
        """Set the session's frame from its first processed scan: with a prior it lives in the
        shared map's frame, without one in its own (docs/architecture.md, "Sessions and frames")."""
        info, s = self.info, self.services
        frame: SessionFrame = "map" if has_prior else "session"
        if info.frame == frame:
            return
        old = info.map_name
        name = s.settings.default_map if has_prior else session_map_name(info.vehicle, info.session)
        log.info(
            "session %s/%s: its first processed scan %s a prior pose: %s frame, map %s",
            info.vehicle, info.session, "carries" if has_prior else "has no", frame, name,
        )  # fmt: skip
        self.grid = s.maps.grid(name)
        info.frame, info.map_name = frame, name
        s.maps.forget_if_empty(old, in_use=s.map_in_use(old))

    def _register(
        self, job: Job, prior: PosePrior | None, behind: bool, points_voxel_m: float | None
    ) -> Registered | Refusal:
        """The scan's payload to the matcher, which decodes and matches it (the keyframe model is
        rebuilt after the pose is out); a session's first sweep without a prior is relocalized on
        the shared map first (:meth:`_relocalized`). A matcher process that died breaks the
        session."""
        relocalized = self._relocalized(job, prior, behind, points_voxel_m)
        if relocalized is not None:
            return relocalized
        frame = self._map_frame(job.scan, prior)
        if self.info.localize_only and frame.window is None:
            name = frame.token[0]
            why = self.localizer.not_on_map(name, self._grid_of(name), prior, self.matcher.poses)
            return Refusal(ErrorCode.NOT_ON_MAP, why)
        registered = self._match(job, frame, behind, points_voxel_m)
        return registered if isinstance(registered, Refusal) else self._unplaced_first(registered)

    def _relocalized(
        self, job: Job, prior: PosePrior | None, behind: bool, points_voxel_m: float | None
    ) -> Registered | Refusal | None:
        """A session's first sweep without a prior, where the service localizes (``localize``,
        or the session only localizes) and has a pose graph: placed on the shared map where its
        places (service/places.py) say it was taken, if the matcher verifies one of the guesses
        on the map around it (:class:`MapFrame`'s ``relocalize``); the session then lives in the
        map's frame from this answer on. ``None``: not relocalized, the sweep maps in the session's
        own frame as before; a session that only localizes is answered ``not_on_map`` instead
        (and tries again at most every :data:`RELOCALIZE_EVERY_S` of its scans' time)."""
        s, info, scan = self.services, self.info, job.scan
        if prior is not None or info.n_scans or s.graph is None:
            return None
        if not (s.settings.localize or info.localize_only) or info.frame != "session":
            return None
        if info.localize_only and scan.stamp_ns < self._relocalize_after_ns:
            return Refusal(ErrorCode.NOT_ON_MAP, NOT_RELOCALIZED_YET)
        self._relocalize_after_ns = scan.stamp_ns + int(RELOCALIZE_EVERY_S * 1e9)
        name = s.settings.default_map
        grid = s.maps.grid(name)
        try:
            xyz = decoded_sweep(job.payload, s.answers.limits)[0]
        except BadMessageError as exc:
            return Refusal(exc.code, str(exc))
        tried = 0
        for guess in s.graph.relocalize(name, np.asarray(xyz, dtype=np.float64)):
            token = (name, *grid.content_token)
            window = self.localizer.window(grid, token, guess, [], "map")
            if window is None:
                continue
            tried += 1
            frame = MapFrame(token, None, None, guess, window, for_map=False, relocalize=True)
            try:
                registered = self._match(job, frame, behind, points_voxel_m)
            except NotRelocalizedError as exc:
                log.info("session %s/%s: a place guessed is not verified: %s", *self.key, exc)
                continue
            if not isinstance(registered, Refusal):
                log.info("session %s/%s relocalized on map %s at its first sweep", *self.key, name)
                self._fix_frame(True)
            return registered
        if not info.localize_only:
            return None
        why = f"none of {tried} places guessed matched" if tried else "no place of the map is like its sweep"
        return Refusal(
            ErrorCode.NOT_ON_MAP,
            f"this session only localizes (localize_only), its scans carry no prior pose and it was not "
            f"relocalized on map {name!r}: {why}; it tries again in {RELOCALIZE_EVERY_S:g} s",
        )

    def _match(
        self, job: Job, frame: MapFrame, behind: bool, points_voxel_m: float | None
    ) -> Registered | Refusal:
        """The sweep matched in ``frame`` (:meth:`_register`); a sweep not relocalized raises
        :class:`NotRelocalizedError` (its matcher as before)."""
        s = self.services
        try:
            registered = self.matcher.register_payload(
                job.payload,
                limits=s.answers.limits,
                behind=behind,
                keyframe_voxel_m=points_voxel_m,
                frame=frame,
            )
        except NotRelocalizedError:
            raise
        except MatcherProcessDiedError as exc:  # (a RandtError too: caught first)
            log.error("session %s/%s: %s; it resumes from its last saved state", *self.key, exc)
            self.broken = True
            return Refusal(*MATCHER_DIED)
        except MatcherProcessError:
            raise  # a bug, not bad input: logged and answered internal_error by the worker loop
        except BadMessageError as exc:  # its bodies did not decode (v2: decompressed there)
            return Refusal(exc.code, str(exc))
        except RandtError as exc:
            return Refusal(ErrorCode.REGISTRATION_FAILED, str(exc))
        if s.capacity is not None:
            s.capacity.matched(
                self.key,
                registered.cpu_s,
                in_process=s.in_process,
                localized=registered.result.localized,
                first=registered.result.index == 0,
            )
        self.localizer.answered(registered.result)
        return self._unplaced_first(registered)

    def _unplaced_first(self, registered: Registered) -> Registered:
        """A session that only localizes answers no pose the map did not give: its first sweep,
        placed at its prior when it did not match the map there, is a ``fallback`` (the session is
        lost until its sweeps match the map: service/tracking.py)."""
        result = registered.result
        if not self.info.localize_only or result.localized or result.status != "first":
            return registered
        unplaced = replace(result, status="fallback", message=NOT_MATCHED_FIRST)
        return replace(registered, result=unplaced)

    def _log_pose(self, scan: ScanHeader, result: ScanResult) -> Refusal | None:
        """Durable before acknowledged: the pose into the session's fsync'd log before it is
        published (and before the map holds its points). When that fails the scan is answered
        ``storage_error`` and the session breaks, to resume from the store."""
        record = PoseLogRecord(
            index=result.index,
            seq=scan.seq,
            stamp_ns=scan.stamp_ns,
            stamp_s=scan.stamp_ns * 1e-9,
            pose=result.T_world_sensor,
            status=result.status,
        )
        try:
            self.services.store.append_pose(scan.vehicle, scan.session, record)
        except (OSError, RandtError) as exc:
            self._broken = self._not_stored = True
            return Refusal(
                ErrorCode.STORAGE_ERROR, not_durable(self.key, scan.seq, str(exc), self.services.answers)
            )
        return None

    def _track(self, scan: ScanHeader, result: ScanResult) -> Refusal | None:
        """Whether the scan's pose may be answered (``None``) or the session is lost
        (:func:`randt.service.tracking.track`)."""
        why = track(self.info, scan, result, self.services.settings.fallback_horizon_s)
        return None if why is None else Refusal(ErrorCode.LOST, why)

    def _hold_map_points(self, registered: Registered) -> Refusal | None:
        """The sweep's map points wait to be folded, into the map they go to and moved by the
        session's newest correction (the map follows the pose graph), after the map agreement
        check; lost when the session's sweeps disagree with its map."""
        if self.info.localize_only:
            return None  # (it holds none: service/matcher_io.py, MapFrame.for_map)
        C, fold_map = self._fold_target()
        if self.localizer.enabled:
            self.localizer.folding(fold_map, self._grid_of(fold_map), registered.map_xyz)
        why, share = self.points.take(registered, C, fold_map)
        if share is not None:
            self.info.map_agreement, self.info.map_disagrees = share, self.gate.disagreeing
        return None if why is None else Refusal(ErrorCode.LOST, why)

    def _keep_resume_sweep(self, registered: Registered) -> None:
        """A matched sweep the matcher returned points of becomes the session's resume sweep,
        which the flusher saves (a reference: nothing is copied on this path)."""
        result, points = registered.result, registered.keyframe_xyz
        if (
            points is None
            or result.status == "fallback"
            or not result.deskewed
            or len(points) < MIN_RESUME_POINTS
        ):
            return
        self.resume_sweep = ResumeSweep(result.index, result.T_world_sensor, points)

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

    def _answer(self, job: Job, outcome: Registered | Refusal) -> None:
        """The scan's one answer: its refusal, or its pose, which goes out once durable
        (service/publishing.py: a new session's first poses wait for its first snapshot)."""
        scan = job.scan
        if isinstance(outcome, Refusal):
            self.info.n_errors += 1
            self.services.answers.error(scan.vehicle, scan.session, scan.seq, outcome.code, outcome.reason)
            return
        result = outcome.result
        answer = pose_message(scan, result, self.info.map_name)
        self.services.metrics.registration_seconds.observe(result.time_s)
        if self._posed:
            self.out.publish(answer, job.received_ns)
        else:  # (a session that only localizes may answer its first sweeps without a pose)
            self._posed = True
            self.out.first(answer, job.received_ns, lambda: self.services.save(self))

    def _offer_keyframe(self, scan: ScanHeader, registered: Registered, prior: PosePrior | None) -> None:
        """A keyframe's points to the pose graph of the session's map, with its prior pose as a
        GNSS/INS fix; a session without priors may join the shared map."""
        s, kf = self.services, registered.keyframe_xyz
        if s.graph is None or kf is None or len(kf) < 10 or not registered.result.deskewed:
            return  # (a sweep not deskewed: the next one is the session's first keyframe)
        info, result = self.info, registered.result
        s.graph.offer(
            scan.vehicle,
            scan.session,
            map_name=info.map_name,
            seq=scan.seq,
            index=result.index,
            stamp_s=scan.stamp_ns * 1e-9,
            T_live=result.T_world_sensor,
            points=kf,
            intensity=registered.keyframe_intensity,
            gnss=self._on_map_fix(result) or self._gnss(scan, prior),
            join=s.settings.default_map if info.frame == "session" else None,
            localized=result.localized,
        )

    # -- where a sweep's points go ---------------------------------------------------------------
    def _fold_target(self) -> tuple[np.ndarray | None, str]:
        """``(correction, map)`` for the session's new map points: the pose graph's newest
        correction of the session (None: none) and the map they are folded into."""
        graph, info = self.services.graph, self.info
        if graph is None:
            return None, info.map_name
        return graph.fold_target(info.vehicle, info.session, info.map_name)

    def _grid_of(self, map_name: str) -> TileGrid:
        """The tiles of ``map_name``: the session's own handle when it is the session's map."""
        return self.grid if map_name == self.info.map_name else self.services.maps.grid(map_name)

    def _map_frame(self, scan: ScanHeader, prior: PosePrior | None) -> MapFrame:
        """Where this sweep's map points go (:class:`~randt.service.matchers.MapFrame`): the matcher
        moves them by the correction and sends only voxels it has not sent to this map's content;
        a first sweep's map seed (:meth:`_map_seed`), a WGS84 prior placed in the map (the payload
        has none), and the map around the vehicle to localize on (service/localizing.py)."""
        C, fold_map = self._fold_target()
        grid = self._grid_of(fold_map)
        token = (fold_map, *grid.content_token)
        window = self.localizer.window(grid, token, prior, self.matcher.poses, self.info.frame)
        # (a first sweep with a window is placed on it: the seed's points would go twice)
        only = self.info.localize_only
        seed = self._map_seed(prior) if self.info.n_scans == 0 and window is None and not only else None
        placed = prior if scan.geo_prior is not None else None
        return MapFrame(token, C, seed, placed, window, for_map=not only)

    def _map_seed(self, prior: PosePrior | None) -> np.ndarray | None:
        """For a session's first sweep with a prior: its map's points within
        :data:`MAP_SEED_REACH_M` of the prior, which the matcher places the sweep against
        (``None`` without a prior or when the map has too few there: the sweep goes at its prior)."""
        if prior is None:
            return None
        xy = np.asarray(prior.T_world_sensor, dtype=np.float64)[:2, 3]
        cloud = self.grid.points_in_bbox(xy - MAP_SEED_REACH_M, xy + MAP_SEED_REACH_M)
        return cloud.xyz.astype(np.float32) if len(cloud.xyz) >= MAP_SEED_MIN_POINTS else None

    @staticmethod
    def _on_map_fix(result: ScanResult) -> tuple[np.ndarray, np.ndarray] | None:
        """A keyframe placed on the map (a first sweep matched to it, a localized sweep): its pose
        there, with :data:`ON_MAP_FIX_COVARIANCE`, as the graph's prior instead of the scan's fix.
        The map match is centimetres; a GNSS fix metres of noise and bias, which pulled a
        session mapping on mapped streets off the map until its sweeps disagreed with it."""
        if not (result.localized or result.message == MATCHED_TO_MAP):
            return None
        return result.T_world_sensor, ON_MAP_FIX_COVARIANCE

    def _gnss(self, scan: ScanHeader, prior: PosePrior | None) -> tuple[np.ndarray, np.ndarray] | None:
        """A keyframe's GNSS for the pose graph: its prior pose with its covariance (in the
        session's map; the graph keeps the heading it gives, core/fleet_map.py), or a ROS 2
        robot's NavSatFix position in the shared map's frame, which the session may join (the
        graph places it there by its fixes); ``None`` when the fix cannot be placed (logged once)."""
        if prior is not None:
            return prior.T_world_sensor, prior.covariance
        if scan.gnss_fix is None:
            return None
        s = self.services
        name = s.settings.default_map
        try:
            return s.projections.fix_in_map(name, s.maps.grid(name), scan.gnss_fix)
        except BadMessageError as exc:
            if not self._fix_refused:
                log.warning("session %s/%s: its GNSS fixes are not used: %s", *self.key, exc)
            self._fix_refused = True
            return None

    def fold(self, *, release: bool = False) -> None:
        """Fold the session's waiting map points into its maps (the session thread, and the
        flusher before it saves); ``release``: what the agreement check holds too."""
        self.points.fold(release=release)


def pose_message(scan: ScanHeader, result: ScanResult, map_name: str) -> PoseMessage:
    """The pose answer of a matched scan (its latency is set when it goes out)."""
    cov = result.covariance
    return PoseMessage(
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
        latency_ms=0.0,
        map=map_name,
        mode="localizing" if result.localized else "mapping",
    )
