"""The pose graphs in the service: loop closure and GNSS fusion beside the live answers.

:class:`ServiceGraph` feeds a session's keyframes (every ``graph_keyframe_m`` of travel) to one
process at the lowest priority (service/graph_process.py: one FleetMapper per map), off the
session threads' GIL; it supervises that process, logs each keyframe before the graph takes it
(service/graph_log.py), and turns what the graph moved into corrections, re-folded tiles and
joins. The per-sweep answers are never rewritten (docs/mapping.md, "In the service").
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import multiprocessing
import multiprocessing.connection
import os
import threading
import time
from collections.abc import Callable, Hashable
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from randt.core.errors import RandtError
from randt.core.fleet_map import FleetMapSettings
from randt.service.graph_log import GraphLog
from randt.service.graph_priority import GRAPH_NICE, YieldGate, process_cpu_s, set_graph_priority
from randt.service.graph_process import MOVE_TOL_DEG, MOVE_TOL_M, MapGeometry, graph_main
from randt.service.graph_state import (
    GraphLoop,
    GraphState,
    GraphView,
    Keyframe,
    correct_trajectory,
)
from randt.service.metrics import ServiceMetrics
from randt.service.processes import start_ignoring_group_signals
from randt.wire.messages import CorrectionMessage

__all__ = [
    "GRAPH_NICE",
    "MOVE_TOL_DEG",
    "MOVE_TOL_M",
    "GraphLoop",
    "GraphState",
    "ServiceGraph",
    "correct_trajectory",
]

log = logging.getLogger(__name__)

SessionKey = tuple[str, str]

#: The graph process runs at ``SCHED_IDLE``, which yields to any other process, ours or not: with
#: work in flight and no answer for this long it is starved (other processes can hold it for good:
#: docs/architecture.md, "Threads or processes"), and runs at the normal policy niced by
#: GRAPH_NICE until its queue is empty (:meth:`ServiceGraph._guard_starvation`).
STARVED_S = 5.0
#: Raised and still behind this long, it runs at the service's own niceness until its queue is
#: empty: niced, beside a CPU burner at the normal niceness, it gets about a tenth of a core.
#: Admission counts the graph's CPU with the service process's (service/capacity.py), so the
#: node's measured capacity leaves it that time.
ESCALATE_S = 30.0


def _retry_key(item: tuple[Any, ...]) -> Hashable:
    """What names an item across the process's deaths: a keyframe by its map, session and seq
    (taken again from the log, it is another object), anything else by identity."""
    return ("keyframe", *item[1:5]) if item[0] == "keyframe" else id(item)


class ServiceGraph:
    """The service's pose graphs, one per map, in a process of their own (module docstring)."""

    def __init__(
        self,
        settings: FleetMapSettings,
        outbox: Callable[[CorrectionMessage], None],
        metrics: ServiceMetrics,
        *,
        geometry: MapGeometry | None = None,
        on_refold: Callable[[str, list[str], np.ndarray, np.ndarray], None] | None = None,
        on_join: Callable[[str, str, str, np.ndarray], None] | None = None,
        keyframe_m: float = 10.0,
        queue_size: int = 64,
        refold_s: float = 20.0,
        yield_to_matchers: bool = True,
        on_restart: Callable[[], None] | None = None,
        log_dir: str | os.PathLike[str] | None = None,
    ) -> None:
        self.settings = settings
        #: The keyframes the graph took, durable (service/graph_log.py): every (re)started process
        #: takes them again first. ``None``: the graph lives in memory only.
        self._log: GraphLog | None = None if log_dir is None else GraphLog(log_dir)
        #: Where the graph process keeps the keyframes' points (rebuilt from the log at each start).
        self._spill: Path | None = None if log_dir is None else Path(log_dir) / "spill"
        #: Items of the log being taken again by the current process (ids), and whether the last
        #: keyframe answered was one: what they make is not published again.
        self._replay_ids: set[int] = set()
        self._answered_replay = False
        #: holds the graph process while sweeps are matched (``graph_yield``); None: never held
        self.gate: YieldGate | None = YieldGate() if yield_to_matchers else None
        self.refold_s = refold_s
        self.geometry = geometry or MapGeometry(20, 0.2, 1)
        self.keyframe_m = keyframe_m
        self._metrics = metrics
        #: What the service knows of the graphs (the receiver writes it, the reads read it).
        self.view = GraphView(metrics, outbox, on_refold, on_join, keyframe_m)
        self._queue_size = queue_size
        self._queued: list[tuple[Any, ...]] = []
        self._offered = 0  # keyframes queued (dropped ones subtracted) ...
        self._done = 0  # ... and answered by the process: wait_idle
        self._syncs = 0  # sync requests sent (wait_idle) ...
        self._synced = 0  # ... and answered
        self._cond = threading.Condition()
        #: One sender on the pipe at a time (the send loop, and close's ``quit``): two sends at
        #: once interleave their bytes.
        self._send_lock = threading.Lock()
        self._closed = False
        self._on_restart = on_restart
        #: The process of the current generation and the service's end of its pipe (``None``
        #: while it is being (re)started); both owned by the supervisor thread.
        self._proc: multiprocessing.process.BaseProcess | None = None
        self._conn: Connection | None = None
        #: Items sent to the current process and not answered yet, in order (it answers in order).
        self._inflight: list[tuple[Any, ...]] = []
        #: Items that were in flight when a process died: in flight at a second death, dropped.
        self._retried: set[Hashable] = set()
        #: Keyframes offered and not yet in the log (:meth:`_log_loop` appends them, in order,
        #: before they are queued for the process); the writer holds ``_writing`` while it does.
        self._unlogged: list[tuple[Any, ...]] = []
        self._writing = threading.Lock()
        self._writer: threading.Thread | None = None
        #: Per map, its deletions the process has not answered yet (:meth:`forget_map`): what it
        #: says of the map until then is of the deleted map, not of a new one of the same name.
        self._forgetting: dict[str, int] = {}
        #: how many times the process died and was started again; how the last one ended
        self.restarts = 0
        self.last_exit: str | None = None
        self._supervisor: threading.Thread | None = None
        self._sender: threading.Thread | None = None
        #: :meth:`cpu_s`: the process last read, its CPU then, and that of the generations before
        #: the last answer, or when work went in flight to an idle process (_guard_starvation)
        self._progress_at = time.monotonic()
        #: the process runs above SCHED_IDLE for now (starved), and how often it was raised; runs
        #: at the service's niceness for now (raised and still behind), and how often
        self.raised = False
        self.starvations = 0
        self.escalated = False
        self.escalations = 0
        self._raised_at = 0.0
        self._cpu_pid: int | None = None
        self._cpu_last = 0.0
        self._cpu_dead = 0.0
        #: each process's CPU when it said it is alive (its start, not counted by :meth:`cpu_s`)
        self._cpu_at_alive: dict[int, float] = {}
        self._restore()

    # -- the durable graph (service/graph_log.py) ----------------------------------------------
    def _restore(self) -> None:
        """A (re)started service: the keyframes the graph took before, as it took them, so that
        the graph process rebuilds the graph from them before it takes new ones; the service's
        side (each keyframe's live pose, the sessions' maps) is set up here."""
        if self._log is None:
            return
        try:
            floors = self._log.floors()
        except RandtError as exc:
            log.error("pose graph: %s: the revisions of maps deleted before may start lower", exc)
            floors = {}
        self.view.bases = {name: (revision, 0) for name, revision in floors.items()}
        records = self._replayable(self._log.read())
        if not records:
            return
        self.view.restore(records)
        log.info("pose graph: %d keyframes to take again from %s", len(records), self._log.path)
        with self._cond:
            self._queue_replay([item for _, item in records])
            self._start()

    @staticmethod
    def _replayable(records: list[tuple[Any, ...]]) -> list[tuple[float, tuple[Any, ...]]]:
        """The logged keyframes the graph is to take again, in order: every one offered, but
        those a ``drop`` record names (dropped by a full queue, or in flight at two deaths of the
        process: the graph never took them)."""
        dropped = {tuple(item[1:5]) for _, item in records if item[0] == "drop"}
        return [
            (stamp, item)
            for stamp, item in records
            if item[0] == "keyframe" and tuple(item[1:5]) not in dropped
        ]

    def _queue_replay(self, items: list[tuple[Any, ...]]) -> None:
        """Queue the logged ``items`` first (under ``_cond``), marked as replayed."""
        self._replay_ids = {id(item) for item in items}
        self._queued[:0] = items
        self._offered += len(items)
        self._cond.notify_all()

    def _log_loop(self) -> None:
        """The writer: each offered keyframe appended to the log and fsync'd, in the order offered,
        then queued for the process (so the graph takes them in the log's order, and shows
        nothing made of a keyframe before it is durable). One that cannot be written is not
        given to the graph (counted; logged)."""
        assert self._log is not None
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._closed or bool(self._unlogged))
                if self._closed:
                    return
            with self._writing:
                with self._cond:
                    if not self._unlogged:  # (taken out by forget_map meanwhile)
                        continue
                    item = self._unlogged[0]
                ok = self._append(self._stamp_of(item), item)
                with self._cond:
                    if self._unlogged and self._unlogged[0] is item:
                        self._unlogged.pop(0)
                    if not ok:
                        self._offered -= 1
                        self._cond.notify_all()
                        dropped = None
                    else:
                        dropped = self._enqueue(item)
                if not ok:
                    self.view.forget_keyframe(item[1], (item[2], item[3]), item[4])
                elif dropped is not None:  # logged before: the graph never took it
                    self._append(0.0, ("drop", *dropped[1:5]))

    def _append(self, stamp_s: float, item: tuple[Any, ...]) -> bool:
        assert self._log is not None
        try:
            self._log.append((stamp_s, item))
        except RandtError:
            self._metrics.store_errors.inc()
            log.exception("pose graph: %s %s/%s seq %d not made durable", item[0], item[2], item[3], item[4])
            return False
        return True

    def _stamp_of(self, item: tuple[Any, ...]) -> float:
        """The stamp of a keyframe item (the service keeps it beside, in its ``Keyframe``)."""
        _, map_name, vehicle, session, _seq, index = item[:6]
        return self.view.stamp_of(map_name, (vehicle, session), index)

    def _enqueue(self, item: tuple[Any, ...]) -> tuple[Any, ...] | None:
        """Queue a keyframe for the process (under ``_cond``); when ``graph_queue`` keyframes
        wait, the oldest is dropped (counted, logged; never one taken again from the log), and
        returned."""
        keyframes = [  # (what the graph took before, from its log, is never dropped)
            i
            for i, queued in enumerate(self._queued)
            if queued[0] == "keyframe" and id(queued) not in self._replay_ids
        ]
        dropped = None
        if len(keyframes) >= self._queue_size:
            dropped = self._queued.pop(keyframes[0])
            self._offered -= 1
            self._metrics.graph_queue_dropped.inc()
            log.warning("pose graph behind: keyframe %s/%s seq %d dropped", *dropped[2:5])
            self.view.forget_keyframe(dropped[1], (dropped[2], dropped[3]), dropped[4])
        self._queued.append(item)
        self._cond.notify_all()
        return dropped

    @property
    def started(self) -> bool:
        """A keyframe has been offered: the graph process is (or is being) run."""
        return self._supervisor is not None

    @property
    def running(self) -> bool:
        """The graph process of the current generation is alive."""
        proc = self._proc
        return proc is not None and proc.is_alive()

    @property
    def pending(self) -> int:
        """Keyframes offered that the process has not answered yet (the graph's lag)."""
        return max(0, self._offered - self._done)

    @property
    def pid(self) -> int | None:
        proc = self._proc
        return None if proc is None else proc.pid

    def cpu_s(self) -> float:
        """CPU seconds the graph's processes have used so far, every generation counted (Linux,
        from /proc; 0 elsewhere): the node's admission counts them (service/capacity.py). A
        process's start (spawn and imports until it says it is alive) is not counted: it is no
        cost per sweep, and billed to one flush's sweeps it would fill the node's capacity
        (docs/benchmarks.md, "One vehicle within capacity")."""
        pid = self.pid
        now = 0.0
        if pid is not None:
            with contextlib.suppress(OSError, ValueError, IndexError):
                started = self._cpu_at_alive.get(pid)
                now = 0.0 if started is None else max(process_cpu_s(pid) - started, 0.0)
        with self.view.lock:
            if pid != self._cpu_pid:  # a new generation: the last one's CPU stays counted
                self._cpu_dead += self._cpu_last
                self._cpu_pid, self._cpu_last = pid, 0.0
            self._cpu_last = max(self._cpu_last, now)
            return self._cpu_dead + self._cpu_last

    def _start(self) -> None:
        """Start the supervisor and the sender with the first keyframe (under ``_cond``): a
        service that never sees one never pays for the process."""
        if self._supervisor is not None:
            return
        # At interpreter exit multiprocessing terminates daemonic children (its own atexit hook,
        # registered at its import, so it runs after this one): the supervisor must not take
        # that for a death to recover from.
        atexit.register(self._closing_at_exit)
        self._supervisor = threading.Thread(target=self._supervise, name="graph-supervisor", daemon=True)
        self._sender = threading.Thread(target=self._send_loop, name="graph-sender", daemon=True)
        self._supervisor.start()
        self._sender.start()
        if self._log is not None:
            self._writer = threading.Thread(target=self._log_loop, name="graph-log-writer", daemon=True)
            self._writer.start()

    def _closing_at_exit(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    # -- the process's life (supervisor thread) ----------------------------------------------
    def _supervise(self) -> None:
        """Run the graph process for as long as this object is open: start it, and start it
        again whenever it dies (logged, counted in ``randt_graph_restarts``, shown by ``/status``
        and ``/readyz``), after a pause that doubles while it keeps dying young.

        The process is started from this thread, which lives until :meth:`close`: the graph
        process asks for SIGKILL when the *thread* that started it exits (``PR_SET_PDEATHSIG``
        follows the forking thread, not the process), so it must not be started from a session's
        worker thread, which ends with its session."""
        pause = 0.0
        while True:
            with self._cond:
                if self._closed:
                    return
            proc, conn = self._spawn()
            receiver = threading.Thread(
                target=self._receive_loop, args=(conn, proc.pid), name="graph-receiver"
            )
            receiver.daemon = True
            receiver.start()
            started = time.monotonic()
            self._metrics.graph_up.set(1)
            self.raised = self.escalated = False  # a new process starts at SCHED_IDLE (lowest_priority)
            while proc.is_alive() and not self._closed:
                multiprocessing.connection.wait([proc.sentinel], timeout=0.5)
                self._guard_starvation(proc.pid)
            if self._closed:
                self._stop_process(proc, conn, receiver)
                return
            proc.join()
            self._died(proc, conn, receiver)
            pause = 0.0 if time.monotonic() - started > 30.0 else min(max(2 * pause, 0.5), 30.0)
            with self._cond:
                self._cond.wait_for(lambda: self._closed, timeout=pause)

    def _guard_starvation(self, pid: int | None) -> None:
        """Raise a starved graph process above ``SCHED_IDLE`` (:data:`STARVED_S`), to the service's
        own niceness if it is still behind (:data:`ESCALATE_S`), and lower it again once it has
        caught up."""
        if pid is None:
            return
        now = time.monotonic()
        with self._cond:
            busy = bool(self._inflight or self._queued)
            starved = bool(self._inflight) and now - self._progress_at > STARVED_S
        if starved and not self.raised and set_graph_priority(pid, idle=False):
            self.raised, self._raised_at = True, now
            self.starvations += 1
            log.warning(
                "pose graph: no answer for %.0f s with work in flight (other processes take every "
                "core): it runs niced by %d instead of SCHED_IDLE until it catches up",
                STARVED_S,
                GRAPH_NICE,
            )
        elif busy and self.raised and not self.escalated and now - self._raised_at > ESCALATE_S:
            if set_graph_priority(pid, idle=False, nice=0):
                self.escalated = True
                self.escalations += 1
                log.warning(
                    "pose graph: still behind %.0f s after it was raised: it runs at the service's "
                    "niceness until it catches up",
                    ESCALATE_S,
                )
        elif not busy and self.raised and set_graph_priority(pid, idle=True):
            self.raised = self.escalated = False
            log.info("pose graph: caught up, back to SCHED_IDLE")

    def _spawn(self) -> tuple[multiprocessing.process.BaseProcess, Connection]:
        ctx = multiprocessing.get_context("spawn")
        conn, child = ctx.Pipe()
        proc = ctx.Process(
            target=graph_main,
            args=(child, self.settings, self.geometry, self.refold_s, os.getpid(), self._spill),
            name="randt-graph",
            daemon=True,
        )
        start_ignoring_group_signals(proc)
        child.close()
        # The gate holds the process only once it says it is alive (_receive_loop): by then it
        # dies with the service even while stopped.
        with self._cond:
            self._proc, self._conn = proc, conn
            self._cond.notify_all()  # the sender may go on
        return proc, conn

    def _died(
        self, proc: multiprocessing.process.BaseProcess, conn: Connection, receiver: threading.Thread
    ) -> None:
        """The process died by itself: what it had not answered goes to the next one (once), the
        maps' revisions and loops go on from where they were, and the sessions it had placed into
        another map than their own are placed there again."""
        if self.gate is not None:
            self.gate.detach()
        receiver.join(10.0)
        conn.close()
        code = proc.exitcode
        how = f"signal {-code}" if code is not None and code < 0 else f"exit code {code}"
        self._metrics.graph_up.set(0)
        self._metrics.graph_restarts.inc()
        with self._writing, self._cond:  # (the writer is between two keyframes)
            self._proc = self._conn = None
            self.restarts += 1
            self.last_exit = how
            retry, poison = [], []
            for item in self._inflight:
                key = _retry_key(item)
                if key in self._retried:  # in flight at two deaths: it may be what kills it
                    self._retried.discard(key)
                    self._replay_ids.discard(id(item))
                    log.error("pose graph: %s dropped, in flight at two deaths of the process", item[0])
                    if item[0] == "keyframe":
                        self._offered -= 1
                        self.view.forget_keyframe(item[1], (item[2], item[3]), item[4])
                        poison.append(item)
                    elif item[0] == "sync":
                        self._synced = max(self._synced, item[1])
                    elif item[0] == "forget":
                        self._forgotten(item[1])
                    continue
                self._retried.add(key)
                retry.append(item)
            self._inflight = []
            places = self.view.rebase(empty=self._log is None)
            self._queued[:0] = places + retry
            if self._log is not None:
                # Every keyframe queued or in flight is in the log: the log, taken again in order,
                # brings them back (but those dropped at two deaths), then what waits to be logged.
                kept = [item for item in self._queued if item[0] != "keyframe"]
                self._offered -= len(self._queued) - len(kept)
                self._queued = kept
                for item in poison:
                    self._append(0.0, ("drop", *item[1:5]))
                self._queue_replay([item for _, item in self._replayable(self._log.read())])
            self._cond.notify_all()
        log.error(
            "the pose graph process died (%s): restarting it; its keyframes before now stay as they "
            "were (%d keyframes re-sent)",
            how,
            sum(item[0] == "keyframe" for item in retry),
        )
        if self._on_restart is not None:
            self._on_restart()

    def _stop_process(
        self, proc: multiprocessing.process.BaseProcess, conn: Connection, receiver: threading.Thread
    ) -> None:
        """:meth:`close`: ask the process to quit, kill it if it does not."""
        if self.gate is not None:
            self.gate.detach()
        if self._send_lock.acquire(timeout=10.0):  # (else a send is stuck: the kill below ends it)
            try:
                with contextlib.suppress(OSError, ValueError):
                    conn.send(("quit",))
            finally:
                self._send_lock.release()
        proc.join(10.0)
        if proc.is_alive():
            proc.kill()
            proc.join(10.0)
        receiver.join(10.0)
        conn.close()
        self._metrics.graph_up.set(0)

    # -- input (session threads) -------------------------------------------------------------
    def forget_map(self, map_name: str) -> None:
        """A deleted map's graph goes (SessionManager.delete_map, whose sessions have ended):
        from the log first (:meth:`GraphLog.without_map`: a restart never brings it back), then
        from the queue, the process and what the service shows. Its revision stays the floor of
        a later map of the same name (``floors.json``). Until the process says it dropped the
        map, what it says of the map is of the deleted one and is not applied.

        Raises
        ------
        FormatError
            The log could not be rewritten (the graph is then as it was).
        """
        revision = self.view.revision(map_name)
        with self._writing:  # (the log's writer waits: nothing of the map is logged after this)
            if self._log is not None:
                self._log.set_floor(map_name, revision)
                gone = self._log.without_map(map_name)
                log.info("pose graph of map %s deleted (%d records out of its log)", map_name, gone)
            with self._cond:
                ours = [it for it in self._unlogged if it[1] == map_name]
                self._unlogged = [
                    it if it[-1] != map_name else (*it[:-1], None)
                    for it in self._unlogged
                    if it[1] != map_name
                ]
                self._offered -= len(ours)
                if self._supervisor is not None and not self._closed:
                    self._forgetting[map_name] = self._forgetting.get(map_name, 0) + 1
                    kept = [it for it in self._queued if not (it[0] == "keyframe" and it[1] == map_name)]
                    self._offered -= len(self._queued) - len(kept)
                    self._replay_ids -= {id(it) for it in self._queued} - {id(it) for it in kept}
                    self._queued = [*kept, ("forget", map_name)]
                self._cond.notify_all()
        self.view.forget(map_name, revision)

    def _forgotten(self, map_name: str) -> None:
        """The process dropped a deleted map (under ``_cond``)."""
        left = self._forgetting.get(map_name, 0) - 1
        if left > 0:
            self._forgetting[map_name] = left
        else:
            self._forgetting.pop(map_name, None)

    def offer(
        self,
        vehicle: str,
        session: str,
        *,
        map_name: str,
        seq: int,
        index: int,
        stamp_s: float,
        T_live: np.ndarray,
        points: np.ndarray,
        intensity: np.ndarray | None = None,
        gnss: tuple[np.ndarray, np.ndarray] | None = None,
        join: str | None = None,
    ) -> None:
        """Queue a keyframe of a session in map ``map_name``: a durable pose ``T_live`` (sweep
        ``index``), its points (sensor frame, deskewed) with their intensity, and its GNSS fix.
        The points also make the map's tiles when the graph re-folds them. ``join``: the shared
        map a session without priors (in a map of its own) may join, once the graph places it
        there (:meth:`joined`). Never blocks: when ``graph_queue`` keyframes wait, the oldest is
        dropped (counted, logged)."""
        map_name = self.view.offered(
            (vehicle, session), map_name, Keyframe(seq, index, stamp_s, T_live.copy())
        )
        if map_name == join:
            join = None
        item = ("keyframe", map_name, vehicle, session, seq, index, T_live, points, intensity, gnss, join)
        with self._cond:
            if self._closed:
                return
            self._start()
            self._offered += 1
            if self._log is None:
                self._enqueue(item)
                return
            self._unlogged.append(item)  # (to the log first: _log_loop)
            if len(self._unlogged) > self._queue_size:  # the disk is behind: never logged, no record
                dropped = self._unlogged.pop(0)
                self._offered -= 1
                self._metrics.graph_queue_dropped.inc()
                log.warning("pose graph log behind: keyframe %s/%s seq %d dropped", *dropped[2:5])
                self.view.forget_keyframe(dropped[1], (dropped[2], dropped[3]), dropped[4])
            self._cond.notify_all()

    def _send_loop(self) -> None:
        """Queued items to the current process, in order; an item whose send fails (the process
        died) waits at the head of the queue for the next one."""
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._closed or (self._queued and self._conn is not None))
                if self._closed:
                    return
                item = self._queued.pop(0)
                conn = self._conn
                assert conn is not None
                if not self._inflight:  # work for a process that had none: starvation counts from now
                    self._progress_at = time.monotonic()
                self._inflight.append(item)
            try:
                with self._send_lock:
                    conn.send(item)
            except (OSError, ValueError):  # the supervisor restarts it
                with self._cond:
                    if self._inflight and self._inflight[-1] is item:
                        self._inflight.pop()
                        self._queued.insert(0, item)
                    dead = conn
                    self._cond.wait_for(lambda: self._closed or self._conn is not dead)  # noqa: B023

    def _answered(self) -> None:
        """The process answered the oldest item in flight (under ``_cond``). Its id leaves the
        sets that mark items by id: once the item is gone, a new one may get the same id (and a
        new keyframe would pass for a replayed one: neither logged nor published)."""
        self._progress_at = time.monotonic()
        if self._inflight:
            item = self._inflight.pop(0)
            self._retried.discard(_retry_key(item))
            self._replay_ids.discard(id(item))

    # -- output (receiver thread) ------------------------------------------------------------
    def _receive_loop(self, conn: Connection, pid: int | None) -> None:
        """One process's answers, until its pipe closes; its first, ``alive``, lets the gate hold it."""
        while True:
            try:
                message = conn.recv()
            except (EOFError, OSError):
                return
            if message[0] == "alive":
                if pid is not None:
                    with contextlib.suppress(OSError, ValueError, IndexError):
                        self._cpu_at_alive[pid] = process_cpu_s(pid)
                if self.gate is not None and pid is not None and not self._closed:
                    self.gate.attach(pid)
                continue
            if message[0] in ("synced", "placed", "forgotten"):
                with self._cond:
                    self._answered()
                    if message[0] == "synced":
                        self._synced = max(self._synced, message[1])
                    if message[0] == "forgotten":
                        self._forgotten(message[1])
                    self._cond.notify_all()
                continue
            if message[0] in ("update", "refused"):  # the answer to the oldest item in flight
                with self._cond:
                    item = self._inflight[0] if self._inflight else None
                    self._answered_replay = item is not None and id(item) in self._replay_ids
            with self._cond:
                stale = message[1] in self._forgetting  # of a deleted map (forget_map)
            try:
                if not stale:
                    self.view.apply(message, publish=not self._answered_replay)
            except Exception:  # a bug must not stop the graph's output
                log.exception("pose graph: an update could not be applied")
            if message[0] in ("update", "refused"):  # one per keyframe offered
                with self._cond:
                    self._answered()
                    self._done += 1
                    self._cond.notify_all()

    # -- reads -------------------------------------------------------------------------------
    # -- reads (the service's view of the graphs: graph_state.GraphView) ---------------------
    def wants_keyframe(self, vehicle: str, session: str, poses: list[np.ndarray]) -> bool:
        """:meth:`GraphView.wants_keyframe`."""
        return self.view.wants_keyframe(vehicle, session, poses)

    def fold_target(self, vehicle: str, session: str, map_name: str) -> tuple[np.ndarray | None, str]:
        """:meth:`GraphView.fold_target`."""
        return self.view.fold_target(vehicle, session, map_name)

    def joined(self, vehicle: str, session: str) -> tuple[str, np.ndarray] | None:
        """:meth:`GraphView.joined`."""
        return self.view.joined(vehicle, session)

    def correction(self, vehicle: str, session: str) -> np.ndarray | None:
        """:meth:`GraphView.correction`."""
        return self.view.correction(vehicle, session)

    def corrected(self, vehicle: str, session: str, poses: np.ndarray) -> tuple[np.ndarray, str | None]:
        """:meth:`GraphView.corrected`."""
        return self.view.corrected(vehicle, session, poses)

    def corrected_marked(
        self, vehicle: str, session: str, poses: np.ndarray
    ) -> tuple[np.ndarray, str | None, np.ndarray]:
        """:meth:`GraphView.corrected_marked`."""
        return self.view.corrected_marked(vehicle, session, poses)

    def maps(self) -> list[str]:
        """:meth:`GraphView.maps`."""
        return self.view.maps()

    def snapshot(self, map_name: str) -> GraphState | None:
        """:meth:`GraphView.snapshot`."""
        return self.view.snapshot(map_name)

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Wait until the process has answered every queued keyframe and re-folded the tiles of
        those that moved (tests and benchmarks: the map as the graph has it now)."""
        deadline = time.monotonic() + timeout

        def wait(done: Callable[[], bool]) -> bool:
            while not done():
                left = deadline - time.monotonic()
                if left <= 0 or self._closed:
                    return False
                self._cond.wait(min(left, 0.5))
            return True

        with self._cond:
            if self._supervisor is None:
                return True
            if not wait(lambda: self._done >= self._offered):
                return False
            self._syncs += 1
            token = self._syncs
            self._queued.append(("sync", token))
            self._cond.notify_all()
            return wait(lambda: self._synced >= token)

    def matching(self) -> contextlib.AbstractContextManager[None]:
        """Around the matching of one sweep (SessionWorker): with ``graph_yield``, the graph
        process does not run while any sweep is inside (:class:`YieldGate`)."""
        return contextlib.nullcontext() if self.gate is None else self.gate.matching()

    def close(self, timeout: float = 10.0) -> None:
        """Stop feeding the process and stop it (what is still queued is not processed)."""
        with self._cond:
            self._closed = True
            self._queued.clear()
            self._cond.notify_all()
        atexit.unregister(self._closing_at_exit)
        if self.gate is not None:
            self.gate.detach()
        if self._sender is not None:
            self._sender.join(timeout)
        if self._supervisor is not None:  # it stops the process (``_stop_process``)
            self._supervisor.join(3 * timeout)
