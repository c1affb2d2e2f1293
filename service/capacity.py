"""What the node can carry: admission by measured capacity.

A session costs the node the rate its scans arrive at (shed ones too: they say what the vehicle
asks for) times the CPU each of its sweeps takes, its matcher's (:meth:`Capacity.matched`) plus
the service process's own, the pose graph's process's counted with it (:meth:`Capacity.service_sample`):
a node that leaves the graph no time drops keyframes and its map drifts. :meth:`Capacity.refusal`
says why a new session does not fit, or ``None`` (docs/architecture.md, "Admission").
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Collection, Hashable
from dataclasses import dataclass

__all__ = ["Capacity", "CapacityFigures", "MeasuredCosts"]

#: Weight of the newest sample in the moving averages.
ALPHA = 0.2
#: A session's rate is its own once this many of its scans arrived; its CPU once this many matched
#: (its first sweeps are cheap, its keyframe model small: counted at them, a burst of young
#: sessions would look cheaper than they are).
MIN_ARRIVALS = 5
MIN_SWEEPS = 20
#: A localizing session's CPU is its own after this many sweeps past its first: it grows no
#: keyframe model, so its cost is what its next sweeps cost (its first, a window prepared and
#: joined and its motion found, is not counted: docs/architecture.md, "Admission").
MIN_LOCALIZED_SWEEPS = 5
#: The service process's CPU per sweep is sampled over at least this many sweeps.
MIN_SERVICE_SWEEPS = 10
#: Sessions expected to localize that may be starting at once, per core: a start joins the map
#: around the vehicle and finds its motion, and many starting together stall every vehicle's scans
#: (docs/architecture.md, "Admission"). A session is starting from when it may start
#: (:meth:`Capacity.try_start`) until its first sweep is answered, STARTING_S at most.
STARTING_PER_CORE = 1
STARTING_S = 2.0
#: A session expected to localize on the map (service/localizing.py), before any localizing session
#: was measured, is counted at this share of a mapping one's expected CPU per sweep (the larger end
#: of what docs/benchmarks.md, "The fleet on mapped streets", measures).
LOCALIZED_SHARE = 0.35


@dataclass(frozen=True)
class CapacityFigures:
    """The node's capacity as measured now (``/status``' ``capacity``, ``/metrics``).

    Attributes
    ----------
    cores:
        CPUs the matchers run on (this node's, or the Ray cluster's).
    target:
        The share of them admission fills at most (``capacity_target``).
    load:
        The running sessions' measured cost as a share of ``cores * target`` (1.0: full).
    used_cores:
        The same in cores (matchers and service process together).
    sweep_cpu_s, service_cpu_s:
        Mean CPU seconds per sweep of the measured sessions' matchers, and of the service process.
    new_session_load:
        What a new session is expected to add to ``load``.
    sessions_more:
        How many more sessions at that cost fit.
    measured_sessions, running_sessions:
        Sessions counted at their own measured cost, and all counted.
    """

    cores: float
    target: float
    load: float
    used_cores: float
    sweep_cpu_s: float
    service_cpu_s: float
    new_session_load: float
    sessions_more: int
    measured_sessions: int
    running_sessions: int


@dataclass(frozen=True)
class MeasuredCosts:
    """What the node's sessions were measured to cost (:meth:`Capacity.measured`), kept across
    restarts (service/capacity_record.py): the last measured sessions' mean CPU per sweep of each
    kind (``None``: only the prior so far) and the service process's per sweep, on ``cores``."""

    cores: float
    mapping_sweep_cpu_s: float | None
    localizing_sweep_cpu_s: float | None
    service_cpu_s: float


@dataclass
class _Load:
    interval_s: float | None = None  # moving average of the intervals between arrivals
    last_arrival: float | None = None
    arrivals: int = 0
    cpu_s: float | None = None  # the matcher's CPU per sweep (of its kind: see Capacity.matched)
    sweeps: int = 0  # sweeps of its kind measured
    cpu_sum_s: float = 0.0  # (localizing: the CPU of those sweeps)
    localizing: bool = False  # its last sweep was localized on the map (or it opened to)
    opened_at: float | None = None  # when it was admitted expecting to localize
    answered: int = 0  # sweeps matched


def _measured(load: _Load) -> bool:
    """Whether the session is counted at its own CPU per sweep (enough of its sweeps measured)."""
    least = MIN_LOCALIZED_SWEEPS if load.localizing else MIN_SWEEPS
    return load.cpu_s is not None and load.sweeps >= least


def _average(old: float | None, new: float) -> float:
    return new if old is None else (1.0 - ALPHA) * old + ALPHA * new


class Capacity:
    """Measured load and admission (module docstring). Thread-safe: intake workers, session
    threads, the flusher and HTTP handlers call it."""

    def __init__(
        self,
        *,
        cores: float | Callable[[], float],
        shares_cores: bool,
        target: float = 0.6,
        rate_hz: float = 10.0,
        sweep_cpu_s: float = 0.09,
        retry_after_s: float = 10.0,
        idle_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not 0 < target <= 1:
            raise ValueError(f"capacity needs 0 < target <= 1, got {target}")
        self._cores = cores if callable(cores) else (lambda: float(cores))
        self.shares_cores = shares_cores
        self.target = target
        self.rate_hz = rate_hz
        self.retry_after_s = retry_after_s
        self.idle_s = idle_s
        self._clock = clock
        self._lock = threading.Lock()
        self._loads: dict[Hashable, _Load] = {}
        #: per kind (localizing or not), the mean of the last measured sessions (mapping: a prior
        #: at first; localizing: absent until one was measured)
        self._last_cpu_s = {False: sweep_cpu_s}
        self._measured_kinds: set[bool] = set()  # (kinds whose _last_cpu_s was measured, not the prior)
        self._service_cpu_s = 0.0
        self._service_mark: tuple[float, int, float] | None = None  # process CPU, sweeps, local CPU
        self._sweeps = 0
        self._local_cpu_s = 0.0

    # -- measurements ---------------------------------------------------------------------------
    def arrived(self, key: Hashable) -> None:
        """A scan for session ``key`` arrived (admitted or not, shed or not)."""
        now = self._clock()
        with self._lock:
            load = self._loads.setdefault(key, _Load())
            if load.last_arrival is not None:
                load.interval_s = _average(load.interval_s, max(now - load.last_arrival, 0.0))
            load.last_arrival = now
            load.arrivals += 1

    def opening(self, key: Hashable, *, localizing: bool) -> None:
        """Session ``key`` opens expecting to localize on the map or not: until measured it is
        counted at the expected cost of its kind (one expected to localize starts when
        :meth:`try_start` lets it)."""
        with self._lock:
            load = self._loads.setdefault(key, _Load())
            load.localizing = localizing
            load.opened_at = None

    def matched(
        self,
        key: Hashable,
        cpu_s: float,
        *,
        in_process: bool = False,
        localized: bool = False,
        first: bool = False,
    ) -> None:
        """Session ``key``'s matcher spent ``cpu_s`` on one sweep (``in_process``: in this process;
        ``localized``: on the map; ``first``: the session's first sweep, which a localizing
        session's expected cost leaves out: :data:`MIN_LOCALIZED_SWEEPS`).

        A mapping session's cost is a moving average (its keyframe model grows); a localizing
        one's the mean since it began to localize: a window joined now and then costs much once
        and little per sweep it serves, which a moving average overstates for a while. A session
        that changes kind is measured anew, counted at its new kind's expected cost meanwhile."""
        cpu_s = max(cpu_s, 0.0)
        with self._lock:
            load = self._loads.setdefault(key, _Load())
            load.answered += 1
            self._sweeps += 1
            if in_process:
                self._local_cpu_s += cpu_s
            if localized != load.localizing:
                load.cpu_s, load.sweeps, load.cpu_sum_s = None, 0, 0.0
            load.localizing = localized
            if first and localized:
                return
            load.sweeps += 1
            if localized:
                load.cpu_sum_s += cpu_s
                load.cpu_s = load.cpu_sum_s / load.sweeps
            else:
                load.cpu_s = _average(load.cpu_s, cpu_s)

    def service_sample(
        self, process_cpu_s: float | None = None, *, graph_cpu_s: float = 0.0, settling: bool = False
    ) -> None:
        """Sample the service's own CPU per sweep (the flusher, every flush): ``process_cpu_s`` is
        this process's CPU time so far (``time.process_time()``), ``graph_cpu_s`` the pose graph
        process's (:meth:`randt.service.graph.ServiceGraph.cpu_s`). ``settling``: the CPU since
        the last sample is the service's own start (the graph replaying its log), not what the
        sweeps cost: it is not sampled, the next sample counts from here."""
        cpu = (time.process_time() if process_cpu_s is None else process_cpu_s) + graph_cpu_s
        with self._lock:
            mark = (cpu, self._sweeps, self._local_cpu_s)
            if self._service_mark is None or settling:
                self._service_mark = mark
                return
            d_cpu, d_sweeps, d_local = (a - b for a, b in zip(mark, self._service_mark, strict=True))
            if d_sweeps < MIN_SERVICE_SWEEPS:
                return
            self._service_mark = mark
            self._service_cpu_s = _average(self._service_cpu_s or None, max(d_cpu - d_local, 0.0) / d_sweeps)

    def forget(self, keep: Collection[Hashable]) -> None:
        """Drop what is known of sessions not in ``keep`` (ended, expired, evicted)."""
        with self._lock:
            for key in [k for k in self._loads if k not in keep]:
                del self._loads[key]

    def measured(self) -> MeasuredCosts:
        """What the sessions measured so far cost (for :meth:`start_from` after a restart)."""
        with self._lock:
            for kind in (False, True):
                self._expected_cpu_s(kind)  # (the running sessions' mean, kept as the last)
            last = {k: v for k, v in self._last_cpu_s.items() if k in self._measured_kinds}
            return MeasuredCosts(self.cores, last.get(False), last.get(True), self._service_cpu_s)

    def start_from(self, costs: MeasuredCosts) -> bool:
        """Count new sessions at what the sessions before a restart were measured to cost, and the
        service process at its measured CPU per sweep, instead of the priors, until measured anew;
        not when they were measured on another number of cores (``False``: not taken)."""
        if abs(costs.cores - self.cores) > 1e-9:
            return False
        with self._lock:
            for kind, cpu in ((False, costs.mapping_sweep_cpu_s), (True, costs.localizing_sweep_cpu_s)):
                if cpu is not None and cpu > 0:
                    self._last_cpu_s[kind] = cpu
                    self._measured_kinds.add(kind)
            if costs.service_cpu_s > 0:
                self._service_cpu_s = costs.service_cpu_s
        return True

    # -- the model ------------------------------------------------------------------------------
    def _expected_cpu_s(self, localizing: bool = False) -> float:
        """What a session not measured yet (young, or opening) is counted at: the measured
        sessions' mean CPU per sweep among those of its kind (localizing on the map or mapping),
        the last measured ones' when none runs, a prior before any (``sweep_cpu_s``, a localizing
        one :data:`LOCALIZED_SHARE` of the mapping one's)."""
        measured = [
            ld.cpu_s
            for ld in self._loads.values()
            if ld.cpu_s is not None and _measured(ld) and ld.localizing == localizing
        ]
        if measured:
            self._last_cpu_s[localizing] = sum(measured) / len(measured)
            self._measured_kinds.add(localizing)
        elif localizing and localizing not in self._last_cpu_s:  # (none measured yet)
            return self._expected_cpu_s() * LOCALIZED_SHARE
        return self._last_cpu_s[localizing]

    def _rate_hz(self, load: _Load, now: float) -> float:
        """The session's measured scan rate; ``rate_hz`` until measured, 0 once idle ``idle_s``."""
        if load.last_arrival is not None and now - load.last_arrival > self.idle_s:
            return 0.0  # it stopped sending: it costs nothing until it sends again
        if load.arrivals >= MIN_ARRIVALS and load.interval_s:
            return 1.0 / load.interval_s
        return self.rate_hz

    @property
    def cores(self) -> float:
        """CPUs the matchers run on now (a Ray cluster's change as nodes come and go); at least 1."""
        return max(float(self._cores()), 1.0)

    def _share(self, matcher_cores: float, service_cores: float, cores: float) -> float:
        """Cores used as a share of what admission may fill (1.0: full): matchers and service
        process together where they share the node's cores; else (Ray) the larger of the
        matchers' share of the cluster and the service process's of its one core (one GIL)."""
        if self.shares_cores:
            return (matcher_cores + service_cores) / (cores * self.target)
        return max(matcher_cores / (cores * self.target), service_cores / self.target)

    def _figures(
        self, running: Collection[Hashable], exclude: Collection[Hashable], localizing: bool = False
    ) -> CapacityFigures:
        now, cores = self._clock(), self.cores
        expected = self._expected_cpu_s(localizing)  # (the new session's)
        of_kind = {kind: self._expected_cpu_s(kind) for kind in (False, True)}
        matcher = service = 0.0
        measured = 0
        for key in running:
            if key in exclude:
                continue
            load = self._loads.get(key) or _Load()
            own = _measured(load)
            measured += own
            rate = self._rate_hz(load, now)
            matcher += rate * (load.cpu_s if own and load.cpu_s is not None else of_kind[load.localizing])
            service += rate * self._service_cpu_s
        new = self._share(self.rate_hz * expected, self.rate_hz * self._service_cpu_s, cores)
        share = self._share(matcher, service, cores)
        more = math.floor((1.0 - share) / new + 1e-9) if new > 0 else 0
        return CapacityFigures(
            cores=cores,
            target=self.target,
            load=share,
            used_cores=matcher + service,
            sweep_cpu_s=expected,
            service_cpu_s=self._service_cpu_s,
            new_session_load=new,
            sessions_more=max(more, 0),
            measured_sessions=measured,
            running_sessions=len([k for k in running if k not in exclude]),
        )

    def figures(self, running: Collection[Hashable]) -> CapacityFigures:
        """The capacity as measured now, over the running (and opening) sessions ``running``."""
        with self._lock:
            return self._figures(running, ())

    def try_start(self, key: Hashable, running: Collection[Hashable]) -> bool:
        """Whether session ``key``, admitted expecting to localize, may start now: fewer than
        :data:`STARTING_PER_CORE` per core of ``running`` are starting (started, no sweep
        answered yet, for :data:`STARTING_S` at most). If so it is starting from now. Its
        opener waits meanwhile, its scans queued: starts follow each other instead of stalling
        every vehicle's scans together (docs/architecture.md, "Admission")."""
        now, most = self._clock(), max(1, round(STARTING_PER_CORE * self.cores))
        with self._lock:
            starting = sum(
                1
                for other in running
                if other != key
                and (load := self._loads.get(other)) is not None
                and load.opened_at is not None
                and load.answered == 0
                and now - load.opened_at < STARTING_S
            )
            if starting >= most:
                return False
            self._loads.setdefault(key, _Load()).opened_at = now
            return True

    def refusal(
        self, running: Collection[Hashable], exclude: Collection[Hashable] = (), *, localizing: bool = False
    ) -> str | None:
        """Why a new session cannot be admitted beside ``running`` (less ``exclude``: a session
        that gives up its slot for it), or ``None``: it fits. A node that carries nothing (no
        session, or none sending) admits one whatever it is expected to cost. ``localizing``: the
        new session is expected to localize on the map (counted at a localizing session's cost)."""
        with self._lock:
            f = self._figures(running, exclude, localizing)
        if f.load <= 0.0 or f.load + f.new_session_load <= 1.0 + 1e-9:
            return None
        return (
            f"the node is at its measured capacity: its {f.running_sessions} sessions use "
            f"{100 * f.load:.0f} % of what it may fill ({f.used_cores:.2f} of {f.cores:g} cores x "
            f"{f.target:g}; {1000 * f.sweep_cpu_s:.0f} ms of matcher and {1000 * f.service_cpu_s:.0f} ms "
            f"of service CPU per sweep) and a new session at {self.rate_hz:g} Hz needs "
            f"{100 * f.new_session_load:.0f} % more: send again in {self.retry_after_s:g} s, or add capacity"
        )


def saturated(capacity: Capacity | None, running: Callable[[], Collection[Hashable]]) -> bool:
    """Whether the node is past what admission may fill (the ``running`` sessions' measured load
    above 1; always without capacity admission): only then does a session that is behind let its
    keyframe model lag. Within capacity a backlog clears by itself, and a session whose model never
    lags gets the offline matcher's poses to the digit."""
    return capacity is None or capacity.figures(running()).load > 1.0
