"""A hashed uniform grid over a point cloud for fixed-radius searches: the SVD step's nearest
neighbours and local planes.

Why not a KD-tree: the SVD step only ever asks for partners within one finest NDT voxel, and
its queries come in scan order, so a grid whose cell is that radius answers with one hash probe
and a handful of points per query, and is built in one pass (docs/registration.md, "Algorithm 3").
The compiled loops live in :mod:`randt.core.kernels` (:func:`~randt.core.kernels.build_grid`,
:func:`~randt.core.kernels.grid_nearest`, :func:`~randt.core.kernels.grid_knn_normals`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from randt.core.errors import InvalidCloudError
from randt.core.kernels import build_grid, cell_block, grid_knn_normals, grid_nearest

__all__ = ["PointGrid"]

#: Cell blocks of reach 1-3, nearest cells first (:func:`randt.core.kernels.cell_block`).
_BLOCKS = {reach: cell_block(reach) for reach in (1, 2, 3)}


@dataclass(frozen=True)
class PointGrid:
    """Points bucketed into cubic cells of ``cell_size_m`` (searches reach at most one cell)."""

    points_xyz: np.ndarray
    cell_size_m: float
    table_key: np.ndarray
    table_idx: np.ndarray
    starts: np.ndarray
    order: np.ndarray

    @classmethod
    def build(cls, points_xyz: np.ndarray, cell_size_m: float) -> PointGrid:
        pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
        table_key, table_idx, starts, order, ok = build_grid(pts, float(cell_size_m))
        if not ok:
            raise InvalidCloudError(
                f"cannot grid the cloud at {cell_size_m:g} m: a point is non-finite or more than "
                "a million cells from the origin"
            )
        return cls(pts, float(cell_size_m), table_key, table_idx, starts, order)

    def nearest(
        self, queries_xyz: np.ndarray, T: np.ndarray, max_distance_m: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Nearest grid point of each query moved by ``T`` (4x4), no farther than
        ``max_distance_m`` (at most the cell size).

        Returns ``(index, distance)``: index -1 and distance inf where nothing is that close.
        """
        if max_distance_m > self.cell_size_m * (1 + 1e-12):
            raise ValueError(
                f"search radius {max_distance_m:g} m exceeds the cell size {self.cell_size_m:g} m"
            )
        q = np.ascontiguousarray(queries_xyz, dtype=np.float64)
        idx = np.empty(q.shape[0], dtype=np.int64)
        d2 = np.empty(q.shape[0])
        R = np.ascontiguousarray(T[:3, :3], dtype=np.float64)
        t = np.ascontiguousarray(T[:3, 3], dtype=np.float64)
        grid_nearest(
            q, R, t,
            self.points_xyz, self.table_key, self.table_idx, self.starts, self.order,
            self.cell_size_m, float(max_distance_m), idx, d2,
        )  # fmt: skip
        return idx, np.sqrt(d2)

    def normals(
        self, which: np.ndarray, k: int, radius_m: float, min_points: int = 5
    ) -> tuple[np.ndarray, np.ndarray]:
        """Unit normals at ``points_xyz[which]`` from up to ``k`` nearest grid points within
        ``radius_m`` (at most three cells; the point itself counts), Open3D's hybrid search.

        Returns ``(normals (n,3), valid (n,))``: fewer than ``min_points`` neighbours leave no
        normal (valid false, normal zero).
        """
        reach = math.ceil(radius_m / self.cell_size_m - 1e-9)
        if not 1 <= reach <= 3:
            raise ValueError(f"normal radius {radius_m:g} m must be within 3 cells of {self.cell_size_m:g} m")
        w = np.ascontiguousarray(which, dtype=np.int64)
        normals = np.empty((w.size, 3))
        valid = np.empty(w.size, dtype=bool)
        grid_knn_normals(
            self.points_xyz, w, self.table_key, self.table_idx, self.starts, self.order,
            self.cell_size_m, _BLOCKS[reach], float(radius_m), int(k), int(min_points), normals, valid,
        )  # fmt: skip
        return normals, valid
