"""The shared real scan pairs with their reference transforms (``../shared/data/README.md``).

Each loader returns ``(source_xyz, target_xyz, T_target_source_reference)`` in the convention
``p_target = T @ p_source``; loaders go through :func:`tests.data.require_data`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from core.io import read_cloud
from tests.data import require_data

Pair = tuple[np.ndarray, np.ndarray, np.ndarray]


def small_gicp() -> Pair:
    d = require_data("pairs/small_gicp/source.ply") / "pairs/small_gicp"
    return (
        read_cloud(d / "source.ply").xyz,
        read_cloud(d / "target.ply").xyz,
        np.loadtxt(d / "T_target_source.txt"),
    )


def argoverse2() -> Pair:
    d = require_data("pairs/argoverse2/T_a_b.txt") / "pairs/argoverse2"
    a = read_cloud(d / "315966265259836000.bin").xyz
    b = read_cloud(d / "315966265360032000.bin").xyz
    return b, a, np.loadtxt(d / "T_a_b.txt")


def bunny() -> Pair:
    """bun045 (source) into bun000's frame; bun.conf: p_world = R(q)^T p + t, bun000 is the world."""
    d = require_data("objects/bunny/bun.conf") / "objects/bunny"
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
    T_ref = np.linalg.inv(poses["bun000.ply"]) @ poses["bun045.ply"]
    return read_cloud(d / "bun045.ply").xyz, read_cloud(d / "bun000.ply").xyz, T_ref


def car() -> Pair:
    """libpointmatcher car: p_400 = gT_401 p_401 (carCloudList.csv)."""
    d = require_data("pairs/libpointmatcher_car/carCloudList.csv") / "pairs/libpointmatcher_car"
    rows = [r.split(",") for r in (d / "carCloudList.csv").read_text().splitlines()[1:] if r.strip()]
    gT = {r[0].strip(): np.array(r[1:17], dtype=float).reshape(4, 4) for r in rows}
    T_ref = np.linalg.inv(gT["car_cloud400.csv"]) @ gT["car_cloud401.csv"]
    return read_cloud(d / "car_cloud401.csv").xyz, read_cloud(d / "car_cloud400.csv").xyz, T_ref


def kitti00_velodyne(frame: int) -> np.ndarray:
    d = require_data(f"kitti00/velodyne/{frame:06d}.bin") / "kitti00/velodyne"
    return read_cloud(d / f"{frame:06d}.bin").xyz


#: name -> (loader, translation tolerance m, rotation tolerance deg, perturbation scale m).
#: Issue 2's bounds are the best peer's accuracy (small_gicp pair 2 cm / 0.3 deg, Argoverse 2 cm /
#: 0.1 deg, bunny 5 mm / 1 deg, car 10 cm / 0.3 deg); where RANDT does better the bound is tightened
#: to about twice what it reaches (measured 2026-11-23 from the identity and 9 perturbed starts
#: each, all landing on the same fixed point: small_gicp 0.60 cm / 0.254 deg, Argoverse 0.32 cm /
#: 0.041 deg, bunny 0.10 mm / 0.099 deg, car 1.84 cm / 0.220 deg).
PAIRS = {
    "small_gicp": (small_gicp, 0.012, 0.3, 1.0),
    "argoverse2": (argoverse2, 0.006, 0.08, 1.0),
    "bunny": (bunny, 0.0005, 0.2, 0.02),
    "car": (car, 0.04, 0.3, 1.0),
}
