"""The running sessions, the ones being opened and the ones being closed, under one lock.

The lock guards these sets only and is never held across a store read, a matcher call or a
matcher warm-up: ``/status`` and other vehicles' scans never wait for one.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from dataclasses import dataclass, field

from randt.service.metrics import ServiceMetrics
from randt.service.queueing import Job, queue_label
from randt.service.session_info import SessionInfo
from randt.service.snapshots import SessionSaver
from randt.service.store import SessionState as RecordState
from randt.service.worker import SessionWorker
from randt.wire.messages import ScanHeader

__all__ = ["Opening", "SessionTable"]

Key = tuple[str, str]


@dataclass
class Opening:
    """A session being opened by an opener thread: holds its slot; its scans wait here meanwhile."""

    first: ScanHeader
    jobs: deque[Job] = field(default_factory=deque)
    #: A running session that gave up its slot (admission): saved and closed before the open.
    evict: SessionWorker | None = None
    #: Expected to localize: the opener waits for a start slot (Capacity.try_start) first.
    localizing: bool = False
    done: threading.Event = field(default_factory=threading.Event)


class SessionTable:
    """Which sessions run, open and close; closing one drains, saves and stops it."""

    def __init__(self, saver: SessionSaver, metrics: ServiceMetrics) -> None:
        self.saver, self.metrics = saver, metrics
        self.lock = threading.RLock()
        self.workers: dict[Key, SessionWorker] = {}
        self.opening: dict[Key, Opening] = {}
        #: Sessions between leaving ``workers`` and their final save: a scan for one is refused
        #: (session_busy) rather than reopening it from an older saved state.
        self.closing: set[Key] = set()
        self.openers: set[threading.Thread] = set()

    # -- queries ----------------------------------------------------------------------------------
    def worker(self, key: Key) -> SessionWorker | None:
        with self.lock:
            return self.workers.get(key)

    def running(self) -> list[SessionWorker]:
        with self.lock:
            return list(self.workers.values())

    def infos(self) -> list[SessionInfo]:
        with self.lock:
            return [w.info for w in self.workers.values()]

    def depths(self) -> dict[str, int]:
        with self.lock:
            return {f"{k[0]}/{k[1]}": w.depth() for k, w in self.workers.items()}

    def keys(self) -> list[Key]:
        """The sessions that count against the node: running and being opened."""
        with self.lock:
            return [*self.workers, *self.opening]

    def opening_keys(self) -> list[Key]:
        with self.lock:
            return list(self.opening)

    def map_in_use(self, map_name: str) -> bool:
        """Whether a running session lives in ``map_name``'s frame."""
        with self.lock:
            return any(w.info.map_name == map_name for w in self.workers.values())

    def users_of(self, map_name: str, *, but: SessionWorker | None = None) -> list[str]:
        """The running sessions (``vehicle/session``) that fold into ``map_name``."""
        with self.lock:
            return sorted(
                f"{w.info.vehicle}/{w.info.session}"
                for w in self.workers.values()
                if w is not but and map_name in (w.info.map_name, w.info.joined_map)
            )

    def wait_openings(self, timeout: float | None = None) -> bool:
        """Wait until no session is being opened; whether that happened in time."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            with self.lock:
                pending = list(self.opening.values())
            if not pending:
                return True
            for opening in pending:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                opening.done.wait(left)

    # -- changes ----------------------------------------------------------------------------------
    def install(self, worker: SessionWorker) -> None:
        """An opened session joins the running set (under the lock)."""
        self.workers[worker.key] = worker
        self.metrics.sessions_active.set(len(self.workers))
        worker.info.last_activity = time.monotonic()

    def leave(self, w: SessionWorker) -> None:
        """A broken session leaves the running set (its worker's call)."""
        with self.lock:
            if self.workers.get(w.key) is w:
                del self.workers[w.key]
                self.metrics.sessions_active.set(len(self.workers))

    def detach(self, key: Key) -> SessionWorker | None:
        """Take a session out of the running set into ``closing`` (under the lock)."""
        w = self.workers.pop(key, None)
        self.metrics.sessions_active.set(len(self.workers))
        if w is not None:
            self.closing.add(w.key)
        return w

    def close(self, key: Key, state: RecordState) -> bool:
        """Finish a session: process what is queued, save it, stop its worker. False if unknown.

        A session being opened is closed once open (this waits for the opening)."""
        with self.lock:
            opening = self.opening.get(key)
        if opening is not None:
            opening.done.wait(120)
        with self.lock:
            w = self.detach(key)
        if w is None:
            return False
        self.finish_close(w, state)
        return True

    def finish_close(self, w: SessionWorker, state: RecordState) -> None:
        """Drain, save and stop a detached session (no lock held: it waits on the worker)."""
        try:
            w.stop(drain=True)
            w.fold(release=True)
            self.saver.save(w, state=state)
        finally:
            with self.lock:
                self.closing.discard(w.key)
        w.matcher.close()
        with contextlib.suppress(KeyError):  # a closed session's queue is no longer a time series
            self.metrics.queue_depth.remove(queue_label(*w.key))
