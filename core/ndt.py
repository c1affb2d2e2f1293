"""Point-to-distribution NDT (Magnusson 2009): score, analytic gradient and Hessian, Newton solver.

The cost minimised is the negative log-likelihood of the moving points under the reference's
voxel Gaussians, with Magnusson's Gaussian approximation of the Gaussian + uniform-outlier mixture
(eq. 6.8-6.9)::

    f(T) = sum over (point i, voxel v) pairs of  d1 * exp(-d2/2 * x^T Sigma_v^-1 x),   x = T p_i - mu_v

with ``c1 = 10 (1 - outlier_ratio)``, ``c2 = outlier_ratio / voxel_size^3``, ``d3 = -log c2``,
``d1 = -log(c1 + c2) - d3`` (negative) and ``d2 = -2 log((-log(c1 e^-1/2 + c2) - d3) / d1)``.

Derivatives are taken w.r.t. the left perturbation ``delta = (t, r)`` of :mod:`randt.core.transforms`:
``x(delta) = R(r) q + t - mu`` with ``q = T p``, so ``dx/dt = I``, ``dx/dr = -[q]x`` and the
second derivative ``d2x/dr_i dr_j = (e_i x (e_j x q) + e_j x (e_i x q)) / 2``. With
``a = Sigma^-1 x``, ``m = x^T a``, ``e = exp(-d2 m / 2)`` and ``w = -d1 d2 e`` (> 0)::

    gradient  g = sum w * J^T a                                     (Magnusson eq. 6.12)
    Hessian   H = sum w * (-d2 (J^T a)(J^T a)^T + J^T Sigma^-1 J + S(a, q))    (eq. 6.13)

where ``S`` is the rotation-rotation block ``S_ij = (a_i q_j + a_j q_i)/2 - (a.q) delta_ij``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from randt.core import kernels
from randt.core.transforms import apply_update, transform_points
from randt.core.voxel import NEIGHBOR_OFFSETS, VoxelGaussianMap

__all__ = [
    "NdtConstants",
    "NdtEvaluation",
    "PointDerivatives",
    "apply_update_about",
    "ndt_constants",
    "ndt_cost",
    "ndt_cost_numpy",
    "ndt_derivatives",
    "ndt_derivatives_numpy",
    "ndt_newton",
    "ndt_point_derivatives",
    "ndt_point_derivatives_numpy",
    "ndt_point_scores",
    "ndt_point_scores_numpy",
]


@dataclass(frozen=True)
class NdtConstants:
    """Magnusson's d1, d2 (eq. 6.9) for one voxel size and outlier ratio."""

    d1: float
    d2: float


def ndt_constants(voxel_size_m: float, outlier_ratio: float = 0.55) -> NdtConstants:
    """Constants of the Gaussian approximation of the outlier mixture (Magnusson eq. 6.9).

    ``outlier_ratio`` 0.55 is PCL's and Autoware's default.
    """
    if not 0.0 < outlier_ratio < 1.0:
        raise ValueError(f"outlier_ratio must be in (0, 1), got {outlier_ratio}")
    c1 = 10.0 * (1.0 - outlier_ratio)
    c2 = outlier_ratio / voxel_size_m**3
    d3 = -np.log(c2)
    d1 = -np.log(c1 + c2) - d3
    d2 = -2.0 * np.log((-np.log(c1 * np.exp(-0.5) + c2) - d3) / d1)
    return NdtConstants(d1=float(d1), d2=float(d2))


@dataclass(frozen=True)
class NdtEvaluation:
    """Cost, gradient (6,) and Hessian (6,6) of the NDT cost at one pose, plus pair counts."""

    cost: float
    gradient: np.ndarray
    hessian: np.ndarray
    gauss_newton_hessian: np.ndarray
    n_pairs: int


def about_origin(ev: NdtEvaluation, pivot: np.ndarray) -> NdtEvaluation:
    """``ev`` (derivatives w.r.t. a left perturbation about ``pivot``) re-expressed about the
    target frame's origin, as :func:`ndt_derivatives` with ``pivot=None`` gives them.

    To first order a perturbation ``(t', r)`` about the origin is ``(t' + r x pivot, r)`` about
    ``pivot``: ``J = [[I, -[pivot]x], [0, I]]``, ``g' = J^T g`` and ``H' = J^T H J``. The two
    parametrizations differ at second order by a term proportional to the gradient, which is
    zero at a converged pose (Test: tests/core/test_ndt.py::test_about_origin_matches_the_origin_evaluation).
    """
    px, py, pz = (float(v) for v in pivot)
    J = np.eye(6)
    J[:3, 3:] = -np.array([[0.0, -pz, py], [pz, 0.0, -px], [-py, px, 0.0]])
    return replace(
        ev,
        gradient=J.T @ ev.gradient,
        hessian=J.T @ ev.hessian @ J,
        gauss_newton_hessian=J.T @ ev.gauss_newton_hessian @ J,
    )


#: Pairs whose term ``exp(-d2 m / 2)`` is below ``exp(-_PRUNE)`` (1e-13) are dropped before the
#: derivatives: they change nothing measurable and are most of DIRECT7's pairs.
_PRUNE = 30.0


def _pairs(
    q: np.ndarray, gmap: VoxelGaussianMap, n_neighbors: int, d2: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Point-voxel pairs with ``y = W x`` (whitened offsets), ``m = |y|^2`` and the pair's weight
    in the cost (:meth:`VoxelGaussianMap.neighbor_pairs`), negligible ones pruned."""
    pidx, vidx, weight = gmap.neighbor_pairs(q, n_neighbors)
    x = q[pidx] - gmap.means[vidx]
    W = gmap.whitening[vidx]
    y = np.einsum("pij,pj->pi", W, x)
    m = np.einsum("pi,pi->p", y, y)
    keep = m < (2.0 * _PRUNE / d2)
    return pidx[keep], W[keep], y[keep], m[keep], weight[keep]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (..., 3) arrays (broadcasting), cheaper than ``np.cross``."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def ndt_cost_numpy(
    points_xyz: np.ndarray,
    T: np.ndarray,
    gmap: VoxelGaussianMap,
    consts: NdtConstants,
    n_neighbors: int = 7,
) -> float:
    """The NDT cost ``f(T)`` (module docstring), vectorized numpy reference of :func:`ndt_cost`."""
    q = transform_points(T, points_xyz)
    _, _, _, m, weight = _pairs(q, gmap, n_neighbors, consts.d2)
    return float(consts.d1 * (weight * np.exp(-0.5 * consts.d2 * m)).sum())


def ndt_derivatives_numpy(
    points_xyz: np.ndarray,
    T: np.ndarray,
    gmap: VoxelGaussianMap,
    consts: NdtConstants,
    n_neighbors: int = 7,
    pivot: np.ndarray | None = None,
    cache: NeighborCache | None = None,
) -> NdtEvaluation:
    """Vectorized numpy reference of :func:`ndt_derivatives` (one row per point-voxel pair)."""
    q_all = transform_points(T, points_xyz)
    pidx, W, y, m, weight = _pairs(q_all, gmap, n_neighbors, consts.d2)
    q = q_all[pidx] - (0.0 if pivot is None else pivot)  # lever arms of the rotation
    e = weight * np.exp(-0.5 * consts.d2 * m)  # the weights held constant in the derivatives
    cost = float(consts.d1 * e.sum())
    w = -consts.d1 * consts.d2 * e
    a = np.einsum("pji,pj->pi", W, y)  # Sigma^-1 x = W^T y
    # J^T a = (a, q x a) for J = [I, -[q]x]
    ja = np.concatenate([a, _cross(q, a)], axis=1)  # (P,6)
    grad = ja.T @ w
    # J^T Sigma^-1 J = B^T B with B = W J, whose row r is (W_r, q x W_r): one product for all pairs.
    B = np.concatenate([W, _cross(q[:, None, :], W)], axis=2).reshape(-1, 6)  # (3P,6)
    jsj = (B * np.repeat(w, 3)[:, None]).T @ B
    outer = (ja * (w * consts.d2)[:, None]).T @ ja
    aq = (a * w[:, None]).T @ q
    s_rr = 0.5 * (aq + aq.T) - np.eye(3) * np.trace(aq)
    hess = jsj - outer
    hess[3:, 3:] += s_rr
    return NdtEvaluation(
        cost=cost,
        gradient=grad,
        hessian=0.5 * (hess + hess.T),
        gauss_newton_hessian=0.5 * (jsj + jsj.T),
        n_pairs=int(pidx.size),
    )


def ndt_point_scores_numpy(
    points_xyz: np.ndarray,
    T: np.ndarray,
    gmap: VoxelGaussianMap,
    consts: NdtConstants,
    n_neighbors: int = 7,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vectorized numpy reference of :func:`ndt_point_scores`.

    Returns
    -------
    score_sum : (N,) sum over neighbour voxels of ``-d1 exp(-d2 m / 2)`` (>= 0)
    score_max : (N,) the largest single-voxel term (0 where no voxel is near)
    best_m : (N,) squared Mahalanobis distance to the best voxel (``inf`` where none)
    """
    q = transform_points(T, points_xyz)
    pidx, _, _, m, _ = _pairs(q, gmap, n_neighbors, consts.d2)
    s = -consts.d1 * np.exp(-0.5 * consts.d2 * m)  # unweighted: a point's fit to each voxel
    n = points_xyz.shape[0]
    score_sum = np.bincount(pidx, weights=s, minlength=n)
    score_max = np.zeros(n)
    np.maximum.at(score_max, pidx, s)
    best_m = np.full(n, np.inf)
    np.minimum.at(best_m, pidx, m)
    return score_sum, score_max, best_m


_ORIGIN = np.zeros(3)


def apply_update_about(delta: np.ndarray, T: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """Left-update ``T`` by ``delta = (t, r)`` rotating about ``pivot``: ``q -> R(r)(q - c) + c + t``."""
    U = apply_update(delta, np.eye(4))
    U[:3, 3] += pivot - U[:3, :3] @ pivot
    updated: np.ndarray = U @ T
    return updated


_KernelArgs = tuple[
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, np.ndarray
]


def _kernel_args(
    points_xyz: np.ndarray, T: np.ndarray, gmap: VoxelGaussianMap, n_neighbors: int
) -> _KernelArgs:
    """The leading arguments every NDT kernel takes: points, ``R``, ``t``, the map's hash table
    (keys, indices), means, inverse covariances, voxel size and neighbour offsets."""
    return (
        np.ascontiguousarray(points_xyz, dtype=np.float64),
        np.ascontiguousarray(T[:3, :3], dtype=np.float64),
        np.ascontiguousarray(T[:3, 3], dtype=np.float64),
        *gmap.hash_table,
        gmap.means,
        gmap.inv_covariances,
        float(gmap.voxel_size_m),
        NEIGHBOR_OFFSETS[n_neighbors],
    )


@dataclass(frozen=True)
class NeighborCache:
    """Each point's cell and neighbour voxels, kept across evaluations on the same points and map
    (see :func:`randt.core.kernels.ndt_accumulate`). Make one per (points, map, neighbourhood)."""

    cells: np.ndarray
    voxels: np.ndarray

    @classmethod
    def empty(cls, n_points: int = 0, n_neighbors: int = 0) -> NeighborCache:
        return cls(
            np.full((n_points, 3), kernels.CACHE_EMPTY, dtype=np.int64),
            np.empty((n_points, n_neighbors), dtype=np.int64),
        )


_NO_CACHE = NeighborCache.empty()


def ndt_cost(
    points_xyz: np.ndarray,
    T: np.ndarray,
    gmap: VoxelGaussianMap,
    consts: NdtConstants,
    n_neighbors: int = 7,
    cache: NeighborCache | None = None,
) -> float:
    """The NDT cost ``f(T)`` (module docstring) of ``points_xyz`` moved by ``T`` (compiled kernel)."""
    cache = cache or _NO_CACHE
    g, h = np.empty(6), np.empty((6, 6))
    cost, _ = kernels.ndt_accumulate(
        *_kernel_args(points_xyz, T, gmap, n_neighbors),
        consts.d1,
        consts.d2,
        2.0 * _PRUNE / consts.d2,
        False,
        _ORIGIN,
        g,
        h,
        h,
        cache.cells,
        cache.voxels,
    )
    return float(cost)


def ndt_derivatives(
    points_xyz: np.ndarray,
    T: np.ndarray,
    gmap: VoxelGaussianMap,
    consts: NdtConstants,
    n_neighbors: int = 7,
    pivot: np.ndarray | None = None,
    cache: NeighborCache | None = None,
) -> NdtEvaluation:
    """Cost, analytic gradient and Hessian of the NDT cost at ``T`` (Magnusson eq. 6.12-6.13).

    Derivatives are w.r.t. the left perturbation about ``pivot`` (target frame; the origin when
    ``None``): ``x(delta) = R(r) (q - pivot) + pivot + t - mu`` (:func:`apply_update_about`).

    One fused pass of :func:`randt.core.kernels.ndt_accumulate`; :func:`ndt_derivatives_numpy` is the
    vectorized reference it is tested against.
    """
    cache = cache or _NO_CACHE
    grad, hess, gn = np.empty(6), np.empty((6, 6)), np.empty((6, 6))
    cost, n_pairs = kernels.ndt_accumulate(
        *_kernel_args(points_xyz, T, gmap, n_neighbors),
        consts.d1,
        consts.d2,
        2.0 * _PRUNE / consts.d2,
        True,
        _ORIGIN if pivot is None else np.ascontiguousarray(pivot, dtype=np.float64),
        grad,
        hess,
        gn,
        cache.cells,
        cache.voxels,
    )
    return NdtEvaluation(
        cost=float(cost), gradient=grad, hessian=hess, gauss_newton_hessian=gn, n_pairs=int(n_pairs)
    )


@dataclass(frozen=True)
class PointDerivatives:
    """The NDT cost and, per point, its gradient (N,3) and Hessian (N,3,3) w.r.t. the moved
    point ``q = T p`` (:func:`ndt_point_derivatives`)."""

    cost: float
    gradient: np.ndarray
    hessian: np.ndarray


def ndt_point_derivatives(
    points_xyz: np.ndarray,
    T: np.ndarray,
    gmap: VoxelGaussianMap,
    consts: NdtConstants,
    n_neighbors: int = 7,
    cache: NeighborCache | None = None,
) -> PointDerivatives:
    """Per point, the derivatives of the NDT cost w.r.t. the moved point (compiled kernel):
    ``sum w a`` and ``sum w (Sigma^-1 - d2 a a^T)`` over its pairs (module docstring). A pose's
    derivatives are these chained by ``J = [I, -[q]x]`` (plus the rotation's second-order term,
    which :func:`ndt_derivatives` adds); other parameters that move the points (a motion during
    the sweep) chain by their own Jacobians."""
    cache = cache or _NO_CACHE
    n = points_xyz.shape[0]
    grad, upper = np.empty((n, 3)), np.empty((n, 6))
    cost = kernels.ndt_point_derivatives(
        *_kernel_args(points_xyz, T, gmap, n_neighbors),
        consts.d1,
        consts.d2,
        2.0 * _PRUNE / consts.d2,
        grad,
        upper,
        cache.cells,
        cache.voxels,
    )
    hess = upper[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(n, 3, 3)
    return PointDerivatives(float(cost), grad, hess)


def ndt_point_derivatives_numpy(
    points_xyz: np.ndarray,
    T: np.ndarray,
    gmap: VoxelGaussianMap,
    consts: NdtConstants,
    n_neighbors: int = 7,
) -> PointDerivatives:
    """Vectorized numpy reference of :func:`ndt_point_derivatives` (one row per pair)."""
    q = transform_points(T, points_xyz)
    pidx, W, y, m, weight = _pairs(q, gmap, n_neighbors, consts.d2)
    e = weight * np.exp(-0.5 * consts.d2 * m)
    w = -consts.d1 * consts.d2 * e
    a = np.einsum("pji,pj->pi", W, y)  # Sigma^-1 x = W^T y
    inv_cov = np.einsum("pki,pkj->pij", W, W)
    n = points_xyz.shape[0]
    grad = np.zeros((n, 3))
    np.add.at(grad, pidx, w[:, None] * a)
    hess = np.zeros((n, 3, 3))
    terms = inv_cov - consts.d2 * np.einsum("pi,pj->pij", a, a)
    np.add.at(hess, pidx, w[:, None, None] * terms)
    return PointDerivatives(float(consts.d1 * e.sum()), grad, hess)


def ndt_point_scores(
    points_xyz: np.ndarray,
    T: np.ndarray,
    gmap: VoxelGaussianMap,
    consts: NdtConstants,
    n_neighbors: int = 7,
    cache: NeighborCache | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-point scores as Autoware reports them (compiled kernel).

    Returns
    -------
    score_sum : (N,) sum over neighbour voxels of ``-d1 exp(-d2 m / 2)`` (>= 0)
    score_max : (N,) the largest single-voxel term (0 where no voxel is near)
    best_m : (N,) squared Mahalanobis distance to the best voxel (``inf`` where none)
    """
    n = points_xyz.shape[0]
    score_sum, score_max, best_m = np.empty(n), np.empty(n), np.empty(n)
    kernels.ndt_scores(
        *_kernel_args(points_xyz, T, gmap, n_neighbors),
        consts.d1,
        consts.d2,
        2.0 * _PRUNE / consts.d2,
        score_sum,
        score_max,
        best_m,
        (cache or _NO_CACHE).cells,
        (cache or _NO_CACHE).voxels,
    )
    return score_sum, score_max, best_m


@dataclass(frozen=True)
class NewtonOutcome:
    """What :func:`ndt_newton` reached."""

    T: np.ndarray
    iterations: int
    converged: bool
    evaluation: NdtEvaluation
    cache: NeighborCache  # the points' cells and neighbour voxels, valid for further evaluations
    pivot: np.ndarray  # (3,) the point ``evaluation``'s rotations are about (:func:`about_origin`)


def _descent_direction(ev: NdtEvaluation) -> np.ndarray:
    """Newton direction with the Hessian made positive definite (eigenvalues mirrored and floored)."""
    evals, evecs = np.linalg.eigh(ev.hessian)
    top = max(float(np.abs(evals).max()), 1e-12)
    evals = np.maximum(np.abs(evals), 1e-6 * top)
    direction: np.ndarray = -(evecs @ ((evecs.T @ ev.gradient) / evals))
    return direction


def ndt_newton(
    points_xyz: np.ndarray,
    gmap: VoxelGaussianMap,
    consts: NdtConstants,
    T_init: np.ndarray,
    *,
    n_neighbors: int = 7,
    max_iterations: int = 30,
    translation_eps_m: float = 1e-4,
    rotation_eps_rad: float = 1e-5,
    max_step_m: float | None = None,
    max_step_rad: float = 0.1,
) -> NewtonOutcome:
    """Minimise the NDT cost by Newton steps with step-length control.

    Each step is the Newton direction of the (positive-definite-ified) analytic Hessian, clamped to
    ``max_step_m`` (default: a quarter voxel, a trust region where the voxel Gaussians still
    describe the cost; PCL and Autoware clamp to 0.1 m) and ``max_step_rad``, then halved until
    the cost decreases (Armijo backtracking, up to 8 halvings). Converged when a step moves less than
    ``translation_eps_m`` and ``rotation_eps_rad``; a proposed step that small is taken without
    evaluating the cost after it, so ``evaluation`` is the one made within that tolerance of the
    returned pose (one evaluation fewer per level).
    """
    if max_step_m is None:
        max_step_m = 0.25 * gmap.voxel_size_m
    T = T_init.copy()
    # Rotate about the moving points' centroid, not the target frame's origin: hundreds of metres
    # from the origin (a long drive, georeferenced maps) a rotation about the origin is mostly a
    # translation, and the clamped, eigenvalue-floored Newton step then stalls in yaw.
    pivot = transform_points(T, points_xyz.mean(axis=0, keepdims=True))[0]
    cache = NeighborCache.empty(points_xyz.shape[0], n_neighbors)
    ev = ndt_derivatives(points_xyz, T, gmap, consts, n_neighbors, pivot, cache)
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 - iterations count is returned
        if ev.n_pairs == 0:
            break
        step = _descent_direction(ev)
        scale = min(
            1.0,
            max_step_m / max(float(np.linalg.norm(step[:3])), 1e-15),
            max_step_rad / max(float(np.linalg.norm(step[3:])), 1e-15),
        )
        step *= scale
        if np.linalg.norm(step[:3]) < translation_eps_m and np.linalg.norm(step[3:]) < rotation_eps_rad:
            # A step below the tolerance: take it and stop without evaluating there (``ev``
            # stays the one a tolerance away): the evaluation would only confirm the step.
            T = apply_update_about(step, T, pivot)
            converged = True
            break
        slope = float(ev.gradient @ step)
        # Full step first, evaluated with derivatives (reused when accepted, the common case);
        # then Armijo backtracking on the cheaper cost alone.
        alpha = 1.0
        T_try = apply_update_about(step, T, pivot)
        ev_try = ndt_derivatives(points_xyz, T_try, gmap, consts, n_neighbors, pivot, cache)
        accepted = ev_try.cost <= ev.cost + 1e-4 * slope
        if not accepted:
            for _ in range(8):
                alpha *= 0.5
                T_try = apply_update_about(alpha * step, T, pivot)
                cost = ndt_cost(points_xyz, T_try, gmap, consts, n_neighbors, cache)
                if cost <= ev.cost + 1e-4 * alpha * slope:
                    accepted = True
                    ev_try = ndt_derivatives(points_xyz, T_try, gmap, consts, n_neighbors, pivot, cache)
                    break
        if not accepted:
            # No decrease along a descent direction: we sit at a (numerical) minimum.
            converged = True
            break
        T, ev = T_try, ev_try
        if (
            np.linalg.norm(alpha * step[:3]) < translation_eps_m
            and np.linalg.norm(alpha * step[3:]) < rotation_eps_rad
        ):
            converged = True
            break
    return NewtonOutcome(T=T, iterations=it, converged=converged, evaluation=ev, cache=cache, pivot=pivot)
