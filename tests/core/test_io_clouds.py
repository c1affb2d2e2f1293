"""Tests for randt.core.io.clouds and randt.core.io.atomic: real files of every kind, round trips, errors."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pypcd4
import pytest

from randt.core.errors import FormatError, InvalidCloudError, NotFoundError
from randt.core.io import (
    SUPPORTED_READ_SUFFIXES,
    PointCloud,
    atomic_open,
    atomic_write_bytes,
    read_cloud,
    write_cloud,
    write_pcd,
    write_ply,
)
from tests.data import require_data


@pytest.fixture(scope="module")
def o3d():
    """Open3D, imported lazily; tests that cross-check with it skip when it is missing."""
    return pytest.importorskip("open3d")


@pytest.fixture
def cloud() -> PointCloud:
    rng = np.random.default_rng(7)
    n = 500
    normals = rng.normal(size=(n, 3))
    return PointCloud(
        xyz=rng.uniform(-50.0, 50.0, size=(n, 3)),
        intensity=rng.uniform(0.0, 255.0, size=n).astype(np.float32),
        normals=normals / np.linalg.norm(normals, axis=1, keepdims=True),
        time_offset_s=np.linspace(0.0, 0.1, n),
    )


# --------------------------------------------------------------------------------------------
# PointCloud
# --------------------------------------------------------------------------------------------


def test_point_cloud_converts_dtypes_and_counts() -> None:
    c = PointCloud(xyz=np.arange(12, dtype=np.float32).reshape(4, 3), intensity=[1, 2, 3, 4])
    assert c.n_points == 4
    assert c.xyz.dtype == np.float64 and c.xyz.shape == (4, 3)
    assert c.intensity is not None and c.intensity.dtype == np.float32
    np.testing.assert_array_equal(c.intensity, [1.0, 2.0, 3.0, 4.0])
    assert c.normals is None and c.time_offset_s is None


@pytest.mark.parametrize(
    "kwargs",
    [
        {"xyz": np.zeros((5, 2))},
        {"xyz": np.zeros(3)},
        {"xyz": np.zeros((5, 3)), "intensity": np.zeros(4)},
        {"xyz": np.zeros((5, 3)), "normals": np.zeros((5, 2))},
        {"xyz": np.zeros((5, 3)), "time_offset_s": np.zeros((5, 1))},
    ],
)
def test_point_cloud_rejects_wrong_shapes(kwargs: dict) -> None:
    with pytest.raises(InvalidCloudError):
        PointCloud(**kwargs)


def test_select_subsets_every_field(cloud: PointCloud) -> None:
    mask = cloud.xyz[:, 0] > 0.0
    sub = cloud.select(mask)
    assert sub.n_points == int(mask.sum())
    np.testing.assert_array_equal(sub.xyz, cloud.xyz[mask])
    np.testing.assert_array_equal(sub.intensity, cloud.intensity[mask])
    np.testing.assert_array_equal(sub.normals, cloud.normals[mask])
    np.testing.assert_array_equal(sub.time_offset_s, cloud.time_offset_s[mask])

    picked = cloud.select([4, 1, 4])
    np.testing.assert_array_equal(picked.xyz, cloud.xyz[[4, 1, 4]])
    np.testing.assert_array_equal(picked.time_offset_s, cloud.time_offset_s[[4, 1, 4]])
    assert cloud.select(3).n_points == 1
    np.testing.assert_array_equal(cloud.select(3).xyz[0], cloud.xyz[3])
    assert cloud.select(slice(10, 20)).n_points == 10
    assert cloud.select([]).n_points == 0
    with pytest.raises(InvalidCloudError, match="integers"):
        cloud.select([0.5, 1.5])


def test_select_keeps_absent_fields_absent() -> None:
    c = PointCloud(xyz=np.eye(3))
    sub = c.select(np.array([True, False, True]))
    assert sub.n_points == 2 and sub.intensity is None and sub.normals is None


def test_select_rejects_mask_of_wrong_length(cloud: PointCloud) -> None:
    with pytest.raises(InvalidCloudError, match="mask"):
        cloud.select(np.ones(cloud.n_points - 1, dtype=bool))


def test_supported_read_suffixes() -> None:
    assert set(SUPPORTED_READ_SUFFIXES) == {
        ".bin",
        ".pcd",
        ".ply",
        ".csv",
        ".txt",
        ".xyz",
        ".npy",
        ".off",
    }


# --------------------------------------------------------------------------------------------
# real data: .bin
# --------------------------------------------------------------------------------------------


def test_read_kitti_bin_counts_and_values() -> None:
    root = require_data("kitti00/velodyne/000001.bin")
    path = root / "kitti00/velodyne/000001.bin"
    cloud = read_cloud(path)
    raw = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    assert cloud.n_points == path.stat().st_size // 16 == 124_605
    np.testing.assert_array_equal(cloud.xyz, raw[:, :3].astype(np.float64))
    assert cloud.intensity is not None and cloud.intensity.dtype == np.float32
    np.testing.assert_array_equal(cloud.intensity, raw[:, 3])
    assert cloud.intensity.max() > 0.0


def test_read_kitti_frame0_has_zero_intensity() -> None:
    # The data README: frame 0's surviving copy has no intensity (stored as zeros).
    root = require_data("kitti00/velodyne/000000.bin")
    cloud = read_cloud(root / "kitti00/velodyne/000000.bin")
    assert cloud.n_points == 1_994_688 // 16
    assert cloud.intensity is not None and not cloud.intensity.any()


def test_read_xyz_only_bin_by_size() -> None:
    root = require_data("kitti07_keyframes/000000.bin", "newer_college/raw_00.bin")
    # 258744 bytes: a multiple of 12, not of 16 -> x,y,z.
    key = read_cloud(root / "kitti07_keyframes/000000.bin")
    assert key.n_points == 258_744 // 12 and key.intensity is None
    raw = read_cloud(root / "newer_college/raw_00.bin")
    # the per-point times file has one float32 per point of the scan
    n_times = (root / "newer_college/times_00.bin").stat().st_size // 4
    assert raw.n_points == n_times == 25_109
    np.testing.assert_array_equal(
        raw.xyz[:2], np.fromfile(root / "newer_college/raw_00.bin", "<f4", count=6).reshape(2, 3)
    )


def test_read_argoverse_bin_matches_its_per_point_files() -> None:
    root = require_data("pairs/argoverse2/315966265259836000.bin")
    d = root / "pairs/argoverse2"
    cloud = read_cloud(d / "315966265259836000.bin")
    n_offsets = (d / "315966265259836000_offset_ns.bin").stat().st_size // 8  # int64
    n_lasers = (d / "315966265259836000_laser_number.bin").stat().st_size  # uint8
    assert cloud.n_points == n_offsets == n_lasers == 99_229
    np.testing.assert_array_equal(cloud.intensity[:5], [10.0, 47.0, 8.0, 60.0, 22.0])


def test_bin_fields_hint_resolves_ambiguous_size() -> None:
    # 238464 bytes divide by 16 and by 12: the size rule says x,y,z,i, the file is x,y,z.
    root = require_data("kitti07_keyframes/000004.bin")
    path = root / "kitti07_keyframes/000004.bin"
    assert path.stat().st_size == 238_464
    assert read_cloud(path).n_points == 238_464 // 16
    xyz_only = read_cloud(path, bin_fields=3)
    assert xyz_only.n_points == 238_464 // 12 and xyz_only.intensity is None
    np.testing.assert_array_equal(xyz_only.xyz, np.fromfile(path, "<f4").reshape(-1, 3).astype(np.float64))


def test_bin_hint_and_suffix_are_case_insensitive(tmp_path: Path) -> None:
    data = np.arange(24, dtype="<f4")  # 96 bytes: 6 xyzi or 8 xyz points
    path = tmp_path / "scan.BIN"
    data.tofile(path)
    assert read_cloud(path).n_points == 6
    assert read_cloud(path, bin_fields=3).n_points == 8
    with pytest.raises(ValueError, match="bin_fields"):
        read_cloud(path, bin_fields=5)


def test_bin_with_bad_size_raises(tmp_path: Path) -> None:
    path = tmp_path / "bad.bin"
    path.write_bytes(b"\x00" * 20)
    with pytest.raises(FormatError, match=r"bad\.bin"):
        read_cloud(path)
    path.write_bytes(b"\x00" * 36)  # 3 xyz points but not 4-field records
    with pytest.raises(FormatError, match="multiple of 16"):
        read_cloud(path, bin_fields=4)


# --------------------------------------------------------------------------------------------
# real data: text, PLY, npy
# --------------------------------------------------------------------------------------------


def test_read_car_csv_with_header_and_normals() -> None:
    root = require_data("pairs/libpointmatcher_car/car_cloud400.csv")
    cloud = read_cloud(root / "pairs/libpointmatcher_car/car_cloud400.csv")
    assert cloud.n_points == 24_989  # 24990 lines minus the "x,y,z,nx,ny,nz" header
    np.testing.assert_array_equal(cloud.xyz[0], [-3.5376, 0.639553, -1.37678])
    assert cloud.normals is not None and cloud.intensity is None
    np.testing.assert_array_equal(cloud.normals[0], [-0.060181, 0.173729, 0.982953])
    np.testing.assert_allclose(np.linalg.norm(cloud.normals, axis=1), 1.0, atol=1e-4)


def test_read_car_whitespace_text_without_header() -> None:
    root = require_data("pairs/libpointmatcher_car/car_cloud401.csv")
    cloud = read_cloud(root / "pairs/libpointmatcher_car/car_cloud401.csv")
    assert cloud.n_points == 25_193
    np.testing.assert_array_equal(cloud.xyz[0], [2.6247663, 0.052711742, -1.0169336])
    assert cloud.intensity is None and cloud.normals is None


def test_randt_csv_equals_its_bin_source() -> None:
    # S2 CSVs are conversions of the S1 KITTI scans: same points, same order.
    root = require_data("randt_velodyne/csv/001038.csv", "randt_velodyne/velodyne/001038.bin")
    from_csv = read_cloud(root / "randt_velodyne/csv/001038.csv")
    from_bin = read_cloud(root / "randt_velodyne/velodyne/001038.bin")
    assert from_csv.n_points == from_bin.n_points == 113_369
    np.testing.assert_array_equal(from_csv.xyz.astype(np.float32), from_bin.xyz)
    np.testing.assert_array_equal(from_csv.intensity, from_bin.intensity)


def test_read_small_gicp_binary_ply_scalar_intensity() -> None:
    root = require_data("pairs/small_gicp/source.ply")
    path = root / "pairs/small_gicp/source.ply"
    cloud = read_cloud(path)
    # Independent reference: the raw little-endian float32 records after the header.
    content = path.read_bytes()
    body = content.index(b"end_header\n") + len(b"end_header\n")
    raw = np.frombuffer(content[body:], dtype="<f4").reshape(-1, 4)
    assert cloud.n_points == 69_792 == len(raw)
    np.testing.assert_array_equal(cloud.xyz, raw[:, :3].astype(np.float64))
    np.testing.assert_array_equal(cloud.intensity, raw[:, 3])


def test_read_bunny_ascii_ply() -> None:
    root = require_data("objects/bunny/bun000.ply")
    cloud = read_cloud(root / "objects/bunny/bun000.ply")
    assert cloud.n_points == 40_256
    np.testing.assert_array_equal(
        cloud.xyz[:2],
        np.array([[-0.06325, 0.0359793, 0.0420873], [-0.06275, 0.0360343, 0.0425949]], "f4"),
    )
    np.testing.assert_array_equal(
        cloud.xyz[-1], read_cloud_last_vertex(root / "objects/bunny/bun000.ply", 40_256)
    )
    assert cloud.intensity is None
    # metres: the bunny is about 15 cm across
    assert 0.1 < np.ptp(cloud.xyz[:, 0]) < 0.2


def read_cloud_last_vertex(path: Path, n_vertices: int) -> np.ndarray:
    """The last vertex line of an ASCII PLY, parsed by hand, rounded to float32."""
    lines = path.read_text().splitlines()
    body = lines.index("end_header") + 1
    return np.array(lines[body + n_vertices - 1].split(), dtype=np.float32).astype(np.float64)


def test_ascii_ply_mesh_vertices_before_faces(tmp_path: Path) -> None:
    # The vertex rows are read; the face rows after them (lists, empty lists) are skipped.
    rng = np.random.default_rng(3)
    vertex = rng.normal(size=(50, 4)).astype(np.float32)  # x, y, z, intensity
    rows = [" ".join(str(v) for v in row) for row in vertex]
    path = tmp_path / "mesh.ply"
    path.write_text(
        "ply\nformat ascii 1.0\ncomment hand-written\nelement vertex 50\n"
        + "".join(f"property float {name}\n" for name in ("x", "y", "z", "intensity"))
        + "element face 3\nproperty list uchar int vertex_indices\nend_header\n"
        + "\n".join([*rows, "3 0 1 2", "4 2 3 4 5", "0"])
        + "\n"
    )
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.xyz, vertex[:, :3])
    np.testing.assert_array_equal(cloud.intensity, vertex[:, 3])


def test_read_3dmatch_npy() -> None:
    root = require_data("pairs/3dmatch/src.npy")
    reference = np.load(root / "pairs/3dmatch/src.npy")
    cloud = read_cloud(root / "pairs/3dmatch/src.npy")
    assert cloud.n_points == 15_953
    np.testing.assert_array_equal(cloud.xyz, reference)
    assert cloud.intensity is None


def test_read_npy_with_intensity_column(tmp_path: Path) -> None:
    table = np.arange(20, dtype=np.float64).reshape(5, 4)
    np.save(tmp_path / "a.npy", table)
    cloud = read_cloud(tmp_path / "a.npy")
    np.testing.assert_array_equal(cloud.xyz, table[:, :3])
    np.testing.assert_array_equal(cloud.intensity, table[:, 3].astype(np.float32))


def test_read_off_is_surface_sampled() -> None:
    root = require_data("objects/modelnet40/chair_0002.off")
    path = root / "objects/modelnet40/chair_0002.off"
    cloud = read_cloud(path, n_mesh_samples=1234, seed=5)
    assert cloud.n_points == 1234 and cloud.intensity is None
    np.testing.assert_array_equal(cloud.xyz, read_cloud(path, n_mesh_samples=1234, seed=5).xyz)
    assert not np.array_equal(cloud.xyz, read_cloud(path, n_mesh_samples=1234, seed=6).xyz)


# --------------------------------------------------------------------------------------------
# delimited text variants
# --------------------------------------------------------------------------------------------


def test_text_header_names_are_matched_case_insensitively(tmp_path: Path) -> None:
    path = tmp_path / "cols.csv"
    path.write_text("Intensity,Z,Y,X\n5,3,2,1\n6,30,20,10\n")
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.xyz, [[1, 2, 3], [10, 20, 30]])
    np.testing.assert_array_equal(cloud.intensity, [5, 6])


def test_text_without_header_fourth_column_is_intensity(tmp_path: Path) -> None:
    path = tmp_path / "pts.xyz"
    path.write_text("# comment\n\n1 2 3 9\n4 5 6 8\n")
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.xyz, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(cloud.intensity, [9, 8])


def test_text_keeps_non_finite_points(tmp_path: Path) -> None:
    path = tmp_path / "nan.txt"
    path.write_text("x y z\n1 2 3\nnan 0 0\n4 5 inf\n")
    cloud = read_cloud(path)
    assert cloud.n_points == 3
    assert np.isnan(cloud.xyz[1, 0]) and np.isinf(cloud.xyz[2, 2])


def test_cloudcompare_style_header(tmp_path: Path) -> None:
    path = tmp_path / "cc.txt"
    path.write_text("//X,Y,Z,Intensity\n1,2,3,4\n")
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.xyz, [[1, 2, 3]])
    np.testing.assert_array_equal(cloud.intensity, [4])


# --------------------------------------------------------------------------------------------
# PCD read (files written by pypcd4 and by Open3D)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "encoding",
    [pypcd4.Encoding.ASCII, pypcd4.Encoding.BINARY, pypcd4.Encoding.BINARY_COMPRESSED],
    ids=lambda e: e.value,
)
def test_read_pcd_encodings_written_by_pypcd4(tmp_path: Path, encoding: pypcd4.Encoding) -> None:
    # A regular grid: LZF compresses it (pypcd4 silently falls back to "binary" on noise).
    grid = np.stack(np.meshgrid(np.arange(10), np.arange(10), np.arange(5)), -1).reshape(-1, 3)
    xyz = (grid * 0.25 - 1.0).astype(np.float32)
    intensity = (grid[:, 0] % 7).astype(np.float32)
    normals = np.tile(np.array([0.0, 0.6, 0.8], np.float32), (len(grid), 1))
    pcd = pypcd4.PointCloud.from_points(
        [*xyz.T, intensity, *normals.T],
        ("x", "y", "z", "intensity", "normal_x", "normal_y", "normal_z"),
        (np.float32,) * 7,
    )
    path = tmp_path / f"{encoding.value}.pcd"
    pcd.save(path, encoding=encoding)
    assert f"DATA {encoding.value}\n".encode() in path.read_bytes()[:400]
    back = read_cloud(path)
    assert back.n_points == 500
    np.testing.assert_array_equal(back.xyz, xyz)
    np.testing.assert_array_equal(back.intensity, intensity)
    np.testing.assert_array_equal(back.normals, normals)


@pytest.mark.parametrize(("write_ascii", "compressed"), [(True, False), (False, False), (False, True)])
def test_read_pcd_written_by_open3d(
    tmp_path: Path, cloud: PointCloud, o3d, write_ascii: bool, compressed: bool
) -> None:
    pcd = o3d.t.geometry.PointCloud()
    pcd.point.positions = o3d.core.Tensor(cloud.xyz.astype(np.float32))
    pcd.point.intensity = o3d.core.Tensor(cloud.intensity.reshape(-1, 1))
    path = tmp_path / "o3d.pcd"
    assert o3d.t.io.write_point_cloud(str(path), pcd, write_ascii=write_ascii, compressed=compressed)
    back = read_cloud(path)
    np.testing.assert_allclose(back.xyz, cloud.xyz.astype(np.float32), rtol=1e-6)
    np.testing.assert_allclose(back.intensity, cloud.intensity, rtol=1e-6)


# --------------------------------------------------------------------------------------------
# writers
# --------------------------------------------------------------------------------------------


def test_write_pcd_round_trip_and_header(tmp_path: Path, cloud: PointCloud) -> None:
    path = tmp_path / "out.pcd"
    write_pcd(path, cloud)
    content = path.read_bytes()
    header_end = content.index(b"DATA binary\n") + len(b"DATA binary\n")
    header = content[:header_end].decode().splitlines()
    assert "VERSION 0.7" in header
    assert "FIELDS x y z intensity" in header
    assert "SIZE 4 4 4 4" in header and "TYPE F F F F" in header
    assert f"WIDTH {cloud.n_points}" in header and "HEIGHT 1" in header
    assert f"POINTS {cloud.n_points}" in header
    assert any(line.startswith("VIEWPOINT 0") for line in header)
    assert len(content) - header_end == 16 * cloud.n_points

    back = read_cloud(path)
    np.testing.assert_array_equal(back.xyz, cloud.xyz.astype(np.float32))
    np.testing.assert_array_equal(back.intensity, cloud.intensity)


def test_write_ply_round_trip(tmp_path: Path, cloud: PointCloud) -> None:
    path = tmp_path / "out.ply"
    write_ply(path, cloud)
    content = path.read_bytes()
    assert content.startswith(b"ply\nformat binary_little_endian 1.0\n")
    body = content.index(b"end_header\n") + len(b"end_header\n")
    assert len(content) - body == 16 * cloud.n_points
    back = read_cloud(path)
    np.testing.assert_array_equal(back.xyz, cloud.xyz.astype(np.float32))
    np.testing.assert_array_equal(back.intensity, cloud.intensity)


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
def test_written_files_read_by_open3d(tmp_path: Path, cloud: PointCloud, o3d, suffix: str) -> None:
    path = tmp_path / f"out{suffix}"
    write_cloud(path, cloud)
    legacy = o3d.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(np.asarray(legacy.points), cloud.xyz.astype(np.float32))
    tensor = o3d.t.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(tensor.point.intensity.numpy().ravel(), cloud.intensity)


def test_write_without_intensity_writes_zeros(tmp_path: Path) -> None:
    cloud = PointCloud(xyz=np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]))
    for name in ("a.pcd", "a.PLY"):
        write_cloud(tmp_path / name, cloud)
        back = read_cloud(tmp_path / name)
        np.testing.assert_array_equal(back.xyz, cloud.xyz)
        np.testing.assert_array_equal(back.intensity, [0.0, 0.0])


def test_write_cloud_rejects_unknown_suffix_and_empty_cloud(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match=r"out\.xyz"):
        write_cloud(tmp_path / "out.xyz", PointCloud(xyz=np.zeros((1, 3))))
    with pytest.raises(InvalidCloudError, match="empty"):
        write_pcd(tmp_path / "empty.pcd", PointCloud(xyz=np.zeros((0, 3))))
    assert not (tmp_path / "empty.pcd").exists()


def test_write_replaces_existing_file(tmp_path: Path, cloud: PointCloud) -> None:
    path = tmp_path / "map.pcd"
    write_pcd(path, cloud)
    write_pcd(path, cloud.select(slice(0, 10)))
    assert read_cloud(path).n_points == 10
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.pcd"]


# --------------------------------------------------------------------------------------------
# atomic writes
# --------------------------------------------------------------------------------------------


def test_atomic_write_bytes_and_text(tmp_path: Path) -> None:
    path = tmp_path / "a.bin"
    atomic_write_bytes(path, b"hello")
    assert path.read_bytes() == b"hello"
    with atomic_open(tmp_path / "a.txt", "w") as fh:
        fh.write("one\ntwo\n")
    assert (tmp_path / "a.txt").read_bytes() == b"one\ntwo\n"
    # a new file gets the umask permissions, not mkstemp's 0o600
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


def test_atomic_open_keeps_original_when_writer_raises(tmp_path: Path) -> None:
    path = tmp_path / "map.bin"
    path.write_bytes(b"original")
    with pytest.raises(RuntimeError, match="boom"), atomic_open(path) as fh:
        fh.write(b"partial new content")
        raise RuntimeError("boom")
    assert path.read_bytes() == b"original"
    assert [p.name for p in tmp_path.iterdir()] == ["map.bin"]  # no temp file left behind


def test_write_pcd_keeps_original_when_serialisation_fails(
    tmp_path: Path, cloud: PointCloud, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "map.pcd"
    write_pcd(path, cloud)
    before = path.read_bytes()

    def failing_header(self, data=None) -> str:  # inside the open temporary file
        raise OSError("disk full")

    monkeypatch.setattr(pypcd4.MetaData, "compose_header", failing_header)
    with pytest.raises(OSError, match="disk full"):
        write_pcd(path, cloud.select(slice(0, 3)))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["map.pcd"]


def test_atomic_open_into_missing_directory_raises_format_error(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="nowhere"):
        atomic_write_bytes(tmp_path / "nowhere" / "a.bin", b"x")


def test_atomic_open_rejects_read_modes(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="mode"), atomic_open(tmp_path / "a", "r"):
        pass


# --------------------------------------------------------------------------------------------
# malformed input
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "content", "match"),
    [
        ("empty.bin", b"", "empty"),
        ("empty.pcd", b"", "empty"),
        ("empty.csv", b"", "empty"),
        ("garbage.pcd", b"this is not a pcd\n" * 3, "PCD"),
        (
            "nofields.pcd",
            b"VERSION 0.7\nFIELDS a b c\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
            b"WIDTH 1\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1\nDATA ascii\n1 2 3\n",
            "x, y, z",
        ),
        ("nodata.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n", "no DATA line"),
        (
            "truncated.pcd",
            b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\n"
            b"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA binary\n" + b"\x00" * 12,
            "announces 2 points",
        ),
        ("garbage.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n", "PLY"),
        (
            "noxyz.ply",
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nend_header\n1\n",
            "x, y, z",
        ),
        (
            "short.ply",
            b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
            b"property float y\nproperty float z\nend_header\n1 2 3\n",
            "PLY",
        ),
        ("header_only.csv", b"x,y,z\n", "no points"),
        ("bad_header.csv", b"a,b,c\n1,2,3\n", "no x, y, z"),
        ("two_cols.txt", b"1 2\n3 4\n", "at least x, y, z"),
        ("ragged.txt", b"1 2 3\n4 5\n", "malformed"),
        ("mismatch.csv", b"x,y,z,intensity\n1,2,3\n", "header has 4 names"),
        ("not_numbers.xyz", b"1 2 3\nfoo bar baz\n", "malformed"),
        ("cube.off", b"OFF\n8 6 0\n0 0 0\n", "data lines"),
        ("unknown.las", b"LASF", "unsupported suffix"),
    ],
)
def test_malformed_files_raise_format_error_naming_the_path(
    tmp_path: Path, name: str, content: bytes, match: str
) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(FormatError, match=match) as info:
        read_cloud(path)
    assert str(path) in str(info.value)


def test_npy_of_wrong_shape_raises(tmp_path: Path) -> None:
    for name, array in (("flat.npy", np.zeros(6)), ("two.npy", np.zeros((4, 2)))):
        np.save(tmp_path / name, array)
        with pytest.raises(FormatError, match=re.escape(name)):
            read_cloud(tmp_path / name)
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(FormatError, match=r"obj\.npy"):
        read_cloud(tmp_path / "obj.npy")


def test_missing_file_raises_not_found(tmp_path: Path) -> None:
    with pytest.raises(NotFoundError, match=r"nothing\.pcd"):
        read_cloud(tmp_path / "nothing.pcd")


# --------------------------------------------------------------------------------------------
# the shared-data helper (core/shared_data.py, tests/data.py)
# --------------------------------------------------------------------------------------------


def test_require_data_skips_locally_and_fails_in_ci(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RANDT_SHARED_DATA", str(tmp_path))
    (tmp_path / "present.txt").write_text("x")
    assert require_data("present.txt") == tmp_path.resolve()

    monkeypatch.delenv("CI", raising=False)
    with pytest.raises(pytest.skip.Exception, match="RANDT_SHARED_DATA") as skipped:
        require_data("present.txt", "kitti00/poses.txt")
    assert str(tmp_path / "kitti00/poses.txt") in str(skipped.value)

    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match=r"kitti00/poses\.txt"):
        require_data("kitti00/poses.txt")
