"""Rigid-transform helpers against scipy's general matrix functions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import fractional_matrix_power

from core.transforms import make_transform, scale_motion


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
