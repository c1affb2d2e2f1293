"""Point-cloud agreement metrics (the RANDT paper's): correspondence RMSE, Chamfer distance,
overlap, voxel-count spread and the PDU (point distribution uniformity).

They take (N,3) float64 points in metres and use scipy ``cKDTree`` nearest neighbours
(``nn_B(p) = min_{q in B} |p - q|``); voxel metrics reuse :mod:`randt.core.voxel`'s keys. Every result
is a frozen dataclass with an ``as_dict()`` giving plain floats, ints and lists.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from randt.core.errors import InvalidCloudError
from randt.core.metrics.values import json_float
from randt.core.transforms import as_transform, transform_points
from randt.core.voxel import pack_keys, voxel_coords

__all__ = [
    "CorrespondenceRmse",
    "PduPerGroup",
    "chamfer_distance",
    "correspondence_rmse",
    "overlap_ratio",
    "pdu",
    "pdu_per_group",
    "voxel_count_std",
]

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# Validation helpers
# --------------------------------------------------------------------------------------------


def _points(points_xyz: np.ndarray, name: str) -> np.ndarray:
    """Return ``points_xyz`` as a finite, non-empty (N,3) float64 array or raise."""
    arr = np.asarray(points_xyz)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidCloudError(f"{name}: expected an (N,3) array of points, got shape {arr.shape}")
    if arr.shape[0] == 0:
        raise InvalidCloudError(f"{name}: the cloud is empty")
    if not np.issubdtype(arr.dtype, np.number):
        raise InvalidCloudError(f"{name}: points must be numeric, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if not np.all(np.isfinite(arr)):
        raise InvalidCloudError(f"{name}: {int((~np.isfinite(arr)).any(axis=1).sum())} points are not finite")
    return arr


def _positive(value: float, name: str) -> float:
    """Return ``value`` as a float if it is > 0 (``inf`` allowed), else raise ``ValueError``."""
    value = float(value)
    if not value > 0.0:
        raise ValueError(f"{name} must be > 0, got {value}")
    return value


def _voxel_size(voxel_size_m: float) -> float:
    """Return ``voxel_size_m`` as a float if it is finite and > 0, else raise ``ValueError``."""
    value = float(voxel_size_m)
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"voxel_size_m must be finite and > 0, got {value}")
    return value


# --------------------------------------------------------------------------------------------
# Cloud metrics
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CorrespondenceRmse:
    """Result of :func:`correspondence_rmse`.

    Attributes
    ----------
    rmse_m : root mean square of the used nearest-neighbour distances, metres (NaN if
        ``n_pairs == 0``).
    n_pairs : number of source points whose nearest target point is within the max distance.
    n_source : number of source points.
    """

    rmse_m: float
    n_pairs: int
    n_source: int

    @property
    def fitness(self) -> float:
        """Share of source points used, ``n_pairs / n_source`` in [0, 1] (Open3D's "fitness")."""
        return self.n_pairs / self.n_source

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict (NaN becomes ``None``)."""
        return {
            "rmse_m": json_float(self.rmse_m),
            "n_pairs": self.n_pairs,
            "n_source": self.n_source,
            "fitness": self.fitness,
        }


def _nn_distances(query_xyz: np.ndarray, tree: cKDTree, max_distance_m: float = math.inf) -> np.ndarray:
    """(N,) distances from each query point to its nearest tree point; ``inf`` beyond the bound.

    The bound is inclusive: a neighbour at exactly ``max_distance_m`` is kept.
    """
    bound = math.inf if math.isinf(max_distance_m) else float(np.nextafter(max_distance_m, math.inf))
    d, _ = tree.query(query_xyz, k=1, distance_upper_bound=bound, workers=-1)
    d = np.asarray(d, dtype=np.float64)
    d[d > max_distance_m] = math.inf
    return d


def correspondence_rmse(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray,
    T_target_source: np.ndarray | None = None,
    *,
    max_distance_m: float = math.inf,
) -> CorrespondenceRmse:
    """RMSE of nearest-neighbour distances from the moved source to the target.

    .. math::

        d_i = \\min_j |T s_i - t_j|, \\qquad
        \\mathrm{RMSE} = \\sqrt{\\tfrac{1}{|I|} \\sum_{i \\in I} d_i^2}, \\qquad
        I = \\{i : d_i \\le d_{max}\\}

    Parameters
    ----------
    source_xyz : (N,3) float64, source points in the source frame, metres.
    target_xyz : (M,3) float64, target points in the target frame, metres.
    T_target_source : (4,4) float64 rigid transform mapping source points into the target
        frame; ``None`` means identity.
    max_distance_m : pairs farther apart than this are excluded (inclusive bound, > 0).

    Returns
    -------
    CorrespondenceRmse
        ``rmse_m`` (NaN when no pair is within range), ``n_pairs = |I|``, ``n_source = N``.

    Raises
    ------
    InvalidCloudError
        Empty, wrongly shaped or non-finite clouds.
    ValueError
        A non-rigid ``T_target_source`` or ``max_distance_m <= 0``.
    """
    source = _points(source_xyz, "source")
    target = _points(target_xyz, "target")
    T = as_transform(T_target_source, name="T_target_source")
    max_distance_m = _positive(max_distance_m, "max_distance_m")
    d = _nn_distances(transform_points(T, source), cKDTree(target), max_distance_m)
    used = d[np.isfinite(d)]
    rmse = float(np.sqrt(np.mean(used * used))) if used.size else math.nan
    if not used.size:
        logger.warning("correspondence_rmse: no source point within %.3g m of the target", max_distance_m)
    return CorrespondenceRmse(rmse_m=rmse, n_pairs=int(used.size), n_source=int(source.shape[0]))


def chamfer_distance(a_xyz: np.ndarray, b_xyz: np.ndarray, *, squared: bool = False) -> float:
    """Symmetric Chamfer distance: the average of the two mean nearest-neighbour distances.

    .. math::

        CD(A, B) = \\frac{1}{2}\\Big(\\frac{1}{|A|}\\sum_{a \\in A} nn_B(a)^k
                   + \\frac{1}{|B|}\\sum_{b \\in B} nn_A(b)^k\\Big),
        \\quad k = 1 \\text{ (default, metres) or } 2 \\text{ (``squared=True``, m}^2)

    Note the halving: some papers report the plain sum of the two means (twice this value).

    Parameters
    ----------
    a_xyz : (N,3) float64, metres.
    b_xyz : (M,3) float64, metres.
    squared : average squared distances instead of distances.

    Returns
    -------
    float
        Metres (or square metres if ``squared``).
    """
    a = _points(a_xyz, "a")
    b = _points(b_xyz, "b")
    d_ab = _nn_distances(a, cKDTree(b))
    d_ba = _nn_distances(b, cKDTree(a))
    if squared:
        d_ab, d_ba = d_ab * d_ab, d_ba * d_ba
    return float(0.5 * (d_ab.mean() + d_ba.mean()))


def overlap_ratio(a_xyz: np.ndarray, b_xyz: np.ndarray, radius_m: float) -> float:
    """Share of ``a``'s points that have a point of ``b`` within ``radius_m`` (asymmetric).

    .. math::  O(A, B) = \\frac{|\\{a \\in A : nn_B(a) \\le r\\}|}{|A|} \\in [0, 1]

    Parameters
    ----------
    a_xyz : (N,3) float64, metres.
    b_xyz : (M,3) float64, metres.
    radius_m : inclusive radius ``r`` > 0, metres.
    """
    a = _points(a_xyz, "a")
    b = _points(b_xyz, "b")
    radius_m = _positive(radius_m, "radius_m")
    d = _nn_distances(a, cKDTree(b), radius_m)
    return float(np.count_nonzero(np.isfinite(d)) / a.shape[0])


def _voxel_counts(points_xyz: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """(V,) int64 point counts of the occupied voxels (cells ``floor(p / voxel_size_m)``)."""
    points = _points(points_xyz, "points")
    _, counts = np.unique(pack_keys(voxel_coords(points, _voxel_size(voxel_size_m))), return_counts=True)
    return counts


def voxel_count_std(points_xyz: np.ndarray, voxel_size_m: float) -> float:
    """Population standard deviation of the point counts of the occupied voxels.

    .. math::  \\sigma = \\sqrt{\\tfrac{1}{V}\\sum_{v=1}^{V} (n_v - \\bar n)^2}, \\quad
               \\bar n = \\tfrac{1}{V}\\sum_v n_v

    where ``n_v`` is the number of points in occupied voxel ``v`` (cubic cells of edge
    ``voxel_size_m``, metres, aligned to the origin) and ``V`` the number of occupied voxels.
    Empty voxels are not counted.

    Parameters
    ----------
    points_xyz : (N,3) float64, metres.
    voxel_size_m : voxel edge length, metres (> 0).

    Returns
    -------
    float
        ``sigma`` in points per voxel.
    """
    return float(np.std(_voxel_counts(points_xyz, voxel_size_m)))


def pdu(points_xyz: np.ndarray, voxel_size_m: float) -> float:
    """Point distribution uniformity (PDU), the plain reading of the RANDT paper's index.

    .. math::  PDU = 1 - \\frac{\\sigma}{\\bar n}

    with ``sigma`` the population standard deviation and ``n-bar`` the mean of the point counts
    of the occupied voxels (see :func:`voxel_count_std`). It is 1 for a perfectly uniform cloud
    (every occupied voxel holds the same number of points), decreases as density varies, and
    goes negative when the coefficient of variation exceeds 1.

    Parameters
    ----------
    points_xyz : (N,3) float64, metres.
    voxel_size_m : voxel edge length, metres (> 0).

    Returns
    -------
    float
        Dimensionless PDU, ``<= 1``.
    """
    counts = _voxel_counts(points_xyz, voxel_size_m)
    return float(1.0 - np.std(counts) / counts.mean())


@dataclass(frozen=True)
class PduPerGroup:
    """Result of :func:`pdu_per_group`, one entry per distinct group id (ascending).

    Attributes
    ----------
    groups : (G,) the distinct group ids.
    pdu : (G,) float64 PDU of each group's points.
    n_voxels : (G,) int64 occupied voxels per group.
    n_points : (G,) int64 points per group.
    """

    groups: np.ndarray
    pdu: np.ndarray
    n_voxels: np.ndarray
    n_points: np.ndarray

    def as_dict(self) -> dict[str, list[Any]]:
        """JSON-ready dict of lists."""
        return {
            "groups": self.groups.tolist(),
            "pdu": self.pdu.tolist(),
            "n_voxels": self.n_voxels.tolist(),
            "n_points": self.n_points.tolist(),
        }


def pdu_per_group(points_xyz: np.ndarray, voxel_size_m: float, group_ids: np.ndarray) -> PduPerGroup:
    """PDU (:func:`pdu`) of each group of points, e.g. per map tile, in one vectorized pass.

    Voxels are counted per (group, voxel) pair, so a voxel straddling two groups contributes a
    count to each; for group ``g`` with occupied-voxel counts ``n_v``:
    ``PDU_g = 1 - sigma_g / mean_g`` (population std). Implemented with ``np.unique`` on combined
    (group, voxel) indices and ``np.bincount`` sums; no loop over groups.

    Parameters
    ----------
    points_xyz : (N,3) float64, metres.
    voxel_size_m : voxel edge length, metres (> 0).
    group_ids : (N,) group label of each point (integers, or anything ``np.unique`` sorts).

    Returns
    -------
    PduPerGroup
    """
    points = _points(points_xyz, "points")
    voxel_size_m = _voxel_size(voxel_size_m)
    group_ids = np.asarray(group_ids)
    if group_ids.shape != (points.shape[0],):
        raise InvalidCloudError(
            f"group_ids must have shape ({points.shape[0]},) to match the points, got {group_ids.shape}"
        )
    groups, g_idx = np.unique(group_ids, return_inverse=True)
    _, v_idx = np.unique(pack_keys(voxel_coords(points, voxel_size_m)), return_inverse=True)
    n_vox_all = int(v_idx.max()) + 1
    pairs, counts = np.unique(g_idx.astype(np.int64) * n_vox_all + v_idx, return_counts=True)
    pair_group = pairs // n_vox_all
    n_groups = groups.size
    n_voxels = np.bincount(pair_group, minlength=n_groups)
    n_points = np.bincount(pair_group, weights=counts, minlength=n_groups)
    mean = n_points / n_voxels
    var = np.bincount(pair_group, weights=(counts - mean[pair_group]) ** 2, minlength=n_groups) / n_voxels
    return PduPerGroup(
        groups=groups,
        pdu=1.0 - np.sqrt(var) / mean,
        n_voxels=n_voxels.astype(np.int64),
        n_points=n_points.astype(np.int64),
    )
