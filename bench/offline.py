"""The service's session matcher run offline: what one matcher process does per sweep, timed.

:func:`service_matcher`, the matcher alone (``bench/matcher.py``, beside KISS-ICP): per sweep the
payload decoded (``randt.service.matchers.decoded_sweep``), ``IncrementalMatcher.register_scan`` with
the model update deferred, then ``update_model``: the matcher process's order (it publishes the
pose before it updates the model), with the settings every session gets
(``ServiceSettings.session_matcher``, ``ServiceSettings.registration``).

:func:`matcher_process`, the whole of a matcher process's work per sweep (``bench/service.py``'s
offline reference, ``bench/main_process.py``'s prepared answers): the same through the process's
own code (``randt.service.matchers._Sessions.register_payload`` with a ``MapFrame``: the map points
moved into the map frame and cut to the voxels not sent before; a keyframe's points where the
pose graph's rule asks for one, ``randt.service.graph_state.wants_keyframe``), then ``update_model``. Only
the pipe and the service around it are missing.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from randt.core.odometry import IncrementalMatcher
from randt.service.graph_state import wants_keyframe
from randt.service.matcher_host import _Sessions
from randt.service.matchers import MapFrame, Registered, decoded_sweep
from randt.service.settings import ServiceSettings


@dataclass
class Run:
    """One odometry over one set of sweeps: poses, per-sweep wall seconds (with a breakdown) and
    per-sweep CPU seconds of this process."""

    name: str
    poses: list[np.ndarray] = field(default_factory=list)
    times_s: list[float] = field(default_factory=list)
    cpu_s: list[float] = field(default_factory=list)
    decode_s: list[float] = field(default_factory=list)
    model_s: list[float] = field(default_factory=list)
    points: list[int] = field(default_factory=list)
    #: :func:`matcher_process`'s answers, when asked to keep them
    registered: list[Registered] = field(default_factory=list)
    #: :func:`matcher_process`: the matcher's state after the last sweep, without its trajectory
    state: dict[str, np.ndarray] = field(default_factory=dict)


def service_matcher(payloads: Iterable[bytes]) -> Run:
    """The service's session matcher over ``payloads`` (one session's sweeps, in order)."""
    s = ServiceSettings()
    matcher = IncrementalMatcher(s.session_matcher(), s.registration)
    run = Run("RANDT (service matcher)")
    for payload in payloads:
        c0, t0 = time.process_time(), time.perf_counter()
        xyz, offsets, _, prior, stamp_s = decoded_sweep(payload, None)
        t1 = time.perf_counter()
        result = matcher.register_scan(
            xyz, time_offset_s=offsets, prior=prior, stamp_s=stamp_s, defer_model=True
        )
        t2 = time.perf_counter()
        matcher.update_model()
        t3, c3 = time.perf_counter(), time.process_time()
        run.poses.append(result.T_world_sensor)
        run.times_s.append(t3 - t0)
        run.cpu_s.append(c3 - c0)
        run.decode_s.append(t1 - t0)
        run.model_s.append(t3 - t2)
        run.points.append(int(xyz.shape[0]))
    return run


def matcher_process(payloads: Iterable[bytes], *, graph: bool = True, keep: bool = False) -> Run:
    """What a matcher process does for one session's ``payloads``, in order (module docstring):
    with ``graph``, a keyframe's points where the pose graph would ask for them
    (:func:`wants_keyframe`); ``keep``: the answers in ``run.registered``."""
    s = ServiceSettings()
    sessions, key = _Sessions(), ("offline", "offline")
    sessions.open(key, None, (s.tile_size_m, s.map_voxel_m, 1), s.session_matcher(), s.registration)
    frame = MapFrame(("default", 0, 0), None)
    keyframe_voxel_m = min(s.fleet_map.keyframe_voxel_m, s.map_voxel_m)
    last_keyframe: np.ndarray | None = None
    run = Run("RANDT (matcher process)")
    for payload in payloads:
        wants = graph and wants_keyframe(run.poses, last_keyframe, s.graph_keyframe_m)
        c0, t0 = time.process_time(), time.perf_counter()
        registered = sessions.register_payload(key, payload, None, keyframe_voxel_m if wants else None, frame)
        t2 = time.perf_counter()
        sessions.matchers[key].update_model()
        t3, c3 = time.perf_counter(), time.process_time()
        if registered.keyframe_xyz is not None and len(registered.keyframe_xyz) >= 10:
            last_keyframe = registered.result.T_world_sensor
        run.poses.append(registered.result.T_world_sensor)
        run.times_s.append(t3 - t0)
        run.cpu_s.append(c3 - c0)
        run.model_s.append(t3 - t2)
        if keep:
            run.registered.append(registered)
    run.state = sessions.snapshot(key)
    return run
