"""Tests for randt.core.io.trajectory: KITTI poses and calibration, TUM trajectories."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from randt.core.errors import FormatError, InvalidCloudError, NotFoundError
from randt.core.io import (
    kitti_velodyne_poses,
    read_kitti_calib,
    read_kitti_poses,
    read_tum,
    write_kitti_poses,
    write_tum,
)
from tests.data import require_data


def random_poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    poses[:, :3, 3] = rng.uniform(-500.0, 500.0, size=(n, 3))
    return poses


# --------------------------------------------------------------------------------------------
# KITTI
# --------------------------------------------------------------------------------------------


def test_read_kitti_poses_values() -> None:
    root = require_data("kitti00/poses.txt")
    poses = read_kitti_poses(root / "kitti00/poses.txt")
    assert poses.shape == (11, 4, 4) and poses.dtype == np.float64
    np.testing.assert_array_equal(poses[:, 3, :], np.tile([0.0, 0.0, 0.0, 1.0], (11, 1)))
    # line 2 of the file: "9.999978e-01 5.272628e-04 -2.066935e-03 -4.690294e-02 ..."
    np.testing.assert_array_equal(poses[1, 0], [9.999978e-01, 5.272628e-04, -2.066935e-03, -4.690294e-02])
    assert poses[1, 2, 3] == 8.586941e-01
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-6)


def test_kitti00_excerpt_matches_full_ground_truth() -> None:
    root = require_data("kitti00/poses.txt", "kitti_gt_poses/00.txt")
    excerpt = read_kitti_poses(root / "kitti00/poses.txt")
    full = read_kitti_poses(root / "kitti_gt_poses/00.txt")
    assert full.shape[0] == 4541  # KITTI sequence 00 has 4541 frames
    np.testing.assert_array_equal(full[: len(excerpt)], excerpt)


def test_read_kitti_calib() -> None:
    root = require_data("kitti00/calib.txt")
    calib = read_kitti_calib(root / "kitti00/calib.txt")
    assert set(calib) == {"P0", "P1", "P2", "P3", "Tr"}
    for key in ("P0", "P1", "P2", "P3"):
        assert calib[key].shape == (3, 4)
    assert calib["P0"][0, 0] == 7.188560e02 and calib["P1"][0, 3] == -3.861448e02
    Tr = calib["Tr"]
    assert Tr.shape == (4, 4)
    np.testing.assert_array_equal(Tr[3], [0.0, 0.0, 0.0, 1.0])
    assert Tr[0, 0] == 4.276802385584e-04 and Tr[0, 1] == -9.999672484946e-01
    # velodyne -> cam0 is (nearly) a rotation: x_cam = -y_velo, y_cam = -z_velo, z_cam = x_velo
    np.testing.assert_allclose(Tr[:3, :3] @ Tr[:3, :3].T, np.eye(3), atol=1e-6)
    np.testing.assert_allclose(Tr[:3, :3], [[0, -1, 0], [0, 0, -1], [1, 0, 0]], atol=0.02)


def test_read_object_detection_style_calib(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    numbers12 = " ".join(str(float(v)) for v in range(12))
    path.write_text(
        f"P2: {numbers12}\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: {numbers12}\n"
        "calib_time: 09-Jan-2012 13:57:47\nT: 1 2 3\n\n"
    )
    calib = read_kitti_calib(path)
    assert set(calib) == {"P2", "R0_rect", "Tr_velo_to_cam", "T"}
    np.testing.assert_array_equal(calib["P2"], np.arange(12.0).reshape(3, 4))
    np.testing.assert_array_equal(calib["R0_rect"], np.eye(3))
    np.testing.assert_array_equal(
        calib["Tr_velo_to_cam"], np.vstack([np.arange(12.0).reshape(3, 4), [0, 0, 0, 1]])
    )
    np.testing.assert_array_equal(calib["T"], [1.0, 2.0, 3.0])


def test_kitti_velodyne_poses_on_kitti00() -> None:
    root = require_data("kitti00/poses.txt", "kitti00/calib.txt")
    cam = read_kitti_poses(root / "kitti00/poses.txt")
    Tr = read_kitti_calib(root / "kitti00/calib.txt")["Tr"]
    velo = kitti_velodyne_poses(cam, Tr)
    assert velo.shape == (11, 4, 4)
    np.testing.assert_allclose(velo, np.linalg.inv(Tr) @ cam @ Tr, rtol=0, atol=1e-12)
    # poses.txt prints P_0 to 7 digits (a 9.999999e-01 on the diagonal), so frame 0 is the
    # identity to the file's precision; with an exact identity P_0 it is identity to 1e-9.
    np.testing.assert_allclose(velo[0], np.eye(4), atol=2e-7)
    exact = cam.copy()
    exact[0] = np.eye(4)
    np.testing.assert_allclose(kitti_velodyne_poses(exact, Tr)[0], np.eye(4), atol=1e-9)
    # The README: the ground truth implies about 8.6 m of travel from frame 0 to frame 10,
    # forward along the velodyne x axis (the car drives forward).
    travel = velo[10, :3, 3] - velo[0, :3, 3]
    assert np.linalg.norm(travel) == pytest.approx(8.6, abs=0.05)
    assert travel[0] > 8.5 and abs(travel[1]) < 0.5 and abs(travel[2]) < 0.5
    # a rigid change of frame keeps the distance travelled
    assert np.linalg.norm(travel) == pytest.approx(np.linalg.norm(cam[10, :3, 3]), abs=0.01)


def test_kitti_velodyne_poses_accepts_3x4_tr() -> None:
    Tr = random_poses(1, seed=1)[0]
    cam = random_poses(4, seed=2)
    np.testing.assert_allclose(kitti_velodyne_poses(cam, Tr[:3]), kitti_velodyne_poses(cam, Tr), atol=1e-12)
    with pytest.raises(InvalidCloudError):
        kitti_velodyne_poses(cam, np.eye(3))
    with pytest.raises(InvalidCloudError):
        kitti_velodyne_poses(cam[0], Tr)


def test_kitti_poses_round_trip(tmp_path: Path) -> None:
    poses = random_poses(25, seed=3)
    path = tmp_path / "poses.txt"
    write_kitti_poses(path, poses)
    lines = path.read_text().splitlines()
    assert len(lines) == 25 and all(len(line.split()) == 12 for line in lines)
    back = read_kitti_poses(path)
    # %.9e keeps 10 significant digits
    np.testing.assert_allclose(back, poses, rtol=1e-9, atol=1e-15)
    assert [p.name for p in tmp_path.iterdir()] == ["poses.txt"]


def test_write_kitti_poses_rejects_bad_input(tmp_path: Path) -> None:
    path = tmp_path / "poses.txt"
    with pytest.raises(InvalidCloudError):
        write_kitti_poses(path, np.eye(4))  # (4, 4) instead of (N, 4, 4)
    not_rigid = random_poses(2, seed=4)
    not_rigid[1, 3, 0] = 0.5
    with pytest.raises(InvalidCloudError, match="bottom row"):
        write_kitti_poses(path, not_rigid)
    assert not path.exists()


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("", "no KITTI pose rows"),
        ("1 0 0 0 0 1 0 0 0 0 1\n", "need 12 numbers, found 11"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n", "cannot parse"),
        ("1 0 0 0 0 1 0 0 0 0 1 nan\n", "non-finite"),
        ("a b c d e f g h i j k l\n", "cannot parse"),
    ],
)
def test_malformed_kitti_poses_raise(tmp_path: Path, content: str, match: str) -> None:
    path = tmp_path / "poses.txt"
    path.write_text(content)
    with pytest.raises(FormatError, match=match) as info:
        read_kitti_poses(path)
    assert str(path) in str(info.value)


def test_malformed_calib_raises(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    path.write_text("just words\n")
    with pytest.raises(FormatError, match=r"calib\.txt"):
        read_kitti_calib(path)
    with pytest.raises(NotFoundError):
        read_kitti_calib(tmp_path / "absent.txt")


# --------------------------------------------------------------------------------------------
# TUM
# --------------------------------------------------------------------------------------------


def test_tum_round_trip(tmp_path: Path) -> None:
    poses = random_poses(50, seed=5)
    stamps = 1_700_000_000.0 + np.cumsum(np.full(50, 0.1))
    path = tmp_path / "traj.tum"
    write_tum(path, stamps, poses)
    back_stamps, back_poses = read_tum(path)
    np.testing.assert_allclose(back_stamps, stamps, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back_poses, poses, rtol=0, atol=1e-9)
    assert path.read_text().startswith("# timestamp tx ty tz qx qy qz qw\n")


def test_tum_quaternion_convention(tmp_path: Path) -> None:
    # 90 degrees about z: q = (x, y, z, w) = (0, 0, sin 45, cos 45), scalar last.
    pose = np.eye(4)
    pose[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = [1.0, 2.0, 3.0]
    path = tmp_path / "traj.txt"
    write_tum(path, np.array([0.5]), pose[None])
    values = np.array(path.read_text().splitlines()[1].split(), dtype=np.float64)
    np.testing.assert_allclose(values, [0.5, 1.0, 2.0, 3.0, 0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-15)


def test_read_tum_skips_comments_and_normalises(tmp_path: Path) -> None:
    path = tmp_path / "traj.txt"
    path.write_text(
        "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n"
        "1305031102.175304 1.2334 -0.0113 1.6941 0.7907 0.4393 -0.1770 -0.3879\n"
        "\n1305031102.211214 1.2321 -0.0106 1.6938 0.7906 0.4393 -0.1772 -0.3880\n"
    )
    stamps, poses = read_tum(path)
    np.testing.assert_array_equal(stamps, [1305031102.175304, 1305031102.211214])
    np.testing.assert_array_equal(poses[0, :3, 3], [1.2334, -0.0113, 1.6941])
    q = np.array([0.7907, 0.4393, -0.1770, -0.3879])
    np.testing.assert_allclose(
        poses[0, :3, :3], Rotation.from_quat(q / np.linalg.norm(q)).as_matrix(), atol=1e-12
    )
    np.testing.assert_allclose(
        poses[:, :3, :3] @ poses[:, :3, :3].transpose(0, 2, 1),
        np.tile(np.eye(3), (2, 1, 1)),
        atol=1e-12,
    )


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("# only a comment\n", "no TUM trajectory rows"),
        ("0 1 2 3 0 0 0 1 9\n", "need 8 numbers, found 9"),
        ("0 1 2 3 0 0 0\n", "need 8 numbers, found 7"),
        ("0 1 2 3 0 0 0 0\n", "not unit length"),
        ("0 1 2 3 1 1 0 0\n", "not unit length"),
    ],
)
def test_malformed_tum_raises(tmp_path: Path, content: str, match: str) -> None:
    path = tmp_path / "traj.txt"
    path.write_text(content)
    with pytest.raises(FormatError, match=match) as info:
        read_tum(path)
    assert str(path) in str(info.value)


def test_write_tum_rejects_mismatched_stamps(tmp_path: Path) -> None:
    with pytest.raises(InvalidCloudError, match="stamps"):
        write_tum(tmp_path / "t.txt", np.zeros(3), random_poses(2, seed=6))
    with pytest.raises(InvalidCloudError, match="non-finite"):
        write_tum(tmp_path / "t.txt", np.array([np.nan]), random_poses(1, seed=6))
    assert not (tmp_path / "t.txt").exists()


def test_read_missing_trajectory_raises_not_found(tmp_path: Path) -> None:
    with pytest.raises(NotFoundError):
        read_tum(tmp_path / "absent.txt")
    with pytest.raises(NotFoundError):
        read_kitti_poses(tmp_path / "absent.txt")
