"""Feature extraction with density-based filtering (the RANDT paper's front end, after Deng et al.).

A LiDAR sweep is split by local density into three classes, then equalized:

- **noise**: points whose voxel (``voxel_size_m``) holds a single point and none of whose 26
  neighbour voxels is occupied: isolated returns (rain, dust, multipath) that no surface explains;
- **ground**: points within ``ground_tolerance_m`` of the lowest point of their XY column
  (``ground_cell_m`` cells), in columns whose lowest point lies at least ``min_ground_depth_m``
  below the sensor;
- **objects**: everything else (buildings, poles, vegetation, vehicles).

Ground dominates a spinning LiDAR's returns near the vehicle yet constrains only z, roll and pitch,
so it is downsampled ``ground_voxel_factor`` times coarser than objects: that is the density
equalization of the features handed to the matcher.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from randt.core.kernels import group_min, group_voxels, isolated_points, masked_group_centroids
from randt.core.voxel import NEIGHBOR_OFFSETS, pack_keys, voxel_coords, voxel_downsample, voxel_groups

__all__ = ["Features", "extract_features"]


@dataclass(frozen=True)
class Features:
    """Classified points of one sweep (sensor frame) and the equalized matching set."""

    ground_mask: np.ndarray
    noise_mask: np.ndarray
    matching_xyz: np.ndarray
    #: The first ``n_object_rows`` rows of ``matching_xyz`` are objects, the rest ground.
    n_object_rows: int

    @property
    def object_matching_xyz(self) -> np.ndarray:
        """The matching set's object rows (a view): what places a sweep along a flat street, where
        the ground matches at any offset."""
        return self.matching_xyz[: self.n_object_rows]

    @property
    def object_mask(self) -> np.ndarray:
        mask: np.ndarray = ~(self.ground_mask | self.noise_mask)
        return mask


def _isolated(points_xyz: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """True for points alone in their voxel with all 26 neighbour voxels empty."""
    return _isolated_and_groups(points_xyz, voxel_size_m)[0]


def _isolated_and_groups(points_xyz: np.ndarray, voxel_size_m: float) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`_isolated`, plus the voxel grouping it made (each point's group, group count)."""
    pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
    inverse, keys, counts, table_key, table_idx, ok = group_voxels(pts, float(voxel_size_m))
    if not ok:
        voxel_groups(pts, voxel_size_m)  # raises the range error
    return (
        isolated_points(pts, float(voxel_size_m), inverse, counts, table_key, table_idx),
        inverse,
        keys.size,
    )


def _isolated_numpy(points_xyz: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Vectorized numpy reference of :func:`_isolated` (``np.unique`` and sorted-key lookups)."""
    coords = voxel_coords(points_xyz, voxel_size_m)
    keys = pack_keys(coords)
    uniq, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    single: np.ndarray = counts[inverse] == 1
    if not np.any(single):
        return single
    cand = coords[single]
    offsets = NEIGHBOR_OFFSETS[27][1:]
    neigh = pack_keys((cand[None, :, :] + offsets[:, None, :]).reshape(-1, 3))
    pos = np.minimum(np.searchsorted(uniq, neigh), uniq.size - 1)
    occupied = (uniq[pos] == neigh).reshape(offsets.shape[0], -1).any(axis=0)
    out = np.zeros(points_xyz.shape[0], dtype=bool)
    out[np.flatnonzero(single)[~occupied]] = True
    return out


def extract_features(
    points_xyz: np.ndarray,
    *,
    voxel_size_m: float = 0.5,
    ground_cell_m: float = 2.0,
    ground_tolerance_m: float = 0.25,
    min_ground_depth_m: float = 0.5,
    ground_voxel_factor: float = 2.0,
) -> Features:
    """Split a sweep into noise, ground and objects and build the equalized matching set.

    Parameters
    ----------
    points_xyz : (N,3) float64 points in the sensor frame (z up).
    voxel_size_m : voxel for the isolation test and for downsampling objects.
    ground_cell_m : XY column size for the lowest-point ground test.
    ground_tolerance_m : height above the column minimum still counted as ground.
    min_ground_depth_m : a column's minimum must be this far below the sensor to be ground.
    ground_voxel_factor : ground is downsampled this many times coarser than objects.
    """
    points_xyz = np.ascontiguousarray(points_xyz, dtype=np.float64)
    noise, groups, n_groups = _isolated_and_groups(points_xyz, voxel_size_m)
    # XY columns: group the points with z flattened to 0.
    flat = points_xyz.copy()
    flat[:, 2] = 0.0
    inverse, keys, _ = voxel_groups(flat, ground_cell_m)
    zmin = group_min(points_xyz[:, 2], inverse, keys.size, noise)
    ground = (
        ~noise
        & (points_xyz[:, 2] <= zmin[inverse] + ground_tolerance_m)
        & (zmin[inverse] <= -min_ground_depth_m)
    )
    objects = ~(ground | noise)
    # Objects reuse the isolation test's voxels: a downsampling without a second grouping.
    object_xyz = masked_group_centroids(points_xyz, groups, n_groups, objects)
    ground_xyz = (
        voxel_downsample(np.compress(ground, points_xyz, axis=0), voxel_size_m * ground_voxel_factor)
        if ground.any()
        else np.zeros((0, 3))
    )
    matching = np.vstack([object_xyz, ground_xyz])
    return Features(
        ground_mask=ground, noise_mask=noise, matching_xyz=matching, n_object_rows=len(object_xyz)
    )
