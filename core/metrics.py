"""Quality metrics: point-cloud agreement (the RANDT paper's) and trajectory error.

Cloud metrics take (N,3) float64 points in metres and use scipy ``cKDTree`` nearest neighbours
(``nn_B(p) = min_{q in B} |p - q|``); voxel metrics reuse :mod:`core.voxel`'s keys.

Trajectory metrics take two (N,4,4) float64 stacks of world<-sensor poses, row ``i`` of the
reference ``Q`` corresponding to row ``i`` of the estimate ``P`` (associate timestamps first):

- :func:`ate`: absolute trajectory error of positions after an optional Umeyama alignment
  (as evo's ``APE`` with ``PoseRelation.translation_part``).
- :func:`rpe`: relative pose error over a fixed frame gap (evo's ``RPE`` definition).
- :func:`kitti_relative_errors`: the KITTI odometry devkit's segment errors
  (``evaluate_odometry.cpp``: 100..800 m segments, every 10th frame as a start).
- :func:`evaluate_trajectory`: the three bundled into one JSON-ready dict.

Every result is a frozen dataclass with an ``as_dict()`` giving plain floats, ints and lists.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from core.errors import InvalidCloudError
from core.svd import kabsch
from core.transforms import as_transform, transform_points
from core.voxel import pack_keys, voxel_coords

__all__ = [
    "KITTI_LENGTHS_M",
    "AteResult",
    "CorrespondenceRmse",
    "ErrorStats",
    "KittiLengthError",
    "KittiResult",
    "PduPerGroup",
    "RpeResult",
    "ate",
    "chamfer_distance",
    "correspondence_rmse",
    "evaluate_trajectory",
    "kitti_relative_errors",
    "overlap_ratio",
    "pdu",
    "pdu_per_group",
    "rpe",
    "umeyama",
    "voxel_count_std",
]

logger = logging.getLogger(__name__)

#: Segment lengths of the KITTI odometry benchmark, metres.
KITTI_LENGTHS_M: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)

AlignMode = Literal["se3", "sim3", "none"]


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


def _poses(poses: np.ndarray, name: str) -> np.ndarray:
    """Return ``poses`` as a finite (N,4,4) float64 stack with bottom rows [0 0 0 1] or raise."""
    arr = np.asarray(poses)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4) or arr.shape[0] == 0:
        raise InvalidCloudError(f"{name}: poses must be (N,4,4) with N > 0, got shape {arr.shape}")
    arr = arr.astype(np.float64, copy=False)
    if not np.all(np.isfinite(arr)):
        raise InvalidCloudError(f"{name}: poses contain non-finite values")
    bad = ~np.all(np.abs(arr[:, 3, :] - [0.0, 0.0, 0.0, 1.0]) <= 1e-9, axis=1)
    if bad.any():
        raise InvalidCloudError(
            f"{name}: pose {int(np.argmax(bad))} has bottom row {arr[int(np.argmax(bad)), 3].tolist()}, "
            "expected [0, 0, 0, 1]"
        )
    return arr


def _pose_pair(reference: np.ndarray, estimate: np.ndarray, min_poses: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate two pose stacks of equal length >= ``min_poses``."""
    Q = _poses(reference, "reference")
    P = _poses(estimate, "estimate")
    if Q.shape[0] != P.shape[0]:
        raise InvalidCloudError(
            f"reference has {Q.shape[0]} poses but estimate has {P.shape[0]}; "
            "associate them by timestamp first"
        )
    if Q.shape[0] < min_poses:
        raise InvalidCloudError(f"need at least {min_poses} poses, got {Q.shape[0]}")
    return Q, P


def _invert_rigid(T: np.ndarray) -> np.ndarray:
    """Batched rigid inverse of (M,4,4) transforms: ``[[R^T, -R^T t], [0, 1]]``."""
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(T[:, :3, :3], 1, 2)
    Ti[:, :3, :3] = Rt
    Ti[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    Ti[:, 3, 3] = 1.0
    return Ti


def _json_float(value: float) -> float | None:
    """A float for JSON: ``None`` for NaN/inf (JSON has no such numbers)."""
    value = float(value)
    return value if math.isfinite(value) else None


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
            "rmse_m": _json_float(self.rmse_m),
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


# --------------------------------------------------------------------------------------------
# Trajectory metrics
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ErrorStats:
    """Summary of a vector of non-negative errors ``e`` (units of the errors).

    ``rmse = sqrt(mean(e^2))``; ``mean``, ``median``, ``max``; ``n = len(e)``.
    """

    rmse: float
    mean: float
    median: float
    max: float
    n: int

    @classmethod
    def from_errors(cls, errors: np.ndarray) -> ErrorStats:
        """Summarize (M,) errors, M >= 1."""
        e = np.asarray(errors, dtype=np.float64)
        return cls(
            rmse=float(np.sqrt(np.mean(e * e))),
            mean=float(e.mean()),
            median=float(np.median(e)),
            max=float(e.max()),
            n=int(e.size),
        )

    def as_dict(self) -> dict[str, float | int]:
        """JSON-ready dict."""
        return {"rmse": self.rmse, "mean": self.mean, "median": self.median, "max": self.max, "n": self.n}


def umeyama(
    source_xyz: np.ndarray, target_xyz: np.ndarray, *, with_scale: bool = True
) -> tuple[np.ndarray, float]:
    """Similarity ``(c, R, t)`` minimising ``sum_i |y_i - (c R x_i + t)|^2`` (Umeyama 1991).

    With ``x`` = source and ``y`` = target rows, ``mu`` their means, ``n`` the row count:

    .. math::

        \\Sigma = \\tfrac{1}{n} \\sum_i (y_i - \\mu_y)(x_i - \\mu_x)^T = U D V^T, \\quad
        S = \\mathrm{diag}(1, 1, \\det U \\det V)

        R = U S V^T, \\quad
        c = \\frac{\\mathrm{tr}(D S)}{\\sigma_x^2}, \\quad
        \\sigma_x^2 = \\tfrac{1}{n}\\sum_i |x_i - \\mu_x|^2, \\quad
        t = \\mu_y - c R \\mu_x

    (eqs. 40-42 of the paper; ``c = 1`` when ``with_scale`` is False).

    Parameters
    ----------
    source_xyz, target_xyz : (N,3) float64 corresponding rows, N >= 3.
    with_scale : estimate ``c`` (Sim(3)); otherwise a rigid SE(3) fit.

    Returns
    -------
    T_target_source : (4,4) float64 ``[[c R, t], [0, 1]]``.
    scale : float ``c``.

    Raises
    ------
    InvalidCloudError
        Mismatched shapes, fewer than 3 rows, or a source with no spread (all rows equal).
    """
    x = _points(source_xyz, "source")
    y = _points(target_xyz, "target")
    if x.shape != y.shape or x.shape[0] < 3:
        raise InvalidCloudError(f"umeyama needs two (N,3) arrays with N >= 3, got {x.shape} and {y.shape}")
    mu_x = x.mean(axis=0)
    mu_y = y.mean(axis=0)
    xc = x - mu_x
    yc = y - mu_y
    var_x = float(np.mean(np.einsum("ij,ij->i", xc, xc)))
    if var_x <= 0.0:
        raise InvalidCloudError("umeyama: all source points coincide; the alignment is undefined")
    U, D, Vt = np.linalg.svd(yc.T @ xc / x.shape[0])
    S = np.array([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
    R = (U * S) @ Vt
    scale = float(D @ S / var_x) if with_scale else 1.0
    T = np.eye(4)
    T[:3, :3] = scale * R
    T[:3, 3] = mu_y - scale * R @ mu_x
    return T, scale


@dataclass(frozen=True)
class AteResult:
    """Result of :func:`ate`.

    Attributes
    ----------
    translation_m : statistics of the per-pose position errors, metres.
    align : the alignment used (``"se3"``, ``"sim3"`` or ``"none"``).
    T_reference_estimate : (4,4) the alignment ``[[c R, t], [0, 1]]`` applied to the estimate.
    scale : ``c`` (1 unless ``align == "sim3"``).
    """

    translation_m: ErrorStats
    align: str
    T_reference_estimate: np.ndarray
    scale: float

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return {
            "align": self.align,
            "translation_m": self.translation_m.as_dict(),
            "scale": self.scale,
            "T_reference_estimate": self.T_reference_estimate.tolist(),
        }


def ate(reference: np.ndarray, estimate: np.ndarray, *, align: AlignMode = "se3") -> AteResult:
    """Absolute trajectory error of positions after aligning the estimate to the reference.

    With reference positions ``q_i`` and estimate positions ``p_i`` (translation columns):

    .. math::  e_i = | q_i - (c R p_i + t) |

    where ``(c, R, t)`` minimises ``sum_i e_i^2``: ``"se3"`` a rigid fit (``c = 1``, Kabsch,
    :func:`core.svd.kabsch`), ``"sim3"`` a similarity (:func:`umeyama` with scale, for monocular
    or scale-drifting estimates), ``"none"`` the identity. This is evo's ``APE`` with
    ``PoseRelation.translation_part`` after ``align(correct_scale=...)``.

    Parameters
    ----------
    reference, estimate : (N,4,4) float64 world<-sensor poses, row-aligned (N >= 3 to align).
    align : ``"se3"`` (default), ``"sim3"`` or ``"none"``.

    Returns
    -------
    AteResult
        ``translation_m`` holds RMSE / mean / median / max of ``e_i`` in metres.
    """
    if align not in ("se3", "sim3", "none"):
        raise ValueError(f"align must be 'se3', 'sim3' or 'none', got {align!r}")
    Q, P = _pose_pair(reference, estimate, 1 if align == "none" else 3)
    q = Q[:, :3, 3]
    p = P[:, :3, 3]
    if align == "se3":
        T, scale = kabsch(p, q), 1.0
    elif align == "sim3":
        T, scale = umeyama(p, q, with_scale=True)
    else:
        T, scale = np.eye(4), 1.0
    errors = np.linalg.norm(q - transform_points(T, p), axis=1)
    stats = ErrorStats.from_errors(errors)
    logger.debug("ATE (%s, scale %.6f): rmse %.4f m over %d poses", align, scale, stats.rmse, stats.n)
    return AteResult(translation_m=stats, align=align, T_reference_estimate=T, scale=scale)


@dataclass(frozen=True)
class RpeResult:
    """Result of :func:`rpe`.

    Attributes
    ----------
    delta : frame gap of the pairs.
    translation_m : statistics of ``|t(E_i)|``, metres.
    rotation_deg : statistics of ``angle(R(E_i))``, degrees.
    """

    delta: int
    translation_m: ErrorStats
    rotation_deg: ErrorStats

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return {
            "delta": self.delta,
            "translation_m": self.translation_m.as_dict(),
            "rotation_deg": self.rotation_deg.as_dict(),
        }


def rpe(reference: np.ndarray, estimate: np.ndarray, *, delta: int = 1, all_pairs: bool = False) -> RpeResult:
    """Relative pose error over a gap of ``delta`` frames (evo's RPE definition).

    For each pair ``(i, j = i + delta)``, with reference ``Q`` and estimate ``P``:

    .. math::

        E_i = \\big(Q_i^{-1} Q_j\\big)^{-1} \\big(P_i^{-1} P_j\\big), \\quad
        e^t_i = |t(E_i)| \\;[\\mathrm{m}], \\quad
        e^r_i = \\angle R(E_i) \\;[\\mathrm{deg}]

    and the RMSE (plus mean, median, max) of each. As evo with ``all_pairs=False``, the pairs are
    consecutive and non-overlapping, ``i = 0, delta, 2 delta, ...`` while ``j < N``;
    ``all_pairs=True`` uses every ``i`` with ``i + delta < N``. No alignment is needed (the error
    is invariant to a rigid transform of either trajectory).

    Parameters
    ----------
    reference, estimate : (N,4,4) float64 world<-sensor poses, row-aligned, N > delta.
    delta : frame gap, >= 1.
    all_pairs : overlapping pairs instead of consecutive ones.

    Returns
    -------
    RpeResult
        ``translation_m.rmse`` (m) and ``rotation_deg.rmse`` (deg) are the usual headline values.
    """
    if int(delta) != delta or delta < 1:
        raise ValueError(f"delta must be an integer >= 1, got {delta}")
    delta = int(delta)
    Q, P = _pose_pair(reference, estimate, delta + 1)
    n = Q.shape[0]
    i = np.arange(n - delta) if all_pairs else np.arange(0, n - delta, delta)
    j = i + delta
    rel_q = _invert_rigid(Q[i]) @ Q[j]
    rel_p = _invert_rigid(P[i]) @ P[j]
    E = _invert_rigid(rel_q) @ rel_p
    t_err = np.linalg.norm(E[:, :3, 3], axis=1)
    r_err = np.degrees(Rotation.from_matrix(E[:, :3, :3]).magnitude())
    result = RpeResult(
        delta=delta,
        translation_m=ErrorStats.from_errors(t_err),
        rotation_deg=ErrorStats.from_errors(r_err),
    )
    logger.debug(
        "RPE (delta %d, %d pairs): %.4f m, %.4f deg RMSE",
        delta,
        i.size,
        result.translation_m.rmse,
        result.rotation_deg.rmse,
    )
    return result


@dataclass(frozen=True)
class KittiLengthError:
    """KITTI errors of the segments of one nominal length (NaN values when ``n_segments == 0``)."""

    length_m: float
    translation_pct: float
    rotation_deg_per_100m: float
    n_segments: int

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict (NaN becomes ``None``)."""
        return {
            "length_m": self.length_m,
            "translation_pct": _json_float(self.translation_pct),
            "rotation_deg_per_100m": _json_float(self.rotation_deg_per_100m),
            "n_segments": self.n_segments,
        }


@dataclass(frozen=True)
class KittiResult:
    """Result of :func:`kitti_relative_errors`.

    Attributes
    ----------
    translation_pct : mean over all segments of ``t_err``, in percent.
    rotation_deg_per_100m : mean over all segments of ``r_err``, in degrees per 100 m.
    per_length : one :class:`KittiLengthError` per requested length, in the given order.
    segment_first, segment_last : (S,) int64 first and last frame of each segment.
    segment_length_m : (S,) float64 nominal length of each segment.
    segment_t_err : (S,) float64 translation error per metre (m/m, the devkit's unit).
    segment_r_err : (S,) float64 rotation error per metre (rad/m, the devkit's unit).
    """

    translation_pct: float
    rotation_deg_per_100m: float
    per_length: tuple[KittiLengthError, ...]
    segment_first: np.ndarray
    segment_last: np.ndarray
    segment_length_m: np.ndarray
    segment_t_err: np.ndarray
    segment_r_err: np.ndarray

    @property
    def n_segments(self) -> int:
        """Number of segments averaged."""
        return int(self.segment_first.size)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the per-segment arrays are left out)."""
        return {
            "translation_pct": self.translation_pct,
            "rotation_deg_per_100m": self.rotation_deg_per_100m,
            "n_segments": self.n_segments,
            "per_length": [entry.as_dict() for entry in self.per_length],
        }


def _path_distances(poses: np.ndarray) -> np.ndarray:
    """(N,) cumulative travelled distance along the positions, ``dist[0] = 0``, metres."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def _kitti_rotation_error(pose_error: np.ndarray) -> np.ndarray:
    """(S,) devkit rotation angle, rad: ``acos(clip((trace(R) - 1) / 2, -1, 1))``."""
    trace = np.trace(pose_error[:, :3, :3], axis1=1, axis2=2)
    return np.arccos(np.clip(0.5 * (trace - 1.0), -1.0, 1.0))


def kitti_relative_errors(
    reference: np.ndarray,
    estimate: np.ndarray,
    *,
    lengths: Sequence[float] = KITTI_LENGTHS_M,
    step: int = 10,
) -> KittiResult:
    """Translation (%) and rotation (deg/100 m) drift of the KITTI odometry devkit.

    Follows ``calcSequenceErrors`` of the devkit's ``evaluate_odometry.cpp``:

    1. ``dist[k]`` = cumulative path length of the REFERENCE positions up to frame ``k``.
    2. For every ``first`` in ``0, step, 2 step, ...`` and every length ``L``, ``last`` is the
       first frame with ``dist[last] > dist[first] + L``; no such frame, no segment.
    3. With ``G`` = reference and ``E`` = estimate (general 4x4 inverses, as the devkit's
       ``Matrix::inv``)::

           delta_gt   = inv(G[first]) @ G[last]
           delta_est  = inv(E[first]) @ E[last]
           pose_error = inv(delta_est) @ delta_gt
           t_err = |t(pose_error)| / L                                    (m/m)
           r_err = acos(clip((trace(R(pose_error)) - 1) / 2, -1, 1)) / L   (rad/m)

    4. The sequence errors are the plain means of ``t_err`` and ``r_err`` over all segments
       (every length pooled), reported as ``100 * mean(t_err)`` percent and
       ``mean(r_err) * 180/pi * 100`` degrees per 100 m; ``per_length`` gives the same means
       over the segments of each length.

    The devkit computes in float32; this computes in float64, so values agree to float32
    precision and a segment end could differ only where ``dist`` ties ``dist[first] + L``
    within float32 rounding.

    Parameters
    ----------
    reference, estimate : (N,4,4) float64 world<-sensor poses, row-aligned (KITTI frames are
        10 Hz, so ``step = 10`` starts a segment every second).
    lengths : segment lengths, metres (> 0); default 100, 200, ..., 800.
    step : frame stride between segment starts, >= 1.

    Returns
    -------
    KittiResult

    Raises
    ------
    InvalidCloudError
        Bad pose stacks, or a reference path not longer than the shortest segment length
        (no segment at all).
    ValueError
        Empty or non-positive ``lengths``, or ``step < 1``.
    """
    lengths_arr = np.asarray(lengths, dtype=np.float64).reshape(-1)
    if lengths_arr.size == 0 or not np.all(np.isfinite(lengths_arr)) or np.any(lengths_arr <= 0.0):
        raise ValueError(f"lengths must be a non-empty sequence of positive metres, got {list(lengths)}")
    if int(step) != step or step < 1:
        raise ValueError(f"step must be an integer >= 1, got {step}")
    G, E = _pose_pair(reference, estimate, 2)
    n = G.shape[0]
    dist = _path_distances(G)
    shortest = float(lengths_arr.min())
    if not dist[-1] > shortest:
        raise InvalidCloudError(
            f"reference path is {dist[-1]:.2f} m long; KITTI errors need a path longer than the "
            f"shortest segment length ({shortest:g} m)"
        )

    firsts = np.arange(0, n, int(step))
    seg_first, seg_last, seg_len = [], [], []
    for length in lengths_arr:  # a handful of lengths; frames are vectorized
        last = np.searchsorted(dist, dist[firsts] + length, side="right")
        ok = last < n
        seg_first.append(firsts[ok])
        seg_last.append(last[ok])
        seg_len.append(np.full(int(ok.sum()), length))
    first_idx = np.concatenate(seg_first).astype(np.int64)
    last_idx = np.concatenate(seg_last).astype(np.int64)
    seg_length = np.concatenate(seg_len)

    delta_gt = np.linalg.inv(G[first_idx]) @ G[last_idx]
    delta_est = np.linalg.inv(E[first_idx]) @ E[last_idx]
    pose_error = np.linalg.inv(delta_est) @ delta_gt
    t_err = np.linalg.norm(pose_error[:, :3, 3], axis=1) / seg_length
    r_err = _kitti_rotation_error(pose_error) / seg_length

    to_deg_per_100m = 180.0 / math.pi * 100.0  # rad/m -> deg/100 m
    per_length = []
    for length in lengths_arr:
        sel = seg_length == length
        count = int(sel.sum())
        t_pct = float(100.0 * t_err[sel].mean()) if count else math.nan
        r_deg = float(r_err[sel].mean() * to_deg_per_100m) if count else math.nan
        per_length.append(
            KittiLengthError(
                length_m=float(length), translation_pct=t_pct, rotation_deg_per_100m=r_deg, n_segments=count
            )
        )
    result = KittiResult(
        translation_pct=float(100.0 * t_err.mean()),
        rotation_deg_per_100m=float(r_err.mean() * to_deg_per_100m),
        per_length=tuple(per_length),
        segment_first=first_idx,
        segment_last=last_idx,
        segment_length_m=seg_length,
        segment_t_err=t_err,
        segment_r_err=r_err,
    )
    logger.debug(
        "KITTI errors over %d segments: %.4f %%, %.4f deg/100 m",
        result.n_segments,
        result.translation_pct,
        result.rotation_deg_per_100m,
    )
    return result


def evaluate_trajectory(reference: np.ndarray, estimate: np.ndarray) -> dict[str, Any]:
    """ATE (SE(3)-aligned), RPE (delta 1 frame) and, if the path allows, the KITTI errors.

    Parameters
    ----------
    reference, estimate : (N,4,4) float64 world<-sensor poses, row-aligned, N >= 3.

    Returns
    -------
    dict
        JSON-ready (plain floats, ints, lists, ``None``)::

            {"n_poses": int, "path_length_m": float,
             "ate": AteResult.as_dict(), "rpe": RpeResult.as_dict(),
             "kitti": KittiResult.as_dict() or None, "notes": [str, ...]}

        ``kitti`` is ``None`` (with a note) when the reference path is not longer than 100 m.
    """
    Q, P = _pose_pair(reference, estimate, 3)
    path_length = float(_path_distances(Q)[-1])
    notes: list[str] = []
    kitti: dict[str, Any] | None = None
    if path_length > KITTI_LENGTHS_M[0]:
        kitti = kitti_relative_errors(Q, P).as_dict()
    else:
        notes.append(
            f"KITTI errors skipped: the reference path is {path_length:.2f} m, not longer than the "
            f"shortest segment ({KITTI_LENGTHS_M[0]:g} m)"
        )
    return {
        "n_poses": int(Q.shape[0]),
        "path_length_m": path_length,
        "ate": ate(Q, P, align="se3").as_dict(),
        "rpe": rpe(Q, P, delta=1).as_dict(),
        "kitti": kitti,
        "notes": notes,
    }
