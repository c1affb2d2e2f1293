"""The pose graph in the service (service/graph.py): corrections, loop edges, corrected trajectories.

The live test drives one simulated vehicle without priors 1.15 times around a 400 m block. Its
sweeps are sent as a LiDAR without per-point times gives them (not deskewed: 1 m of motion
distortion at 10 m/s), which is a real cause of odometry drift. The graph, in its own process,
must close the loop at the true revisits, publish the keyframes it moved as correction messages,
and serve a corrected trajectory closer to the truth than the live one.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from core.transforms import invert, transform_error, umeyama
from service.graph import correct_trajectory
from service.metrics import ServiceMetrics
from service.sessions import SessionManager
from service.settings import ServiceSettings
from service.store import Store
from sim.drive import plan_fleet, simulate
from sim.lidar import Lidar64
from sim.town import Town
from wire.messages import (
    CorrectionMessage,
    ErrorMessage,
    PoseMessage,
    decode_correction,
    encode,
    scan_from_arrays,
)


def _pose(yaw_deg: float, xyz: tuple[float, float, float]) -> np.ndarray:
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = xyz
    return T


def test_correct_trajectory_moves_keyframes_exactly_and_interpolates_between() -> None:
    poses = np.stack([_pose(0.0, (float(i), 0.0, 0.0)) for i in range(21)])
    indices = np.array([0, 10, 20])
    live = poses[indices]
    C = [_pose(0.0, (0.0, 0.0, 0.0)), _pose(2.0, (1.0, -0.5, 0.0)), _pose(4.0, (2.0, -1.0, 0.2))]
    optimized = np.stack([c @ p for c, p in zip(C, live, strict=True)])
    out = correct_trajectory(poses, indices, live, optimized)
    for k, i in enumerate(indices):
        np.testing.assert_allclose(out[i], optimized[k], atol=1e-12)
    # halfway between keyframes 0 and 10: half the translation and half the yaw of the correction
    half = _pose(1.0, (0.5, -0.25, 0.0)) @ poses[5]
    dt, dr = transform_error(out[5], half)
    assert dt < 1e-9 and dr < 1e-9
    # before the first and after the last keyframe: their correction
    tail = correct_trajectory(np.concatenate([poses, poses[-1:]]), indices, live, optimized)
    np.testing.assert_allclose(tail[-1], C[2] @ poses[-1], atol=1e-12)


def test_correct_trajectory_with_one_or_no_keyframe() -> None:
    poses = np.stack([_pose(0.0, (float(i), 0.0, 0.0)) for i in range(5)])
    C = _pose(10.0, (3.0, 1.0, 0.0))
    out = correct_trajectory(poses, np.array([2]), poses[2:3], (C @ poses[2])[None])
    np.testing.assert_allclose(out, C @ poses, atol=1e-12)
    np.testing.assert_array_equal(correct_trajectory(poses, np.array([], int), poses[:0], poses[:0]), poses)


@pytest.fixture(scope="module")
def loop_drive():
    town = Town.generate(0)
    vehicle = plan_fleet(town, 1, seed=0, route_length_m=400.0)[0]
    n = int(np.ceil(1.15 * vehicle.route.length_m))  # 10 m/s at 10 Hz: one sweep per metre
    lidar = Lidar64(n_azimuth=1000, max_range_m=70.0)
    scans = list(
        simulate(
            town, vehicle.route, n_scans=n, seed=vehicle.seed, lidar=lidar, start_s_m=vehicle.start_s_m,
            deskewed=False,
        )
    )  # fmt: skip
    out: list = []
    with tempfile.TemporaryDirectory() as tmp:
        # Every sweep is submitted at once (faster than real time): the queues hold them all.
        settings = ServiceSettings(
            data_dir=Path(tmp),
            queue_size=len(scans),
            intake_queue_scans=len(scans),
            intake_queue_bytes=1 << 32,
            intake_total_bytes=1 << 32,
        )
        mgr = SessionManager(settings, Store(Path(tmp)), out.append, ServiceMetrics())
        try:
            assert mgr.wait_matchers(120)
            for scan in scans:
                mgr.submit(
                    "car", encode(scan_from_arrays("car", "d1", scan.index, scan.stamp_ns, scan.points_xyz))
                )
            deadline = time.monotonic() + 300
            while sum(isinstance(m, PoseMessage | ErrorMessage) for m in out) < len(scans):
                assert time.monotonic() < deadline, "not every scan was answered in 300 s"
                time.sleep(0.1)
            assert mgr.graph is not None and mgr.graph.wait_idle(300)
            _, live = mgr.trajectory("car", "d1")
            corrected, graph_map = mgr.graph.corrected("car", "d1", live)
            state = mgr.graph.snapshot("car.d1")
            metrics = mgr.metrics
        finally:
            mgr.stop()
    return scans, out, live, corrected, graph_map, state, metrics


def _truth_mid_sweep(scans) -> np.ndarray:
    """Sensor positions at mid-sweep (a pose of a sweep without per-point times refers to it)."""
    truth = np.stack([s.T_world_sensor[:3, 3] for s in scans])
    truth[:-1] = 0.5 * (truth[:-1] + truth[1:])
    return truth


def _ate(positions: np.ndarray, truth: np.ndarray) -> float:
    T, _ = umeyama(positions, truth)
    aligned = positions @ T[:3, :3].T + T[:3, 3]
    return float(np.sqrt(np.mean(np.sum((aligned - truth) ** 2, axis=1))))


def test_live_graph_closes_the_loop_and_corrects_the_trajectory(loop_drive) -> None:
    scans, _out, live, corrected, graph_map, state, metrics = loop_drive
    assert len(live) == len(scans)
    # A session without priors has its own map, and its graph is that map's.
    assert graph_map == "car.d1"
    assert state is not None and state.placed == {("car", "d1")}
    truth = {s.index: s.T_world_sensor for s in scans}
    accepted = [loop for loop in state.loops if loop.accepted]
    assert len(accepted) >= 2, state.loops
    for loop in state.loops:
        # every verification is between the session's own keyframes; accepted ones are true places
        # (the revisit of the first lap: within 10 m) and the graph holds their relative pose
        a, b = loop.a[2], loop.b[2]
        gap = float(np.linalg.norm(truth[a][:3, 3] - truth[b][:3, 3]))
        if loop.accepted:
            assert gap < 10.0, f"loop {a} -> {b} accepted between places {gap:.1f} m apart"
            assert a - b > 300, f"loop {a} -> {b} is no revisit"
    kfs = state.session_keyframes(("car", "d1"))
    assert 40 <= len(kfs) <= 52, f"{len(kfs)} keyframes for {len(scans)} m at one per 10 m"
    spacing = np.linalg.norm(np.diff([k.live[:3, 3] for k in kfs], axis=0), axis=1)
    assert spacing.min() > 8.0 and spacing.max() < 12.0, spacing
    # The corrected trajectory is closer to the truth than the live one (measured: 0.61 -> 0.29 m).
    mid = _truth_mid_sweep(scans)
    ate_live, ate_corrected = _ate(live[:, :3, 3], mid), _ate(corrected[:, :3, 3], mid)
    assert ate_live > 0.3, f"no drift to correct (live ATE {ate_live:.2f} m): the test lost its point"
    assert ate_corrected < 0.6 * ate_live, f"ATE live {ate_live:.2f} m, corrected {ate_corrected:.2f} m"
    # Each keyframe's corrected pose is its optimized one.
    for kf in kfs:
        if kf.optimized is not None:
            np.testing.assert_allclose(corrected[kf.index], kf.optimized, atol=1e-9)

    def total(counter, label: str) -> float:
        return sum(
            s.value
            for m in counter.collect()
            for s in m.samples
            if s.name.endswith("_total") and s.labels.get("result") == label
        )

    assert total(metrics.graph_keyframes, "added") == len(kfs) and state.n_refused == 0
    assert total(metrics.graph_loops, "accepted") == len(accepted)


def test_corrections_are_published_and_replay_to_the_graph_state(loop_drive) -> None:
    scans, out, _live, corrected, _graph_map, state, _ = loop_drive
    poses = {m.seq: m for m in out if isinstance(m, PoseMessage)}
    assert len(poses) == len(scans), "every scan still gets exactly one pose"
    corrections = [m for m in out if isinstance(m, CorrectionMessage)]
    assert corrections, "no correction was published"
    revisions = [m.revision for m in corrections]
    assert revisions == sorted(revisions)
    latest: dict[int, np.ndarray] = {}
    for message in corrections:
        again = decode_correction(encode(message))  # what a subscriber decodes
        assert again.map == "car.d1" and again.vehicle == "car" and again.session == "d1"
        for seq, pose, live_pose in zip(again.seqs(), again.poses(), again.live_poses(), strict=True):
            # ``live`` is the pose answered for that scan
            np.testing.assert_allclose(live_pose, poses[int(seq)].matrix(), atol=1e-9)
            latest[int(seq)] = pose
    # A client applying every correction in order holds the graph's final keyframe poses; the
    # keyframes never listed are where they were answered.
    by_seq = {kf.seq: kf for kf in state.session_keyframes(("car", "d1"))}
    assert all(kf.optimized is not None for kf in by_seq.values())
    assert set(latest) <= set(by_seq) and len(latest) > len(by_seq) // 2
    for seq, kf in by_seq.items():
        np.testing.assert_allclose(latest.get(seq, kf.live), kf.optimized, atol=1e-9)
    moved = sorted(latest)
    # The correction of the last keyframe, applied to its answer, is the corrected pose.
    last = max(moved)
    C = latest[last] @ invert(poses[last].matrix())
    dt, dr = transform_error(C @ poses[last].matrix(), corrected[last])
    assert dt < 1e-6 and dr < 1e-6
