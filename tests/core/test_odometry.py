"""Algorithm 2 (incremental matcher) on real KITTI frames and on controlled failures."""

from __future__ import annotations

import functools
import re
from typing import Any

import numpy as np
import pytest

from randt.core import odometry
from randt.core.errors import InvalidCloudError
from randt.core.features import extract_features
from randt.core.io import kitti_velodyne_poses, read_cloud, read_kitti_calib, read_kitti_poses
from randt.core.odometry import (
    MATCHED_TO_MAP,
    MID_SWEEP,
    RELOCALIZE_EVERY,
    IncrementalMatcher,
    MatcherSettings,
    PosePrior,
    deskew,
    on_map_stride,
)
from randt.core.scenes import synthetic_room
from randt.core.transforms import invert, make_transform, scale_motion, transform_error, transform_points
from randt.sim.drive import Motion, Route, SimScan
from tests.data import require_data


@pytest.fixture(scope="module")
def kitti00():
    root = require_data("kitti00/velodyne/000010.bin", "kitti00/poses.txt", "kitti00/calib.txt") / "kitti00"
    P = kitti_velodyne_poses(
        read_kitti_poses(root / "poses.txt"), read_kitti_calib(root / "calib.txt")["Tr"]
    )[:11]
    P = np.array([invert(P[0]) @ p for p in P])
    scans = [read_cloud(root / f"velodyne/{k:06d}.bin").xyz for k in range(11)]
    return scans, P


@pytest.fixture(scope="module")
def kitti00_run(kitti00):
    scans, _ = kitti00
    matcher = IncrementalMatcher()
    return matcher, [matcher.register_scan(s) for s in scans]


def _f2f(poses) -> np.ndarray:
    return np.array([invert(poses[i]) @ poses[i + 1] for i in range(len(poses) - 1)])


def test_kitti00_every_scan_matches(kitti00_run) -> None:
    _, results = kitti00_run
    assert [r.status for r in results] == ["first"] + ["ok"] * 10
    assert all(r.converged for r in results)
    assert min(r.inlier_ratio for r in results[1:]) > 0.5


def test_kitti00_frame_to_frame_against_ground_truth(kitti00, kitti00_run) -> None:
    """Bounds from KISS-ICP on the same frames (0.109 m, 0.174 deg; bench/odometry.py): the ground
    truth of these 11 frames is itself about 10 % long (data README), hence the 0.11 m floor."""
    _, P = kitti00
    matcher, _ = kitti00_run
    err = np.array([transform_error(a, b) for a, b in zip(_f2f(matcher.poses), _f2f(P), strict=True)])
    assert err[:, 0].mean() < 0.13
    assert err[:, 1].mean() < 0.21


def test_kitti00_travel_matches_what_the_scans_imply(kitti00_run) -> None:
    """KISS-ICP, point-to-plane ICP and facade correlation agree on about 7.6 m (data README)."""
    matcher, _ = kitti00_run
    travel = float(np.linalg.norm(matcher.poses[-1][:3, 3]))
    assert 7.4 < travel < 7.8


def test_model_is_bounded_by_keyframes(kitti00, kitti00_run) -> None:
    matcher, results = kitti00_run
    assert sum(r.is_keyframe for r in results) >= 3
    scans, _ = kitti00
    assert matcher.model_size < 2 * max(s.shape[0] for s in scans)


def test_garbage_scan_falls_back_to_prediction_and_says_so() -> None:
    rng = np.random.default_rng(0)
    room = synthetic_room(rng)
    matcher = IncrementalMatcher(MatcherSettings(voxel_sizes_m=(2.0, 1.0, 0.5)))
    step = make_transform(translation=(0.3, 0.0, 0.0))
    poses = [np.eye(4), step, step @ step]
    for T in poses:
        r = matcher.register_scan(transform_points(invert(T), room))
        assert r.status in ("first", "ok")
    garbage = rng.uniform(-40, 40, size=(20000, 3))
    r = matcher.register_scan(garbage)
    assert r.status == "fallback" and r.message
    predicted = matcher.poses[-2] @ step
    err_m, err_deg = transform_error(r.T_world_sensor, predicted)
    assert err_m < 0.05 and err_deg < 0.5
    assert not r.is_keyframe, "a fallback scan must not enter the model"


def test_a_lost_session_stops_retrying(monkeypatch) -> None:
    """Each failing sweep tries the prediction and its yaw retries (5 registrations here); after
    3 fallbacks in a row the session counts as lost and tries the prediction only, so a lost
    vehicle cannot take the CPU of the others; one good match ends it."""
    import randt.core.odometry as odometry

    calls = []
    real = odometry.register
    monkeypatch.setattr(odometry, "register", lambda *a, **k: calls.append(1) or real(*a, **k))
    rng = np.random.default_rng(0)
    room = synthetic_room(rng)
    matcher = IncrementalMatcher(MatcherSettings(voxel_sizes_m=(2.0, 1.0, 0.5)))
    step = make_transform(translation=(0.3, 0.0, 0.0))
    for T in (np.eye(4), step, step @ step):
        assert matcher.register_scan(transform_points(invert(T), room)).status in ("first", "ok")
    per_sweep = []
    for _ in range(5):
        calls.clear()
        assert matcher.register_scan(rng.uniform(-40, 40, size=(20000, 3))).status == "fallback"
        per_sweep.append(len(calls))
    assert per_sweep == [5, 5, 5, 1, 1], per_sweep
    # The prediction keeps moving at the last velocity; a sweep that matches it ends the loss.
    T = matcher.poses[-1] @ step
    assert matcher.register_scan(transform_points(invert(T), room)).status == "ok"
    calls.clear()
    matcher.register_scan(rng.uniform(-40, 40, size=(20000, 3)))
    assert len(calls) == 5


def test_prior_pose_seeds_the_first_scan_and_gates_jumps() -> None:
    rng = np.random.default_rng(1)
    room = synthetic_room(rng)
    T0 = make_transform(euler_deg=(0, 0, 30), translation=(100.0, 50.0, 0.0))
    cov = np.diag([0.05**2] * 3 + [0.01**2] * 3)
    matcher = IncrementalMatcher(MatcherSettings(voxel_sizes_m=(2.0, 1.0, 0.5)))
    r0 = matcher.register_scan(room, prior=PosePrior(T0, cov))
    assert r0.status == "first" and np.allclose(r0.T_world_sensor, T0)
    # The next scan is the same view, but the prior claims a 3 m jump with 5 cm sigma.
    jump = T0 @ make_transform(translation=(3.0, 0, 0))
    r1 = matcher.register_scan(room, prior=PosePrior(jump, cov))
    assert r1.status == "fallback" and "prior" in r1.message
    np.testing.assert_allclose(r1.T_world_sensor, jump)


def test_deskew_recovers_a_sweep_taken_while_moving() -> None:
    """A sweep seen from a sensor turning 3 deg and moving 1 m a period (the screw motion: an arc
    at constant speed) is put back into its start frame to round-off."""
    rng = np.random.default_rng(2)
    pts = synthetic_room(rng, 2000)
    tau = rng.uniform(0, 0.1, pts.shape[0])
    delta = make_transform(rotvec=(0, 0, np.radians(3.0)), translation=(1.0, 0.1, 0.0))  # per 0.1 s
    # p_tau: where the point appears from the sensor at time tau (the motion so far undone).
    undo = [invert(scale_motion(delta, k / 0.1)) for k in tau]
    p_tau = np.array([T[:3, :3] @ p + T[:3, 3] for T, p in zip(undo, pts, strict=True)])
    back = deskew(p_tau, tau, delta, 0.1)
    assert np.abs(back - pts).max() < 1e-9


def test_a_first_sweep_with_point_times_is_not_deskewed_and_says_so() -> None:
    """A session's first sweep is matched before any motion is known: with point times its
    points carry the sweep's own motion (a metre at 10 m/s), and its result says so (the service
    keeps none of them for the map or the pose graph: issue 57, 46 cm graph errors from
    loops to such keyframes). The second sweep is deskewed; a sweep without times needs none."""
    rng = np.random.default_rng(4)
    pts = synthetic_room(rng, 4000)
    tau = rng.uniform(0, 0.1, pts.shape[0])
    timed, untimed = IncrementalMatcher(), IncrementalMatcher()
    first = timed.register_scan(pts, time_offset_s=tau)
    second = timed.register_scan(pts + [0.05, 0.0, 0.0], time_offset_s=tau)
    assert not first.deskewed and len(first.deskewed_xyz) > 1000
    assert second.deskewed and second.status == "ok"
    assert untimed.register_scan(pts, time_offset_s=None).deskewed


def test_mismatched_time_offsets_are_an_invalid_cloud() -> None:
    matcher = IncrementalMatcher()
    with pytest.raises(InvalidCloudError, match="time offsets"):
        matcher.register_scan(np.zeros((100, 3)) + 5, time_offset_s=np.zeros(99))


def test_features_split_ground_objects_noise(kitti00) -> None:
    scans, _ = kitti00
    f = extract_features(scans[0], voxel_size_m=0.5)
    ground_z = scans[0][f.ground_mask, 2]
    assert 0.4 < f.ground_mask.mean() < 0.75  # a KITTI street is mostly road
    assert np.median(ground_z) == pytest.approx(-1.73, abs=0.15)  # HDL-64E 1.73 m above the road
    assert f.noise_mask.mean() < 0.01
    assert 3000 < f.matching_xyz.shape[0] < 20000
    # The matching set's object rows come first; the ground rows (below them) are the rest.
    objects, ground = f.object_matching_xyz, f.matching_xyz[f.n_object_rows :]
    assert len(objects) > 1000 and len(ground) > 1000
    assert np.median(ground[:, 2]) == pytest.approx(-1.73, abs=0.15)
    assert np.median(objects[:, 2]) > -1.0
    # Ground downsampled like objects (factor 1) keeps 2.4 times what the default factor 2 does.
    fine = extract_features(scans[0], voxel_size_m=0.5, ground_voxel_factor=1.0)
    assert fine.n_object_rows == f.n_object_rows
    assert 2.0 < (len(fine.matching_xyz) - fine.n_object_rows) / len(ground) < 3.0


def test_state_dict_resumes_the_same_trajectory(kitti00) -> None:
    """A matcher rebuilt from its state after 6 sweeps continues exactly like the original."""
    scans, _ = kitti00
    a = IncrementalMatcher()
    for s in scans[:6]:
        a.register_scan(s)
    state = {k: v.copy() for k, v in a.state_dict().items()}
    b = IncrementalMatcher()
    b.load_state_dict(state)
    for s in scans[6:9]:
        ra, rb = a.register_scan(s), b.register_scan(s)
        np.testing.assert_allclose(rb.T_world_sensor, ra.T_world_sensor, atol=1e-9)
    assert len(b.poses) == 9


def test_a_failing_scan_leaves_the_matcher_unchanged() -> None:
    """A first sweep too sparse to model raises and leaves no pose behind (poses and the caller's
    stamps stay in step); a later failure leaves poses, velocity and model as they were."""
    rng = np.random.default_rng(4)
    matcher = IncrementalMatcher(MatcherSettings(voxel_sizes_m=(2.0, 1.0, 0.5)))
    sparse = rng.uniform(-50, 50, size=(40, 3))  # no voxel holds enough points for a Gaussian
    with pytest.raises(InvalidCloudError):
        matcher.register_scan(sparse)
    assert matcher.poses == [] and matcher.model_size == 0
    room = synthetic_room(rng)
    step = make_transform(translation=(0.3, 0.0, 0.0))
    for T in (np.eye(4), step):
        assert matcher.register_scan(transform_points(invert(T), room)).status in ("first", "ok")
    before = matcher.state_dict()
    with pytest.raises(InvalidCloudError):
        matcher.register_scan(np.full((50, 3), np.nan))
    after = matcher.state_dict()
    assert before.keys() == after.keys()
    for key in before:
        np.testing.assert_array_equal(before[key], after[key], err_msg=key)
    r = matcher.register_scan(transform_points(invert(step @ step), room))
    assert r.index == 2 and r.status == "ok"


def _raw_corner_run(redeskew: bool) -> tuple[int, float, float]:
    """70 distorted simulated sweeps at a constant 12 m/s from 120 m along the loop through its
    first corner (onset about 195 m along), a plain 9 m arc entered without a clothoid
    (``transition_m=0``, no braking: the yaw rate jumps from 0 to 76 deg/s inside one sweep, a
    stress test no car drives), deskewed by the matcher from the per-point times; returns
    (fallbacks, final translation error m, rotation error deg)."""
    from randt.sim.drive import Motion, Route, simulate
    from randt.sim.town import Town

    town = Town.generate(1)
    route = Route.loop(town, 3, length_m=1000.0, transition_m=0.0)
    matcher = IncrementalMatcher(MatcherSettings(redeskew=redeskew))
    phase = float(np.random.default_rng([1, 2**31]).uniform(0.0, 2.0 * np.pi))
    motion = Motion(route, 12.0, 0.0, phase_rad=phase, start_s_m=120.0, max_lateral_mps2=np.inf)
    gt, fallbacks = [], 0
    # workers=1: the sweeps are ray cast in another process, beside the matching
    for scan in simulate(
        town, route, n_scans=70, speed_mps=12.0, seed=1, deskewed=False, workers=1, start_s_m=120.0,
        max_lateral_mps2=np.inf,
    ):  # fmt: skip
        r = matcher.register_scan(scan.points_xyz.astype(np.float64), time_offset_s=scan.time_offset_s)
        fallbacks += r.status == "fallback"
        gt.append(motion.sensor_poses_at(scan.index * 0.1 + 0.05)[0])
    G = np.array([invert(gt[0]) @ g for g in gt])
    err_m, err_deg = transform_error(matcher.poses[-1], G[-1])
    return fallbacks, err_m, err_deg


def test_deskew_follows_a_corner_onset() -> None:
    """At a sharp corner's onset the previous sweep's velocity warps a distorted sweep the wrong
    way; deskewing again with the matched velocity (and per yaw hypothesis) keeps the track
    (measured: 0 fallbacks, 3.2 cm and 0.016 deg at the end). Without it (``redeskew=False``)
    this drive falls back from sweep 62 on (inlier ratio below 0.3) and ends 4.3 m and 57 deg
    off; bench/odometry.py's raw drive ended 286 m off (ATE) that way. (On the car-like corners,
    clothoids and braking, both keep the track.)"""
    fallbacks, err_m, err_deg = _raw_corner_run(True)
    assert fallbacks == 0
    assert err_m < 0.10 and err_deg < 0.3, (err_m, err_deg)


@functools.cache
def _car_corner_drive() -> tuple[Motion, tuple[SimScan, ...]]:
    """40 distorted simulated sweeps (per-point times) through the first corner of the loop of
    :func:`_raw_corner_run`, driven as a car drives it (clothoid entry and exit, braking to 3 m/s^2
    lateral, 12 m/s on the straights), and the motion that took them."""
    from randt.sim.drive import simulate
    from randt.sim.town import Town

    town = Town.generate(1)
    route = Route.loop(town, 3, length_m=1000.0)
    scans = simulate(
        town, route, n_scans=40, speed_mps=12.0, seed=1, deskewed=False, workers=1, start_s_m=170.0
    )
    phase = float(np.random.default_rng([1, 2**31]).uniform(0.0, 2.0 * np.pi))  # simulate's, for seed 1
    return Motion(route, 12.0, 0.0, phase_rad=phase, start_s_m=170.0), tuple(scans)


def _corner_run(gain: float, monkeypatch: pytest.MonkeyPatch) -> tuple[int, int, float, float]:
    """:func:`_car_corner_drive`'s sweeps matched with ``acceleration_gain``: (fallbacks, sweeps matched a
    second time once deskewed with the matched velocity, final error m, deg)."""
    again = 0
    match_again = IncrementalMatcher._match_again

    def counted(self: IncrementalMatcher, *args: Any) -> Any:
        nonlocal again
        again += 1
        return match_again(self, *args)

    monkeypatch.setattr(IncrementalMatcher, "_match_again", counted)
    matcher = IncrementalMatcher(MatcherSettings(acceleration_gain=gain))
    motion, scans = _car_corner_drive()
    results = [
        matcher.register_scan(
            scan.points_xyz.astype(np.float64), time_offset_s=scan.time_offset_s, stamp_s=scan.stamp_ns * 1e-9
        )
        for scan in scans
    ]
    fallbacks = sum(r.status == "fallback" for r in results)
    # a deskewed sweep's pose is the sensor's at mid-sweep
    gt = motion.sensor_poses_at(np.array([0.05, len(scans) * 0.1 - 0.05]))
    err_m, err_deg = transform_error(matcher.poses[-1], invert(gt[0]) @ gt[1])
    return fallbacks, again, err_m, err_deg


def test_a_corner_driven_as_a_car_drives_it_is_predicted_with_its_acceleration(monkeypatch) -> None:
    """Through a corner's clothoid the yaw rate grows sweep by sweep, and the speed changes as the
    car brakes and speeds up again: a constant-velocity prediction is a sweep behind both, its
    first deskew warps the sweep by the difference, and most of these sweeps are deskewed and
    matched a second time. Carrying the velocity's change on (``acceleration_gain=1``, the
    default) predicts them: measured 13 sweeps matched a second time against 31 with
    ``acceleration_gain=0``, no fallback either way, and both ends within 1 cm (0.59, 0.65) and
    0.003 deg of the truth after 40 sweeps (about 40 m)."""
    fallbacks, again, err_m, err_deg = _corner_run(1.0, monkeypatch)
    fallbacks_cv, again_cv, err_m_cv, err_deg_cv = _corner_run(0.0, monkeypatch)
    assert fallbacks == fallbacks_cv == 0
    assert again_cv >= 20 and again <= 0.6 * again_cv, (again, again_cv)
    assert err_m < 0.02 and err_deg < 0.02, (err_m, err_deg)
    assert err_m_cv < 0.02 and err_deg_cv < 0.02, (err_m_cv, err_deg_cv)


def _two_raw_sweeps(start_s_m: float) -> tuple[list[SimScan], list[np.ndarray]]:
    """The first two distorted sweeps on town 1's loop from ``start_s_m`` at 10 m/s and the true
    sensor poses at their middles."""
    from randt.sim.drive import Motion, Route, simulate
    from randt.sim.town import Town

    town = Town.generate(1)
    route = Route.loop(town, 3, length_m=1000.0)
    motion = Motion(route, 10.0, 0.0, start_s_m=start_s_m)
    scans = list(
        simulate(
            town, route, n_scans=2, speed_mps=10.0, seed=1, deskewed=False, workers=1, start_s_m=start_s_m
        )
    )
    return scans, [motion.sensor_poses_at(0.1 * s.index + 0.05)[0] for s in scans]


def _second_sweep_error_m(start_s_m: float, *, again: bool) -> float:
    """The second pose's error (m, relative to the first) on town 1's loop from ``start_s_m``:
    two distorted sweeps at 10 m/s, deskewed by the matcher; ``again=False`` keeps the first match
    (the first keyframe is still deskewed afterwards, as before 2026-11-28)."""
    scans, truth = _two_raw_sweeps(start_s_m)
    matcher = IncrementalMatcher(MatcherSettings())
    if not again:

        def first_match(outcome: Any, *_: Any) -> Any:
            velocity = invert(matcher.poses[-1]) @ outcome.T
            matcher._deskew_first_keyframe(velocity)
            return outcome

        matcher._second_sweep_again = first_match  # type: ignore[method-assign]
    for s in scans:
        r = matcher.register_scan(
            s.points_xyz.astype(np.float64), time_offset_s=s.time_offset_s, stamp_s=0.1 * s.index
        )
        assert r.status in ("first", "ok")
    return transform_error(invert(matcher.poses[0]) @ matcher.poses[1], invert(truth[0]) @ truth[1])[0]


@pytest.mark.parametrize("start_s_m", [20.0, 60.0])
def test_the_second_sweep_is_matched_again_once_the_first_is_deskewed(start_s_m: float) -> None:
    """The second sweep is matched before any velocity is known, against the first sweep as it
    came (warped by a metre of motion at 10 m/s). Matched again once both are deskewed with the
    velocity found, its pose is within 1 cm (measured 0.03 and 0.10 cm); the first match alone
    was 6.3 and 33.5 cm off, answered ``ok``."""
    assert _second_sweep_error_m(start_s_m, again=True) < 0.01
    assert _second_sweep_error_m(start_s_m, again=False) > 0.05


@pytest.mark.parametrize("start_s_m", [20.0, 60.0])
def test_the_first_keyframe_ends_deskewed_with_the_settled_velocity(start_s_m: float) -> None:
    """The first keyframe is deskewed again with each new match's velocity until it settles: the
    last velocity it is deskewed with is the true motion over a period to 2 mm and 0.01 deg
    (measured 0.5 mm, 0.005 deg), while the first (the match against the raw first sweep) was
    further off (6.5 cm from 20 m on)."""
    scans, truth = _two_raw_sweeps(start_s_m)
    matcher = IncrementalMatcher(MatcherSettings())
    used: list[np.ndarray] = []
    deskew_first = matcher._deskew_first_keyframe

    def recording(velocity: np.ndarray) -> None:
        used.append(velocity)
        deskew_first(velocity)

    matcher._deskew_first_keyframe = recording  # type: ignore[method-assign]
    for s in scans:
        matcher.register_scan(
            s.points_xyz.astype(np.float64), time_offset_s=s.time_offset_s, stamp_s=0.1 * s.index
        )
    true_velocity = invert(truth[0]) @ truth[1]
    errors = [transform_error(v, true_velocity) for v in used]
    assert 2 <= len(used) <= 3, errors
    assert errors[-1][0] < 0.002 and errors[-1][1] < 0.01, errors
    assert errors[0][0] > errors[-1][0], errors


def _tarp() -> np.ndarray:
    """A sweep of a sensor blocked by a tarp: 3000 points 2-4 m away in every direction."""
    rng = np.random.default_rng(0)
    tarp = rng.normal(size=(3000, 3))
    return tarp * (rng.uniform(2.0, 4.0, (3000, 1)) / np.linalg.norm(tarp, axis=1, keepdims=True))


@functools.cache
def _loop_sweeps() -> tuple[SimScan, ...]:
    """The first 50 sweeps (deskewed) of town 1's 1000 m loop at 12 m/s, simulated once for the
    tests that drive it (read-only: they copy the points they change)."""
    from randt.sim.drive import Route, simulate
    from randt.sim.town import Town

    town = Town.generate(1)
    route = Route.loop(town, 3, length_m=1000.0)
    return tuple(simulate(town, route, n_scans=50, speed_mps=12.0, seed=1, workers=2))


@functools.cache
def _fleet_sweeps() -> dict[int, SimScan]:
    """The 60 sweeps of town 1's one-vehicle fleet at 10 m/s (seed 3), by index, simulated once."""
    from randt.sim.drive import simulate_fleet
    from randt.sim.town import Town

    return {
        s.index: s
        for _, s in simulate_fleet(Town.generate(1), 1, n_scans=60, seed=3, speed_mps=10.0, workers=2)
    }


def test_a_session_blocked_while_standing_finds_its_track_again() -> None:
    """The sensor is blocked for 1.5 s (a tarp 2-4 m away) while the vehicle stands still; the
    prediction drives on at 12 m/s, so when the sweeps are good again the match lies 18 m behind
    it. That match is accepted (the correction limit grows with every fallback) and the velocity
    is measured from the last match before the blockage, so tracking resumes at once. Before,
    the 2 m limit refused the match forever and the session flew off along its last velocity."""
    scans = _loop_sweeps()[:45]
    tarp = _tarp()
    fed = [(s.points_xyz.astype(np.float64), s.T_world_sensor) for s in scans[:20]]
    fed += [(tarp, scans[19].T_world_sensor)] * 15
    fed += [(s.points_xyz.astype(np.float64), s.T_world_sensor) for s in scans[20:]]
    matcher = IncrementalMatcher()
    statuses = [matcher.register_scan(xyz, stamp_s=0.1 * i).status for i, (xyz, _) in enumerate(fed)]
    assert statuses[20:35] == ["fallback"] * 15
    assert statuses[35:] == ["ok"] * 25, statuses[35:]
    gt = [T for _, T in fed]
    err_m, err_deg = transform_error(invert(matcher.poses[0]) @ matcher.poses[-1], invert(gt[0]) @ gt[-1])
    assert err_m < 0.05 and err_deg < 0.1, (err_m, err_deg)


def _blocked_through_a_u_turn(
    relocalize: bool, **settings: float
) -> tuple[list[str], list[np.ndarray], IncrementalMatcher, list[str]]:
    """40 sweeps at 12 m/s, 20 blocked ones (a tarp) while the vehicle turns round, then the same
    street driven back (the sweeps from the 40th down, seen by the sensor turned by 180 degrees):
    the prediction drives on forwards, the vehicle drives back."""
    from scipy.spatial.transform import Rotation

    scans = _loop_sweeps()[:40]
    tarp = _tarp()
    turned = np.eye(4)
    turned[:3, :3] = Rotation.from_euler("z", 180.0, degrees=True).as_matrix()
    fed = [(s.points_xyz.astype(np.float64), s.T_world_sensor) for s in scans]
    fed += [(tarp, scans[-1].T_world_sensor @ turned)] * 20
    back = scans[:4:-1]
    fed += [(s.points_xyz.astype(np.float64) @ turned[:3, :3], s.T_world_sensor @ turned) for s in back]
    matcher = IncrementalMatcher(MatcherSettings(relocalize=relocalize, **settings))
    results = [matcher.register_scan(xyz, stamp_s=0.1 * i) for i, (xyz, _) in enumerate(fed)]
    return [r.status for r in results], [T for _, T in fed], matcher, [r.message for r in results]


def test_a_session_that_turned_round_unseen_relocalizes_by_global_registration() -> None:
    """Out of the prediction's reach (180 degrees, and metres more every sweep, against a NDT
    basin of a few metres and degrees), the session is found again by global registration of a
    sweep against its keyframes (the nearest by Scan Context) on the first try after the tarp
    (measured: sweep 62), and tracks on: every later sweep matches, within 5 cm of the truth.
    Without relocalization it never finds its track: 104 m off at the end."""
    statuses, gt, matcher, _ = _blocked_through_a_u_turn(True)
    assert statuses[:40] == ["first"] + ["ok"] * 39
    assert all(s == "fallback" for s in statuses[40:60])
    back = statuses.index("ok", 60)
    assert back <= 60 + RELOCALIZE_EVERY, statuses[60:]  # tries come every RELOCALIZE_EVERY fallbacks
    assert statuses[back:] == ["ok"] * (len(statuses) - back), statuses[back:]
    errors = [
        transform_error(invert(matcher.poses[0]) @ matcher.poses[i], invert(gt[0]) @ gt[i])
        for i in range(back, len(gt))
    ]
    assert max(e[0] for e in errors) < 0.05 and max(e[1] for e in errors) < 0.1, max(errors)

    statuses, gt, matcher, _ = _blocked_through_a_u_turn(False)
    err_end = transform_error(invert(matcher.poses[0]) @ matcher.poses[-1], invert(gt[0]) @ gt[-1])
    assert err_end[0] > 10.0, (statuses[60:], err_end)


def test_a_match_whose_objects_miss_the_map_is_refused_whatever_the_ground_says() -> None:
    """With the ground as dense as objects (``ground_voxel_factor`` 1) the first sweep after the
    U-turn, matched from the prediction (25 m on and 180 degrees off), keeps 30 % inliers: the
    street's ground matches anywhere along it (54 %), its objects do not (2 %). Refused on its
    objects (``min_object_inlier_ratio``); accepted without that check, its keyframe anchored every
    later sweep at the wrong place (96 m off at the end). (With the default factor 2 its inlier
    ratio alone, 22 %, refuses it.)"""
    statuses, gt, matcher, messages = _blocked_through_a_u_turn(True, ground_voxel_factor=1.0)
    assert statuses[60] == "fallback" and messages[60].startswith("objects' inlier ratio 0.0"), messages[60]
    statuses, gt, matcher, messages = _blocked_through_a_u_turn(
        True, ground_voxel_factor=1.0, min_object_inlier_ratio=0.0
    )
    assert statuses[60] == "ok"
    err = transform_error(invert(matcher.poses[0]) @ matcher.poses[-1], invert(gt[0]) @ gt[-1])
    assert err[0] > 50.0, err


def _shifted_sweep_run(**settings: float) -> tuple[list[str], list[str], list[float]]:
    """30 sweeps of town 1's loop at 12 m/s, then one whose points are moved 1 m to the left (as
    if the vehicle stood 1 m right of where it can be 0.1 s after the last match: a place that
    looks alike, a wrong-town sweep), then 10 more: (statuses, messages, position errors m).
    Sideways, as the street's walls pull the match the whole metre; moved 1 m along the street
    (before 2026-11-28) the matcher with the trilinearly weighted 8 voxels stays at the
    prediction, answered 2.3 cm from the truth, and the gate has nothing to refuse."""
    scans = _loop_sweeps()[:41]
    matcher = IncrementalMatcher(MatcherSettings(**settings))
    statuses, messages, errors = [], [], []
    for i, s in enumerate(scans):
        xyz = s.points_xyz.astype(np.float64) + (np.array([0.0, 1.0, 0.0]) if i == 30 else 0.0)
        r = matcher.register_scan(xyz, stamp_s=0.1 * i)
        statuses.append(r.status)
        messages.append(r.message)
        truth = invert(scans[0].T_world_sensor) @ s.T_world_sensor
        errors.append(float(np.linalg.norm(r.T_world_sensor[:3, 3] - truth[:3, 3])))
    return statuses, messages, errors


def test_a_tracking_session_refuses_a_match_where_the_vehicle_cannot_be() -> None:
    """While a session tracks, its prediction is off by what the vehicle accelerated since the
    last sweep (5 cm at 1 g over 0.1 s) plus the matches' own error: a match 1 m from it is
    refused (the tracking gate, 0.55 m at 10 Hz), the prediction answered instead (within 5 cm
    of the truth) and the next sweep matches. Under the 2 m a period the gate allowed before,
    the shifted sweep was answered ``ok`` about 1 m off."""
    statuses, messages, errors = _shifted_sweep_run()
    assert statuses == ["first"] + ["ok"] * 29 + ["fallback"] + ["ok"] * 10, statuses
    moved = re.fullmatch(r"match moved the prediction ([0-9.]+) m \(limit 0\.55 m\)", messages[30])
    assert moved and 0.9 < float(moved.group(1)) < 1.1, messages[30]
    assert max(errors) < 0.05, max(errors)
    statuses, _, errors = _shifted_sweep_run(max_tracking_correction_m=2.0)
    assert statuses[30] == "ok" and errors[30] > 0.9, (statuses[30], errors[30])


def _gapped_run(use_stamps: bool) -> tuple[int, float, float, int]:
    """50 simulated sweeps at 12 m/s with runs of sweeps missing, as an overloaded service sheds
    them (drop-oldest): returns (fallbacks, final translation error m, rotation deg, sweeps fed)."""
    missing = {1, 2, 8, 9, 10, 17, 18, 30, 31, 32, 33, 41}
    matcher = IncrementalMatcher()
    fallbacks, fed, gt = 0, 0, []
    for scan in _loop_sweeps():
        if scan.index in missing:
            continue
        stamp = scan.stamp_ns * 1e-9 if use_stamps else None
        r = matcher.register_scan(scan.points_xyz.astype(np.float64), stamp_s=stamp)
        fallbacks += r.status == "fallback"
        fed += 1
        gt.append(scan.T_world_sensor)
    err_m, err_deg = transform_error(invert(matcher.poses[0]) @ matcher.poses[-1], invert(gt[0]) @ gt[-1])
    return fallbacks, err_m, err_deg, fed


def test_stamps_carry_the_prediction_over_dropped_sweeps() -> None:
    """With stamps, gaps of up to 5 periods (6 m at 12 m/s) are predicted at the session's velocity
    and every sweep matches, the second sweep (0.3 s after the first, no velocity yet) too: its
    correction gate grows with the gap. Without stamps the prediction is one period long and the
    first gap fails the gate (a 3.6 m correction against 2 m), which is why the service passes
    stamps."""
    fallbacks, err_m, err_deg, fed = _gapped_run(True)
    assert fed == 38
    assert fallbacks == 0
    assert err_m < 0.02 and err_deg < 0.05, (err_m, err_deg)  # measured 6.6 mm, 0.014 deg
    fallbacks_unstamped, *_ = _gapped_run(False)
    assert fallbacks_unstamped > 0


def test_deferred_model_gives_the_same_trajectory(kitti00, kitti00_run) -> None:
    """``defer_model=True`` with ``update_model()`` after each answer only moves the keyframe
    model's rebuild after the answer: the poses are those of the synchronous matcher."""
    scans, _ = kitti00
    sync, _ = kitti00_run
    deferred = IncrementalMatcher()
    pending_seen = 0
    for k, s in enumerate(scans):
        r = deferred.register_scan(s, defer_model=True)
        if r.is_keyframe and k > 0:
            assert "model" not in r.stage_times_s  # not rebuilt yet
            pending_seen += 1
            assert deferred.update_model() > 0.0  # the caller folds it in
            assert deferred.update_model() == 0.0  # once
        np.testing.assert_allclose(r.T_world_sensor, sync.poses[k], atol=1e-9)
    assert pending_seen >= 3
    sizes = deferred.state_dict()["keyframe_sizes"]
    np.testing.assert_array_equal(sizes, sync.state_dict()["keyframe_sizes"])


def test_a_caller_behind_rebuilds_once_for_two_keyframes(kitti00, kitti00_run, monkeypatch) -> None:
    """A caller that never calls ``update_model`` (always behind): each sweep matches a model
    at most one keyframe old, the model is rebuilt once per two keyframes, every sweep matches,
    and the poses stay within a few millimetres of the synchronous matcher's; a pending keyframe
    is part of the saved state."""
    scans, _ = kitti00
    sync, sync_results = kitti00_run
    behind = IncrementalMatcher()
    rebuilds = []
    original = behind._prepare
    monkeypatch.setattr(behind, "_prepare", lambda store: rebuilds.append(1) or original(store))
    results = [behind.register_scan(s, defer_model=True) for s in scans]
    assert [r.status for r in results] == [r.status for r in sync_results]
    assert [r.is_keyframe for r in results] == [r.is_keyframe for r in sync_results]
    n_keyframes = sum(r.is_keyframe for r in results)
    assert len(rebuilds) <= 1 + (n_keyframes - 1 + 1) // 2, (len(rebuilds), n_keyframes)
    for k in range(len(scans)):
        err_m, err_deg = transform_error(behind.poses[k], sync.poses[k])
        assert err_m < 0.015 and err_deg < 0.03, (k, err_m, err_deg)  # measured 6.3 mm, 0.015 deg
    # Poses a few mm apart put a few keyframe points in other voxels: compare counts.
    assert behind.state_dict()["keyframe_sizes"].size == sync.state_dict()["keyframe_sizes"].size


def test_a_long_gap_through_a_corner_is_bridged() -> None:
    """Gaps of 13-14 sweeps (1.3 s) over a corner's onset and end, as an overloaded service leaves
    them: the constant-velocity prediction misses by 17-28 degrees (asserted from the ground truth
    below, so the test keeps its teeth), the turns scored over the gap find the match, and the
    session keeps its track. Without the gap search a drive with gaps of 8 sweeps lost its track
    for good (inlier ratio 0.20), found by bench/service.py with 4 vehicles; that was on the
    simulator's old corners, whose yaw rate jumped to 64 deg/s at once (on the car-like ones an
    8-sweep gap misses by 15 degrees at most)."""
    from randt.core.transforms import rotation_angle_deg, scale_motion

    keep = [0, 1, 2, 3, 17, 18, 19, 33, 34, 47, 48, 59]
    scans = _fleet_sweeps()
    matcher = IncrementalMatcher()
    misses = []
    for a, i in enumerate(keep):
        scan = scans[i]
        if a > 0:
            prev = keep[a - 1]
            truth = invert(scans[prev].T_world_sensor) @ scan.T_world_sensor
            predicted = scale_motion(matcher.state.delta, i - prev)
            misses.append(rotation_angle_deg((invert(predicted) @ truth)[:3, :3]))
        prior = PosePrior(scan.T_world_sensor, np.diag([1e-4] * 3 + [1e-5] * 3)) if i == 0 else None
        stamp_s = scan.stamp_ns * 1e-9
        r = matcher.register_scan(scan.points_xyz.astype(np.float64), prior=prior, stamp_s=stamp_s)
        assert r.status in ("first", "ok"), (i, r.message)
        err_m, err_deg = transform_error(r.T_world_sensor, scan.T_world_sensor)
        assert err_m < 0.05 and err_deg < 0.1, (i, err_m, err_deg)
    assert max(misses) > 25.0 and sum(m > 15.0 for m in misses) >= 2, misses


def test_a_caller_behind_still_bridges_a_long_gap() -> None:
    """A caller that never calls ``update_model`` (an overloaded matcher process: the model a
    keyframe behind) and gaps of up to 14 sweeps (1.4 s, 14 m) through a corner: the
    constant-velocity prediction misses the 25 -> 39 gap by 33 degrees (asserted). The gap search's
    turns reach 100 degrees either way; with 60, as first built, this drive lost its track on the
    simulator's old corners, where that gap was missed by 73 degrees (found by replaying
    bench/service.py's drop patterns at 8 vehicles)."""
    from randt.core.transforms import rotation_angle_deg, scale_motion

    keep = [*range(13), 17, 25, 39, 44, 54, 58]
    scans = _fleet_sweeps()  # (its first 59 were simulated for it before they were shared)
    matcher = IncrementalMatcher()
    misses = []
    for a, i in enumerate(keep):
        scan = scans[i]
        if a > 0:
            truth = invert(scans[keep[a - 1]].T_world_sensor) @ scan.T_world_sensor
            predicted = scale_motion(matcher.state.delta, i - keep[a - 1])
            misses.append(rotation_angle_deg((invert(predicted) @ truth)[:3, :3]))
        prior = PosePrior(scan.T_world_sensor, np.diag([1e-4] * 3 + [1e-5] * 3)) if i == 0 else None
        stamp_s = scan.stamp_ns * 1e-9
        r = matcher.register_scan(
            scan.points_xyz.astype(np.float64), prior=prior, stamp_s=stamp_s, defer_model=True
        )
        assert r.status in ("first", "ok"), (i, r.message)
        err_m, err_deg = transform_error(r.T_world_sensor, scan.T_world_sensor)
        assert err_m < 0.05 and err_deg < 0.1, (i, err_m, err_deg)
    assert max(misses) > 30.0, misses


def test_a_sweep_failing_after_its_pose_was_appended_leaves_the_state_equal(monkeypatch) -> None:
    """The failure comes late (the keyframe's model cannot be built, after the pose, velocity and
    stamp were updated): the state object is put back whole, equal field by field to its snapshot."""
    rng = np.random.default_rng(5)
    settings = MatcherSettings(voxel_sizes_m=(2.0, 1.0, 0.5), keyframe_distance_m=0.5)
    matcher = IncrementalMatcher(settings)
    room = synthetic_room(rng)
    step = make_transform(translation=(0.3, 0.0, 0.0))
    for k, T in enumerate((np.eye(4), step)):
        matcher.register_scan(transform_points(invert(T), room), stamp_s=0.1 * k)
    before = matcher.state.snapshot()
    assert before == matcher.state
    seen_at_failure = []

    def unbuildable(store: object) -> None:
        seen_at_failure.append((len(matcher.poses), matcher.state.last_stamp_s))
        raise InvalidCloudError("model: too sparse")

    monkeypatch.setattr(matcher, "_prepare", unbuildable)
    with pytest.raises(InvalidCloudError, match="too sparse"):  # 0.6 m from the last keyframe
        matcher.register_scan(transform_points(invert(step @ step), room), stamp_s=0.2)
    assert seen_at_failure == [(3, 0.2)], "the sweep failed after its pose and stamp were recorded"
    assert matcher.state == before
    assert len(matcher.poses) == 2 and matcher.state.last_stamp_s == 0.1
    monkeypatch.undo()
    r = matcher.register_scan(transform_points(invert(step @ step), room), stamp_s=0.2)
    assert r.index == 2 and r.status == "ok"
    assert matcher.state != before, "the equality sees a sweep's changes"


def _levels_per_sweep(matcher: IncrementalMatcher, scans, monkeypatch, stamps=None) -> list[list[float]]:
    """The NDT levels each sweep's registrations ran (a spy on the solver), by sweep."""
    import randt.core.odometry as odometry
    import randt.core.registration as registration

    runs: list[list[float]] = []
    solver, register = registration.ndt_newton, odometry.register

    def spy_solver(moving, gmap, *args, **kwargs):  # type: ignore[no-untyped-def]
        runs[-1].append(gmap.voxel_size_m)
        return solver(moving, gmap, *args, **kwargs)

    def spy_register(*args, **kwargs):  # type: ignore[no-untyped-def]
        runs.append([])
        return register(*args, **kwargs)

    monkeypatch.setattr(registration, "ndt_newton", spy_solver)
    monkeypatch.setattr(odometry, "register", spy_register)
    by_sweep = []
    for k, s in enumerate(scans):
        n = len(runs)
        matcher.register_scan(s, stamp_s=None if stamps is None else stamps[k])
        by_sweep.append([v for run in runs[n:] for v in run])
    return by_sweep


def test_adaptive_levels_skip_the_coarse_levels_a_good_prediction_does_not_need(kitti00, monkeypatch) -> None:
    """KITTI 00: after three matches from the prediction (corrections of centimetres), a sweep
    runs only the levels within LEVEL_MARGIN x its largest recent correction (here the two finest,
    1.6 and 0.8 m) instead of all five, and the poses stay those of every level to 2 mm."""
    from randt.core.odometry import LEVEL_MARGIN

    scans, P_gt = kitti00
    every = IncrementalMatcher(MatcherSettings(adaptive_levels=False))
    for s in scans:
        every.register_scan(s)
    adaptive = IncrementalMatcher()
    levels = _levels_per_sweep(adaptive, scans, monkeypatch)
    all_levels = list(adaptive.registration.voxel_sizes_m or ())
    assert len(all_levels) == 5 and all_levels[-1] == pytest.approx(0.8)
    assert levels[0] == []  # the first sweep is the first keyframe
    assert all(levels[k] == all_levels for k in (1, 2, 3, 4))  # too few corrections known yet
    corrections = adaptive._state.recent_corrections
    assert 0 < max(corrections) * LEVEL_MARGIN < 1.6  # centimetres: the two finest levels do
    assert all(levels[k] == all_levels[-2:] for k in range(5, 11)), levels
    moved = np.linalg.norm(np.array(adaptive.poses)[:, :3, 3] - np.array(every.poses)[:, :3, 3], axis=1)
    assert moved.max() < 0.002, moved
    e_adaptive, e_every = _f2f(adaptive.poses), _f2f(every.poses)
    gt = _f2f(P_gt)
    err = [
        np.mean([transform_error(a, b)[0] for a, b in zip(e, gt, strict=True)]) for e in (e_adaptive, e_every)
    ]
    assert abs(err[0] - err[1]) < 0.001, err


def test_after_a_gap_every_level_runs_again(kitti00, monkeypatch) -> None:
    """A sweep after dropped ones (stamps 0.2 s apart) runs every level, and so do the next ones
    until three corrections are known again; the state_dict carries the corrections."""
    scans, _ = kitti00
    stamps = [0.1 * k for k in range(11)]
    kept = [k for k in range(11) if k != 7]  # sweep 7 dropped upstream
    matcher = IncrementalMatcher()
    levels = _levels_per_sweep(matcher, [scans[k] for k in kept], monkeypatch, [stamps[k] for k in kept])
    all_levels = list(matcher.registration.voxel_sizes_m or ())
    by_index = dict(zip(kept, levels, strict=True))
    assert by_index[6] == all_levels[-2:]
    assert all(by_index[k] == all_levels for k in (8, 9, 10)), levels  # 8 follows the gap
    resumed = IncrementalMatcher()
    resumed.load_state_dict(matcher.state_dict())
    assert list(resumed._state.recent_corrections) == list(matcher._state.recent_corrections)
    assert len(matcher._state.recent_corrections) == 2  # sweeps 9 and 10


@pytest.mark.parametrize("n", [1000, 2500, 2501, 36_000, 120_000, 190_000])
def test_a_sweep_localized_on_the_map_is_taken_at_a_prime_stride(n: int) -> None:
    """At most ON_MAP_SWEEP_POINTS rows of a localized sweep are looked at (about 2,500: 2,118 of a
    36,000-point reduced sweep, 2,264 of a raw HDL-64E sweep), at the smallest stride that leaves
    so few, one prime to every ring count of 16 to 128, so every ring keeps points."""
    import math

    from randt.core.odometry import ON_MAP_STRIDES, ON_MAP_SWEEP_POINTS

    k = on_map_stride(n)
    assert math.ceil(n / k) <= ON_MAP_SWEEP_POINTS + 1
    smaller = [s for s in ON_MAP_STRIDES if s < k]
    assert not smaller or math.ceil(n / smaller[-1]) > ON_MAP_SWEEP_POINTS
    assert all(math.gcd(k, rings) == 1 for rings in (16, 32, 64, 128))
    assert (on_map_stride(1000), on_map_stride(36_000), on_map_stride(120_000)) == (1, 17, 53)


def _gnss_like(T: np.ndarray, offset_m, yaw_deg: float = 0.0) -> np.ndarray:
    """``T`` moved by ``offset_m`` (world frame) and turned by ``yaw_deg``: a GNSS/INS prior's error."""
    out = make_transform(euler_deg=(0, 0, yaw_deg)) @ T
    out[:3, 3] = T[:3, 3] + np.asarray(offset_m, dtype=np.float64)
    return out


def test_a_first_sweep_with_a_prior_is_placed_against_the_map_where_it_has_points() -> None:
    """A GNSS prior is metres off: the first sweep of a session starting where its map has points
    is matched to them from the prior and placed within centimetres of the truth, when the match
    agrees with the prior's covariance; without the map, or with a prior claiming more precision
    than it has, the sweep goes at the prior."""
    sweeps = _loop_sweeps()
    seed = np.vstack([transform_points(sweeps[k].T_world_sensor, sweeps[k].points_xyz) for k in (0, 10)])
    truth = sweeps[5].T_world_sensor
    prior_T = _gnss_like(truth, (1.5, -1.0, 0.3), yaw_deg=0.5)
    loose = PosePrior(prior_T, np.diag([1.0, 1.0, 4.0, 1e-3, 1e-3, 1e-3]))

    placed = IncrementalMatcher().register_scan(sweeps[5].points_xyz, prior=loose, map_seed=seed)
    dt, dr = transform_error(placed.T_world_sensor, truth)
    assert placed.status == "first" and placed.message == MATCHED_TO_MAP
    assert dt < 0.05 and dr < 0.1

    alone = IncrementalMatcher().register_scan(sweeps[5].points_xyz, prior=loose)
    np.testing.assert_allclose(alone.T_world_sensor, prior_T)
    tight = PosePrior(prior_T, np.diag([0.05**2] * 3 + [1e-4] * 3))
    refused = IncrementalMatcher().register_scan(sweeps[5].points_xyz, prior=tight, map_seed=seed)
    np.testing.assert_allclose(refused.T_world_sensor, prior_T)
    assert refused.message == ""


@pytest.mark.parametrize("k", [0, 24])
def test_a_first_sweep_with_point_times_is_deskewed_on_the_map(
    k: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No velocity is known at a session's first sweep: matched to the map as it came, a sweep
    at 12 m/s (k=0, straight, 1.2 m a sweep) or in a corner (k=24, 0.6 m and 3 deg a sweep) is
    placed off the truth by a good part of its travel. Deskewed with the motion its points fit
    the map best (found with its pose in one Newton solve), and matched again, it lands within a
    centimetre (measured: 0.4 and 0.2 cm, 0.01 deg, against 16 and 19 cm matched as it came;
    0.1-0.9 cm over the whole corner), and the second sweep's prediction moves with that motion."""
    motion, scans = _car_corner_drive()
    mid = [motion.sensor_poses_at(s.index * 0.1 + 0.05)[0] for s in scans]
    pieces = []
    for j in range(0, 30, 2):  # the map: the other sweeps, deskewed with the true motion
        if abs(j - k) > 3:
            delta = invert(mid[j]) @ mid[j + 1]
            tau = scans[j].time_offset_s
            flat = deskew(scans[j].points_xyz, tau, delta, 0.1, reference_fraction=MID_SWEEP)
            pieces.append(transform_points(mid[j], flat))
    seed = np.vstack(pieces)
    loose = np.diag([1.0, 1.0, 4.0, 1e-3, 1e-3, 1e-3])
    prior = PosePrior(_gnss_like(mid[k], (1.2, -0.8, 0.2), yaw_deg=0.4), loose)
    raw = scans[k].points_xyz.astype(np.float64), scans[k].time_offset_s

    def first(matcher: IncrementalMatcher) -> tuple[float, float]:
        placed = matcher.register_scan(raw[0], time_offset_s=raw[1], prior=prior, map_seed=seed)
        assert placed.message == MATCHED_TO_MAP
        return transform_error(placed.T_world_sensor, mid[k])

    matcher = IncrementalMatcher()
    dt, dr = first(matcher)
    assert dt < 0.03 and dr < 0.05, (dt, dr)
    true_delta = invert(mid[k]) @ mid[k + 1]
    assert transform_error(matcher._state.delta, true_delta)[0] < 0.1  # (the velocity found)
    monkeypatch.setattr(odometry, "FIRST_MOTION_ITERATIONS", 0)  # (no motion searched: as it came)
    dt_skewed, _ = first(IncrementalMatcher())
    assert dt_skewed > 0.15, dt_skewed


def test_priors_on_every_sweep_gate_jumps_not_the_sessions_drift() -> None:
    """The session's poses drift from its priors as it drives: the prior gate compares each match
    with the last agreeing sweep's offset from its prior, so priors creeping 2 cm a sweep away
    from the odometry (0.6 m over 30 sweeps, 15 sigma of their 4 cm) are all matched, while a
    prior that jumps 1 m makes that sweep fall back, to the prior moved by the session's drift."""
    sweeps = _loop_sweeps()
    cov = np.diag([0.04**2] * 3 + [1e-4] * 3)
    matcher = IncrementalMatcher()
    statuses = []
    for k in range(31):
        T = _gnss_like(sweeps[k].T_world_sensor, (0.02 * k, 0.0, 0.0))
        statuses.append(matcher.register_scan(sweeps[k].points_xyz, prior=PosePrior(T, cov)).status)
    assert statuses == ["first"] + ["ok"] * 30
    drift = matcher.poses[-1][:3, 3] - _gnss_like(sweeps[30].T_world_sensor, (0.6, 0, 0))[:3, 3]
    jumped = _gnss_like(sweeps[31].T_world_sensor, (0.62 + 1.0, 0.0, 0.0))
    r = matcher.register_scan(sweeps[31].points_xyz, prior=PosePrior(jumped, cov))
    assert r.status == "fallback" and "prior" in r.message
    np.testing.assert_allclose(r.T_world_sensor[:3, 3], jumped[:3, 3] + drift, atol=0.05)
