"""A session resumed after a crash matches from where its vehicle is (issue 33).

A running session's snapshot (its matcher's keyframes) is written when it opens and then every
``snapshot_distance_m`` or ``snapshot_interval_s``; a kill -9 between two leaves the keyframes
tens of metres behind the last pose its log holds. Found by bench/graph_crash.py: a vehicle killed
34 m past its only snapshot never matched again (12 % inliers against a gate of 30 %: 266 of 300
sweeps fell back). Now the flusher also saves a recent sweep at its logged pose (``resume.npz``),
which joins the snapshot's keyframes on resume.

The crash is the data directory as a kill -9 leaves it: copied while the service runs, between two
answered scans (every file the store writes is written atomically or fsync'd before the answer).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from randt.service.metrics import ServiceMetrics
from randt.service.sessions import SessionManager
from randt.service.settings import ServiceSettings
from randt.service.store import RESUME_FILENAME, ResumeSweep, Store
from randt.sim.town import Town
from randt.wire.codes import ErrorCode
from randt.wire.messages import ErrorMessage, PoseMessage
from tests.service.test_agreement import MAPPED, _drive, _send

CUT, AFTER = 40, 5  # sweeps before the crash (about 40 m), and after it


def _manager(data: Path, out: list, **settings: float) -> SessionManager:
    """Without the pose graph; the flusher runs only when the test calls it."""
    s = ServiceSettings(data_dir=data, flush_interval_s=3600, capacity_target=0, graph=False, **settings)
    mgr = SessionManager(s, Store(data), out.append, ServiceMetrics())
    assert mgr.wait_matchers(300)
    return mgr


def _resume(data: Path, scans: list) -> list[PoseMessage | ErrorMessage]:
    out: list = []
    mgr = _manager(data, out)
    try:
        for scan in scans[CUT : CUT + AFTER]:
            _send(mgr, out, "car", scan, prior=False)
    finally:
        mgr.stop()
    return [m for m in out if isinstance(m, PoseMessage | ErrorMessage)]


def test_a_session_killed_far_past_its_snapshot_resumes_matching(tmp_path: Path) -> None:
    scans = list(_drive(Town.generate(MAPPED), CUT + AFTER, seed=1))
    out: list = []
    # Snapshots by time only, and not for an hour: the session's only one is its first.
    live = tmp_path / "live"
    mgr = _manager(live, out, snapshot_distance_m=0, snapshot_interval_s=3600)
    try:
        for scan in scans[:CUT]:
            _send(mgr, out, "car", scan, prior=scan.index == 0)
        mgr.flush()  # (the flusher, which saves the resume sweep)
        crash = tmp_path / "crash"
        shutil.copytree(live, crash)  # what a kill -9 now leaves
    finally:
        mgr.stop()
    saved = Store(crash).load_resume_sweep("car", "d1")
    assert saved is not None
    travel = np.linalg.norm(scans[CUT - 1].T_world_sensor[:3, 3] - scans[0].T_world_sensor[:3, 3])
    assert travel > 35.0  # past what the first keyframe alone matches (about 30 m)
    assert CUT - 12 <= saved.pose_index < CUT  # a sweep the map agreement check asked for (every 10th)

    # With it: every sweep after the crash matched, on the truth.
    answers = _resume(shutil.copytree(crash, tmp_path / "with"), scans)
    assert [type(m).__name__ for m in answers] == ["PoseMessage"] * AFTER
    assert all(m.status == "ok" for m in answers if isinstance(m, PoseMessage))
    errors = [
        np.linalg.norm(np.reshape(m.pose, (4, 4))[:3, 3] - scans[m.seq].T_world_sensor[:3, 3])
        for m in answers
        if isinstance(m, PoseMessage)
    ]
    assert max(errors) < 0.05, errors

    # Without it (as before), or with one that is not at the logged pose (not used): the first
    # sweeps after the crash do not match the snapshot's keyframes, 40 m behind; answered lost.
    without = shutil.copytree(crash, tmp_path / "without")
    (without / "sessions" / "car" / "d1" / RESUME_FILENAME).unlink()
    wrong = shutil.copytree(crash, tmp_path / "wrong")
    moved = saved.pose.copy()
    moved[0, 3] += 0.5
    Store(wrong).save_resume_sweep("car", "d1", ResumeSweep(saved.pose_index, moved, saved.points))
    for data in (without, wrong):
        answers = _resume(data, scans)
        first = answers[0]
        assert isinstance(first, ErrorMessage) and first.code == ErrorCode.LOST, first


def test_the_resume_sweep_round_trips_and_a_damaged_one_is_not_used(tmp_path: Path, caplog) -> None:
    store = Store(tmp_path)
    assert store.load_resume_sweep("car", "d1") is None
    (tmp_path / "sessions" / "car" / "d1").mkdir(parents=True)
    pose = np.eye(4)
    pose[:3, 3] = (1.0, 2.0, 3.0)
    points = np.random.default_rng(0).normal(size=(500, 3)).astype(np.float32)
    store.save_resume_sweep("car", "d1", ResumeSweep(7, pose, points))
    back = store.load_resume_sweep("car", "d1")
    assert back is not None and back.pose_index == 7
    np.testing.assert_array_equal(back.pose, pose)
    np.testing.assert_array_equal(back.points, points)
    path = tmp_path / "sessions" / "car" / "d1" / RESUME_FILENAME
    path.write_bytes(path.read_bytes()[:100])
    assert store.load_resume_sweep("car", "d1") is None
    assert "unreadable" in caplog.text
    store.reset_pose_log("car", "d1")  # a session id that starts afresh: its old sweep goes too
    assert not path.exists()
