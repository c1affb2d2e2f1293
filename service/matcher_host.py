"""What runs where the matchers run: inside a matcher process (service/matcher_pool.py) or a Ray
matcher host (service/ray_executor.py).

A worker holds several sessions' :class:`~randt.core.odometry.IncrementalMatcher` (:class:`_Sessions`)
and serves one request at a time (:func:`serve_requests`): ``(op, key, args)`` in, ``(ok, value)``
out, over a pipe or a socket. The ops are ``open``, ``register_payload`` (the scan's bytes as the
vehicle sent them, decoded here: the service process reads only the header), ``state``,
``snapshot`` and ``drop``. A keyframe's model rebuild runs on a thread beside the answer
(:class:`_Rebuilds`); each answer is billed with the CPU it cost (:class:`CpuLedger`).

An exception raised here goes back as the same class with the same attributes, the worker's
traceback attached as a note; one that cannot be pickled goes back as a
:class:`~randt.service.matcher_io.MatcherProcessError` naming it (:func:`portable_error`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import threading
import time
import traceback
from collections.abc import Iterator
from dataclasses import replace
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from randt.core.config import RegistrationSettings
from randt.core.odometry import IncrementalMatcher, MatcherSettings
from randt.core.tiles import SentVoxels, TileGrid
from randt.core.transforms import transform_points
from randt.service.matcher_io import (
    Key,
    MapFrame,
    MapWindows,
    MatcherProcessError,
    Registered,
    decoded_sweep,
    without_trajectory,
)
from randt.service.processes import ignore_group_signals, single_threaded_blas
from randt.wire.messages import WireLimits
from randt.wire.ros2 import Ros2Scan

__all__ = ["READY", "CpuLedger", "portable_error", "serve_process", "serve_requests", "warm_up"]

log = logging.getLogger(__name__)

#: The first message a worker sends, once warmed up (the service's channel waits for it).
READY = (True, "ready")


def warm_up() -> None:
    """Load (or compile) the numba kernels before the first sweep arrives: an incremental matcher
    fed three sweeps of a small synthetic room (registration, Algorithm 1, feature extraction and
    the map's candidate mask) and a fourth localized on a window of the room's map, and one
    pairwise registration with the default settings (moving-point selection and the SVD step,
    which a matcher configured so would use), so a vehicle's first scan does not pay for it. A
    cold numba cache makes this a compile (docs/architecture.md gives how long each takes)."""
    from randt.core.registration import register
    from randt.core.scenes import synthetic_room

    room = synthetic_room(np.random.default_rng(0), 5000)
    register(room + [0.2, 0.1, 0.0], room)
    matcher = IncrementalMatcher()
    grid = TileGrid()
    for i in range(3):
        result = matcher.register_scan(room - [0.1 * i, 0.0, 0.0])
        grid.candidate_mask(transform_points(result.T_world_sensor, result.deskewed_xyz))
    # localizing on the map: a window joined from pieces, a sweep matched on it, what it lacks
    window = matcher.join_map([matcher.prepare_map_piece(room)])
    matcher.register_scan(room - [0.3, 0.0, 0.0], on_map=window)
    window.maps[-1].contains(room)


def portable_error(exc: Exception) -> Exception:
    """``exc`` with the worker's traceback as a note, if it survives pickling; else a
    :class:`MatcherProcessError` naming it (the caller's ``recv`` must never fail to unpickle)."""
    exc.add_note(f"raised in matcher process pid {os.getpid()}:\n{''.join(traceback.format_exception(exc))}")
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:
        return MatcherProcessError(f"in matcher process pid {os.getpid()}: {type(exc).__name__}: {exc}")
    return exc


class CpuLedger:
    """Each session's CPU time where its matcher runs, billed to its sweeps
    (:attr:`Registered.cpu_s`): a request's own thread CPU time, plus what the session's model
    rebuilds cost since its last sweep (:meth:`carry`). Thread CPU time: the matchers' kernels and
    BLAS run single-threaded on the calling thread, and it does not count the time a busy machine
    gives to other processes."""

    def __init__(self) -> None:
        self._carried: dict[Key, float] = {}

    @contextlib.contextmanager
    def carry(self, key: Key) -> Iterator[None]:
        """Around work for ``key`` that is billed to its next sweep (a model rebuild)."""
        t0 = time.thread_time()
        try:
            yield
        finally:
            self._carried[key] = self._carried.get(key, 0.0) + time.thread_time() - t0

    def add(self, key: Key, cpu_s: float) -> None:
        """CPU time spent for ``key`` on another thread (a map window joined behind its sweeps),
        billed to its next answer."""
        if cpu_s:
            self._carried[key] = self._carried.get(key, 0.0) + cpu_s

    def bill(self, op: str, key: Key, value: Any, spent_s: float) -> Any:
        """Request ``op``'s value: a :class:`Registered` with the request's CPU (``spent_s``) and
        what was carried in ``cpu_s``; any other value as it is (``drop`` forgets the carry)."""
        if op == "drop":
            self._carried.pop(key, None)
        if not isinstance(value, Registered):
            return value
        return replace(value, cpu_s=spent_s + self._carried.pop(key, 0.0))


class _Rebuilds:
    """Keyframe model rebuilds (:meth:`IncrementalMatcher.update_model`) on threads of their own,
    at most one per session: started as soon as a sweep is matched, so the rebuild runs on another
    core beside the rest of the request (the map points), the reply and whatever the worker does
    next, instead of after them. The session's next request waits for it (:meth:`wait`), so every
    sweep still matches against the model of all keyframes before it, as offline: the poses do not
    depend on timing. The kernels release the GIL. The rebuild's CPU time is billed to the
    session's next sweep."""

    def __init__(self, ledger: CpuLedger) -> None:
        self._ledger = ledger
        self._lock = threading.Lock()  # (a Ray host serves several connections on threads)
        self._running: dict[Key, threading.Thread] = {}

    def start(self, key: Key, matcher: IncrementalMatcher) -> None:
        thread = threading.Thread(target=self._rebuild, args=(key, matcher), name="randt-rebuild")
        thread.daemon = True  # (a worker that quits waits for them: wait_all)
        with self._lock:
            self._running[key] = thread
        thread.start()

    def _rebuild(self, key: Key, matcher: IncrementalMatcher) -> None:
        try:
            with self._ledger.carry(key):
                matcher.update_model()
        except Exception:  # a bug, not bad input: the next request would meet it too
            log.exception("keyframe model update failed")

    def wait(self, key: Key) -> None:
        """Until ``key``'s rebuild, if one runs, is done."""
        with self._lock:
            thread = self._running.pop(key, None)
        if thread is not None:
            thread.join()

    def wait_all(self) -> None:
        with self._lock:
            threads, self._running = list(self._running.values()), {}
        for thread in threads:
            thread.join()


class _Sessions:
    """The matchers of one worker (a matcher process, a Ray matcher host): one per session key,
    with an empty grid of each session's map (its sizes and cap) to cut the answers to."""

    def __init__(self) -> None:
        self.matchers: dict[Key, IncrementalMatcher] = {}
        self.grids: dict[Key, TileGrid | None] = {}
        self.sent: dict[Key, SentVoxels] = {}
        self.windows: dict[Key, MapWindows] = {}
        self.ledger = CpuLedger()
        self.rebuilds = _Rebuilds(self.ledger)

    def open(
        self,
        key: Key,
        state: dict[str, np.ndarray] | None,
        grid_params: tuple[int, float, int] | None,
        settings: MatcherSettings | None,
        registration: RegistrationSettings | None,
    ) -> None:
        matcher = IncrementalMatcher(settings, registration)
        if state:
            matcher.load_state_dict(state)
        self.matchers[key] = matcher
        self.windows[key] = MapWindows()
        self.grids[key] = None if grid_params is None else TileGrid(*grid_params)
        if grid_params is not None:
            self.sent[key] = SentVoxels(*grid_params)

    def register_payload(
        self,
        key: Key,
        payload: bytes | Ros2Scan,
        limits: WireLimits | None,
        keyframe_voxel_m: float | None,
        frame: MapFrame | None = None,
        rebuild: bool = False,
    ) -> Registered:
        """One sweep, decoded here (:func:`decoded_sweep`). A keyframe's model rebuild is deferred:
        with ``rebuild`` it starts on a thread at once (:class:`_Rebuilds`), beside the rest of this
        request and the reply, else it is left for the caller (``self.matchers[key].model_pending``).
        With the session's map known, only the points it could keep go back, already in the frame
        they are folded in (float32, as the map stores them): with a ``frame``, those of voxels not
        sent before (:class:`SentVoxels`), else the candidates; the service process's insert handles
        those and transforms nothing."""
        xyz, offsets, intensity, prior, stamp_s = decoded_sweep(payload, limits, frame)
        matcher = self.matchers[key]
        result = matcher.register_scan(
            xyz,
            time_offset_s=offsets,
            prior=prior,
            stamp_s=stamp_s,
            defer_model=True,
            map_seed=None if frame is None else frame.seed_xyz,
            on_map=self.windows[key].on_map(matcher, None if frame is None else frame.window),
            relocalize=frame is not None and frame.relocalize,
        )
        self.ledger.add(key, self.windows[key].take_cpu_s())  # (a window joined behind)
        if rebuild and matcher.model_pending:  # (it and Registered.of only read the sweep's points)
            self.rebuilds.start(key, matcher)
        registered = Registered.of(
            result, self.grids.get(key), keyframe_voxel_m, frame, self.sent.get(key), self.windows[key]
        )
        return registered.with_intensity(intensity)

    def state(self, key: Key) -> dict[str, np.ndarray]:
        return self.matchers[key].state_dict()

    def snapshot(self, key: Key) -> dict[str, np.ndarray]:
        """The session's state for a snapshot: what crosses the pipe does not grow with its length."""
        return without_trajectory(self.matchers[key].state_dict())

    def drop(self, key: Key) -> bool:
        self.grids.pop(key, None)
        self.sent.pop(key, None)
        self.windows.pop(key, None)
        return self.matchers.pop(key, None) is not None

    def _catch_up(self, key: Key, behind: bool) -> None:
        """A session that is not behind matches against its whole model: a keyframe whose rebuild
        was left while it was behind is folded in before its next sweep. Only a session that is
        behind lets the model lag (else a vehicle's trajectory would depend on when its requests
        met other sessions', and differ from the offline one)."""
        matcher = self.matchers.get(key)
        if matcher is not None and not behind:
            matcher.update_model()

    def handle(self, op: str, key: Key, args: tuple[Any, ...]) -> Any:
        """One request of the protocol (``open``, ``register_payload``, ``state``, ``snapshot``,
        ``drop``): its value, a :class:`Registered` billed with the CPU it cost
        (:class:`CpuLedger`). The session's model rebuild started by its previous sweep is waited
        for first; a sweep whose session is not behind starts its keyframe's rebuild
        (:meth:`register_payload`)."""
        self.rebuilds.wait(key)
        t0 = time.thread_time()
        value = self._value(op, key, args)
        return self.ledger.bill(op, key, value, time.thread_time() - t0)

    def _value(self, op: str, key: Key, args: tuple[Any, ...]) -> Any:
        if op == "open":
            return self.open(key, *args)
        if op == "register_payload":
            payload, limits, behind, keyframe_voxel_m, frame = args
            self._catch_up(key, behind)
            return self.register_payload(key, payload, limits, keyframe_voxel_m, frame, not behind)
        if op == "state":
            return self.state(key)
        if op == "snapshot":
            return self.snapshot(key)
        if op == "drop":
            return self.drop(key)
        raise ValueError(f"unknown request {op!r}")


def serve_requests(conn: Connection, sessions: _Sessions) -> None:
    """The loop of a matcher process (or of a Ray matcher host's connection): one request at a
    time, ``(op, key, args)`` in, ``(ok, value)`` out, until ``quit`` or the connection closes.
    Keyframe model rebuilds run on threads beside it (:class:`_Rebuilds`)."""
    while True:
        try:
            op, key, args = conn.recv()
        except (EOFError, OSError):  # the service is gone (even a kill -9 closes the pipe)
            return
        if op == "quit":
            sessions.rebuilds.wait_all()
            conn.send((True, None))
            return
        try:
            value = sessions.handle(op, key, args)
        except Exception as exc:  # raised again in the session thread, as itself (module docstring)
            conn.send((False, portable_error(exc)))
        else:
            conn.send((True, value))


def serve_process(conn: Connection) -> None:
    """A matcher process (the target the pool spawns): warm up, say so (:data:`READY`), then
    :func:`serve_requests` until the service quits or is gone.

    SIGINT and SIGTERM are ignored (service/processes.py): the service stops its matcher
    processes itself after draining and saving the sessions (``quit``, or the pipe closing, which
    a service killed with SIGKILL closes too), so a stop of the whole process group cannot end
    them before the sessions are saved.
    """
    ignore_group_signals()
    single_threaded_blas()
    try:
        warm_up()
    except Exception:  # a failed warm-up only costs the first sweep its compile time
        log.exception("matcher process warm-up failed")
    try:
        conn.send(READY)
    except (BrokenPipeError, OSError):  # the service is gone already
        return
    serve_requests(conn, _Sessions())
