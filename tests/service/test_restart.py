"""A stopped and restarted service restores its tiles and resumes its sessions where they were."""

from __future__ import annotations

import time

import numpy as np

from randt.core.transforms import transform_error
from randt.service.runtime import Service
from randt.service.settings import ServiceSettings
from randt.sim.drive import Route, simulate
from randt.sim.town import Town
from randt.wire.messages import ErrorMessage, PoseMessage, encode, scan_from_arrays


def _wait(out: list[object], n: int, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while (
        len([m for m in out if isinstance(m, PoseMessage | ErrorMessage)]) < n and time.monotonic() < deadline
    ):
        time.sleep(0.05)


def test_restart_restores_tiles_and_resumes_the_session(tmp_path) -> None:
    town = Town.generate(3)
    route = Route.loop(town, 1, length_m=600.0)
    scans = list(simulate(town, route, n_scans=8, speed_mps=8.0, seed=2))
    T0 = scans[0].T_world_sensor
    cov = np.diag([0.01**2] * 3 + [1e-4] * 3)

    def payload(k: int) -> bytes:
        s = scans[k]
        prior = dict(prior_pose=T0, prior_covariance=cov) if k == 0 else {}
        return encode(
            scan_from_arrays("v1", "d1", k, s.stamp_ns, s.points_xyz, intensity=s.intensity, **prior)
        )

    settings = ServiceSettings(data_dir=tmp_path, flush_interval_s=0.3)
    first = Service(settings, with_zenoh=False)
    first.start()
    for k in range(5):
        first.sessions.submit("v1", payload(k))
    _wait(first._sent, 5)
    first.stop()
    before = {
        tid: first.sessions.maps["default"].get(tid) for tid in first.sessions.maps["default"].tile_ids()
    }
    assert before

    second = Service(settings, with_zenoh=False)
    second.start()
    try:
        grid = second.sessions.maps["default"]
        assert set(grid.tile_ids()) == set(before)
        for tid, tile in before.items():
            np.testing.assert_array_equal(grid.get(tid).points, tile.points)
            assert grid.get(tid).version == tile.version
        # the vehicle goes on: seq 4 again is a duplicate, 5..7 continue the trajectory
        for k in (4, 5, 6, 7):
            second.sessions.submit("v1", payload(k))
        _wait(second._sent, 4)
        answers = {m.seq: m for m in second._sent if isinstance(m, PoseMessage | ErrorMessage)}
        assert isinstance(answers[4], ErrorMessage) and answers[4].code == "duplicate_seq"
        for k in (5, 6, 7):
            msg = answers[k]
            assert isinstance(msg, PoseMessage) and msg.status == "ok", msg
            err_m, err_deg = transform_error(np.array(msg.pose).reshape(4, 4), scans[k].T_world_sensor)
            assert err_m < 0.1 and err_deg < 0.3, (k, err_m, err_deg)
        assert second.sessions.worker("v1", "d1").info.n_scans == 8
    finally:
        second.stop()
