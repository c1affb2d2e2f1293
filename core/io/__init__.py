"""File input/output: point clouds, meshes, trajectories, and the atomic writer they share.

Readers raise :class:`~randt.core.errors.FormatError` (with the path) for files they cannot use and
:class:`~randt.core.errors.NotFoundError` for paths that do not exist; every writer replaces its target
atomically (:func:`atomic_open`).
"""

from randt.core.io.atomic import atomic_open, atomic_write_bytes
from randt.core.io.clouds import (
    SUPPORTED_READ_SUFFIXES,
    SUPPORTED_WRITE_SUFFIXES,
    PointCloud,
    read_cloud,
    write_cloud,
    write_pcd,
    write_ply,
)
from randt.core.io.mesh import read_off, sample_surface
from randt.core.io.trajectory import (
    kitti_velodyne_poses,
    read_kitti_calib,
    read_kitti_poses,
    read_tum,
    write_kitti_poses,
    write_tum,
)

__all__ = [
    "SUPPORTED_READ_SUFFIXES",
    "SUPPORTED_WRITE_SUFFIXES",
    "PointCloud",
    "atomic_open",
    "atomic_write_bytes",
    "kitti_velodyne_poses",
    "read_cloud",
    "read_kitti_calib",
    "read_kitti_poses",
    "read_off",
    "read_tum",
    "sample_surface",
    "write_cloud",
    "write_kitti_poses",
    "write_pcd",
    "write_ply",
    "write_tum",
]
