"""VehiclePublisher over a real in-process Zenoh router: answers, counting, overflow, reconnection."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from randt.clients.publisher import PublisherSettings, VehiclePublisher
from randt.core.errors import BadMessageError
from randt.wire.messages import ErrorMessage, PoseMessage
from tests.clients.conftest import FakeService, Router


def _cloud(n: int = 500, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(0, 10, (n, 4)).astype(np.float32)


@pytest.mark.parametrize("mode", ["client", "peer"])
def test_every_scan_is_answered_and_counted(
    restartable_router: Router, fake_service: FakeService, mode: str
) -> None:
    poses: list[PoseMessage] = []
    errors: list[ErrorMessage] = []
    done = threading.Event()
    with VehiclePublisher(
        "car-1",
        "drive-a",
        mode=mode,  # type: ignore[arg-type]
        connect=[restartable_router.endpoint],
        on_pose=poses.append,
        on_error=lambda e: (errors.append(e), done.set()),
    ) as pub:
        assert pub.wait_connected(10), "the fake service's subscriber was matched"
        seqs = [pub.publish(_cloud(300 + i, i), stamp_ns=1_000 + i) for i in range(6)]
        assert pub.flush(20)
        stats = pub.stats()
    assert seqs == list(range(6))
    assert [p.seq for p in poses] == [0, 1, 2, 4, 5], "one pose per accepted scan, in order"
    assert [(e.seq, e.code) for e in errors] == [(3, "invalid_field")]
    assert (stats.published, stats.sent, stats.acknowledged, stats.rejected) == (6, 6, 5, 1)
    assert stats.dropped == stats.lost == stats.queued == stats.in_flight == 0
    assert stats.rejected_codes == {"invalid_field": 1}
    # the service saw xyzi points with the right counts, on this vehicle's key and session
    assert [r[:3] for r in fake_service.received] == [("car-1", "drive-a", i) for i in range(6)]
    assert [r[3] for r in fake_service.received] == [300 + i for i in range(6)]


def test_bad_arrays_raise_at_once_with_the_service_code(restartable_router: Router) -> None:
    with VehiclePublisher("car-1", connect=[restartable_router.endpoint]) as pub:
        bad = _cloud()
        bad[17, 0] = np.nan
        with pytest.raises(BadMessageError) as info:
            pub.publish(bad)
        assert info.value.code == "nonfinite_points"
        with pytest.raises(BadMessageError):
            pub.publish(np.zeros((10, 2)))
        assert pub.publish(_cloud()) == 2, "a scan that raised used up its seq"
    with pytest.raises(BadMessageError) as info:
        VehiclePublisher("car/1", connect=[restartable_router.endpoint])
    assert info.value.code == "invalid_id"
    with pytest.raises(ValueError, match="not a Zenoh endpoint"):
        PublisherSettings(connect=("localhost:7447",))


def test_full_queue_drops_the_oldest_and_never_blocks(restartable_router: Router) -> None:
    """Nobody listens: scans wait in a queue of 3, older ones dropped; a service then gets the newest."""
    pub = VehiclePublisher("car-2", "d", connect=[restartable_router.endpoint], queue_size=3)
    try:
        tic = time.perf_counter()
        for i in range(10):
            pub.publish(_cloud(200), stamp_ns=i)
        assert time.perf_counter() - tic < 1.0, "publish() does not wait for the network"
        s = pub.stats()
        assert (s.published, s.sent, s.dropped, s.queued) == (10, 0, 7, 3)
        svc = FakeService(restartable_router.endpoint)
        try:
            assert pub.flush(20)
            assert sorted(r[2] for r in svc.received) == [7, 8, 9], "the three newest were kept"
        finally:
            svc.close()
        s = pub.stats()
        assert (s.acknowledged, s.dropped, s.lost, s.settled) == (3, 7, 0, 10)
    finally:
        pub.close()


def test_publisher_starts_before_the_router_and_connects_later() -> None:
    router = Router()  # not started: opening the session fails, the publisher retries quietly
    pub = VehiclePublisher("car-3", "d", connect=[router.endpoint], settings=PublisherSettings(retry_s=0.2))
    try:
        pub.publish(_cloud(), stamp_ns=0)
        assert not pub.connected
        router.start()
        svc = FakeService(router.endpoint)
        try:
            assert pub.flush(30)
            assert pub.stats().acknowledged == 1
        finally:
            svc.close()
    finally:
        pub.close()
        router.stop()


def test_router_restart_mid_stream(restartable_router: Router, fake_service: FakeService) -> None:
    """Stop and restart the router while publishing at 20 Hz: no exception, losses counted, recovery."""
    router = restartable_router
    acked: list[int] = []
    pub = VehiclePublisher(
        "car-4",
        "d",
        connect=[router.endpoint],
        queue_size=4,
        answer_timeout_s=3.0,
        on_pose=lambda p: acked.append(p.seq),
    )
    fake_service.reject_seqs = frozenset()
    try:
        assert pub.wait_connected(10)
        for i in range(10):
            pub.publish(_cloud(200, i), stamp_ns=i)
            time.sleep(0.05)
        assert pub.flush(10)
        router.stop()
        outage_start = time.monotonic()
        n = 10
        while time.monotonic() - outage_start < 1.5:  # 1.5 s without a router at 20 Hz
            pub.publish(_cloud(200, n), stamp_ns=n)
            n += 1
            time.sleep(0.05)
        router.start()
        assert pub.wait_connected(20), "the publisher's client session re-dialled the router"
        first_after = n
        n_outage = first_after - 10
        for _ in range(10):
            pub.publish(_cloud(200, n), stamp_ns=n)
            n += 1
            time.sleep(0.05)
        assert pub.flush(30)
        s = pub.stats()
    finally:
        pub.close()
    assert s.published == n
    assert s.settled == n, f"every scan ends acknowledged, rejected, dropped or lost: {s}"
    assert s.outages >= 1
    assert n_outage >= 20
    # at most the queue's 4 newest outage scans survive; every other one is counted as lost
    assert s.dropped + s.lost >= n_outage - 4, f"{n_outage} scans in the outage: {s}"
    assert s.acknowledged <= 10 + 4 + 10
    assert set(range(10)) <= set(acked), "everything before the outage was answered"
    assert set(range(first_after, n)) <= set(acked), "everything after the recovery was answered"
    assert s.acknowledged == len(acked) and s.rejected == 0


def test_flush_waits_for_the_callbacks(restartable_router: Router, fake_service: FakeService) -> None:
    """After flush() every answer's callback has finished (the docs example prints the stats right
    after flush; a callback still printing interleaved its line with them)."""
    finished: list[int] = []

    def slow(msg: PoseMessage) -> None:
        time.sleep(0.2)
        finished.append(msg.seq)

    with VehiclePublisher("car-5", connect=[restartable_router.endpoint], on_pose=slow) as pub:
        assert pub.wait_connected(10)
        for i in range(3):
            pub.publish(_cloud(300, i), stamp_ns=i)
        assert pub.flush(20)
        assert finished == [0, 1, 2]
