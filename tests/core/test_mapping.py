"""Map building on simulated drives with exact ground truth, and the map's density uniformity."""

from __future__ import annotations

import numpy as np
import pytest

from randt.core.datasets import open_sequence
from randt.core.mapping import MapBuilder
from randt.core.metrics.cloud import pdu
from randt.core.metrics.trajectory import kitti_relative_errors, rpe
from randt.core.transforms import invert, transform_points
from randt.sim.drive import Motion, Route, simulate
from randt.sim.town import Town
from tests.data import require_data


def _drive(n_scans: int, speed_mps: float, *, raw: bool):
    town = Town.generate(1)
    route = Route.loop(town, 3, length_m=1000.0)
    motion = Motion(route, speed_mps=speed_mps)
    builder = MapBuilder()
    gt = []
    sweeps = simulate(town, route, n_scans=n_scans, speed_mps=speed_mps, seed=1, deskewed=not raw, workers=1)
    for scan in sweeps:  # ray cast in another process, beside the mapping
        update = builder.add_scan(
            scan.points_xyz.astype(np.float64),
            intensity=scan.intensity,
            time_offset_s=scan.time_offset_s if raw else None,
        )
        assert update.scan.status != "fallback", update.scan.message
        # with per-point times, poses refer to mid-sweep (core/odometry.py)
        gt.append(motion.sensor_poses_at(scan.index * 0.1 + (0.05 if raw else 0.0))[0])
    G = np.array([invert(gt[0]) @ g for g in gt])
    return builder, G, np.array(builder.poses)


@pytest.fixture(scope="module")
def drive_120m():
    return _drive(100, 12.0, raw=False)


def test_simulated_drive_kitti_errors(drive_120m) -> None:
    """120 m, exact ground truth: the benchmark's 1 km targets are 1 % and 0.5 deg/100 m; here
    (100 m segments only) the looser 0.5 % and 0.25 deg/100 m still hold with a wide margin."""
    _, G, P = drive_120m
    k = kitti_relative_errors(G, P, lengths=(100,))
    assert k.translation_pct < 0.5
    assert k.rotation_deg_per_100m < 0.25
    r = rpe(G, P)
    assert r.translation_m.rmse < 0.02 and r.rotation_deg.rmse < 0.05


def test_simulated_map_tiles_are_bounded_and_equalized(drive_120m) -> None:
    builder, _, _ = drive_120m
    tiles = builder.tiles
    assert len(tiles) >= 10
    cloud = tiles.to_cloud()
    keys = np.floor(cloud.xyz / 0.2).astype(np.int64)
    _, counts = np.unique(keys, axis=0, return_counts=True)
    assert counts.max() == 1, "the map keeps at most one point per 0.2 m voxel"
    assert builder.matcher.model_size < 400_000


def test_raw_sweeps_are_deskewed() -> None:
    """Sweeps taken while moving at 12 m/s (1.2 m of motion per sweep) stay on track when deskewed."""
    _, G, P = _drive(40, 12.0, raw=True)
    err = np.linalg.norm(P[:, :3, 3] - G[:, :3, 3], axis=1)
    assert err.max() < 0.10, f"max position error {err.max():.3f} m over 47 m"


def test_kitti00_map_is_more_uniform_than_raw_scans() -> None:
    root = require_data("kitti00/velodyne/000010.bin")
    seq = open_sequence(root / "kitti00")
    builder = MapBuilder()
    raw = []
    for cloud in seq:
        u = builder.add_scan(cloud.xyz, intensity=cloud.intensity)
        raw.append(transform_points(u.scan.T_world_sensor, cloud.xyz))
    map_pdu = pdu(builder.tiles.to_cloud().xyz.astype(np.float64), 0.5)
    raw_pdu = pdu(np.vstack(raw), 0.5)
    assert map_pdu > raw_pdu + 1.5, (map_pdu, raw_pdu)  # measured 0.26 vs -1.87
    per_tile = builder.tiles.tile_pdu(0.5)
    assert len(per_tile) == len(builder.tiles) and all(np.isfinite(v) for v in per_tile.values())
