"""Rare snapshots whose cost does not grow with the session (issue 31).

* A snapshot writes the same bytes at 1000 and at 20000 poses: the trajectory is in the pose log
  already, and neither the commit nor the views rewrite it.
* Between snapshots the flusher asks no matcher for its state; a snapshot is due after
  ``snapshot_interval_s`` or ``snapshot_distance_m``, and at close.
* A crash at each step of a snapshot (segmenting the commit's own poses, closing off the log,
  the commit, the views) loses no pose, repeats none, and leaves a store the next process loads
  and goes on writing; so does a crash while a store of the format before segments is converted.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pytest

import randt.service.session_store as store_module
from randt.core.scenes import synthetic_room
from randt.core.transforms import make_transform, transform_points
from randt.service.matchers import LocalMatcher, MatcherPool, with_trajectory, without_trajectory
from randt.service.runtime import Service
from randt.service.settings import ServiceSettings
from randt.service.store import (
    MATCHER_FILENAME,
    POSE_LOG_FILENAME,
    TRAJECTORY_FILENAME,
    PoseLogRecord,
    SessionRecord,
    Store,
    segment_name,
)
from randt.wire.messages import PoseMessage, encode, scan_from_arrays
from tests.service.api_server import wait_answers

V, S = "car", "drive"


def _poses(first: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
    """Poses and stamps of scans ``first .. stop - 1`` of a made-up drive (0.5 m and 0.3 deg a scan)."""
    i = np.arange(first, stop, dtype=np.float64)
    poses = np.array(
        [
            make_transform(rotvec=(0.0, 0.0, 0.005 * k), translation=(0.5 * k, np.sin(0.01 * k), 0.0))
            for k in i
        ]
    )
    return poses, 1.7e9 + 0.1 * i


def _record(n: int, **kw: Any) -> SessionRecord:
    return SessionRecord(vehicle=V, session=S, map="default", n_scans=n, last_seq=n - 1, frame="map", **kw)


def _state(n: int, points: int = 20_000) -> dict[str, np.ndarray]:
    """A snapshot's matcher state at ``n`` poses (without its trajectory, as the service sends it)."""
    rng = np.random.default_rng(n)
    return {
        "delta": make_transform(translation=(0.5, 0.0, 0.0)),
        "keyframe_points": rng.normal(size=(points, 3)),
        "keyframe_sizes": np.array([points], dtype=np.int64),
        "n_poses": np.array(n, dtype=np.int64),
    }


def _log(store: Store, first: int, stop: int) -> None:
    """Scans ``first .. stop - 1`` acknowledged: each pose appended to the log (seq = index)."""
    poses, stamps = _poses(first, stop)
    for k, (pose, stamp) in enumerate(zip(poses, stamps, strict=True)):
        i = first + k
        status: Literal["first", "ok", "fallback"] = "first" if i == 0 else "ok"
        store.append_pose(V, S, PoseLogRecord(i, i, round(stamp * 1e9), stamp, pose, status))


def _snapshot(store: Store, first: int, n: int) -> SessionRecord:
    """A snapshot as the service writes it: the poses since its last one (``first``) given again."""
    poses, stamps = _poses(first, n)
    return store.save_session(_record(n), poses, stamps, _state(n), first_index=first)


def _written() -> int:
    """Bytes this process has written so far (``wchar``: every write(2), fsync'd or not)."""
    for line in Path("/proc/self/io").read_text().splitlines():
        if line.startswith("wchar:"):
            return int(line.split()[1])
    raise AssertionError("no wchar in /proc/self/io")


@pytest.mark.skipif(not Path("/proc/self/io").exists(), reason="needs Linux's /proc/self/io")
def test_a_snapshot_writes_the_same_bytes_at_1000_and_at_20000_poses(tmp_path: Path) -> None:
    written: dict[int, int] = {}
    for n in (1000, 20_000):
        with Store(tmp_path / str(n)) as store:
            poses, stamps = _poses(0, n)
            store.save_session(_record(n), poses, stamps, _state(n))  # the session so far, in one go
            _log(store, n, n + 10)
            _snapshot(store, n, n + 10)  # (moves the n poses saved above into a segment, once)
            costs = []
            m = n + 10
            for _ in range(3):  # then 1 s of scans at 10 Hz, and the next snapshot
                _log(store, m, m + 10)
                before = _written()
                _snapshot(store, m, m + 10)
                costs.append(_written() - before)
                m += 10
            written[n] = min(costs)
            loaded = store.load_session(V, S)
            assert loaded.record.n_scans == m
            np.testing.assert_array_equal(loaded.poses, _poses(0, m)[0])
            directory = store.session_dir(V, S)
            assert read_rows(directory / TRAJECTORY_FILENAME) == m
            on_disk = sum(p.stat().st_size for p in directory.iterdir())
    state_bytes = sum(a.nbytes for a in _state(0).values())
    # the commit (the matcher state and a small header per array), 10 TUM rows, session.json
    assert written[1000] < state_bytes + 12_000, written
    assert abs(written[20_000] - written[1000]) < 400, written  # digits of the numbers, no more
    assert on_disk > state_bytes + 20_000 * 150  # what a snapshot used to rewrite: all of it


def read_rows(path: Path) -> int:
    return sum(1 for line in path.read_text().splitlines() if line and not line.startswith("#"))


# ------------------------------------------------------------------------------ the service


ROOM = synthetic_room(np.random.default_rng(0), 2500)


def _scan(seq: int, step_m: float = 0.05) -> bytes:
    T = make_transform(translation=(step_m * seq, 0.0, 0.0))
    pts = transform_points(np.linalg.inv(T), ROOM).astype(np.float32)
    return encode(scan_from_arrays(V, S, seq, seq * 100_000_000, pts))


def test_between_snapshots_a_flush_asks_no_matcher_for_its_state(tmp_path: Path, monkeypatch) -> None:
    calls: list[str] = []
    real_state, real_snapshot = LocalMatcher.state_dict, LocalMatcher.snapshot_state

    def state_dict(self: LocalMatcher) -> dict[str, np.ndarray]:
        calls.append("state_dict")
        return real_state(self)

    def snapshot_state(self: LocalMatcher) -> dict[str, np.ndarray]:
        calls.append(f"snapshot at {len(self.poses)}")
        return real_snapshot(self)

    monkeypatch.setattr(LocalMatcher, "state_dict", state_dict)
    monkeypatch.setattr(LocalMatcher, "snapshot_state", snapshot_state)
    settings = ServiceSettings(
        data_dir=tmp_path, matcher_processes=0, flush_interval_s=3600, snapshot_interval_s=3600, graph=False
    )
    svc = Service(settings, with_zenoh=False)
    svc.start()
    mgr = svc.sessions
    assert mgr is not None

    def snapshots() -> list[str]:
        assert calls[1::2] == ["state_dict"] * (len(calls) // 2), calls  # only inside a snapshot
        return calls[::2]

    try:
        for seq in range(8):
            mgr.submit(V, _scan(seq))
            wait_answers(svc, seq + 1)
            mgr.flush()  # one flush per scan: none of them is a snapshot
        assert all(isinstance(m, PoseMessage) for m in wait_answers(svc, 8))
        assert snapshots() == ["snapshot at 1"]  # the session's first
        w = mgr.worker(V, S)
        assert w is not None and w.info.dirty and w.info.saved_scans == 1
        _, poses = mgr.stored_trajectory(V, S)  # yet every acknowledged pose is on disk
        np.testing.assert_array_equal(poses, np.array(w.matcher.poses))
        # due by time: snapshot_interval_s after the last one
        w.info.snapshot_at -= settings.snapshot_interval_s
        mgr.flush()
        assert snapshots() == ["snapshot at 1", "snapshot at 8"]
        w.info.snapshot_at -= settings.snapshot_interval_s
        mgr.flush()
        assert len(snapshots()) == 2, "nothing changed since the last one: no snapshot"
        w.info.snapshot_at += settings.snapshot_interval_s
        # due by distance: the vehicle is snapshot_distance_m from where the last one was taken
        mgr.submit(V, _scan(8))
        wait_answers(svc, 9)
        mgr.flush()
        assert len(snapshots()) == 2
        assert w.info.snapshot_xyz is not None
        w.info.snapshot_xyz = w.info.snapshot_xyz - [settings.snapshot_distance_m, 0.0, 0.0]
        mgr.flush()
        assert snapshots()[-1] == "snapshot at 9"
        # and at close, whatever the time
        mgr.submit(V, _scan(9))
        wait_answers(svc, 10)
        assert mgr.close(V, S)
        assert snapshots() == ["snapshot at 1", "snapshot at 8", "snapshot at 9", "snapshot at 10"]
        record, _, poses, state = mgr.store.load_session(V, S)
        assert record.state == "closed" and record.n_scans == poses.shape[0] == 10
        assert "poses" not in state and int(state["n_poses"]) == 10  # the trajectory is the store's
    finally:
        svc.stop()


def test_a_matcher_process_sends_its_snapshot_state_without_the_trajectory() -> None:
    pool = MatcherPool(1)
    try:
        remote = pool.open((V, S))
        for seq in range(4):
            T = make_transform(translation=(0.05 * seq, 0.0, 0.0))
            remote.register_scan(transform_points(np.linalg.inv(T), ROOM))
        full = remote.state_dict()
        snap = remote.snapshot_state()
        assert "poses" not in snap and int(snap["n_poses"]) == 4
        assert snap.keys() - {"n_poses"} == full.keys() - {"poses"}
        back = with_trajectory(snap, np.array(remote.poses))
        assert back.keys() == full.keys()
        for key, value in full.items():
            np.testing.assert_array_equal(back[key], value, err_msg=key)
        assert with_trajectory(full, np.zeros((0, 4, 4))) is full  # an older snapshot kept its poses
        assert without_trajectory(full).keys() == snap.keys()
    finally:
        pool.close()


# ------------------------------------------------------------------------------ crash at each step


class CrashError(Exception):
    """The process dies here (nothing after this point of the snapshot reaches the disk)."""


def _crash_at(monkeypatch: pytest.MonkeyPatch, step: int | None, steps: list[str]) -> None:
    """Record each write step of the session's snapshots in ``steps``; raise :class:`CrashError` at
    the one numbered ``step`` (counting from 0 after this call)."""
    real_write, real_commit, real_view, real_replace = (
        store_module.atomic_write_bytes,
        store_module.write_commit,
        store_module.SessionStore._extend_view,
        os.replace,
    )

    def hit(name: str) -> None:
        steps.append(name)
        if step is not None and len(steps) - 1 == step:
            raise CrashError(name)

    def write(path: Path, data: bytes) -> None:
        hit(f"write {Path(path).name}")
        real_write(path, data)

    def commit(path: Path, arrays: dict[str, np.ndarray]) -> None:
        hit("commit")
        real_commit(path, arrays)

    def view(self: store_module.SessionStore, *args: Any) -> None:
        hit("view")
        real_view(self, *args)

    def replace(src: Any, dst: Any) -> None:
        if Path(src).name == POSE_LOG_FILENAME:
            hit(f"close off -> {Path(dst).name}")
        real_replace(src, dst)

    monkeypatch.setattr(store_module, "atomic_write_bytes", write)
    monkeypatch.setattr(store_module, "write_commit", commit)
    monkeypatch.setattr(store_module.SessionStore, "_extend_view", view)
    monkeypatch.setattr(os, "replace", replace)


def _history(store: Store) -> None:
    """A session up to its last snapshot: a first snapshot, logged poses closed off into a segment,
    a snapshot with poses that were never logged (kept by its commit), two more logged poses."""
    _log(store, 0, 1)
    _snapshot(store, 0, 1)
    _log(store, 1, 6)
    _snapshot(store, 1, 6)  # the log (6 records, SEGMENT_RECORDS = 2) becomes poses.0000000000.log
    _snapshot(store, 6, 8)  # poses 6, 7 given, never logged: the commit's own
    _log(store, 8, 10)


def _snapshot_poses(state: dict[str, np.ndarray]) -> int:
    """The poses a snapshot's matcher state was taken at (an older one kept them)."""
    return int(state["n_poses"]) if "n_poses" in state else len(state["poses"])


def _check(store: Store, n: int, snapshot: int) -> None:
    """Poses 0 .. n - 1 once each, in order, as logged or saved; the matcher state and the views
    those of the snapshot of ``snapshot`` poses."""
    record, stamps, poses, state = store.load_session(V, S)
    want_poses, want_stamps = _poses(0, n)
    assert (record.n_scans, record.last_seq, poses.shape) == (n, n - 1, (n, 4, 4))
    np.testing.assert_array_equal(poses, want_poses)
    np.testing.assert_array_equal(stamps, want_stamps)
    assert _snapshot_poses(state) == snapshot
    directory = store.session_dir(V, S)
    assert read_rows(directory / TRAJECTORY_FILENAME) == snapshot  # the view of the snapshot's poses
    assert SessionRecord.model_validate_json((directory / "session.json").read_text()).n_scans == snapshot


@pytest.mark.parametrize("legacy", [False, True], ids=["segments", "format-before-segments"])
def test_a_crash_at_each_step_of_a_snapshot_loses_and_repeats_no_pose(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, legacy: bool
) -> None:
    monkeypatch.setattr(store_module, "SEGMENT_RECORDS", 2)
    prepare = _legacy_history if legacy else _history
    steps: list[str] = []
    # the last snapshot's steps, counted once without a crash
    with monkeypatch.context() as m, Store(tmp_path / "count") as store:
        prepare(store)
        _crash_at(m, None, steps)
        _snapshot(store, 10, 10)
    expected = (
        ["write poses.0000000000.log", "write poses.log", "close off -> poses.0000000006.log"]
        if legacy
        else ["write poses.0000000006.log", "close off -> poses.0000000008.log"]
    )
    assert steps == [*expected, "commit", "view", "write session.json"], steps
    for step in range(len(steps)):
        data = tmp_path / f"crash{step}"
        with Store(data) as store:
            prepare(store)
        with monkeypatch.context() as m, Store(data) as store:
            _crash_at(m, step, [])
            with pytest.raises(CrashError):
                store.save_session(_record(10), *_poses(10, 10), _state(10), first_index=10)
        with Store(data) as store:  # the next process
            committed = steps[step] in ("view", "write session.json")
            _check(store, 10, 10 if committed else (6 if legacy else 8))
            _log(store, 10, 12)  # it goes on logging and snapshotting
            _snapshot(store, 10, 12)
            _check(store, 12, 12)
        with Store(data) as store:
            _check(store, 12, 12)
            names = sorted(p.name for p in store.session_dir(V, S).iterdir())
            assert MATCHER_FILENAME in names and not [n for n in names if n.endswith(".tmp")], names


def _legacy_history(store: Store) -> None:
    """A session as the store wrote it before segments: its commit held every pose (0..5 here)
    and the log the poses logged since, some of them also in the commit (a crash before the log
    was compacted)."""
    directory = store.session_dir(V, S)
    directory.mkdir(parents=True)
    poses, stamps = _poses(0, 6)
    state = _state(6)
    state.pop("n_poses")
    state["poses"] = poses  # the matcher state kept its trajectory then
    arrays = {
        **state,
        "_store_record": np.array(_record(6).model_dump_json()),
        "_store_stamps": stamps,
        "_store_poses": poses,
    }
    np.savez(directory / MATCHER_FILENAME, **arrays)  # type: ignore[arg-type]
    log_poses, log_stamps = _poses(4, 10)
    with (directory / POSE_LOG_FILENAME).open("wb") as fh:
        for k, (pose, stamp) in enumerate(zip(log_poses, log_stamps, strict=True)):
            i = 4 + k
            fh.write(PoseLogRecord(i, i, round(stamp * 1e9), stamp, pose, "ok").to_bytes())


def test_a_store_of_the_format_before_segments_loads_as_it_did(tmp_path: Path) -> None:
    with Store(tmp_path) as store:
        _legacy_history(store)
    with Store(tmp_path) as store:
        record, stamps, poses, state = store.load_session(V, S)
        assert record.n_scans == 10 and record.last_seq == 9  # the commit's 6 and the log's 4 more
        np.testing.assert_array_equal(poses, _poses(0, 10)[0])
        np.testing.assert_array_equal(stamps, _poses(0, 10)[1])
        assert state["poses"].shape == (6, 4, 4)  # the snapshot's matcher state, as saved
        assert with_trajectory(state, poses) is state
        # the service's next snapshot converts it: no pose rewritten but the commit's, once
        directory = store.session_dir(V, S)
        store.save_session(
            record, poses[10:], stamps[10:], without_trajectory({**state, "poses": poses}), first_index=10
        )
        names = sorted(p.name for p in directory.iterdir())
        assert segment_name(0) in names
        loaded = store.load_session(V, S)
        np.testing.assert_array_equal(loaded.poses, poses)
        assert int(loaded.state["n_poses"]) == 10


def test_the_log_is_closed_off_into_segments_and_loads_whole(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(store_module, "SEGMENT_RECORDS", 5)
    with Store(tmp_path) as store:
        n = 0
        for stop in (1, 4, 9, 12, 17, 18):
            _log(store, n, stop)
            _snapshot(store, n, stop)
            n = stop
        directory = store.session_dir(V, S)
        names = sorted(p.name for p in directory.iterdir())
        # the log is closed off at the first snapshot that finds it holding 5 records or more
        assert names == [
            MATCHER_FILENAME,
            segment_name(0),
            segment_name(9),
            POSE_LOG_FILENAME,
            "session.json",
            TRAJECTORY_FILENAME,
        ], names
    with Store(tmp_path) as store:
        record, _, poses, _ = store.load_session(V, S)
        assert record.n_scans == 18 and record.n_fallbacks == 0  # (the commit's count, kept)
        np.testing.assert_array_equal(poses, _poses(0, 18)[0])
        # a segment cut short is damage, not a torn tail: the session fails clearly
        segment = directory / segment_name(9)
        segment.write_bytes(segment.read_bytes()[:-10])
    with Store(tmp_path) as store:
        with pytest.raises(store_module.FormatError, match="damaged pose-log segment"):
            store.load_session(V, S)
        assert [p.name for p in store.load_all().problems] == [f"{V}/{S}"]


def test_a_pose_that_does_not_continue_the_trajectory_is_refused(tmp_path: Path) -> None:
    with Store(tmp_path) as store:
        _log(store, 0, 3)
        poses, stamps = _poses(5, 6)
        with pytest.raises(store_module.FormatError, match="does not continue"):
            store.append_pose(V, S, PoseLogRecord(5, 5, 0, float(stamps[0]), poses[0], "ok"))
        with pytest.raises(store_module.InvalidCloudError, match="neither logged nor given"):
            store.save_session(_record(6), poses, stamps, _state(6), first_index=5)


def test_trajectory_view_appends_between_snapshots(tmp_path: Path) -> None:
    """trajectory.tum grows by the new rows (the file is appended to, its start never rewritten)."""
    with Store(tmp_path) as store:
        _log(store, 0, 1)
        _snapshot(store, 0, 1)
        path = store.session_dir(V, S) / TRAJECTORY_FILENAME
        head = path.read_bytes()
        inode = path.stat().st_ino
        _log(store, 1, 30)
        _snapshot(store, 1, 30)
        assert path.read_bytes().startswith(head) and path.stat().st_ino == inode
        assert read_rows(path) == 30


def test_the_snapshot_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    defaults = ServiceSettings()
    assert (defaults.snapshot_interval_s, defaults.snapshot_distance_m) == (30.0, 20.0)
    monkeypatch.setenv("RANDT_SNAPSHOT_INTERVAL_S", "5")
    monkeypatch.setenv("RANDT_SNAPSHOT_DISTANCE_M", "0")  # by time only
    assert (ServiceSettings().snapshot_interval_s, ServiceSettings().snapshot_distance_m) == (5.0, 0.0)
    for bad in ({"snapshot_interval_s": 0}, {"snapshot_interval_s": -1}, {"snapshot_distance_m": -1}):
        with pytest.raises(ValueError):
            ServiceSettings(**bad)  # type: ignore[arg-type]


def test_the_record_is_brought_forward_over_the_poses_logged_after_the_snapshot(tmp_path: Path) -> None:
    with Store(tmp_path) as store:
        _log(store, 0, 1)
        _snapshot(store, 0, 1)
        poses, stamps = _poses(1, 4)
        for k, status in enumerate(("ok", "fallback", "fallback")):
            i = 1 + k
            store.append_pose(V, S, PoseLogRecord(i, 40 + i, 0, float(stamps[k]), poses[k], status))  # type: ignore[arg-type]
    with Store(tmp_path) as store:
        record = store.load_session(V, S).record
        assert (record.n_scans, record.n_fallbacks, record.last_seq) == (4, 2, 43)
