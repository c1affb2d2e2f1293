"""Localizing on the map in the service (service/localizing.py, ``RANDT_LOCALIZE``).

A first vehicle maps the simulator's streets; a second drives them after it, with a first prior
1.5 m off (a GNSS fix): its sweeps are matched on the map around it in the matcher processes
(``mode: localizing``), in the map's frame from its first answer, each within a few centimetres of
the truth; with ``localize`` off the same drive maps as before.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

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


def _mapped(
    tmp_path: Path, out: list, metrics: ServiceMetrics, mapper: list[SimScan], **settings: Any
) -> SessionManager:
    """A service (``settings`` over these tests' own) whose first vehicle drove ``mapper`` with
    an exact first prior and closed its session: the graph idle (when on), the map saved."""
    full = ServiceSettings(data_dir=tmp_path, flush_interval_s=0.3, capacity_target=0, **settings)  # type: ignore[call-arg]
    mgr = SessionManager(full, Store(tmp_path), out.append, metrics)
    try:
        assert mgr.wait_matchers(300)
        _send(mgr, out, "mapper", mapper, mapper[0].T_world_sensor, EXACT)
        mgr.close("mapper", "d1")
        assert mgr.graph is None or mgr.graph.wait_idle(120)
        mgr.flush()
    except BaseException:
        mgr.stop()
        raise
    return mgr


@pytest.mark.parametrize("localize", [True, False])
def test_a_second_vehicle_localizes_on_the_first_ones_map(tmp_path: Path, localize: bool) -> None:
    """The first drive maps (localize off); on a restart with ``localize`` the second drive
    localizes on its map from its first sweep, within 5 cm, and folds only what the map lacks."""
    mapper, second = _drive(1), _drive(2)
    out: list = []
    metrics = ServiceMetrics()

    def manager(localize: bool) -> SessionManager:
        settings = ServiceSettings(
            data_dir=tmp_path, flush_interval_s=0.3, capacity_target=0, graph=False, localize=localize
        )  # type: ignore[call-arg]
        mgr = SessionManager(settings, Store(tmp_path), out.append, metrics)
        assert mgr.wait_matchers(300)
        return mgr

    mgr = manager(False)
    try:
        _send(mgr, out, "mapper", mapper, mapper[0].T_world_sensor, EXACT)
        mgr.close("mapper", "d1")
        mapped = _map_points(mgr)
    finally:
        mgr.stop()
    mgr = manager(localize)
    try:
        assert _map_points(mgr) == mapped  # (as saved)
        T0 = second[0].T_world_sensor.copy()
        T0[:2, 3] += (1.5, -1.0)  # the GNSS fix's error
        localized_before = metrics.scans_localized._value.get()
        _send(mgr, out, "second", second, T0, GNSS)
        localized = metrics.scans_localized._value.get() - localized_before
        info = next(w.info for w in mgr.table.running() if w.info.vehicle == "second")
        assert localized == info.n_localized == (N_SCANS if localize else 0)  # counted as answered
        mgr.close("second", "d1")
        grown = _map_points(mgr) - mapped
    finally:
        mgr.stop()
    # Localized, a sweep folds only what the map lacks (not its surfaces seen again): the second
    # drive grows the map by 0.7 % (measured: 1,736 points on 254,199), mapping it again by 9.0 %
    # (22,983).
    assert (grown < 0.02 * mapped) if localize else (grown > 0.05 * mapped), (grown, mapped)
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


def _map_points(mgr: SessionManager) -> int:
    mgr.flush()
    return sum(t.n_points for t in mgr.maps.grid("default").tiles())


def test_a_localized_drive_adds_no_graph_keyframe_where_the_graph_has_one(tmp_path: Path) -> None:
    """Growth by area: the second drive, localized on the same streets, offers the graph no
    keyframe within KNOWN_PLACE_M and KNOWN_PLACE_DEG of one it holds (counted ``known_place``),
    from its first sweep on; the first drive's keyframes are there every 10 m."""
    from randt.service.graph import KNOWN_PLACE_M

    mapper, second = _drive(1), _drive(2)
    out: list = []
    metrics = ServiceMetrics()
    mgr = _mapped(tmp_path, out, metrics, mapper, localize=True)
    try:
        assert mgr.graph is not None
        T0 = second[0].T_world_sensor.copy()
        T0[:2, 3] += (1.5, -1.0)
        _send(mgr, out, "second", second, T0, GNSS)
        assert mgr.graph.wait_idle(120)
        state = mgr.graph.snapshot("default")
    finally:
        mgr.stop()
    assert state is not None
    # the first maps its new streets from first to last sweep (never localized on its own trail)
    assert {m.mode for m in out if isinstance(m, PoseMessage) and m.vehicle == "mapper"} == {"mapping"}
    first_kfs = state.session_keyframes(("mapper", "d1"))
    travel = np.linalg.norm(mapper[-1].T_world_sensor[:3, 3] - mapper[0].T_world_sensor[:3, 3])
    assert len(first_kfs) >= travel // 10  # the first drive left one every 10 m
    # the second: none where the first left one within reach, its first sweep's neither
    second_kfs = state.session_keyframes(("second", "d1"))
    firsts = np.array([kf.live[:3, 3] for kf in first_kfs])
    for kf in second_kfs:
        assert np.linalg.norm(firsts - kf.live[:3, 3], axis=1).min() > KNOWN_PLACE_M, kf
    skipped = metrics.graph_keyframes.labels("known_place")._value.get()
    assert skipped >= len(first_kfs) - 2 - len(second_kfs), (skipped, len(first_kfs), len(second_kfs))


def _street(x0: float, x1: float, rng: np.random.Generator) -> np.ndarray:
    """Points of a street between two walls (ground, walls, posts) from x0 to x1."""
    n = int(300 * (x1 - x0))
    x = rng.uniform(x0, x1, n)
    side = rng.integers(0, 3, n)
    y = np.where(side == 0, rng.uniform(-8, 8, n), np.where(side == 1, -8.0, 8.0)) + rng.normal(0, 0.02, n)
    z = np.where(side == 0, rng.normal(0, 0.02, n), rng.uniform(0, 4, n))
    return np.stack([x, y, z], axis=1)


def test_a_window_moved_sends_only_the_tiles_new_to_it(tmp_path: Path) -> None:
    """The session sends a window's tiles once: cut again after the reload distance, only the tiles
    the window before did not hold (or that grew by more than RESEND_GROWTH) carry points, and the
    matcher joins the rest from what it kept: the same map as preparing every tile's points. A
    matcher that lost its pieces (a new process) holds no such window: the sweep maps, the next
    one tries the same window, and after a second miss the window is sent whole."""
    from types import SimpleNamespace

    from randt.core.odometry import IncrementalMatcher, MatcherSettings
    from randt.core.tiles import TileGrid
    from randt.service.localizing import RESEND_GROWTH, SessionLocalizer
    from randt.service.matcher_io import MapWindows

    rng = np.random.default_rng(5)
    grid = TileGrid(20, 0.2, 2)
    grid.insert(_street(0.0, 200.0, rng))
    settings = ServiceSettings(
        data_dir=tmp_path,
        localize=True,
        localize_radius_m=30.0,
        localize_reload_m=20.0,
        localize_min_map_points=1000,
    )  # type: ignore[call-arg]
    loc, windows = SessionLocalizer(settings), MapWindows()
    matcher = IncrementalMatcher(MatcherSettings(voxel_sizes_m=(4.0, 2.0, 1.0)))
    token = ("default", *grid.content_token)

    def at(x: float) -> list[np.ndarray]:
        T = np.eye(4)
        T[0, 3] = x
        return [T]

    def same_map(ref, tiles) -> None:  # type: ignore[no-untyped-def]
        whole = matcher.prepare_map(np.concatenate([grid.get(tid).points for tid, _ in tiles]))
        assert ref.n_input_points == whole.n_input_points
        for a, b in zip(ref.maps, whole.maps, strict=True):
            np.testing.assert_array_equal(a.keys, b.keys)
            np.testing.assert_allclose(a.means, b.means, atol=1e-9)

    w1 = loc.window(grid, token, None, at(60.0), "map")
    assert w1 is not None and w1.tiles is not None and set(w1.points) == {t for t, _ in w1.tiles}
    ref1 = windows.on_map(matcher, w1)
    same_map(ref1, w1.tiles)
    held = loc.window(grid, token, None, at(75.0), "map")  # (within the reload distance: held)
    assert held is not None and held.tiles is None and held.center_xy == w1.center_xy
    w2 = loc.window(grid, token, None, at(85.0), "map")
    assert w2 is not None and w2.tiles is not None
    new = {t for t, _ in w2.tiles} - {t for t, _ in w1.tiles}
    assert len(new) >= 2 and set(w2.points) == new
    # joined behind: the sweep it came with is matched on the window held, the next on the new one
    assert windows.on_map(matcher, w2) is ref1
    after = loc.window(grid, token, None, at(86.0), "map")
    assert after is not None and after.tiles is None and after.center_xy == w2.center_xy
    same_map(windows.on_map(matcher, after), w2.tiles)
    assert windows.take_cpu_s() > 0 and windows.take_cpu_s() == 0  # (its CPU, billed once)
    # a tile of the window grows by more than RESEND_GROWTH: sent again with the next window
    grown = grid.get("5_0")
    grid.insert(_street(100.0, 120.0, rng)[:, :] + (0.0, 0.0, 4.5))
    assert grid.get("5_0").n_points > grown.n_points * (1 + RESEND_GROWTH)
    w3 = loc.window(grid, token, None, at(110.0), "map")
    assert w3 is not None and "5_0" in w3.points and "4_0" not in w3.points
    assert windows.on_map(matcher, w3) is not None
    ref3 = windows.on_map(matcher, loc.window(grid, token, None, at(111.0), "map"))
    assert ref3 is not None
    same_map(ref3, w3.tiles)
    # a matcher without the pieces holds no such window; the next one sends every tile
    lost = MapWindows()
    w4 = loc.window(grid, token, None, at(135.0), "map")
    assert w4 is not None and lost.on_map(matcher, w4) is None
    miss = SimpleNamespace(localized=False)
    loc.answered(miss)  # type: ignore[arg-type]
    again = loc.window(grid, token, None, at(135.0), "map")  # (one miss: the same window again)
    assert again is not None and again.tiles is None and lost.on_map(matcher, again) is None
    loc.answered(miss)  # type: ignore[arg-type]
    w5 = loc.window(grid, token, None, at(135.0), "map")  # (two: the window sent whole)
    assert w5 is not None and w5.tiles is not None and set(w5.points) == {t for t, _ in w5.tiles}
    same_map(lost.on_map(matcher, w5), w5.tiles)


def test_a_sessions_first_window_is_smaller_and_the_whole_one_follows(tmp_path: Path) -> None:
    """A session's first window holds the tiles within localize_first_radius_m (its start prepares
    fewer); it is cut again once the vehicle has as little map ahead as a whole window leaves at
    its reload (after localize_reload_m less the difference of the radii, 10 m), then whole, with
    only the tiles the first did not hold, and held for localize_reload_m."""
    from randt.core.tiles import TileGrid
    from randt.service.localizing import SessionLocalizer

    grid = TileGrid(20, 0.2, 2)
    grid.insert(_street(0.0, 400.0, np.random.default_rng(6)))
    settings = ServiceSettings(data_dir=tmp_path, localize=True, localize_min_map_points=1000)  # type: ignore[call-arg]
    assert (settings.localize_first_radius_m, settings.localize_radius_m, settings.localize_reload_m) == (
        50,
        80,
        40,
    )
    loc, token = SessionLocalizer(settings), ("default", *grid.content_token)

    def at(x: float):  # type: ignore[no-untyped-def]
        T = np.eye(4)
        T[0, 3] = x
        return loc.window(grid, token, None, [T], "map")

    first = at(200.0)
    assert first is not None and first.tiles is not None and first.radius_m == 50.0
    assert {t for t, _ in first.tiles} == {t.id for t in grid.tiles_near((200.0, 0.0), 50.0)}
    held = at(209.0)
    assert held is not None and held.tiles is None and held.radius_m == 50.0
    whole = at(211.0)
    assert whole is not None and whole.tiles is not None and whole.radius_m == 80.0
    assert {t for t, _ in whole.tiles} == {t.id for t in grid.tiles_near((211.0, 0.0), 80.0)}
    assert set(whole.points) == {t for t, _ in whole.tiles} - {t for t, _ in first.tiles}
    kept = at(250.0)
    assert kept is not None and kept.tiles is None and kept.radius_m == 80.0
    assert at(252.0).tiles is not None  # type: ignore[union-attr]


def test_a_session_maps_only_after_misses_in_a_row(tmp_path: Path) -> None:
    """One sweep the map did not hold is tried again (on mapped streets a refused match is no
    reason to map); MISSES_BEFORE_MAPPING in a row map for MAP_AFTER_MISS sweeps, then it tries
    again; a localized sweep between misses starts the count over."""
    from types import SimpleNamespace

    from randt.core.tiles import TileGrid
    from randt.service.localizing import MAP_AFTER_MISS, MISSES_BEFORE_MAPPING, SessionLocalizer

    grid = TileGrid(20, 0.2, 2)
    grid.insert(_street(0.0, 100.0, np.random.default_rng(1)))
    settings = ServiceSettings(data_dir=tmp_path, localize=True, localize_min_map_points=1000)  # type: ignore[call-arg]
    loc, token, pose = SessionLocalizer(settings), ("default", *grid.content_token), [np.eye(4)]
    miss, hit = SimpleNamespace(localized=False), SimpleNamespace(localized=True)
    asked = []
    for answer in (
        [miss, hit, miss, miss, hit] + [miss] * MISSES_BEFORE_MAPPING + [hit] * (MAP_AFTER_MISS + 2)
    ):
        asked.append(loc.window(grid, token, None, pose, "map") is not None)
        if asked[-1]:
            loc.answered(answer)  # type: ignore[arg-type]
    assert MISSES_BEFORE_MAPPING == 3 and all(asked[: 5 + MISSES_BEFORE_MAPPING])
    assert not any(asked[5 + MISSES_BEFORE_MAPPING : 5 + MISSES_BEFORE_MAPPING + MAP_AFTER_MISS])
    assert asked[5 + MISSES_BEFORE_MAPPING + MAP_AFTER_MISS]


def test_a_session_does_not_localize_on_the_trail_it_leaves(tmp_path: Path) -> None:
    """A session mapping a new street folds more than ``localize_min_map_points`` around it: it
    still maps (what its points reach, by its folds or the graph's re-folds, is not map to it);
    where the map held points before it came, and for the next session on its street, it
    localizes."""
    from randt.core.tiles import TileGrid
    from randt.service.localizing import SessionLocalizer

    rng = np.random.default_rng(2)
    grid = TileGrid(20, 0.2, 2)
    settings = ServiceSettings(data_dir=tmp_path, localize=True, localize_min_map_points=1000)  # type: ignore[call-arg]
    mapper, pose = SessionLocalizer(settings), [np.eye(4)]
    for x0 in range(0, 100, 10):  # its sweeps, each about to be folded, then folded
        sweep = _street(float(x0), x0 + 10.0, rng)
        mapper.folding("default", grid, sweep)
        grid.insert(sweep)
        pose[0][0, 3] = x0 + 5.0
        assert grid.n_points > 1000
        assert mapper.window(grid, ("default", *grid.content_token), None, pose, "map") is None
    grid.insert(_street(120.0, 160.0, rng))  # another's street ahead of it
    pose[0][0, 3] = 140.0
    assert mapper.window(grid, ("default", *grid.content_token), None, pose, "map") is not None
    pose[0][0, 3] = 50.0
    assert SessionLocalizer(settings).window(grid, ("default", *grid.content_token), None, pose, "map")


def test_a_localized_sweep_keeps_for_the_map_only_what_the_map_lacks(tmp_path: Path) -> None:
    """Of a sweep localized on its window, only the points in no voxel of the window's finest
    level and within its radius go to the map: a box on the street the map does not hold, not
    the street seen again nor what lies beyond the window (issue 57: growth by area)."""
    from randt.core.odometry import IncrementalMatcher, MatcherSettings, ScanResult
    from randt.core.tiles import TileGrid
    from randt.service.localizing import SessionLocalizer
    from randt.service.matcher_io import MapFrame, MapWindows, Registered

    rng = np.random.default_rng(6)
    grid = TileGrid(20, 0.2, 2)
    for _ in range(4):  # (a map as dense as a drive leaves: a Gaussian in every 1 m voxel of it)
        grid.insert(_street(0.0, 200.0, rng))
    settings = ServiceSettings(
        data_dir=tmp_path, localize=True, localize_radius_m=30.0, localize_min_map_points=1000
    )  # type: ignore[call-arg]
    loc, windows = SessionLocalizer(settings), MapWindows()
    matcher = IncrementalMatcher(MatcherSettings(voxel_sizes_m=(4.0, 2.0, 1.0)))
    token = ("default", *grid.content_token)
    T = np.eye(4)
    T[0, 3] = 100.0
    window = loc.window(grid, token, None, [T], "map")
    assert window is not None and windows.on_map(matcher, window) is not None
    again = _street(90.0, 110.0, rng) - (100.0, 0.0, 0.0)  # (sensor frame)
    # 5 m ahead, above the road (a box in the road's own 1 m voxels would count as the road's)
    box = rng.uniform((5.0, -2.0, 1.2), (6.0, -1.0, 2.8), (400, 3))
    beyond = _street(135.0, 140.0, rng) - (100.0, 0.0, 0.0)  # past the window's 30 m
    sweep = np.vstack([again, box, beyond])
    result = ScanResult(
        index=5, T_world_sensor=T, status="ok", converged=True, fitness=0.0, inlier_ratio=0.9,
        is_keyframe=False, time_s=0.0, covariance=np.eye(6), deskewed_xyz=sweep,
        map_index=np.arange(len(sweep)), n_points=len(sweep), n_nonfinite_dropped=0, localized=True,
    )  # fmt: skip
    frame = MapFrame(token, window=window)
    kept = Registered.of(result, None, frame=frame, windows=windows)
    rows = set(kept.map_index.tolist())
    box_rows = set(range(len(again), len(again) + len(box)))
    assert len(rows & box_rows) == len(box)  # the box, new to the map
    assert len(rows - box_rows) < 0.02 * len(again)  # the street seen again: in the map's voxels
    # the same sweep mapped (not localized) keeps every point
    mapped = Registered.of(replace(result, localized=False), None, frame=frame, windows=windows)
    assert len(mapped.map_index) == len(sweep)
    # a graph correction of the session moves a mapped sweep's points, never a localized one's:
    # its pose is the map's already (a corrected localized fold put points metres off)
    C = np.eye(4)
    C[:3, 3] = (0.0, 0.0, -2.0)
    moved = MapFrame(token, C, window=window)
    corrected = Registered.of(result, None, frame=moved, windows=windows)
    np.testing.assert_array_equal(corrected.map_xyz, kept.map_xyz)
    assert corrected.correction is None
    remapped = Registered.of(replace(result, localized=False), None, frame=moved, windows=windows)
    np.testing.assert_allclose(remapped.map_xyz[:, 2], mapped.map_xyz[:, 2] - 2.0, atol=1e-5)


def test_a_keyframe_placed_on_the_map_enters_the_graph_with_its_map_pose_not_the_fix() -> None:
    """A first sweep matched to the map, or a localized one, is offered to the pose graph with its
    pose on the map (5 cm, 0.2 deg) as its prior: the scan's GNSS fix, metres of noise and bias,
    pulled a session mapping mapped streets off the map (the service bench: 180 of 200 scans lost
    with noisy GNSS, none with this). A sweep matched on the session's own keyframes keeps the fix."""
    from randt.core.odometry import MATCHED_TO_MAP, ScanResult
    from randt.service.worker import ON_MAP_FIX_COVARIANCE, SessionWorker

    T = np.eye(4)
    T[:3, 3] = (12.0, -3.0, 0.5)
    result = ScanResult(
        index=0, T_world_sensor=T, status="first", converged=True, fitness=0.0, inlier_ratio=1.0,
        is_keyframe=True, time_s=0.0, covariance=np.full((6, 6), np.nan), deskewed_xyz=np.zeros((0, 3)),
        map_index=np.zeros(0, np.intp), n_points=0, n_nonfinite_dropped=0, message=MATCHED_TO_MAP,
    )  # fmt: skip
    for placed in (result, replace(result, index=7, status="ok", message="", localized=True)):
        fix = SessionWorker._on_map_fix(placed)
        assert fix is not None
        np.testing.assert_array_equal(fix[0], T)
        np.testing.assert_array_equal(fix[1], ON_MAP_FIX_COVARIANCE)
        assert np.sqrt(fix[1][0, 0]) == 0.05
    assert SessionWorker._on_map_fix(replace(result, index=7, status="ok", message="")) is None


def test_the_services_tile_pieces_serve_every_sessions_window(tmp_path: Path) -> None:
    """With its NDT levels fixed, the service prepares each tile once for every session's windows
    (``MapPieces``): two sessions cutting windows over the same tiles send the same pieces, which
    the matcher joins into the map it prepares from the points; a tile grown by more than
    RESEND_GROWTH is prepared again, one grown less keeps its piece and the version it had."""
    from randt.core.odometry import IncrementalMatcher
    from randt.core.tiles import TileGrid
    from randt.service.localizing import RESEND_GROWTH, MapPieces, SessionLocalizer
    from randt.service.matcher_io import MapWindows

    rng = np.random.default_rng(8)
    grid = TileGrid(20, 0.2, 2)
    grid.insert(_street(0.0, 200.0, rng))
    settings = ServiceSettings(
        data_dir=tmp_path, localize=True, localize_radius_m=30.0, localize_min_map_points=1000
    )  # type: ignore[call-arg]
    pieces = MapPieces.for_settings(settings)
    assert pieces is not None and pieces.preparation.levels == settings.session_matcher().voxel_sizes_m
    assert MapPieces.for_settings(settings.model_copy(update={"localize": False})) is None
    token = ("default", *grid.content_token)
    T = np.eye(4)
    T[0, 3] = 60.0
    a, b = SessionLocalizer(settings, pieces), SessionLocalizer(settings, pieces)
    wa, wb = a.window(grid, token, None, [T], "map"), b.window(grid, token, None, [T], "map")
    assert wa is not None and wb is not None and wa.tiles is not None and not wa.points
    assert set(wa.pieces) == {tid for tid, _ in wa.tiles} and len(pieces) == len(wa.pieces)
    assert all(wa.pieces[tid] is wb.pieces[tid] for tid in wa.pieces)  # (prepared once)
    matcher = IncrementalMatcher(settings.session_matcher(), settings.registration)
    joined = MapWindows().on_map(matcher, wa)
    whole = matcher.prepare_map(np.concatenate([grid.get(tid).points for tid, _ in wa.tiles]))
    assert joined is not None and joined.n_input_points == whole.n_input_points
    for x, y in zip(joined.maps, whole.maps, strict=True):
        np.testing.assert_array_equal(x.keys, y.keys)
        np.testing.assert_allclose(x.covariances, y.covariances, atol=1e-9)
    # a tile that grows: by less than RESEND_GROWTH its piece stays, by more it is prepared again
    tile = grid.get("3_0")
    before = pieces.get(token, tile)
    few = int(tile.n_points * RESEND_GROWTH / 2)
    grid.insert(rng.uniform((61.0, -5.0, 3.0), (79.0, 5.0, 3.5), (few, 3)))
    assert pieces.get(token, grid.get("3_0")) is before
    grid.insert(rng.uniform((61.0, -5.0, 3.6), (79.0, 5.0, 6.0), (tile.n_points, 3)))
    again = pieces.get(token, grid.get("3_0"))
    assert again is not before and again[0] == grid.get("3_0").version and again[1] > before[1]


def test_vehicles_opening_together_on_the_map_start_one_a_core_at_a_time(tmp_path: Path) -> None:
    """Three vehicles send their first scans on mapped streets at once to a 2-core node: two
    start (their windows joined, their motion found), the third's opener waits until one of them
    has its first sweep matched (Capacity.try_start), its scan queued meanwhile: every scan is
    answered with a localized pose, none refused (measured: the third started 44 ms after them)."""
    mapper, second = _drive(1), _drive(2)
    out: list = []
    settings = ServiceSettings(data_dir=tmp_path, flush_interval_s=0.3, graph=False, capacity_target=0.6)  # type: ignore[call-arg]
    mgr = SessionManager(settings, Store(tmp_path), out.append, ServiceMetrics())
    try:
        assert mgr.wait_matchers(300)
        _send(mgr, out, "mapper", mapper, mapper[0].T_world_sensor, EXACT)
        mgr.close("mapper", "d1")
        mgr.flush()
    finally:
        mgr.stop()
    out.clear()
    settings = settings.model_copy(update={"localize": True})
    mgr = SessionManager(settings, Store(tmp_path), out.append, ServiceMetrics())
    try:
        assert mgr.wait_matchers(300)
        assert mgr.capacity is not None and mgr.capacity.cores == 2
        capacity, matched_at = mgr.capacity, []
        matched = capacity.matched

        def timed(*args: object, **kwargs: object) -> None:
            matched_at.append(time.monotonic())
            matched(*args, **kwargs)  # type: ignore[arg-type]

        capacity.matched = timed  # type: ignore[method-assign]
        vehicles = ["v1", "v2", "v3"]
        for k in range(3):  # (each vehicle its own stretch of the second drive)
            scan = second[10 * k]
            first = scan_from_arrays(
                vehicles[k], "d1", 0, scan.stamp_ns, scan.points_xyz,
                prior_pose=scan.T_world_sensor, prior_covariance=EXACT,
            )  # fmt: skip
            mgr.submit(vehicles[k], encode(first))
        deadline = time.monotonic() + 120
        while sum(isinstance(m, PoseMessage | ErrorMessage) for m in list(out)) < 3:
            assert time.monotonic() < deadline, "the service stopped answering"
            time.sleep(0.01)
        started = sorted(mgr.capacity._loads[(v, "d1")].opened_at or 0.0 for v in vehicles)
    finally:
        mgr.stop()
    # two started before any sweep was matched, the third once the first of them was
    assert started[1] < matched_at[0] <= started[2] < started[0] + 0.9, (started, matched_at)
    answers = [m for m in out if isinstance(m, PoseMessage | ErrorMessage)]
    assert all(isinstance(m, PoseMessage) and m.mode == "localizing" for m in answers), answers
    for k, m in enumerate(sorted(answers, key=lambda m: m.vehicle)):
        assert transform_error(m.matrix(), second[10 * k].T_world_sensor)[0] < 0.05


def _send_only(
    mgr: SessionManager,
    out: list,
    vehicle: str,
    scans: list[SimScan],
    first_T: np.ndarray | None,
    shift: np.ndarray | None = None,
    *,
    only: bool = True,
) -> list[PoseMessage | ErrorMessage]:
    """``scans`` as a session that only localizes (``localize_only``; ``only`` false: one that
    maps too), the first with a GNSS prior at ``first_T`` (``None``: none), or with ``shift`` every
    scan with one at its true pose moved by ``shift``: its answers, in order."""
    for k, scan in enumerate(scans):
        extra = {"prior_pose": first_T, "prior_covariance": GNSS} if k == 0 and first_T is not None else {}
        if shift is not None:
            extra = {"prior_pose": shift @ scan.T_world_sensor, "prior_covariance": GNSS}
        msg = scan_from_arrays(vehicle, "d1", k, scan.stamp_ns, scan.points_xyz, localize_only=only, **extra)
        mgr.submit(vehicle, encode(msg))
        deadline = time.monotonic() + 60
        while sum(isinstance(m, PoseMessage | ErrorMessage) and m.vehicle == vehicle for m in list(out)) <= k:
            assert time.monotonic() < deadline, "the service stopped answering"
            time.sleep(0.002)
    return sorted(
        (m for m in out if isinstance(m, PoseMessage | ErrorMessage) and m.vehicle == vehicle),
        key=lambda m: m.seq,
    )


def _keyframes(mgr: SessionManager) -> int:
    assert mgr.graph is not None
    state = mgr.graph.snapshot("default")
    return 0 if state is None else sum(len(kfs) for kfs in state.keyframes.values())


def test_a_session_that_only_localizes_never_adds_to_the_map(tmp_path: Path) -> None:
    """``localize_only`` (with the service's ``localize`` off): on the first drive's streets every
    answer is localized on its map, within 5 cm, and the map's points and the graph's keyframes
    stay as they were; far from any tile each scan is answered ``not_on_map`` saying why, and
    nothing reaches the map; a first prior 45 m off is never answered as a good pose. (Without a
    prior: relocalized, the test below.)"""
    mapper, second = _drive(1), _drive(2)
    out: list = []
    mgr = _mapped(tmp_path, out, ServiceMetrics(), mapper, localize=False)
    try:
        assert mgr.graph is not None
        mapped, keyframes = _map_points(mgr), _keyframes(mgr)
        T0 = second[0].T_world_sensor.copy()
        T0[:2, 3] += (1.5, -1.0)  # the GNSS fix's error
        answers = _send_only(mgr, out, "second", second, T0)
        far = np.eye(4)
        far[:2, 3] = (500.0, 0.0)
        away = _send_only(mgr, out, "far", second[:5], None, far)  # (GNSS on every scan)
        off = second[0].T_world_sensor.copy()
        off[:2, 3] += second[-1].T_world_sensor[:2, 3] - second[0].T_world_sensor[:2, 3]  # the drive's end
        assert np.linalg.norm(off[:2, 3] - T0[:2, 3]) > 40.0
        off_answers = _send_only(mgr, out, "off", second[:20], off)
        assert mgr.graph.wait_idle(120)
        after, keyframes_after = _map_points(mgr), _keyframes(mgr)
        record = mgr.saver.record(("second", "d1"))
    finally:
        mgr.stop()
    poses = [a for a in answers if isinstance(a, PoseMessage)]
    assert len(poses) == len(answers) and [a.mode for a in poses] == ["localizing"] * N_SCANS, answers
    errors = np.array(
        [transform_error(a.matrix(), s.T_world_sensor) for a, s in zip(poses, second, strict=True)]
    )
    assert errors[:, 0].max() < 0.05 and errors[:, 1].max() < 0.3, errors.max(axis=0)
    assert (after, keyframes_after) == (mapped, keyframes)  # nothing folded, no keyframe offered
    assert record is not None and record.localize_only and record.frame == "map"
    assert all(isinstance(m, ErrorMessage) and m.code == "not_on_map" for m in away), away
    reasons = [m.reason for m in away if isinstance(m, ErrorMessage)]
    assert len(reasons) == len(away) and all("points within 50 m" in r for r in reasons), reasons
    good = [m for m in off_answers if isinstance(m, PoseMessage) and m.status in ("ok", "first")]
    truth = {k: s.T_world_sensor for k, s in enumerate(second)}
    assert all(transform_error(m.matrix(), truth[m.seq])[0] < 0.3 for m in good), [
        (m.seq, m.status, transform_error(m.matrix(), truth[m.seq])[0]) for m in good
    ]


def test_a_session_without_a_prior_is_relocalized_on_the_map_from_its_first_sweep(tmp_path: Path) -> None:
    """Relocalization (service/places.py): a vehicle without GNSS starting midway between two of the
    first drive's keyframes, 5 m from each, is placed on the shared map at its first sweep from the
    places of the graph and localizes there, every answer within 5 cm in map ``default``; one that
    only localizes the same; a sweep of a town the map never saw is not placed: it maps in its own
    frame, or, only localizing, is answered ``not_on_map``."""
    mapper, second = _drive(1), _drive(2)
    town = Town.generate(5)
    plan = plan_fleet(town, 1, seed=0, route_length_m=400.0)[0]
    elsewhere = list(
        simulate(
            town, plan.route, n_scans=3, seed=3, lidar=Lidar64(n_azimuth=1000, max_range_m=70.0), workers=2
        )
    )
    out: list = []
    mgr = _mapped(tmp_path, out, ServiceMetrics(), mapper, localize=True)
    try:
        assert mgr.graph is not None
        kfs = [kf.live[:3, 3] for kf in mgr.graph.snapshot("default").session_keyframes(("mapper", "d1"))]
        start = 5
        assert min(np.linalg.norm(np.array(kfs) - second[start].T_world_sensor[:3, 3], axis=1)) > 3.0
        blind = _send_only(mgr, out, "blind", second[start:], None, only=False)
        only = _send_only(mgr, out, "only", second[start:], None)
        lost = _send_only(mgr, out, "lost", elsewhere, None, only=False)
        lost_only = _send_only(mgr, out, "lostonly", elsewhere, None)
    finally:
        mgr.stop()
    for answers in (blind, only):
        poses = [a for a in answers if isinstance(a, PoseMessage)]
        assert len(poses) == len(answers) == N_SCANS - start, answers[:3]
        assert {a.map for a in poses} == {"default"} and {a.mode for a in poses} == {"localizing"}
        errors = np.array(
            [
                transform_error(a.matrix(), s.T_world_sensor)
                for a, s in zip(poses, second[start:], strict=True)
            ]
        )
        assert errors[:, 0].max() < 0.05 and errors[:, 1].max() < 0.3, errors.max(axis=0)
    assert all(isinstance(a, PoseMessage) and a.map == "lost.d1" and a.mode == "mapping" for a in lost), lost
    assert all(isinstance(a, ErrorMessage) and a.code == "not_on_map" for a in lost_only), lost_only


def test_the_places_come_back_from_the_graphs_log_and_guess_where_a_sweep_was_taken() -> None:
    """A restarted service's view takes its places again from the logged keyframes (their points):
    the sweep of the second drive at a keyframe's place is guessed within 3 m and 3 deg of where it
    was taken, in the pose the graph holds; a deleted map's places are gone."""
    from randt.service.graph_state import GraphView
    from randt.service.places import MapPlaces

    mapper, second = _drive(1), _drive(2)
    view = GraphView(ServiceMetrics(), lambda _: None, None, None, 10.0, MapPlaces())
    records = [
        (s.stamp_ns * 1e-9, ("keyframe", "default", "mapper", "d1", k, k, s.T_world_sensor, s.points_xyz))
        for k, s in enumerate(mapper)
        if k % 10 == 0
    ]
    view.restore(records)
    assert len(view.places) == len(records) == 5
    for k in (12, 27, 44):
        guesses = view.guesses("default", second[k].points_xyz)
        assert guesses, k
        err = transform_error(guesses[0].T_world_sensor, second[k].T_world_sensor)
        assert err[0] < 3.0 and err[1] < 3.0, (k, err)
    view.forget("default", 1)
    assert not view.guesses("default", second[12].points_xyz) and not len(view.places)


def test_a_window_mostly_of_the_sessions_own_points_is_not_localized_on(tmp_path: Path) -> None:
    """MIN_MAP_SHARE: where the map held a street before the session came, and the session's own
    points (a stretch it mapped, what it saw from afar) came to make more than a quarter of the
    window's, it maps; where they are fewer, it localizes."""
    from randt.core.tiles import TileGrid
    from randt.service.localizing import MIN_MAP_SHARE, SessionLocalizer

    rng = np.random.default_rng(3)
    settings = ServiceSettings(data_dir=tmp_path, localize=True, localize_min_map_points=1000)  # type: ignore[call-arg]
    pose = [np.eye(4)]
    pose[0][0, 3] = 50.0
    for own_share, localizes in ((0.1, True), (0.4, False)):
        grid = TileGrid(20, 0.2, 2)
        grid.insert(_street(0.0, 100.0, rng))  # another's street
        before = grid.n_points
        loc = SessionLocalizer(settings)
        own = _street(0.0, 100.0, rng)[: int(own_share / (1 - own_share) * before)] + [0.0, 0.0, 0.05]
        loc.folding("default", grid, own)
        grid.insert(own)
        share = before / grid.n_points
        assert (share >= MIN_MAP_SHARE) == localizes, share
        window = loc.window(grid, ("default", *grid.content_token), None, pose, "map")
        assert (window is not None) == localizes, (own_share, share)
