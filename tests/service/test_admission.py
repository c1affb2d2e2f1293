"""Admission by measured capacity (service/capacity.py, issue 32).

The model on its own, with a clock of its own: a node's load is the running sessions' rate times
their CPU per sweep (the matcher's and the service process's) against its cores times the target,
and a new session is admitted only if its expected cost still fits. Then the real session manager:
the CPU each sweep costs is measured where the matcher runs (a worker process, or in process), and
a vehicle the node cannot carry is refused ``sessions_full`` with ``retry_after_s`` before it
costs anything, and admitted once the load is gone.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from randt.core.scenes import synthetic_room
from randt.service.capacity import Capacity
from randt.service.matchers import MatcherPool
from randt.service.metrics import ServiceMetrics
from randt.service.sessions import SessionManager
from randt.service.settings import ServiceSettings
from randt.service.store import Store
from randt.wire.codes import ErrorCode
from randt.wire.messages import ErrorMessage, PoseMessage, decode_scan, encode, scan_from_arrays

ROOM = synthetic_room(np.random.default_rng(0), 3000).astype(np.float32)


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _drive(
    cap: Capacity, clock: Clock, keys: str | list[str], *, hz: float, cpu_s: float, n: int = 25
) -> None:
    """``n`` scans of each session of ``keys`` at ``hz`` (interleaved), each matched at ``cpu_s``."""
    keys = [keys] if isinstance(keys, str) else keys
    for _ in range(n):
        for key in keys:
            cap.arrived(key)
            cap.matched(key, cpu_s)
        clock.t += 1.0 / hz


def test_the_load_is_rate_times_cpu_per_sweep_against_the_cores() -> None:
    clock = Clock()
    cap = Capacity(cores=2, shares_cores=True, target=0.85, clock=clock)
    cap.service_sample(0.0)
    _drive(cap, clock, ["a", "b"], hz=10.0, cpu_s=0.045)
    cap.service_sample(0.0)  # (no service CPU measured: 0 ms per sweep)
    f = cap.figures(["a", "b"])
    # 2 sessions x 10 Hz x 45 ms = 0.9 cores of 2 x 0.85
    assert f.measured_sessions == 2 and f.used_cores == pytest.approx(0.9, rel=0.05)
    assert f.load == pytest.approx(0.9 / 1.7, rel=0.05)
    assert f.new_session_load == pytest.approx(0.45 / 1.7, rel=1e-6) and f.sessions_more == 1
    assert cap.refusal(["a", "b"]) is None  # a third fits: 0.79
    why = cap.refusal(["a", "b", "c"])  # a fourth does not: 0.79 + 0.26
    assert why is not None and "measured capacity" in why and "45 ms of matcher" in why
    # one of them gives up its slot: it fits again
    assert cap.refusal(["a", "b", "c"], exclude=["c"]) is None


def test_the_service_processes_own_cpu_counts_and_a_cluster_is_measured_apart() -> None:
    clock = Clock()
    shared = Capacity(cores=2, shares_cores=True, target=1.0, clock=clock)
    shared.service_sample(10.0)
    _drive(shared, clock, "a", hz=10.0, cpu_s=0.02, n=25)
    shared.service_sample(10.0 + 25 * 0.03)  # 30 ms of this process's CPU per sweep
    f = shared.figures(["a"])
    assert f.service_cpu_s == pytest.approx(0.03) and f.used_cores == pytest.approx(0.5, rel=0.05)
    # A Ray cluster of 8 CPUs: the matchers' share against them, the service process's against
    # its one core: 3 sessions use 0.6 of 8 matcher cores but 0.9 of the service's core.
    clock2 = Clock()
    cluster = Capacity(cores=lambda: 8.0, shares_cores=False, target=1.0, clock=clock2)
    cluster.service_sample(0.0)
    _drive(cluster, clock2, ["a", "b", "c"], hz=10.0, cpu_s=0.02, n=25)
    cluster.service_sample(75 * 0.03)
    f = cluster.figures(["a", "b", "c"])
    assert f.load == pytest.approx(0.9, rel=0.05) and f.sessions_more == 0
    assert cluster.refusal(["a", "b", "c"]) is not None


def test_the_graph_replaying_its_log_is_not_billed_to_the_sweeps() -> None:
    """After a restart the graph process replays its log (seconds of CPU) while the first
    sessions open: that CPU is the service's start, not what their sweeps cost (issue 57: two of
    eight localizing vehicles were admitted, the rest refused on it)."""
    clock = Clock()
    cap = Capacity(cores=2, shares_cores=True, target=0.85, clock=clock)
    cap.service_sample(0.0, graph_cpu_s=0.0)
    _drive(cap, clock, "a", hz=10.0, cpu_s=0.02, n=25)
    # 6 s of replay and 25 sweeps at 4 ms of service CPU: not sampled while it settles
    cap.service_sample(25 * 0.004, graph_cpu_s=6.0, settling=True)
    assert cap.figures(["a"]).service_cpu_s == 0.0
    _drive(cap, clock, "a", hz=10.0, cpu_s=0.02, n=25)
    cap.service_sample(50 * 0.004, graph_cpu_s=6.0 + 25 * 0.002)
    assert cap.figures(["a"]).service_cpu_s == pytest.approx(0.006)
    # unsettled, the same replay would be billed at 240 ms a sweep and refuse a second session
    other = Capacity(cores=2, shares_cores=True, target=0.85, clock=clock)
    other.service_sample(0.0, graph_cpu_s=0.0)
    _drive(other, clock, "a", hz=10.0, cpu_s=0.02, n=25)
    other.service_sample(25 * 0.004, graph_cpu_s=6.0)
    assert other.figures(["a"]).service_cpu_s == pytest.approx(0.244) and other.refusal(["a"]) is not None


def test_a_silent_session_costs_nothing_and_a_young_one_its_expected_cost() -> None:
    clock = Clock()
    cap = Capacity(cores=2, shares_cores=True, target=0.85, sweep_cpu_s=0.05, clock=clock)
    # A burst at shift start: nothing measured yet, each counts 10 Hz x 50 ms = 0.5 cores.
    running: list[str] = []
    for key in "abcdefgh":
        if cap.refusal(running) is None:
            running.append(key)
            cap.arrived(key)
    assert running == ["a", "b", "c"]  # 3 x 0.5 = 1.5 of 1.7 cores; a fourth would be 2.0
    # A vehicle that stopped sending a second ago frees its share.
    clock.t += 1.5
    assert cap.figures(running).load == 0.0 and cap.refusal(running) is None
    # A session measured at 2 Hz costs 2 Hz.
    _drive(cap, clock, "slow", hz=2.0, cpu_s=0.05)
    assert cap.figures(["slow"]).used_cores == pytest.approx(0.1, rel=0.05)


def test_a_session_expected_to_localize_is_counted_at_a_localizing_sessions_cost() -> None:
    """Sessions opening on mapped streets (issue 57): before any localizing session is measured,
    one counts LOCALIZED_SHARE of a mapping one's expected cost; once some are measured (five
    sweeps past their first, which prepares a window and is not counted), their mean. A mapping
    session's expectation stays its own."""
    from randt.service.capacity import LOCALIZED_SHARE, MIN_LOCALIZED_SWEEPS

    clock = Clock()
    cap = Capacity(cores=2, shares_cores=True, target=0.85, sweep_cpu_s=0.05, clock=clock)
    running: list[str] = []
    for key in "abcdefghij":
        if cap.refusal(running, localizing=True) is None:
            running.append(key)
            cap.opening(key, localizing=True)
            cap.arrived(key)
    # each counts 10 Hz x 17.5 ms = 0.175 cores: 9 fit in 1.7 (3 mapping ones would)
    assert LOCALIZED_SHARE == 0.35 and running == list("abcdefghi")
    assert cap.refusal(running) is not None  # a mapping one (0.5 more) does not fit beside them
    # measured: each session's first sweep (a window prepared: 150 ms) left out, the next at 15 ms
    for k in range(25):
        for key in running:
            cap.arrived(key)
            cap.matched(key, 0.15 if k == 0 else 0.015, localized=True, first=k == 0)
        clock.t += 0.1
    f = cap.figures(running)
    assert f.measured_sessions == 9 and f.used_cores == pytest.approx(9 * 0.15, rel=0.05)
    assert cap.refusal(running, localizing=True) is None  # 1.35 + 0.15 of 1.7
    assert cap.refusal(running) is not None  # a mapping one at its prior: 1.35 + 0.5 of 1.7
    assert cap.refusal(running[:7]) is None  # 1.05 + 0.5
    # a young one: its first sweep (150 ms) is not what it costs; measured from five after it
    young = Capacity(cores=2, shares_cores=True, target=0.85, sweep_cpu_s=0.05, clock=clock)
    young.opening("a", localizing=True)
    for k in range(1 + MIN_LOCALIZED_SWEEPS):
        assert young.figures(["a"]).measured_sessions == 0  # (the prior until then)
        young.arrived("a")
        young.matched("a", 0.15 if k == 0 else 0.015, localized=True, first=k == 0)
        clock.t += 0.1
    f = young.figures(["a"])
    assert f.measured_sessions == 1 and f.used_cores == pytest.approx(10 * 0.015)


def test_sessions_expected_to_localize_start_one_a_core_at_a_time() -> None:
    """A start joins the map around its vehicle and finds its motion: eight started together
    stalled every vehicle's scans. While a core's worth of sessions are starting (started, no
    sweep answered yet), another waits (its opener, its scans queued; not refused); one answered
    frees its slot, and one that never sends a sweep holds it STARTING_S at most."""
    from randt.service.admission import Admission
    from randt.service.capacity import STARTING_S

    clock = Clock()
    cap = Capacity(cores=2, shares_cores=True, target=0.85, sweep_cpu_s=0.01, clock=clock)
    running = list("abc")
    for key in running:
        cap.opening(key, localizing=True)
    assert cap.try_start("a", running) and cap.try_start("b", running)
    assert not cap.try_start("c", running)  # (two cores: two at a time)
    assert cap.try_start("c", ["a", "c"])  # (one that is no longer running holds no slot)
    cap.matched("a", 0.1, localized=True, first=True)
    assert not cap.try_start("d", [*running, "d"])  # (b and c are starting)
    cap.matched("b", 0.1, localized=True, first=True)
    assert cap.try_start("d", [*running, "d"])  # b answered: its slot is free
    assert not cap.try_start("e", [*running, "d", "e"])
    clock.t += STARTING_S
    assert cap.try_start("e", [*running, "d", "e"])  # (c and d never answered: they expired)
    # admission itself no longer refuses them for it: they queue behind the starts
    fresh = Capacity(cores=2, shares_cores=True, target=0.85, sweep_cpu_s=0.01, clock=clock)
    admission = Admission(ServiceSettings(max_sessions=0), fresh)  # type: ignore[call-arg]
    keys = [("d", "s"), ("e", "s")]
    for key in keys:
        fresh.opening(key, localizing=True)
        assert fresh.try_start(key, keys)
    assert admission.admit(("f", "s"), {}, keys, (), localizing=True) is None
    assert admission.refusal_on_header(keys, localizing=True) is None
    assert not fresh.try_start(("f", "s"), [*keys, ("f", "s")])


def test_a_matcher_process_measures_the_cpu_of_each_sweep() -> None:
    """:attr:`Registered.cpu_s` from a real worker process: positive, at most the wall time of the
    call, and including the keyframe model's rebuild after the previous sweep."""
    pool = MatcherPool(1)
    try:
        assert pool.wait_ready(300)
        matcher = pool.open(("v", "s"))
        rng = np.random.default_rng(1)
        cpus, walls = [], []
        for seq in range(6):
            xyz = (ROOM + rng.normal(scale=0.005, size=ROOM.shape) + [0.3 * seq, 0, 0]).astype(np.float32)
            payload = encode(scan_from_arrays("v", "s", seq, seq * 100_000_000, xyz))
            decode_scan(payload)  # (valid)
            t0 = time.perf_counter()
            registered = matcher.register_payload(payload)
            walls.append(time.perf_counter() - t0)
            cpus.append(registered.cpu_s)
            time.sleep(0.2)  # the process rebuilds the keyframe model meanwhile (billed to the next)
        assert all(c > 0 for c in cpus), cpus
        assert all(c <= w + 0.5 for c, w in zip(cpus[:1], walls[:1], strict=True))
        assert sum(cpus) < sum(walls) + 6 * 0.2 + 0.1, (cpus, walls)
        matcher.close()
    finally:
        pool.close()


def _wait(out: list[object], n: int, timeout: float = 120.0) -> list[PoseMessage | ErrorMessage]:
    deadline = time.monotonic() + timeout
    while True:
        answers = [m for m in list(out) if isinstance(m, PoseMessage | ErrorMessage)]
        if len(answers) >= n:
            return answers
        assert time.monotonic() < deadline, f"{len(answers)} of {n} answered"
        time.sleep(0.02)


def _scan(vehicle: str, seq: int) -> bytes:
    return encode(scan_from_arrays(vehicle, "s1", seq, seq * 100_000_000, ROOM))


def test_a_vehicle_the_node_cannot_carry_is_refused_with_retry_after_then_admitted(tmp_path) -> None:
    """One vehicle runs (in-process matcher: one core); a second whose expected cost cannot fit is
    refused ``sessions_full`` with ``retry_after_s`` and opens no session; once the first has
    been silent for a second it costs nothing and the second is admitted. The status figures are
    the measured ones. (``session_rate_hz`` high: a new session's expected cost is then clearly
    more than one core, whatever this machine's speed.)"""
    out: list[object] = []
    settings = ServiceSettings(
        data_dir=tmp_path,
        matcher_processes=0,
        flush_interval_s=0.2,
        session_rate_hz=200.0,
        admission_retry_s=7.0,
        capacity_target=0.6,  # (the default; the test suite's environment turns it off)
    )
    mgr = SessionManager(settings, Store(tmp_path), out.append, ServiceMetrics())
    try:
        assert mgr.capacity is not None and mgr.capacity.cores == 1.0
        for seq in range(22):  # one at a time (none shed): a session's cost is its own after 20 sweeps
            mgr.handle("first", _scan("first", seq), time.time_ns())
            _wait(out, seq + 1)
        mgr.handle("second", _scan("second", 0), time.time_ns())
        refused = _wait(out, 23)[-1]
        assert isinstance(refused, ErrorMessage) and refused.code == ErrorCode.SESSIONS_FULL, refused
        assert refused.retry_after_s == 7.0 and "measured capacity" in refused.reason
        assert ("second", "s1") not in {(s.vehicle, s.session) for s in mgr.sessions()}
        f = mgr.capacity_figures()
        assert f is not None and f.measured_sessions == 1 and 0.001 < f.sweep_cpu_s < 2.0, f
        time.sleep(1.2)  # the first vehicle went quiet
        assert mgr.capacity.refusal([("first", "s1")]) is None
        mgr.handle("second", _scan("second", 1), time.time_ns())
        admitted = _wait(out, 24)[-1]
        assert isinstance(admitted, PoseMessage) and admitted.vehicle == "second", admitted
    finally:
        mgr.stop()


def _drive_payloads(n: int) -> list[bytes]:
    """``n`` sweeps of a simulated car (town 0's first route, 10 m/s: a keyframe every 2 m, every
    second sweep), encoded as a vehicle sends them."""
    from randt.sim.drive import plan_fleet, simulate
    from randt.sim.lidar import Lidar64
    from randt.sim.town import Town

    town = Town.generate(0)
    route = plan_fleet(town, 1, seed=0, route_length_m=400.0)[0].route
    scans = simulate(town, route, n_scans=n, seed=0, lidar=Lidar64(n_azimuth=1000, max_range_m=70.0))
    return [encode(scan_from_arrays("car", "d1", s.index, s.stamp_ns, s.points_xyz)) for s in scans]


@pytest.mark.parametrize("capacity_target", [0.6, 0.0])
def test_a_session_behind_lets_its_model_lag_only_on_a_node_past_its_capacity(
    tmp_path, monkeypatch, capacity_target: float
) -> None:
    """A session whose queue holds several scans lets its keyframe model lag (one rebuild for two
    keyframes) only when the node is past its capacity (``SessionManager.saturated``): within it
    the backlog clears by itself, and lagging made one vehicle's error depend on when its scans
    queued (5.7 to 10.8 cm max over the same 600 sweeps, against 5.8 cm offline). Here every scan
    finds the queue behind (``depth`` patched), and the scans come at 5 Hz: within capacity the
    poses are the offline matcher process's to the digit (``bench/offline.py``); without capacity
    admission (``capacity_target=0``: the node's load unknown, taken as past it) the model lags
    and they differ."""
    from bench.offline import matcher_process
    from randt.service.worker import BEHIND_DEPTH, SessionWorker

    payloads = _drive_payloads(10)
    monkeypatch.setattr(SessionWorker, "depth", lambda self: BEHIND_DEPTH)
    out: list[object] = []
    settings = ServiceSettings(
        data_dir=tmp_path, matcher_processes=1, flush_interval_s=0.3, capacity_target=capacity_target
    )
    mgr = SessionManager(settings, Store(tmp_path), out.append, ServiceMetrics())
    try:
        assert mgr.wait_matchers(300)
        for k, payload in enumerate(payloads):
            t0 = time.monotonic()
            mgr.submit("car", payload)
            _wait(out, k + 1)
            time.sleep(max(0.0, 0.2 - (time.monotonic() - t0)))
        saturated = mgr.saturated()
    finally:
        mgr.stop()
    answers = [m for m in out if isinstance(m, PoseMessage)]
    assert [m.seq for m in answers] == list(range(10)) and {m.status for m in answers[1:]} == {"ok"}
    served = np.array([np.array(m.pose).reshape(4, 4) for m in answers])
    offline = np.array(matcher_process(payloads, graph=False).poses)
    gap = float(np.abs(served - offline).max())
    if capacity_target:
        assert gap < 1e-9, gap
    else:
        assert gap > 1e-6, gap  # (measured: 0.9 mm)
    assert saturated is (capacity_target == 0.0)


def test_a_restarted_node_admits_from_what_its_sessions_were_measured_to_cost(tmp_path) -> None:
    """``DATA/capacity.json``: the sessions' measured CPU per sweep of each kind and the service
    process's, written atomically and read at the start. From it, eight sessions expected to
    localize at 10 ms a sweep fit a 2-core node at once (at the priors, 31.5 ms each, three); a
    damaged file or one from a node of other cores is not taken (the priors, as before)."""
    from randt.service.capacity import MeasuredCosts
    from randt.service.capacity_record import CAPACITY_FILENAME, load_costs, save_costs

    clock = Clock()
    before = Capacity(cores=2, shares_cores=True, target=0.6, sweep_cpu_s=0.09, clock=clock)
    assert before.measured() == MeasuredCosts(2.0, None, None, 0.0)  # (nothing measured: the priors)
    for key in "ab":
        before.opening(key, localizing=True)
    for _ in range(25):
        for key in "ab":
            before.arrived(key)
            before.matched(key, 0.01, localized=True)
        clock.t += 0.1
    costs = before.measured()
    assert costs.localizing_sweep_cpu_s == pytest.approx(0.01) and costs.mapping_sweep_cpu_s is None
    save_costs(tmp_path, costs)
    assert load_costs(tmp_path) == costs

    def admitted(cap: Capacity) -> int:
        running: list[str] = []
        for key in "cdefghijkl":
            if cap.refusal(running, localizing=True) is None:
                running.append(key)
                cap.opening(key, localizing=True)
                cap.arrived(key)
        return len(running)

    restarted = Capacity(cores=2, shares_cores=True, target=0.6, sweep_cpu_s=0.09, clock=clock)
    assert restarted.start_from(load_costs(tmp_path))  # type: ignore[arg-type]
    assert admitted(restarted) >= 8
    assert admitted(Capacity(cores=2, shares_cores=True, target=0.6, sweep_cpu_s=0.09, clock=clock)) == 3
    other = Capacity(cores=4, shares_cores=True, target=0.6, sweep_cpu_s=0.09, clock=clock)
    assert not other.start_from(costs)  # (measured on 2 cores)
    (tmp_path / CAPACITY_FILENAME).write_text('{"version": 1, "cores": 2, "service_cpu_s": -3}')
    assert load_costs(tmp_path) is None
    (tmp_path / CAPACITY_FILENAME).write_text("{not json")
    assert load_costs(tmp_path) is None
    (tmp_path / CAPACITY_FILENAME).unlink()
    assert load_costs(tmp_path) is None


def test_a_localizing_sessions_cost_is_its_mean_and_a_change_of_kind_is_measured_anew() -> None:
    """A window joined every 20 m costs a localizing session tens of milliseconds once: its cost
    is its mean since it began to localize (the spike's share of the sweeps it serves), where a
    moving average counted it at several times that for a second. Mapping again, it is measured
    anew (counted at a mapping session's expected cost until then)."""
    from randt.service.capacity import MIN_SWEEPS

    clock = Clock()
    cap = Capacity(cores=2, shares_cores=True, target=0.85, sweep_cpu_s=0.05, clock=clock)
    cap.opening("a", localizing=True)

    def sweeps(n: int, cpu_s: float, localized: bool) -> None:
        for _ in range(n):
            cap.arrived("a")
            cap.matched("a", cpu_s, localized=localized)
            clock.t += 0.1

    sweeps(9, 0.01, True)
    sweeps(1, 0.11, True)  # (a window joined behind, billed to this sweep)
    f = cap.figures(["a"])
    assert f.measured_sessions == 1 and f.used_cores == pytest.approx(10 * 0.02, rel=0.05)  # the mean
    sweeps(1, 0.02, False)  # mapping now: not measured as a mapping session yet
    assert cap.figures(["a"]).measured_sessions == 0
    sweeps(MIN_SWEEPS, 0.04, False)
    f = cap.figures(["a"])
    assert f.measured_sessions == 1 and f.used_cores == pytest.approx(10 * 0.04, rel=0.1)
