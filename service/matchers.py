"""What a session asks of its matcher, wherever the matcher runs, and the one that runs in the
session's own thread.

A session worker (service/worker.py) hands its matcher one scan payload at a time
(:meth:`SessionMatcher.register_payload`: the bytes as the vehicle sent them, decoded where the
matcher runs) and reads the answer (:class:`~randt.service.matcher_io.Registered`). Where the
matchers run is the executor (:class:`MatcherExecutor`, ``executor`` in the settings):

- the session thread itself (:class:`LocalMatcher`, ``matcher_processes=0``);
- local worker processes (:class:`~randt.service.matcher_pool.MatcherPool`, the default: one per
  core), served by service/matcher_host.py;
- Ray actors across a cluster (:class:`randt.service.ray_executor.RayMatcherPool`), served by the
  same code.

A snapshot's matcher state leaves the trajectory out (:meth:`SessionMatcher.snapshot_state`,
:func:`~randt.service.matcher_io.without_trajectory`): the store already holds every pose (its pose
log), so what crosses the pipe and is written does not grow with the session's length;
:func:`~randt.service.matcher_io.with_trajectory` puts it back when the session resumes.

The names the session layer uses from the modules below are importable from here as well.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Protocol

import numpy as np

from randt.core.config import RegistrationSettings
from randt.core.odometry import IncrementalMatcher, MatcherSettings
from randt.core.tiles import TileGrid
from randt.service.matcher_host import serve_requests, warm_up
from randt.service.matcher_io import (
    TRAJECTORY_LENGTH_KEY,
    Key,
    MapFrame,
    MapWindows,
    MatcherProcessDiedError,
    MatcherProcessError,
    Registered,
    decoded_sweep,
    prior_of,
    scan_payload,
    with_trajectory,
    without_trajectory,
)
from randt.service.matcher_pool import MatcherPool, RemoteMatcher
from randt.service.processes import (
    ignore_group_signals,
    single_threaded_blas,
    start_ignoring_group_signals,
)
from randt.wire.messages import WireLimits
from randt.wire.ros2 import Ros2Scan

__all__ = [
    "TRAJECTORY_LENGTH_KEY",
    "LocalMatcher",
    "MapFrame",
    "MatcherExecutor",
    "MatcherPool",
    "MatcherProcessDiedError",
    "MatcherProcessError",
    "Registered",
    "RemoteMatcher",
    "SessionMatcher",
    "decoded_sweep",
    "ignore_group_signals",
    "prior_of",
    "scan_payload",
    "serve_requests",
    "single_threaded_blas",
    "start_ignoring_group_signals",
    "warm_up",
    "with_trajectory",
    "without_trajectory",
]


class SessionMatcher(Protocol):
    """What a session worker asks of its matcher, wherever it runs: in the session thread
    (:class:`LocalMatcher`), in a worker process (:class:`~randt.service.matcher_pool.RemoteMatcher`)
    or in a Ray actor (:class:`randt.service.ray_executor.RayMatcher`)."""

    @property
    def poses(self) -> list[np.ndarray]: ...

    def register_payload(
        self,
        payload: bytes | Ros2Scan,
        *,
        limits: WireLimits | None = None,
        behind: bool = False,
        keyframe_voxel_m: float | None = None,
        frame: MapFrame | None = None,
    ) -> Registered:
        """The scan in ``payload`` registered (decoded where the matcher runs:
        :func:`~randt.service.matcher_io.decoded_sweep`), with the points the session's map may
        keep. ``behind``: several of the session's scans are waiting, so the keyframe model may
        lag by a sweep. Raises the decoder's :class:`~randt.core.errors.BadMessageError` for bodies
        that do not decode."""
        ...

    def update_model(self) -> float: ...

    def state_dict(self) -> dict[str, np.ndarray]: ...

    def snapshot_state(self) -> dict[str, np.ndarray]:
        """:meth:`state_dict` without the trajectory (:func:`without_trajectory`), for a snapshot."""
        ...

    def close(self) -> None: ...


class MatcherExecutor(Protocol):
    """Where the sessions' matchers run (``executor`` in the settings): local worker processes
    (:class:`~randt.service.matcher_pool.MatcherPool`) or Ray actors
    (:class:`randt.service.ray_executor.RayMatcherPool`). Order, back-pressure and drops stay the
    session layer's, the same for both."""

    @property
    def ready(self) -> bool: ...

    def wait_ready(self, timeout: float | None = None) -> bool: ...

    def open(
        self,
        key: Key,
        state: dict[str, np.ndarray] | None = None,
        grid: TileGrid | None = None,
        settings: MatcherSettings | None = None,
        registration: RegistrationSettings | None = None,
    ) -> SessionMatcher: ...

    def close(self) -> None: ...


class LocalMatcher(IncrementalMatcher):
    """An in-process matcher with :class:`SessionMatcher`'s interface (``matcher_processes=0``)."""

    #: CPU seconds of model rebuilds not billed to a sweep yet (:attr:`Registered.cpu_s`)
    _carried_cpu_s: float = 0.0
    #: the map window it holds (localizing on the map)
    _windows: MapWindows | None = None

    def update_model(self) -> float:
        """:meth:`IncrementalMatcher.update_model`, its CPU time billed to the next sweep."""
        t0 = time.thread_time()
        try:
            return super().update_model()
        finally:
            self._carried_cpu_s += time.thread_time() - t0

    def register_payload(
        self,
        payload: bytes | Ros2Scan,
        *,
        limits: WireLimits | None = None,
        behind: bool = False,
        keyframe_voxel_m: float | None = None,
        frame: MapFrame | None = None,
    ) -> Registered:
        """The payload decoded here (:func:`decoded_sweep`), :meth:`register_scan` with the model
        rebuild deferred (the caller runs :meth:`update_model` after publishing, unless ``behind``),
        and every point of the sweep in the map frame (:class:`Registered`; with
        ``keyframe_voxel_m``, the keyframe's points too)."""
        del behind  # (the caller's to act on: it skips update_model then)
        t0 = time.thread_time()
        xyz, offsets, intensity, prior, stamp_s = decoded_sweep(payload, limits, frame)
        self._windows = self._windows or MapWindows()
        result = self.register_scan(
            xyz,
            time_offset_s=offsets,
            prior=prior,
            stamp_s=stamp_s,
            defer_model=True,
            map_seed=None if frame is None else frame.seed_xyz,
            on_map=self._windows.on_map(self, None if frame is None else frame.window),
            relocalize=frame is not None and frame.relocalize,
        )
        self._carried_cpu_s += self._windows.take_cpu_s()  # (a window joined behind)
        registered = Registered.of(result, None, keyframe_voxel_m, frame, windows=self._windows)
        registered = registered.with_intensity(intensity)
        cpu_s, self._carried_cpu_s = time.thread_time() - t0 + self._carried_cpu_s, 0.0
        return replace(registered, cpu_s=cpu_s)

    def snapshot_state(self) -> dict[str, np.ndarray]:
        """:meth:`state_dict` without the trajectory (:func:`without_trajectory`)."""
        return without_trajectory(self.state_dict())

    def close(self) -> None:
        """Nothing to release."""
