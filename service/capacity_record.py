"""What the node's sessions were measured to cost, across restarts: ``DATA/capacity.json``, written
by the flusher, read at the start (:class:`randt.service.capacity.MeasuredCosts`).

Without it a restarted node counts every session at the prior (``sweep_cpu_estimate_s``, a
localizing one ``LOCALIZED_SHARE`` of it) until its sessions are measured again: the vehicles that
were driving when it restarted come back together and most are refused for a second or two.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

from randt.core.io import atomic_write_bytes
from randt.service.capacity import MeasuredCosts

__all__ = ["CAPACITY_FILENAME", "load_costs", "save_costs"]

logger = logging.getLogger(__name__)

CAPACITY_FILENAME = "capacity.json"


def save_costs(data_dir: Path, costs: MeasuredCosts) -> None:
    """Write ``costs`` to ``data_dir/capacity.json`` atomically (temp file, fsync, rename)."""
    body = {
        "version": 1,
        "cores": costs.cores,
        "mapping_sweep_cpu_s": costs.mapping_sweep_cpu_s,
        "localizing_sweep_cpu_s": costs.localizing_sweep_cpu_s,
        "service_cpu_s": costs.service_cpu_s,
    }
    atomic_write_bytes(Path(data_dir) / CAPACITY_FILENAME, (json.dumps(body, indent=1) + "\n").encode())


def load_costs(data_dir: Path) -> MeasuredCosts | None:
    """The costs :func:`save_costs` wrote; ``None`` without the file. A damaged file, or values
    that are not positive finite seconds below one, is logged and read as ``None`` (admission
    starts from its priors; nothing else depends on it)."""
    path = Path(data_dir) / CAPACITY_FILENAME
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        logger.error("store: %s is unreadable (%s); admission starts from its priors", path, exc)
        return None

    def seconds(name: str, *, optional: bool = True) -> float | None:
        value = doc.get(name) if isinstance(doc, dict) else None
        if value is None and optional:
            return None
        if (
            not isinstance(value, int | float)
            or isinstance(value, bool)
            or not 0 <= value < 1
            or not math.isfinite(value)
        ):
            raise ValueError(f"{name} is {value!r}, not seconds in [0, 1)")
        return float(value)

    try:
        cores = doc.get("cores") if isinstance(doc, dict) else None
        if not isinstance(cores, int | float) or isinstance(cores, bool) or not 0 < cores < 1e6:
            raise ValueError(f"cores is {cores!r}")
        service = seconds("service_cpu_s", optional=False)
        assert service is not None
        return MeasuredCosts(
            float(cores), seconds("mapping_sweep_cpu_s"), seconds("localizing_sweep_cpu_s"), service
        )
    except ValueError as exc:
        logger.error("store: %s is not what admission wrote (%s); it starts from its priors", path, exc)
        return None
