"""Prometheus metrics of one service instance (prometheus_client, one registry per instance).

A registry per :class:`service.runtime.Service` (not the global default) keeps instances, and
tests, independent. ``GET /metrics`` renders :attr:`ServiceMetrics.registry`.
"""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

__all__ = ["ServiceMetrics"]


class ServiceMetrics:
    """The service's counters, gauges and histograms."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.scans_received = Counter("randt_scans_received", "Scan messages received", registry=r)
        self.scans_processed = Counter(
            "randt_scans_processed", "Scans registered (pose published)", ["status"], registry=r
        )
        self.scans_rejected = Counter(
            "randt_scans_rejected", "Scans rejected with an error message", ["reason"], registry=r
        )
        self.scans_dropped = Counter(
            "randt_scans_dropped", "Scans dropped by the overload policy (oldest first)", registry=r
        )
        self.registration_seconds = Histogram(
            "randt_registration_seconds",
            "Matcher time per scan",
            buckets=(0.01, 0.025, 0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 2.0, 5.0),
            registry=r,
        )
        self.latency_seconds = Histogram(
            "randt_scan_to_pose_latency_seconds",
            "Receive-to-pose-publish latency",
            buckets=(0.01, 0.025, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0),
            registry=r,
        )
        self.queue_depth = Gauge(
            "randt_session_queue_depth", "Scans waiting per session", ["session"], registry=r
        )
        self.sessions_active = Gauge("randt_sessions_active", "Sessions with a running worker", registry=r)
        self.tiles_written = Counter("randt_tiles_written", "Tile files written to the store", registry=r)
        self.store_errors = Counter("randt_store_errors", "Failed writes to the store", registry=r)
