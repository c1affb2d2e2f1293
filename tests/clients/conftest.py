"""Fixtures for client tests: a restartable in-process Zenoh router and a fake service.

The fake service answers every scan like the real one (a pose, or an error for the seqs it is told
to reject) without running the matcher, so publisher tests take seconds. Tests that need the real
matcher start :class:`randt.service.runtime.Service` instead.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh

from randt.core.errors import BadMessageError
from randt.wire.codes import ErrorCode
from randt.wire.keys import ALL_SCANS, key_for
from randt.wire.messages import ErrorMessage, PoseMessage, decode_scan, encode
from randt.wire.zenoh_config import zenoh_config
from tests.service.conftest import free_port


class Router:
    """A Zenoh router on a fixed loopback port that can be stopped and started again."""

    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self._session: zenoh.Session | None = None

    def start(self) -> None:
        if self._session is None:
            self._session = zenoh.open(zenoh_config("router", listen=(self.endpoint,)))

    def stop(self) -> None:
        if self._session is not None:
            self._session.close()
            self._session = None


@pytest.fixture
def restartable_router() -> Iterator[Router]:
    """A started :class:`Router`; stopped at the end of the test."""
    r = Router()
    r.start()
    try:
        yield r
    finally:
        r.stop()


class FakeService:
    """Answers scans on ``randt/fleet/*/scan`` with identity poses (errors for ``reject_seqs``).

    Answers are published from a worker thread, never inside the Zenoh callback.
    """

    def __init__(self, endpoint: str, reject_seqs: frozenset[int] = frozenset()) -> None:
        self.reject_seqs = reject_seqs
        #: Scans received within this long of the first are refused ``sessions_full`` with
        #: ``retry_after_s`` (:attr:`retry_after_s`), as admission refuses a session with no room.
        self.full_for_s = 0.0
        self.retry_after_s = 0.3
        self._first_at: float | None = None
        self.received: list[tuple[str, str, int, int]] = []  # vehicle, session, seq, n_points
        self._jobs: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        self._zs = zenoh.open(zenoh_config("client", connect=(endpoint,)))
        self._sub = self._zs.declare_subscriber(ALL_SCANS, lambda s: self._jobs.put(s.payload.to_bytes()))
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while (payload := self._jobs.get()) is not None:
            try:
                scan = decode_scan(payload)
            except BadMessageError:
                continue
            self.received.append((scan.vehicle, scan.session, scan.seq, scan.n_points))
            now = time.monotonic()
            self._first_at = now if self._first_at is None else self._first_at
            if now - self._first_at < self.full_for_s:
                answer: ErrorMessage | PoseMessage = ErrorMessage(
                    vehicle=scan.vehicle,
                    session=scan.session,
                    seq=scan.seq,
                    code=ErrorCode.SESSIONS_FULL,
                    reason="no room for a new session (test)",
                    retry_after_s=self.retry_after_s,
                )
            elif scan.seq in self.reject_seqs:
                answer = ErrorMessage(
                    vehicle=scan.vehicle,
                    session=scan.session,
                    seq=scan.seq,
                    code=ErrorCode.INVALID_FIELD,
                    reason="test",
                )
            else:
                answer = PoseMessage(
                    vehicle=scan.vehicle,
                    session=scan.session,
                    seq=scan.seq,
                    stamp_ns=scan.stamp_ns,
                    pose=np.eye(4).ravel().tolist(),
                    fitness=1.0,
                    inlier_ratio=1.0,
                    converged=True,
                    status="ok",
                    latency_ms=0.0,
                    map="default",
                )
            self._zs.put(key_for(answer), encode(answer))

    def close(self) -> None:
        self._jobs.put(None)
        self._thread.join(5)
        self._sub.undeclare()
        self._zs.close()


@pytest.fixture
def fake_service(restartable_router: Router) -> Iterator[FakeService]:
    """A :class:`FakeService` connected to ``restartable_router``."""
    svc = FakeService(restartable_router.endpoint, reject_seqs=frozenset({3}))
    try:
        yield svc
    finally:
        svc.close()
