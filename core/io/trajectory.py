"""Trajectory files: KITTI poses and calibration, TUM trajectories.

Poses are (N, 4, 4) float64 homogeneous transforms ``T_world_sensor`` (they map points from the
sensor frame at stamp ``k`` into the world frame of the file).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from randt.core.errors import FormatError, InvalidCloudError, NotFoundError
from randt.core.io.atomic import atomic_open

__all__ = [
    "kitti_velodyne_poses",
    "read_kitti_calib",
    "read_kitti_poses",
    "read_tum",
    "write_kitti_poses",
    "write_tum",
]

logger = logging.getLogger(__name__)

# A rigid pose's bottom row must be this to be written as a 3x4 (KITTI) or a quaternion (TUM).
_BOTTOM_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_BOTTOM_ROW_TOL = 1e-9
# TUM quaternions are normalised on reading; a norm this far from 1 means a broken file
# (wrong column order, a missing column), not rounding.
_QUAT_NORM_TOL = 1e-2


def _load_table(path: Path, n_columns: int, what: str) -> np.ndarray:
    """Load a whitespace-separated numeric table with exactly ``n_columns`` columns.

    Blank lines and ``#`` comment lines are skipped.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise NotFoundError(f"{path}: no such file") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: cannot read {what}: {exc}") from exc
    rows = [s for s in text.splitlines() if s.strip() and not s.lstrip().startswith("#")]
    if not rows:
        raise FormatError(f"{path}: no {what} rows")
    try:
        table = np.loadtxt(rows, dtype=np.float64, comments=None, ndmin=2)
    except ValueError as exc:
        raise FormatError(f"{path}: cannot parse as {what}: {exc}") from exc
    if table.shape[1] != n_columns:
        raise FormatError(f"{path}: {what} rows need {n_columns} numbers, found {table.shape[1]}")
    if not np.isfinite(table).all():
        raise FormatError(f"{path}: non-finite number in {what}")
    return table


def _check_poses(poses: np.ndarray, path: Path) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or poses.shape[0] == 0:
        raise InvalidCloudError(f"poses for {path} must be (N, 4, 4) with N > 0, got {poses.shape}")
    if not np.isfinite(poses).all():
        raise InvalidCloudError(f"poses for {path} contain non-finite values")
    if np.abs(poses[:, 3, :] - _BOTTOM_ROW).max() > _BOTTOM_ROW_TOL:
        raise InvalidCloudError(f"poses for {path} are not homogeneous: bottom row != [0 0 0 1]")
    return poses


def _homogeneous(rows_3x4: np.ndarray) -> np.ndarray:
    """(N, 3, 4) -> (N, 4, 4) with bottom row [0 0 0 1]."""
    poses = np.zeros((rows_3x4.shape[0], 4, 4))
    poses[:, :3, :] = rows_3x4
    poses[:, 3, 3] = 1.0
    return poses


def read_kitti_poses(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a KITTI odometry pose file (12 numbers a line, a row-major 3x4 matrix).

    Parameters
    ----------
    path:
        e.g. ``poses/00.txt``; KITTI ground truth is ``T_cam0(0)_cam0(k)``.

    Returns
    -------
    np.ndarray
        (N, 4, 4) float64 poses.

    Raises
    ------
    NotFoundError
        ``path`` does not exist.
    FormatError
        Empty file, a line without exactly 12 numbers, or a non-finite value.
    """
    path = Path(path)
    table = _load_table(path, 12, "KITTI pose")
    return _homogeneous(table.reshape(-1, 3, 4))


def write_kitti_poses(path: str | os.PathLike[str], poses: np.ndarray) -> None:
    """Write poses in the KITTI format (row-major 3x4, ``%.9e``), atomically.

    Parameters
    ----------
    path:
        Target file (replaced if it exists).
    poses:
        (N, 4, 4) homogeneous poses.

    Raises
    ------
    InvalidCloudError
        Wrong shape, non-finite values, or a bottom row other than ``[0 0 0 1]``.
    FormatError
        The file could not be written.
    """
    path = Path(path)
    poses = _check_poses(poses, path)
    with atomic_open(path, "w") as fh:
        np.savetxt(fh, poses[:, :3, :].reshape(-1, 12), fmt="%.9e", delimiter=" ")


def read_kitti_calib(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Read a KITTI calibration file of ``KEY: numbers`` lines.

    Parameters
    ----------
    path:
        e.g. odometry ``sequences/00/calib.txt`` (``P0..P3``, ``Tr``) or an object-detection
        ``calib/*.txt`` (``R0_rect``, ``Tr_velo_to_cam``, ``Tr_imu_to_velo``).

    Returns
    -------
    dict[str, np.ndarray]
        12 numbers become a (3, 4) matrix, except keys starting with ``Tr`` (rigid transforms)
        which become (4, 4) homogeneous; 9 numbers become (3, 3); any other count stays a 1-D
        array. Lines whose values are not numbers (``calib_time: ...``) are skipped.

    Raises
    ------
    NotFoundError
        ``path`` does not exist.
    FormatError
        The file cannot be read or holds no ``KEY: numbers`` line.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise NotFoundError(f"{path}: no such file") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: cannot read calibration: {exc}") from exc
    calib: dict[str, np.ndarray] = {}
    for line in text.splitlines():  # a handful of lines
        key, sep, values = line.partition(":")
        key = key.strip()
        if not sep or not key or key.startswith("#"):
            continue
        try:
            numbers = np.array(values.split(), dtype=np.float64)
        except ValueError:
            logger.debug("%s: skipping non-numeric calibration entry %r", path, key)
            continue
        if numbers.size == 0:
            continue
        if numbers.size == 12 and key.startswith("Tr"):
            calib[key] = _homogeneous(numbers.reshape(1, 3, 4))[0]
        elif numbers.size == 12:
            calib[key] = numbers.reshape(3, 4)
        elif numbers.size == 9:
            calib[key] = numbers.reshape(3, 3)
        else:
            calib[key] = numbers
    if not calib:
        raise FormatError(f"{path}: no 'KEY: numbers' calibration lines")
    return calib


def kitti_velodyne_poses(cam_poses: np.ndarray, Tr: np.ndarray) -> np.ndarray:
    """Convert KITTI camera-0 poses to Velodyne poses: ``T_velo_k = inv(Tr) @ P_k @ Tr``.

    Parameters
    ----------
    cam_poses:
        (N, 4, 4) ground-truth poses ``P_k = T_cam0(0)_cam0(k)``.
    Tr:
        (4, 4) or (3, 4) ``Tr`` from ``calib.txt``: ``T_cam0_velo`` (velodyne -> cam0).

    Returns
    -------
    np.ndarray
        (N, 4, 4) ``T_velo(0)_velo(k)``; frame 0 is the identity when ``P_0`` is.

    Raises
    ------
    InvalidCloudError
        Wrong shapes or a singular ``Tr``.

    Notes
    -----
    ``Tr`` is inverted with :func:`numpy.linalg.inv`, not as a rigid transform: KITTI's ``Tr``
    is orthonormal only to about 1e-7, and the exact inverse keeps ``inv(Tr) @ I @ Tr == I``.
    """
    cam_poses = np.asarray(cam_poses, dtype=np.float64)
    Tr = np.asarray(Tr, dtype=np.float64)
    if cam_poses.ndim != 3 or cam_poses.shape[1:] != (4, 4):
        raise InvalidCloudError(f"cam_poses must be (N, 4, 4), got {cam_poses.shape}")
    if Tr.shape == (3, 4):
        Tr = _homogeneous(Tr[None])[0]
    if Tr.shape != (4, 4):
        raise InvalidCloudError(f"Tr must be (4, 4) or (3, 4), got {Tr.shape}")
    try:
        Tr_inv = np.linalg.inv(Tr)
    except np.linalg.LinAlgError as exc:
        raise InvalidCloudError(f"Tr is singular: {exc}") from exc
    lidar_poses: np.ndarray = Tr_inv @ cam_poses @ Tr
    return lidar_poses


def read_tum(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory: ``timestamp tx ty tz qx qy qz qw`` a line, ``#`` comments.

    Parameters
    ----------
    path:
        A TUM RGB-D benchmark style file.

    Returns
    -------
    stamps:
        (N,) float64 seconds.
    poses:
        (N, 4, 4) float64 ``T_world_sensor``; quaternions are normalised.

    Raises
    ------
    NotFoundError
        ``path`` does not exist.
    FormatError
        Empty file, a line without exactly 8 numbers, a non-finite value, or a quaternion whose
        norm is not within 1e-2 of 1.
    """
    path = Path(path)
    table = _load_table(path, 8, "TUM trajectory")
    quats = table[:, 4:8]
    norms = np.linalg.norm(quats, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > _QUAT_NORM_TOL)
    if bad.size:
        raise FormatError(
            f"{path}: {bad.size} quaternions are not unit length (first at data row "
            f"{int(bad[0])}, norm {norms[bad[0]]:.6g}); expected columns "
            "timestamp tx ty tz qx qy qz qw"
        )
    poses = np.zeros((len(table), 4, 4))
    poses[:, :3, :3] = Rotation.from_quat(quats).as_matrix()
    poses[:, :3, 3] = table[:, 1:4]
    poses[:, 3, 3] = 1.0
    return table[:, 0].copy(), poses


def write_tum(path: str | os.PathLike[str], stamps: np.ndarray, poses: np.ndarray) -> None:
    """Write a TUM trajectory (``timestamp tx ty tz qx qy qz qw``), atomically.

    Stamps are written with nanosecond resolution (``%.9f``); translations and quaternions with
    17 significant digits, so a float64 trajectory round-trips exactly. Quaternions are
    canonical (``qw >= 0``); the rotation block is projected onto SO(3) by
    :meth:`scipy.spatial.transform.Rotation.from_matrix`.

    Parameters
    ----------
    path:
        Target file (replaced if it exists).
    stamps:
        (N,) seconds.
    poses:
        (N, 4, 4) homogeneous poses.

    Raises
    ------
    InvalidCloudError
        Wrong shapes, mismatched lengths, non-finite values or a non-homogeneous bottom row.
    FormatError
        The file could not be written.
    """
    path = Path(path)
    poses = _check_poses(poses, path)
    stamps = np.asarray(stamps, dtype=np.float64)
    if stamps.shape != (poses.shape[0],):
        raise InvalidCloudError(
            f"stamps for {path} must be ({poses.shape[0]},) to match poses, got {stamps.shape}"
        )
    if not np.isfinite(stamps).all():
        raise InvalidCloudError(f"stamps for {path} contain non-finite values")
    quats = Rotation.from_matrix(poses[:, :3, :3]).as_quat(canonical=True)  # (x, y, z, w)
    table = np.column_stack([stamps, poses[:, :3, 3], quats])
    with atomic_open(path, "w") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        np.savetxt(fh, table, fmt=["%.9f"] + ["%.17g"] * 7, delimiter=" ")
