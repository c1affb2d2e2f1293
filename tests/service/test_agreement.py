"""Issue 32: only sweeps that agree with the map reach it (service/agreement.py).

A vehicle drives a town the map knows, then, along the same coordinates, a town the map never saw
(the simulator's town 5 where the map holds town 0): its matcher tracks itself as well as ever,
so every NDT check passes, and before the map agreement check about 46,000 points off the map's
true surfaces were folded in (bench/unmapped_town.py). Now the session is answered ``lost`` from
its first check in the other town on, and the shared map gains no point off town 0's surfaces;
the same for a session without priors that joined the shared map through the pose graph.
"""

from __future__ import annotations

import time
from collections.abc import Generator
from pathlib import Path

import numpy as np
import pytest

from randt.core.odometry import MatcherSettings
from randt.core.tiles import TileGrid
from randt.service.agreement import AGREEING_CHECKS, AgreementGate
from randt.service.metrics import ServiceMetrics
from randt.service.sessions import SessionManager
from randt.service.settings import ServiceSettings
from randt.service.store import Store
from randt.sim.drive import SimScan, plan_fleet, simulate
from randt.sim.lidar import Lidar64
from randt.sim.town import Town
from randt.wire.codes import ErrorCode
from randt.wire.messages import CorrectionMessage, ErrorMessage, PoseMessage, encode, scan_from_arrays

MAPPED, NEVER_MAPPED = 0, 5
OFF_M = 0.3  # a map point farther than this from town 0's true surfaces is off them
PRIOR_COV = np.diag([1e-4] * 3 + [1e-5] * 3)


def _drive(
    town: Town, n: int, seed: int, start_back_m: float = 0.0, start_stamp_ns: int = 0, first: int = 0
) -> Generator[SimScan, None, None]:
    """Sweeps ``first`` to ``n - 1`` of the route through ``town``, simulated as they are taken
    (two processes ahead of the taker, until the generator is closed)."""
    plan = plan_fleet(Town.generate(MAPPED), 1, seed=0, route_length_m=400.0)[0]
    lidar = Lidar64(n_azimuth=1000, max_range_m=70.0)
    start = (plan.start_s_m - start_back_m) % plan.route.length_m
    yield from simulate(
        town, plan.route, n_scans=n, seed=seed, lidar=lidar, start_s_m=start,
        start_stamp_ns=start_stamp_ns, workers=2, first_index=first,
    )  # fmt: skip


def _manager(data: Path, out: list, **settings: object) -> SessionManager:
    s = ServiceSettings(data_dir=data, flush_interval_s=0.3, capacity_target=0, **settings)  # type: ignore[arg-type]
    mgr = SessionManager(s, Store(data), out.append, ServiceMetrics())
    assert mgr.wait_matchers(300)
    return mgr


def _answered(out: list) -> int:
    return sum(isinstance(m, PoseMessage | ErrorMessage) for m in list(out))


def _send(mgr: SessionManager, out: list, vehicle: str, scan, prior: bool) -> None:
    """One scan, once the one before is answered (none shed)."""
    n = _answered(out)
    extra = {"prior_pose": scan.T_world_sensor, "prior_covariance": PRIOR_COV} if prior else {}
    mgr.submit(
        vehicle, encode(scan_from_arrays(vehicle, "d1", scan.index, scan.stamp_ns, scan.points_xyz, **extra))
    )
    deadline = time.monotonic() + 60
    while _answered(out) < n + 1:
        assert time.monotonic() < deadline, "the service stopped answering"
        time.sleep(0.002)


def _off_surface(mgr: SessionManager, town: Town) -> int:
    mgr.flush()
    grid = mgr.maps.get("default")
    if grid is None or not len(grid):
        return 0
    xyz = np.concatenate([t.points for t in grid.tiles()]).astype(np.float64)
    return int((town.surface_distance(xyz) > OFF_M).sum())


def _answers(out: list, vehicle: str) -> dict[int, PoseMessage | ErrorMessage]:
    return {m.seq: m for m in out if isinstance(m, PoseMessage | ErrorMessage) and m.vehicle == vehicle}


@pytest.fixture(scope="module")
def towns() -> tuple[Town, Town]:
    return Town.generate(MAPPED), Town.generate(NEVER_MAPPED)


N_GOOD, N_BAD = 80, 40
#: The joined session's switch to the other town: at this sweep (or 20 after it joined, if later),
#: where its matcher (measured alone) fell back three times in the new town and then matched
#: 1.27 m off the prediction, inside the 2 m a period (and more per fallback) its correction gate
#: allows after fallbacks, and tracked on 1.3 m off (beside two CPU burners, which moved the join
#: and so the switch here, it was answered ``ok`` nine times 1.24-1.53 m off).
HARD_SWITCH = 166


@pytest.fixture(scope="module")
def town_switch(towns: tuple[Town, Town]) -> list[SimScan]:
    """:data:`N_GOOD` sweeps of the mapped town, then :data:`N_BAD` of the other along the same route."""
    mapped, other = towns
    return [*_drive(mapped, N_GOOD, seed=1), *_drive(other, N_GOOD + N_BAD, seed=1, first=N_GOOD)]


def test_a_session_driving_a_town_the_map_never_saw_is_lost_and_adds_nothing(
    tmp_path, towns, town_switch
) -> None:
    """80 sweeps of town 0 with a prior on the first, then 40 of town 5 along the same route: the
    sweeps after the switch are answered ``ok`` only until the first check (every 10 sweeps),
    within 0.5 m of the truth, then ``lost`` with the check's figures; the map gains no point off
    town 0's surfaces (the check dropped the held points instead: thousands of them).

    The map check is the second line: the matcher itself now refuses the other town's sweeps on
    their objects (the next test), so here that check is off (``min_object_inlier_ratio`` 0), as
    it was when the check was built: the ground alone matched them."""
    mapped, _ = towns
    n_good, n_bad, scans = N_GOOD, N_BAD, town_switch
    truth = {s.index: s.T_world_sensor for s in scans}
    out: list = []
    mgr = _manager(tmp_path, out, graph=False, matcher=MatcherSettings(min_object_inlier_ratio=0.0))
    try:
        for s in scans:
            if s.index == n_good:
                off_before, points_before = _off_surface(mgr, mapped), mgr.maps["default"].n_points
            _send(mgr, out, "car", s, prior=s.index == 0)
        off_after = _off_surface(mgr, mapped)
        w = mgr.worker("car", "d1")
        assert w is not None
        info, gate = w.info, w.gate
        disagreements = mgr.metrics.map_disagreements._value.get()
    finally:
        mgr.stop()
    answers = _answers(out, "car")
    assert sorted(answers) == list(range(n_good + n_bad))
    before = [answers[i] for i in range(n_good)]
    assert all(isinstance(m, PoseMessage) and m.status in ("first", "ok") for m in before)
    after = [answers[i] for i in range(n_good, n_good + n_bad)]
    ok_after = [m for m in after if isinstance(m, PoseMessage)]
    assert len(ok_after) <= 10  # until the first check in the other town
    for m in ok_after:
        err = np.linalg.norm(np.reshape(m.pose, (4, 4))[:3, 3] - truth[m.seq][:3, 3])
        assert err < 0.5, (m.seq, err)
    lost = after[len(ok_after) :]
    assert lost and all(isinstance(m, ErrorMessage) and m.code == ErrorCode.LOST for m in lost)
    assert "do not agree with map 'default'" in lost[0].reason, lost[0].reason
    # the map: nothing off town 0's surfaces before or after, though thousands of points came
    assert off_before == 0 and off_after == 0, (off_before, off_after)
    assert gate.n_dropped_points > 5000 and mgr.maps["default"].n_points >= points_before
    assert info.map_disagrees and info.map_agreement < 0.4 and disagreements == 1
    assert info.n_lost == len(lost)


def test_the_matcher_refuses_a_town_the_map_never_saw_on_its_objects(tmp_path, towns, town_switch) -> None:
    """The same drive with the matcher's defaults: the first sweep of town 5 matched against the
    model of town 0 keeps its ground and 1-6 % of its objects, below ``min_object_inlier_ratio``
    (10 %): no sweep after the switch is answered with a pose but the 0.5 s of predictions a
    fallback may answer (marked ``fallback``), then ``lost``; the map gains no point at all."""
    mapped, _ = towns
    n_good, n_bad, scans = N_GOOD, N_BAD, town_switch
    out: list = []
    mgr = _manager(tmp_path, out, graph=False)
    try:
        for s in scans:
            if s.index == n_good:
                mgr.flush()
                points_before = mgr.maps["default"].n_points
            _send(mgr, out, "car", s, prior=s.index == 0)
        mgr.flush()
        points_after = mgr.maps["default"].n_points
        off_after = _off_surface(mgr, mapped)
    finally:
        mgr.stop()
    answers = _answers(out, "car")
    assert sorted(answers) == list(range(n_good + n_bad))
    after = [answers[i] for i in range(n_good, n_good + n_bad)]
    posed = [m for m in after if isinstance(m, PoseMessage)]
    assert all(m.status == "fallback" for m in posed), [m.status for m in posed]
    assert len(posed) <= 5  # a prediction is answered for 0.5 s at most
    lost = after[len(posed) :]
    assert len(lost) >= n_bad - 5
    assert all(isinstance(m, ErrorMessage) and m.code == ErrorCode.LOST for m in lost)
    assert points_after == points_before and off_after == 0, (points_before, points_after, off_after)


def test_a_joined_session_that_drives_into_a_town_the_map_never_saw_adds_nothing(tmp_path, towns) -> None:
    """``gnss`` maps town 0 with a prior; ``nognss``, without priors, starts 100 m behind it,
    joins the shared map through the pose graph, and 20 sweeps after joining drives town 5
    along the same route: from its first check there it is answered ``lost``, the shared map
    gains no point off town 0's surfaces, and nothing it sent after the switch reaches the graph.
    Then a service restarted on the same data shows the same graph and join (issue 33).

    Found by this test: its matcher fell back twice in the new town and then relocalized 18 m
    off (one global registration, 30 % inliers), answered ``ok``. A relocalization is now the
    first of two agreeing registrations, not an answer, and the sweep that verifies it is
    checked against the map (here: 14 % of its points near it, lost)."""
    mapped, other = towns
    n = 260  # at most: the drive ends 40 sweeps after the switch
    late = {"start_back_m": 100.0, "start_stamp_ns": 50_000_000}
    gnss, nognss_here = _drive(mapped, n, seed=1), _drive(mapped, n, seed=2, **late)
    nognss_there: dict[int, SimScan] = {}
    out: list = []
    mgr = _manager(tmp_path, out, graph=True)
    switch: int | None = None
    try:
        graph = mgr.graph
        assert graph is not None
        for k in range(n):
            if switch is not None and k == switch + 40:
                n = k
                break
            _send(mgr, out, "gnss", next(gnss), prior=k == 0)
            if switch is None and graph.joined("nognss", "d1") is not None:
                switch = max(k + 20, HARD_SWITCH)
                there = _drive(other, switch + 40, seed=2, first=switch, **late)  # type: ignore[arg-type]
                nognss_there = {s.index: s for s in there}
            _send(
                mgr, out, "nognss", nognss_there[k] if k in nognss_there else next(nognss_here), prior=False
            )
            # The graph keeps pace with the drive (a condition, not a clock): beside two CPU
            # burners it fell so far behind that the session joined after sweep 220, or never.
            assert graph.wait_idle(120), "the pose graph did not catch up"
        gnss.close()  # (their simulating processes)
        nognss_here.close()
        assert graph.wait_idle(300)
        off_after = _off_surface(mgr, mapped)
        joined = graph.joined("nognss", "d1")
        state = graph.snapshot("default")
        live = mgr.trajectory("nognss", "d1")
        assert live is not None
        corrected, graph_map = graph.corrected("nognss", "d1", live[1])
    finally:
        mgr.stop()
    assert switch is not None and switch + 40 == n, f"nognss joined too late to test ({switch})"
    assert joined is not None and joined[0] == "default"
    answers = _answers(out, "nognss")
    after = [answers[i] for i in range(switch, n)]
    ok_after = [m for m in after if isinstance(m, PoseMessage)]
    assert len(ok_after) <= 10
    truth = {k: s.T_world_sensor for k, s in nognss_there.items()}
    assert graph_map == "default"
    for m in ok_after:  # its answers are in its own frame: corrected into the shared map's
        assert np.allclose(live[1][m.seq], np.reshape(m.pose, (4, 4)))
        assert np.linalg.norm(corrected[m.seq][:3, 3] - truth[m.seq][:3, 3]) < 0.5
    assert all(isinstance(m, ErrorMessage) and m.code == ErrorCode.LOST for m in after[len(ok_after) :])
    assert off_after == 0, off_after
    assert state is not None
    taken = [kf.index for kf in state.session_keyframes(("nognss", "d1"))]
    assert taken and max(taken) < switch + 10, (max(taken), switch)
    # Issue 33, on the same data: a restarted service takes the graph's log again (service/
    # graph_log.py): the session is joined where it was, the graph is the one it showed, nothing
    # is published again, and its old map's name still says where it went.
    out = []
    mgr = _manager(tmp_path, out, graph=True)
    try:
        graph = mgr.graph
        assert graph is not None and graph.wait_idle(300)
        again = graph.joined("nognss", "d1")
        restored = graph.snapshot("default")
        merged = mgr.maps.merged_into("nognss.d1")
        own_loaded = "nognss.d1" in mgr.maps
    finally:
        mgr.stop()
    assert again is not None and again[0] == "default" and np.abs(again[1] - joined[1]).max() < 1e-3
    assert restored is not None and restored.placed == state.placed and restored.revision == state.revision
    kf = lambda st: {(k, i) for k, kfs in st.keyframes.items() for i in kfs}  # noqa: E731
    assert kf(restored) == kf(state)
    assert merged == ("default", "nognss/d1") and not own_loaded
    assert not [m for m in out if isinstance(m, CorrectionMessage)]


def _wall_map() -> tuple[TileGrid, np.ndarray]:
    """A map of ground (20 m x 10 m) and two 6 m walls 4 m high on it, and the same walls as a
    sweep (sensor frame = map)."""
    y, z = np.meshgrid(np.linspace(-3, 3, 61), np.linspace(0.5, 4.5, 41))
    walls = np.vstack([np.c_[np.full(y.size, x), y.ravel(), z.ravel()] for x in (5.0, -5.0)])
    gx, gy = np.meshgrid(np.linspace(-10, 10, 101), np.linspace(-5, 5, 51))
    grid = TileGrid(20, 0.2, 1)
    grid.insert(np.vstack([np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)], walls]))
    return grid, walls


def test_the_gate_holds_points_until_a_check_and_needs_two_agreeing_checks_after_a_disagreement() -> None:
    """AgreementGate alone, against a real TileGrid: points wait for the next check; a check that
    agrees lets them through, one that disagrees drops them and the session stays lost through
    one agreeing check, folding again only after the second; a check where the map has too few
    points has no opinion."""
    grid, walls = _wall_map()
    gate = AgreementGate(min_share=0.5, every=3, min_points=100)
    pts = lambda k: ("default", np.full((k, 3), 1.0, np.float32), None)  # noqa: E731
    here, there = np.eye(4), np.eye(4)
    there[:3, 3] = [2.0, 0.0, 0.0]  # 2 m across them, over the mapped ground: none near
    assert gate.due()  # a session's first sweep is checked
    assert gate.hold(pts(5)) == [] and [len(x) for _, x, _ in gate.check(grid, here, walls)] == [5]
    gate.hold(pts(7))
    gate.matched()
    assert not gate.due()
    gate.hold(pts(11))
    gate.matched()
    assert gate.due()
    gate.hold(pts(13))
    assert gate.check(grid, there, walls) == [] and gate.disagreeing
    assert gate.last is not None and gate.last.share < 0.1 and gate.n_dropped_points == 7 + 11 + 13
    assert "do not agree with map 'default'" in gate.lost_reason("default")
    assert gate.release() == []  # a session closing while disagreeing folds nothing
    assert gate.check(grid, here, walls) == [] and gate.disagreeing  # 1 of 2
    assert f"1 of {AGREEING_CHECKS} checks" in gate.lost_reason("default")
    gate.hold(pts(3))
    assert [len(x) for _, x, _ in gate.check(grid, here, walls)] == [3] and not gate.disagreeing
    far = np.eye(4)
    far[:3, 3] = [500.0, 0.0, 0.0]  # where the map has nothing: no opinion, points go through
    gate.hold(pts(2))
    assert [len(x) for _, x, _ in gate.check(grid, far, walls)] == [2] and gate.last.checked == 0
    off = AgreementGate(min_share=0.0, every=3, min_points=100)
    assert not off.due() and [len(x) for _, x, _ in off.hold(pts(4))] == [4]


def test_a_sweep_localized_on_the_map_is_an_agreeing_check() -> None:
    """A localized sweep's match was with the map (issue 57): it releases what the gate holds as
    an agreeing check does, with no points checked; after a disagreement it counts as one of the
    AGREEING_CHECKS."""
    gate = AgreementGate(min_share=0.5, every=10, min_points=10)
    a, b = ("m", np.zeros((3, 3), np.float32), None), ("m", np.ones((2, 3), np.float32), None)
    assert gate.hold(a) == []
    assert gate.localized() == [a] and gate.held == [] and gate.since_check == 0
    gate.disagreeing = True
    assert gate.hold(b) == [] and gate.localized() == []  # the first of AGREEING_CHECKS: dropped
    assert gate.n_dropped_points == 2 and gate.disagreeing
    assert gate.hold(b) == [] and gate.localized() == [b] and not gate.disagreeing
