"""How the service's processes are set up: one BLAS thread in each, and child processes (the
matcher processes, the pose graph's) that leave the process group's signals to the service.

Ctrl-C in a terminal reaches the whole process group, and so does systemd's stop
(``KillMode=control-group``, or ``kill -- -PGID``). The service stops its children itself after
draining and saving the sessions, so a child ignores SIGINT and SIGTERM from its first
instruction (:func:`start_ignoring_group_signals` in the parent, :func:`ignore_group_signals` in
the child) and is killed at interpreter exit if it still runs.
"""

from __future__ import annotations

import atexit
import contextlib
import multiprocessing.process
import multiprocessing.util
import signal
import threading
import weakref
from collections.abc import Iterator, Sequence
from typing import Any

__all__ = [
    "GROUP_SIGNALS",
    "ignore_group_signals",
    "single_threaded_blas",
    "start_ignoring_group_signals",
]


def single_threaded_blas() -> None:
    """Limit the BLAS/OpenMP thread pools of this process to one thread (for the rest of its life).

    The service runs one matcher process per core next to its own threads, so the cores are
    always busy: a multi-threaded BLAS call then has its threads spin-wait for a core (OpenBLAS
    does), several times slower (docs/architecture.md). The service process
    (:meth:`randt.service.runtime.Service.start`) and every matcher process call this. It uses
    threadpoolctl, which sets the limit through each loaded library's own API, so it works after
    numpy is imported (environment variables such as ``OPENBLAS_NUM_THREADS`` are read only when
    the library loads).
    """
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)


#: The signals a terminal (Ctrl-C) or systemd (its stop) sends the whole process group: the
#: service's child processes leave them to the service, which stops them after saving.
GROUP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_spawning = threading.local()
_SPAWNV = multiprocessing.util.spawnv_passfds


def _spawnv_passfds(path: bytes, args: Sequence[Any], passfds: Sequence[int]) -> int:
    """multiprocessing's fork and exec of a spawned child (``multiprocessing.util``'s, wrapped):
    inside :func:`_sigint_ignored_by_children`, with SIGINT and SIGTERM blocked in this thread
    for the fork and exec, so that the child starts with them blocked; elsewhere as it was."""
    if not getattr(_spawning, "active", False):
        return int(_SPAWNV(path, args, passfds))
    old = signal.pthread_sigmask(signal.SIG_BLOCK, GROUP_SIGNALS)
    try:
        return int(_SPAWNV(path, args, passfds))
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


multiprocessing.util.spawnv_passfds = _spawnv_passfds


@contextlib.contextmanager
def _sigint_ignored_by_children() -> Iterator[None]:
    """Start child processes (spawn) from this thread with SIGINT and SIGTERM ignored from their
    first instruction: a Ctrl-C (or a stop of the process group) during a child's first second
    (interpreter start, imports, before :func:`ignore_group_signals` runs in it) cannot kill it
    with a KeyboardInterrupt traceback on the terminal; the service stops it after saving.

    The signals are *blocked* in the starting thread around the fork and exec (the wrapped
    ``spawnv_passfds``): a child inherits its parent thread's signal mask through fork and exec,
    so neither can reach it until it ignores them itself (:func:`ignore_group_signals`), and a
    blocked signal that arrives meanwhile stays pending and is dropped then. Only the starting
    thread blocks them, so a Ctrl-C in that moment still reaches the service (its main thread);
    setting the disposition to ignored instead would be process-wide and lose it.
    """
    _spawning.active = True
    try:
        yield
    finally:
        _spawning.active = False


#: The processes started with the two signals ignored (:func:`start_ignoring_group_signals`).
_IGNORING: weakref.WeakSet[multiprocessing.process.BaseProcess] = weakref.WeakSet()


def start_ignoring_group_signals(proc: multiprocessing.process.BaseProcess) -> None:
    """Start ``proc`` (spawn) so that it ignores SIGINT and SIGTERM from its first instruction
    (:func:`_sigint_ignored_by_children`), and kill it at interpreter exit if it still runs:
    multiprocessing's own exit hook stops daemonic children with SIGTERM, which they ignore, and
    then waits for them (for ever, if they were never stopped)."""
    with _sigint_ignored_by_children():
        proc.start()
    _IGNORING.add(proc)


def _kill_ignoring_children() -> None:
    for proc in list(_IGNORING):
        with contextlib.suppress(Exception):
            if proc.is_alive():
                proc.kill()


# (atexit runs its hooks last in, first out: this one before multiprocessing's, registered when
# multiprocessing.util was imported, above)
atexit.register(_kill_ignoring_children)


def ignore_group_signals() -> None:
    """In a child process of the service: ignore SIGINT and SIGTERM (the service stops it), then
    unblock them (a child starts with them blocked, :func:`_sigint_ignored_by_children`; ignoring
    a signal discards it if pending, so nothing is delivered late), so that the child's own
    threads and processes start with a clean signal mask."""
    for sig in GROUP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, GROUP_SIGNALS)
