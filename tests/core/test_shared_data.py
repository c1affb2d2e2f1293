"""randt.core.shared_data: where the real data set is, without pytest in the way."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from randt.core import shared_data
from randt.core.errors import NotFoundError
from tests import pairs
from tests.data import require_data


def test_data_root_follows_the_environment_variable(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(shared_data.DATA_DIR_ENV_VAR, str(tmp_path))
    assert shared_data.data_root() == tmp_path.resolve()
    monkeypatch.delenv(shared_data.DATA_DIR_ENV_VAR)
    # resolved as data_root resolves it: a clone whose ../shared is a symbolic link gets its target
    repo = Path(shared_data.__file__).resolve().parents[1]
    assert shared_data.data_root() == (repo.parent / "shared" / "data").resolve()


def test_data_root_resolves_a_symlinked_shared_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``../shared`` (or the environment variable) as a symbolic link: the root is its target, and
    require() finds the files through it."""
    target = tmp_path / "elsewhere" / "shared"
    (target / "data" / "kitti00").mkdir(parents=True)
    (target / "data" / "kitti00" / "poses.txt").write_text("x")
    (tmp_path / "repo").mkdir()
    (tmp_path / "shared").symlink_to(target, target_is_directory=True)
    expected = (target / "data").resolve()
    assert (tmp_path / "shared").is_symlink() and expected != tmp_path / "shared" / "data"

    monkeypatch.delenv(shared_data.DATA_DIR_ENV_VAR, raising=False)
    monkeypatch.setattr(shared_data, "_REPO_ROOT", tmp_path / "repo")
    assert shared_data.data_root() == expected
    assert shared_data.require("kitti00/poses.txt") == expected

    monkeypatch.setenv(shared_data.DATA_DIR_ENV_VAR, str(tmp_path / "shared" / "data"))
    assert shared_data.data_root() == expected
    assert shared_data.require("kitti00/poses.txt") == expected


def test_require_raises_not_found_naming_the_first_missing_path(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(shared_data.DATA_DIR_ENV_VAR, str(tmp_path))
    (tmp_path / "present.txt").write_text("x")
    assert shared_data.require("present.txt") == tmp_path.resolve()
    with pytest.raises(NotFoundError, match=r"kitti00/poses\.txt does not exist .*RANDT_SHARED_DATA"):
        shared_data.require("present.txt", "kitti00/poses.txt")
    with pytest.raises(NotFoundError, match="pairs/small_gicp"):
        shared_data.small_gicp()


def test_kitti_pair_loader_reads_the_scan() -> None:
    require_data("kitti00/velodyne/000000.bin")
    xyz = shared_data.kitti00_velodyne(0)
    assert xyz.ndim == 2 and xyz.shape[1] == 3 and xyz.shape[0] > 100_000  # an HDL-64E sweep
    assert np.isfinite(xyz).all()
    assert list(shared_data.PAIRS) == ["small_gicp", "argoverse2", "bunny", "car"]


def test_the_revisit_pairs_load_with_poses_that_are_rigid_and_agree_with_the_sweeps() -> None:
    loops = pairs.kitti00_loop_pairs()
    assert len(loops) == 21
    first = loops[0]
    assert (first.i, first.j) == (120, 1576)
    for loop in loops:
        for T in (loop.T_icp, loop.T_gt):
            assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4)
        # the ICP pose and KITTI's own disagree by at most the README's 1.1 m at these revisits
        assert np.linalg.norm(loop.T_icp[:3, 3] - loop.T_gt[:3, 3]) < 1.2
    assert pairs.kitti00_loops_velodyne(first.j).shape[1] == 3


def test_3dmatch_and_bun315_pairs_are_large_rotations() -> None:
    for loader in (pairs.threedmatch, lambda: pairs.bunny("bun315")):
        _, _, T = loader()
        angle = np.degrees(np.arccos((np.trace(T[:3, :3]) - 1) / 2))
        assert angle > 15


def test_the_revisit_sweeps_lidar_poses_give_the_listed_relative_poses() -> None:
    poses = pairs.kitti00_loops_poses()
    assert sorted(poses) == [120, 129, 172, 198, 199, 202, 404, 492, 493, 496, 508, 512, 528, 539, 558,
                             1576, 1615, 1634, 3421, 3426, 3493, 3495, 3534, 4235, 4236, 4237]  # fmt: skip
    for loop in pairs.kitti00_loop_pairs():
        T = np.linalg.inv(poses[loop.i]) @ poses[loop.j]  # p_i = T p_j
        assert np.allclose(T, loop.T_gt, atol=1e-6)
        assert abs(np.linalg.norm(T[:3, 3]) - loop.gt_distance_m) < 0.04
    # inv(Tr) @ P_cam @ Tr: the world is the LiDAR at frame 0, z up; the car drives on level roads
    assert all(T[2, 2] > 0.99 for T in poses.values())
    step = np.linalg.inv(poses[120]) @ poses[129]  # 9 frames on, forward along the LiDAR's x
    assert 3.0 < step[0, 3] < 5.0 and abs(step[1, 3]) < 1.0
