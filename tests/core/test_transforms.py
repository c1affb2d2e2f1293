"""Rigid-transform helpers against scipy's general matrix functions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import fractional_matrix_power
from scipy.spatial.transform import Rotation

from randt.core.errors import InvalidCloudError
from randt.core.transforms import (
    invert,
    make_transform,
    rotation_angle_deg,
    scale_motion,
    so3_exp,
    so3_log,
    transform_error,
    transform_points,
    umeyama,
)


@pytest.mark.parametrize("k", [0.0, 0.25, 0.5, 1.0, 2.0, 3.7, -1.0])
@pytest.mark.parametrize(
    "rotvec",
    [(0.0, 0.0, 0.0), (0.0, 0.0, 1e-9), (0.01, -0.02, 0.12), (0.3, 0.5, -1.2)],
)
def test_scale_motion_is_the_real_matrix_power(k: float, rotvec) -> None:
    T = make_transform(rotvec=rotvec, translation=(1.2, -0.3, 0.05))
    np.testing.assert_allclose(scale_motion(T, k), np.real(fractional_matrix_power(T, k)), atol=1e-9)


def test_scale_motion_composes_along_the_screw() -> None:
    """A turning car's motion over three periods is the one-period motion applied three times."""
    step = make_transform(rotvec=(0.0, 0.0, np.radians(7.0)), translation=(1.2, 0.0, 0.0))
    np.testing.assert_allclose(scale_motion(step, 3.0), step @ step @ step, atol=1e-12)
    np.testing.assert_allclose(scale_motion(scale_motion(step, 3.0), 1 / 3), step, atol=1e-12)


def test_so3_exp_and_log_are_scipys_everywhere() -> None:
    """Random rotations, angles from 1e-9 rad to within 1e-9 rad of 180 degrees: the closed
    forms give scipy's matrices and rotation vectors to rounding."""
    rng = np.random.default_rng(7)
    axes = rng.normal(size=(4000, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate(
        [
            10 ** rng.uniform(-9, -2, 1000),
            rng.uniform(0, np.pi, 1000),
            np.pi - 10 ** rng.uniform(-9, -1, 1000),
        ]
    )
    angles = np.concatenate([angles, rng.uniform(0, 3, 1000)])
    for rotvec in axes * angles[:, None]:
        R = Rotation.from_rotvec(rotvec).as_matrix()
        np.testing.assert_allclose(so3_exp(rotvec), R, rtol=0, atol=1e-14)
        np.testing.assert_allclose(so3_log(R), Rotation.from_matrix(R).as_rotvec(), rtol=0, atol=1e-12)
    assert rotation_angle_deg(Rotation.from_rotvec([0.0, 0.0, np.pi - 1e-7]).as_matrix()) == pytest.approx(
        180.0 - np.degrees(1e-7), abs=1e-9
    )
    np.testing.assert_array_equal(so3_exp(np.zeros(3)), np.eye(3))
    np.testing.assert_array_equal(so3_log(np.eye(3)), np.zeros(3))


def test_kabsch_recovers_exact_transform_and_is_rigid() -> None:
    rng = np.random.default_rng(2)
    src = rng.normal(size=(50, 3)) * [10.0, 1.0, 0.1]  # badly scaled on purpose
    T = make_transform(euler_deg=(30.0, -50.0, 120.0), translation=(5.0, -2.0, 1.0))
    est, _ = umeyama(src, transform_points(T, src))
    err_m, err_deg = transform_error(est, T)
    assert err_m < 1e-9 and err_deg < 1e-7
    assert np.linalg.det(est[:3, :3]) == pytest.approx(1.0)


def test_umeyama_recovers_a_similarity() -> None:
    rng = np.random.default_rng(1)
    x = rng.normal(0.0, 5.0, (50, 3))
    R = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix()
    y = 2.5 * x @ R.T + [10.0, -4.0, 1.0]
    T, scale = umeyama(x, y, with_scale=True)
    assert scale == pytest.approx(2.5, rel=1e-12)
    np.testing.assert_allclose(T[:3, :3], 2.5 * R, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [10.0, -4.0, 1.0], atol=1e-10)
    T_rigid, unit = umeyama(x, y, with_scale=False)
    assert unit == 1.0
    np.testing.assert_allclose(T_rigid[:3, :3], R, atol=1e-12)  # the rotation does not depend on scale
    with pytest.raises(InvalidCloudError, match="coincide"):
        umeyama(np.ones((5, 3)), y[:5])


def test_invert_of_a_stack_is_each_inverse_and_undoes_it() -> None:
    rng = np.random.default_rng(3)
    stack = np.stack(
        [make_transform(rotvec=rng.normal(size=3), translation=rng.normal(0.0, 20.0, 3)) for _ in range(5)]
    )
    inverses = invert(stack)
    for T, Ti in zip(stack, inverses, strict=True):
        np.testing.assert_allclose(Ti, invert(T), atol=1e-12)
        np.testing.assert_allclose(Ti @ T, np.eye(4), atol=1e-12)
