"""From the intake to a session: each scan's header decoded at bounded cost, admission, the
sequence check, and the session's queue, or the opening of a new session on an opener thread
(``docs/architecture.md``, "One scan, through the service"). Never waits for a store read or a
matcher."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

from randt.core.errors import BadMessageError, RandtError
from randt.service.admission import Admission, Refused
from randt.service.answers import Answers
from randt.service.capacity import Capacity
from randt.service.intake import Intake
from randt.service.localizing import expects_to_localize
from randt.service.opener import SessionOpener
from randt.service.queueing import Job, drop_index, queue_label
from randt.service.session_table import Opening, SessionTable
from randt.service.settings import ServiceSettings
from randt.service.worker import SessionWorker
from randt.wire.codes import ErrorCode
from randt.wire.ids import UNKNOWN_ID
from randt.wire.messages import SCAN_V2, ScanHeader, decode_scan, decode_scan_header, peek_ids, peek_seq
from randt.wire.ros2 import Ros2Scan
from randt.wire.ros2 import scan_header as ros2_scan_header
from randt.wire.ros2 import sweep_arrays as ros2_sweep_arrays

__all__ = ["ScanRouter"]

log = logging.getLogger(__name__)

#: A session expected to localize waits this long at most for a start slot (one start a core at
#: a time, service/capacity.py), checking every START_POLL_S.
START_WAIT_S = 1.0
START_POLL_S = 0.01


class ScanRouter:
    """Takes each scan from the transport to its session's queue; answers the ones it refuses."""

    def __init__(
        self,
        settings: ServiceSettings,
        table: SessionTable,
        answers: Answers,
        admission: Admission,
        capacity: Capacity | None,
        opener: SessionOpener,
    ) -> None:
        self.settings, self.table, self.answers = settings, table, answers
        self.admission, self.capacity, self.opener = admission, capacity, opener
        self.metrics, self.limits = answers.metrics, answers.limits
        self.intake = Intake(
            self.handle,
            self._answer_intake_drop,
            workers=settings.intake_workers,
            max_scans=settings.intake_queue_scans,
            max_bytes=settings.intake_queue_bytes,
            total_bytes=settings.intake_total_bytes,
        )

    # -- the transport callback's thread: enqueue only (service/intake.py) -------------------------
    def submit(self, key_vehicle: str, payload: bytes | Ros2Scan, received_ns: int | None = None) -> None:
        """Queue one scan payload published on ``randt/fleet/<key_vehicle>/scan`` (never blocks).

        The payload waits in ``key_vehicle``'s intake queue until an intake worker calls
        :meth:`handle`. A ``key_vehicle`` that is not an id has no key to answer on: the scan is
        counted as rejected (``invalid_id``) and logged, not queued.
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

    # -- an intake worker's thread --------------------------------------------------------------------
    def handle(self, key_vehicle: str, payload: bytes | Ros2Scan, received_ns: int) -> None:
        """Decode, validate and route one scan to its session."""
        try:
            scan = self._checked_header(key_vehicle, payload)
        except BadMessageError as exc:
            self.reject(key_vehicle, *self._peek(payload), exc.code, str(exc))
            return
        if scan is None:  # refused for capacity on its header
            return
        if self.capacity is not None:
            self.capacity.arrived((scan.vehicle, scan.session))
        with self.table.lock:
            dropped, refusal = self._route(Job(scan, received_ns, payload))
        if refusal is not None:
            self.reject(scan.vehicle, scan.session, scan.seq, *refusal)
        if dropped is not None:
            self._answer_dropped(dropped)

    def _checked_header(self, key_vehicle: str, payload: bytes | Ros2Scan) -> ScanHeader | None:
        """A scan's header, its bodies left to the matcher (raises BadMessageError); ``None`` when
        the scan would open a session the node cannot carry (answered here).

        A scan that may open a session is decoded whole first (rare: once a session): a body that
        does not decode never takes a slot, opens a session or reads the store."""
        if isinstance(payload, Ros2Scan):
            scan = ros2_scan_header(payload, self.limits)
        else:
            scan = decode_scan_header(payload, self.limits)
        if self._refused_for_capacity(scan, key_vehicle):  # (before its body costs anything)
            return None
        if (scan.vehicle, scan.session) not in self.table.workers:
            if isinstance(payload, Ros2Scan):
                ros2_sweep_arrays(payload)
            elif scan.v == SCAN_V2:
                decode_scan(payload, self.limits)
        if scan.vehicle != key_vehicle:
            raise BadMessageError(
                f"vehicle: message says {scan.vehicle!r} but was published on {key_vehicle!r}'s key",
                code=ErrorCode.INVALID_FIELD,
            )
        return scan

    def _refused_for_capacity(self, scan: ScanHeader, key_vehicle: str) -> bool:
        """A scan that would open a session the node cannot carry is refused on its header alone
        (answered ``sessions_full`` with ``retry_after_s``); admission checks again under the lock."""
        key, t = (scan.vehicle, scan.session), self.table
        if self.capacity is None or scan.vehicle != key_vehicle or key in t.workers or key in t.opening:
            return False
        why = self.admission.refusal_on_header([*t.workers, *t.opening], localizing=self._localizing(scan))
        if why is None:
            return False
        self.reject(
            scan.vehicle, scan.session, scan.seq, ErrorCode.SESSIONS_FULL, why, self.capacity.retry_after_s
        )
        return True

    def _localizing(self, scan: ScanHeader) -> bool:
        """Whether a session opened by ``scan`` is expected to localize on the map (its prior in
        the default map; admission counts it at a localizing session's cost)."""
        if not (self.settings.localize or scan.localize_only) or scan.prior is None:
            return False
        grid = self.opener.services.maps.grid(self.settings.default_map)
        return expects_to_localize(self.settings, grid, scan.prior.pose, only=scan.localize_only)

    def _route(self, job: Job) -> tuple[Job | None, tuple[str, str] | Refused | None]:
        """The job into its session's queue, the queue of the session being opened, or a new
        session's opening (under the table's lock); ``(the job dropped, the refusal)``."""
        scan, t = job.scan, self.table
        key = (scan.vehicle, scan.session)
        worker, opening, record = t.workers.get(key), t.opening.get(key), self.opener.saver.record(key)
        if worker is not None:
            return self._enqueue(worker, job), None
        if opening is not None:
            # The first scan opens the session (like a scan being processed); the others wait as
            # in a session queue, with a young session's overload policy.
            dropped = None
            if len(opening.jobs) - 1 >= self.settings.queue_size:
                k = 1 + drop_index(deque(list(opening.jobs)[1:]), n_processed=0)
                dropped = opening.jobs[k]
                del opening.jobs[k]
            opening.jobs.append(job)
            return dropped, None
        if key in t.closing:
            why = "the session is being saved (closed or expired a moment ago): send the scan again"
            return None, (ErrorCode.SESSION_BUSY, why)
        if record is not None and record.state == "closed":
            why = (
                f"session {scan.session!r} of vehicle {scan.vehicle!r} was closed: "
                "publish under a new session id"
            )
            return None, (ErrorCode.SESSION_CLOSED, why)
        localizing = self._localizing(scan)
        admitted = self.admission.admit(key, t.workers, t.opening, t.closing, localizing=localizing)
        if isinstance(admitted, tuple):
            return None, admitted
        if admitted is not None:
            log.info(
                "session %s/%s gives its slot to %s/%s (idle %.1f s): saved as expired",
                *admitted.key, *key, time.monotonic() - admitted.info.last_activity,
            )  # fmt: skip
            t.detach(admitted.key)
        opening = t.opening[key] = Opening(scan, deque([job]), evict=admitted, localizing=localizing)
        opener = threading.Thread(
            target=self._open, args=(key, opening), name=f"open-{key[0]}-{key[1]}", daemon=True
        )
        t.openers.add(opener)
        opener.start()
        return None, None

    def _enqueue(self, worker: SessionWorker, job: Job) -> Job | None:
        """Seq check and enqueue on a running session (under the table's lock); the job dropped."""
        scan, info = job.scan, worker.info
        if scan.seq == info.last_seq:
            why = f"seq {scan.seq} was already received for this session"
            self.reject(scan.vehicle, scan.session, scan.seq, ErrorCode.DUPLICATE_SEQ, why)
            return None
        if scan.seq < info.last_seq:
            why = f"seq {scan.seq} arrived after seq {info.last_seq}: scans must come in order"
            self.reject(scan.vehicle, scan.session, scan.seq, ErrorCode.OUT_OF_ORDER, why)
            return None
        info.last_seq = scan.seq
        info.last_activity = time.monotonic()
        dropped = worker.submit(job)
        self.metrics.queue_depth.labels(queue_label(scan.vehicle, scan.session)).set(worker.depth())
        return dropped

    def _answer_dropped(self, dropped: Job) -> None:
        self.metrics.scans_dropped.inc()
        scan = dropped.scan
        why = (
            f"dropped: the session's queue was full ({self.settings.queue_size} scans waiting): the "
            "service is behind and sheds this session's scans evenly until it catches up"
        )
        self.reject(scan.vehicle, scan.session, scan.seq, ErrorCode.DROPPED, why, count=False)

    # -- an opener thread -------------------------------------------------------------------------
    def _open(self, key: tuple[str, str], opening: Opening) -> None:
        """Free an evicted slot, open the session outside the lock, then hand it the scans that
        waited behind the placeholder (seq-checked now that its last seq is known)."""
        t = self.table
        try:
            if opening.evict is not None:
                t.finish_close(opening.evict, "expired")
            if opening.localizing:
                self._wait_to_start(key)
            worker: SessionWorker | None = None
            error: tuple[str, str] | None = None
            try:
                worker = self.opener.open(opening.first)
            except BadMessageError as exc:
                error = (exc.code, str(exc))
            except RandtError as exc:
                error = (ErrorCode.SESSION_ERROR, str(exc))
            except Exception:  # a bug: the scans still get their answer
                log.exception("opening session %s/%s failed", *key)
                error = (ErrorCode.INTERNAL_ERROR, "internal error while opening the session (logged)")
            dropped: list[Job] = []
            with t.lock:
                del t.opening[key]
                jobs = list(opening.jobs)
                opening.jobs.clear()
                if worker is not None:
                    t.install(worker)
                    dropped = [gone for job in jobs if (gone := self._enqueue(worker, job)) is not None]
            if error is not None:
                for job in jobs:
                    self.reject(job.scan.vehicle, job.scan.session, job.scan.seq, *error)
            for job in dropped:
                self._answer_dropped(job)
        finally:
            opening.done.set()
            with t.lock:
                t.openers.discard(threading.current_thread())

    def _wait_to_start(self, key: tuple[str, str]) -> None:
        """Until the session may start (:meth:`Capacity.try_start`: one start a core at a time),
        :data:`START_WAIT_S` at most; its scans wait in its opening's queue meanwhile, answered
        late rather than refused (docs/architecture.md, "Admission")."""
        if self.capacity is None:
            return
        deadline = time.monotonic() + START_WAIT_S
        while True:
            with self.table.lock:
                running = [*self.table.workers, *self.table.opening]
            if self.capacity.try_start(key, running) or time.monotonic() >= deadline:
                return
            time.sleep(START_POLL_S)

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
        """Answer one scan with an error (:meth:`Answers.error`) and count it on its session."""
        answered_on = self.answers.error(vehicle, session, seq, code, reason, retry_after_s, count=count)
        w = None if answered_on is None else self.table.workers.get((vehicle, answered_on))  # (no lock)
        if w is not None:
            w.info.n_errors += 1
