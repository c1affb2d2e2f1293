"""ICP baselines in the same framework: point-to-point (SVD) and point-to-plane (Gauss-Newton).

Both use a scipy ``cKDTree`` on the target for nearest neighbours, reject pairs farther than
``max_correspondence_m``, and stop when an update moves less than the given epsilons.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from core.svd import kabsch
from core.transforms import apply_update, transform_points

__all__ = ["IcpOutcome", "estimate_normals", "icp_point_to_plane", "icp_point_to_point"]


@dataclass(frozen=True)
class IcpOutcome:
    """What an ICP run reached."""

    T: np.ndarray
    iterations: int
    converged: bool
    n_correspondences: int
    rmse_m: float


def estimate_normals(points_xyz: np.ndarray, tree: cKDTree | None = None, k: int = 10) -> np.ndarray:
    """Unit normals (N,3): smallest-eigenvalue eigenvector of each point's k-neighbour covariance."""
    tree = cKDTree(points_xyz) if tree is None else tree
    _, idx = tree.query(points_xyz, k=k)
    nb = points_xyz[idx]  # (N,k,3)
    d = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", d, d)
    _, evecs = np.linalg.eigh(cov)
    return evecs[:, :, 0]


def _small(delta_t: float, delta_r: float, eps_t: float, eps_r: float) -> bool:
    return delta_t < eps_t and delta_r < eps_r


def icp_point_to_point(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray,
    T_init: np.ndarray,
    *,
    max_correspondence_m: float,
    max_iterations: int = 50,
    translation_eps_m: float = 1e-4,
    rotation_eps_rad: float = 1e-5,
    tree: cKDTree | None = None,
) -> IcpOutcome:
    """Point-to-point ICP: nearest neighbours, then the closed-form SVD step (Besl & McKay 1992)."""
    tree = cKDTree(target_xyz) if tree is None else tree
    T = T_init.copy()
    converged, it, n_corr, rmse = False, 0, 0, np.inf
    for it in range(1, max_iterations + 1):  # noqa: B007
        q = transform_points(T, source_xyz)
        dist, idx = tree.query(q, distance_upper_bound=max_correspondence_m)
        ok = np.isfinite(dist)
        n_corr = int(ok.sum())
        if n_corr < 6:
            break
        rmse = float(np.sqrt(np.mean(dist[ok] ** 2)))
        D = kabsch(q[ok], target_xyz[idx[ok]])
        T = D @ T
        dr = np.arccos(np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))
        if _small(np.linalg.norm(D[:3, 3]), dr, translation_eps_m, rotation_eps_rad):
            converged = True
            break
    return IcpOutcome(T=T, iterations=it, converged=converged, n_correspondences=n_corr, rmse_m=rmse)


def icp_point_to_plane(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray,
    T_init: np.ndarray,
    *,
    max_correspondence_m: float,
    max_iterations: int = 50,
    translation_eps_m: float = 1e-4,
    rotation_eps_rad: float = 1e-5,
    tree: cKDTree | None = None,
    target_normals: np.ndarray | None = None,
) -> IcpOutcome:
    """Point-to-plane ICP (Chen & Medioni 1992), one Gauss-Newton step per iteration.

    Residual ``r_i = n_i . (T s_i - t_i)``; Jacobian w.r.t. the left perturbation ``(t, r)``
    is ``(n_i, q_i x n_i)``.
    """
    tree = cKDTree(target_xyz) if tree is None else tree
    normals = estimate_normals(target_xyz, tree) if target_normals is None else target_normals
    T = T_init.copy()
    converged, it, n_corr, rmse = False, 0, 0, np.inf
    for it in range(1, max_iterations + 1):  # noqa: B007
        q = transform_points(T, source_xyz)
        dist, idx = tree.query(q, distance_upper_bound=max_correspondence_m)
        ok = np.isfinite(dist)
        n_corr = int(ok.sum())
        if n_corr < 6:
            break
        qo, n = q[ok], normals[idx[ok]]
        r = np.einsum("ij,ij->i", qo - target_xyz[idx[ok]], n)
        rmse = float(np.sqrt(np.mean(r**2)))
        J = np.concatenate([n, np.cross(qo, n)], axis=1)
        delta = np.linalg.lstsq(J.T @ J, -J.T @ r, rcond=None)[0]
        T = apply_update(delta, T)
        if _small(
            np.linalg.norm(delta[:3]),
            np.linalg.norm(delta[3:]),
            translation_eps_m,
            rotation_eps_rad,
        ):
            converged = True
            break
    return IcpOutcome(T=T, iterations=it, converged=converged, n_correspondences=n_corr, rmse_m=rmse)
