"""The shared real data set: where it is, and the scan pairs with their reference transforms.

The data live outside the repository (never copy them in): ``$RANDT_SHARED_DATA`` if set, else
``<repo root>/../shared/data``. See ``../shared/data/README.md`` for what each folder holds. The
tests (``tests/data.py`` turns a missing file into a skip, or a failure under ``CI=true``) and the
benchmarks (``bench/``, which must run without pytest) both read it through this module.

Each pair loader returns ``(source_xyz, target_xyz, T_target_source_reference)`` in the convention
``p_target = T @ p_source``.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from randt.core.errors import NotFoundError
from randt.core.io import read_cloud
from randt.core.transforms import orthonormalize

__all__ = [
    "DATA_DIR_ENV_VAR",
    "PAIRS",
    "LoopPair",
    "Pair",
    "argoverse2",
    "bunny",
    "car",
    "data_root",
    "kitti00_loop_pairs",
    "kitti00_loops_poses",
    "kitti00_loops_velodyne",
    "kitti00_velodyne",
    "require",
    "small_gicp",
    "threedmatch",
]

DATA_DIR_ENV_VAR = "RANDT_SHARED_DATA"
_REPO_ROOT = Path(__file__).resolve().parents[1]

Pair = tuple[np.ndarray, np.ndarray, np.ndarray]


def data_root() -> Path:
    """Return where the shared data should be: ``$RANDT_SHARED_DATA`` or ``<repo>/../shared/data``,
    resolved (symbolic links followed, so a symlinked ``../shared`` gives its target)."""
    override = os.environ.get(DATA_DIR_ENV_VAR)
    if override:
        return Path(override).expanduser().resolve()
    return (_REPO_ROOT.parent / "shared" / "data").resolve()


def require(*relative_paths: str) -> Path:
    """Return the data directory if it and every ``relative_paths`` entry in it exist.

    Parameters
    ----------
    *relative_paths:
        Files or folders relative to the data directory, e.g. ``"kitti00/poses.txt"``.

    Raises
    ------
    NotFoundError
        Naming the first missing path and ``$RANDT_SHARED_DATA``.
    """
    root = data_root()
    missing = [p for p in ("", *relative_paths) if not (root / p).exists()]
    if missing:
        raise NotFoundError(
            f"real test data missing: {root / missing[0]} does not exist (set {DATA_DIR_ENV_VAR} to the "
            f"shared data directory; without it the default is <repo root>/../shared/data)"
        )
    return root


def small_gicp() -> Pair:
    """small_gicp's example pair (indoor, short range)."""
    d = require("pairs/small_gicp/source.ply") / "pairs/small_gicp"
    return (
        read_cloud(d / "source.ply").xyz,
        read_cloud(d / "target.ply").xyz,
        np.loadtxt(d / "T_target_source.txt"),
    )


def argoverse2() -> Pair:
    """Two Argoverse 2 LiDAR sweeps (outdoor)."""
    d = require("pairs/argoverse2/T_a_b.txt") / "pairs/argoverse2"
    a = read_cloud(d / "315966265259836000.bin").xyz
    b = read_cloud(d / "315966265360032000.bin").xyz
    return b, a, np.loadtxt(d / "T_a_b.txt")


def bunny(source: str = "bun045") -> Pair:
    """Bunny scan ``source`` (bun045 by default; bun315 is 45 deg the other way) into bun000's frame;
    bun.conf: p_world = R(q)^T p + t, bun000 is the world."""
    d = require("objects/bunny/bun.conf") / "objects/bunny"
    poses = {}
    for line in (d / "bun.conf").read_text().splitlines():
        parts = line.split()
        if parts and parts[0] == "bmesh":
            t = np.array(parts[2:5], dtype=float)
            q = np.array(parts[5:9], dtype=float)
            T = np.eye(4)
            T[:3, :3] = Rotation.from_quat(q).as_matrix().T
            T[:3, 3] = t
            poses[parts[1]] = T
    if f"{source}.ply" not in poses:
        raise NotFoundError(f"bunny scan {source!r}: not in {d / 'bun.conf'} (known: {sorted(poses)})")
    T_ref = np.linalg.inv(poses["bun000.ply"]) @ poses[f"{source}.ply"]
    return read_cloud(d / f"{source}.ply").xyz, read_cloud(d / "bun000.ply").xyz, T_ref


def threedmatch() -> Pair:
    """The 3DMatch-style indoor fragment pair (2.5 cm voxels, 17.8 deg apart): p_ref = gt p_src.

    ``gt.npy`` is stored to about 4 digits (R R^T is 7e-5 off the identity): it is returned
    orthonormalized (the nearest rotation; 0.004 deg from the stored block).
    """
    d = require("pairs/3dmatch/gt.npy") / "pairs/3dmatch"
    return np.load(d / "src.npy"), np.load(d / "ref.npy"), orthonormalize(np.load(d / "gt.npy"))


def car() -> Pair:
    """libpointmatcher car: p_400 = gT_401 p_401 (carCloudList.csv)."""
    d = require("pairs/libpointmatcher_car/carCloudList.csv") / "pairs/libpointmatcher_car"
    rows = [r.split(",") for r in (d / "carCloudList.csv").read_text().splitlines()[1:] if r.strip()]
    gT = {r[0].strip(): np.array(r[1:17], dtype=float).reshape(4, 4) for r in rows}
    T_ref = np.linalg.inv(gT["car_cloud400.csv"]) @ gT["car_cloud401.csv"]
    return read_cloud(d / "car_cloud401.csv").xyz, read_cloud(d / "car_cloud400.csv").xyz, T_ref


def kitti00_velodyne(frame: int) -> np.ndarray:
    """(N,3) points of KITTI odometry sequence 00's velodyne scan ``frame``."""
    d = require(f"kitti00/velodyne/{frame:06d}.bin") / "kitti00/velodyne"
    return read_cloud(d / f"{frame:06d}.bin").xyz


def kitti00_loops_velodyne(frame: int) -> np.ndarray:
    """(N,3) points of KITTI 00 sweep ``frame`` of the revisit set ``kitti00_loops/``."""
    d = require(f"kitti00_loops/velodyne/{frame:06d}.bin") / "kitti00_loops/velodyne"
    return read_cloud(d / f"{frame:06d}.bin").xyz


@dataclass(frozen=True)
class LoopPair:
    """A KITTI 00 revisit: frames ``i`` and ``j`` (p_i = T p_j in LiDAR frames)."""

    i: int
    j: int
    gt_distance_m: float
    #: the ICP-refined relative pose (good to a few cm where ``icp_inlier_fraction`` is high)
    T_icp: np.ndarray
    #: the relative pose from KITTI's ground truth (off by 0.7-1.1 m at these revisits)
    T_gt: np.ndarray
    icp_inlier_fraction: float


def kitti00_loop_pairs() -> list[LoopPair]:
    """The 21 revisit pairs of ``kitti00_loops/loop_pairs.csv``, in the file's order."""
    path = require("kitti00_loops/loop_pairs.csv") / "kitti00_loops/loop_pairs.csv"
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))

    def pose(row: dict[str, str], prefix: str) -> np.ndarray:
        T = np.eye(4)
        T[:3, :] = np.array([float(row[f"{prefix}{k}"]) for k in range(12)]).reshape(3, 4)
        return T

    return [
        LoopPair(
            int(r["i"]),
            int(r["j"]),
            float(r["gt_dist_m"]),
            pose(r, "T_icp_velo_i_from_j_"),
            pose(r, "T_gt_velo_i_from_j_"),
            float(r["icp_inlier_frac_0.3m"]),
        )
        for r in rows
    ]


#: The shared pairs with reference transforms, name -> loader, in the benchmarks' order.
PAIRS: dict[str, Callable[[], Pair]] = {
    "small_gicp": small_gicp,
    "argoverse2": argoverse2,
    "bunny": bunny,
    "car": car,
}


def kitti00_loops_poses() -> dict[int, np.ndarray]:
    """LiDAR poses in the world (4x4, ``p_world = T @ p_lidar``) of the 26 ``kitti00_loops/`` sweeps.

    From ``poses_gt.txt`` (KITTI's left-camera poses, world = camera at frame 0) and
    ``calib_Tr_velo_to_cam.txt``: a LiDAR pose is ``inv(Tr) @ P_cam @ Tr``, so the world is the
    LiDAR at frame 0 (z up). Keyed by frame index.
    """
    d = require("kitti00_loops/poses_gt.txt", "kitti00_loops/calib_Tr_velo_to_cam.txt") / "kitti00_loops"
    Tr = np.eye(4)
    Tr[:3, :] = np.loadtxt(d / "calib_Tr_velo_to_cam.txt", comments="#").reshape(3, 4)
    Tr_inv = np.linalg.inv(Tr)
    rows = np.atleast_2d(np.loadtxt(d / "poses_gt.txt", comments="#"))
    out: dict[int, np.ndarray] = {}
    for row in rows:
        P = np.eye(4)
        P[:3, :] = row[2:14].reshape(3, 4)
        out[int(row[0])] = Tr_inv @ P @ Tr
    return out
