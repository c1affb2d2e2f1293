"""Tests for randt.service.store: round trips, safe names, temp-file clean-up, damaged files, and SIGKILL.

Run as a script (``python -m tests.service.test_store --crash-worker DATA SEED``) this module is
the crash test's worker: it loops saving a growing map and two growing sessions into ``DATA``,
resuming from what is on disk, until the test kills it.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
import yaml
from pydantic import ValidationError

from randt.core.errors import FormatError, InvalidCloudError, NotFoundError, RandtError
from randt.core.io import read_cloud, read_tum
from randt.core.io.autoware import AUTOWARE_METADATA_NAME, GRID_SIDECAR_NAME
from randt.core.odometry import IncrementalMatcher, MatcherSettings
from randt.core.scenes import synthetic_room
from randt.core.tiles import Tile, TileGrid
from randt.core.transforms import invert, make_transform, transform_error, transform_points
from randt.service.store import (
    LOCK_FILENAME,
    MATCHER_FILENAME,
    POSE_LOG_FILENAME,
    POSE_LOG_RECORD_SIZE,
    SESSION_FILENAME,
    TRAJECTORY_FILENAME,
    PoseLogRecord,
    SessionRecord,
    Store,
)
from randt.wire.ids import validate_id

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def store(tmp_path: Path):
    with Store(tmp_path / "data") as s:
        yield s


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 4, 4) random rigid transforms, translations up to 100 m."""
    return np.array(
        [make_transform(rotvec=rng.normal(size=3), translation=rng.uniform(-100, 100, 3)) for _ in range(n)]
    )


def small_grid(seed: int = 0) -> TileGrid:
    rng = np.random.default_rng(seed)
    grid = TileGrid(tile_size_m=20, voxel_size_m=0.5, max_points_per_voxel=2)
    xyz = np.column_stack([rng.uniform(-25, 35, 8000), rng.uniform(-15, 25, 8000), rng.uniform(0, 3, 8000)])
    grid.insert(xyz, rng.uniform(0, 255, 8000))
    return grid


def assert_same_tiles(a: TileGrid, b: TileGrid) -> None:
    assert a.tile_ids() == b.tile_ids()
    for ta, tb in zip(a.tiles(), b.tiles(), strict=True):
        assert (ta.id, ta.version) == (tb.id, tb.version)
        np.testing.assert_array_equal(ta.points, tb.points)
        np.testing.assert_array_equal(ta.intensity, tb.intensity)


# --------------------------------------------------------------------------------------------
# maps
# --------------------------------------------------------------------------------------------


def test_tiles_round_trip_with_versions(store: Store) -> None:
    grid = small_grid()
    assert store.load_map("town") is None and store.list_maps() == []
    written = store.save_tiles("town", grid, grid.tile_ids())
    assert written == grid.tile_ids() and len(written) == 12  # 4 x 3 cells of 20 m cover 60 x 40 m
    assert store.list_maps() == ["town"]
    restored = store.load_map("town")
    assert restored is not None
    assert_same_tiles(restored, grid)
    assert (restored.voxel_size_m, restored.max_points_per_voxel) == (0.5, 2)


def test_save_tiles_rewrites_only_the_changed_tiles(store: Store) -> None:
    grid = small_grid()
    store.save_tiles("town", grid, grid.tile_ids())
    directory = store.map_dir("town")
    inodes = {p.name: p.stat().st_ino for p in directory.iterdir()}
    changed = grid.insert(np.array([[5.0, 5.0, 7.5], [5.2, 5.0, 7.5]]))  # a new voxel in tile 0_0
    assert changed == ["0_0"] and grid.get("0_0").version == 2
    assert store.save_tiles("town", grid, changed) == ["0_0"]
    after = {p.name: p.stat().st_ino for p in directory.iterdir()}
    replaced = {name for name in after if after[name] != inodes[name]}
    assert replaced == {"0_0.pcd", AUTOWARE_METADATA_NAME, GRID_SIDECAR_NAME}
    restored = store.load_map("town")
    assert restored is not None
    assert_same_tiles(restored, grid)
    assert restored.get("0_0").n_points == grid.get("0_0").n_points


def test_save_tiles_writes_tiles_missing_on_disk_and_skips_empty_grids(store: Store) -> None:
    grid = small_grid()
    store.save_tiles("town", grid, [])  # nothing named, but no file exists yet: all are written
    assert sorted(p.stem for p in store.map_dir("town").glob("*.pcd")) == sorted(grid.tile_ids())
    assert store.save_tiles("empty", TileGrid(), []) == []
    assert not store.map_dir("empty").exists() and store.list_maps() == ["town"]
    with pytest.raises(NotFoundError):
        store.save_tiles("town", grid, ["99_99"])


# --------------------------------------------------------------------------------------------
# sessions
# --------------------------------------------------------------------------------------------


def session_record(vehicle: str = "car-01", session: str = "2024.06.11_a", n: int = 5, **kw) -> SessionRecord:
    return SessionRecord(vehicle=vehicle, session=session, map="town", n_scans=n, last_seq=n - 1, **kw)


def test_session_round_trip(store: Store) -> None:
    rng = np.random.default_rng(1)
    poses = random_poses(rng, 25)
    stamps = 1.7e9 + np.cumsum(rng.uniform(0.09, 0.11, 25))
    state = {
        "poses": poses[:, :, :],
        "keyframe_points": rng.normal(size=(500, 3)),
        "keyframe_sizes": np.array([200, 300], dtype=np.int64),
        "levels": np.array([2.0, 1.0, 0.5]),
        "last_keyframe_pose": np.full((4, 4), np.nan),
        "flags": np.array([True, False]),
    }
    meta = session_record(n=25, n_fallbacks=2, frame="map")
    before = datetime.now(UTC)
    saved = store.save_session(meta, poses, stamps, state)
    assert saved.updated >= before and saved.created == meta.created

    record, got_stamps, got_poses, got_state = store.load_session("car-01", "2024.06.11_a")
    assert record == saved
    assert (record.n_scans, record.n_fallbacks, record.last_seq, record.frame) == (25, 2, 24, "map")
    np.testing.assert_array_equal(got_stamps, stamps)
    np.testing.assert_array_equal(got_poses, poses)
    assert set(got_state) == set(state)
    for key, value in state.items():
        np.testing.assert_array_equal(got_state[key], value)
        assert got_state[key].dtype == value.dtype

    directory = store.session_dir("car-01", "2024.06.11_a")
    tum_stamps, tum_poses = read_tum(directory / TRAJECTORY_FILENAME)
    np.testing.assert_allclose(tum_stamps, stamps, rtol=0, atol=1e-9)
    np.testing.assert_allclose(tum_poses, poses, rtol=0, atol=1e-9)
    document = json.loads((directory / SESSION_FILENAME).read_text())
    assert document["vehicle"] == "car-01" and document["state"] == "active" and document["n_scans"] == 25
    assert datetime.fromisoformat(document["updated"]) == saved.updated
    assert store.list_sessions() == [saved] and store.problems == []


def test_mark_session_and_list(store: Store) -> None:
    rng = np.random.default_rng(2)
    for vehicle, session in [("b", "s1"), ("a", "s2"), ("a", "s1")]:
        store.save_session(session_record(vehicle, session, n=3), random_poses(rng, 3), np.arange(3.0), {})
    assert [(r.vehicle, r.session) for r in store.list_sessions()] == [("a", "s1"), ("a", "s2"), ("b", "s1")]
    marked = store.mark_session("a", "s2", "closed")
    assert marked.state == "closed"
    store.mark_session("b", "s1", "expired")
    states = {(r.vehicle, r.session): r.state for r in store.list_sessions()}
    assert states == {("a", "s1"): "active", ("a", "s2"): "closed", ("b", "s1"): "expired"}
    assert json.loads((store.session_dir("a", "s2") / SESSION_FILENAME).read_text())["state"] == "closed"
    with pytest.raises(ValueError, match="state"):
        store.mark_session("a", "s1", "paused")  # type: ignore[arg-type]
    with pytest.raises(NotFoundError):
        store.mark_session("a", "s9", "closed")


def test_save_session_rejects_inconsistent_input(store: Store) -> None:
    rng = np.random.default_rng(3)
    poses = random_poses(rng, 4)
    with pytest.raises(InvalidCloudError, match="n_scans"):
        store.save_session(session_record(n=3), poses, np.arange(4.0), {})
    with pytest.raises(InvalidCloudError):
        store.save_session(session_record(n=4), poses, np.arange(3.0), {})
    with pytest.raises(InvalidCloudError):
        store.save_session(session_record(n=4), poses[:, :3], np.arange(4.0), {})
    with pytest.raises(InvalidCloudError, match="finite"):
        store.save_session(session_record(n=4), poses, np.array([0, 1, np.nan, 3]), {})
    bad = poses.copy()
    bad[1, 3, 0] = 0.5
    with pytest.raises(InvalidCloudError, match="homogeneous"):
        store.save_session(session_record(n=4), bad, np.arange(4.0), {})
    with pytest.raises(FormatError, match="_store_"):
        store.save_session(session_record(n=4), poses, np.arange(4.0), {"_store_record": np.zeros(1)})
    with pytest.raises(FormatError, match="not usable"):
        store.save_session(session_record(n=4), poses, np.arange(4.0), {"a/b": np.zeros(1)})
    with pytest.raises(FormatError, match="object"):
        store.save_session(session_record(n=4), poses, np.arange(4.0), {"x": np.array([{}, 1], dtype=object)})
    with pytest.raises(ValidationError):
        session_record(n=2, n_fallbacks=3)
    assert not store.session_dir("car-01", "2024.06.11_a").exists()  # nothing half-written


def test_created_is_kept_from_the_first_save(tmp_path: Path) -> None:
    rng = np.random.default_rng(9)
    poses = random_poses(rng, 3)
    first = datetime(2024, 6, 11, 8, 0, tzinfo=UTC)
    with Store(tmp_path) as store:
        saved = store.save_session(session_record(n=2, created=first), poses[:2], np.arange(2.0), {})
        assert saved.created == first and saved.updated > first and saved.key == ("car-01", "2024.06.11_a")
    with Store(tmp_path) as store:  # a new store reads it from the commit
        again = store.save_session(session_record(n=3), poses, np.arange(3.0), {})  # created: now
        assert again.created == first and again.updated >= saved.updated
        assert store.load_session(*again.key).record.created == first


def test_a_session_without_scans_has_no_trajectory_file(store: Store) -> None:
    rng = np.random.default_rng(10)
    directory = store.session_dir("car-01", "2024.06.11_a")
    store.save_session(session_record(n=0), np.array([]), np.array([]), {})
    assert sorted(p.name for p in directory.iterdir()) == [MATCHER_FILENAME, SESSION_FILENAME]
    record, stamps, poses, state = store.load_session("car-01", "2024.06.11_a")
    assert (record.n_scans, record.last_seq, stamps.shape, poses.shape, state) == (0, -1, (0,), (0, 4, 4), {})
    poses = random_poses(rng, 2)
    store.save_session(session_record(n=2), poses, np.arange(2.0), {})
    np.testing.assert_allclose(read_tum(directory / TRAJECTORY_FILENAME)[1], poses, rtol=0, atol=1e-9)
    assert [r.n_scans for r in store.list_sessions()] == [2]


def test_matcher_resumes_identically_from_a_saved_session(tmp_path: Path) -> None:
    """A matcher restored from the store continues exactly like the one that never stopped."""
    rng = np.random.default_rng(4)
    room = synthetic_room(rng, 3000)
    step = make_transform(euler_deg=(0.0, 0.0, 4.0), translation=(0.6, 0.1, 0.0))
    truth = [np.eye(4)]
    for _ in range(6):
        truth.append(truth[-1] @ step)
    sweeps = [transform_points(invert(T), room) + rng.normal(scale=0.005, size=room.shape) for T in truth]
    settings = MatcherSettings(voxel_sizes_m=(2.0, 1.0, 0.5))

    a = IncrementalMatcher(settings)
    assert [a.register_scan(s).status for s in sweeps[:4]] == ["first", "ok", "ok", "ok"]
    stamps = 0.1 * np.arange(4)
    with Store(tmp_path) as store:
        store.save_session(session_record(n=4), np.array(a.poses), stamps, a.state_dict())
    with Store(tmp_path) as store:
        record, got_stamps, got_poses, state = store.load_session("car-01", "2024.06.11_a")
    np.testing.assert_array_equal(got_stamps, stamps)
    np.testing.assert_array_equal(got_poses, np.array(a.poses))
    assert record.n_scans == 4 and state["keyframe_sizes"].size == 2  # keyframes at sweeps 0 and 3
    for key, value in a.state_dict().items():
        np.testing.assert_array_equal(state[key], value)

    b = IncrementalMatcher(settings)
    b.load_state_dict(state)
    for sweep, T_true in zip(sweeps[4:], truth[4:], strict=True):
        ra, rb = a.register_scan(sweep), b.register_scan(sweep)
        assert ra.status == rb.status == "ok"
        np.testing.assert_allclose(rb.T_world_sensor, ra.T_world_sensor, rtol=0, atol=1e-9)
        err_m, err_deg = transform_error(rb.T_world_sensor, T_true)
        assert err_m < 0.05 and err_deg < 0.3  # the matcher's own accuracy on this room: 2.5 cm, 0.15 deg
    assert len(b.poses) == 7


# --------------------------------------------------------------------------------------------
# names
# --------------------------------------------------------------------------------------------

BAD_NAMES = [
    "",
    ".",
    "..",
    "../etc",
    "a/b",
    "/abs",
    "a\\b",
    ".hidden",
    "-dash",
    "_under",
    "has space",
    "nul\x00",
    "newline\n",
    "caf\u00e9",
    "x" * 65,
]


@pytest.mark.parametrize("name", BAD_NAMES)
def test_unsafe_names_are_rejected(tmp_path: Path, store: Store, name: str) -> None:
    rng = np.random.default_rng(5)
    poses, stamps = random_poses(rng, 1), np.zeros(1)
    with pytest.raises(ValueError, match="invalid"):
        validate_id(name, "map")
    with pytest.raises(ValueError, match="invalid map name"):
        store.save_tiles(name, small_grid(), [])
    with pytest.raises(ValueError, match="invalid map name"):
        store.load_map(name)
    with pytest.raises(ValueError, match="invalid vehicle name"):
        store.load_session(name, "s1")
    with pytest.raises(ValueError, match="invalid session name"):
        store.load_session("car", name)
    with pytest.raises(ValueError, match="invalid session name"):
        store.mark_session("car", name, "closed")
    with pytest.raises(ValidationError, match="invalid vehicle name"):
        SessionRecord(vehicle=name, session="s1", n_scans=1)
    with pytest.raises(ValidationError, match="invalid map name"):
        SessionRecord(vehicle="car", session="s1", map=name, n_scans=1)
    # A record built without validation still cannot reach the file system.
    sneaky = SessionRecord.model_construct(**{**session_record(n=1).model_dump(), "session": name})
    with pytest.raises(ValueError, match="invalid session name"):
        store.save_session(sneaky, poses, stamps, {})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
    assert [p.name for p in (tmp_path / "data" / "maps").iterdir()] == []
    assert [p.name for p in (tmp_path / "data" / "sessions").iterdir()] == []


# --------------------------------------------------------------------------------------------
# opening: temp files, lock
# --------------------------------------------------------------------------------------------


def test_leftover_temp_files_are_removed_on_open(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(6)
    with Store(tmp_path) as store:
        grid = small_grid()
        store.save_tiles("town", grid, grid.tile_ids())
        store.save_session(session_record(n=2), random_poses(rng, 2), np.arange(2.0), {})
        map_dir, session_dir = store.map_dir("town"), store.session_dir("car-01", "2024.06.11_a")
    # What randt.core.io.atomic leaves behind when a process dies mid-write: mkstemp(prefix=".<name>.",
    # suffix=".tmp") next to the target.
    leftovers = [
        tempfile.mkstemp(prefix=".0_0.pcd.", suffix=".tmp", dir=map_dir),
        tempfile.mkstemp(prefix=f".{AUTOWARE_METADATA_NAME}.", suffix=".tmp", dir=map_dir),
        tempfile.mkstemp(prefix=f".{MATCHER_FILENAME}.", suffix=".tmp", dir=session_dir),
        tempfile.mkstemp(prefix=".counters.json.", suffix=".tmp", dir=tmp_path),  # DATA's own file
    ]
    for fd, _ in leftovers:
        os.write(fd, b"half a file")
        os.close(fd)
    keep = [map_dir / "notes.tmp", session_dir / ".keep", tmp_path / ".other.tmp"]
    for path in keep:
        path.write_text("not ours to delete")

    with caplog.at_level(logging.INFO, logger="randt.service.store"), Store(tmp_path) as store:
        assert store.removed_temp_files == 4
        assert "removed 4 temporary files" in caplog.text
        assert not any(Path(name).exists() for _, name in leftovers)
        assert all(path.exists() for path in keep)
        contents = store.load_all()
        assert contents.problems == [] and set(contents.maps) == {"town"} and len(contents.sessions) == 1
    with Store(tmp_path) as store:
        assert store.removed_temp_files == 0


def open_in_another_process(data_dir: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; from randt.service.store import Store; Store(sys.argv[1]).close()",
            data_dir,
        ],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_one_process_per_data_directory(tmp_path: Path) -> None:
    first = Store(tmp_path)
    assert first.writable()
    refused = open_in_another_process(tmp_path)
    assert refused.returncode != 0 and "already open in another process" in refused.stderr

    # In this process a second store shares the lock (a service restarted in-process) and leaves
    # temporary files alone: they could be the first store's writes in flight.
    fd, in_flight = tempfile.mkstemp(prefix=".0_0.pcd.", suffix=".tmp", dir=tmp_path / "maps")
    os.close(fd)
    second = Store(tmp_path)
    assert second.removed_temp_files == 0 and Path(in_flight).exists()
    first.close()
    assert not first.is_open and not first.writable() and second.is_open
    with pytest.raises(RandtError, match="closed"):
        first.list_maps()
    assert open_in_another_process(tmp_path).returncode != 0  # still held by the second store
    second.close()
    assert open_in_another_process(tmp_path).returncode == 0  # free: it opens and cleans up
    assert not Path(in_flight).exists()
    with Store(tmp_path) as third:
        assert third.removed_temp_files == 0 and third.list_maps() == []


# --------------------------------------------------------------------------------------------
# damaged files
# --------------------------------------------------------------------------------------------


def test_damaged_session_and_map_are_skipped_and_reported(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    with Store(tmp_path) as store:
        for name in ("town", "village"):
            grid = small_grid(seed=len(name))
            store.save_tiles(name, grid, grid.tile_ids())
        trajectories = {}
        for vehicle in ("car1", "car2", "car3"):
            poses = random_poses(rng, 6)
            store.save_session(
                session_record(vehicle, "s1", n=6), poses, np.arange(6.0), {"pts": rng.normal(size=(4000, 3))}
            )
            trajectories[vehicle] = poses
        npz = store.session_dir("car2", "s1") / MATCHER_FILENAME
        village = store.map_dir("village")

    # A buggy older version left a truncated archive; a tile listed in the metadata vanished.
    npz.write_bytes(npz.read_bytes()[: npz.stat().st_size // 2])
    next(village.glob("*.pcd")).unlink()
    (tmp_path / "sessions" / "..oops").mkdir()  # not a valid vehicle name

    with Store(tmp_path) as store:
        records = store.list_sessions()
        assert [r.vehicle for r in records] == ["car1", "car3"]
        problems = {(p.kind, p.name) for p in store.problems}
        assert problems == {("session", "car2/s1"), ("entry", "sessions/..oops")}
        assert next(p for p in store.problems if p.kind == "session").path == npz
        with pytest.raises(FormatError, match="commit"):
            store.load_session("car2", "s1")

        contents = store.load_all()
        assert set(contents.maps) == {"town"}
        assert set(contents.sessions) == {("car1", "s1"), ("car3", "s1")}
        for vehicle in ("car1", "car3"):
            np.testing.assert_array_equal(contents.sessions[(vehicle, "s1")].poses, trajectories[vehicle])
        kinds = sorted((p.kind, p.name) for p in contents.problems)
        assert kinds == [("entry", "sessions/..oops"), ("map", "village"), ("session", "car2/s1")]
        assert "incomplete" in next(p.message for p in contents.problems if p.kind == "map")
        assert store.problems == contents.problems


def test_lagging_or_damaged_views_are_rewritten_from_the_commit(store: Store) -> None:
    """A crash after matcher.npz but before trajectory.tum / session.json leaves old views behind."""
    rng = np.random.default_rng(8)
    poses = random_poses(rng, 8)
    directory = store.session_dir("car-01", "2024.06.11_a")
    store.save_session(session_record(n=5), poses[:5], np.arange(5.0), {"k": np.arange(5)})
    old_tum, old_json = (
        (directory / TRAJECTORY_FILENAME).read_bytes(),
        (directory / SESSION_FILENAME).read_bytes(),
    )
    saved = store.save_session(session_record(n=8), poses, np.arange(8.0), {"k": np.arange(8)})
    (directory / TRAJECTORY_FILENAME).write_bytes(old_tum)
    (directory / SESSION_FILENAME).write_bytes(old_json)

    record, got_stamps, got_poses, state = store.load_session("car-01", "2024.06.11_a")
    assert got_stamps.tolist() == list(range(8))
    assert record == saved and record.n_scans == 8 and state["k"].tolist() == list(range(8))
    np.testing.assert_array_equal(got_poses, poses)
    tum_stamps, tum_poses = read_tum(directory / TRAJECTORY_FILENAME)
    assert tum_stamps.tolist() == list(range(8))
    np.testing.assert_allclose(tum_poses, poses, rtol=0, atol=1e-9)
    assert SessionRecord.model_validate_json((directory / SESSION_FILENAME).read_text()) == saved

    (directory / SESSION_FILENAME).write_text("{not json")
    (directory / TRAJECTORY_FILENAME).unlink()
    assert store.load_session("car-01", "2024.06.11_a").record == saved
    assert json.loads((directory / SESSION_FILENAME).read_text())["n_scans"] == 8
    assert read_tum(directory / TRAJECTORY_FILENAME)[0].shape == (8,)


# --------------------------------------------------------------------------------------------
# SIGKILL at random moments
# --------------------------------------------------------------------------------------------

CRASH_MAP = "town"
CRASH_SESSIONS = (("car1", "s1", 1), ("car2", "run.2", 3))  # vehicle, session, scans per iteration
CRASH_CREATED = datetime(2024, 6, 11, 8, 0, tzinfo=UTC)
CRASH_SEED = 11


def crash_grid() -> TileGrid:
    return TileGrid(tile_size_m=20, voxel_size_m=0.5, max_points_per_voxel=2)


def crash_batch(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Iteration ``k``'s points: 1500 around x = 5 k (new tiles keep appearing), seeded by k."""
    rng = np.random.default_rng([CRASH_SEED, k])
    n = 1500
    xyz = np.column_stack(
        [rng.uniform(5.0 * k - 12, 5.0 * k + 12, n), rng.uniform(-12, 12, n), rng.uniform(0, 2, n)]
    )
    return xyz, rng.uniform(0, 255, n)


def crash_session(which: int, k: int) -> tuple[SessionRecord, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Session ``which`` after iteration ``k``: record, poses, stamps and a growing matcher state."""
    vehicle, session, per = CRASH_SESSIONS[which]
    n = per * (k + 1)
    i = np.arange(n, dtype=np.float64)
    poses = np.array(
        [make_transform(rotvec=(0, 0, 0.01 * j), translation=(0.5 * j, np.sin(j), 0.0)) for j in i]
    )
    rng = np.random.default_rng([CRASH_SEED, which, k])
    state = {
        "poses": poses,
        "delta": make_transform(translation=(0.5, 0.0, 0.0)),
        "keyframe_points": rng.normal(size=(2000 * min(k + 1, 40), 3)),
        "keyframe_sizes": np.full(min(k + 1, 40), 2000, dtype=np.int64),
    }
    record = SessionRecord(
        vehicle=vehicle,
        session=session,
        map=CRASH_MAP,
        created=CRASH_CREATED,
        last_seq=k,
        n_scans=n,
        n_fallbacks=k // 4,
        frame="map",
    )
    return record, poses, 1.7e9 + 0.1 * i, state


def crash_worker(data_dir: Path) -> None:
    """Save a growing map and sessions until killed, resuming from what is on disk."""
    store = Store(data_dir)
    grid = store.load_map(CRASH_MAP) or crash_grid()
    done = {(r.vehicle, r.session): r.last_seq for r in store.list_sessions()}
    k0 = min(done.get((v, s), -1) for v, s, _ in CRASH_SESSIONS) + 1
    sys.stdout.write(f"ready {k0}\n")
    sys.stdout.flush()
    parent, deadline = os.getppid(), time.monotonic() + 60.0
    k = k0
    while os.getppid() == parent and time.monotonic() < deadline:  # never outlive the test
        store.save_tiles(CRASH_MAP, grid, grid.insert(*crash_batch(k)))
        for which in range(len(CRASH_SESSIONS)):
            record, poses, stamps, state = crash_session(which, k)
            store.save_session(record, poses, stamps, state)
        sys.stdout.write(f"done {k}\n")
        sys.stdout.flush()
        k += 1


def check_files_open(data_dir: Path) -> int:
    """Open every file of the store with its own reader; return the number of temporary files."""
    n_temp = 0
    for path in sorted(p for p in data_dir.rglob("*") if p.is_file()):
        name = path.name
        if name == LOCK_FILENAME:
            continue
        if name.startswith(".") and name.endswith(".tmp"):
            n_temp += 1
        elif path.suffix == ".pcd":
            assert read_cloud(path).n_points > 0
        elif path.suffix == ".yaml":
            assert isinstance(yaml.safe_load(path.read_text()), dict)
        elif path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as npz:
                assert all(npz[key].size >= 0 for key in npz.files)
        elif path.suffix == ".json":
            assert json.loads(path.read_text())["vehicle"] in ("car1", "car2")
        elif path.suffix == ".tum":
            assert read_tum(path)[0].size >= 1
        elif path.suffix == ".log":  # a pose-log segment (whole) or the log (a torn tail aside)
            data, size = path.read_bytes(), POSE_LOG_RECORD_SIZE
            records = [PoseLogRecord.from_bytes(data[k : k + size]) for k in range(0, len(data), size)]
            whole = records if path.name != POSE_LOG_FILENAME else records[:-1]
            assert records and all(r is not None for r in whole), path
        else:
            pytest.fail(f"unexpected file {path}")
    return n_temp


class Reference:
    """The map after each iteration, built here without the store (tile snapshots per iteration)."""

    def __init__(self) -> None:
        self.grid = crash_grid()
        self.after: list[dict[str, Tile]] = []

    def tiles(self, k: int) -> dict[str, Tile]:
        if k < 0:
            return {}
        while len(self.after) <= k:
            self.grid.insert(*crash_batch(len(self.after)))
            self.after.append({t.id: t for t in self.grid.tiles()})
        return self.after[k]


def matching_iteration(points: np.ndarray, tid: str, ref: Reference, ks: tuple[int, ...]) -> int:
    """Which of the iterations ``ks`` the tile's points equal exactly (fails if none)."""
    for k in ks:
        tile = ref.tiles(k).get(tid)
        if tile is not None and np.array_equal(points.astype(np.float32), tile.points):
            return k
    pytest.fail(f"tile {tid}: {points.shape[0]} points match the reference after none of iterations {ks}")


def test_sigkill_at_random_moments_never_leaves_a_damaged_store(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    rng = np.random.default_rng(2024)
    ref = Reference()
    seen_points: dict[str, int] = {}  # tile file -> points when last checked
    seen_versions: dict[str, int] = {}
    last_k, temp_files, n_kills = -1, 0, 12
    for kill in range(n_kills):
        with (tmp_path / f"worker{kill}.err").open("w") as err:
            proc = subprocess.Popen(
                [sys.executable, "-m", "tests.service.test_store", "--crash-worker", str(data_dir)],
                cwd=REPO_ROOT,
                stdout=subprocess.PIPE,
                stderr=err,
                text=True,
            )
            try:
                ready = proc.stdout.readline() if proc.stdout else ""
                assert ready.startswith("ready"), (tmp_path / f"worker{kill}.err").read_text()
                assert int(ready.split()[1]) == last_k + 1  # resumes after the last committed iteration
                # Every second run is killed only after its first commit (a condition, not a clock:
                # beside two CPU burners a worker committed nothing within 0.5 s in 12 runs), the
                # others from the moment they are ready, inside their first save too.
                early = proc.stdout.readline() if proc.stdout and kill % 2 == 0 else ""
                time.sleep(rng.uniform(0.05, 0.5))
                proc.send_signal(signal.SIGKILL)
                proc.wait(timeout=10)
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
            out = early + (proc.stdout.read() if proc.stdout else "")
            if proc.stdout:
                proc.stdout.close()
        assert proc.returncode == -signal.SIGKILL, (tmp_path / f"worker{kill}.err").read_text()
        reported = [int(line.split()[1]) for line in out.splitlines() if line.startswith("done ")]

        # 1. Every file opens with its own reader (temporary files aside).
        n_temp = check_files_open(data_dir)
        temp_files += n_temp
        map_dir = data_dir / "maps" / CRASH_MAP
        tile_files = {p.stem: p for p in map_dir.glob("*.pcd")} if map_dir.is_dir() else {}
        metadata_path = map_dir / AUTOWARE_METADATA_NAME
        if metadata_path.is_file():
            listed = {k for k in yaml.safe_load(metadata_path.read_text()) if k.endswith(".pcd")}
            assert {f"{tid}.pcd" for tid in tile_files} >= listed  # only tiles whose files exist

        # 2. The store re-opens, removes the temporary files and loads everything.
        with Store(data_dir) as store:
            assert store.removed_temp_files == n_temp and check_files_open(data_dir) == 0
            contents = store.load_all()
            assert contents.problems == []
            k_done = min((s.record.last_seq for s in contents.sessions.values()), default=-1)
            if len(contents.sessions) < len(CRASH_SESSIONS):
                k_done = -1
            assert k_done >= max(reported, default=last_k)  # what the worker reported is durable
            assert k_done >= last_k

            # 3. Each tile file, old or new, is intact: exactly the reference after iteration
            #    k_done or k_done + 1 (the save in flight), and no tile lost points.
            for tid, path in tile_files.items():
                matching_iteration(read_cloud(path).xyz, tid, ref, (k_done, k_done + 1))
            for tid, n_points in seen_points.items():
                assert tid in tile_files and read_cloud(tile_files[tid]).n_points >= n_points
            seen_points = {tid: read_cloud(p).n_points for tid, p in tile_files.items()}
            assert set(tile_files) >= set(ref.tiles(k_done))  # every tile of a committed save
            grid = contents.maps.get(CRASH_MAP)
            if k_done >= 0:
                assert grid is not None
            for tile in grid.tiles() if grid is not None else []:
                k = matching_iteration(tile.points, tile.id, ref, (k_done, k_done + 1))
                assert tile.version >= ref.tiles(k)[tile.id].version  # versions never under-report
                assert tile.version >= seen_versions.get(tile.id, 0)
                seen_versions[tile.id] = tile.version

            # 4. Sessions are exactly what the worker saved at their last_seq, views repaired.
            for (vehicle, session), loaded in contents.sessions.items():
                which = [(v, s) for v, s, _ in CRASH_SESSIONS].index((vehicle, session))
                k = loaded.record.last_seq
                assert k in (k_done, k_done + 1)
                record, poses, stamps, state = crash_session(which, k)
                assert loaded.record.model_dump(exclude={"updated"}) == record.model_dump(exclude={"updated"})
                np.testing.assert_array_equal(loaded.poses, poses)
                np.testing.assert_array_equal(loaded.stamps, stamps)
                assert set(loaded.state) == set(state)
                for key, value in state.items():
                    np.testing.assert_array_equal(loaded.state[key], value)
                directory = store.session_dir(vehicle, session)
                assert SessionRecord.model_validate_json((directory / SESSION_FILENAME).read_text()) == (
                    loaded.record
                )
                tum_stamps, tum_poses = read_tum(directory / TRAJECTORY_FILENAME)
                np.testing.assert_allclose(tum_poses, poses, rtol=0, atol=1e-9)
                np.testing.assert_allclose(tum_stamps, stamps, rtol=0, atol=1e-6)
        last_k = k_done
    # A sanity floor, not a speed test (24-65 iterations on a quiet machine; at least one in every
    # second run by construction).
    assert last_k >= 4, f"the workers committed only {last_k + 1} iterations in {n_kills} runs"
    logging.getLogger(__name__).info(
        "%d kills over %d iterations left %d temporary files behind", n_kills, last_k + 1, temp_files
    )


def _main(argv: list[str]) -> None:
    if len(argv) == 2 and argv[0] == "--crash-worker":
        logging.basicConfig(level=logging.WARNING)
        crash_worker(Path(argv[1]))
    else:
        raise SystemExit("usage: python -m tests.service.test_store --crash-worker DATA_DIR")


if __name__ == "__main__":
    _main(sys.argv[1:])


def test_delete_map_is_atomic_and_an_interrupted_one_is_finished_on_open(tmp_path: Path) -> None:
    with Store(tmp_path) as store:
        grid = small_grid()
        store.save_tiles("keep", grid, grid.tile_ids())
        store.save_tiles("drop", grid, grid.tile_ids())
        assert store.delete_map("drop") is True
        assert store.delete_map("drop") is False  # already gone
        assert store.list_maps() == ["keep"]
        assert sorted(p.name for p in (tmp_path / "maps").iterdir()) == ["keep"]
        with pytest.raises(ValueError):
            store.delete_map("../sessions")
    # A crash between the rename and the removal leaves a .deleted-* directory: never listed as a
    # map, removed when the store opens next.
    trash = tmp_path / "maps" / ".deleted-keep-1-2"
    (tmp_path / "maps" / "keep").rename(trash)
    with Store(tmp_path) as store:
        assert not trash.exists()
        assert store.list_maps() == []


def test_a_finalizer_inside_the_lock_guard_does_not_deadlock(tmp_path: Path) -> None:
    """A Store's finalizer can run from the garbage collector while this thread is inside the
    lock guard (opening another Store): a CI run hung there. The release is queued and done at
    the next entry into the guard: the flock is free afterwards."""
    from randt.service import data_dir_lock

    first = Store(tmp_path / "a")
    key = (tmp_path / "a").resolve()
    with data_dir_lock._guarded():  # as if the GC ran first's finalizer in acquire_lock
        first._finalizer()  # queued, returns at once instead of waiting on the guard
        assert key in data_dir_lock._HELD_LOCKS
    with Store(tmp_path / "b"):  # the next entry into the guard performs the queued release
        assert key not in data_dir_lock._HELD_LOCKS
    assert open_in_another_process(tmp_path / "a").returncode == 0
