"""Register a moving scan to a reference, the RANDT way or with a baseline.

The whole pipeline in one screen (:func:`register`)::

    sanitize  -> drop non-finite points (counted), reject empty / too small / wrong-shape clouds
    levels    -> NDT voxel sizes, coarse to fine (given, or derived from the target's scale)
    reference -> downsample; Algorithm 1: IQR outlier removal on Mahalanobis distances; Gaussians
    moving    -> downsample; Algorithm 1: keep only high-probability moving points
    match     -> per level: Newton on the NDT cost (randt.core.ndt) from the previous level's pose
    refine    -> Algorithm 3: SVD on high-probability correspondences, kept only if NDT agrees
    judge     -> fitness as Autoware reports it, inlier ratio, covariance from the Hessian,
                 degeneracy test; never the initial guess dressed up as a result

Baselines share every stage they can: ``ndt`` is the same solver without outlier removal, moving
point selection or the SVD step; ``icp-point`` and ``icp-plane`` replace the NDT solver. Each
stage and why: docs/registration.md.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from randt.core.config import Method, RegistrationSettings
from randt.core.errors import DegenerateProblemError, InvalidCloudError, RegistrationFailedError
from randt.core.grid import PointGrid
from randt.core.icp import icp_point_to_plane, icp_point_to_point
from randt.core.kernels import best_voxel, group_moments, plane_information, projected_pair_moments
from randt.core.ndt import (
    NdtEvaluation,
    NeighborCache,
    about_origin,
    apply_update_about,
    ndt_constants,
    ndt_derivatives,
    ndt_newton,
    ndt_point_scores,
)
from randt.core.outliers import iqr_inlier_mask, statistical_outlier_mask, tukey_fences
from randt.core.transforms import (
    as_transform,
    invert,
    orthonormalize,
    rotation_angle_deg,
    so3_log,
    transform_points,
    umeyama,
)
from randt.core.voxel import (
    NEIGHBOR_OFFSETS,
    VoxelGaussianMap,
    merge_moments,
    pack_keys,
    stratified_subsample,
    voxel_coords,
    voxel_downsample,
    voxel_groups,
)

__all__ = [
    "PreparedReference",
    "ReferencePiece",
    "RegistrationResult",
    "auto_voxel_sizes",
    "centroid_start",
    "inlier_ratio",
    "is_sparse_cloud",
    "join_reference",
    "prepare_reference",
    "reference_inlier_mask",
    "reference_piece",
    "register",
    "sanitize_points",
]

log = logging.getLogger(__name__)

#: 99 % quantile of the chi-square distribution with 3 degrees of freedom: a moving point whose
#: squared Mahalanobis distance to its best voxel is below this counts as an inlier.
CHI2_3DOF_99 = 11.3449


@dataclass(frozen=True)
class RegistrationResult:
    """Everything a caller needs to judge a registration, not just the matrix.

    Attributes
    ----------
    T_target_source : (4,4) maps source points into the target frame.
    converged : the solver met its convergence criteria at every level.
    iterations : solver iterations summed over levels (plus SVD iterations).
    transform_probability : Autoware's TP: NDT score per moving point at the finest level.
    nearest_voxel_transformation_likelihood : Autoware's NVTL: mean best-voxel score of the
        moving points that have a voxel nearby.
    inlier_ratio : share of moving points whose squared Mahalanobis distance to the best voxel is
        below the chi-square(3) 99 % quantile (11.34).
    covariance : (6,6) pose covariance, order (tx, ty, tz, rx, ry, rz), the inverse Hessian of the
        NDT negative log-likelihood at the solution (Laplace approximation). Points are treated as
        independent, so it is optimistic; compare it between scans rather than read it absolutely.
    """

    T_target_source: np.ndarray
    converged: bool
    iterations: int
    transform_probability: float
    nearest_voxel_transformation_likelihood: float
    inlier_ratio: float
    covariance: np.ndarray
    method: str
    voxel_sizes_m: tuple[float, ...]
    n_source_points: int
    n_target_points: int
    n_source_used: int
    n_nonfinite_dropped: int
    svd_accepted: bool
    stage_times_s: dict[str, float] = field(default_factory=dict)
    message: str = ""

    @property
    def fitness(self) -> float:
        """The single fitness number: NVTL (higher is better; 0 means no overlap)."""
        return self.nearest_voxel_transformation_likelihood

    @property
    def time_s(self) -> float:
        return float(sum(self.stage_times_s.values()))

    def to_dict(self) -> dict[str, object]:
        """JSON-ready summary (the ``randt register --json`` object)."""
        return {
            "T_target_source": self.T_target_source.tolist(),
            "converged": self.converged,
            "iterations": self.iterations,
            "fitness": self.fitness,
            "transform_probability": self.transform_probability,
            "nearest_voxel_transformation_likelihood": self.nearest_voxel_transformation_likelihood,
            "inlier_ratio": self.inlier_ratio,
            "time_s": self.time_s,
            "method": self.method,
            "voxel_sizes_m": list(self.voxel_sizes_m),
            "covariance": self.covariance.tolist(),
            "n_source_points": self.n_source_points,
            "n_target_points": self.n_target_points,
            "n_nonfinite_dropped": self.n_nonfinite_dropped,
            "svd_accepted": self.svd_accepted,
            "stage_times_s": self.stage_times_s,
            "message": self.message,
        }


def sanitize_points(points: npt.ArrayLike | None, *, name: str, min_points: int) -> tuple[np.ndarray, int]:
    """Return ``(finite (N,3) float64 points, number of non-finite rows dropped)``.

    Accepts (N,3) or (N,>=4) arrays (extra columns such as intensity are ignored).
    """
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise InvalidCloudError(f"{name}: expected an (N,3) array of points, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise InvalidCloudError(f"{name}: points must be numeric, got dtype {arr.dtype}")
    xyz = np.ascontiguousarray(arr[:, :3], dtype=np.float64)
    n_bad = 0
    # Any NaN or inf makes the sum non-finite (a finite sum proves every point finite); only then,
    # or when a huge finite sum overflows, check point by point.
    if not np.isfinite(np.add.reduce(xyz, axis=None)):
        finite = np.isfinite(xyz).all(axis=1)
        n_bad = int(xyz.shape[0] - finite.sum())
        if n_bad:
            xyz = xyz[finite]
    if xyz.shape[0] < min_points:
        raise InvalidCloudError(
            f"{name}: {xyz.shape[0]} finite points (after dropping {n_bad} non-finite), "
            f"need at least {min_points}"
        )
    return xyz, n_bad


def centroid_start(source_xyz: npt.ArrayLike, target_xyz: npt.ArrayLike) -> np.ndarray:
    """An initial guess for two views of one object with no better one: the translation that
    moves the source's centroid onto the target's (no rotation).

    For object scans and CAD samples posed far apart (the ModelNet40 protocol: up to 0.5 of the
    object's radius per axis), NDT from the identity can start outside its basin
    (docs/registration.md, "Inputs and errors"). Not for LiDAR sweeps: a sweep's centroid moves
    with what it sees, while the sensor's origin is a far better guess. Non-finite rows are
    ignored.
    """
    src, _ = sanitize_points(source_xyz, name="source", min_points=1)
    tgt, _ = sanitize_points(target_xyz, name="target", min_points=1)
    T = np.eye(4)
    T[:3, 3] = tgt.mean(axis=0) - src.mean(axis=0)
    return T


#: Points :func:`auto_voxel_sizes` measures a large cloud's scale on.
_SCALE_SAMPLE = 20_000


def auto_voxel_sizes(points_xyz: np.ndarray) -> tuple[float, ...]:
    """Four NDT levels (8r, 4r, 2r, r) from the cloud's scale.

    ``r`` is the median distance of the points from their median point divided by 12, rounded to
    one significant digit: about 1 m for a KITTI sweep, 0.5 m indoors, 4 mm for a bunny scan.
    Clouds of more than :data:`_SCALE_SAMPLE` points are measured on that many points drawn with
    a fixed seed (close to the whole cloud's scale at a fraction of the time; a stride would be
    biased on organized clouds).

    A sparse cloud (fewer than :data:`_SPARSE_POINTS_PER_VOXEL` points per occupied voxel of
    ``r`` by the mean, such as 1024 points sampled on a ModelNet40 object) gets ``r`` doubled
    until its voxels hold :data:`_DENSE_POINTS_PER_VOXEL` by the mean: otherwise too few voxels
    hold the points a Gaussian needs. Real scans are left as they are (docs/registration.md,
    "Levels").
    """
    r, spread = _scale_r(points_xyz)
    if is_sparse_cloud(points_xyz, r):
        while _points_per_voxel(points_xyz, r) < _DENSE_POINTS_PER_VOXEL and r < spread:
            r *= 2.0
    return (8 * r, 4 * r, 2 * r, r)


def _scale_r(points_xyz: np.ndarray) -> tuple[float, float]:
    """:func:`auto_voxel_sizes`'s ``r`` from the cloud's scale (before any growth), and the spread."""
    n = points_xyz.shape[0]
    sample = points_xyz
    if n > _SCALE_SAMPLE:
        sample = points_xyz[np.random.default_rng(0).integers(0, n, _SCALE_SAMPLE)]
    centre = np.median(sample, axis=0)
    spread = float(np.median(np.linalg.norm(sample - centre, axis=1)))
    if spread <= 0:
        raise InvalidCloudError("cloud has no spatial extent (all points coincide)")
    r = spread / 12.0
    exp = np.floor(np.log10(r))
    return float(np.round(r / 10**exp) * 10**exp), spread


def is_sparse_cloud(points_xyz: np.ndarray, r: float | None = None) -> bool:
    """A cloud of at most :data:`_SCALE_SAMPLE` points holding fewer than
    :data:`_SPARSE_POINTS_PER_VOXEL` per occupied voxel of its scale's ``r``
    (:func:`auto_voxel_sizes`): 1024 points sampled on a ModelNet40 object, not any real scan of
    the shared data (2.9 to 21)."""
    if points_xyz.shape[0] > _SCALE_SAMPLE or points_xyz.shape[0] == 0:
        return False
    if r is None:
        try:
            r = _scale_r(points_xyz)[0]
        except InvalidCloudError:
            return False
    return _points_per_voxel(points_xyz, r) < _SPARSE_POINTS_PER_VOXEL


#: :func:`auto_voxel_sizes`: a cloud with fewer points than this per occupied voxel of its scale's
#: ``r`` is sparse, and its ``r`` grows until its voxels hold :data:`_DENSE_POINTS_PER_VOXEL`.
_SPARSE_POINTS_PER_VOXEL = 2.0
_DENSE_POINTS_PER_VOXEL = 8.0


def _points_per_voxel(points_xyz: np.ndarray, voxel_m: float) -> float:
    """The mean number of points per occupied voxel of ``voxel_m``."""
    keys = pack_keys(voxel_coords(points_xyz, voxel_m))
    return float(points_xyz.shape[0] / max(1, np.unique(keys).size))


#: Local planes of the SVD step come from neighbours at most this many finest voxels away. One
#: voxel leaves sparse scans (the car pair) short of neighbours, so that the SVD step fails its
#: acceptance test; two voxels match the unbounded k-NN normals (docs/registration.md, "Algorithm 3").
NORMAL_RADIUS_VOXELS = 2.0


@dataclass(frozen=True)
class PreparedReference:
    """A reference cloud made ready for repeated registration: filtered points and NDT pyramid.

    Its KD-tree and the surface normals the SVD step asks for are computed on first use and kept,
    so an incremental matcher pays for them once per keyframe, not once per sweep.
    """

    points_xyz: np.ndarray
    maps: tuple[VoxelGaussianMap, ...]
    n_input_points: int
    n_removed_outliers: int
    #: The downsampled reference before outlier removal (the SVD step's partners unless
    #: ``svd_on_filtered_points``); ``None`` when kept for no SVD step (:func:`prepare_reference`).
    unfiltered_xyz: np.ndarray | None = None

    @property
    def voxel_sizes_m(self) -> tuple[float, ...]:
        return tuple(m.voxel_size_m for m in self.maps)

    @cached_property
    def unfiltered(self) -> PreparedReference:
        """This reference with :attr:`unfiltered_xyz` as its points (itself when nothing was
        removed or nothing kept): the SVD step's partners, grid and normals."""
        if self.unfiltered_xyz is None or self.unfiltered_xyz is self.points_xyz:
            return self
        return PreparedReference(self.unfiltered_xyz, self.maps, self.n_input_points, 0)

    @cached_property
    def kdtree(self) -> cKDTree:
        """KD-tree over :attr:`points_xyz` (built on first use)."""
        return cKDTree(self.points_xyz)

    @cached_property
    def grid(self) -> PointGrid:
        """Hashed grid over :attr:`points_xyz`, cells one finest voxel wide (built on first use)."""
        return PointGrid.build(self.points_xyz, self.maps[-1].voxel_size_m)

    @cached_property
    def _normal_cache(self) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        return {}

    def normals_at(self, index: np.ndarray, k: int = 16) -> tuple[np.ndarray, np.ndarray]:
        """Unit surface normals at ``points_xyz[index]`` and whether each exists, computed once each.

        A normal comes from up to ``k`` nearest reference points within
        :data:`NORMAL_RADIUS_VOXELS` finest voxels (:meth:`PointGrid.normals`, Open3D's hybrid
        search); fewer than 5 such points leave none.
        """
        if k not in self._normal_cache:
            n = self.points_xyz.shape[0]
            self._normal_cache[k] = (np.zeros((n, 3)), np.zeros(n, dtype=bool), np.zeros(n, dtype=bool))
        normals, valid, known = self._normal_cache[k]
        need = np.unique(index[~known[index]])
        if need.size:
            normals[need], valid[need] = self.grid.normals(
                need, k, NORMAL_RADIUS_VOXELS * self.grid.cell_size_m
            )
            known[need] = True
        return normals[index], valid[index]


def prepare_reference(
    target_xyz: np.ndarray,
    settings: RegistrationSettings,
    voxel_sizes_m: tuple[float, ...],
    *,
    downsampled_at_m: float | None = None,
    keep_unjudged: bool = False,
) -> PreparedReference:
    """Downsample the reference, remove outliers (IQR, SOR or none) and build the NDT pyramid.

    ``keep_unjudged``: Algorithm 1 keeps the points of voxels too sparse for a Gaussian, for a
    sparse cloud (:func:`is_sparse_cloud`; :func:`register` decides it once per call): there they
    say nothing about their points (it would drop the thin parts of a ModelNet40 object first).

    ``downsampled_at_m``: the voxel size ``target_xyz`` was already downsampled at (by
    :func:`~randt.core.voxel.voxel_downsample`). When it equals this reference's downsampling voxel,
    downsampling again would return the same points (one centroid per voxel, first-seen order),
    so it is skipped: the incremental matcher's fused model is built that way.
    """
    finest = voxel_sizes_m[-1]
    voxel = finest * settings.target_voxel_fraction
    if downsampled_at_m is not None and abs(downsampled_at_m - voxel) <= 1e-9 * voxel:
        pts = np.ascontiguousarray(target_xyz, dtype=np.float64)
    else:
        pts = voxel_downsample(target_xyz, voxel)
    n_in = pts.shape[0]
    keep = reference_inlier_mask(pts, settings, finest, keep_unjudged=keep_unjudged)
    unfiltered = pts if settings.svd_refinement and not settings.svd_on_filtered_points else None
    if not keep.all():
        pts = np.compress(keep, pts, axis=0)
    maps = VoxelGaussianMap.build_pyramid(
        pts,
        voxel_sizes_m,
        min_points_per_voxel=settings.min_points_per_voxel,
        eigenvalue_ratio=settings.eigenvalue_ratio,
    )
    return PreparedReference(pts, maps, n_in, n_in - pts.shape[0], unfiltered)


@dataclass(frozen=True)
class ReferencePiece:
    """A part of a reference (one map tile, say) made ready to be joined with others
    (:func:`join_reference`): its points downsampled as :func:`prepare_reference` does and their
    moments at the finest NDT voxel. A window of a map moved by a few tiles is joined from the
    pieces it kept and the few new ones: only those are downsampled and grouped again."""

    voxel_sizes_m: tuple[float, ...]
    points_xyz: np.ndarray
    keys: np.ndarray
    counts: np.ndarray
    means: np.ndarray
    scatter: np.ndarray
    n_input_points: int


def reference_piece(
    target_xyz: np.ndarray,
    settings: RegistrationSettings,
    voxel_sizes_m: tuple[float, ...],
    *,
    downsample: bool = True,
) -> ReferencePiece:
    """One piece of a reference for :func:`join_reference` (no outlier removal: the pieces' points
    are judged nowhere, as ``outlier_removal="none"`` has them). Pieces cut on boundaries that are
    multiples of the downsampling voxel and of the finest NDT voxel join into exactly the
    reference :func:`prepare_reference` makes of them all; elsewhere a voxel cut by a boundary
    keeps a centroid on each side and its moments are combined (:func:`~randt.core.voxel.merge_moments`).

    ``downsample`` false: the points are taken as they are (a map's tiles, whose density is
    equalized already: the downsample was most of a piece's cost), and the piece keeps
    their finest voxels' means as its points (float32): a prepared reference's points serve its
    counts and the baselines, NDT reads its moments, and a piece crosses to a matcher process
    (a tenth of the tile's points)."""
    sizes = tuple(float(v) for v in voxel_sizes_m)
    finest = min(sizes)
    if np.asarray(target_xyz).shape[0] == 0:
        return ReferencePiece(
            sizes, np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)),
            np.zeros((0, 3, 3)), 0,
        )  # fmt: skip
    if downsample:
        pts = voxel_downsample(target_xyz, finest * settings.target_voxel_fraction)
    else:
        pts = np.ascontiguousarray(target_xyz, dtype=np.float64)
    inverse, keys, _ = voxel_groups(pts, finest)
    counts, means, scatter = group_moments(pts, inverse, keys.size)
    kept = pts if downsample else means.astype(np.float32)
    return ReferencePiece(sizes, kept, keys, counts, means, scatter, pts.shape[0])


def join_reference(pieces: list[ReferencePiece], settings: RegistrationSettings) -> PreparedReference:
    """The reference of all ``pieces`` (:func:`reference_piece`, all at the same voxel sizes):
    their points, and the NDT pyramid from their finest moments (sizes that do not nest by powers
    of two: from their points).

    Raises
    ------
    ValueError
        No piece, pieces at different voxel sizes, or settings that judge the reference's points
        (``outlier_removal`` other than ``"none"``: its fences are the whole reference's).
    InvalidCloudError
        Too few points for the voxel sizes (as :func:`prepare_reference`).
    """
    if not pieces:
        raise ValueError("no piece to join")
    sizes = pieces[0].voxel_sizes_m
    if any(p.voxel_sizes_m != sizes for p in pieces):
        raise ValueError("the pieces were prepared at different voxel sizes")
    if settings.outlier_removal != "none":
        raise ValueError(f"pieces are joined without outlier removal, not {settings.outlier_removal!r}")
    pts = np.concatenate([p.points_xyz for p in pieces])
    finest = min(sizes)
    if pts.shape[0] == 0:
        raise InvalidCloudError("the reference has no points")
    moments = merge_moments(
        np.concatenate([p.keys for p in pieces]),
        np.concatenate([p.counts for p in pieces]),
        np.concatenate([p.means for p in pieces]),
        np.concatenate([p.scatter for p in pieces]),
    )
    min_points, ratio = settings.min_points_per_voxel, settings.eigenvalue_ratio
    if all(abs(v - finest * 2.0 ** round(np.log2(v / finest))) <= 1e-9 * v for v in sizes):
        maps = VoxelGaussianMap.pyramid_from_moments(
            moments, finest, sizes, min_points_per_voxel=min_points, eigenvalue_ratio=ratio
        )
    else:
        maps = VoxelGaussianMap.build_pyramid(
            pts, sizes, min_points_per_voxel=min_points, eigenvalue_ratio=ratio
        )
    n_in = sum(p.n_input_points for p in pieces)
    unfiltered = pts if settings.svd_refinement and not settings.svd_on_filtered_points else None
    return PreparedReference(pts, maps, n_in, 0, unfiltered)


def reference_inlier_mask(
    points_xyz: np.ndarray,
    settings: RegistrationSettings,
    finest_m: float,
    *,
    keep_unjudged: bool = False,
    groups: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """The reference's outlier removal as the settings choose: Algorithm 1 (``"iqr"``, with
    Gaussians at the finest NDT voxel ``finest_m``), SOR, or none (all True). ``keep_unjudged``:
    Algorithm 1 keeps the points of voxels too sparse for a Gaussian instead of dropping them
    (a sparse cloud, :func:`is_sparse_cloud`). ``groups``: the points' finest voxels when the
    caller has them (:func:`randt.core.outliers.iqr_inlier_mask`)."""
    if settings.outlier_removal == "iqr":
        return _algorithm1_mask(points_xyz, finest_m, settings, keep_unjudged=keep_unjudged, groups=groups)
    if settings.outlier_removal == "sor":
        return statistical_outlier_mask(points_xyz)
    return np.ones(points_xyz.shape[0], dtype=bool)


def _algorithm1_mask(
    points_xyz: np.ndarray,
    voxel_size_m: float,
    settings: RegistrationSettings,
    *,
    keep_unjudged: bool = False,
    groups: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Algorithm 1's inlier mask with the settings' fence, voxel and quartile rules."""
    return iqr_inlier_mask(
        points_xyz,
        voxel_size_m,
        k=settings.iqr_k,
        min_points_per_voxel=settings.min_points_per_voxel,
        min_points_for_voxel_quartiles=settings.iqr_min_points_for_voxel_quartiles,
        eigenvalue_ratio=settings.eigenvalue_ratio,
        keep_unjudged=keep_unjudged,
        groups=groups,
    )


def _moving_survivors(
    source_xyz: np.ndarray, settings: RegistrationSettings, finest: float, *, keep_unjudged: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Algorithm 1 on the moving cloud: the cloud downsampled at ``target_voxel_fraction`` of the
    finest voxel, keeping the points of high probability under its own Gaussians.

    A moving cloud too sparse for Gaussians at the finest voxel (one already equalized at a
    coarser voxel, say) keeps everything: Algorithm 1 would keep less than
    :data:`MIN_SELECTED_SHARE` of it, not because those points are improbable but because their
    voxels hold too few to judge (the problem would become degenerate).

    Returns the downsampled cloud and its survivors (the same array when nothing was dropped)."""
    pre = voxel_downsample(source_xyz, finest * settings.target_voxel_fraction)
    if settings.select_moving_points:
        try:
            keep = _algorithm1_mask(pre, finest, settings, keep_unjudged=keep_unjudged)
        except InvalidCloudError:
            log.debug("moving cloud too sparse for Algorithm 1 at %g m: selection skipped", finest)
        else:
            if keep.sum() >= settings.min_points and keep.mean() >= MIN_SELECTED_SHARE:
                return pre, pre[keep]
            log.debug("Algorithm 1 kept %.1f %% of the moving cloud: not used", 100 * keep.mean())
    return pre, pre


#: Algorithm 1's moving-point selection is used only when it keeps at least this share
#: (:func:`_moving_survivors`).
MIN_SELECTED_SHARE = 0.25


#: A RANDT registration from scratch (every level) whose inlier ratio is below this is run once
#: more without its coarsest level, and the result with more inliers kept (:func:`register`): at
#: 8r a voxel's Gaussian can pull a sparse or equalized source into a wrong basin (figure 9's
#: scene: inlier ratio 0.04-0.05 there, 0.10-0.20 placed from 4r; placed results of the paper's
#: protocol hold 0.12-0.28, real pairs more).
RETRY_BELOW_INLIER_RATIO = 0.1


#: Coarse NDT levels use at least this many moving points (or all of them).
MIN_COARSE_POINTS = 1500


def _coarse_points(
    moving: np.ndarray,
    voxel_size_m: float,
    settings: RegistrationSettings,
    memo: dict[float, np.ndarray] | None = None,
) -> np.ndarray:
    """The moving points a coarse level sees: downsampled at half its voxel, halving the voxel
    until at least :data:`MIN_COARSE_POINTS` remain (small objects keep enough shape to rotate).

    ``memo`` (voxel -> downsampled points) shares the downsamplings between the levels of one
    registration: on a KITTI sweep the three coarsest levels all halve down to the same voxel.
    """
    memo = {} if memo is None else memo
    v = voxel_size_m * settings.source_voxel_fraction
    finest = v
    while True:
        if v not in memo:
            memo[v] = voxel_downsample(moving, v)
        pts = memo[v]
        if pts.shape[0] >= MIN_COARSE_POINTS or pts.shape[0] >= 0.5 * moving.shape[0]:
            return pts
        v *= 0.5
        if v < 0.05 * finest:
            return moving


def _svd_refine(
    moving: np.ndarray,
    ref: PreparedReference,
    T: np.ndarray,
    settings: RegistrationSettings,
) -> tuple[np.ndarray, int, float, float]:
    """Algorithm 3: iterate Kabsch on high-probability correspondences.

    The moving points are Algorithm 1's high-probability selection. One takes part when its
    nearest reference point is within one finest voxel (a :class:`~randt.core.grid.PointGrid` search)
    and that distance is inside the Tukey fence of all such distances. Its partner is the nearest
    reference point projected onto that point's local plane (normal from the
    ``svd_normal_neighbors`` nearest reference points, :meth:`PreparedReference.normals_at`): the
    SVD of these pairs has the point-to-plane optimum as its fixed point, so the step refines
    NDT's voxel-level fit with the surface itself instead of pulling points onto sampled positions.
    The iteration converges linearly; :func:`_extrapolate` (Besl & McKay's acceleration) cuts the
    number of iterations by about a third, and correspondences are searched again only every
    :data:`_SVD_SEARCH_EVERY` Kabsch solves (between searches only the projections onto the same
    planes change; docs/registration.md, "Algorithm 3"). It stops only on a small step taken right
    after a search, so its fixed point is that of searching every time; that search's pairs give
    the final RMSE (the pose moved less than the tolerance since).

    Returns the refined transform, iterations, and the trimmed point-to-plane RMSE before and after.
    """
    finest = ref.maps[-1]
    grid = ref.grid

    def search(T_cur: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Correspondences at ``T_cur``: (moving points, reference points, their normals)."""
        idx, dist = grid.nearest(moving, T_cur, finest.voxel_size_m)
        ok = idx >= 0
        if ok.sum() < 10:
            return None
        _, hi = tukey_fences(dist[ok], settings.svd_fence_k)
        ok &= dist <= hi
        normals, has_normal = ref.normals_at(idx[ok], settings.svd_normal_neighbors)
        sel = np.flatnonzero(ok)[has_normal]
        if sel.size < 10:
            return None
        src, dst, nrm = moving[sel], ref.points_xyz[idx[sel]], normals[has_normal]
        if settings.svd_residual_fence_k is not None:
            r = np.abs(np.einsum("ij,ij->i", transform_points(T_cur, src) - dst, nrm))
            keep = r <= tukey_fences(r, settings.svd_residual_fence_k)[1]
            if keep.sum() < 10:
                return None
            src, dst, nrm = src[keep], dst[keep], nrm[keep]
        return src, dst, nrm

    corr = search(T)
    if corr is None:
        return T, 0, np.inf, np.inf
    rmse_before = _projected_kabsch(T, corr)[2]
    # Rotation is weighed by the points' RMS radius so twists compare in metres.
    radius = max(float(np.sqrt(((moving - moving.mean(axis=0)) ** 2).sum(axis=1).mean())), 1e-12)
    previous: np.ndarray | None = None
    since_search = 0
    it = 0
    for it in range(1, settings.svd_iterations + 1):
        D, c, _ = _projected_kabsch(T, corr)
        T = D @ T
        # The step as a rotation about the matched points' centroid ``c`` (not the frame's
        # origin, which may be far away) and the centroid's translation.
        step = np.concatenate([D[:3, :3] @ c + D[:3, 3] - c, so3_log(D[:3, :3])])
        small = (
            np.linalg.norm(step[:3]) < settings.svd_translation_eps_m
            and np.linalg.norm(step[3:]) < settings.svd_rotation_eps_rad
        )
        if small and since_search == 0:
            # Converged on freshly searched correspondences: the pose moved less than the
            # tolerance since that search, so its pairs are the final pose's too.
            return T, it, rmse_before, _projected_kabsch(T, corr)[2]
        if not small:
            T, previous = _extrapolate(T, step, previous, radius, c)
        since_search += 1
        if small or since_search >= _SVD_SEARCH_EVERY:
            corr = search(T)
            since_search = 0
            if corr is None:
                return T, it, rmse_before, np.inf
    final = search(T)
    if final is None:
        return T, it, rmse_before, np.inf
    return T, it, rmse_before, _projected_kabsch(T, final)[2]


def _projected_kabsch(
    T: np.ndarray, corr: tuple[np.ndarray, np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray, float]:
    """One Kabsch solve of the SVD step: the rigid motion ``D`` taking the moving points
    ``corr[0]`` (moved by ``T``) onto their projections on the partners' planes (points
    ``corr[1]``, normals ``corr[2]``), the moved points' centroid, and their point-to-plane RMSE
    at ``T``.

    :func:`~randt.core.transforms.umeyama` on the moved and the projected points, with the moving,
    projecting and the sums fused into one compiled pass
    (:func:`~randt.core.kernels.projected_pair_moments`): the step solves this many times a
    registration, and numpy's temporaries would dominate it.
    """
    src, dst, nrm = corr
    mu_q, mu_y, cross = np.empty(3), np.empty(3), np.empty((3, 3))
    R = np.ascontiguousarray(T[:3, :3])
    t = np.ascontiguousarray(T[:3, 3])
    sum_r2 = projected_pair_moments(src, dst, nrm, R, t, mu_q, mu_y, cross)
    U, _, Vt = np.linalg.svd(cross)
    signs = np.array([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    D = np.eye(4)
    D[:3, :3] = U @ np.diag(signs) @ Vt
    D[:3, 3] = mu_y - D[:3, :3] @ mu_q
    return D, mu_q, float(np.sqrt(sum_r2 / src.shape[0]))


#: The SVD step searches correspondences again after this many Kabsch solves on the same ones (the
#: refinement moves millimetres: between searches only the projections onto the planes change).
_SVD_SEARCH_EVERY = 3


#: Most the accelerated SVD step extrapolates, in multiples of the last step (Besl & McKay 1992).
_MAX_EXTRAPOLATION = 8.0


def _extrapolate(
    T: np.ndarray, step: np.ndarray, previous: np.ndarray | None, radius: float, pivot: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None]:
    """Besl & McKay's accelerated ICP, applied to the SVD step's fixed-point iteration.

    Projected-point Kabsch converges linearly: successive steps point the same way and shrink by a
    near-constant ratio ``rho``. When two consecutive steps (twists, rotation scaled by ``radius``)
    agree in direction within about 10 degrees, the rest of the geometric series,
    ``rho / (1 - rho)`` times the last step (at most :data:`_MAX_EXTRAPOLATION`), is applied at
    once. The next steps then start a fresh estimate (an overshoot shows as a reversed step, which
    breaks the agreement and so is never extrapolated). Returns the new transform and the step to
    compare the next one with.
    """
    u = np.concatenate([step[:3], step[3:] * radius])
    if previous is None:
        return T, u
    nu, nv = float(np.linalg.norm(u)), float(np.linalg.norm(previous))
    if nu == 0.0 or nv == 0.0 or float(u @ previous) < 0.985 * nu * nv or nu >= nv:
        return T, u
    rho = nu / nv
    return apply_update_about(min(rho / (1.0 - rho), _MAX_EXTRAPOLATION) * step, T, pivot), None


def _svd_refine_voxel(
    moving: np.ndarray, ref: PreparedReference, T: np.ndarray, settings: RegistrationSettings
) -> tuple[np.ndarray, int, float, float]:
    """Algorithm 3 on the finest NDT level's Gaussians: iterate Kabsch on high-probability pairs.

    Each moving point's partner is chosen by probability: the neighbour voxel (1, 7 or 27 as the
    solver uses) where its squared Mahalanobis distance is least, kept when that distance is under
    the chi-square(3) 99 % quantile and its point-to-plane distance inside the Tukey fence of all
    of them. The partner is the point projected onto that voxel's plane (mean and smallest-
    eigenvalue normal), so the SVD's fixed point is the point-to-plane optimum over the NDT
    surface patches. One compiled pass per iteration (:func:`randt.core.kernels.best_voxel`).

    Returns the refined transform, iterations, and the trimmed point-to-plane RMSE before and after.
    """
    gmap = ref.maps[-1]
    offsets = NEIGHBOR_OFFSETS[settings.n_neighbors]
    table_key, table_idx = gmap.hash_table
    n = moving.shape[0]
    vox, m = np.empty(n, dtype=np.int64), np.empty(n)
    pts = np.ascontiguousarray(moving, dtype=np.float64)

    def pairs(T_cur: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        best_voxel(
            pts, np.ascontiguousarray(T_cur[:3, :3]), np.ascontiguousarray(T_cur[:3, 3]),
            table_key, table_idx, gmap.means, gmap.inv_covariances, gmap.voxel_size_m, offsets, vox, m,
        )  # fmt: skip
        ok = m < CHI2_3DOF_99
        if ok.sum() < 10:
            return pts[:0], pts[:0], pts[:0, 0]
        q = transform_points(T_cur, pts[ok])
        v = vox[ok]
        nrm = gmap.normals[v]
        r = np.einsum("ij,ij->i", q - gmap.means[v], nrm)
        _, hi = tukey_fences(np.abs(r), settings.svd_fence_k)
        keep = np.abs(r) <= hi
        q, nrm, r = q[keep], nrm[keep], r[keep]
        return q, q - nrm * r[:, None], r

    q, proj, r = pairs(T)
    if q.shape[0] < 10:
        return T, 0, np.inf, np.inf
    rmse_before = float(np.sqrt(np.mean(r**2)))
    eps_t, eps_deg = settings.svd_translation_eps_m, np.degrees(settings.svd_rotation_eps_rad)
    it = 0
    for it in range(1, settings.svd_iterations + 1):
        D, _ = umeyama(q, proj)
        T = D @ T
        q, proj, r = pairs(T)
        if q.shape[0] < 10:
            return T, it, rmse_before, np.inf
        if np.linalg.norm(D[:3, 3]) < eps_t and rotation_angle_deg(D[:3, :3]) < eps_deg:
            break
    return T, it, rmse_before, float(np.sqrt(np.mean(r**2)))


def _plane_information(moving: np.ndarray, T: np.ndarray, gmap: VoxelGaussianMap) -> np.ndarray:
    """6x6 point-to-plane information of the matched points (those in a map voxel), rotation
    scaled by their RMS radius; zeros when fewer than 6 match (compiled:
    :func:`randt.core.kernels.plane_information`)."""
    table_key, table_idx = gmap.hash_table
    information, n_matched = plane_information(
        np.ascontiguousarray(moving, dtype=np.float64),
        np.ascontiguousarray(T[:3, :3], dtype=np.float64),
        np.ascontiguousarray(T[:3, 3], dtype=np.float64),
        table_key,
        table_idx,
        gmap.normals,
        float(gmap.voxel_size_m),
    )
    return information if n_matched >= 6 else np.zeros((6, 6))


def _plane_information_numpy(moving: np.ndarray, T: np.ndarray, gmap: VoxelGaussianMap) -> np.ndarray:
    """:func:`_plane_information` vectorized: the kernel's reference (the tests)."""
    q = transform_points(T, moving)
    pidx, vidx = gmap.neighbors(q, 1)
    if pidx.size < 6:
        return np.zeros((6, 6))
    qq, n = q[pidx], gmap.normals[vidx]
    centre = qq.mean(axis=0)
    rel = qq - centre
    radius = max(float(np.sqrt((rel**2).sum(axis=1).mean())), 1e-9)
    J = np.concatenate([n, np.cross(rel, n) / radius], axis=1)
    information: np.ndarray = J.T @ J / pidx.size
    return information


_AXES = ("tx", "ty", "tz", "rx", "ry", "rz")


class _StageClock:
    """Wall time per named stage: ``with clock("match"): ...`` adds to ``clock.times["match"]``."""

    def __init__(self) -> None:
        self.times: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        t0 = time.perf_counter()
        yield
        self.times[stage] = self.times.get(stage, 0.0) + time.perf_counter() - t0


@dataclass(frozen=True)
class _Inputs:
    """The sanitized clouds and the NDT levels, coarse to fine."""

    source_xyz: np.ndarray
    target_xyz: np.ndarray
    levels: tuple[float, ...]
    n_nonfinite_dropped: int
    #: :func:`is_sparse_cloud` of each (False with a prepared reference)
    source_sparse: bool = False
    target_sparse: bool = False


@dataclass(frozen=True)
class _Match:
    """Where the solver (NDT or ICP, every level) left the pose."""

    T: np.ndarray
    iterations: int
    converged: bool
    final_cache: NeighborCache | None  # the finest NDT level's neighbour cache, reused by the judge
    final_evaluation: NdtEvaluation | None = None  # the finest level's derivatives at ``T``


@dataclass(frozen=True)
class _Judgement:
    """Autoware's fitness scores, the inlier ratio and the uncertainty at the final pose."""

    transform_probability: float
    nvtl: float
    inlier_ratio: float
    covariance: np.ndarray
    plane_information: np.ndarray


def _resolve_settings(settings: RegistrationSettings | None, method: Method | None) -> RegistrationSettings:
    """The settings to use: ``method``'s defaults when it overrides (or no settings are given)."""
    if settings is None:
        return RegistrationSettings.for_method(method or "randt")
    if method is not None and method != settings.method:
        return RegistrationSettings.for_method(method)
    return settings


def _sanitize_inputs(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray | None,
    reference: PreparedReference | None,
    settings: RegistrationSettings,
) -> _Inputs:
    """Finite points only (counted), clouds too small rejected; the levels given, the reference's,
    or derived from the target's scale (:func:`auto_voxel_sizes`)."""
    src, n_bad_s = sanitize_points(source_xyz, name="source", min_points=settings.min_points)
    if reference is None:
        tgt, n_bad_t = sanitize_points(target_xyz, name="target", min_points=settings.min_points)
        levels = settings.voxel_sizes_m or auto_voxel_sizes(tgt)
        sparse = (is_sparse_cloud(src), is_sparse_cloud(tgt))
    else:  # (a prepared reference: the incremental matcher's per-sweep path, real sweeps)
        tgt, n_bad_t = reference.points_xyz, 0
        levels = reference.voxel_sizes_m
        sparse = (False, False)
    return _Inputs(src, tgt, tuple(levels), n_bad_s + n_bad_t, *sparse)


def _reference(
    inputs: _Inputs, reference: PreparedReference | None, settings: RegistrationSettings
) -> PreparedReference:
    """The reference given, or the target prepared (:func:`prepare_reference`)."""
    if reference is not None:
        return reference
    return prepare_reference(inputs.target_xyz, settings, inputs.levels, keep_unjudged=inputs.target_sparse)


def _moving_points(
    source_xyz: np.ndarray, settings: RegistrationSettings, finest: float, *, sparse: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """The NDT solver's moving points (Algorithm 1's survivors downsampled at
    ``source_voxel_fraction`` of the finest voxel) and the SVD step's: by default the cloud
    downsampled at ``svd_source_voxel_fraction`` before Algorithm 1 (its fences trim the pairs,
    :func:`_svd_refine`); with ``svd_on_filtered_points`` the survivors, at their own fraction or
    the solver's very points. Refuses a cloud too sparse to match."""
    pre, survivors = _moving_survivors(source_xyz, settings, finest, keep_unjudged=sparse)
    moving = voxel_downsample(survivors, finest * settings.source_voxel_fraction)
    if moving.shape[0] < settings.min_points:
        raise InvalidCloudError(f"source: only {moving.shape[0]} points survive downsampling at {finest:g} m")
    if not settings.svd_refinement:
        return moving, moving
    fraction = settings.svd_source_voxel_fraction
    if settings.svd_on_filtered_points:
        return moving, moving if fraction is None else voxel_downsample(survivors, finest * fraction)
    return moving, voxel_downsample(pre, finest * (fraction or settings.source_voxel_fraction))


def _match(
    moving: np.ndarray,
    ref: PreparedReference,
    levels: tuple[float, ...],
    T: np.ndarray,
    settings: RegistrationSettings,
    coarsest_voxel_m: float | None = None,
) -> _Match:
    """The solver from ``T``: NDT for ``randt`` and ``ndt``, ICP for the ICP baselines; levels
    coarser than ``coarsest_voxel_m`` skipped (the finest always kept)."""
    first = 0
    if coarsest_voxel_m is not None:
        first = min(sum(v > coarsest_voxel_m * (1 + 1e-9) for v in levels), len(levels) - 1)
    if settings.method in ("randt", "ndt"):
        return _match_ndt(moving, ref, T, settings, first)
    return _match_icp(moving, ref, levels[first:], T, settings)


def _match_ndt(
    moving: np.ndarray,
    ref: PreparedReference,
    T: np.ndarray,
    settings: RegistrationSettings,
    first_level: int = 0,
) -> _Match:
    """Newton on the NDT cost (:func:`randt.core.ndt.ndt_newton`), level by level from the previous
    pose, from level ``first_level`` (0: the coarsest) on."""
    iterations = 0
    converged = True
    final_cache = None
    final_evaluation = None
    memo: dict[float, np.ndarray] = {}
    for level, gmap in enumerate(ref.maps):
        if level < first_level:
            continue
        final = level == len(ref.maps) - 1
        consts = ndt_constants(gmap.voxel_size_m, settings.outlier_ratio)
        # Coarse levels only need to hand a good start to the next: stop at 1 % of a voxel.
        level_moving = moving if final else _coarse_points(moving, gmap.voxel_size_m, settings, memo)
        out = ndt_newton(
            level_moving,
            gmap,
            consts,
            T,
            n_neighbors=settings.n_neighbors,
            max_iterations=settings.max_iterations,
            translation_eps_m=settings.translation_eps_m if final else 0.01 * gmap.voxel_size_m,
            rotation_eps_rad=settings.rotation_eps_rad if final else 1e-3,
        )
        T, iterations = out.T, iterations + out.iterations
        converged = converged and out.converged
        final_cache = out.cache if final else None
        final_evaluation = about_origin(out.evaluation, out.pivot) if final else None
    return _Match(T, iterations, converged, final_cache, final_evaluation)


def _match_icp(
    moving: np.ndarray,
    ref: PreparedReference,
    levels: tuple[float, ...],
    T: np.ndarray,
    settings: RegistrationSettings,
) -> _Match:
    """The ICP baselines: one run per level, the level's voxel as the correspondence distance."""
    tree = ref.kdtree
    icp = icp_point_to_point if settings.method == "icp-point" else icp_point_to_plane
    iterations = 0
    for v in levels:
        out_icp = icp(
            moving,
            ref.points_xyz,
            T,
            max_correspondence_m=v,
            max_iterations=settings.max_iterations,
            translation_eps_m=settings.translation_eps_m,
            rotation_eps_rad=settings.rotation_eps_rad,
            tree=tree,
        )
        T, iterations = out_icp.T, iterations + out_icp.iterations
    return _Match(T, iterations, out_icp.converged, None)


def _refine(
    moving: np.ndarray, ref: PreparedReference, T: np.ndarray, settings: RegistrationSettings
) -> tuple[np.ndarray, int, bool]:
    """Algorithm 3 (the SVD step), kept only if it agrees: returns the pose, the SVD iterations
    and whether the step was accepted (the trimmed point-to-plane RMSE rises by at most
    ``svd_max_rmse_rise`` and the step stays within one finest voxel).

    The tolerance: the RMSE before and after is taken over each pose's own fenced
    correspondences, and on real pairs a good step moves it a little either way, so a strict
    "must lower it" test turns on that jitter. The allowed rise is far below what a step into a
    wrong basin does (the guard's purpose; docs/registration.md, "Algorithm 3")."""
    if settings.svd_correspondences == "voxel":
        T_svd, n_svd, rmse_before, rmse_after = _svd_refine_voxel(moving, ref, T, settings)
    else:
        T_svd, n_svd, rmse_before, rmse_after = _svd_refine(moving, ref, T, settings)
    step_t = float(np.linalg.norm((invert(T) @ T_svd)[:3, 3]))
    rises_little = np.isfinite(rmse_after) and rmse_after <= rmse_before * (1.0 + settings.svd_max_rmse_rise)
    if rises_little and step_t < ref.maps[-1].voxel_size_m:
        return T_svd, n_svd, True
    return T, n_svd, False


def _judge(
    moving: np.ndarray,
    T: np.ndarray,
    ref: PreparedReference,
    settings: RegistrationSettings,
    final_cache: NeighborCache | None,
    evaluation: NdtEvaluation | None = None,
) -> _Judgement:
    """Fitness as Autoware reports it (TP, NVTL), the inlier ratio, the covariance from the NDT
    Hessian and the point-to-plane information the degeneracy test reads; never the initial guess
    dressed up as a result (no overlap raises). ``evaluation``: the finest level's derivatives at
    ``T`` when the solver has them (computed here otherwise)."""
    finest_map = ref.maps[-1]
    consts = ndt_constants(finest_map.voxel_size_m, settings.outlier_ratio)
    n_neighbors = settings.n_neighbors
    score_sum, score_max, best_m = ndt_point_scores(moving, T, finest_map, consts, n_neighbors, final_cache)
    has = score_max > 0
    if not np.any(has):
        raise RegistrationFailedError(
            "no moving point lies near a reference voxel at the final pose: the clouds do not "
            "overlap from this initial guess"
        )
    ev = evaluation or ndt_derivatives(moving, T, finest_map, consts, n_neighbors, cache=final_cache)
    H = ev.hessian
    if np.linalg.eigvalsh(H).min() <= 0:
        H = ev.gauss_newton_hessian
    covariance = np.linalg.pinv(H)
    return _Judgement(
        transform_probability=float(score_sum.sum() / moving.shape[0]),
        nvtl=float(score_max[has].mean()),
        inlier_ratio=float(np.mean(best_m < CHI2_3DOF_99)),
        covariance=0.5 * (covariance + covariance.T),
        plane_information=_plane_information(moving, T, finest_map),
    )


def inlier_ratio(
    points_xyz: np.ndarray, T: np.ndarray, reference: PreparedReference, settings: RegistrationSettings
) -> float:
    """Share of ``points_xyz`` (source frame) that ``T`` puts within the chi-square gate
    (:data:`CHI2_3DOF_99`) of their best voxel at the reference's finest level: the
    :attr:`RegistrationResult.inlier_ratio` test applied to any points (``nan`` for none)."""
    if len(points_xyz) == 0:
        return float("nan")
    finest_map = reference.maps[-1]
    consts = ndt_constants(finest_map.voxel_size_m, settings.outlier_ratio)
    pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
    _, _, best_m = ndt_point_scores(pts, T, finest_map, consts, settings.n_neighbors)
    return float(np.mean(best_m < CHI2_3DOF_99))


def _raise_if_degenerate(result: RegistrationResult, information: np.ndarray, threshold: float) -> None:
    """Raise :class:`DegenerateProblemError` (holding ``result``) when a direction of the
    point-to-plane information is weaker than ``threshold`` times the strongest.

    With ``m`` weak directions it names the ``m`` axes lying most in their span (each axis's
    squared projection onto it): the weak eigenvectors of a plane may be any rotation of tx and ty
    within that span, so naming each by its own largest component could name ty twice."""
    evals, evecs = np.linalg.eigh(information)
    ratio = evals / max(evals[-1], 1e-300)
    weak = ratio < threshold
    if np.any(weak):
        in_span = (evecs[:, weak] ** 2).sum(axis=1)
        names = tuple(_AXES[i] for i in sorted(np.argsort(-in_span, kind="stable")[: int(weak.sum())]))
        raise DegenerateProblemError(
            f"the geometry does not constrain {len(names)} degree(s) of freedom "
            f"(mostly {', '.join(names)}; eigenvalue ratios {np.array2string(ratio[weak], precision=2)}): "
            "the scene is likely a single plane or a featureless corridor",
            result=result,
            weak_directions=names,
        )


def register(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray | None,
    init_T_target_source: np.ndarray | None = None,
    *,
    settings: RegistrationSettings | None = None,
    method: Method | None = None,
    reference: PreparedReference | None = None,
    coarsest_voxel_m: float | None = None,
) -> RegistrationResult:
    """Align ``source_xyz`` to ``target_xyz``; returns a :class:`RegistrationResult`.

    The stages are the module docstring's: sanitize, reference, moving, match, refine (SVD), judge.

    Parameters
    ----------
    source_xyz : (N,3) moving points (extra columns ignored; non-finite rows dropped and counted).
    target_xyz : (M,3) reference points (ignored, and may be ``None``, when ``reference`` is given).
    init_T_target_source : (4,4) initial guess, identity when ``None``.
    settings : algorithm settings; ``method`` overrides ``settings.method`` with that method's
        defaults (:meth:`RegistrationSettings.for_method`).
    reference : a :class:`PreparedReference` to reuse across calls (incremental matching).
    coarsest_voxel_m : NDT levels coarser than this are skipped (the finest always runs): an
        initial guess known to be within a fraction of a level's voxel needs no coarser ones.
        ``None`` runs every level.

    Raises
    ------
    InvalidCloudError : empty, too small or wrongly shaped input.
    DegenerateProblemError : the geometry leaves a direction unconstrained (``.result`` holds
        the pose reached, ``.weak_directions`` names the directions).
    RegistrationFailedError : the solver produced a non-finite pose or found no overlap at all.
    """
    settings = _resolve_settings(settings, method)
    T = as_transform(init_T_target_source, name="init_T_target_source")
    clock = _StageClock()
    with clock("sanitize"):
        inputs = _sanitize_inputs(source_xyz, target_xyz, reference, settings)
    with clock("reference"):
        ref = _reference(inputs, reference, settings)
    with clock("moving"):
        moving, svd_moving = _moving_points(
            inputs.source_xyz, settings, inputs.levels[-1], sparse=inputs.source_sparse
        )
        if settings.max_match_points is not None:  # a few thousand drive Newton (docs/mapping.md)
            moving = stratified_subsample(
                moving, settings.max_match_points, settings.match_cell_voxels * inputs.levels[-1]
            )
    T_init = T

    def solve(coarsest: float | None) -> tuple[np.ndarray, int, bool, _Match, _Judgement]:
        """Match from ``T_init`` (levels coarser than ``coarsest`` skipped), refine, judge."""
        with clock("match"):
            match = _match(moving, ref, inputs.levels, T_init, settings, coarsest)
        T, iterations, svd_accepted = match.T, match.iterations, False
        if settings.svd_refinement:
            with clock("svd"):
                svd_ref = ref if settings.svd_on_filtered_points else ref.unfiltered
                T, n_svd, svd_accepted = _refine(svd_moving, svd_ref, T, settings)
                iterations += n_svd
        with clock("judge"):
            if not np.all(np.isfinite(T)):
                raise RegistrationFailedError("registration produced a non-finite transform")
            T = orthonormalize(T)
            # Newton's last evaluation, within its tolerance of the pose (unless the SVD step moved it).
            evaluation = None if svd_accepted else match.final_evaluation
            judged = _judge(moving, T, ref, settings, match.final_cache, evaluation)
        return T, iterations, svd_accepted, match, judged

    T, iterations, svd_accepted, match, judged = solve(coarsest_voxel_m)
    if (
        settings.method == "randt"
        and coarsest_voxel_m is None
        and len(inputs.levels) > 2
        and judged.inlier_ratio < RETRY_BELOW_INLIER_RATIO
    ):
        # A wrong basin at the coarsest level (RETRY_BELOW_INLIER_RATIO): once more from the
        # second level, and the result with more inliers is kept.
        try:
            retry = solve(inputs.levels[1])
        except RegistrationFailedError:
            retry = None
        if retry is not None and retry[4].inlier_ratio > judged.inlier_ratio:
            iterations += retry[1]
            T, _, svd_accepted, match, judged = retry
    result = RegistrationResult(
        T_target_source=T,
        converged=bool(match.converged),
        iterations=int(iterations),
        transform_probability=judged.transform_probability,
        nearest_voxel_transformation_likelihood=judged.nvtl,
        inlier_ratio=judged.inlier_ratio,
        covariance=judged.covariance,
        method=settings.method,
        voxel_sizes_m=tuple(float(v) for v in inputs.levels),
        n_source_points=int(inputs.source_xyz.shape[0]),
        n_target_points=int(inputs.target_xyz.shape[0]),
        n_source_used=int(moving.shape[0]),
        n_nonfinite_dropped=inputs.n_nonfinite_dropped,
        svd_accepted=svd_accepted,
        stage_times_s=clock.times,
        message="" if match.converged else "solver stopped at the iteration limit before converging",
    )
    _raise_if_degenerate(result, judged.plane_information, settings.degeneracy_threshold)
    return result
