"""What goes on the link: encode_sweep's reduction and compact scans, checked point by point, and a
real KITTI sweep against the 12 Mbit/s budget (docs/clients.md)."""

from __future__ import annotations

import numpy as np
import pytest

from randt.clients.publisher import PublisherSettings, encode_sweep, first_per_voxel
from randt.core.datasets import open_sequence
from randt.core.errors import BadMessageError
from randt.wire.messages import decode_scan
from tests.data import require_data

#: 12 Mbit/s at 10 Hz: bytes per sweep at most.
BUDGET_BYTES = 12e6 / 8 / 10


def sweep(n: int = 20_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A spinning-LiDAR-like sweep: rings of points in azimuth order (native order), walls and a
    floor, a few far points; per-point time offsets from the azimuth and intensities in [0, 1]."""
    rng = np.random.default_rng(seed)
    az = np.linspace(-np.pi, np.pi, n // 16, endpoint=False)
    ring = np.repeat(np.arange(16), len(az))
    a = np.tile(az, 16)
    r = 5.0 + 20.0 * np.abs(np.sin(3 * a)) + rng.normal(0.0, 0.02, a.size)
    elev = np.radians(-3.0 + 0.2 * ring)
    xyz = np.c_[r * np.cos(a) * np.cos(elev), r * np.sin(a) * np.cos(elev), r * np.sin(elev)]
    order = np.lexsort((ring, a))  # column by column, as a spinning sensor fires
    xyz = xyz[order]
    xyz[::1000] = rng.uniform(-300.0, 300.0, size=(len(xyz[::1000]), 3))
    t = 0.1 * (a[order] + np.pi) / (2 * np.pi)
    return xyz, t, rng.uniform(0.0, 1.0, len(xyz))


def test_first_per_voxel_is_the_first_point_of_each_occupied_voxel() -> None:
    xyz, _, _ = sweep()
    keep = first_per_voxel(xyz, 0.2)
    cells = np.floor(xyz.astype(np.float32) / np.float32(0.2)).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)  # the reference: first occurrences
    np.testing.assert_array_equal(keep, np.sort(first))
    assert np.all(np.diff(keep) > 0)  # the sweep's own order
    far = xyz.copy()
    far[3] = [4.0e5, -4.0e5, 1.0]  # 2e6 voxels from the rest: the unpacked fallback
    keep = first_per_voxel(far, 0.2)
    _, first = np.unique(np.floor(far / 0.2), axis=0, return_index=True)
    np.testing.assert_array_equal(keep, np.sort(first))


def test_reduced_sweep_round_trip_point_by_point() -> None:
    xyz, t, intensity = sweep()
    settings = PublisherSettings(voxel_m=0.2, xyz_quantum_m=0.01, time_quantum_s=1e-5)
    payload = encode_sweep(
        "car-1", "s", 3, 10**18, xyz, intensity=intensity, time_offset_s=t, settings=settings
    )
    got = decode_scan(payload)
    keep = first_per_voxel(xyz, 0.2)
    assert got.n_points == len(keep) < len(xyz) / 2
    assert (got.vehicle, got.session, got.seq, got.stamp_ns, got.fields) == ("car-1", "s", 3, 10**18, "xyzi")
    enc = got.encoding
    assert enc is not None and (enc.voxel_m, enc.xyz_quantum_m, enc.time_quantum_s) == (0.2, 0.01, 1e-5)
    # the kept points are input points, in input order, each with its own offset and intensity
    err = np.abs(got.xyz() - xyz[keep])
    assert err.max() <= 0.005 + 3e-5, err.max()  # half a step + float32 rounding at 300 m
    assert np.abs(got.time_offset_s() - t[keep]).max() <= 0.5e-5 + 1e-7
    assert np.abs(got.intensity() - intensity[keep]).max() <= 0.5 * enc.intensity_quantum + 1e-6
    # one point per voxel, and every occupied voxel has its point
    cells = np.floor(xyz.astype(np.float32) / np.float32(0.2)).astype(np.int64)
    assert len(np.unique(cells[keep], axis=0)) == len(keep) == len(np.unique(cells, axis=0))
    # wrong attributes would show: shifting the offsets by one kept point breaks the bound
    assert np.abs(got.time_offset_s()[1:] - t[keep][:-1]).max() > 1e-4


def test_no_reduction_and_raw_mode() -> None:
    xyz, t, intensity = sweep(4000)
    got = decode_scan(
        encode_sweep("car", "s", 0, 0, xyz, time_offset_s=t, settings=PublisherSettings(voxel_m=0))
    )
    assert got.n_points == len(xyz) and got.encoding is not None and got.encoding.voxel_m == 0.0
    assert np.abs(got.xyz() - xyz).max() <= 0.005 + 3e-5
    raw = decode_scan(
        encode_sweep(
            "car", "s", 0, 0, np.c_[xyz, intensity], time_offset_s=t, settings=PublisherSettings(raw=True)
        )
    )
    assert raw.encoding is None and raw.fields == "xyzi"
    np.testing.assert_array_equal(raw.points_f32(), np.c_[xyz, intensity].astype(np.float32))
    np.testing.assert_array_equal(raw.time_offset_s(), t.astype(np.float32))


def test_the_environment_chooses_raw(monkeypatch: pytest.MonkeyPatch) -> None:
    xyz, _, _ = sweep(4000)
    monkeypatch.setenv("RANDT_VEHICLE_RAW", "1")
    assert decode_scan(encode_sweep("car", "s", 0, 0, xyz)).encoding is None
    monkeypatch.setenv("RANDT_VEHICLE_RAW", "0")
    monkeypatch.setenv("RANDT_VEHICLE_VOXEL_M", "0.5")
    enc = decode_scan(encode_sweep("car", "s", 0, 0, xyz)).encoding
    assert enc is not None and enc.voxel_m == 0.5


@pytest.mark.parametrize(
    ("change", "code", "words"),
    [
        ("nan", "nonfinite_points", "first at index 7"),
        ("offset", "invalid_points", "first at index 9"),
        ("short", "invalid_points", "intensity: expected shape"),
        ("empty", "empty_scan", "no points"),
    ],
)
def test_bad_sweeps_fail_on_every_point_before_the_reduction(change: str, code: str, words: str) -> None:
    xyz, t, intensity = sweep(4000)
    xyz[6] = xyz[7]  # point 7 shares point 6's voxel: the reduction would drop it
    if change == "nan":
        xyz[7, 2] = np.nan
    elif change == "offset":
        xyz[9] = xyz[8]
        t[9] = 1.5
    elif change == "short":
        intensity = intensity[:-1]
    else:
        xyz, t, intensity = xyz[:0], t[:0], intensity[:0]
    with pytest.raises(BadMessageError) as info:
        encode_sweep("car", "s", 0, 0, xyz, intensity=intensity, time_offset_s=t)
    assert info.value.code == code and words in str(info.value), str(info.value)


def test_a_real_kitti_sweep_fits_the_link_budget() -> None:
    """KITTI 00 frame 0 (124 668 points) with time offsets from the azimuth, library defaults."""
    root = require_data("kitti00/velodyne")
    scan = next(iter(open_sequence(root / "kitti00")))
    xyz = scan.xyz
    t = 0.1 * 0.5 * (-np.arctan2(xyz[:, 1], xyz[:, 0]) / np.pi + 1.0)
    payload = encode_sweep("car", "s", 0, 0, xyz, time_offset_s=t, settings=PublisherSettings())
    raw = encode_sweep("car", "s", 0, 0, xyz, time_offset_s=t, settings=PublisherSettings(raw=True))
    got = decode_scan(payload)
    assert len(xyz) == 124_668 and 28_000 < got.n_points < 36_000  # about 31.8k occupied 0.2 m voxels
    assert len(payload) < BUDGET_BYTES, f"{len(payload)} bytes: {len(payload) * 80 / 1e6:.1f} Mbit/s at 10 Hz"
    assert len(payload) / got.n_points < 3.5  # measured 3.09 B per point (xyz 2.4, time 0.65)
    assert len(raw) > 15 * len(payload)  # 1.99 MB raw (xyz + offsets as float32)
    assert np.abs(got.xyz() - xyz[first_per_voxel(xyz, 0.2)]).max() <= 0.005 + 1e-5
