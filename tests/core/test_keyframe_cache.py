"""Keyframe points on disk, the recent ones in memory: the same arrays back, the same graph."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from randt.core.fleet_map import FleetMapper
from randt.core.keyframe_cache import KeyframeCache
from randt.core.transforms import make_transform
from randt.sim.drive import SimScan


def test_the_cache_keeps_capacity_keyframes_in_memory_and_every_one_on_disk(tmp_path) -> None:
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "stale.npy").write_bytes(b"left by the last process")
    cache = KeyframeCache(tmp_path / "c", capacity=2)
    assert list((tmp_path / "c").iterdir()) == [], "a cache opened on a directory clears it"
    rng = np.random.default_rng(0)
    arrays = {k: (rng.normal(size=(100 + k, 3)).astype(np.float32), rng.random(100 + k)) for k in range(5)}
    for k, (a, b) in arrays.items():
        cache.put(("s", k), a, b)
    assert cache.in_memory == 2 and len(cache) == 5 and ("s", 4) in cache and ("t", 0) not in cache
    for k in (3, 0, 0):
        got = cache.get(("s", k))
        np.testing.assert_array_equal(got[0], arrays[k][0])
        np.testing.assert_array_equal(got[1], arrays[k][1])
        assert got[0].dtype == np.float32
    assert cache.loads == 1, "key 3 was in memory, key 0 read once and kept"
    cache.drop(("s", 0))
    with pytest.raises(KeyError):
        cache.get(("s", 0))
    assert len(list((tmp_path / "c").iterdir())) == 2 * 4
    cache.clear()
    assert not (tmp_path / "c").exists() and len(cache) == 0


@functools.cache
def _sweeps() -> tuple[SimScan, ...]:
    from randt.sim.drive import Route, simulate
    from randt.sim.town import Town

    town = Town.generate(1)
    return tuple(simulate(town, Route.loop(town, 3, length_m=1000.0), n_scans=26, speed_mps=12.0, seed=1))


def _mapper(cache: KeyframeCache | None) -> FleetMapper:
    """Session ``a`` placed, keyframes at sweeps 0, 10, 20 of a simulated drive; session ``b``,
    not placed, at sweeps 5, 15, 25 in a frame of its own: placement votes register its keyframes
    against ``a``'s (the points of both, read from the cache)."""
    sweeps = _sweeps()
    mapper = FleetMapper(points=cache)
    mapper.place("a", np.eye(4))
    elsewhere = make_transform(euler_deg=(0, 0, 40), translation=(300.0, -20.0, 0.0))
    for k in (0, 10, 20):
        mapper.add_keyframe("a", sweeps[k].T_world_sensor, sweeps[k].points_xyz)
    for k in (5, 15, 25):
        mapper.add_keyframe("b", elsewhere @ sweeps[k].T_world_sensor, sweeps[k].points_xyz)
    return mapper


def test_a_fleet_mapper_with_its_points_on_disk_builds_the_same_graph(tmp_path) -> None:
    in_memory = _mapper(None)
    cache = KeyframeCache(tmp_path / "points", capacity=1)
    on_disk = _mapper(cache)
    assert in_memory.placed_sessions() == on_disk.placed_sessions() == ["a", "b"]
    assert [(r.a, r.b, r.accepted, r.n_inliers) for r in on_disk.loops] == [
        (r.a, r.b, r.accepted, r.n_inliers) for r in in_memory.loops
    ]
    for key, T in in_memory.poses().items():
        np.testing.assert_allclose(on_disk.poses()[key], T, atol=1e-9)
    assert cache.in_memory == 1 and cache.loads > 0, "the verifications read keyframes back from disk"
    assert len(list((tmp_path / "points").iterdir())) == 6
    # the sessions keep poses and fixes only: no points, no query descriptors
    assert all(kf.descriptors is None for s in on_disk.sessions.values() for kf in s.keyframes)
