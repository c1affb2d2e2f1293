"""The pose graph process's life: started with the first keyframe, started again whenever it
dies, its answers read and applied, stopped with the service.

:class:`GraphSupervisor` runs the threads around the process: the supervisor (spawn, watch, a
dead process's work handed to the next), the receiver (answers into the service's view), the
sender (service/graph_queue.py) and the log writer (service/graph_journal.py).
docs/architecture.md, "Threads or processes".
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
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess

from randt.core.fleet_map import FleetMapSettings
from randt.service.graph_journal import GraphJournal
from randt.service.graph_priority import CpuMeter, StarvationGuard, YieldGate
from randt.service.graph_process import MapGeometry, graph_main
from randt.service.graph_queue import GraphQueue
from randt.service.graph_state import GraphView
from randt.service.metrics import ServiceMetrics
from randt.service.processes import start_ignoring_group_signals

__all__ = ["GraphSupervisor"]

log = logging.getLogger(__name__)


class GraphSupervisor:
    """Runs the graph process for as long as it is open (module docstring)."""

    def __init__(
        self,
        process_args: tuple[FleetMapSettings, MapGeometry, float],
        queue: GraphQueue,
        journal: GraphJournal,
        view: GraphView,
        metrics: ServiceMetrics,
        *,
        gate: YieldGate | None,
        on_restart: Callable[[], None] | None = None,
    ) -> None:
        self._process_args = process_args
        self._queue = queue
        self._journal = journal
        self._view = view
        self._metrics = metrics
        #: holds the graph process while sweeps are matched (``graph_yield``); None: never held
        self.gate = gate
        self._on_restart = on_restart
        self.guard = StarvationGuard()
        self.cpu = CpuMeter()
        #: The process of the current generation (``None`` while it is being (re)started).
        self.proc: BaseProcess | None = None
        #: how many times the process died and was started again; how the last one ended
        self.restarts = 0
        self.last_exit: str | None = None
        self._threads: dict[str, threading.Thread] = {}

    @property
    def started(self) -> bool:
        return bool(self._threads)

    def start(self) -> None:
        """Start the threads with the first keyframe: a service that never sees one never pays
        for the process."""
        with self._queue.cond:
            if self._threads:
                return
            # At interpreter exit multiprocessing terminates daemonic children (its own atexit
            # hook, registered at its import, so it runs after this one): the supervisor must not
            # take that for a death to recover from.
            atexit.register(self._closing_at_exit)
            loops = {"graph-supervisor": self._supervise, "graph-sender": self._queue.send_loop}
            if self._journal.durable:
                loops["graph-log-writer"] = self._journal.write_loop
            for name, loop in loops.items():
                self._threads[name] = threading.Thread(target=loop, name=name, daemon=True)
                self._threads[name].start()

    def _closing_at_exit(self) -> None:
        self._queue.close(clear=False)

    def _supervise(self) -> None:
        """Start the process, and start it again whenever it dies (logged, counted in
        ``randt_graph_restarts``, shown by ``/status`` and ``/readyz``), after a pause that
        doubles while it keeps dying young.

        The process is started from this thread, which lives until :meth:`stop`: the graph
        process asks for SIGKILL when the *thread* that started it exits (``PR_SET_PDEATHSIG``
        follows the forking thread, not the process), so it must not be started from a session's
        worker thread, which ends with its session."""
        q = self._queue
        pause = 0.0
        while not q.closed:
            proc, conn = self._spawn()
            receiver = threading.Thread(
                target=self._receive_loop, args=(conn, proc.pid), name="graph-receiver", daemon=True
            )
            receiver.start()
            started = time.monotonic()
            self._metrics.graph_up.set(1)
            self.guard.reset()
            while proc.is_alive() and not q.closed:
                multiprocessing.connection.wait([proc.sentinel], timeout=0.5)
                if proc.pid is not None:
                    busy, waited_s = q.busy()
                    self.guard.check(proc.pid, busy=busy, waited_s=waited_s)
            if q.closed:
                self._stop_process(proc, conn, receiver)
                return
            proc.join()
            self.died(proc, conn, receiver)
            pause = 0.0 if time.monotonic() - started > 30.0 else min(max(2 * pause, 0.5), 30.0)
            with q.cond:
                q.cond.wait_for(lambda: q.closed, timeout=pause)

    def _spawn(self) -> tuple[BaseProcess, Connection]:
        ctx = multiprocessing.get_context("spawn")
        conn, child = ctx.Pipe()
        settings, geometry, refold_s = self._process_args
        proc = ctx.Process(
            target=graph_main,
            args=(child, settings, geometry, refold_s, os.getpid(), self._journal.spill),
            name="randt-graph",
            daemon=True,
        )
        start_ignoring_group_signals(proc)
        child.close()
        # The gate holds the process only once it says it is alive (_receive_loop): by then it
        # dies with the service even while stopped.
        with self._queue.cond:
            self.proc = proc
            self._queue.attach(conn)  # the sender may go on
        return proc, conn

    def died(self, proc: BaseProcess, conn: Connection, receiver: threading.Thread) -> None:
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
        q, journal = self._queue, self._journal
        with journal.writing, q.cond:  # (the writer is between two keyframes)
            self.proc = None
            q.attach(None)
            self.restarts += 1
            self.last_exit = how
            retry, poison = q.take_back(self._view.rebase(empty=not journal.durable))
            if journal.durable:
                # Every keyframe queued or in flight is in the log: the log, taken again in order,
                # brings them back (but those dropped at two deaths), then what waits to be logged.
                q.drop_keyframes()
                for item in poison:
                    journal.drop(item)
                journal.replay()
        log.error(
            "the pose graph process died (%s): restarting it; its keyframes before now stay as they "
            "were (%d keyframes re-sent)",
            how,
            sum(item[0] == "keyframe" for item in retry),
        )
        if self._on_restart is not None:
            self._on_restart()

    def _stop_process(self, proc: BaseProcess, conn: Connection, receiver: threading.Thread) -> None:
        """:meth:`stop`: ask the process to quit, kill it if it does not."""
        if self.gate is not None:
            self.gate.detach()
        if self._queue.send_lock.acquire(timeout=10.0):  # (else a send is stuck: the kill ends it)
            try:
                with contextlib.suppress(OSError, ValueError):
                    conn.send(("quit",))
            finally:
                self._queue.send_lock.release()
        proc.join(10.0)
        if proc.is_alive():
            proc.kill()
            proc.join(10.0)
        receiver.join(10.0)
        conn.close()
        self._metrics.graph_up.set(0)

    def _receive_loop(self, conn: Connection, pid: int | None) -> None:
        """One process's answers, until its pipe closes; its first, ``alive``, lets the gate hold it."""
        q = self._queue
        while True:
            try:
                message = conn.recv()
            except (EOFError, OSError):
                return
            kind = message[0]
            if kind == "alive":
                if pid is not None:
                    self.cpu.alive(pid)
                if self.gate is not None and pid is not None and not q.closed:
                    self.gate.attach(pid)
            elif kind in ("synced", "placed", "forgotten"):
                with q.cond:
                    q.answered()
                    if kind == "synced":
                        q.synced_to(message[1])
                    elif kind == "forgotten":
                        q.forgotten(message[1])
            else:
                self._apply(message)

    def _apply(self, message: tuple[object, ...]) -> None:
        """An update, a refusal (the answer to the oldest item in flight: a keyframe) or a
        re-fold, into the service's view; what the process says of a deleted map is dropped."""
        keyframe = message[0] in ("update", "refused")
        replayed = self._queue.answering_replay() if keyframe else self._queue.answered_replay
        try:
            if not self._queue.stale(str(message[1])):
                self._view.apply(message, publish=not replayed)
        except Exception:  # a bug must not stop the graph's output
            log.exception("pose graph: an update could not be applied")
        if keyframe:
            self._queue.answered(keyframe=True)

    def stop(self, timeout: float) -> None:
        """Stop the threads (the supervisor stops the process)."""
        atexit.unregister(self._closing_at_exit)
        if self.gate is not None:
            self.gate.detach()
        for name in ("graph-sender", "graph-supervisor"):
            thread = self._threads.get(name)
            if thread is not None:
                thread.join(timeout if name == "graph-sender" else 3 * timeout)
