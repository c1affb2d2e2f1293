"""The work between the service and its pose graph process: what waits to be logged, what is
queued, what was sent and not answered, and what a dead process leaves to the next one.

:class:`GraphQueue` holds it all under one condition: the session threads offer keyframes, the
log writer (service/graph_journal.py) moves them to the queue, the sender sends them, the receiver
marks them answered, and the supervisor (service/graph_supervisor.py) hands what a dead process
had in flight to the next one (docs/architecture.md, "Threads or processes").
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Hashable
from multiprocessing.connection import Connection
from typing import Any

from randt.service.metrics import ServiceMetrics

__all__ = ["GraphQueue", "Item", "retry_key"]

log = logging.getLogger(__name__)

#: What goes to the process: ("keyframe", map, vehicle, session, seq, index, ...), ("place", ...),
#: ("forget", map), ("sync", token).
Item = tuple[Any, ...]


def retry_key(item: Item) -> Hashable:
    """What names an item across the process's deaths: a keyframe by its map, session and seq
    (taken again from the log, it is another object), anything else by identity."""
    return ("keyframe", *item[1:5]) if item[0] == "keyframe" else id(item)


class GraphQueue:
    """The items on their way to the graph process and back (module docstring). Every field is
    read and written under :attr:`cond` (re-entrant: a method may be called with it held).

    ``forget_keyframe(item)`` tells the service's view that a keyframe it counted will never be
    taken (dropped by a full queue, or at two deaths of the process)."""

    def __init__(
        self, metrics: ServiceMetrics, forget_keyframe: Callable[[Item], None], queue_size: int = 64
    ) -> None:
        self.cond = threading.Condition()
        self._metrics = metrics
        self._forget_keyframe = forget_keyframe
        self.size = queue_size
        self.queued: list[Item] = []
        #: Items sent to the current process and not answered yet, in order (it answers in order).
        self.inflight: list[Item] = []
        #: Items that were in flight when a process died: in flight at a second death, dropped.
        self.retried: set[Hashable] = set()
        #: Keyframes offered and not yet in the log (the journal appends them, in order, before
        #: they are queued).
        self.unlogged: list[Item] = []
        #: Items of the log being taken again by the current process (ids), and whether the last
        #: keyframe answered was one: what they make is not published again.
        self.replay_ids: set[int] = set()
        self.answered_replay = False
        self.offered = 0  # keyframes queued (dropped ones subtracted) ...
        self.done = 0  # ... and answered by the process: wait_idle
        self.syncs = 0  # sync requests sent (wait_idle) ...
        self.synced = 0  # ... and answered
        #: Per map, its deletions the process has not answered yet: what it says of the map until
        #: then is of the deleted map, not of a new one of the same name.
        self.forgetting: dict[str, int] = {}
        #: The current process's end of the pipe (None while it is being (re)started), and one
        #: sender on it at a time (the sender, and the supervisor's ``quit``).
        self.pipe: Connection | None = None
        self.send_lock = threading.Lock()
        #: When the work in flight last moved (an answer, or work sent to an idle process).
        self.progress_at = time.monotonic()
        self.closed = False

    # -- in ------------------------------------------------------------------------------------
    def offer(self, item: Item, *, logged: bool) -> bool:
        """A new keyframe: to the log first (``logged``: the journal moves it on) or straight to
        the queue. False once closed. When the disk is behind by ``size`` keyframes, the oldest
        not logged is dropped (counted, logged; never logged, so no record)."""
        with self.cond:
            if self.closed:
                return False
            self.offered += 1
            if not logged:
                self.enqueue(item)
                return True
            self.unlogged.append(item)
            if len(self.unlogged) > self.size:
                dropped = self.unlogged.pop(0)
                self._drop(dropped, "pose graph log behind")
            self.cond.notify_all()
            return True

    def enqueue(self, item: Item) -> Item | None:
        """Queue a keyframe for the process; when ``size`` keyframes wait, the oldest is dropped
        (counted, logged; never one taken again from the log), and returned."""
        with self.cond:
            keyframes = [  # (what the graph took before, from its log, is never dropped)
                i
                for i, queued in enumerate(self.queued)
                if queued[0] == "keyframe" and id(queued) not in self.replay_ids
            ]
            dropped = None
            if len(keyframes) >= self.size:
                dropped = self.queued.pop(keyframes[0])
                self._drop(dropped, "pose graph behind")
            self.queued.append(item)
            self.cond.notify_all()
            return dropped

    def _drop(self, item: Item, why: str) -> None:
        self.offered -= 1
        self._metrics.graph_queue_dropped.inc()
        log.warning("%s: keyframe %s/%s seq %d dropped", why, *item[2:5])
        self._forget_keyframe(item)

    def replay(self, items: list[Item]) -> None:
        """Queue the logged ``items`` first, marked as replayed."""
        with self.cond:
            self.replay_ids = {id(item) for item in items}
            self.queued[:0] = items
            self.offered += len(items)
            self.cond.notify_all()

    def not_logged(self) -> None:
        """The head of :attr:`unlogged` could not be written (the caller popped it)."""
        with self.cond:
            self.offered -= 1
            self.cond.notify_all()

    # -- to the process (the sender thread) ----------------------------------------------------
    def send_loop(self) -> None:
        """Queued items to the current process, in order; an item whose send fails (the process
        died) waits at the head of the queue for the next one."""
        while True:
            with self.cond:
                self.cond.wait_for(lambda: self.closed or (bool(self.queued) and self.pipe is not None))
                if self.closed:
                    return
                item = self.queued.pop(0)
                conn = self.pipe
                assert conn is not None
                if not self.inflight:  # work for a process that had none: starvation counts from now
                    self.progress_at = time.monotonic()
                self.inflight.append(item)
            try:
                with self.send_lock:
                    conn.send(item)
            except (OSError, ValueError):  # the supervisor restarts it
                with self.cond:
                    if self.inflight and self.inflight[-1] is item:
                        self.inflight.pop()
                        self.queued.insert(0, item)
                    dead = conn
                    self.cond.wait_for(lambda: self.closed or self.pipe is not dead)  # noqa: B023

    def attach(self, pipe: Connection | None) -> None:
        """The pipe of a new process (None: it died); the sender goes on with it."""
        with self.cond:
            self.pipe = pipe
            self.cond.notify_all()

    # -- back (the receiver thread) ------------------------------------------------------------
    def answered(self, *, keyframe: bool = False) -> None:
        """The process answered the oldest item in flight (``keyframe``: with an update or a
        refusal, one per keyframe offered). Its id leaves the sets that mark items by id: once
        the item is gone, a new one may get the same id (and a new keyframe would pass for a
        replayed one: neither logged nor published)."""
        with self.cond:
            self.progress_at = time.monotonic()
            if self.inflight:
                item = self.inflight.pop(0)
                self.retried.discard(retry_key(item))
                self.replay_ids.discard(id(item))
            if keyframe:
                self.done += 1
            self.cond.notify_all()

    def answering_replay(self) -> bool:
        """The answer now read is to an item taken again from the log (not published again)."""
        with self.cond:
            item = self.inflight[0] if self.inflight else None
            self.answered_replay = item is not None and id(item) in self.replay_ids
            return self.answered_replay

    def synced_to(self, token: int) -> None:
        with self.cond:
            self.synced = max(self.synced, token)
            self.cond.notify_all()

    def forgotten(self, map_name: str) -> None:
        """The process dropped a deleted map."""
        with self.cond:
            left = self.forgetting.get(map_name, 0) - 1
            if left > 0:
                self.forgetting[map_name] = left
            else:
                self.forgetting.pop(map_name, None)
            self.cond.notify_all()

    def stale(self, map_name: str) -> bool:
        """What the process says of ``map_name`` is of a deleted map (:meth:`forget_map`)."""
        with self.cond:
            return map_name in self.forgetting

    # -- a dead process (the supervisor) --------------------------------------------------------
    def take_back(self, places: list[Item]) -> tuple[list[Item], list[Item]]:
        """The process died: what it had in flight goes first to the next one, after the
        ``places`` of the sessions it had placed into another map; what was in flight at two
        deaths is dropped (it may be what kills the process). Returns (retried, dropped
        keyframes)."""
        with self.cond:
            retry, poison = [], []
            for item in self.inflight:
                key = retry_key(item)
                if key not in self.retried:
                    self.retried.add(key)
                    retry.append(item)
                    continue
                self.retried.discard(key)
                self.replay_ids.discard(id(item))
                log.error("pose graph: %s dropped, in flight at two deaths of the process", item[0])
                if item[0] == "keyframe":
                    self.offered -= 1
                    self._forget_keyframe(item)
                    poison.append(item)
                elif item[0] == "sync":
                    self.synced = max(self.synced, item[1])
                elif item[0] == "forget":
                    self.forgotten(item[1])
            self.inflight = []
            self.queued[:0] = places + retry
            self.cond.notify_all()
            return retry, poison

    def drop_keyframes(self) -> None:
        """Every queued keyframe out (a durable graph takes them again from its log)."""
        with self.cond:
            kept = [item for item in self.queued if item[0] != "keyframe"]
            self.offered -= len(self.queued) - len(kept)
            self.queued = kept

    # -- a deleted map -------------------------------------------------------------------------
    def forget_map(self, map_name: str, *, running: bool) -> None:
        """Every keyframe of ``map_name`` out of what waits to be logged, and, with a process
        (``running``), out of the queue, followed by its ``forget``. Keyframes of other maps
        waiting to be logged that would join ``map_name`` join none."""
        with self.cond:
            ours = [it for it in self.unlogged if it[1] == map_name]
            self.unlogged = [
                it if it[-1] != map_name else (*it[:-1], None) for it in self.unlogged if it[1] != map_name
            ]
            self.offered -= len(ours)
            if running and not self.closed:
                self.forgetting[map_name] = self.forgetting.get(map_name, 0) + 1
                kept = [it for it in self.queued if not (it[0] == "keyframe" and it[1] == map_name)]
                self.offered -= len(self.queued) - len(kept)
                self.replay_ids -= {id(it) for it in self.queued} - {id(it) for it in kept}
                self.queued = [*kept, ("forget", map_name)]
            self.cond.notify_all()

    # -- reads ---------------------------------------------------------------------------------
    @property
    def pending(self) -> int:
        """Keyframes offered that the process has not answered yet (the graph's lag)."""
        return max(0, self.offered - self.done)

    def busy(self) -> tuple[bool, float | None]:
        """Work queued or in flight, and how long the work in flight has waited for an answer."""
        with self.cond:
            waited = time.monotonic() - self.progress_at if self.inflight else None
            return bool(self.inflight or self.queued), waited

    def wait_idle(self, timeout: float) -> bool:
        """Until the process has answered every keyframe offered, then a ``sync`` sent after them
        (it answers once it has re-folded what moved)."""
        deadline = time.monotonic() + timeout

        def wait(done: Callable[[], bool]) -> bool:
            while not done():
                left = deadline - time.monotonic()
                if left <= 0 or self.closed:
                    return False
                self.cond.wait(min(left, 0.5))
            return True

        with self.cond:
            if not wait(lambda: self.done >= self.offered):
                return False
            self.syncs += 1
            token = self.syncs
            self.queued.append(("sync", token))
            self.cond.notify_all()
            return wait(lambda: self.synced >= token)

    def close(self, *, clear: bool = True) -> None:
        """Nothing more goes in or out (what is still queued is not processed; ``clear``: and it
        goes)."""
        with self.cond:
            self.closed = True
            if clear:
                self.queued.clear()
            self.cond.notify_all()
