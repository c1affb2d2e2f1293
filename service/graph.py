"""The pose graphs in the service: loop closure and GNSS fusion beside the live answers.

:class:`ServiceGraph` feeds a session's keyframes (every ``graph_keyframe_m`` of travel) to one
process at the lowest priority (service/graph_process.py: one FleetMapper per map), off the
session threads' GIL, and turns what the graph moved into corrections, re-folded tiles and joins
(service/graph_state.py). Its parts: the queue between the service and the process
(graph_queue.py), the log each keyframe is made durable in first (graph_journal.py), the process's
life (graph_supervisor.py) and its priority (graph_priority.py). The per-sweep answers are never
rewritten (docs/mapping.md, "In the service").
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable

import numpy as np

from randt.core.fleet_map import FleetMapSettings
from randt.core.odometry import PosePrior
from randt.service.graph_journal import GraphJournal
from randt.service.graph_priority import GRAPH_NICE, YieldGate
from randt.service.graph_process import MOVE_TOL_DEG, MOVE_TOL_M, MapGeometry
from randt.service.graph_queue import GraphQueue, Item
from randt.service.graph_state import (
    GraphLoop,
    GraphState,
    GraphView,
    Keyframe,
    correct_trajectory,
)
from randt.service.graph_supervisor import GraphSupervisor
from randt.service.metrics import ServiceMetrics
from randt.service.places import MapPlaces
from randt.wire.messages import CorrectionMessage

__all__ = [
    "GRAPH_NICE",
    "KNOWN_PLACE_DEG",
    "KNOWN_PLACE_M",
    "MOVE_TOL_DEG",
    "MOVE_TOL_M",
    "GraphLoop",
    "GraphState",
    "ServiceGraph",
    "correct_trajectory",
]


#: A localized sweep within this reach and turn of a keyframe the map's graph holds adds no
#: keyframe: the graph has that view of the place (three quarters of the keyframe spacing; another
#: heading sees other faces), so repeated drives add none and a place keeps a few views, one per
#: heading. The check is made every keyframe spacing of travel, so it keeps the phase it started at:
#: at half the spacing a vehicle passing the graph's keyframes midway was never within reach
#: (docs/benchmarks.md, "The fleet on mapped streets").
KNOWN_PLACE_M = 7.5
KNOWN_PLACE_DEG = 30.0


class ServiceGraph:
    """The service's pose graphs, one per map, in a process of their own (module docstring)."""

    def __init__(
        self,
        settings: FleetMapSettings,
        outbox: Callable[[CorrectionMessage], None],
        metrics: ServiceMetrics,
        *,
        geometry: MapGeometry | None = None,
        on_refold: Callable[[str, list[str], np.ndarray, np.ndarray], None] | None = None,
        on_join: Callable[[str, str, str, np.ndarray], None] | None = None,
        keyframe_m: float = 10.0,
        queue_size: int = 64,
        refold_s: float = 20.0,
        yield_to_matchers: bool = True,
        on_restart: Callable[[], None] | None = None,
        log_dir: str | os.PathLike[str] | None = None,
    ) -> None:
        self.settings = settings
        self.refold_s = refold_s
        self.geometry = geometry or MapGeometry(20, 0.2, 1)
        self.keyframe_m = keyframe_m
        #: What the service knows of the graphs (the receiver writes it, the reads read it).
        self.view = GraphView(metrics, outbox, on_refold, on_join, keyframe_m, MapPlaces(settings.place))
        self.queue = GraphQueue(metrics, self._forget_keyframe, queue_size)
        #: The keyframes the graph took, durable (service/graph_log.py): every (re)started process
        #: takes them again first. No ``log_dir``: the graph lives in memory only.
        self.journal = GraphJournal(log_dir, self.queue, self.view, metrics)
        self.supervisor = GraphSupervisor(
            (settings, self.geometry, refold_s),
            self.queue,
            self.journal,
            self.view,
            metrics,
            gate=YieldGate() if yield_to_matchers else None,
            on_restart=on_restart,
        )
        if self.journal.restore():
            self.supervisor.start()

    def _forget_keyframe(self, item: Item) -> None:
        self.view.forget_keyframe(item[1], (item[2], item[3]), item[4])

    # -- the process ---------------------------------------------------------------------------
    @property
    def gate(self) -> YieldGate | None:
        """Holds the graph process while sweeps are matched (``graph_yield``); None: never held."""
        return self.supervisor.gate

    @property
    def started(self) -> bool:
        """A keyframe has been offered: the graph process is (or is being) run."""
        return self.supervisor.started

    @property
    def running(self) -> bool:
        """The graph process of the current generation is alive."""
        proc = self.supervisor.proc
        return proc is not None and proc.is_alive()

    @property
    def pid(self) -> int | None:
        proc = self.supervisor.proc
        return None if proc is None else proc.pid

    @property
    def restarts(self) -> int:
        """How many times the process died and was started again."""
        return self.supervisor.restarts

    @property
    def last_exit(self) -> str | None:
        """How the process last died ('signal 9', 'exit code 1')."""
        return self.supervisor.last_exit

    @property
    def replaying(self) -> bool:
        """The process is still taking keyframes again from the log (after a start or a death):
        until then the graph it shows lacks some of what it had (``/readyz`` waits for it)."""
        with self.queue.cond:
            return bool(self.queue.replay_ids)

    @property
    def pending(self) -> int:
        """Keyframes offered that the process has not answered yet (the graph's lag)."""
        return self.queue.pending

    def cpu_s(self) -> float:
        """CPU seconds the graph's processes have used so far (:class:`CpuMeter`)."""
        return self.supervisor.cpu.read(self.pid)

    # -- input (session threads) -------------------------------------------------------------
    def forget_map(self, map_name: str) -> None:
        """A deleted map's graph goes (SessionManager.delete_map, whose sessions have ended):
        from the log first (a restart never brings it back), then from the queue, the process and
        what the service shows. Until the process says it dropped the map, what it says of the
        map is of the deleted one and is not applied.

        Raises
        ------
        FormatError
            The log could not be rewritten (the graph is then as it was).
        """
        revision = self.view.revision(map_name)
        with self.journal.writing:  # (the log's writer waits: nothing of the map is logged after this)
            self.journal.forget_map(map_name, revision)
            self.queue.forget_map(map_name, running=self.supervisor.started)
        self.view.forget(map_name, revision)

    def offer(
        self,
        vehicle: str,
        session: str,
        *,
        map_name: str,
        seq: int,
        index: int,
        stamp_s: float,
        T_live: np.ndarray,
        points: np.ndarray,
        intensity: np.ndarray | None = None,
        gnss: tuple[np.ndarray, np.ndarray] | None = None,
        join: str | None = None,
        localized: bool = False,
    ) -> None:
        """Queue a keyframe of a session in map ``map_name``: a durable pose ``T_live`` (sweep
        ``index``), its points (sensor frame, deskewed) with their intensity, and its GNSS fix.
        The points also make the map's tiles when the graph re-folds them. ``join``: the shared
        map a session without priors (in a map of its own) may join, once the graph places it
        there (:meth:`joined`). Never blocks: when ``graph_queue`` keyframes wait, the oldest is
        dropped (counted, logged). A ``localized`` sweep (matched on the map) at a place the
        graph holds (:data:`KNOWN_PLACE_M`, :data:`KNOWN_PLACE_DEG`) adds nothing: the graph grows
        with the area, not with the distance driven (counted ``known_place``)."""
        if localized and self.passes_known_place(vehicle, session, map_name, T_live):
            return
        map_name = self.view.offered(
            (vehicle, session), map_name, Keyframe(seq, index, stamp_s, T_live.copy()), points
        )
        if map_name == join:
            join = None
        item = ("keyframe", map_name, vehicle, session, seq, index, T_live, points, intensity, gnss, join)
        if not self.queue.closed:
            self.supervisor.start()
        self.queue.offer(item, logged=self.journal.durable)

    def relocalize(self, map_name: str, xyz: np.ndarray) -> list[PosePrior]:
        """Guesses of the pose on ``map_name`` of a sweep without a prior (``xyz``, sensor frame),
        from the places of its graph's keyframes (service/places.py), nearest first."""
        return self.view.guesses(map_name, xyz)

    def passes_known_place(self, vehicle: str, session: str, map_name: str, T_live: np.ndarray) -> bool:
        """A localizing session about to reach its next keyframe's spacing at ``T_live``: True
        when the graph holds a keyframe there (:data:`KNOWN_PLACE_M`, :data:`KNOWN_PLACE_DEG`),
        which :meth:`offer` would not add (counted ``known_place``; the next one's spacing counts
        from here): the matcher need not return the sweep's points for it."""
        if not self.view.known_place(map_name, T_live, KNOWN_PLACE_M, KNOWN_PLACE_DEG):
            return False
        self.view.passed((vehicle, session), T_live)
        self.view.metrics.graph_keyframes.labels("known_place").inc()
        return True

    # -- reads (the service's view of the graphs: graph_state.GraphView) ---------------------
    def wants_keyframe(self, vehicle: str, session: str, poses: list[np.ndarray]) -> bool:
        """:meth:`GraphView.wants_keyframe`."""
        return self.view.wants_keyframe(vehicle, session, poses)

    def fold_target(self, vehicle: str, session: str, map_name: str) -> tuple[np.ndarray | None, str]:
        """:meth:`GraphView.fold_target`."""
        return self.view.fold_target(vehicle, session, map_name)

    def joined(self, vehicle: str, session: str) -> tuple[str, np.ndarray] | None:
        """:meth:`GraphView.joined`."""
        return self.view.joined(vehicle, session)

    def correction(self, vehicle: str, session: str) -> np.ndarray | None:
        """:meth:`GraphView.correction`."""
        return self.view.correction(vehicle, session)

    def corrected(self, vehicle: str, session: str, poses: np.ndarray) -> tuple[np.ndarray, str | None]:
        """:meth:`GraphView.corrected`."""
        return self.view.corrected(vehicle, session, poses)

    def corrected_marked(
        self, vehicle: str, session: str, poses: np.ndarray
    ) -> tuple[np.ndarray, str | None, np.ndarray]:
        """:meth:`GraphView.corrected_marked`."""
        return self.view.corrected_marked(vehicle, session, poses)

    def maps(self) -> list[str]:
        """:meth:`GraphView.maps`."""
        return self.view.maps()

    def snapshot(self, map_name: str) -> GraphState | None:
        """:meth:`GraphView.snapshot`."""
        return self.view.snapshot(map_name)

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Wait until the process has answered every queued keyframe and re-folded the tiles of
        those that moved (tests and benchmarks: the map as the graph has it now)."""
        return not self.supervisor.started or self.queue.wait_idle(timeout)

    def matching(self) -> contextlib.AbstractContextManager[None]:
        """Around the matching of one sweep (SessionWorker): with ``graph_yield``, the graph
        process does not run while any sweep is inside (:class:`YieldGate`)."""
        return contextlib.nullcontext() if self.gate is None else self.gate.matching()

    def close(self, timeout: float = 10.0) -> None:
        """Stop feeding the process and stop it (what is still queued is not processed)."""
        self.queue.close()
        self.supervisor.stop(timeout)
