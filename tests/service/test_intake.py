"""Intake that cannot be stalled, fair admission, counters that persist (issue 13, defect 5).

* eight 16 MiB msgpack maps of 5.6 M tiny entries, through the real Zenoh path, do not delay
  another vehicle's scan (11.3 s on the old code, where the callback unpacked and peeked them);
* ``/status`` and ``/sessions`` answer while a session's opening is stuck (the old ``submit``
  held the manager lock across the store read and the matcher start);
* sessions that sent one scan and went quiet cannot squat the admission limit; one vehicle cannot
  hold more than ``max_sessions_per_vehicle`` sessions;
* the intake serves vehicles round-robin and answers every payload it drops;
* the ``/status`` counters go on across a restart.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import zenoh
from fastapi.testclient import TestClient

from randt.core.scenes import synthetic_room
from randt.service.app import create_app
from randt.service.intake import Intake
from randt.service.metrics import ServiceMetrics
from randt.service.opener import SessionOpener
from randt.service.runtime import Service
from randt.service.sessions import SessionManager
from randt.service.settings import ServiceSettings
from randt.service.store import Store
from randt.wire.messages import ErrorMessage, PoseMessage, decode_error, decode_pose, encode, scan_from_arrays
from randt.wire.zenoh_config import zenoh_config

ROOM = synthetic_room(np.random.default_rng(0), 3000).astype(np.float32)

#: The hostile payload of the issue: a 16 MiB msgpack map32 of 5 592 403 three-byte entries
#: (key "a", value 1): unpacking it and peeking it cost about 3 s of CPU each on the old code.
N_TINY = (16 * 1024 * 1024 - 5) // 3
HOSTILE = b"\xdf" + N_TINY.to_bytes(4, "big") + b"\xa1a\x01" * N_TINY


def good(vehicle: str, seq: int, session: str = "s1") -> bytes:
    return encode(scan_from_arrays(vehicle, session, seq, seq * 100_000_000, ROOM))


def _answers(out: list[object]) -> list[PoseMessage | ErrorMessage]:
    return [m for m in out if isinstance(m, PoseMessage | ErrorMessage)]


def _wait(out: list[object], n: int, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while len(_answers(out)) < n and time.monotonic() < deadline:
        time.sleep(0.02)


# ------------------------------------------------------------------ defect 5: hostile payloads


def test_hostile_payloads_over_zenoh_do_not_delay_another_vehicles_scan(router, tmp_path) -> None:
    """Eight hostile 16 MiB maps published just before another vehicle's scan: that scan is answered
    within 2 s (old code: about 11 s), and each hostile payload gets exactly one `malformed`."""
    assert len(HOSTILE) == 16 * 1024 * 1024 - 2
    settings = ServiceSettings(
        data_dir=tmp_path / "data",
        zenoh_mode="client",
        listen=(),
        connect=(router,),
        matcher_processes=0,
        max_payload_bytes=16 * 1024 * 1024,
        flush_interval_s=0.5,
    )
    service = Service(settings)
    service.start()
    got: dict[str, list[tuple[float, PoseMessage | ErrorMessage]]] = {"good": [], "hostile": []}
    lock = threading.Lock()

    def on_answer(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        msg = decode_pose(payload) if key.endswith("/pose") else decode_error(payload)
        with lock:
            got[msg.vehicle].append((time.monotonic(), msg))

    # One Zenoh session publishes both vehicles' scans: same link, so the good scan arrives after
    # the eight hostile payloads, as in the reproduction.
    fleet = zenoh.open(zenoh_config("client", connect=(router,)))
    try:
        subs = [
            fleet.declare_subscriber(f"randt/fleet/{v}/{kind}", on_answer)
            for v in ("good", "hostile")
            for kind in ("pose", "error")
        ]
        block = zenoh.CongestionControl.BLOCK  # every payload is delivered, none dropped at the source
        pub_good = fleet.declare_publisher("randt/fleet/good/scan", congestion_control=block)
        pub_bad = fleet.declare_publisher("randt/fleet/hostile/scan", congestion_control=block)
        deadline = time.monotonic() + 30
        while not (pub_good.matching_status.matching and pub_bad.matching_status.matching):
            assert time.monotonic() < deadline, "the service's subscriber was not seen"
            time.sleep(0.05)
        pub_good.put(good("good", 0))  # the good session is open and warm before the attack
        deadline = time.monotonic() + 60
        while not got["good"]:
            assert time.monotonic() < deadline, "no answer to the first good scan"
            time.sleep(0.05)
        assert isinstance(got["good"][0][1], PoseMessage)

        for _ in range(8):
            pub_bad.put(HOSTILE)
        sent = time.monotonic()
        pub_good.put(good("good", 1))
        deadline = sent + 60
        while len(got["good"]) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(got["good"]) == 2, "the good scan was never answered"
        answered, msg = got["good"][1]
        delay = answered - sent
        assert isinstance(msg, PoseMessage) and msg.seq == 1, msg
        assert delay < 2.0, f"another vehicle's scan took {delay:.2f} s behind the hostile payloads"

        deadline = time.monotonic() + 30
        while len(got["hostile"]) < 8 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)  # no second answer may follow
        errors = [m for _, m in got["hostile"]]
        received = service.metrics.registry.get_sample_value("randt_scans_received_total")
        assert received == 10, "all eight hostile payloads reached the service"
        assert len(errors) == 8, "each hostile payload gets exactly one answer"
        assert all(isinstance(e, ErrorMessage) and e.code == "malformed" for e in errors), errors
        assert "5592403 entries" in errors[0].reason
        for s in subs:
            s.undeclare()
    finally:
        fleet.close()
        service.stop()


def test_status_and_other_vehicles_do_not_wait_for_a_stuck_session_open(tmp_path, monkeypatch) -> None:
    """A session whose opening hangs (a slow store read or a cold matcher warm-up, here until the
    test lets it go, at most 30 s): /status and /sessions answer within 2 s and another vehicle's
    scan gets its pose meanwhile; the stuck session's scan is answered once it is open. (The bound
    is far above the 15 ms they take and far below the hang: in a long test run on 2 loaded cores
    a request took 0.65 s.)"""
    original = SessionOpener.open
    release = threading.Event()

    def slow_open(self: SessionOpener, scan):  # type: ignore[no-untyped-def]
        if scan.vehicle == "slow":
            release.wait(30.0)
        return original(self, scan)

    monkeypatch.setattr(SessionOpener, "open", slow_open)
    # (admission by count: two sessions on one in-process core pass the measured capacity)
    settings = ServiceSettings(
        data_dir=tmp_path, matcher_processes=0, flush_interval_s=0.2, capacity_target=0
    )
    with TestClient(create_app(settings, with_zenoh=False)) as client:
        svc: Service = client.app.state.service  # type: ignore[attr-defined]
        out = svc._sent
        # The transport's callback path (Service._on_scan); on the old code it blocked in the open.
        threading.Thread(
            target=svc._on_scan, args=("slow", good("slow", 0), time.time_ns()), daemon=True
        ).start()
        time.sleep(0.5)  # the open is under way and stuck
        try:
            for path in ("/status", "/sessions"):
                t0 = time.monotonic()
                r = client.get(path)
                took = time.monotonic() - t0
                assert r.status_code == 200, r.text
                assert took < 2.0, f"{path} took {took:.2f} s while a session open was stuck"
            t0 = time.monotonic()
            threading.Thread(
                target=svc._on_scan, args=("quick", good("quick", 0), time.time_ns()), daemon=True
            ).start()
            while not any(m.vehicle == "quick" for m in _answers(out)) and time.monotonic() - t0 < 10:
                time.sleep(0.02)
            took = time.monotonic() - t0
            assert any(isinstance(m, PoseMessage) and m.vehicle == "quick" for m in _answers(out))
            assert took < 2.0, f"another vehicle's first scan took {took:.2f} s behind the stuck open"
            assert not any(m.vehicle == "slow" for m in _answers(out)), "the slow open is still stuck"
        finally:
            release.set()
        _wait(out, 2)
        slow = [m for m in _answers(out) if m.vehicle == "slow"]
        assert len(slow) == 1 and isinstance(slow[0], PoseMessage), slow


# ------------------------------------------------------------------ fair admission


def test_one_scan_squatters_give_their_slots_to_a_live_vehicle(tmp_path) -> None:
    """Four sessions that sent one scan each fill max_sessions=4; a fifth vehicle arriving after
    they idled slot_idle_s gets poses (old code: sessions_full), the squatter that gave up its slot
    is saved as expired, and it resumes where it stopped when it comes back."""
    # (the count cap and its slots: four sessions on one in-process core pass the measured capacity)
    settings = ServiceSettings(
        data_dir=tmp_path, max_sessions=4, matcher_processes=0, flush_interval_s=0.2, capacity_target=0
    )
    # (set without validation, so the old code, which has no such setting, runs the same test)
    settings = settings.model_copy(update={"slot_idle_s": 1.0})
    out: list[object] = []
    store = Store(tmp_path)
    mgr = SessionManager(settings, store, out.append, ServiceMetrics())
    try:
        for k in range(4):
            mgr.submit(f"squat{k}", good(f"squat{k}", 0))
            _wait(out, k + 1)  # in order: squat0 is the idlest
        assert all(isinstance(m, PoseMessage) for m in _answers(out))
        time.sleep(1.5)
        for seq in range(3):
            mgr.submit("legit", good("legit", seq))
        _wait(out, 7)
        legit = [m for m in _answers(out) if m.vehicle == "legit"]
        assert [(type(m).__name__, getattr(m, "code", None)) for m in legit] == [("PoseMessage", None)] * 3
        deadline = time.monotonic() + 10
        while store.load_session("squat0", "s1").record.state != "expired" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert store.load_session("squat0", "s1").record.state == "expired"
        assert mgr.worker("squat0", "s1") is None and len(mgr.sessions()) == 4
        time.sleep(1.1)  # squat1 idles long enough to give its slot to squat0
        mgr.submit("squat0", good("squat0", 1))
        _wait(out, 8)
        back = [m for m in _answers(out) if m.vehicle == "squat0"]
        assert isinstance(back[-1], PoseMessage) and back[-1].seq == 1, back
        assert mgr.worker("squat0", "s1").info.n_scans == 2, "it resumed, not restarted"
    finally:
        mgr.stop()


def test_one_vehicle_cannot_hold_more_than_its_sessions(tmp_path) -> None:
    settings = ServiceSettings(
        data_dir=tmp_path,
        max_sessions=8,
        max_sessions_per_vehicle=2,
        slot_idle_s=30.0,
        vehicle_slot_idle_s=1.0,
        matcher_processes=0,
        flush_interval_s=0.2,
        capacity_target=0,  # (the per-vehicle cap alone: test_admission.py has the measured capacity)
    )
    out: list[object] = []
    mgr = SessionManager(settings, Store(tmp_path), out.append, ServiceMetrics())
    try:
        for session in ("a", "b", "c"):
            mgr.handle("greedy", good("greedy", 0, session), time.time_ns())
        mgr.handle("other", good("other", 0), time.time_ns())
        _wait(out, 4)
        by = {(m.vehicle, m.session): m for m in _answers(out)}
        assert isinstance(by[("greedy", "a")], PoseMessage) and isinstance(by[("greedy", "b")], PoseMessage)
        refused = by[("greedy", "c")]
        assert isinstance(refused, ErrorMessage) and refused.code == "vehicle_sessions_full"
        assert "maximum of 2 sessions" in refused.reason
        assert isinstance(by[("other", "s1")], PoseMessage), "other vehicles are not affected"
        assert (
            mgr.metrics.registry.get_sample_value(
                "randt_scans_rejected_total", {"reason": "vehicle_sessions_full"}
            )
            == 1
        )
        mgr.handle("greedy", good("greedy", 1, "b"), time.time_ns())  # b active after a
        _wait(out, 5)
        time.sleep(1.2)  # a and b idle past vehicle_slot_idle_s: the vehicle's idlest (a) makes room
        mgr.handle("greedy", good("greedy", 1, "c"), time.time_ns())
        _wait(out, 6)
        assert isinstance(_answers(out)[-1], PoseMessage)
        assert sorted(s.session for s in mgr.sessions() if s.vehicle == "greedy") == ["b", "c"]
    finally:
        mgr.stop()


# ------------------------------------------------------------------ the intake itself


def test_intake_serves_vehicles_round_robin_and_answers_every_drop() -> None:
    """One worker, a flood of one vehicle queued before another's single payload: the other's is
    handled second, not after the flood; the flood beyond max_scans loses its oldest payloads,
    each answered once; handled + dropped = put."""
    gate = threading.Event()
    handled: list[tuple[str, bytes]] = []
    dropped: list[tuple[str, bytes, str]] = []

    def handle(vehicle: str, payload: bytes, received_ns: int) -> None:
        gate.wait(10)
        handled.append((vehicle, payload))

    intake = Intake(
        handle,
        lambda v, p, reason: dropped.append((v, p, reason)),
        workers=1,
        max_scans=4,
        max_bytes=10_000,
        total_bytes=100_000,
    )
    try:
        intake.put("flood", b"f0", 0)
        time.sleep(0.1)  # the worker holds f0 (gated)
        for k in range(1, 10):
            intake.put("flood", f"f{k}".encode(), 0)
        intake.put("calm", b"c0", 0)
        gate.set()
        assert intake.wait_idle(10)
        assert handled[:2] == [("flood", b"f0"), ("calm", b"c0")], handled
        assert [p for v, p in handled if v == "flood"] == [b"f0", b"f6", b"f7", b"f8", b"f9"]
        assert [p for _, p, _ in dropped] == [f"f{k}".encode() for k in range(1, 6)]
        assert all("intake queue was full" in r for _, _, r in dropped)
        assert len(handled) + len(dropped) == 11
    finally:
        intake.stop()


def test_intake_byte_limits_drop_the_largest_queue_first() -> None:
    handled: list[str] = []
    dropped: list[str] = []
    gate = threading.Event()

    def handle(vehicle: str, payload: bytes, received_ns: int) -> None:
        gate.wait(10)
        handled.append(vehicle)

    intake = Intake(
        handle,
        lambda v, p, r: dropped.append(v),
        workers=1,
        max_scans=100,
        max_bytes=50_000,
        total_bytes=61_000,
    )
    try:
        intake.put("x", b"0", 0)
        time.sleep(0.1)  # gated in the worker
        intake.put("big", b"b" * 20_000, 0)
        intake.put("big", b"b" * 20_000, 0)
        intake.put("small", b"s" * 10_000, 0)
        intake.put("small", b"s" * 10_000, 0)  # total > 61 000: big (40 000 queued) pays
        assert dropped == ["big"]
        intake.put("big", b"b" * 40_000, 0)  # big's own limit: 50 000
        assert dropped == ["big", "big"]
        gate.set()
        assert intake.wait_idle(10)
        assert sorted(handled) == ["big", "small", "small", "x"]
    finally:
        intake.stop()


# ------------------------------------------------------------------ counters across a restart


def test_status_counters_go_on_across_a_restart(tmp_path) -> None:
    settings = ServiceSettings(data_dir=tmp_path, matcher_processes=0, flush_interval_s=0.2)

    def counts(svc: Service) -> tuple[float, float, float]:
        r = svc.metrics.registry
        return (
            r.get_sample_value("randt_scans_received_total") or 0.0,
            r.get_sample_value("randt_scans_processed_total", {"status": "first"}) or 0.0,
            r.get_sample_value("randt_scans_rejected_total", {"reason": "malformed"}) or 0.0,
        )

    first = Service(settings, with_zenoh=False)
    first.start()
    for seq in range(3):
        first.sessions.submit("v1", good("v1", seq))
    first.sessions.submit("v1", b"\x93 not a scan")
    _wait(first._sent, 4)
    first.stop()
    assert counts(first) == (4.0, 1.0, 1.0)

    second = Service(settings, with_zenoh=False)
    second.start()
    try:
        assert counts(second) == (4.0, 1.0, 1.0), "the counters restart where they stopped"
        assert (tmp_path / "counters.json").is_file()
        second.sessions.submit("v2", good("v2", 0))
        _wait(second._sent, 1)
        assert counts(second) == (5.0, 2.0, 1.0)
    finally:
        second.stop()
    third = Service(settings, with_zenoh=False)
    third.start()
    try:
        processed = third.metrics.registry.get_sample_value("randt_scans_processed_total", {"status": "ok"})
        assert counts(third) == (5.0, 2.0, 1.0) and processed == 2.0
    finally:
        third.stop()
