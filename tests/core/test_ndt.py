"""NDT score: analytic gradient and Hessian against finite differences; constants; IQR; Kabsch."""

from __future__ import annotations

import numpy as np
import pytest

from randt.core.ndt import about_origin, ndt_constants, ndt_cost, ndt_derivatives, ndt_newton
from randt.core.outliers import iqr_inlier_mask, tukey_fences
from randt.core.scenes import synthetic_room as _box_room
from randt.core.transforms import apply_update, make_transform, transform_points
from randt.core.voxel import VoxelGaussianMap, voxel_downsample


@pytest.fixture(scope="module")
def problem():
    rng = np.random.default_rng(0)
    target = _box_room(rng) + 0.02 * rng.normal(size=(1, 3))
    gmap = VoxelGaussianMap.build(target, 1.0)
    consts = ndt_constants(1.0)
    T = make_transform(euler_deg=(1.0, 2.0, 3.0), translation=(0.3, -0.2, 0.1))
    source = voxel_downsample(_box_room(rng), 0.5)
    # Keep points well inside their voxels so the tiny steps below never change the neighbour sets
    # (the NDT cost is piecewise smooth: it jumps where a point crosses a voxel boundary).
    q = transform_points(T, source)
    frac = q - np.floor(q)
    source = source[np.minimum(frac, 1 - frac).min(axis=1) > 0.02]
    return source, gmap, consts, T


def test_gradient_matches_central_differences(problem) -> None:
    source, gmap, consts, T = problem
    ev = ndt_derivatives(source, T, gmap, consts)
    h = 1e-6
    fd = np.array(
        [
            (
                ndt_cost(source, apply_update(h * e, T), gmap, consts)
                - ndt_cost(source, apply_update(-h * e, T), gmap, consts)
            )
            / (2 * h)
            for e in np.eye(6)
        ]
    )
    np.testing.assert_allclose(ev.gradient, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def test_hessian_matches_second_differences(problem) -> None:
    source, gmap, consts, T = problem
    ev = ndt_derivatives(source, T, gmap, consts)

    def f(d: np.ndarray) -> float:
        return ndt_cost(source, apply_update(d, T), gmap, consts)

    h = 3e-5
    E = np.eye(6) * h
    fd = np.array(
        [
            [
                (f(E[i] + E[j]) - f(E[i] - E[j]) - f(-E[i] + E[j]) + f(-E[i] - E[j])) / (4 * h * h)
                for j in range(6)
            ]
            for i in range(6)
        ]
    )
    assert np.abs(ev.hessian - fd).max() < 2e-3 * np.abs(fd).max()


def test_about_origin_matches_the_origin_evaluation(problem) -> None:
    """Newton's derivatives about the moving points' centroid, re-expressed about the origin,
    are what ndt_derivatives gives about the origin at the converged pose (the registration's
    judge reuses them for the covariance): gradient and Gauss-Newton Hessian exactly, the full
    Hessian up to the gradient-proportional second-order term."""
    source, _, consts, T = problem
    far = np.array([300.0, -200.0, 10.0])  # far from the origin, as a long drive's poses are
    shifted = VoxelGaussianMap.build(transform_points(T, source) + far, 1.0)
    start = make_transform(translation=(far[0] + 0.05, far[1] - 0.04, far[2]), rotvec=(0.0, 0.0, 0.01)) @ T
    out = ndt_newton(source, shifted, consts, start, translation_eps_m=1e-6, rotation_eps_rad=1e-7)
    assert out.converged
    assert np.linalg.norm(out.pivot - far) < 6.0  # the pivot is the centroid, not the origin
    direct = ndt_derivatives(source, out.T, shifted, consts)
    moved = about_origin(out.evaluation, out.pivot)
    np.testing.assert_allclose(moved.gauss_newton_hessian, direct.gauss_newton_hessian, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(moved.gradient, direct.gradient, atol=1e-6 * np.abs(direct.hessian).max())
    assert np.abs(moved.hessian - direct.hessian).max() < 1e-4 * np.abs(direct.hessian).max()
    # without the re-expression the rotation blocks are far off: the test can fail
    assert np.abs(out.evaluation.hessian - direct.hessian).max() > 0.1 * np.abs(direct.hessian).max()


def test_constants_reproduce_the_mixture_at_zero_and_one_sigma() -> None:
    """d1 exp(-d2 m/2) + d3 equals -log(c1 exp(-m/2) + c2) at m = 0 and m = 1 (Magnusson eq. 6.9)."""
    for res, ratio in [(1.0, 0.55), (2.0, 0.3), (0.005, 0.55)]:
        c = ndt_constants(res, ratio)
        c1, c2 = 10 * (1 - ratio), ratio / res**3
        d3 = -np.log(c2)
        for m in (0.0, 1.0):
            assert c.d1 * np.exp(-c.d2 * m / 2) + d3 == pytest.approx(
                -np.log(c1 * np.exp(-m / 2) + c2), rel=1e-12
            )
        assert c.d1 < 0 < c.d2


def test_tukey_fences_by_hand() -> None:
    # quartiles of 1..9 with linear interpolation: Q1 = 3, Q3 = 7, IQR = 4
    lo, hi = tukey_fences(np.arange(1.0, 10.0), k=1.5)
    assert (lo, hi) == (-3.0, 13.0)


def test_iqr_removes_planted_outliers_only() -> None:
    rng = np.random.default_rng(1)
    # dense 1 m cells: flat patches; one far point planted inside each of 20 cells
    cells = rng.integers(0, 30, size=(20, 2)).astype(float)
    patch = np.concatenate(
        [
            np.c_[
                c[0] + rng.uniform(0.1, 0.9, (200, 1)),
                c[1] + rng.uniform(0.1, 0.9, (200, 1)),
                0.5 + 0.005 * rng.normal(size=(200, 1)),
            ]
            for c in cells
        ]
    )
    planted = np.c_[cells + 0.5, np.full(20, 0.95)]
    pts = np.vstack([patch, planted])
    keep = iqr_inlier_mask(pts, 1.0, k=3.0)
    assert not keep[-20:].any(), "every planted point sits 90 sigma off its voxel's plane"
    assert keep[:-20].mean() > 0.99
