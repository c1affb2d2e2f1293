"""The durable pose graph (issue 33): the keyframes the graph took are in the store
(service/graph_log.py), and a restarted service (or graph process) takes them again before any
new one, so the graph it shows is the one it showed, and corrections go on from there. A joined
session after a restart: tests/service/test_agreement.py (its joined drive is restarted too)."""

from __future__ import annotations

import time

import numpy as np

from randt.service.api.health import readiness
from randt.service.graph import GraphState, ServiceGraph
from randt.service.graph_log import GRAPH_DIRNAME, GRAPH_LOG_FILENAME, GraphLog, decode_items
from randt.wire.messages import CorrectionMessage
from tests.service.api_server import live_server
from tests.service.test_graph_supervision import N_SCANS, _drives, _send


def _graph(server) -> ServiceGraph:
    mgr = server.service.sessions
    assert mgr is not None and mgr.graph is not None
    return mgr.graph


def _keyframes(state: GraphState) -> dict[tuple[str, str, int], np.ndarray | None]:
    return {(v, s, kf.seq): kf.optimized for (v, s), kfs in state.keyframes.items() for kf in kfs.values()}


def test_a_restarted_service_shows_the_graph_it_had_and_corrects_on_from_there(tmp_path) -> None:
    """Two vehicles drive; the service stops; a new one on the same data directory restores the
    graph from its log: the same keyframes at the same optimized poses (within 1 mm), the same
    placements, loop records and revision; what the vehicles then send is corrected with higher
    revisions only, and nothing is published again for the keyframes taken from the log."""
    drives = _drives()
    data = tmp_path / "data"
    with live_server(data, capacity_target=0) as server:
        graph = _graph(server)
        for vehicle in ("first", "evicted"):
            _send(server, vehicle, drives[vehicle][:N_SCANS])
        assert graph.wait_idle(120)
        before = graph.snapshot("default")
        assert before is not None
        sent = [m for m in server.service._sent if isinstance(m, CorrectionMessage)]
    kb0 = _keyframes(before)
    assert len(GraphLog(data / GRAPH_DIRNAME)) == len(kb0) >= 4

    with live_server(data, capacity_target=0) as server:
        graph = _graph(server)
        # /readyz answers 200 only once the graph shows every keyframe and loop it showed before
        deadline = time.monotonic() + 120
        while not readiness(server.service).ready:
            assert time.monotonic() < deadline, readiness(server.service)
            time.sleep(0.01)
        at_ready = graph.snapshot("default")
        assert at_ready is not None and not graph.replaying
        ready_keyframes = _keyframes(at_ready)
        assert ready_keyframes.keys() == kb0.keys() and at_ready.loops == before.loops
        for key, P in kb0.items():
            Q = ready_keyframes[key]
            assert P is not None and Q is not None and np.abs(P - Q).max() < 1e-3, key
        assert graph.wait_idle(120)
        after = graph.snapshot("default")
        assert after is not None
        assert after.placed == before.placed and after.revision == before.revision
        assert after.loops == before.loops
        kb, ka = _keyframes(before), _keyframes(after)
        assert ka.keys() == kb.keys()
        for key, P in kb.items():
            Q = ka[key]
            assert P is not None and Q is not None and np.abs(P - Q).max() < 1e-3, key
        assert not [m for m in server.service._sent if isinstance(m, CorrectionMessage)]
        # the vehicles drive on: new keyframes, corrections numbered after the restored ones
        for vehicle in ("first", "evicted"):
            _send(server, vehicle, drives[vehicle][N_SCANS : 2 * N_SCANS])
        assert graph.wait_idle(120)
        later = graph.snapshot("default")
        assert later is not None and len(_keyframes(later)) > len(kb)
        new = [m for m in server.service._sent if isinstance(m, CorrectionMessage)]
        assert all(m.revision > before.revision for m in new)
        # The map is deleted (its sessions closed first): its graph goes, from the log too
        mgr = server.service.sessions
        assert mgr is not None
        for vehicle in ("first", "evicted"):
            mgr.close(vehicle, "d1")
        mgr.delete_map("default")
        assert graph.snapshot("default") is None
        assert len(GraphLog(data / GRAPH_DIRNAME)) == 0
        # ... and a new map of its name numbers its revisions above the deleted one's
        _send(server, "later", drives["later"][:N_SCANS])
        assert graph.wait_idle(120)
        fresh = graph.snapshot("default")
        assert fresh is not None and set(fresh.keyframes) == {("later", "d1")}
        assert fresh.revision >= later.revision
        logged = len(GraphLog(data / GRAPH_DIRNAME))
        assert logged == len(_keyframes(fresh)) >= 2
    assert max((m.revision for m in sent), default=0) <= before.revision

    with live_server(data, capacity_target=0) as server:  # the deleted graph does not come back
        graph = _graph(server)
        assert graph.wait_idle(120)
        again = graph.snapshot("default")
        assert again is not None and set(again.keyframes) == {("later", "d1")}
        assert again.revision == fresh.revision and len(_keyframes(again)) == logged


def test_an_offered_keyframe_is_durable_before_the_graph_takes_it(tmp_path) -> None:
    """The log is written when a keyframe is offered, before the process takes it: a graph that
    lags (stopped here) loses nothing to a kill -9, and a restart takes everything offered. (When
    it was written as the process took them, a kill -9 lost every keyframe still queued: 18 were
    logged after ten kills of bench/graph_crash.py's 2 x 400-sweep drive.)"""
    import os
    import signal

    from randt.core.fleet_map import FleetMapSettings
    from randt.service.metrics import ServiceMetrics
    from tests.pairs import kitti00_velodyne

    log_dir = tmp_path / GRAPH_DIRNAME
    graph = ServiceGraph(
        FleetMapSettings(), lambda m: None, ServiceMetrics(), yield_to_matchers=False, log_dir=log_dir
    )

    def offer(k: int) -> None:
        T = np.eye(4)
        T[:3, 3] = (2.5 * k, 0.0, 0.0)
        xyz = kitti00_velodyne(3 * k)[::4].astype(np.float32)  # (frames 0-10 are in the shared data)
        graph.offer(
            "car", "d1", map_name="default", seq=10 * k, index=10 * k, stamp_s=float(k), T_live=T, points=xyz
        )

    try:
        offer(0)
        deadline = time.monotonic() + 120
        while graph.pid is None or not graph.running:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert graph.wait_idle(120)
        os.kill(graph.pid, signal.SIGSTOP)  # the graph takes nothing more
        try:
            for k in range(1, 4):
                offer(k)
            deadline = time.monotonic() + 60  # (the process's start may have taken the first one's)
            # (read without repairing: a GraphLog would cut the writer's record in progress as torn)
            while len(decode_items((log_dir / GRAPH_LOG_FILENAME).read_bytes())[0]) < 4:
                assert time.monotonic() < deadline, "offered keyframes not logged"
                time.sleep(0.05)
            assert graph.queue.done == 1  # none of them taken
        finally:
            os.kill(graph.pid, signal.SIGCONT)
    finally:
        graph.close()
    again = ServiceGraph(
        FleetMapSettings(), lambda m: None, ServiceMetrics(), yield_to_matchers=False, log_dir=log_dir
    )
    try:
        assert again.wait_idle(120)
        state = again.snapshot("default")
        assert state is not None and sorted(kf.seq for kf in state.keyframes[("car", "d1")].values()) == [
            0,
            10,
            20,
            30,
        ]
        assert all(kf.optimized is not None for kf in state.keyframes[("car", "d1")].values())
    finally:
        again.close()
