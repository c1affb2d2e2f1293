"""A session's answers on their way out: poses go out durable only (a new session's first poses
wait for its first snapshot, which fixes its frame and holds its first keyframe: its later poses
are resumable only on top of it), each with its latency, in order."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from randt.service.answers import Answers
from randt.service.session_info import SessionInfo
from randt.wire.codes import ErrorCode
from randt.wire.messages import PoseMessage

__all__ = ["SessionOutbox"]

log = logging.getLogger(__name__)


class SessionOutbox:
    """One session's poses to the outbox, held while its first snapshot is being written.

    Each pose's latency and each refusal go into the session's ``info``; ``wake`` is the session's
    condition, notified when the first snapshot failed (the session is then abandoned:
    :attr:`failed`)."""

    def __init__(self, info: SessionInfo, answers: Answers, wake: threading.Condition) -> None:
        self.info, self.answers, self._wake = info, answers, wake
        self.key = (info.vehicle, info.session)
        self._lock = threading.Lock()
        self._held: list[tuple[PoseMessage, int]] = []
        #: None while the first snapshot is written, then whether it was (a resumed session has one).
        self._first_saved: bool | None = True
        self._first_save: threading.Thread | None = None
        #: A pose could not be made durable: the session is abandoned, to resume from the store.
        self.failed = False

    def first(self, pose: PoseMessage, received_ns: int, save: Callable[[], bool]) -> None:
        """A new session's first pose: held while ``save`` writes its first snapshot on a thread of
        its own (the session goes on matching meanwhile)."""
        with self._lock:
            self._first_saved = None
            self._held.append((pose, received_ns))
        self._first_save = threading.Thread(
            target=self._save_first, args=(save,), name=f"first-save-{self.key[0]}-{self.key[1]}", daemon=True
        )
        self._first_save.start()

    def publish(self, pose: PoseMessage, received_ns: int) -> None:
        """Send a durable pose, or hold it while the first snapshot is being written (sent then, or
        answered ``storage_error`` if that save failed)."""
        with self._lock:
            if self._first_saved is None:
                self._held.append((pose, received_ns))
                return
            if self._first_saved:
                self._send(pose, received_ns)
                return
        self.refuse_not_durable(pose, "its first snapshot could not be saved")

    def _send(self, pose: PoseMessage, received_ns: int) -> None:
        latency_ms = (time.time_ns() - received_ns) * 1e-6
        self.info.last_latency_ms = latency_ms
        metrics = self.answers.metrics
        metrics.latency_seconds.observe(latency_ms * 1e-3)
        metrics.scans_processed.labels(pose.status).inc()
        if pose.mode == "localizing":
            metrics.scans_localized.inc()
            self.info.n_localized += 1
        self.answers.send(pose.model_copy(update={"latency_ms": latency_ms}))

    def _save_first(self, save: Callable[[], bool]) -> None:
        """Write the first snapshot, then send the poses held meanwhile in order, or answer them
        ``storage_error`` (and fail the session) if it could not be written."""
        saved = False
        try:
            saved = save()
        finally:
            with self._lock:
                held, self._held = self._held, []
                self._first_saved = saved
                if saved:
                    for pose, received_ns in held:
                        self._send(pose, received_ns)
        if not saved:
            for pose, _ in held:
                self.refuse_not_durable(pose, "its first snapshot could not be saved")
            with self._wake:  # an idle worker wakes up to abandon the session
                self._wake.notify()

    def wait_first_save(self, timeout: float | None = None) -> bool:
        """Wait for the first snapshot (if it is being written); whether it is done."""
        thread = self._first_save
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)
            return not thread.is_alive()
        return True

    def refuse_not_durable(self, pose: PoseMessage, why: str) -> None:
        """Answer a pose's scan ``storage_error`` instead: counted, and the session failed."""
        reason = not_durable(self.key, pose.seq, why, self.answers)
        self.failed = True
        self.info.n_errors += 1
        self.answers.error(pose.vehicle, pose.session, pose.seq, ErrorCode.STORAGE_ERROR, reason)


def not_durable(key: tuple[str, str], seq: int, why: str, answers: Answers) -> str:
    """Log and count a pose that could not be made durable; the reason its scan is answered."""
    log.error("session %s/%s: scan %d not durable: %s", *key, seq, why)
    answers.metrics.store_errors.inc()
    return f"the pose could not be made durable ({why}): not acknowledged"
