"""The paper's Algorithm 3: SVD (Kabsch/Umeyama) alignment of corresponding points.

Both point sets are centred and scaled to unit RMS radius before the SVD (scale is only an
intermediate normalization that conditions the 3x3 cross-covariance); the rotation is scale
invariant, and the returned transform is rigid (Umeyama 1991, eq. 39-42 without the scale).
"""

from __future__ import annotations

import numpy as np

__all__ = ["kabsch"]


def kabsch(source_xyz: np.ndarray, target_xyz: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Rigid 4x4 ``T`` minimising ``sum w_i |T s_i - t_i|^2`` over corresponding rows.

    Parameters
    ----------
    source_xyz, target_xyz : (N,3) float64, row i of one corresponds to row i of the other.
    weights : (N,) non-negative, optional.
    """
    if source_xyz.shape != target_xyz.shape or source_xyz.shape[0] < 3:
        raise ValueError("kabsch needs two (N,3) arrays of the same shape with N >= 3")
    w = np.ones(source_xyz.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mu_s = w @ source_xyz
    mu_t = w @ target_xyz
    s = source_xyz - mu_s
    t = target_xyz - mu_t
    # Intermediate normalization: unit weighted RMS radius for both sets.
    s /= max(np.sqrt(w @ np.einsum("ij,ij->i", s, s)), 1e-12)
    t /= max(np.sqrt(w @ np.einsum("ij,ij->i", t, t)), 1e-12)
    cross = (t * w[:, None]).T @ s
    U, _, Vt = np.linalg.svd(cross)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mu_t - R @ mu_s
    return T
