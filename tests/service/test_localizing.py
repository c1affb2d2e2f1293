"""Localizing on the map in the service (service/localizing.py, ``RANDT_LOCALIZE``).

A first vehicle maps the simulator's streets; a second drives them after it, with a first prior
1.5 m off (a GNSS fix): its sweeps are matched on the map around it in the matcher processes
(``mode: localizing``), in the map's frame from its first answer, each within a few centimetres of
the truth; with ``localize`` off the same drive maps as before.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from randt.core.transforms import transform_error
from randt.service.metrics import ServiceMetrics
from randt.service.sessions import SessionManager
from randt.service.settings import ServiceSettings
from randt.service.store import Store
from randt.sim.drive import SimScan, plan_fleet, simulate
from randt.sim.lidar import Lidar64
from randt.sim.town import Town
from randt.wire.messages import ErrorMessage, PoseMessage, encode, scan_from_arrays

N_SCANS = 50
EXACT = np.diag([1e-4] * 3 + [1e-6] * 3)
GNSS = np.diag([1.0] * 3 + [np.radians(5.0) ** 2] * 3)


def _drive(seed: int) -> list[SimScan]:
    town = Town.generate(0)
    plan = plan_fleet(town, 1, seed=0, route_length_m=400.0)[0]
    lidar = Lidar64(n_azimuth=1000, max_range_m=70.0)
    return list(
        simulate(
            town, plan.route, n_scans=N_SCANS, seed=seed, lidar=lidar, start_s_m=plan.start_s_m, workers=2
        )
    )


def _send(
    mgr: SessionManager, out: list, vehicle: str, scans: list[SimScan], first_T: np.ndarray, cov
) -> None:
    for k, scan in enumerate(scans):
        n = sum(isinstance(m, PoseMessage | ErrorMessage) for m in list(out))
        extra = {"prior_pose": first_T, "prior_covariance": cov} if k == 0 else {}
        mgr.submit(
            vehicle, encode(scan_from_arrays(vehicle, "d1", k, scan.stamp_ns, scan.points_xyz, **extra))
        )
        deadline = time.monotonic() + 60
        while sum(isinstance(m, PoseMessage | ErrorMessage) for m in list(out)) < n + 1:
            assert time.monotonic() < deadline, "the service stopped answering"
            time.sleep(0.002)


@pytest.mark.parametrize("localize", [True, False])
def test_a_second_vehicle_localizes_on_the_first_ones_map(tmp_path: Path, localize: bool) -> None:
    mapper, second = _drive(1), _drive(2)
    settings = ServiceSettings(
        data_dir=tmp_path, flush_interval_s=0.3, capacity_target=0, graph=False, localize=localize
    )  # type: ignore[call-arg]
    out: list = []
    metrics = ServiceMetrics()
    mgr = SessionManager(settings, Store(tmp_path), out.append, metrics)
    try:
        assert mgr.wait_matchers(300)
        _send(mgr, out, "mapper", mapper, mapper[0].T_world_sensor, EXACT)
        mgr.close("mapper", "d1")
        mgr.flush()
        T0 = second[0].T_world_sensor.copy()
        T0[:2, 3] += (1.5, -1.0)  # the GNSS fix's error
        localized_before = metrics.scans_localized._value.get()
        _send(mgr, out, "second", second, T0, GNSS)
        localized = metrics.scans_localized._value.get() - localized_before
        info = next(w.info for w in mgr.table.running() if w.info.vehicle == "second")
        assert localized == info.n_localized == (N_SCANS if localize else 0)  # counted as answered
    finally:
        mgr.stop()
    answers = {m.seq: m for m in out if isinstance(m, PoseMessage) and m.vehicle == "second"}
    assert sorted(answers) == list(range(N_SCANS))
    modes = [answers[k].mode for k in range(N_SCANS)]
    errors = np.array([transform_error(answers[k].matrix(), s.T_world_sensor) for k, s in enumerate(second)])
    if not localize:
        assert set(modes) == {"mapping"}
        return
    assert modes.count("localizing") == N_SCANS, modes  # from its first sweep on
    assert all(a.map == "default" and a.status in ("first", "ok") for a in answers.values())
    assert errors[:, 0].max() < 0.05 and errors[:, 1].max() < 0.3, errors.max(axis=0)


def test_a_localized_drive_adds_no_graph_keyframe_where_the_graph_has_one(tmp_path: Path) -> None:
    """Growth by area: the second drive, localized on the same streets, offers the graph no
    keyframe within KNOWN_PLACE_M and KNOWN_PLACE_DEG of one it holds (counted ``known_place``);
    the first drive's keyframes are there every 10 m."""
    from randt.service.graph import KNOWN_PLACE_M

    mapper, second = _drive(1), _drive(2)
    settings = ServiceSettings(data_dir=tmp_path, flush_interval_s=0.3, capacity_target=0, localize=True)  # type: ignore[call-arg]
    out: list = []
    metrics = ServiceMetrics()
    mgr = SessionManager(settings, Store(tmp_path), out.append, metrics)
    try:
        assert mgr.wait_matchers(300) and mgr.graph is not None
        _send(mgr, out, "mapper", mapper, mapper[0].T_world_sensor, EXACT)
        mgr.close("mapper", "d1")
        mgr.flush()
        T0 = second[0].T_world_sensor.copy()
        T0[:2, 3] += (1.5, -1.0)
        _send(mgr, out, "second", second, T0, GNSS)
        assert mgr.graph.wait_idle(120)
        state = mgr.graph.snapshot("default")
    finally:
        mgr.stop()
    assert state is not None
    first_kfs = state.session_keyframes(("mapper", "d1"))
    travel = np.linalg.norm(mapper[-1].T_world_sensor[:3, 3] - mapper[0].T_world_sensor[:3, 3])
    assert len(first_kfs) >= travel // 10  # the first drive left one every 10 m
    # the second: none where the first left one within reach (its first sweep's only, if any)
    second_kfs = state.session_keyframes(("second", "d1"))
    firsts = np.array([kf.live[:3, 3] for kf in first_kfs])
    for kf in second_kfs:
        assert np.linalg.norm(firsts - kf.live[:3, 3], axis=1).min() > KNOWN_PLACE_M or kf.index == 0, kf
    skipped = metrics.graph_keyframes.labels("known_place")._value.get()
    assert skipped >= len(first_kfs) - 2 - len(second_kfs), (skipped, len(first_kfs), len(second_kfs))
