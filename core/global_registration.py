"""Global (prior-free) registration: align two clouds with no initial guess.

:func:`register_global`: scale -> downsample -> normals -> FPFH features (Rusu et al., ICRA
2009) -> mutual nearest neighbours -> pairwise-consistency pruning (maximum k-core, then a greedy
clique: the ROBIN / TEASER++ idea) -> GNC-TLS (Yang et al., RA-L 2020) -> NDT refinement
(:func:`randt.core.registration.register`) -> judge (confident or not, with the reason). Every stage
is vectorized over points; the only Python loops are over GNC iterations and k-core levels. Each
stage and why: docs/registration.md, "Global registration".
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from randt.core.config import RegistrationSettings
from randt.core.errors import DegenerateProblemError, InvalidCloudError, RegistrationFailedError
from randt.core.kernels import consistency_graph, core_numbers, eigh3, spfh_histograms
from randt.core.registration import auto_voxel_sizes, register, sanitize_points
from randt.core.transforms import rotation_angle_deg, transform_points, umeyama
from randt.core.voxel import voxel_downsample

__all__ = [
    "GlobalResult",
    "GlobalSettings",
    "fpfh",
    "register_global",
]

#: The NDT refinement is kept when at least this fraction of the robust solver's inliers stay
#: within the noise bound under the refined pose.
KEPT_INLIER_FRACTION = 0.8

#: FPFH bins per angle (three angles: 33 values), as in PCL and Open3D.
FPFH_BINS = 11


class GlobalSettings(BaseModel):
    """How :func:`register_global` aligns two clouds without an initial guess."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    voxel_m: float | None = Field(
        default=None,
        gt=0,
        description="feature voxel v; None: voxel_fraction x the finest NDT level of the target's scale "
        "(randt.core.registration.auto_voxel_sizes): 0.6-0.7 m for a KITTI sweep, 4 mm for a bunny scan",
    )
    voxel_fraction: float = Field(
        default=1.0, gt=0, le=4, description="with voxel_m None: v = this x the finest NDT level"
    )
    max_points: int = Field(
        default=3000,
        ge=100,
        description="with voxel_m None: v grows until neither cloud keeps many more voxels than "
        "this (bounded time, every real pair still placed)",
    )
    max_range_m: float | None = Field(
        default=None, gt=0, description="points farther from the sensor are ignored; None keeps all"
    )
    normal_radius_voxels: float = Field(default=2.0, gt=0, description="normal neighbourhood / v")
    feature_radius_voxels: float = Field(default=5.0, gt=0, description="FPFH neighbourhood / v")
    max_neighbors: int = Field(default=48, ge=8, description="FPFH neighbours per point, nearest first")
    normal_neighbors: int = Field(default=24, ge=5, description="normal neighbours per point, nearest first")
    noise_bound_voxels: float = Field(
        default=1.0, gt=0, description="correspondence noise bound / v (consistency and GNC-TLS)"
    )
    max_correspondences: int = Field(
        default=3000, ge=10, description="correspondences kept for pruning, best feature distance first"
    )
    min_inliers: int = Field(
        default=12, ge=3, description="fewer consistent correspondences than this: not confident"
    )
    refine: bool = Field(default=True, description="NDT refinement from the coarse pose")
    refine_coarsest_voxels: float = Field(
        default=2.0, gt=0, description="the refinement skips NDT levels coarser than this x v"
    )
    max_refine_shift_voxels: float = Field(
        default=4.0, gt=0, description="refinement moving the coarse pose farther: not confident"
    )
    max_refine_rotation_deg: float = Field(default=5.0, gt=0)
    min_overlap: float = Field(
        default=0.3,
        ge=0,
        le=1,
        description="fraction of source voxels with a target point within the noise bound after "
        "the final pose; below it: not confident",
    )
    registration: RegistrationSettings = Field(
        default_factory=RegistrationSettings, description="the NDT refinement's settings"
    )


@dataclass(frozen=True)
class GlobalResult:
    """What :func:`register_global` found (``p_target = T_target_source @ p_source``)."""

    T_target_source: np.ndarray
    #: the robust solver's pose, before the NDT refinement
    T_coarse: np.ndarray
    #: False: do not trust the pose (``reason`` says why)
    confident: bool
    reason: str
    voxel_m: float
    n_source_points: int
    n_target_points: int
    n_correspondences: int
    #: correspondences in the consistent clique
    n_inliers: int
    #: fraction of the source voxels that land within the noise bound of a target point
    overlap: float
    #: the NDT refinement's pose was kept (False: the coarse pose is the answer)
    refined: bool
    time_s: float
    stage_times_s: dict[str, float] = field(default_factory=dict)
    #: the kept refinement's translation uncertainty, its largest sigma over its smallest (1: as
    #: well held along every direction; large: NDT could slide along one, a corridor); nan
    #: without a refinement kept
    anisotropy: float = float("nan")

    def to_dict(self) -> dict[str, object]:
        """JSON-ready: matrices as nested lists (``randt register --global --json``)."""
        return {
            "T_target_source": self.T_target_source.tolist(),
            "T_coarse": self.T_coarse.tolist(),
            "confident": self.confident,
            "reason": self.reason,
            "voxel_m": self.voxel_m,
            "n_source_points": self.n_source_points,
            "n_target_points": self.n_target_points,
            "n_correspondences": self.n_correspondences,
            "n_inliers": self.n_inliers,
            "overlap": self.overlap,
            "refined": self.refined,
            "anisotropy": self.anisotropy,
            "time_s": self.time_s,
            "stage_times_s": dict(self.stage_times_s),
        }


def _neighbors(tree: cKDTree, points: np.ndarray, radius: float, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(N,k) neighbour indices and distances within ``radius``; missing ones have index N."""
    k = min(k, tree.n)
    dist, idx = tree.query(points, k=k, distance_upper_bound=radius)
    dist, idx = np.asarray(dist, dtype=np.float64), np.asarray(idx, dtype=np.int64)
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    return idx, dist


def _normals(points: np.ndarray, tree: cKDTree, radius: float, k: int) -> np.ndarray:
    """Unit normals (N,3) from each point's neighbours within ``radius``, towards the origin."""
    idx, _ = _neighbors(tree, points, radius, k)
    valid = idx < points.shape[0]
    padded = np.vstack([points, np.zeros((1, 3))])
    nb = padded[idx]  # (N,k,3), missing rows are zeros and weighted out
    w = valid.astype(np.float64)
    count = np.maximum(w.sum(axis=1), 1.0)
    mean = np.einsum("nk,nki->ni", w, nb) / count[:, None]
    d = (nb - mean[:, None, :]) * w[:, :, None]
    cov = np.einsum("nki,nkj->nij", d, d)
    _, evecs = eigh3(cov)
    normals = np.ascontiguousarray(evecs[:, :, 0])
    flip = np.einsum("ni,ni->n", normals, points) > 0  # point away from the sensor at the origin
    normals[flip] *= -1
    return normals


def spfh_reference(points: np.ndarray, normals: np.ndarray, neighbors: np.ndarray, bins: int) -> np.ndarray:
    """The numpy form of :func:`randt.core.kernels.spfh_histograms` (same arguments and result), kept as
    its reference (slower: the cross products and histograms over every pair at once)."""
    n = points.shape[0]
    valid = (neighbors < n) & (neighbors != np.arange(n)[:, None])
    rows = np.nonzero(valid)[0]
    cols = neighbors[valid]
    d = points[cols] - points[rows]
    length = np.linalg.norm(d, axis=1)
    keep = length > 0
    rows, cols, d, length = rows[keep], cols[keep], d[keep], length[keep]
    d /= length[:, None]
    n1, n2 = normals[rows], normals[cols]
    swap = np.abs(np.einsum("ni,ni->n", n1, d)) < np.abs(np.einsum("ni,ni->n", n2, d))
    u = np.where(swap[:, None], n2, n1)
    nt = np.where(swap[:, None], n1, n2)
    line = np.where(swap[:, None], -d, d)
    v = np.cross(u, line)
    v_norm = np.linalg.norm(v, axis=1)
    ok = v_norm > 1e-12
    v[ok] /= v_norm[ok, None]
    w = np.cross(u, v)
    alpha = np.einsum("ni,ni->n", v, nt)
    phi = np.einsum("ni,ni->n", u, line)
    theta = np.arctan2(np.einsum("ni,ni->n", w, nt), np.einsum("ni,ni->n", u, nt))
    index = np.stack(
        [
            np.clip(((alpha + 1.0) * 0.5 * bins).astype(np.int64), 0, bins - 1),
            np.clip(((phi + 1.0) * 0.5 * bins).astype(np.int64), 0, bins - 1) + bins,
            np.clip(((theta + np.pi) / (2 * np.pi) * bins).astype(np.int64), 0, bins - 1) + 2 * bins,
        ]
    )
    flat = (rows[None, :] * 3 * bins + index).ravel()
    spfh = np.bincount(flat, minlength=n * 3 * bins).reshape(n, 3 * bins).astype(np.float64)
    counts = np.bincount(rows, minlength=n).astype(np.float64)
    spfh *= 100.0 / np.maximum(counts, 1.0)[:, None]
    return spfh


def fpfh(points: np.ndarray, normals: np.ndarray, tree: cKDTree, radius: float, k: int) -> np.ndarray:
    """Fast Point Feature Histograms (N,33) of ``points`` with unit ``normals``.

    For each point p and neighbour q within ``radius`` (at most ``k``), the Darboux frame of the
    pair gives three angles, each binned in :data:`FPFH_BINS` bins (:func:`randt.core.kernels.
    spfh_histograms`); a point's FPFH adds its neighbours' histograms weighted by 1 / distance and
    averaged (Rusu et al. 2009, eq. 4), each angle's histogram then renormalized to 100. Points
    with no neighbour get zeros.
    """
    n = points.shape[0]
    idx, dist = _neighbors(tree, points, radius, k + 1)
    spfh = spfh_histograms(points, normals, idx, FPFH_BINS)
    valid = (idx < n) & (idx != np.arange(n)[:, None])
    rows = np.nonzero(valid)[0]
    weights = csr_matrix((1.0 / np.maximum(dist[valid], 1e-12), (rows, idx[valid])), shape=(n, n))
    counts = valid.sum(axis=1).astype(np.float64)
    features = np.asarray(spfh + (weights @ spfh) / np.maximum(counts, 1.0)[:, None], dtype=np.float64)
    per_angle = features.reshape(n, 3, FPFH_BINS)
    totals = per_angle.sum(axis=2, keepdims=True)
    per_angle *= 100.0 / np.maximum(totals, 1e-12)
    return per_angle.reshape(n, 3 * FPFH_BINS)


def _nearest_both_ways(
    fs: np.ndarray, ft: np.ndarray, block: int = 1024
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest neighbours in feature space both ways, from one matrix product.

    Returns ``(nn_st, d2_st, nn_ts)``: for each row of ``fs`` its nearest row of ``ft`` and the
    squared distance, and for each row of ``ft`` its nearest row of ``fs``. Squared distances are
    ``|f|^2 - 2 f.g + |g|^2`` in float32 blocks of ``block`` rows (BLAS: faster than a
    33-dimensional KD-tree, docs/registration.md, "Global registration").
    """
    a, b = fs.astype(np.float32), ft.astype(np.float32)
    na, nb_ = np.einsum("ij,ij->i", a, a), np.einsum("ij,ij->i", b, b)
    nn_st = np.empty(a.shape[0], np.int64)
    d2_st = np.empty(a.shape[0], np.float32)
    best_t = np.full(b.shape[0], np.inf, np.float32)
    nn_ts = np.zeros(b.shape[0], np.int64)
    for lo in range(0, a.shape[0], block):
        d2 = a[lo : lo + block] @ b.T
        d2 *= -2.0
        d2 += na[lo : lo + block, None]
        d2 += nb_[None, :]
        rows = np.argmin(d2, axis=1)
        nn_st[lo : lo + block] = rows
        d2_st[lo : lo + block] = d2[np.arange(rows.size), rows]
        cols = np.argmin(d2, axis=0)
        col_best = d2[cols, np.arange(b.shape[0])]
        better = col_best < best_t
        best_t[better] = col_best[better]
        nn_ts[better] = cols[better] + lo
    return nn_st, d2_st, nn_ts


def _correspondences(
    source_features: np.ndarray, target_features: np.ndarray, max_count: int
) -> tuple[np.ndarray, np.ndarray]:
    """Source and target indices of mutual nearest neighbours in feature space, best first; when
    fewer than a tenth of ``max_count`` are mutual, each source point's best match instead."""
    has_s = source_features.any(axis=1)
    has_t = target_features.any(axis=1)
    s_ids, t_ids = np.nonzero(has_s)[0], np.nonzero(has_t)[0]
    if s_ids.size == 0 or t_ids.size == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    nn_st, d2_st, nn_ts = _nearest_both_ways(source_features[s_ids], target_features[t_ids])
    mutual = nn_ts[nn_st] == np.arange(s_ids.size)
    if mutual.sum() < max(max_count // 10, 10):
        mutual = np.ones(s_ids.size, dtype=bool)
    keep = np.nonzero(mutual)[0]
    keep = keep[np.argsort(d2_st[keep], kind="stable")][:max_count]
    return s_ids[keep], t_ids[nn_st[keep]]


def _greedy_clique(adjacency: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """A clique among ``candidates``, highest degree first (each vertex kept when it agrees with
    every vertex kept so far)."""
    sub = adjacency[np.ix_(candidates, candidates)]
    order = np.argsort(-sub.sum(axis=1), kind="stable")
    allowed = np.ones(candidates.size, dtype=bool)
    clique: list[int] = []
    for v in order:
        if allowed[v]:
            clique.append(int(v))
            allowed &= sub[v]
    return candidates[np.array(clique, dtype=np.int64)]


def _gnc_tls(
    src: np.ndarray, dst: np.ndarray, noise_bound: float, iterations: int = 100
) -> tuple[np.ndarray, np.ndarray]:
    """GNC-TLS rigid fit of ``dst ~ T src``; returns ``(T, inlier mask)``."""
    w = np.ones(src.shape[0])
    T, _ = umeyama(src, dst, weights=w)
    c2 = noise_bound**2
    r2 = np.sum((transform_points(T, src) - dst) ** 2, axis=1)
    mu = 1.0 / max(2.0 * r2.max() / c2 - 1.0, 1e-6)
    for _ in range(iterations):
        if mu > 1e4:
            break
        lo, hi = mu / (mu + 1.0) * c2, (mu + 1.0) / mu * c2
        w = np.where(
            r2 <= lo,
            1.0,
            np.where(r2 >= hi, 0.0, noise_bound * np.sqrt(mu * (mu + 1.0) / np.maximum(r2, 1e-300)) - mu),
        )
        if w.sum() < 3:
            break
        T, _ = umeyama(src, dst, weights=w)
        r2 = np.sum((transform_points(T, src) - dst) ** 2, axis=1)
        mu *= 1.4
    return T, r2 <= c2


def register_global(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray,
    settings: GlobalSettings | None = None,
) -> GlobalResult:
    """Align ``source_xyz`` to ``target_xyz`` with no initial guess (module docstring's stages).

    Raises
    ------
    InvalidCloudError : empty, too small or wrongly shaped input.
    """
    s = settings or GlobalSettings()
    t_start = time.perf_counter()
    times: dict[str, float] = {}

    def lap(name: str, t0: float) -> float:
        now = time.perf_counter()
        times[name] = now - t0
        return now

    t0 = t_start
    src_all, _ = sanitize_points(source_xyz, name="source", min_points=10)
    dst_all, _ = sanitize_points(target_xyz, name="target", min_points=10)
    if s.max_range_m is not None:
        src_all = src_all[np.linalg.norm(src_all, axis=1) <= s.max_range_m]
        dst_all = dst_all[np.linalg.norm(dst_all, axis=1) <= s.max_range_m]
    v = s.voxel_m if s.voxel_m is not None else auto_voxel_sizes(dst_all)[-1] * s.voxel_fraction
    t0 = lap("scale", t0)
    src = voxel_downsample(src_all, v)
    dst = voxel_downsample(dst_all, v)
    larger = max(src.shape[0], dst.shape[0])
    if s.voxel_m is None and larger > s.max_points:
        # A surface's voxel count falls as 1 / v^2: one coarser voxel brings both near the budget.
        v *= float(np.sqrt(larger / s.max_points))
        src, dst = voxel_downsample(src_all, v), voxel_downsample(dst_all, v)
    if min(src.shape[0], dst.shape[0]) < 10:
        raise InvalidCloudError(
            f"global registration: {src.shape[0]} source and {dst.shape[0]} target voxels of {v:g} m; "
            "at least 10 each are needed (a smaller voxel_m?)"
        )
    t0 = lap("downsample", t0)
    src_tree, dst_tree = cKDTree(src), cKDTree(dst)
    src_n = _normals(src, src_tree, s.normal_radius_voxels * v, s.normal_neighbors)
    dst_n = _normals(dst, dst_tree, s.normal_radius_voxels * v, s.normal_neighbors)
    t0 = lap("normals", t0)
    radius = s.feature_radius_voxels * v
    src_f = fpfh(src, src_n, src_tree, radius, s.max_neighbors)
    dst_f = fpfh(dst, dst_n, dst_tree, radius, s.max_neighbors)
    t0 = lap("features", t0)
    si, ti = _correspondences(src_f, dst_f, s.max_correspondences)
    t0 = lap("match", t0)
    noise = s.noise_bound_voxels * v
    a, b = src[si], dst[ti]
    T = np.eye(4)
    inliers = np.empty(0, np.int64)
    if si.size >= 3:
        adjacency = consistency_graph(a, b, 2.0 * noise)
        core = core_numbers(adjacency)
        clique = _greedy_clique(adjacency, np.nonzero(core == core.max())[0])
        t0 = lap("prune", t0)
        if clique.size >= 3:
            T, mask = _gnc_tls(a[clique], b[clique], noise)
            inliers = clique[mask]
    t0 = lap("solve", t0)
    T_coarse = T.copy()

    def overlap_of(T_: np.ndarray) -> float:
        d, _ = dst_tree.query(transform_points(T_, src), k=1, distance_upper_bound=noise)
        return float(np.mean(np.isfinite(d)))

    reason = ""
    overlap = overlap_of(T_coarse)
    refined_kept, anisotropy = False, float("nan")
    if inliers.size < s.min_inliers:
        reason = f"{inliers.size} consistent correspondences, fewer than {s.min_inliers}"
    elif s.refine:
        try:
            # The coarse pose is within a few v: NDT levels coarser than refine_coarsest_voxels * v
            # have nothing to find.
            refined = register(
                src_all, dst_all, T_coarse, settings=s.registration,
                coarsest_voxel_m=s.refine_coarsest_voxels * v,
            )  # fmt: skip
        except (RegistrationFailedError, DegenerateProblemError) as exc:
            # a corridor's refinement may not constrain every axis: a reason, not a crash
            reason = f"NDT refinement failed: {exc}"
        else:
            T_ref = refined.T_target_source
            shift = float(np.linalg.norm(T_ref[:3, 3] - T_coarse[:3, 3]))
            turn = rotation_angle_deg(T_coarse[:3, :3].T @ T_ref[:3, :3])
            refined_overlap = overlap_of(T_ref)
            if shift > s.max_refine_shift_voxels * v or turn > s.max_refine_rotation_deg:
                reason = (
                    f"NDT refinement moved the coarse pose {shift:.3g} m / {turn:.3g} deg "
                    f"(limits {s.max_refine_shift_voxels * v:.3g} m / {s.max_refine_rotation_deg:g} deg)"
                )
            else:
                # NDT can slide along a partial overlap (docs/registration.md, "Global
                # registration"): keep it only when it keeps the verified correspondences.
                r2 = np.sum((transform_points(T_ref, a[inliers]) - b[inliers]) ** 2, axis=1)
                if np.count_nonzero(r2 <= noise**2) >= KEPT_INLIER_FRACTION * inliers.size:
                    T, overlap, refined_kept = T_ref, refined_overlap, True
                    anisotropy = _anisotropy(refined.covariance)
    t0 = lap("refine", t0)
    if not reason and overlap < s.min_overlap:
        reason = f"overlap {overlap:.2f} below {s.min_overlap:g}"
    lap("judge", t0)
    return GlobalResult(
        T_target_source=T,
        T_coarse=T_coarse,
        confident=not reason,
        reason=reason,
        voxel_m=float(v),
        n_source_points=int(src.shape[0]),
        n_target_points=int(dst.shape[0]),
        n_correspondences=int(si.size),
        n_inliers=int(inliers.size),
        overlap=overlap,
        refined=refined_kept,
        anisotropy=anisotropy,
        time_s=time.perf_counter() - t_start,
        stage_times_s=times,
    )


def _anisotropy(covariance: np.ndarray) -> float:
    """Largest over smallest translation sigma of a (t, r) covariance; nan when it is not finite."""
    c = np.asarray(covariance, dtype=np.float64)[:3, :3]
    if not np.all(np.isfinite(c)):
        return float("nan")
    ev = np.linalg.eigvalsh(0.5 * (c + c.T))
    return float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float("inf")
