"""The durable pose graph (issue 33): the keyframes the graph took are in the store
(service/graph_log.py), and a restarted service (or graph process) takes them again before any
new one, so the graph it shows is the one it showed, and corrections go on from there."""

from __future__ import annotations

import numpy as np

from service.graph import GraphState, ServiceGraph
from service.graph_log import GRAPH_DIRNAME, GraphLog
from tests.service.api_server import live_server
from tests.service.test_graph_supervision import N_SCANS, _drives, _send
from wire.messages import CorrectionMessage


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
    assert len(GraphLog(data / GRAPH_DIRNAME)) == len(_keyframes(before)) >= 4

    with live_server(data, capacity_target=0) as server:
        graph = _graph(server)
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
    assert max((m.revision for m in sent), default=0) <= before.revision


def test_after_a_restart_a_joined_session_is_still_in_the_shared_map_and_its_old_map_says_so(
    tmp_path,
) -> None:
    """``gnss`` maps the shared map; ``nognss`` (no priors, 100 m behind) joins it through the
    graph, and its own map is merged in. A new service on the same data takes the graph's log
    again: the session is joined where it was (within 1 mm), its keyframes are in the shared
    map's graph, and its old map's name still answers where it went."""
    from sim.town import Town
    from tests.service.test_agreement import MAPPED, _drive, _manager
    from tests.service.test_agreement import _send as send_one

    town = Town.generate(MAPPED)
    n = 220
    gnss = _drive(town, n, seed=1)
    nognss = _drive(town, n, seed=2, start_back_m=100.0, start_stamp_ns=50_000_000)
    data = tmp_path / "data"
    out: list = []
    mgr = _manager(data, out, graph=True)
    try:
        graph = mgr.graph
        assert graph is not None
        for k in range(n):
            send_one(mgr, out, "gnss", gnss[k], prior=k == 0)
            send_one(mgr, out, "nognss", nognss[k], prior=False)
        assert graph.wait_idle(300)
        joined = graph.joined("nognss", "d1")
        assert joined is not None and joined[0] == "default", "nognss did not join: nothing to test"
        before = graph.snapshot("default")
        assert before is not None and mgr.merged_into("nognss.d1") == ("default", "nognss/d1")
    finally:
        mgr.stop()
    out = []
    mgr = _manager(data, out, graph=True)
    try:
        graph = mgr.graph
        assert graph is not None and graph.wait_idle(300)
        again = graph.joined("nognss", "d1")
        assert again is not None and again[0] == "default"
        assert np.abs(again[1] - joined[1]).max() < 1e-3
        after = graph.snapshot("default")
        assert after is not None and after.placed == before.placed and after.revision == before.revision
        assert _keyframes(after).keys() == _keyframes(before).keys()
        assert mgr.merged_into("nognss.d1") == ("default", "nognss/d1")
        assert "nognss.d1" not in mgr.maps
        assert not [m for m in out if isinstance(m, CorrectionMessage)]
    finally:
        mgr.stop()
