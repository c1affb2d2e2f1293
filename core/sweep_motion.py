"""A sweep's pose and the motion during it, found together on a fixed map (one Newton solve).

A sweep's points are measured over its period; deskewed with the motion during it (a function
of a few parameters: forward and sideways metres and yaw degrees a period, say), they fit the
map best at the right pose *and* the right motion. :func:`pose_and_motion_on_map` minimises the
NDT cost over both at once: the pose's left perturbation about the points' centroid (6) and the
motion's parameters (k), by Newton steps on the chained per-point derivatives
(:func:`randt.core.ndt.ndt_point_derivatives`), the motion's point Jacobians by central
differences of the caller's deskew. It replaces a pattern search over the motion with a full pose
match at each probe (docs/mapping.md, "In the service").

Stages of each iteration::

    derivatives -> per point, the cost's gradient and Hessian w.r.t. the moved point
    chain       -> by the pose's Jacobian [I, -[q - c]x] and the motion's (R dd/dm)
    step        -> Newton direction (Hessian made positive definite), clamped to a trust region
    line search -> halved until the cost decreases (the sweep deskewed again at each try)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from randt.core.ndt import (
    NdtConstants,
    NeighborCache,
    apply_update_about,
    ndt_cost,
    ndt_point_derivatives,
)
from randt.core.transforms import transform_points
from randt.core.voxel import VoxelGaussianMap

__all__ = ["PoseAndMotion", "pose_and_motion_on_map"]

#: Halvings of a step before the line search gives up (a minimum, numerically).
_HALVINGS = 8


@dataclass(frozen=True)
class PoseAndMotion:
    """What :func:`pose_and_motion_on_map` reached: the pose, the motion's parameters, the cost
    there and the Newton iterations taken."""

    T: np.ndarray
    motion: np.ndarray
    cost: float
    iterations: int


def _cross_matrices(r: np.ndarray) -> np.ndarray:
    """``-[r]x`` for each row of ``r`` (N,3): the rotation's columns of the pose Jacobian."""
    z = np.zeros(len(r))
    skew = np.array([[z, -r[:, 2], r[:, 1]], [r[:, 2], z, -r[:, 0]], [-r[:, 1], r[:, 0], z]])
    out: np.ndarray = -skew.transpose(2, 0, 1)
    return out


def _direction(gradient: np.ndarray, hessian: np.ndarray) -> np.ndarray:
    """Newton direction with the Hessian's eigenvalues mirrored and floored (as ``ndt_newton``)."""
    evals, evecs = np.linalg.eigh(0.5 * (hessian + hessian.T))
    top = max(float(np.abs(evals).max()), 1e-12)
    evals = np.maximum(np.abs(evals), 1e-6 * top)
    out: np.ndarray = -(evecs @ ((evecs.T @ gradient) / evals))
    return out


def pose_and_motion_on_map(
    deskewed: Callable[[np.ndarray], np.ndarray],
    motion: np.ndarray,
    motion_step: np.ndarray,
    motion_eps: np.ndarray,
    T: np.ndarray,
    gmap: VoxelGaussianMap,
    consts: NdtConstants,
    *,
    max_iterations: int = 20,
    translation_eps_m: float = 1e-3,
    rotation_eps_rad: float = 1e-4,
    max_step_rad: float = 0.05,
) -> PoseAndMotion:
    """The pose ``T`` and motion parameters (from ``motion``, k of them) with which the points
    ``deskewed(motion)`` (N,3, the sweep's frame) fit ``gmap`` best (module docstring).

    ``motion_step`` (k,): the largest step of each parameter in one iteration (with a quarter
    voxel of translation and ``max_step_rad`` of rotation: the trust region, the whole step
    scaled down together) and, a tenth of it, the central difference of its Jacobian.
    Converged when a step moves less than ``translation_eps_m``, ``rotation_eps_rad`` and
    ``motion_eps`` (k,)."""
    motion = np.asarray(motion, dtype=np.float64).copy()
    motion_step = np.asarray(motion_step, dtype=np.float64)
    k = motion.size
    cloud = deskewed(motion)
    n = cloud.shape[0]
    cache = NeighborCache.empty(n, 7)
    pivot = transform_points(T, cloud.mean(axis=0, keepdims=True))[0]
    max_step_m = 0.25 * gmap.voxel_size_m
    h = motion_step / 10.0
    J = np.zeros((n, 3, 6 + k))
    J[:, :, :3] = np.eye(3)
    cost = ndt_cost(cloud, T, gmap, consts, cache=cache)
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 - iterations count is returned
        d = ndt_point_derivatives(cloud, T, gmap, consts, cache=cache)
        q = transform_points(T, cloud)
        J[:, :, 3:6] = _cross_matrices(q - pivot)
        for j in range(k):
            e = np.zeros(k)
            e[j] = h[j]
            dd = (deskewed(motion + e) - deskewed(motion - e)) / (2.0 * h[j])
            J[:, :, 6 + j] = dd @ T[:3, :3].T
        gradient = np.einsum("nij,ni->j", J, d.gradient)
        hessian = np.einsum("nki,nkl,nlj->ij", J, d.hessian, J)
        aq = d.gradient.T @ (q - pivot)  # the rotation's second-order term (as ndt_derivatives)
        hessian[3:6, 3:6] += 0.5 * (aq + aq.T) - np.eye(3) * np.trace(aq)
        step = _direction(gradient, hessian)
        scale = min(
            1.0,
            max_step_m / max(float(np.linalg.norm(step[:3])), 1e-15),
            max_step_rad / max(float(np.linalg.norm(step[3:6])), 1e-15),
            *(float(s) / max(abs(float(v)), 1e-15) for s, v in zip(motion_step, step[6:], strict=True)),
        )
        step *= scale
        slope = float(gradient @ step)
        alpha, accepted = 1.0, False
        for _ in range(_HALVINGS + 1):
            T_try = apply_update_about(alpha * step[:6], T, pivot)
            m_try = motion + alpha * step[6:]
            cloud_try = deskewed(m_try)
            cost_try = ndt_cost(cloud_try, T_try, gmap, consts, cache=cache)
            if cost_try <= cost + 1e-4 * alpha * slope:
                accepted = True
                break
            alpha *= 0.5
        if not accepted:
            break  # no decrease along a descent direction: a minimum, numerically
        T, motion, cloud, cost = T_try, m_try, cloud_try, cost_try
        small = alpha * step
        if (
            np.linalg.norm(small[:3]) < translation_eps_m
            and np.linalg.norm(small[3:6]) < rotation_eps_rad
            and np.all(np.abs(small[6:]) < motion_eps)
        ):
            break
    return PoseAndMotion(T, motion, cost, it)
