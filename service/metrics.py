"""Prometheus metrics of one service instance (prometheus_client, one registry per instance, not
the global default: instances, and tests, stay independent).

Events are counted where they happen, and the totals of :attr:`ServiceMetrics.PERSISTENT` count
across restarts (saved by the flusher, :meth:`ServiceMetrics.restore` at start); the maps' tiles
and points are read at each scrape (:meth:`ServiceMetrics.watch`). ``GET /metrics`` renders the
registry; the series: docs/api.md, "GET /metrics".
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, Info
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

__all__ = ["MapStats", "ServiceMetrics"]

#: What :meth:`ServiceMetrics.watch` reads at scrape time: map name -> (tiles, points).
MapStats = Callable[[], Mapping[str, tuple[int, int]]]


class _MapCollector(Collector):
    """Per-map tile and point counts, read from the live maps at every scrape."""

    def __init__(self, read: MapStats) -> None:
        self._read = read

    def collect(self) -> Iterator[Metric]:
        tiles = GaugeMetricFamily("randt_map_tiles", "Non-empty tiles per map", labels=["map"])
        points = GaugeMetricFamily("randt_map_points", "Points per map (after equalization)", labels=["map"])
        for name, (n_tiles, n_points) in sorted(self._read().items()):
            tiles.add_metric([name], n_tiles)
            points.add_metric([name], n_points)
        yield tiles
        yield points


class ServiceMetrics:
    """The service's counters, gauges and histograms (module docstring).

    Attributes
    ----------
    registry:
        This instance's registry; render it with ``prometheus_client.generate_latest``.
    scans_received, scans_processed, scans_rejected, scans_dropped:
        Counters. ``scans_processed`` is labelled by the pose ``status`` (``first``, ``ok``,
        ``fallback``), ``scans_rejected`` by ``reason`` (the error code sent to the vehicle).
    registration_seconds:
        Histogram of the matcher's time per scan.
    latency_seconds:
        Histogram of the time from receiving a scan to publishing its pose (the service's share
        of a vehicle's publish-to-pose time; the wire carries no publish time to measure the rest).
    map_disagreements:
        Counter of the times a session's map agreement check found it disagreeing with its map.
    queue_depth:
        Gauge of scans waiting per session, labelled ``session="<vehicle>/<session>"``; updated on
        every enqueue and dequeue, removed when the session closes.
    sessions_active, tiles_written, store_errors:
        Running session workers; tile files written; failed writes to the store.
    graph_keyframes, graph_loops, graph_update_seconds, graph_refold_seconds, graph_queue_dropped,
    graph_tiles_refolded:
        The pose graph (service/graph.py): keyframes it took (``result``: ``added`` or ``refused``),
        loop verifications (``result``: ``accepted``, ``refused``), the graph process's time per
        keyframe (place recognition, verification, iSAM2) and per re-fold of a map's tiles (at most
        every ``graph_refold_s``), keyframes dropped because its queue was full, tiles re-folded
        because the graph moved the keyframes behind them.
    graph_up, graph_restarts:
        Gauge: 1 while the graph process runs (0 before the first keyframe and while it is being
        restarted); counter: how many times it died and was started again.
    """

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.info = Info("randt_service", "The service instance", registry=r)
        self.scans_received = Counter("randt_scans_received", "Scan messages received", registry=r)
        self.scans_localized = Counter(
            "randt_scans_localized",
            "Scans of scans_processed matched on the map around the vehicle (localizing, not mapping)",
            registry=r,
        )
        self.scans_processed = Counter(
            "randt_scans_processed", "Scans registered (pose published)", ["status"], registry=r
        )
        self.scans_rejected = Counter(
            "randt_scans_rejected", "Scans rejected with an error message", ["reason"], registry=r
        )
        self.scans_dropped = Counter(
            "randt_scans_dropped", "Scans dropped by the overload policy (shed evenly)", registry=r
        )
        self.map_disagreements = Counter(
            "randt_map_disagreements",
            "Sessions found disagreeing with the map they fold into (then lost; service/agreement.py)",
            registry=r,
        )
        self.registration_seconds = Histogram(
            "randt_registration_seconds",
            "Matcher time per scan until its pose (a keyframe's model rebuild follows the answer)",
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
        self.graph_keyframes = Counter(
            "randt_graph_keyframes", "Keyframes offered to the pose graph", ["result"], registry=r
        )
        self.graph_loops = Counter("randt_graph_loops", "Loop verifications", ["result"], registry=r)
        self.ros2_samples = Counter(
            "randt_ros2_samples",
            "ROS 2 PointCloud2 samples by topic and outcome (accepted, ignored, or the error code)",
            ["topic", "outcome"],
            registry=r,
        )
        self.graph_update_seconds = Histogram(
            "randt_graph_update_seconds",
            "Pose graph time per keyframe (place recognition, verification, iSAM2)",
            buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.2, 0.35, 0.5, 1.0, 2.0, 5.0),
            registry=r,
        )
        self.graph_refold_seconds = Histogram(
            "randt_graph_refold_seconds",
            "Pose graph time per re-fold of a map's tiles (its moved keyframes' points, equalized)",
            buckets=(0.01, 0.025, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0),
            registry=r,
        )
        self.graph_tiles_refolded = Counter(
            "randt_graph_tiles_refolded",
            "Tiles re-folded because the pose graph moved their keyframes",
            registry=r,
        )
        self.graph_queue_dropped = Counter(
            "randt_graph_queue_dropped", "Keyframes dropped: the pose graph's queue was full", registry=r
        )
        self.graph_up = Gauge("randt_graph_up", "1 while the pose graph process runs", registry=r)
        self.graph_restarts = Counter(
            "randt_graph_restarts", "Times the pose graph process died and was started again", registry=r
        )
        # admission by measured capacity (service/capacity.py), updated every flush
        self.capacity_cores = Gauge("randt_capacity_cores", "CPUs the matchers run on", registry=r)
        self.capacity_load = Gauge(
            "randt_capacity_load",
            "The running sessions' measured CPU as a share of what admission may fill (1: full)",
            registry=r,
        )
        self.capacity_sessions_more = Gauge(
            "randt_capacity_sessions_more", "New sessions that fit, at the expected cost of one", registry=r
        )
        self.capacity_sweep_cpu_seconds = Gauge(
            "randt_capacity_sweep_cpu_seconds",
            "Matcher CPU per sweep, mean of the measured sessions",
            registry=r,
        )
        self.capacity_service_cpu_seconds = Gauge(
            "randt_capacity_service_cpu_seconds", "The service process's own CPU per sweep", registry=r
        )
        self._map_collector: _MapCollector | None = None

    #: The counters whose totals persist across restarts (DATA/counters.json, service/store.py).
    PERSISTENT = (
        "scans_received",
        "scans_processed",
        "scans_localized",
        "scans_rejected",
        "scans_dropped",
        "tiles_written",
        "store_errors",
    )

    def totals(self) -> dict[str, dict[str, float]]:
        """``{counter: {label value ("" if unlabelled): total}}`` of :attr:`PERSISTENT`."""
        out: dict[str, dict[str, float]] = {}
        for name in self.PERSISTENT:
            values: dict[str, float] = {}
            for metric in getattr(self, name).collect():
                for sample in metric.samples:
                    if sample.name.endswith("_total"):
                        values[next(iter(sample.labels.values()), "")] = sample.value
            out[name] = values
        return out

    def restore(self, totals: Mapping[str, Mapping[str, float]]) -> None:
        """Add saved totals (:meth:`totals` of an earlier run) to this instance's counters, so
        ``/status`` and ``/metrics`` count from where the previous run stopped. Unknown counter
        names are ignored."""
        for name, values in totals.items():
            if name not in self.PERSISTENT:
                continue
            counter: Counter = getattr(self, name)
            for label, value in values.items():
                if value <= 0:
                    continue
                if counter._labelnames:  # prometheus_client has no public accessor
                    if label:
                        counter.labels(label).inc(value)
                elif not label:
                    counter.inc(value)

    def watch(self, maps: MapStats, *, instance: str) -> None:
        """Report the live maps at every scrape (``randt_map_tiles``, ``randt_map_points``).

        Parameters
        ----------
        maps:
            Returns ``{map name: (tiles, points)}``; called on every scrape, so keep it cheap.
        instance:
            The instance name, exported as ``randt_service_info{instance=...}``.

        Calling it again replaces the previous source (a restarted service in one process).
        """
        self.info.info({"instance": instance})
        if self._map_collector is not None:
            self.registry.unregister(self._map_collector)
        self._map_collector = _MapCollector(maps)
        self.registry.register(self._map_collector)
