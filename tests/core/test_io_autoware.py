"""Autoware's divided-map files (core.io.autoware) on their own, without a TileGrid."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from core.errors import FormatError, NotFoundError
from core.io import PointCloud, read_cloud
from core.io.autoware import (
    AUTOWARE_METADATA_NAME,
    GRID_SIDECAR_NAME,
    read_metadata,
    read_sidecar,
    remove_stale_tile_files,
    write_metadata,
    write_sidecar,
    write_tile_file,
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
