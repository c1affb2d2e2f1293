"""Metric values as reports carry them."""

from __future__ import annotations

import math

__all__ = ["json_float"]


def json_float(value: float) -> float | None:
    """A float for JSON: ``None`` for NaN/inf (JSON has no such numbers)."""
    value = float(value)
    return value if math.isfinite(value) else None
