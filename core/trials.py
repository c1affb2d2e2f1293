"""The RANDT paper's robustness trials: a real scan, a known rigid transform, noise, outliers, cropping.

One trial (:func:`make_trial`) takes a scan as the reference and builds a moving cloud from it:

1. two azimuth sectors of 270 degrees whose overlap is 135 degrees, so each cloud shares half of
   its sector with the other (50 % partial overlap); the reference keeps one, the moving the other;
2. the moving sector is mapped by ``inv(T_true)`` with ``T_true`` random, translation norm up to
   ``max_translation_m`` and rotation up to ``max_rotation_deg`` about a random axis;
3. Gaussian noise of ``noise_sigma_m`` on every moving point;
4. ``outlier_fraction`` of extra points drawn uniformly in the moving cloud's bounding box.

Registration must recover ``T_target_source = T_true``. Used by the tests and ``bench/register.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from randt.core.transforms import make_transform, transform_points

__all__ = ["Trial", "make_trial"]


@dataclass(frozen=True)
class Trial:
    source_xyz: np.ndarray
    target_xyz: np.ndarray
    T_true: np.ndarray
    noise_sigma_m: float


def make_trial(
    scan_xyz: np.ndarray,
    rng: np.random.Generator,
    *,
    max_translation_m: float = 2.0,
    max_rotation_deg: float = 10.0,
    noise_sigma_m: tuple[float, float] = (0.01, 0.05),
    outlier_fraction: float = 0.10,
    sector_deg: float = 270.0,
    overlap_deg: float = 135.0,
) -> Trial:
    """One seeded trial (module docstring)."""
    az = np.degrees(np.arctan2(scan_xyz[:, 1], scan_xyz[:, 0])) % 360.0
    start = rng.uniform(0.0, 360.0)
    rel_t = (az - start) % 360.0
    target = scan_xyz[rel_t < sector_deg]
    rel_s = (az - (start + sector_deg - overlap_deg)) % 360.0
    moving = scan_xyz[rel_s < sector_deg]

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    T_true = make_transform(
        rotvec=axis * np.radians(rng.uniform(0.0, max_rotation_deg)),
        translation=direction * rng.uniform(0.0, max_translation_m),
    )
    sigma = float(rng.uniform(*noise_sigma_m))
    source = transform_points(np.linalg.inv(T_true), moving) + rng.normal(scale=sigma, size=moving.shape)
    n_out = round(outlier_fraction * source.shape[0])
    lo, hi = source.min(axis=0), source.max(axis=0)
    source = np.vstack([source, rng.uniform(lo, hi, size=(n_out, 3))])
    return Trial(
        source_xyz=source[rng.permutation(source.shape[0])],
        target_xyz=target,
        T_true=T_true,
        noise_sigma_m=sigma,
    )
