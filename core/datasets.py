"""Scan sequences on disk: a KITTI odometry sequence folder or a folder of point-cloud files.

- **KITTI layout**: ``DIR/velodyne/*.bin`` (float32 x, y, z, intensity), optionally ``DIR/times.txt``
  (one time in seconds per scan), ``DIR/poses.txt`` and ``DIR/calib.txt`` (ground truth, camera
  frame, converted with ``Tr`` to the velodyne frame).
- **Plain folder**: every ``.bin``, ``.pcd``, ``.ply``, ``.csv``, ``.txt`` or ``.npy`` file in ``DIR``,
  in file-name order (sorted lexicographically: zero-pad your numbers).
- **ROS bag**: a rosbag2 folder (sqlite3 or MCAP) or a ROS 1 ``.bag`` file, one PointCloud2 topic
  (:mod:`randt.core.io.bags`; :func:`open_scans` picks it).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from randt.core.errors import FormatError, NotFoundError
from randt.core.io import PointCloud, kitti_velodyne_poses, read_cloud, read_kitti_calib, read_kitti_poses
from randt.core.io.bags import BagSequence, is_bag, open_bag
from randt.core.transforms import invert

__all__ = ["NoScansError", "ScanSequence", "Scans", "open_scans", "open_sequence"]

_SCAN_SUFFIXES = (".bin", ".pcd", ".ply", ".csv", ".txt", ".npy")


class NoScansError(FormatError):
    """A sequence folder exists but holds no scan files (or none in the requested range)."""


@dataclass(frozen=True)
class ScanSequence:
    """The files of one sequence, their times and (if present) reference poses."""

    root: Path
    layout: str
    files: tuple[Path, ...]
    stamps_s: np.ndarray | None

    def __len__(self) -> int:
        return len(self.files)

    def read(self, index: int) -> PointCloud:
        """Read scan ``index`` (any supported format)."""
        return read_cloud(self.files[index])

    def label(self, index: int) -> str:
        """How to name scan ``index`` in a message."""
        return self.files[index].name

    def __iter__(self) -> Iterator[PointCloud]:
        for i in range(len(self.files)):
            yield self.read(i)

    def reference_poses(self) -> np.ndarray | None:
        """KITTI ground truth as velodyne poses in the first scan's frame, if the folder has it."""
        poses, calib = self.root / "poses.txt", self.root / "calib.txt"
        if self.layout != "kitti" or not poses.is_file():
            return None
        P = read_kitti_poses(poses)
        if calib.is_file():
            P = kitti_velodyne_poses(P, read_kitti_calib(calib)["Tr"])
        P = P[: len(self.files)]
        return np.array([invert(P[0]) @ p for p in P])


def open_sequence(directory: str | Path, *, start: int = 0, end: int | None = None) -> ScanSequence:
    """Find the scans of a sequence folder (module docstring); ``start``/``end`` slice them."""
    root = Path(directory)
    if not root.exists():
        raise NotFoundError(f"{root}: no such directory")
    if not root.is_dir():
        raise NotADirectoryError(20, "not a directory, expected a sequence folder of scan files", str(root))
    velodyne = root / "velodyne"
    if velodyne.is_dir():
        files = sorted(velodyne.glob("*.bin"))
        layout = "kitti"
        times = root / "times.txt"
        stamps = np.loadtxt(times, ndmin=1) if times.is_file() else None
    else:
        files = sorted(p for p in root.iterdir() if p.is_file() and p.suffix.lower() in _SCAN_SUFFIXES)
        layout = "files"
        stamps = None
    if not files:
        raise NoScansError(
            f"{root}: no scan files (expected velodyne/*.bin or files ending in {', '.join(_SCAN_SUFFIXES)})"
        )
    if stamps is not None and stamps.shape[0] < len(files):
        stamps = None
    sl = slice(start, end)
    files = files[sl]
    if stamps is not None:
        stamps = stamps[sl]
    if not files:
        raise NoScansError(f"{root}: no scan files in the range start={start} end={end}")
    return ScanSequence(root=root, layout=layout, files=tuple(files), stamps_s=stamps)


#: A sequence of sweeps on disk: files or a bag's topic.
Scans = ScanSequence | BagSequence


def open_scans(
    path: str | Path, *, topic: str | None = None, start: int = 0, end: int | None = None
) -> Scans:
    """The sweeps at ``path``: a ROS bag's PointCloud2 ``topic`` (the only one by default), or a
    sequence folder (:func:`open_sequence`; ``topic`` is then refused)."""
    if is_bag(path):
        return open_bag(path, topic=topic, start=start, end=end)
    if topic is not None:
        raise FormatError(f"{path}: --topic is for ROS bags, and this is no bag")
    return open_sequence(path, start=start, end=end)
