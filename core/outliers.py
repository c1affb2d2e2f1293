"""Outlier removal: the paper's IQR rule on Mahalanobis distances (Algorithm 1) and the SOR baseline.

Algorithm 1 of Johnson et al. (2026), as implemented here
--------------------------------------------------------
1. Voxelize the reference cloud and fit one Gaussian per voxel (mean, conditioned covariance).
2. For every point, its squared Mahalanobis distance to its own voxel's Gaussian,
   ``d2 = (p - mu)^T Sigma^-1 (p - mu)``.
3. Per voxel, the quartiles ``Q1, Q3`` of those distances, by linear interpolation between order
   statistics (NumPy's default ``"linear"`` method: the q-quantile of n sorted values sits at
   position ``q * (n - 1)``), then Tukey's fences ``[Q1 - k IQR, Q3 + k IQR]`` with ``IQR = Q3 - Q1``.
4. Voxels with fewer than ``min_points_for_voxel_quartiles`` points cannot give stable quartiles:
   their points are judged by fences computed once from the pooled distances of *all* points in
   voxels that have a Gaussian. Points in voxels too sparse for any Gaussian
   (< ``min_points_per_voxel``) are isolated returns and are outliers.
5. Points outside their fences are removed; the caller refits the Gaussians on what remains.

Per-voxel quartiles come from one counting sort by voxel and a sort of each voxel's few
distances (:func:`randt.core.kernels.grouped_fence_mask`, instead of one ``np.lexsort`` by (voxel,
distance)); :func:`iqr_inlier_mask_numpy` keeps the vectorized formulation the tests compare with.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from randt.core.kernels import grouped_fence_mask, mahalanobis_to_assigned
from randt.core.voxel import VoxelGaussianMap

__all__ = [
    "iqr_fence_mask",
    "iqr_inlier_mask",
    "iqr_inlier_mask_numpy",
    "statistical_outlier_mask",
    "tukey_fences",
]


def tukey_fences(values: np.ndarray, k: float = 1.5) -> tuple[float, float]:
    """Tukey's fences ``(Q1 - k IQR, Q3 + k IQR)`` of a 1-D array (linear-interpolated quartiles)."""
    q1, q3 = np.percentile(values, [25.0, 75.0])
    iqr = q3 - q1
    return float(q1 - k * iqr), float(q3 + k * iqr)


def _mahalanobis_to_voxel(points_xyz: np.ndarray, gmap: VoxelGaussianMap, vidx: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance of each point to voxel ``vidx`` (inf where it is -1)."""
    d2 = np.full(points_xyz.shape[0], np.inf)
    hit = vidx >= 0
    diff = points_xyz[hit] - gmap.means[vidx[hit]]
    d2[hit] = np.einsum("ni,nij,nj->n", diff, gmap.inv_covariances[vidx[hit]], diff)
    return d2


def _grouped_quantile(
    sorted_vals: np.ndarray, starts: np.ndarray, counts: np.ndarray, q: float
) -> np.ndarray:
    """Linear-interpolated q-quantile of each contiguous sorted group."""
    pos = q * (counts - 1)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, counts - 1)
    frac = pos - lo
    quantile: np.ndarray = sorted_vals[starts + lo] * (1.0 - frac) + sorted_vals[starts + hi] * frac
    return quantile


def iqr_inlier_mask(
    points_xyz: np.ndarray,
    voxel_size_m: float,
    *,
    k: float = 1.5,
    min_points_per_voxel: int = 6,
    min_points_for_voxel_quartiles: int = 10,
    eigenvalue_ratio: float = 0.01,
    keep_unjudged: bool = False,
    groups: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Algorithm 1's outlier test: True for points inside their voxel's Tukey fences.

    Parameters
    ----------
    points_xyz : (N,3) float64 reference points.
    voxel_size_m : NDT voxel size used for the Gaussians.
    k : fence multiplier (1.5 is Tukey's "outlier", 3.0 his "far out").
    min_points_per_voxel : voxels with fewer points get no Gaussian; their points are outliers.
    min_points_for_voxel_quartiles : below this, a voxel uses the pooled fences (module docstring).
    keep_unjudged : points of voxels without a Gaussian are kept (True) instead of outliers.
    groups : the points' voxels when the caller has them, as :func:`randt.core.voxel.voxel_groups`
        gives them with ``sort`` (the keyframe model's, :mod:`randt.core.model`).

    Returns
    -------
    (N,) bool inlier mask.
    """
    gmap, vidx = VoxelGaussianMap.build_with_assignment(
        points_xyz,
        voxel_size_m,
        min_points_per_voxel=min_points_per_voxel,
        eigenvalue_ratio=eigenvalue_ratio,
        groups=groups,
    )
    mask = iqr_fence_mask(
        points_xyz, gmap, vidx, k=k, min_points_for_voxel_quartiles=min_points_for_voxel_quartiles
    )
    if keep_unjudged:
        mask |= vidx < 0
    return mask


def iqr_fence_mask(
    points_xyz: np.ndarray,
    gmap: VoxelGaussianMap,
    vidx: np.ndarray,
    *,
    k: float = 1.5,
    min_points_for_voxel_quartiles: int = 10,
) -> np.ndarray:
    """Steps 2-5 of Algorithm 1 with given Gaussians: True for points inside their voxel's fences.

    ``vidx`` (N,) is each point's voxel in ``gmap`` (-1: no Gaussian, an outlier). The quartiles
    of a voxel are those of the distances of the points given in it; :func:`iqr_inlier_mask`
    gives a cloud's own Gaussians, the incremental keyframe model (:mod:`randt.core.model`) the fused
    model's, judging a joining keyframe's points only.
    """
    pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
    d = np.sqrt(mahalanobis_to_assigned(pts, vidx, gmap.means, gmap.inv_covariances))
    has = vidx >= 0
    if not np.any(has):
        return np.zeros(points_xyz.shape[0], dtype=bool)
    pooled_lo, pooled_hi = tukey_fences(d[has], k)
    return grouped_fence_mask(d, vidx, gmap.n_voxels, k, min_points_for_voxel_quartiles, pooled_lo, pooled_hi)


def iqr_inlier_mask_numpy(
    points_xyz: np.ndarray,
    voxel_size_m: float,
    *,
    k: float = 1.5,
    min_points_per_voxel: int = 6,
    min_points_for_voxel_quartiles: int = 10,
    eigenvalue_ratio: float = 0.01,
) -> np.ndarray:
    """Vectorized numpy reference of :func:`iqr_inlier_mask` (one ``np.lexsort``), for the tests.

    Parameters
    ----------
    points_xyz : (N,3) float64 reference points.
    voxel_size_m : NDT voxel size used for the Gaussians.
    k : fence multiplier (1.5 is Tukey's "outlier", 3.0 his "far out").
    min_points_per_voxel : voxels with fewer points get no Gaussian; their points are outliers.
    min_points_for_voxel_quartiles : below this, a voxel uses the pooled fences (module docstring).

    Returns
    -------
    (N,) bool inlier mask.
    """
    gmap, vidx = VoxelGaussianMap.build_with_assignment(
        points_xyz,
        voxel_size_m,
        min_points_per_voxel=min_points_per_voxel,
        eigenvalue_ratio=eigenvalue_ratio,
    )
    d2 = _mahalanobis_to_voxel(points_xyz, gmap, vidx)
    d = np.sqrt(d2)
    has = vidx >= 0
    inlier = np.zeros(points_xyz.shape[0], dtype=bool)
    if not np.any(has):
        return inlier
    pooled_lo, pooled_hi = tukey_fences(d[has], k)

    idx_has = np.flatnonzero(has)
    order = idx_has[np.lexsort((d[idx_has], vidx[idx_has]))]
    v_sorted, d_sorted = vidx[order], d[order]
    starts = np.flatnonzero(np.r_[True, v_sorted[1:] != v_sorted[:-1]])
    counts = np.diff(np.r_[starts, v_sorted.size])
    q1 = _grouped_quantile(d_sorted, starts, counts, 0.25)
    q3 = _grouped_quantile(d_sorted, starts, counts, 0.75)
    iqr = q3 - q1
    lo = np.where(counts >= min_points_for_voxel_quartiles, q1 - k * iqr, pooled_lo)
    hi = np.where(counts >= min_points_for_voxel_quartiles, q3 + k * iqr, pooled_hi)
    group = np.repeat(np.arange(starts.size), counts)
    inlier[order] = (d_sorted >= lo[group]) & (d_sorted <= hi[group])
    return inlier


def statistical_outlier_mask(
    points_xyz: np.ndarray, *, n_neighbors: int = 16, std_ratio: float = 2.0
) -> np.ndarray:
    """Statistical outlier removal (PCL's SOR), the ablation baseline for Algorithm 1.

    A point is an outlier when its mean distance to its ``n_neighbors`` nearest neighbours exceeds
    the global mean of that quantity by more than ``std_ratio`` standard deviations.
    """
    tree = cKDTree(points_xyz)
    dist, _ = tree.query(points_xyz, k=n_neighbors + 1)
    assert isinstance(dist, np.ndarray)  # (N, k) for an (N,3) query
    mean_d = dist[:, 1:].mean(axis=1)
    inlier: np.ndarray = mean_d <= mean_d.mean() + std_ratio * mean_d.std()
    return inlier
