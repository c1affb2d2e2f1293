"""service/graph_log.py: the pose graph's durable input (issue 33)."""

from __future__ import annotations

import numpy as np

from randt.service.graph_log import GRAPH_LOG_FILENAME, GraphLog
from tests.pairs import kitti00_velodyne


def _item(k: int, *, gnss: bool = True, join: str | None = None) -> tuple:
    """A keyframe item as ServiceGraph.offer queues it, with a real KITTI sweep's points."""
    xyz = kitti00_velodyne(k)[::10].astype(np.float32)
    T = np.eye(4)
    T[:3, 3] = [float(k), 0.5 * k, 0.0]
    fix = (T[:3, 3].copy(), np.eye(3) * 0.04) if gnss else None
    intensity = np.linspace(0, 1, len(xyz), dtype=np.float32)
    return ("keyframe", "default", "car", "d1", 10 * k, 10 * k, T, xyz, intensity, fix, join)


def _same(a: tuple, b: tuple) -> bool:
    if len(a) != len(b):
        return False
    for x, y in zip(a, b, strict=True):
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if not (isinstance(x, np.ndarray) and isinstance(y, np.ndarray)):
                return False
            if x.dtype != y.dtype or not np.array_equal(x, y):
                return False
        elif isinstance(x, tuple) and isinstance(y, tuple):
            if not _same(x, y):
                return False
        elif x != y:
            return False
    return True


def test_keyframes_come_back_exactly_and_in_order(tmp_path) -> None:
    log = GraphLog(tmp_path / "graph")
    items = [_item(0), _item(1, gnss=False, join="default"), _item(2)]
    for item in items:
        log.append(item)
    again = GraphLog(tmp_path / "graph").read()
    assert len(again) == 3 and all(_same(a, b) for a, b in zip(items, again, strict=True))
    assert again[1][9] is None and again[1][10] == "default" and again[0][7].dtype == np.float32


def test_a_torn_tail_is_cut_and_the_next_keyframe_follows_the_last_good_one(tmp_path) -> None:
    log = GraphLog(tmp_path)
    log.append(_item(0))
    log.append(_item(1))
    path = tmp_path / GRAPH_LOG_FILENAME
    whole = path.stat().st_size
    data = path.read_bytes()
    path.write_bytes(data[: whole - 1000])  # a crash in the middle of the second append
    log = GraphLog(tmp_path)
    assert len(log.read()) == 1 and path.stat().st_size < whole - 1000
    log.append(_item(2))
    got = GraphLog(tmp_path).read()
    assert [g[4] for g in got] == [0, 20]


def test_a_corrupt_record_ends_the_log(tmp_path) -> None:
    log = GraphLog(tmp_path)
    path = tmp_path / GRAPH_LOG_FILENAME
    log.append(_item(0))
    first = path.stat().st_size
    for k in (1, 2):
        log.append(_item(k))
    data = bytearray(path.read_bytes())
    data[first + 100] ^= 0xFF  # a flipped byte inside the second record's body
    path.write_bytes(bytes(data))
    assert [g[4] for g in GraphLog(tmp_path).read()] == [0]


def test_a_deleted_map_leaves_the_log_and_its_revision_stays_as_a_floor(tmp_path) -> None:
    log = GraphLog(tmp_path)
    own = ("keyframe", "car.d1", *_item(3)[2:10], "default")  # a session without priors, joining
    items = [_item(0), own, _item(1), ("keyframe", "other", *_item(2)[2:])]
    for item in items:
        log.append((1.0, item))
    assert log.without_map("default") == 2
    again = GraphLog(tmp_path).read()
    assert [item[1] for _, item in again] == ["car.d1", "other"]
    assert again[0][1][-1] is None  # its offer to the deleted map is gone with it
    assert _same(again[0][1][:-1], own[:-1]) and _same(again[1][1], items[3])
    assert log.without_map("default") == 0
    assert log.floors() == {}
    log.set_floor("default", 7)
    log.set_floor("default", 3)  # the highest stays
    assert GraphLog(tmp_path).floors() == {"default": 7}
