"""The service's session matcher run offline: what one matcher process does per sweep, timed.

Used by ``bench/matcher.py`` (the matcher beside KISS-ICP) and ``bench/service.py`` (the same
sweeps offline, the reference the service's poses and CPU are compared with). Per sweep: the
payload decoded (``service.matchers.decoded_sweep``), ``IncrementalMatcher.register_scan`` with
the model update deferred, then ``update_model``: the matcher process's order (it publishes the
pose before it updates the model), with the settings every session gets
(``ServiceSettings.session_matcher``, ``ServiceSettings.registration``).
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from core.odometry import IncrementalMatcher
from service.matchers import decoded_sweep
from service.settings import ServiceSettings


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
