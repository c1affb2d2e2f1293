"""The local executor: the sessions' matchers in a pool of worker processes, so the numeric work
uses every core (the matcher's Python glue holds the GIL: docs/architecture.md, "Threads or
processes"). ``matcher_processes`` in the settings: one per core by default, 0 keeps them in the
session threads (:class:`randt.service.matchers.LocalMatcher`).

Each session thread still owns its queue and its order; it hands one sweep at a time to its
:class:`RemoteMatcher`, which forwards it to the process the session was assigned to (the one
with fewest sessions) and waits for the result. A process serves its sessions one request at a
time (service/matcher_host.py). Requests and results are pickled through a pipe.

An exception raised in a worker process reaches the session thread as the same class with the
same attributes (a :class:`~randt.core.errors.DegenerateProblemError` keeps its ``weak_directions``, a
``ValueError`` stays a ``ValueError``), the worker's traceback attached as a note; one that cannot
be pickled arrives as a :class:`MatcherProcessError` naming it. If a worker process dies, the calls
on it raise :class:`MatcherProcessDiedError`; the session manager then drops the affected sessions
without saving them (their last snapshot plus their pose log is the truth) and the next scan
resumes each from the store on a fresh process.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from randt.core.config import RegistrationSettings
from randt.core.odometry import MatcherSettings, PosePrior, ScanResult
from randt.core.tiles import TileGrid
from randt.service.matcher_host import READY, serve_process
from randt.service.matcher_io import (
    Key,
    MapFrame,
    MatcherProcessDiedError,
    MatcherProcessError,
    Registered,
    scan_payload,
)
from randt.service.processes import start_ignoring_group_signals
from randt.wire.messages import WireLimits
from randt.wire.ros2 import Ros2Scan

__all__ = ["Channel", "ForwardingMatcher", "MatcherPool", "RemoteMatcher"]

log = logging.getLogger(__name__)


class Channel:
    """A connection to a worker that speaks :func:`randt.service.matcher_host.serve_requests`'
    protocol (a matcher process's pipe, a Ray matcher host's socket): the worker's ready message
    first, then one call at a time (a lock). A closed connection marks it dead: its calls raise
    :class:`MatcherProcessDiedError`."""

    def __init__(self, conn: Connection, name: str) -> None:
        self._conn = conn
        self.name = name
        self._lock = threading.Lock()
        self.sessions: set[Key] = set()
        self.dead = False
        self.ready = False  # set once the worker has sent its ready message (warm-up done)

    def _take_ready(self, timeout: float | None) -> bool:
        """Consume the ready message if it has come within ``timeout`` (call with the lock held)."""
        if self.ready:
            return True
        if timeout is not None and not self._conn.poll(timeout):
            return False
        message = self._conn.recv()
        if message != READY:
            raise MatcherProcessError(f"{self.name} sent {message!r} before being ready")
        self.ready = True
        return True

    def wait_ready(self, timeout: float | None) -> bool:
        """Whether the worker finished its warm-up within ``timeout`` s (None: wait for it)."""
        with self._lock:
            if self.dead:
                return False
            try:
                return self._take_ready(timeout)
            except (EOFError, OSError):
                self.dead = True
                return False

    def poll_ready(self) -> bool:
        """Whether the warm-up is done, without waiting (False while a first call waits for it)."""
        if self.ready:
            return True
        if not self._lock.acquire(blocking=False):
            return False
        try:
            return not self.dead and self._take_ready(0.0)
        except (EOFError, OSError):
            self.dead = True
            return False
        finally:
            self._lock.release()

    def _wait_answer(self) -> None:
        """Return once the answer can be read (or the connection is closed). A pipe to a child
        process closes when the child dies, so this does nothing; a socket across machines
        overrides it to notice a dead peer that cannot close its end."""

    def call(self, op: str, key: Key | None, *args: object) -> Any:
        with self._lock:
            if self.dead:
                raise MatcherProcessDiedError(f"{self.name} is gone")
            try:
                self._take_ready(None)
                self._conn.send((op, key, args))
                self._wait_answer()
                ok, value = self._conn.recv()
            except (EOFError, OSError) as exc:
                self.dead = True
                raise MatcherProcessDiedError(f"{self.name} died: {exc or type(exc).__name__}") from exc
        if ok:
            return value
        raise value

    def close(self) -> None:
        """Close the connection (the worker's loop ends, or waits for another)."""
        self.dead = True
        self._conn.close()


class _WorkerProcess(Channel):
    """One child process and the pipe to it."""

    def __init__(self, ctx: multiprocessing.context.SpawnContext, index: int) -> None:
        conn, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=serve_process, args=(child,), name=f"randt-matcher-{index}", daemon=True
        )
        start_ignoring_group_signals(self._proc)
        child.close()
        super().__init__(conn, f"matcher process {index} (pid {self._proc.pid})")
        self.index = index

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def _warm(self) -> bool:
        """Whether the process has finished its warm-up (without waiting for it; a call in progress
        counts as warm)."""
        if not self._lock.acquire(blocking=False):
            return True
        try:
            return self._take_ready(0)
        except (EOFError, OSError, MatcherProcessError):
            return False
        finally:
            self._lock.release()

    def close(self, timeout: float = 10.0) -> None:
        if not self.dead and (self.sessions or self._warm()):
            with contextlib.suppress(MatcherProcessDiedError):
                self.call("quit", None)
        elif self._proc.is_alive():  # still warming up, nothing to keep: not worth the wait
            self._proc.kill()
        self._proc.join(timeout)
        if self._proc.is_alive():  # (it ignores SIGTERM: serve_process)
            self._proc.kill()
            self._proc.join(timeout)
        self._conn.close()
        self.dead = True


class MatcherPool:
    """``n`` worker processes (started with ``spawn``: the service has threads, so no ``fork``)."""

    def __init__(self, n: int) -> None:
        if n < 1:
            raise ValueError(f"a matcher pool needs at least one process, got {n}")
        self._ctx = multiprocessing.get_context("spawn")
        self._lock = threading.Lock()
        self._procs = [_WorkerProcess(self._ctx, i) for i in range(n)]
        self._next_index = n

    def __len__(self) -> int:
        return len(self._procs)

    def pids(self) -> list[int | None]:
        return [p.pid for p in self._procs]

    def wait_ready(self, timeout: float | None = None) -> bool:
        """Whether every process finished its warm-up (compiled or loaded the kernels) within
        ``timeout`` s in all (None: wait as long as it takes). Sessions may open before: their
        first call waits for the warm-up instead."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._lock:
            procs = list(self._procs)
        for p in procs:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not p.wait_ready(left):
                return False
        return True

    @property
    def ready(self) -> bool:
        """Every process has finished its warm-up (a non-blocking check)."""
        procs = list(self._procs)  # no lock: /status must not wait while open() replaces a process
        return all(p.poll_ready() for p in procs)

    def open(
        self,
        key: Key,
        state: dict[str, np.ndarray] | None = None,
        grid: TileGrid | None = None,
        settings: MatcherSettings | None = None,
        registration: RegistrationSettings | None = None,
    ) -> RemoteMatcher:
        """A matcher for session ``key`` (restored from ``state``) on the least busy process.

        With ``grid`` (the session's map), results carry only the points ``grid.insert`` could
        keep (:meth:`~randt.core.tiles.TileGrid.candidate_mask`, computed in the worker process).
        ``settings`` and ``registration`` are the :class:`~randt.core.odometry.IncrementalMatcher`'s
        (None: its defaults).
        """
        with self._lock:
            for i, p in enumerate(self._procs):
                if p.dead:  # replace a dead process before placing anyone on it
                    log.warning("matcher process %d died: starting a replacement", p.index)
                    p.close(timeout=1.0)
                    self._procs[i] = _WorkerProcess(self._ctx, self._next_index)
                    self._next_index += 1
            proc = min(self._procs, key=lambda p: len(p.sessions))
            proc.sessions.add(key)
        params = None if grid is None else (grid.tile_size_m, grid.voxel_size_m, grid.max_points_per_voxel)
        try:
            return RemoteMatcher(self, proc, key, state, params, settings, registration)
        except BaseException:
            proc.sessions.discard(key)
            raise

    def _release(self, proc: _WorkerProcess, key: Key) -> None:
        proc.sessions.discard(key)

    def close(self) -> None:
        with self._lock:
            procs, self._procs = self._procs, []
        for p in procs:
            p.close()


class ForwardingMatcher:
    """A session's matcher running elsewhere (a worker process, a Ray actor), reached through the
    subclass's :meth:`_call` (one request of the worker's protocol). The trajectory is kept here
    as well (appended from each result, so reading it needs no round trip); there is no model
    update to ask for (the far side rebuilds the model on a thread as soon as the sweep is
    matched)."""

    def __init__(self, state: dict[str, np.ndarray] | None) -> None:
        self.poses: list[np.ndarray] = [] if not state else list(np.asarray(state["poses"]).reshape(-1, 4, 4))

    def _call(self, op: str, *args: Any) -> Any:
        """Request ``op`` for this session on its worker: the value, or the worker's exception
        raised as itself (a dead worker: :class:`MatcherProcessDiedError`)."""
        raise NotImplementedError

    def register_payload(
        self,
        payload: bytes | Ros2Scan,
        *,
        limits: WireLimits | None = None,
        behind: bool = False,
        keyframe_voxel_m: float | None = None,
        frame: MapFrame | None = None,
    ) -> Registered:
        """:meth:`IncrementalMatcher.register_scan` of a scan payload on the session's worker: sent
        as the bytes that came, decoded there (:func:`randt.service.matcher_io.decoded_sweep`), the
        answer with the points the session's map may keep and their intensities
        (:class:`Registered`; with ``keyframe_voxel_m``, the keyframe's points too). A payload whose
        bodies do not decode raises the decoder's :class:`~randt.core.errors.BadMessageError`.

        Unless ``behind`` (several of the session's scans are waiting), the worker starts a
        keyframe's model rebuild on a thread as soon as the sweep is matched, beside the reply,
        and the session's next request waits for it. Only when ``behind`` does the next sweep
        match without the newest keyframe (the model rebuilt once for two,
        :meth:`IncrementalMatcher.update_model`)."""
        registered: Registered = self._call(
            "register_payload", payload, limits, behind, keyframe_voxel_m, frame
        )
        self.poses.append(registered.result.T_world_sensor)
        return registered

    def register_scan(
        self,
        points_xyz: np.ndarray,
        *,
        time_offset_s: np.ndarray | None = None,
        prior: PosePrior | None = None,
        stamp_s: float | None = None,
        defer_model: bool = True,
        behind: bool = False,
    ) -> ScanResult:
        """:meth:`register_payload`'s result for a sweep's arrays, sent as a vehicle would send them
        (:func:`randt.service.matcher_io.scan_payload`: points and offsets float32, the stamp in
        whole ns, 0 without one), for tests that compare with an in-process
        :class:`~randt.core.odometry.IncrementalMatcher` (``defer_model`` is accepted for its
        signature: the far side always defers). With the session's map given to the executor's
        ``open``, its ``deskewed_xyz`` is empty: the map's points are in the answer."""
        del defer_model
        payload = scan_payload(
            points_xyz,
            stamp_ns=0 if stamp_s is None else round(stamp_s * 1e9),
            seq=len(self.poses),
            time_offset_s=time_offset_s,
            prior=prior,
        )
        return self.register_payload(payload, behind=behind).result

    def update_model(self) -> float:
        """Nothing to do here: the far side rebuilds the model itself."""
        return 0.0

    def state_dict(self) -> dict[str, np.ndarray]:
        state: dict[str, np.ndarray] = self._call("state")
        return state

    def snapshot_state(self) -> dict[str, np.ndarray]:
        """:meth:`state_dict` without the trajectory
        (:func:`randt.service.matcher_io.without_trajectory`), built on the far side."""
        state: dict[str, np.ndarray] = self._call("snapshot")
        return state


class RemoteMatcher(ForwardingMatcher):
    """A session's matcher in one of the pool's worker processes."""

    def __init__(
        self,
        pool: MatcherPool,
        proc: _WorkerProcess,
        key: Key,
        state: dict[str, np.ndarray] | None,
        grid_params: tuple[int, float, int] | None = None,
        settings: MatcherSettings | None = None,
        registration: RegistrationSettings | None = None,
    ) -> None:
        self._pool, self._proc, self._key = pool, proc, key
        self._call("open", state, grid_params, settings, registration)
        super().__init__(state)

    @property
    def process_index(self) -> int:
        return self._proc.index

    def _call(self, op: str, *args: Any) -> Any:
        return self._proc.call(op, self._key, *args)

    def close(self) -> None:
        """Forget the session in its process (its state should have been saved first)."""
        try:
            self._call("drop")
        except MatcherProcessDiedError:
            pass
        finally:
            self._pool._release(self._proc, self._key)
