"""The session manager: builds the rooms a scan passes through, runs the flusher that saves the
sessions and the maps, the maps' lifecycle, and what status asks.

A scan's way (``docs/architecture.md``, "One scan, through the service"): the transport callback
hands its bytes to :mod:`randt.service.routing` (intake, header, admission, seq check, the
session's queue or its opening); the session's worker (:mod:`randt.service.worker`) does the
rest. Every scan gets exactly one answer.
"""

from __future__ import annotations

import functools
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from randt.core.errors import ConflictError, NotFoundError, RandtError, UnavailableError
from randt.core.geo import GeoOrigin
from randt.service.admission import Admission
from randt.service.answers import Answers, Outbox
from randt.service.capacity import Capacity, CapacityFigures, MeasuredCosts, saturated
from randt.service.capacity_record import load_costs, save_costs
from randt.service.counters import Counters
from randt.service.georef import MapProjections
from randt.service.graph import ServiceGraph
from randt.service.graph_log import GRAPH_DIRNAME
from randt.service.graph_process import MapGeometry
from randt.service.live_maps import LiveMaps
from randt.service.localizing import MapPieces
from randt.service.matchers import MatcherExecutor, MatcherPool
from randt.service.metrics import ServiceMetrics
from randt.service.opener import SessionOpener
from randt.service.routing import ScanRouter
from randt.service.session_info import SessionInfo
from randt.service.session_table import SessionTable
from randt.service.settings import ServiceSettings
from randt.service.snapshots import SessionSaver
from randt.service.store import SessionRecord, Store
from randt.service.store import SessionState as RecordState
from randt.service.worker import SessionWorker, WorkerServices
from randt.wire.ids import session_map_name
from randt.wire.messages import WireLimits
from randt.wire.ros2 import Ros2Scan

__all__ = ["MapInUseError", "Outbox", "SessionManager"]

log = logging.getLogger(__name__)


class MapInUseError(ConflictError):
    """A map cannot be deleted while running sessions fold scans into it."""


class SessionManager:
    """The sessions and maps of one service: builds their collaborators, routes scans to them
    (:class:`~randt.service.routing.ScanRouter`), saves them (the flusher), runs the maps'
    lifecycle and answers what status asks."""

    def __init__(
        self,
        settings: ServiceSettings,
        store: Store,
        outbox: Outbox,
        metrics: ServiceMetrics | None = None,
        executor: MatcherExecutor | None = None,
    ) -> None:
        self.settings, self.store, self.outbox = settings, store, outbox
        if settings.map_origin is not None:  # before anything starts: a wrong one stops it, saying why
            name = settings.default_map
            MapProjections(store).give(name, name in store.list_maps(), GeoOrigin(*settings.map_origin))
        self.metrics = metrics or ServiceMetrics()
        self.limits = WireLimits(max_points=settings.max_points, max_payload_bytes=settings.max_payload_bytes)
        self.answers = Answers(outbox, self.metrics, self.limits)
        self._flush_lock = threading.Lock()  # one flush at a time; map deletion waits for it
        self.pool: MatcherExecutor | None = executor if executor is not None else _executor(settings)
        self.capacity: Capacity | None = _capacity(settings, self.pool)
        self._costs_saved: tuple[MeasuredCosts, float] | None = None  # (what, when: monotonic)
        costs = None if self.capacity is None else load_costs(Path(settings.data_dir))
        if self.capacity is not None and costs is not None and self.capacity.start_from(costs):
            self._costs_saved = (costs, time.monotonic())
        self.admission = Admission(settings, self.capacity)
        self.max_sessions = self.admission.max_sessions
        contents = store.load_all()  # a damaged map or session is reported and skipped, not fatal
        for problem in contents.problems:
            log.error("store: skipped %s %s: %s", problem.kind, problem.name, problem.message)
        self.saver = SessionSaver(
            store, settings, self.metrics, {k: loaded.record for k, loaded in contents.sessions.items()}
        )
        self.table = SessionTable(self.saver, self.metrics)
        self.pieces = MapPieces.for_settings(settings)  # (tiles prepared once for every window)
        self.maps = LiveMaps(
            store,
            dict(contents.maps),
            tile_size_m=settings.tile_size_m,
            voxel_size_m=settings.map_voxel_m,
            default_map=settings.default_map,
            metrics=self.metrics,
            outbox=outbox,
        )
        #: Each map's geodetic origin, if it has one (service/georef.py).
        self.projections = MapProjections(store)
        #: The maps' pose graphs (service/graph.py); their process starts with the first keyframe.
        self.graph: ServiceGraph | None = self._pose_graph() if settings.graph else None
        self._tiles_saved_at = time.monotonic()  # the flusher saves tiles every tile_save_interval_s
        self._graph_was_replaying = False  # (the flusher: the last capacity sample saw the graph replay)
        self.counters = Counters(store.data_dir, self.metrics)
        opener = SessionOpener(self._services(), self.saver, self.pool)
        self.router = ScanRouter(settings, self.table, self.answers, self.admission, self.capacity, opener)
        self.intake = self.router.intake
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_loop, name="store-flusher", daemon=True)
        self._flusher.start()

    def _pose_graph(self) -> ServiceGraph:
        s = self.settings
        return ServiceGraph(
            s.fleet_map,
            self.outbox,
            self.metrics,
            geometry=MapGeometry(s.tile_size_m, s.map_voxel_m, 1),
            on_refold=self.maps.refold,
            on_join=self._joined,
            keyframe_m=s.graph_keyframe_m,
            queue_size=s.graph_queue,
            refold_s=s.graph_refold_s,
            yield_to_matchers=s.executor == "local" if s.graph_yield is None else s.graph_yield,
            on_restart=self.maps.graph_restarted,
            log_dir=Path(s.data_dir) / GRAPH_DIRNAME,
        )

    def _services(self) -> WorkerServices:
        """What a session worker gets of the service."""
        return WorkerServices(
            settings=self.settings,
            metrics=self.metrics,
            answers=self.answers,
            maps=self.maps,
            store=self.store,
            projections=self.projections,
            graph=self.graph,
            capacity=self.capacity,
            in_process=self.pool is None,
            saturated=functools.partial(saturated, self.capacity, self.table.keys),
            map_in_use=self.table.map_in_use,
            save=self.saver.save,
            leave=self.table.leave,
            pieces=self.pieces,
        )

    # -- the scan's way in (service/routing.py) ------------------------------------------------------
    def submit(self, key_vehicle: str, payload: bytes | Ros2Scan, received_ns: int | None = None) -> None:
        """Queue one scan payload published on ``randt/fleet/<key_vehicle>/scan`` (never blocks)."""
        self.router.submit(key_vehicle, payload, received_ns)

    def handle(self, key_vehicle: str, payload: bytes | Ros2Scan, received_ns: int) -> None:
        """Decode, validate and route one scan to its session (an intake worker's call)."""
        self.router.handle(key_vehicle, payload, received_ns)

    # -- the maps' lifecycle ----------------------------------------------------------------------
    def fold_map(self, vehicle: str, session: str) -> str | None:
        """The map a running session's points go into (the shared map it joined, or its own);
        ``None`` when the session is not running."""
        w = self.table.worker((vehicle, session))
        return None if w is None else (w.info.joined_map or w.info.map_name)

    def _joined(self, vehicle: str, session: str, map_name: str, T_map_session: np.ndarray) -> None:
        """The pose graph placed a session without priors into ``map_name`` (service/graph.py):
        from now on its points fold there, and its own map is merged in and removed."""
        w = self.table.worker((vehicle, session))
        own = session_map_name(vehicle, session)
        if w is None and own not in self.maps:  # the graph's log taken again after a restart:
            self.maps.note_merged(own, map_name, f"{vehicle}/{session}")  # merged before it
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
        """Merge the session's own map into the map it joined, and remove it (the graph's next
        re-fold then replaces the tiles its keyframes touch); ``GET /maps/<own>`` says where it
        went. A map another running session also uses is left alone."""
        own = w.info.map_name
        w.fold(release=True)  # its points still waiting for the own map go in first
        with self._flush_lock:  # no flush saves the own map while it goes
            if self.table.users_of(own, but=w) or own == self.settings.default_map:
                return
            n_tiles = self.maps.merge(own, into, T_into_own, f"{w.info.vehicle}/{w.info.session}")
        if n_tiles is not None:
            log.info("map %s merged into %s (%d tiles) and removed", own, into, n_tiles)

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
        with self._flush_lock, self.table.lock:
            users = self.table.users_of(map_name)
            if users:
                raise MapInUseError(
                    f"map {map_name!r} is in use by {len(users)} running session(s) "
                    f"({', '.join(users[:5])}): close them first"
                )
            self.maps.check_exists(map_name)
            if self.graph is not None:  # its pose graph first: a restart must not bring it back
                try:
                    self.graph.forget_map(map_name)
                except RandtError as exc:
                    raise UnavailableError(f"map {map_name!r} not deleted: its pose graph: {exc}") from exc
            n_tiles = self.maps.delete(map_name)
            self.projections.forget(map_name)
        log.info("map %s deleted (%d tiles)", map_name, n_tiles)
        return n_tiles

    # -- closing, flushing, stopping --------------------------------------------------------------
    def close(self, vehicle: str, session: str, *, state: RecordState = "closed") -> bool:
        """Finish a session: process what is queued, save it, stop its worker. False if unknown."""
        return self.table.close((vehicle, session), state)

    def flush(self, *, tiles: bool = True) -> None:
        """Save changed sessions (and, with ``tiles``, dirty tiles, publishing their updates),
        expire idle sessions."""
        with self._flush_lock:
            workers = self.table.running()
            self.saver.save_resume_sweeps(workers)  # first: small, and what a resume after a crash needs
            if tiles:
                self._tiles_saved_at = time.monotonic()
                for w in workers:  # what sessions that were behind processed goes into this save
                    w.fold()
                self.maps.save_dirty()
            now = time.monotonic()
            for w in workers:
                if self.saver.due(w, now):
                    self.saver.save(w)
                if w.depth() == 0 and now - w.info.last_activity > self.settings.idle_expiry_s:
                    self.close(*w.key, state="expired")
            self.counters.save()

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
        graph = self.graph
        # (the graph replaying its log after a start: its CPU is not the sweeps'; nor that of the
        # flush that saw it end)
        replaying = graph is not None and graph.replaying
        settling, self._graph_was_replaying = replaying or self._graph_was_replaying, replaying
        self.capacity.service_sample(graph_cpu_s=0.0 if graph is None else graph.cpu_s(), settling=settling)
        running = self.table.keys()
        self.capacity.forget(running)
        self._save_costs()
        f, m = self.capacity.figures(running), self.metrics
        m.capacity_cores.set(f.cores)
        m.capacity_load.set(f.load)
        m.capacity_sessions_more.set(f.sessions_more)
        m.capacity_sweep_cpu_seconds.set(f.sweep_cpu_s)
        m.capacity_service_cpu_seconds.set(f.service_cpu_s)

    def _save_costs(self) -> None:
        """What the sessions were measured to cost, to ``DATA/capacity.json`` when it changed by
        more than :data:`COSTS_CHANGE` since last written, :data:`COSTS_EVERY_S` apart at most
        (a restarted node admits from it: service/capacity_record.py)."""
        assert self.capacity is not None
        costs, now = self.capacity.measured(), time.monotonic()
        if costs.mapping_sweep_cpu_s is None and costs.localizing_sweep_cpu_s is None:
            return
        if self._costs_saved is not None:
            before, at = self._costs_saved
            if now - at < COSTS_EVERY_S or not _costs_changed(before, costs):
                return
        try:
            save_costs(Path(self.settings.data_dir), costs)
        except RandtError as exc:
            log.warning("the measured session costs could not be saved: %s", exc)
            return
        self._costs_saved = (costs, now)

    def saturated(self) -> bool:
        """Whether the node is past what admission may fill (:func:`randt.service.capacity.saturated`)."""
        return saturated(self.capacity, self.table.keys)

    def capacity_figures(self) -> CapacityFigures | None:
        """The node's capacity as measured now (``/status``), or None without capacity admission."""
        return None if self.capacity is None else self.capacity.figures(self.table.keys())

    def stop(self) -> None:
        """Drain the intake and every session, save everything, stop the flusher (SIGTERM path)."""
        self._stop.set()
        self.intake.stop()
        self.wait_openings(60)
        self._flusher.join(10)
        workers = self.table.running()
        for w in workers:
            w.stop(drain=True)
        self.flush()
        for w in workers:
            self.saver.save(w)
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
        return self.table.wait_openings(timeout)

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
        return self.table.opening_keys()

    def sessions(self) -> list[SessionInfo]:
        return self.table.infos()

    def worker(self, vehicle: str, session: str) -> SessionWorker | None:
        return self.table.worker((vehicle, session))

    def queue_depths(self) -> dict[str, int]:
        return self.table.depths()

    def records(self) -> dict[tuple[str, str], SessionRecord]:
        """The stored record of every session known to the store (a copy; running ones as last saved)."""
        return self.saver.records()

    def trajectory(self, vehicle: str, session: str) -> tuple[np.ndarray, np.ndarray] | None:
        """``(stamps_s (N,), poses (N, 4, 4))`` of a running session, or ``None`` if it is not running.

        Read without the worker's lock (held while the matcher runs): both lists only grow, one
        entry per scan in the same order, so their common prefix belongs to the same scans.
        """
        w = self.worker(vehicle, session)
        if w is None:
            return None
        pose_list = list(w.matcher.poses)  # copies of append-only lists (atomic under the GIL)
        stamp_list = list(w.info.stamps_s)
        n = min(len(pose_list), len(stamp_list))
        poses = np.array(pose_list[:n], dtype=np.float64).reshape(-1, 4, 4)
        return np.array(stamp_list[:n], dtype=np.float64), poses

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
        if self.table.worker((vehicle, session)) is not None or self.saver.record((vehicle, session)) is None:
            return None
        record = self.store.mark_session(vehicle, session, "closed")  # file I/O: outside the lock
        self.saver.set_record((vehicle, session), record)
        return record


def _executor(settings: ServiceSettings) -> MatcherExecutor | None:
    """Where the sessions' matchers run: Ray actors, local worker processes, or (``None``) the
    session threads themselves (one core: no process is worth its start)."""
    if settings.executor == "ray":
        from randt.service.ray_executor import RayMatcherPool  # the ray extra

        return RayMatcherPool(settings.ray_address, settings.ray_transport)
    n_procs = settings.matcher_processes
    if n_procs < 0:
        cores = os.cpu_count() or 1
        n_procs = cores if cores > 1 else 0
    return MatcherPool(n_procs) if n_procs > 0 else None


#: The measured session costs are written again when one changed by more than this share, at most
#: every COSTS_EVERY_S (SessionManager._save_costs).
COSTS_CHANGE = 0.1
COSTS_EVERY_S = 30.0


def _costs_changed(before: MeasuredCosts, now: MeasuredCosts) -> bool:
    pairs = (
        (before.mapping_sweep_cpu_s, now.mapping_sweep_cpu_s),
        (before.localizing_sweep_cpu_s, now.localizing_sweep_cpu_s),
        (before.service_cpu_s, now.service_cpu_s),
    )
    return any(
        (a is None) != (b is None) or (a is not None and b is not None and abs(b - a) > COSTS_CHANGE * a)
        for a, b in pairs
    )


def _capacity(settings: ServiceSettings, pool: MatcherExecutor | None) -> Capacity | None:
    """Admission by measured capacity (service/capacity.py); ``None``: by max_sessions only."""
    if settings.capacity_target <= 0:
        return None
    # a Ray cluster's CPUs (they change); else this node's, or one core for in-process matchers
    cpus = getattr(pool, "cpus", None)
    cores: float | Callable[[], float] = (
        cpus if callable(cpus) else float(os.cpu_count() or 1) if pool is not None else 1.0
    )
    return Capacity(
        cores=cores,
        shares_cores=cpus is None,
        target=settings.capacity_target,
        rate_hz=settings.session_rate_hz,
        sweep_cpu_s=settings.sweep_cpu_estimate_s,
        retry_after_s=settings.admission_retry_s,
    )
