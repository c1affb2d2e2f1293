"""The scan counters' totals across restarts: ``DATA/counters.json``, written by the flusher
(:class:`randt.service.counters.Counters`, the counters of :mod:`randt.service.metrics`).
"""

from __future__ import annotations

import logging
from pathlib import Path

from randt.core.io import atomic_write_bytes

__all__ = ["COUNTERS_FILENAME", "CounterTotals", "load_counters", "save_counters"]

logger = logging.getLogger(__name__)

#: The counters' totals, so ``/status`` and ``/metrics`` go on counting across restarts.
COUNTERS_FILENAME = "counters.json"

#: ``{counter name: {label value ("" when unlabelled): total}}``.
CounterTotals = dict[str, dict[str, float]]


def save_counters(data_dir: Path, totals: CounterTotals) -> None:
    """Write the counters' totals to ``data_dir/counters.json`` atomically (temp file, fsync, rename).

    A crash loses at most the counts since the previous write (one flush interval).
    """
    import json

    body = json.dumps({"version": 1, "counters": totals}, sort_keys=True, indent=1) + "\n"
    atomic_write_bytes(Path(data_dir) / COUNTERS_FILENAME, body.encode())


def load_counters(data_dir: Path) -> CounterTotals:
    """The totals :func:`save_counters` wrote; ``{}`` when there is no file. A damaged file is
    logged and read as ``{}`` (counting restarts from zero; the maps and sessions are unaffected);
    entries that are not non-negative finite numbers are skipped."""
    import json
    import math

    path = Path(data_dir) / COUNTERS_FILENAME
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as exc:
        logger.error("store: %s is unreadable (%s); counters start from zero", path, exc)
        return {}
    counters = doc.get("counters") if isinstance(doc, dict) else None
    if not isinstance(counters, dict):
        logger.error("store: %s holds no counters; counters start from zero", path)
        return {}
    out: CounterTotals = {}
    for name, values in counters.items():
        if not isinstance(name, str) or not isinstance(values, dict):
            continue
        kept = {
            str(label): float(v)
            for label, v in values.items()
            if isinstance(label, str)
            and len(label) <= 64
            and isinstance(v, int | float)
            and not isinstance(v, bool)
            and math.isfinite(v)
            and v >= 0
        }
        if kept:
            out[name] = kept
    return out
