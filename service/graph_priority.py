"""How the pose graph's process shares the cores with the matchers: it runs at ``SCHED_IDLE``
(else niced), is held off the cores while sweeps are matched (:class:`YieldGate`), is raised when
starved, dies with the service, and its CPU is read for admission (``docs/architecture.md``,
"Threads or processes")."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
from collections.abc import Iterator

__all__ = [
    "ESCALATE_S",
    "GRAPH_NICE",
    "STARVED_S",
    "CpuMeter",
    "StarvationGuard",
    "YieldGate",
    "die_with_parent",
    "lowest_priority",
    "process_cpu_s",
    "set_graph_priority",
]

log = logging.getLogger(__name__)

#: The graph process's niceness (added to the service's).
GRAPH_NICE = 10
#: The graph process runs at ``SCHED_IDLE``, which yields to any other process, ours or not: with
#: work in flight and no answer for this long it is starved (other processes can hold it for good:
#: docs/architecture.md, "Threads or processes"), and runs at the normal policy niced by
#: GRAPH_NICE until its queue is empty (:class:`StarvationGuard`).
STARVED_S = 5.0
#: Raised and still behind this long, it runs at the service's own niceness until its queue is
#: empty: niced, beside a CPU burner at the normal niceness, it gets about a tenth of a core.
#: Admission counts the graph's CPU with the service process's (service/capacity.py), so the
#: node's measured capacity leaves it that time.
ESCALATE_S = 30.0


class YieldGate:
    """Keeps the graph process off the cores while sweeps are being matched: stopped
    (``SIGSTOP``) when the first sweep enters :meth:`matching`, continued (``SIGCONT``) when the
    last one leaves. ``SCHED_IDLE`` alone gives the matchers every core they ask for, but not the
    caches, memory bandwidth and clock the graph shares with them from the other core.

    The graph is never starved: once it has been held ``max_hold_s`` without a break, it runs
    ``min_run_s`` whatever arrives. POSIX only (elsewhere it does nothing); the process it holds
    must die with its parent (``die_with_parent``), since a stopped process cannot exit itself.
    """

    def __init__(self, *, max_hold_s: float = 1.0, min_run_s: float = 0.2) -> None:
        self.max_hold_s = max_hold_s
        self.min_run_s = min_run_s
        self._lock = threading.Lock()
        self._pid: int | None = None
        self._pidfd: int | None = None
        self._busy = 0
        self._held_since: float | None = None  # monotonic time of the SIGSTOP, while held
        self._free_until = 0.0  # no hold before this (the starvation guard)
        #: seconds the process was held, and how many holds (metrics, benchmarks)
        self.held_s = 0.0
        self.holds = 0

    def attach(self, pid: int) -> None:
        with self._lock:
            self._pid = pid if hasattr(signal, "SIGSTOP") else None
            # A pidfd names this process and no other: once it has exited and been reaped, its
            # pid may be another process's, which a plain kill would stop (Linux >= 5.3).
            try:
                self._pidfd = os.pidfd_open(pid) if self._pid is not None else None
            except ProcessLookupError:  # gone already: nothing to hold (its pid may be reused)
                self._pid = self._pidfd = None
            except (AttributeError, OSError):  # no pidfd here: the plain pid
                self._pidfd = None

    def detach(self) -> None:
        """Continue the process for good (before stopping it, or when it is gone)."""
        with self._lock:
            self._release(time.monotonic())
            self._pid = None
            if self._pidfd is not None:
                os.close(self._pidfd)
                self._pidfd = None

    def _signal(self, sig: int) -> bool:
        """Send ``sig`` to the process; False when it is gone."""
        assert self._pid is not None
        try:
            if self._pidfd is not None:
                signal.pidfd_send_signal(self._pidfd, sig)
            else:
                os.kill(self._pid, sig)
        except ProcessLookupError:
            return False
        return True

    def _release(self, now: float) -> None:
        if self._held_since is None or self._pid is None:
            return
        self._signal(signal.SIGCONT)
        self.held_s += now - self._held_since
        self._held_since = None

    def _enter(self) -> None:
        with self._lock:
            self._busy += 1
            now = time.monotonic()
            if self._pid is None:
                return
            if self._held_since is not None and now - self._held_since > self.max_hold_s:
                self._release(now)  # held too long without a break: it runs for a while
                self._free_until = now + self.min_run_s
            elif self._held_since is None and now >= self._free_until and self._signal(signal.SIGSTOP):
                self._held_since = now
                self.holds += 1

    def _exit(self) -> None:
        with self._lock:
            self._busy -= 1
            if self._busy == 0:
                self._release(time.monotonic())

    @contextlib.contextmanager
    def matching(self) -> Iterator[None]:
        """Around the matching of one sweep: the graph does not run while any is inside."""
        self._enter()
        try:
            yield
        finally:
            self._exit()


def process_cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process (all its threads), from ``/proc`` (Linux)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


def die_with_parent() -> None:
    """Linux: this process gets SIGKILL when the service's process dies, even while it is
    stopped by :class:`YieldGate` (a stopped process would otherwise outlive a killed service)."""
    with contextlib.suppress(OSError, AttributeError):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def lowest_priority() -> None:
    """Run this process only on a core nothing else wants: ``SCHED_IDLE`` (Linux), else niced by
    ``GRAPH_NICE``. Niced alone, the graph still slowed the matchers' answers; at ``SCHED_IDLE``
    it hardly does, and still takes every keyframe (docs/benchmarks.md, "Service with the pose
    graph on and off")."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):  # not Linux, or refused
        with contextlib.suppress(OSError):
            os.nice(GRAPH_NICE)
        return
    # A policy is a thread's own: threads started before this call (the worker pools the imports
    # start: BLAS, TBB) kept the normal one.
    with contextlib.suppress(OSError):
        for tid in os.listdir("/proc/self/task"):
            with contextlib.suppress(OSError, ValueError):
                os.sched_setscheduler(int(tid), os.SCHED_IDLE, os.sched_param(0))


def set_graph_priority(pid: int, *, idle: bool, nice: int = GRAPH_NICE) -> bool:
    """Every thread of process ``pid`` at ``SCHED_IDLE`` (``idle``), or at the normal policy niced
    by ``nice`` beyond this process's own niceness; False if any was refused (not Linux, not
    permitted, gone)."""
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        niceness = min(19, os.getpriority(os.PRIO_PROCESS, 0) + nice)
        policy = os.SCHED_IDLE if idle else os.SCHED_OTHER
    except (AttributeError, OSError, ValueError):
        return False
    done = True
    for tid in tids:
        try:
            os.sched_setscheduler(tid, policy, os.sched_param(0))
            if not idle:
                os.setpriority(os.PRIO_PROCESS, tid, niceness)
        except ProcessLookupError:  # a thread that ended meanwhile
            continue
        except OSError:
            done = False
    return done


class StarvationGuard:
    """Raises a starved graph process above ``SCHED_IDLE`` (:data:`STARVED_S`), to the service's
    own niceness if it is still behind (:data:`ESCALATE_S`), and lowers it again once it has
    caught up; :meth:`check` runs at each of the supervisor's looks at the process."""

    def __init__(self) -> None:
        #: the process runs above SCHED_IDLE for now (starved), and how often it was raised; runs
        #: at the service's niceness for now (raised and still behind), and how often
        self.raised = False
        self.starvations = 0
        self.escalated = False
        self.escalations = 0
        self._raised_at = 0.0

    def reset(self) -> None:
        """A new process: it starts at ``SCHED_IDLE`` (:func:`lowest_priority`)."""
        self.raised = self.escalated = False

    def check(self, pid: int, *, busy: bool, waited_s: float | None) -> None:
        """``busy``: work queued or in flight; ``waited_s``: how long the work in flight has
        waited for an answer (None: none in flight)."""
        now = time.monotonic()
        starved = waited_s is not None and waited_s > STARVED_S
        if starved and not self.raised and set_graph_priority(pid, idle=False):
            self.raised, self._raised_at = True, now
            self.starvations += 1
            log.warning(
                "pose graph: no answer for %.0f s with work in flight (other processes take every "
                "core): it runs niced by %d instead of SCHED_IDLE until it catches up",
                STARVED_S,
                GRAPH_NICE,
            )
        elif busy and self.raised and not self.escalated and now - self._raised_at > ESCALATE_S:
            if set_graph_priority(pid, idle=False, nice=0):
                self.escalated = True
                self.escalations += 1
                log.warning(
                    "pose graph: still behind %.0f s after it was raised: it runs at the service's "
                    "niceness until it catches up",
                    ESCALATE_S,
                )
        elif not busy and self.raised and set_graph_priority(pid, idle=True):
            self.raised = self.escalated = False
            log.info("pose graph: caught up, back to SCHED_IDLE")


class CpuMeter:
    """CPU seconds the graph's processes have used, every generation counted (Linux, from /proc;
    0 elsewhere): the node's admission counts them (service/capacity.py). A process's start
    (spawn and imports until it says it is alive) is not counted: it is no cost per sweep, and
    billed to one flush's sweeps it would fill the node's capacity (docs/benchmarks.md, "One
    vehicle within capacity")."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        #: the process last read, its CPU then, and that of the generations before
        self._pid: int | None = None
        self._last = 0.0
        self._dead = 0.0
        #: each process's CPU when it said it is alive (its start, not counted)
        self._at_alive: dict[int, float] = {}

    def alive(self, pid: int) -> None:
        """Process ``pid`` says it is alive: its CPU counts from now."""
        with contextlib.suppress(OSError, ValueError, IndexError):
            self._at_alive[pid] = process_cpu_s(pid)

    def read(self, pid: int | None) -> float:
        """The total so far, ``pid`` the current process (None: none runs)."""
        now = 0.0
        if pid is not None:
            with contextlib.suppress(OSError, ValueError, IndexError):
                started = self._at_alive.get(pid)
                now = 0.0 if started is None else max(process_cpu_s(pid) - started, 0.0)
        with self._lock:
            if pid != self._pid:  # a new generation: the last one's CPU stays counted
                self._dead += self._last
                self._pid, self._last = pid, 0.0
            self._last = max(self._last, now)
            return self._dead + self._last
