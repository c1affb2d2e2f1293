"""Scan intake: the Zenoh callback only enqueues bytes; intake workers decode and admit them, fairly.

:meth:`Intake.put` (the callback's, O(1)) appends a payload to its vehicle's bounded queue; on
overflow the vehicle's oldest (for the total, the largest queue's) is dropped and answered
``dropped``. The workers serve vehicles round-robin, a vehicle on one worker at a time so its scans
stay in order: a vehicle that floods loses only its own payloads, and another's scan waits for at
most one bounded-cost payload of each vehicle with work (docs/architecture.md, "Intake").
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from randt.wire.ros2 import Ros2Scan

__all__ = ["ITEM_OVERHEAD_BYTES", "Intake"]

log = logging.getLogger(__name__)

#: Bytes charged per queued payload on top of its length (the item's bookkeeping), so a flood of
#: tiny payloads is bounded by the byte limits too.
ITEM_OVERHEAD_BYTES = 256

#: ``handle(vehicle, payload, received_ns)``: decode, validate and admit one payload.
Handler = Callable[[str, "bytes | Ros2Scan", int], None]
#: ``on_drop(vehicle, payload, reason)``: answer a payload the intake dropped (``dropped``).
DropHandler = Callable[[str, "bytes | Ros2Scan", str], None]


@dataclass
class _Item:
    payload: bytes | Ros2Scan
    received_ns: int

    @property
    def cost(self) -> int:
        return len(self.payload) + ITEM_OVERHEAD_BYTES


@dataclass
class _VehicleQueue:
    items: deque[_Item] = field(default_factory=deque)
    nbytes: int = 0
    scheduled: bool = False  # in the ready ring, or being handled by a worker


class Intake:
    """Bounded per-vehicle queues of undecoded scans and the workers that drain them (module docstring).

    Parameters
    ----------
    handle:
        Called on a worker thread with one payload; must not raise (exceptions are logged).
    on_drop:
        Called with a payload dropped by the overload policy, on the thread that dropped it (the
        callback's): must be cheap and not block (a bounded peek and an outbox put).
    workers:
        Worker threads.
    max_scans, max_bytes:
        Per vehicle: payloads and bytes (with :data:`ITEM_OVERHEAD_BYTES` each) waiting at most.
        A vehicle with an empty queue always gets one payload in, whatever its size.
    total_bytes:
        All vehicles: bytes waiting at most; beyond, the vehicle with the most bytes waiting loses
        its oldest payload.
    """

    def __init__(
        self,
        handle: Handler,
        on_drop: DropHandler,
        *,
        workers: int,
        max_scans: int,
        max_bytes: int,
        total_bytes: int,
    ) -> None:
        self._handle = handle
        self._on_drop = on_drop
        self.max_scans = max_scans
        self.max_bytes = max_bytes
        self.total_bytes = total_bytes
        self._cond = threading.Condition()
        self._queues: dict[str, _VehicleQueue] = {}
        self._ready: deque[str] = deque()
        self._nbytes = 0
        self._busy = 0
        self._stopping = False
        self._threads = [
            threading.Thread(target=self._run, name=f"intake-{i}", daemon=True) for i in range(workers)
        ]
        for t in self._threads:
            t.start()

    # -- the callback side ------------------------------------------------------------------------
    def put(self, vehicle: str, payload: bytes | Ros2Scan, received_ns: int) -> None:
        """Queue one payload of ``vehicle`` (O(1) and non-blocking but for the overload answers)."""
        item = _Item(payload, received_ns)
        dropped: list[tuple[str, _Item, str]] = []
        with self._cond:
            if self._stopping:
                dropped.append((vehicle, item, "the service is stopping"))
            else:
                q = self._queues.get(vehicle)
                if q is None:
                    q = self._queues[vehicle] = _VehicleQueue()
                q.items.append(item)
                q.nbytes += item.cost
                self._nbytes += item.cost
                while len(q.items) > self.max_scans or (q.nbytes > self.max_bytes and len(q.items) > 1):
                    dropped.append((vehicle, self._pop_oldest(q), self._reason(q)))
                while self._nbytes > self.total_bytes:
                    victim, vq = max(self._queues.items(), key=lambda kv: kv[1].nbytes)
                    if not vq.items:
                        break
                    dropped.append(
                        (
                            victim,
                            self._pop_oldest(vq),
                            f"dropped: the service's intake held {self.total_bytes} bytes of undecoded "
                            "scans and this vehicle's queue was the largest",
                        )
                    )
                if q.items and not q.scheduled:
                    q.scheduled = True
                    self._ready.append(vehicle)
                    self._cond.notify()
        for who, gone, reason in dropped:
            try:
                self._on_drop(who, gone.payload, reason)
            except Exception:
                log.exception("answering a dropped scan of %r failed", who[:40])

    def _reason(self, q: _VehicleQueue) -> str:
        return (
            f"dropped: the vehicle's intake queue was full ({self.max_scans} scans or {self.max_bytes} "
            "bytes waiting to be decoded): send slower or smaller scans"
        )

    def _pop_oldest(self, q: _VehicleQueue) -> _Item:
        item = q.items.popleft()
        q.nbytes -= item.cost
        self._nbytes -= item.cost
        return item

    # -- the worker side --------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._ready:
                    if self._stopping and self._busy == 0:  # drained
                        self._cond.notify_all()
                        return
                    self._cond.wait()
                vehicle = self._ready.popleft()
                q = self._queues[vehicle]
                if not q.items:  # emptied by the total-bytes policy while waiting in the ring
                    q.scheduled = False
                    del self._queues[vehicle]
                    continue
                item = self._pop_oldest(q)
                self._busy += 1
            try:
                self._handle(vehicle, item.payload, item.received_ns)
            except Exception:  # never let one payload kill an intake worker
                log.exception("intake: handling a scan of %r failed", vehicle[:40])
            with self._cond:
                self._busy -= 1
                if q.items:
                    self._ready.append(vehicle)  # to the back of the ring: round-robin
                else:
                    q.scheduled = False
                    if self._queues.get(vehicle) is q:
                        del self._queues[vehicle]
                self._cond.notify_all()

    # -- state and shutdown -----------------------------------------------------------------------
    def depths(self) -> dict[str, int]:
        """Payloads waiting per vehicle."""
        with self._cond:
            return {v: len(q.items) for v, q in self._queues.items() if q.items}

    @property
    def queued_bytes(self) -> int:
        return self._nbytes

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Wait until nothing is queued or being handled; whether that happened in time."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while self._ready or self._busy:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def stop(self, timeout: float = 30.0) -> None:
        """Refuse new payloads (answered ``dropped``), handle the queued ones, stop the workers."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        deadline = time.monotonic() + timeout
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
