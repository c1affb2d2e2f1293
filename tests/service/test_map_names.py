"""Sessions without priors get a map each, under an injective name, and stored maps migrate.

Issue 13, defect 3: vehicle ``col.a`` session ``b`` and vehicle ``col`` session ``a.b`` both folded
into map ``col.a.b`` (two unrelated frames fused). Names now come from
:func:`randt.wire.ids.session_map_name`; a store written with the old names is migrated when it opens.
"""

from __future__ import annotations

import numpy as np

from randt.core.scenes import synthetic_room
from randt.core.tiles import TileGrid
from randt.service.runtime import Service
from randt.service.settings import ServiceSettings
from randt.service.store import SessionRecord, Store
from randt.wire.messages import PoseMessage, encode, scan_from_arrays
from tests.service.api_server import wait_answers


def test_col_a_b_and_col_a_dot_b_keep_separate_maps(tmp_path) -> None:
    room = synthetic_room(np.random.default_rng(3), 3000).astype(np.float32)
    high = room + np.float32([0.0, 0.0, 50.0])  # the second vehicle's scene: 50 m higher
    service = Service(ServiceSettings(data_dir=tmp_path, flush_interval_s=0.2), with_zenoh=False)
    service.start()
    try:
        mgr = service.sessions
        assert mgr is not None
        for seq in range(2):  # no priors: each session in its own frame and its own map
            mgr.submit("col.a", encode(scan_from_arrays("col.a", "b", seq, seq * 100_000_000, room)))
            mgr.submit("col", encode(scan_from_arrays("col", "a.b", seq, seq * 100_000_000, high)))
        answers = wait_answers(service, 4)
        assert all(isinstance(m, PoseMessage) for m in answers), answers
        maps = {(m.vehicle, m.session): m.map for m in answers if isinstance(m, PoseMessage)}
        assert maps == {("col.a", "b"): "col_-a.b", ("col", "a.b"): "col.a.b"}
        mgr.flush()  # the sessions' points are folded into their maps (fold_scans) before a save
        low_z = np.concatenate(
            [mgr.maps["col_-a.b"].get(t).points[:, 2] for t in mgr.maps["col_-a.b"].tile_ids()]
        )
        high_z = np.concatenate(
            [mgr.maps["col.a.b"].get(t).points[:, 2] for t in mgr.maps["col.a.b"].tile_ids()]
        )
        # each map holds its own scene only (the rooms are a few metres tall)
        assert low_z.max() < 25.0 and high_z.min() > 25.0
    finally:
        service.stop()


def _legacy_store(data) -> dict[str, TileGrid]:
    """A store as the service wrote it before the injective names: two sessions fused in col.a.b,
    one session (van_1/d1) alone in van_1.d1."""
    rng = np.random.default_rng(0)
    grids = {}
    with Store(data) as store:
        for name, offset in (("col.a.b", 0.0), ("van_1.d1", 100.0)):
            grid = TileGrid(tile_size_m=20, voxel_size_m=0.2)
            grid.insert(rng.uniform(0, 30, (4000, 3)) + offset, None)
            store.save_tiles(name, grid, grid.tile_ids())
            grids[name] = grid
        poses = np.repeat(np.eye(4)[None], 2, axis=0)
        for vehicle, session, map_name in (
            ("col.a", "b", "col.a.b"),
            ("col", "a.b", "col.a.b"),
            ("van_1", "d1", "van_1.d1"),
        ):
            record = SessionRecord(
                vehicle=vehicle, session=session, map=map_name, frame="session", last_seq=1, n_scans=2
            )
            store.save_session(record, poses, np.array([0.0, 0.1]), {})
    return grids


def _points(grid: TileGrid) -> np.ndarray:
    return np.concatenate([grid.get(t).points for t in sorted(grid.tile_ids())])


def test_a_store_with_legacy_names_migrates_on_open(tmp_path) -> None:
    data = tmp_path / "data"
    grids = _legacy_store(data)
    with Store(data) as store:
        contents = store.load_all()
        assert contents.problems == []
        records = {r.key: r.map for r in store.list_sessions()}
        assert records == {
            ("col.a", "b"): "col_-a.b",
            ("col", "a.b"): "col.a.b",
            ("van_1", "d1"): "van__1.d1",
        }
        assert sorted(contents.maps) == ["col.a.b", "col_-a.b", "van__1.d1"]
        # the fused map stays fused (nothing can split it), each session keeps a copy; the lone one moved
        for name, legacy in (("col.a.b", "col.a.b"), ("col_-a.b", "col.a.b"), ("van__1.d1", "van_1.d1")):
            np.testing.assert_array_equal(_points(contents.maps[name]), _points(grids[legacy]))
        assert not (data / "maps/van_1.d1").exists()
        assert store.migrate_map_names() == []  # done once


def test_an_interrupted_migration_finishes_on_the_next_open(tmp_path) -> None:
    data = tmp_path / "data"
    grids = _legacy_store(data)
    # interrupted after step 1 for van_1/d1 (directory renamed, record not yet saved) and in the
    # middle of copying col.a.b (a scratch copy left behind)
    (data / "maps/van_1.d1").rename(data / "maps/van__1.d1")
    scratch = data / "maps/.deleted-copy-col_-a.b-1-2"
    scratch.mkdir()
    (scratch / "0_0.pcd").write_bytes(b"half a tile")
    with Store(data) as store:
        contents = store.load_all()
        assert contents.problems == []
        assert {r.key: r.map for r in store.list_sessions()}[("van_1", "d1")] == "van__1.d1"
        np.testing.assert_array_equal(_points(contents.maps["van__1.d1"]), _points(grids["van_1.d1"]))
        np.testing.assert_array_equal(_points(contents.maps["col_-a.b"]), _points(grids["col.a.b"]))
    assert not scratch.exists()
