"""The scan counters' totals across restarts (``DATA/counters.json``), restored at start and
written by the flusher when they changed."""

from __future__ import annotations

import logging
from pathlib import Path

from randt.service.counter_totals import load_counters, save_counters
from randt.service.metrics import ServiceMetrics

__all__ = ["Counters"]

log = logging.getLogger(__name__)


class Counters:
    """The metrics' totals, started from what the store kept (a missing file: from zero)."""

    def __init__(self, data_dir: Path, metrics: ServiceMetrics) -> None:
        self.data_dir, self.metrics = data_dir, metrics
        totals = load_counters(data_dir)
        if totals:
            metrics.restore(totals)
            received = int(totals.get("scans_received", {}).get("", 0))
            log.info("counters restored: %d scans received so far", received)
        self._saved = metrics.totals()

    def save(self) -> None:
        """Write the totals when they changed (the flusher, and the last flush at stop)."""
        totals = self.metrics.totals()
        if totals == self._saved:
            return
        try:
            save_counters(self.data_dir, totals)
            self._saved = totals
        except OSError:
            self.metrics.store_errors.inc()
            log.exception("saving the counters failed")
