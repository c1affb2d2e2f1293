"""A session that loses its track answers ``lost`` without a pose, folds nothing, and answers poses
again only after two consecutive matches (issue 32: predictions drifting hundreds of metres were
answered as poses).

A simulated vehicle drives town 1's loop at 10 m/s; its sensor is blocked (a tarp 2-4 m away, no
scene to match) for 1.5 s while it drives on at the same speed, then sees the street again. The
prediction is right for a short gap, so the first ``fallback_horizon_s`` (0.5 s) of the blockage
is answered with it (status ``fallback``); the rest is ``lost``. The first match after the blockage
is answered ``lost`` too (one of two), the next ones ``ok``, within centimetres of the truth.
"""

from __future__ import annotations

import numpy as np

from randt.core.transforms import invert, transform_error
from randt.service.runtime import Service
from randt.service.settings import ServiceSettings
from randt.sim.drive import Route, simulate
from randt.sim.lidar import Lidar64
from randt.sim.town import Town
from randt.wire.codes import ErrorCode
from randt.wire.messages import ErrorMessage, PoseMessage, encode, scan_from_arrays
from tests.service.api_server import answers, wait_answers

GOOD, BLOCKED, AFTER = 20, 15, 15


def _tarp(n: int = 3000) -> np.ndarray:
    rng = np.random.default_rng(0)
    tarp = rng.normal(size=(n, 3))
    return (tarp * (rng.uniform(2.0, 4.0, (n, 1)) / np.linalg.norm(tarp, axis=1, keepdims=True))).astype(
        np.float32
    )


def test_a_blocked_sensor_is_answered_lost_past_the_horizon_and_poses_resume_after_two_matches(
    tmp_path,
) -> None:
    town = Town.generate(1)
    route = Route.loop(town, 3, length_m=1000.0)
    lidar = Lidar64(n_azimuth=1000)
    scans = list(simulate(town, route, n_scans=GOOD + BLOCKED + AFTER, speed_mps=10.0, seed=1, lidar=lidar))
    settings = ServiceSettings(data_dir=tmp_path, flush_interval_s=0.2, matcher_processes=0, graph=False)
    service = Service(settings, with_zenoh=False)
    service.start()
    try:
        for k, scan in enumerate(scans):
            points = _tarp() if GOOD <= k < GOOD + BLOCKED else scan.points_xyz
            extra = (
                {"prior_pose": scan.T_world_sensor, "prior_covariance": np.eye(6) * 1e-4} if k == 0 else {}
            )
            payload = encode(scan_from_arrays("car", "d1", k, scan.stamp_ns, points, **extra))
            service.sessions.submit("car", payload)
            wait_answers(service, k + 1)  # one at a time, as a vehicle within capacity
        got = {m.seq: m for m in answers(service)}
        info = service.sessions.table.workers[("car", "d1")].info
        lost_flag, n_lost = info.lost, info.n_lost
    finally:
        service.stop()
    horizon = round(settings.fallback_horizon_s / 0.1)
    kinds = [
        "ok" if isinstance(got[k], PoseMessage) and got[k].status in ("ok", "first") else
        "fallback" if isinstance(got[k], PoseMessage) else str(got[k].code)  # type: ignore[union-attr]
        for k in range(len(scans))
    ]  # fmt: skip
    assert kinds[:GOOD] == ["ok"] * GOOD, kinds[:GOOD]
    # the prediction for 0.5 s, then lost, through the blockage and the first match after it
    assert kinds[GOOD : GOOD + horizon] == ["fallback"] * horizon, kinds[GOOD:]
    assert kinds[GOOD + horizon : GOOD + BLOCKED + 1] == [ErrorCode.LOST] * (BLOCKED - horizon + 1), kinds[
        GOOD:
    ]
    assert kinds[GOOD + BLOCKED + 1 :] == ["ok"] * (AFTER - 1), kinds[GOOD:]
    assert "1 of 2" in got[GOOD + BLOCKED].reason  # type: ignore[union-attr]
    assert not lost_flag and n_lost == BLOCKED - horizon + 1
    # every pose answered is right: the fallbacks within their short gap, the matches after it
    T0, G0 = np.reshape(got[0].pose, (4, 4)), scans[0].T_world_sensor  # type: ignore[union-attr]
    for k, m in got.items():
        if isinstance(m, ErrorMessage):
            continue
        err_m, _ = transform_error(
            invert(T0) @ np.reshape(m.pose, (4, 4)), invert(G0) @ scans[k].T_world_sensor
        )
        assert err_m < (0.5 if m.status == "fallback" else 0.1), (k, m.status, err_m)
