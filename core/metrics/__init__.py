"""Quality metrics: point-cloud agreement (:mod:`randt.core.metrics.cloud`, the RANDT paper's) and
trajectory error (:mod:`randt.core.metrics.trajectory`)."""

from __future__ import annotations

from randt.core.metrics.values import json_float

__all__ = ["json_float"]
