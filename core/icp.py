"""ICP baselines in the same framework: point-to-point (SVD) and point-to-plane (Gauss-Newton).

Both use a scipy ``cKDTree`` on the target for nearest neighbours, reject pairs farther than
``max_correspondence_m``, and stop when an update moves less than the given epsilons.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from randt.core.transforms import apply_update, rotation_angle_deg, transform_points, umeyama

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


def _icp_loop(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray,
    T_init: np.ndarray,
    step: Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, float]],
    *,
    max_correspondence_m: float,
    max_iterations: int,
    translation_eps_m: float,
    rotation_eps_rad: float,
    tree: cKDTree,
) -> IcpOutcome:
    """Shared ICP iteration: nearest neighbours within range, one ``step``, convergence test.

    ``step(q, target_points, target_index)`` returns the left update ``D`` (4x4) for the matched
    moving points ``q`` and the RMSE of the residual it minimises.
    """
    T = T_init.copy()
    converged, it, n_corr, rmse = False, 0, 0, np.inf
    for it in range(1, max_iterations + 1):  # noqa: B007 - iterations count is returned
        q = transform_points(T, source_xyz)
        dist, idx = tree.query(q, distance_upper_bound=max_correspondence_m)
        assert isinstance(idx, np.ndarray)  # (N,) for an (N,3) query
        ok = np.isfinite(dist)
        n_corr = int(ok.sum())
        if n_corr < 6:
            break
        D, rmse = step(q[ok], target_xyz[idx[ok]], idx[ok])
        T = D @ T
        if np.linalg.norm(D[:3, 3]) < translation_eps_m and rotation_angle_deg(D[:3, :3]) < np.degrees(
            rotation_eps_rad
        ):
            converged = True
            break
    return IcpOutcome(T=T, iterations=it, converged=converged, n_correspondences=n_corr, rmse_m=float(rmse))


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

    def step(q: np.ndarray, t: np.ndarray, _: np.ndarray) -> tuple[np.ndarray, float]:
        return umeyama(q, t)[0], float(np.sqrt(np.mean(np.sum((q - t) ** 2, axis=1))))

    return _icp_loop(
        source_xyz,
        target_xyz,
        T_init,
        step,
        max_correspondence_m=max_correspondence_m,
        max_iterations=max_iterations,
        translation_eps_m=translation_eps_m,
        rotation_eps_rad=rotation_eps_rad,
        tree=cKDTree(target_xyz) if tree is None else tree,
    )


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

    def step(q: np.ndarray, t: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, float]:
        n = normals[idx]
        r = np.einsum("ij,ij->i", q - t, n)
        J = np.concatenate([n, np.cross(q, n)], axis=1)
        delta = np.linalg.lstsq(J.T @ J, -J.T @ r, rcond=None)[0]
        return apply_update(delta, np.eye(4)), float(np.sqrt(np.mean(r**2)))

    return _icp_loop(
        source_xyz,
        target_xyz,
        T_init,
        step,
        max_correspondence_m=max_correspondence_m,
        max_iterations=max_iterations,
        translation_eps_m=translation_eps_m,
        rotation_eps_rad=rotation_eps_rad,
        tree=tree,
    )
