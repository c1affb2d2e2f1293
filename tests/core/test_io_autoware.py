"""Autoware's divided-map files (randt.core.io.autoware) on their own, without a TileGrid."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from randt.core.errors import FormatError, InvalidCloudError, NotFoundError
from randt.core.io import PointCloud, read_cloud
from randt.core.io.autoware import (
    AUTOWARE_METADATA_NAME,
    GRID_SIDECAR_NAME,
    read_metadata,
    read_sidecar,
    remove_stale_tile_files,
    write_metadata,
    write_sidecar,
    write_tile_file,
    write_tile_table,
)


def test_metadata_round_trip_is_the_loader_format(tmp_path: Path) -> None:
    entries = write_metadata(tmp_path, 20, {"-1_0": (-20, 0), "0_2": (0, 40)})
    assert entries == {"-1_0.pcd": [-20, 0], "0_2.pcd": [0, 40]}
    assert yaml.safe_load((tmp_path / AUTOWARE_METADATA_NAME).read_text()) == {
        "x_resolution": 20.0,
        "y_resolution": 20.0,
        "-1_0.pcd": [-20, 0],
        "0_2.pcd": [0, 40],
    }
    assert read_metadata(tmp_path) == (20, {"-1_0.pcd": (-1, 0), "0_2.pcd": (0, 2)})


def test_metadata_errors_name_the_problem(tmp_path: Path) -> None:
    with pytest.raises(NotFoundError):
        read_metadata(tmp_path)
    (tmp_path / AUTOWARE_METADATA_NAME).write_text("x_resolution: 20\ny_resolution: 20\na.pcd: [5, 0]\n")
    with pytest.raises(FormatError, match="not a multiple of the 20 m tile size"):
        read_metadata(tmp_path)


def test_sidecar_round_trip_and_mismatched_tile_size(tmp_path: Path) -> None:
    assert read_sidecar(tmp_path, 20) == ({}, {})
    write_sidecar(tmp_path, tile_size_m=20, voxel_size_m=0.2, max_points_per_voxel=1, versions={"0_0": 3})
    saved, versions = read_sidecar(tmp_path, 20)
    assert versions == {"0_0": 3}
    assert saved["voxel_size_m"] == 0.2 and saved["max_points_per_voxel"] == 1
    assert list(saved) == ["format", "tile_size_m", "voxel_size_m", "max_points_per_voxel", "versions"]
    with pytest.raises(FormatError, match="disagrees"):
        read_sidecar(tmp_path, 40)
    assert (tmp_path / GRID_SIDECAR_NAME).is_file()


def test_a_tile_written_from_its_table_is_the_same_file(tmp_path: Path) -> None:
    xyzi = np.random.default_rng(4).uniform(-50.0, 50.0, size=(333, 4)).astype("<f4")
    cloud = PointCloud(xyz=xyzi[:, :3].astype(np.float64), intensity=xyzi[:, 3])
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    from_cloud = write_tile_file(tmp_path / "a", "1_2", cloud)
    from_table = write_tile_table(tmp_path / "b", "1_2", xyzi)
    assert from_table.read_bytes() == from_cloud.read_bytes()
    back = read_cloud(from_table)
    np.testing.assert_array_equal(back.xyz, xyzi[:, :3].astype(np.float64))
    with pytest.raises(InvalidCloudError):
        write_tile_table(tmp_path, "0_0", xyzi[:0])
    with pytest.raises(InvalidCloudError):
        write_tile_table(tmp_path, "0_0", xyzi.astype(np.float64))


def test_metadata_and_sidecar_text_is_pyyamls_at_a_fraction_of_its_cost(tmp_path: Path) -> None:
    """The metadata is written as PyYAML writes it (Autoware reads that text), and the sidecar
    loads back equal (its versions in block style), for ids PyYAML quotes (``'0_0'`` reads as an
    integer in YAML 1.1) and ids it does not (``-1_2``)."""
    import yaml

    rng = np.random.default_rng(5)
    ids = [f"{a}_{b}" for a, b in rng.integers(-300, 300, (400, 2))] + ["0_0", "-1_2", "12_-7"]
    corners = {
        tid: (int(x), int(y))
        for tid, (x, y) in zip(ids, rng.integers(-6000, 6000, (len(ids), 2)), strict=True)
    }
    write_metadata(tmp_path, 20, corners)
    document = {"x_resolution": 20.0, "y_resolution": 20.0}
    document |= {f"{tid}.pcd": [x, y] for tid, (x, y) in corners.items()}
    expected = yaml.dump(document, Dumper=yaml.SafeDumper, sort_keys=False, default_flow_style=None)
    assert (tmp_path / AUTOWARE_METADATA_NAME).read_text() == expected
    versions = {tid: int(v) for tid, v in zip(ids, rng.integers(1, 10**6, len(ids)), strict=True)}
    write_sidecar(tmp_path, tile_size_m=20, voxel_size_m=0.2, max_points_per_voxel=1, versions=versions)
    saved, back = read_sidecar(tmp_path, 20)
    assert back == versions and saved["voxel_size_m"] == 0.2


def test_tile_files_and_stale_removal(tmp_path: Path) -> None:
    cloud = PointCloud(xyz=np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]), intensity=np.array([7.0, 8.0]))
    path = write_tile_file(tmp_path, "0_0", cloud)
    assert path == tmp_path / "0_0.pcd"
    back = read_cloud(path)
    np.testing.assert_array_equal(back.xyz, cloud.xyz)
    np.testing.assert_array_equal(back.intensity, cloud.intensity)
    write_tile_file(tmp_path, "5_5", cloud)
    (tmp_path / "other.pcd").write_bytes(path.read_bytes())
    remove_stale_tile_files(tmp_path, {"0_0.pcd": [0, 0]})
    assert sorted(p.name for p in tmp_path.glob("*.pcd")) == ["0_0.pcd", "other.pcd"]
