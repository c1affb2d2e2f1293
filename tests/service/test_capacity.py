"""Issue 14's service-side defaults for a fleet on one small node: eight vehicles are admitted, BLAS
runs on one thread in the service, a pose never waits behind a burst of tile updates, and a session
folds its scans into the map together, every fold_scans scans."""

from __future__ import annotations

import os

import numpy as np
from threadpoolctl import threadpool_info

from randt.core.scenes import synthetic_room
from randt.core.transforms import invert, make_transform, transform_points
from randt.service.runtime import Service
from randt.service.settings import ServiceSettings
from randt.service.transport import ZenohTransport
from randt.wire.codes import ErrorCode
from randt.wire.messages import (
    ErrorMessage,
    PoseMessage,
    decode_error,
    decode_pose,
    encode,
    scan_from_arrays,
    tile_update_from_arrays,
)
from tests.service.api_server import wait_answers

ROOM = synthetic_room(np.random.default_rng(0), 4000)


def test_the_default_admits_four_sessions_per_core_so_eight_vehicles_on_two(tmp_path) -> None:
    svc = Service(ServiceSettings(data_dir=tmp_path, matcher_processes=0), with_zenoh=False)
    svc.start()
    try:
        assert svc.sessions is not None
        assert svc.sessions.max_sessions == 4 * (os.cpu_count() or 1) >= 8
        # BLAS and OpenMP pools of the service process run one thread (service/matchers.py)
        pools = [p for p in threadpool_info() if p["user_api"] in ("blas", "openmp")]
        assert pools and all(p["num_threads"] == 1 for p in pools), pools
    finally:
        svc.stop()


class _FakeSession:
    def __init__(self) -> None:
        self.keys: list[str] = []
        self.payloads: list[bytes] = []

    def put(self, key: str, payload: bytes, **_: object) -> None:
        self.keys.append(key)
        self.payloads.append(payload)


def test_answers_leave_before_tile_updates_queued_earlier(tmp_path) -> None:
    transport = ZenohTransport(ServiceSettings(data_dir=tmp_path), lambda *a: None, lambda *a: None)
    fake = _FakeSession()
    transport._session = fake  # type: ignore[assignment]  # the sender only calls put
    pts = np.zeros((1000, 3), np.float32)
    for i in range(3):
        transport.send(tile_update_from_arrays("default", i, 0, 1, pts, np.zeros(1000, np.float32)))
    pose = PoseMessage(
        vehicle="car",
        session="s",
        seq=7,
        stamp_ns=1,
        pose=tuple(np.eye(4).ravel().tolist()),
        fitness=1.0,
        inlier_ratio=1.0,
        converged=True,
        status="ok",
        covariance=None,
        latency_ms=1.0,
        map="default",
    )
    transport.send(pose)
    transport.send(ErrorMessage(vehicle="car", session="s", seq=8, code=ErrorCode.DROPPED, reason="full"))
    transport._out.put((2, 10**9, None))  # the stop mark: after everything queued
    transport._send_loop()
    assert [k.rsplit("/", 1)[-1] for k in fake.keys[:2]] == ["pose", "error"]
    assert decode_pose(fake.payloads[0]).seq == 7 and decode_error(fake.payloads[1]).seq == 8
    assert len(fake.keys) == 5 and all("/tile/" in k for k in fake.keys[2:])
    assert [k.rsplit("/", 1)[-1] for k in fake.keys[2:]] == ["0_0", "1_0", "2_0"]  # tiles in order


def _room_scan(seq: int) -> bytes:
    T = make_transform(euler_deg=(0.0, 0.0, 1.0 * seq), translation=(0.3 * seq, 0.0, 0.0))
    pts = transform_points(invert(T), ROOM).astype(np.float32)
    prior = dict(prior_pose=np.eye(4), prior_covariance=np.diag([1e-4] * 3 + [1e-5] * 3)) if seq == 0 else {}
    return encode(scan_from_arrays("v1", "d1", seq, seq * 100_000_000, pts, **prior))


def test_a_session_folds_its_scans_into_the_map_every_fold_scans_scans(tmp_path) -> None:
    """With ``fold_scans=4`` a session's map points wait until its fourth scan and then enter the
    map together (one insert, one version step); the map saved after 8 scans is exactly the one
    folding every scan (``fold_scans=1``) leaves, through fewer tile versions."""
    maps = []
    for name, fold_scans in (("a", 1), ("b", 4)):
        settings = ServiceSettings(  # no flusher run meanwhile: it folds before it saves
            data_dir=tmp_path / name,
            matcher_processes=0,
            fold_scans=fold_scans,
            flush_interval_s=3600,
            map_agreement_min=0,  # (the check would hold the points until it ran: test_agreement)
        )
        svc = Service(settings, with_zenoh=False)
        svc.start()
        try:
            live_points = []
            for seq in range(8):
                svc.sessions.submit("v1", _room_scan(seq))
                wait_answers(svc, seq + 1)
                grid = svc.sessions.maps.get("default")
                live_points.append(0 if grid is None else grid.n_points)
            if fold_scans == 1:
                assert all(n > 0 for n in live_points)
            else:  # nothing until the 4th scan, then the 4 scans' points at once; again at the 8th
                assert live_points[:3] == [0, 0, 0] and live_points[3] > 0, live_points
                assert live_points[4:7] == [live_points[3]] * 3 and live_points[7] > live_points[3]
            answers = wait_answers(svc, 8)
            assert [(type(m), m.seq) for m in answers] == [(PoseMessage, seq) for seq in range(8)]
            svc.sessions.flush()
            maps.append(svc.sessions.maps.durable("default"))
        finally:
            svc.stop()
    a, b = maps
    assert a is not None and b is not None and sorted(a.by_id) == sorted(b.by_id)
    for tid in a.by_id:
        np.testing.assert_array_equal(a.by_id[tid].points, b.by_id[tid].points)
    assert max(t.version for t in b.by_id.values()) <= 2  # two folds
    assert sum(t.version for t in b.by_id.values()) < sum(t.version for t in a.by_id.values())
