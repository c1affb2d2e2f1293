"""Synthetic scenes for where no real data may be assumed: a warm-up on a bare machine, unit tests."""

from __future__ import annotations

import numpy as np

__all__ = ["synthetic_room"]


def synthetic_room(rng: np.random.Generator, n: int = 6000) -> np.ndarray:
    """Floor, two walls and a pillar (about 3.5 n points): a scene that constrains all 6 DoF.

    Used where no real data may be assumed (``randt demo-register`` on a bare machine, unit tests).
    """
    floor = np.c_[rng.uniform(-10, 10, (n, 2)), np.zeros(n)]
    wall_x = np.c_[np.full(n, 10.0), rng.uniform(-10, 10, n), rng.uniform(0, 3, n)]
    wall_y = np.c_[rng.uniform(-10, 10, n), np.full(n, 10.0), rng.uniform(0, 3, n)]
    ang = rng.uniform(0, 2 * np.pi, n // 4)
    pillar = np.c_[2 + 0.3 * np.cos(ang), -3 + 0.3 * np.sin(ang), rng.uniform(0, 3, n // 4)]
    return np.vstack([floor, wall_x, wall_y, pillar])
