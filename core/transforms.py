"""Rigid transforms: 4x4 homogeneous matrices, small-perturbation updates and error measures.

Conventions
-----------
``T_a_b`` maps points of frame ``b`` into frame ``a``: ``p_a = T_a_b @ p_b``.
A 6-vector perturbation ``delta = (tx, ty, tz, rx, ry, rz)`` (translation first, as in ROS pose
covariances) updates a transform on the left: ``T <- exp(delta) @ T`` with
``exp(delta) = [[R(r), t], [0, 1]]`` and ``R(r)`` the rotation vector ``r``'s rotation (the
"decoupled" left update used by the NDT derivatives in :mod:`randt.core.ndt`).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from randt.core.errors import InvalidCloudError

__all__ = [
    "apply_update",
    "as_transform",
    "invert",
    "make_transform",
    "orthonormalize",
    "rotation_angle_deg",
    "scale_motion",
    "transform_error",
    "transform_points",
    "umeyama",
    "yawed",
]


def as_transform(T: np.ndarray | None, *, name: str = "transform") -> np.ndarray:
    """Validate and copy a 4x4 rigid transform (``None`` gives the identity)."""
    if T is None:
        return np.eye(4)
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{name} must be a finite 4x4 matrix, got shape {T.shape}")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise ValueError(f"{name} last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
        raise ValueError(f"{name} rotation block is not a proper rotation")
    return T.copy()


def make_transform(
    rotvec: npt.ArrayLike | None = None,
    translation: npt.ArrayLike | None = None,
    *,
    euler_deg: tuple[float, float, float] | None = None,
) -> np.ndarray:
    """Build a 4x4 transform from a rotation vector (rad) or xyz Euler angles (deg) and a translation."""
    T = np.eye(4)
    if euler_deg is not None:
        T[:3, :3] = Rotation.from_euler("xyz", euler_deg, degrees=True).as_matrix()
    elif rotvec is not None:
        T[:3, :3] = Rotation.from_rotvec(np.asarray(rotvec, dtype=np.float64)).as_matrix()
    if translation is not None:
        T[:3, 3] = np.asarray(translation, dtype=np.float64)
    return T


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Project the rotation block back onto SO(3) (long products of transforms drift off it)."""
    out = T.copy()
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4,4) transform or of each of an (M,4,4) stack: ``[[R^T, -R^T t], [0, 1]]``.

    Exact (no general matrix inverse).
    """
    if T.ndim == 3:
        Ts = np.zeros_like(T)
        Rt = np.swapaxes(T[:, :3, :3], 1, 2)
        Ts[:, :3, :3] = Rt
        Ts[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
        Ts[:, 3, 3] = 1.0
        return Ts
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def transform_points(T: np.ndarray, points_xyz: np.ndarray) -> np.ndarray:
    """Apply ``T`` (4x4) to ``points_xyz`` (N,3); returns (N,3) float64.

    Column by column (``x R[i,0] + y R[i,1] + z R[i,2] + t[i]``), not ``points @ R.T``: an (N,3)
    by (3,3) product goes through BLAS, whose threads on an oversubscribed machine cost far more
    than these nine fused multiply-adds over columns.
    """
    pts = np.asarray(points_xyz, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    if pts.ndim != 2:
        single: np.ndarray = pts @ R.T + t  # one point (3,): no BLAS threads for that
        return single
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    moved = np.empty((pts.shape[0], 3))
    for i in range(3):
        col = moved[:, i]
        np.multiply(x, R[i, 0], out=col)
        col += y * R[i, 1]
        col += z * R[i, 2]
        col += t[i]
    return moved


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a rotation vector (Rodrigues; series below 1e-4 rad): what
    ``Rotation.from_rotvec(rotvec).as_matrix()`` gives, to rounding (tested), for one rotation
    without scipy's per-call overhead (the matcher does this several times a sweep: pose updates,
    motion scaling, convergence checks)."""
    x, y, z = float(rotvec[0]), float(rotvec[1]), float(rotvec[2])
    theta2 = x * x + y * y + z * z
    if theta2 < 1e-8:
        a, b = 1.0 - theta2 / 6.0, 0.5 - theta2 / 24.0
    else:
        theta = math.sqrt(theta2)
        a, b = math.sin(theta) / theta, (1.0 - math.cos(theta)) / theta2
    return np.array(
        [
            [1.0 - b * (y * y + z * z), b * x * y - a * z, b * x * z + a * y],
            [b * x * y + a * z, 1.0 - b * (x * x + z * z), b * y * z - a * x],
            [b * x * z - a * y, b * y * z + a * x, 1.0 - b * (x * x + y * y)],
        ]
    )


def so3_log(R: np.ndarray) -> np.ndarray:
    """(3,) rotation vector of a rotation matrix: ``Rotation.from_matrix(R).as_rotvec()`` to
    rounding (tested, near 0 and 180 degrees too), by the same route (Shepperd's quaternion: the
    largest of its four components first, then the angle by ``atan2``), without scipy's per-call
    overhead (:func:`so3_exp`)."""
    m = R.tolist()
    r00, r01, r02 = m[0]
    r10, r11, r12 = m[1]
    r20, r21, r22 = m[2]
    trace = r00 + r11 + r22
    big = max(trace, r00, r11, r22)
    if big == trace:
        w = 0.5 * math.sqrt(max(1.0 + trace, 0.0))
        f = 0.25 / w
        qx, qy, qz, qw = (r21 - r12) * f, (r02 - r20) * f, (r10 - r01) * f, w
    elif big == r00:
        qx = 0.5 * math.sqrt(max(1.0 + r00 - r11 - r22, 0.0))
        f = 0.25 / qx
        qy, qz, qw = (r01 + r10) * f, (r02 + r20) * f, (r21 - r12) * f
    elif big == r11:
        qy = 0.5 * math.sqrt(max(1.0 - r00 + r11 - r22, 0.0))
        f = 0.25 / qy
        qx, qz, qw = (r01 + r10) * f, (r12 + r21) * f, (r02 - r20) * f
    else:
        qz = 0.5 * math.sqrt(max(1.0 - r00 - r11 + r22, 0.0))
        f = 0.25 / qz
        qx, qy, qw = (r02 + r20) * f, (r12 + r21) * f, (r10 - r01) * f
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if qw < 0.0:
        norm = -norm
    qx, qy, qz, qw = qx / norm, qy / norm, qz / norm, qw / norm
    n = math.sqrt(qx * qx + qy * qy + qz * qz)
    angle = 2.0 * math.atan2(n, qw)
    if angle <= 1e-3:
        scale = 2.0 + angle * angle / 12.0 + 7.0 * angle**4 / 2880.0
    else:
        scale = angle / math.sin(0.5 * angle)
    return np.array([scale * qx, scale * qy, scale * qz])


def apply_update(delta: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Left-update ``T`` by the 6-vector ``delta = (t, r)``: ``exp(delta) @ T`` (module docstring)."""
    U = np.eye(4)
    U[:3, :3] = so3_exp(delta[3:6])
    U[:3, 3] = delta[:3]
    updated: np.ndarray = U @ T
    return updated


def _skew(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _se3_left_jacobian(w: np.ndarray) -> np.ndarray:
    """``V(w)`` with ``exp([w, u]) = [[R(w), V(w) u], [0, 1]]`` (series near ``|w| = 0``)."""
    theta2 = float(w @ w)
    W = _skew(w)
    if theta2 < 1e-10:
        V: np.ndarray = np.eye(3) + 0.5 * W + W @ W / 6.0
        return V
    theta = np.sqrt(theta2)
    V = np.eye(3) + (1.0 - np.cos(theta)) / theta2 * W + (theta - np.sin(theta)) / (theta2 * theta) * W @ W
    return V


def se3_log(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(w, u)`` with ``T = exp([w, u])``: the rotation vector and the screw's translation
    (``T[:3, 3] = V(w) u``), for rotations under 180 degrees."""
    w = so3_log(T[:3, :3])
    u: np.ndarray = np.linalg.solve(_se3_left_jacobian(w), T[:3, 3])
    return w, u


def scale_motion(T: np.ndarray, k: float) -> np.ndarray:
    """``T`` to the real power ``k``: the same screw motion, ``k`` times as long.

    ``exp(k log T)`` on SE(3) (rotation and translation move together along the screw, so a car
    turning at constant speed is extrapolated along its arc): the motion over one sweep period
    scaled to ``k`` periods. Equal to ``scipy.linalg.fractional_matrix_power(T, k)`` for rotations
    under 180 degrees (tested), in closed form.
    """
    if k == 1.0:
        return T.copy()
    w, u = se3_log(T)
    out = np.eye(4)
    out[:3, :3] = so3_exp(k * w)
    out[:3, 3] = _se3_left_jacobian(k * w) @ (k * u)
    return out


def yawed(T: np.ndarray, yaw_deg: float) -> np.ndarray:
    """``T`` turned by ``yaw_deg`` about its own z axis (a pose's heading changed in place)."""
    a = math.radians(yaw_deg)
    R = np.eye(4)
    R[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    out: np.ndarray = T @ R
    return out


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a 3x3 rotation in degrees (robust near 0 and 180 degrees)."""
    return math.degrees(float(np.linalg.norm(so3_log(R))))


def transform_error(T_estimate: np.ndarray, T_reference: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of ``inv(T_reference) @ T_estimate``."""
    E = invert(T_reference) @ T_estimate
    return float(np.linalg.norm(E[:3, 3])), rotation_angle_deg(E[:3, :3])


def umeyama(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    with_scale: bool = False,
) -> tuple[np.ndarray, float]:
    """Rigid (Kabsch) or similarity (Umeyama 1991) fit of corresponding rows: ``(T, c)``.

    Minimises ``sum_i w_i |y_i - (c R x_i + t)|^2`` with ``x`` = source and ``y`` = target rows.
    With ``mu`` the weighted means and ``x' = x - mu_x``, ``y' = y - mu_y``:

    .. math::

        \\Sigma = \\sum_i w_i y'_i x_i'^T = U D V^T, \\quad
        S = \\mathrm{diag}(1, 1, \\det U \\det V)

        R = U S V^T, \\quad
        c = \\frac{\\mathrm{tr}(D S)}{\\sigma_x^2}, \\quad
        \\sigma_x^2 = \\sum_i w_i |x'_i|^2, \\quad
        t = \\mu_y - c R \\mu_x

    (eqs. 40-42 of the paper, weights normalised to sum 1; ``c = 1`` when ``with_scale`` is False,
    Kabsch's rigid fit, the closed-form step of the paper's Algorithm 3). Both centred sets are
    scaled to unit weighted RMS radius before the SVD: the rotation is scale invariant and the
    3x3 cross-covariance is better conditioned; ``c`` is scaled back.

    Parameters
    ----------
    source_xyz, target_xyz : (N,3) float64 corresponding rows, N >= 3.
    weights : (N,) non-negative, optional (all equal when ``None``).
    with_scale : estimate ``c`` (Sim(3)); otherwise a rigid SE(3) fit.

    Returns
    -------
    T_target_source : (4,4) float64 ``[[c R, t], [0, 1]]``.
    scale : float ``c`` (1.0 without ``with_scale``).

    Raises
    ------
    InvalidCloudError
        Mismatched shapes, fewer than 3 rows, or a source with no spread (all rows equal).
    """
    if source_xyz.shape != target_xyz.shape or source_xyz.ndim != 2 or source_xyz.shape[0] < 3:
        raise InvalidCloudError(
            f"umeyama needs two (N,3) arrays with N >= 3, got {source_xyz.shape} and {target_xyz.shape}"
        )
    w = np.ones(source_xyz.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mu_s = w @ source_xyz
    mu_t = w @ target_xyz
    s = source_xyz - mu_s
    t = target_xyz - mu_t
    radius_s = float(np.sqrt(w @ np.einsum("ij,ij->i", s, s)))
    if radius_s <= 0.0:
        raise InvalidCloudError("umeyama: all source points coincide; the alignment is undefined")
    radius_t = float(np.sqrt(w @ np.einsum("ij,ij->i", t, t)))
    # Intermediate normalization: unit weighted RMS radius for both sets.
    s /= max(radius_s, 1e-12)
    t /= max(radius_t, 1e-12)
    cross = (t * w[:, None]).T @ s
    U, D, Vt = np.linalg.svd(cross)
    signs = np.array([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ np.diag(signs) @ Vt
    scale = 1.0
    if with_scale:
        # tr(D S) of the normalised sets is tr(D S) / (radius_s radius_t) of the centred ones.
        scale = float(D @ signs) * max(radius_t, 1e-12) / max(radius_s, 1e-12)
        R = scale * R
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mu_t - R @ mu_s
    return T, scale
