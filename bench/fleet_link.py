"""A benchmark's vehicles over Zenoh: one session per vehicle publishing spooled sweeps at 10 Hz
(staggered over one period, as unsynchronised sensors are), and a listener that records every pose
and error the service answers (bench/service.py and bench/main_process.py)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Each vehicle's sweep rate.
RATE_HZ = 10.0

Key = tuple[str, int]  # (vehicle, seq)


@dataclass
class Answers:
    """What the vehicles sent (publication times) and what the service answered, filled from Zenoh's
    callback threads under one lock."""

    map_name: str = "default"
    sent: dict[Key, float] = field(default_factory=dict)
    got: dict[Key, float] = field(default_factory=dict)
    #: the poses in ``map_name`` (others are only counted: a session that lost its anchor)
    pose_of: dict[Key, np.ndarray] = field(default_factory=dict)
    not_in_map: int = 0
    #: the poses in another map's frame (a session without priors answers in its own)
    pose_own: dict[Key, np.ndarray] = field(default_factory=dict)
    #: each pose's status (``first``, ``ok``, ``fallback``)
    status_of: dict[Key, str] = field(default_factory=dict)
    statuses: dict[str, int] = field(default_factory=dict)
    #: poses matched on the map around the vehicle (``mode: localizing``)
    localized: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    #: the first error other than ``dropped``, as "code: reason"
    example: str = ""
    #: per vehicle, the ``retry_after_s`` of its refusals (``sessions_full``: when to send again)
    retry_after: dict[str, float] = field(default_factory=dict)
    last_answer: float = 0.0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_pose(self, sample: Any) -> None:
        from randt.wire.messages import decode_pose

        t = time.monotonic()
        m = decode_pose(sample.payload.to_bytes())
        with self.lock:
            self.got[(m.vehicle, m.seq)] = self.last_answer = t
            self.status_of[(m.vehicle, m.seq)] = m.status
            self.statuses[m.status] = self.statuses.get(m.status, 0) + 1
            self.localized += getattr(m, "mode", None) == "localizing"
            if m.map == self.map_name:
                self.pose_of[(m.vehicle, m.seq)] = np.reshape(m.pose, (4, 4))
            else:
                self.not_in_map += 1
                self.pose_own[(m.vehicle, m.seq)] = np.reshape(m.pose, (4, 4))

    def on_error(self, sample: Any) -> None:
        from randt.wire.messages import decode_error

        m = decode_error(sample.payload.to_bytes())
        with self.lock:
            self.errors[m.code] = self.errors.get(m.code, 0) + 1
            if m.retry_after_s is not None:
                self.retry_after[m.vehicle] = m.retry_after_s
            if m.code != "dropped":
                self.example = self.example or f"{m.code}: {m.reason}"
            self.last_answer = time.monotonic()

    def wait_all_answered(self, timeout_s: float) -> None:
        """Until every scan sent has a pose or an error, or ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                if len(self.got) + sum(self.errors.values()) >= len(self.sent):
                    return
            time.sleep(0.05)

    def wall_s(self, t0: float) -> float:
        """Seconds from ``t0`` (the first publication) to the last answer."""
        with self.lock:
            return max(self.last_answer, t0 + 1e-3) - t0

    def latencies_ms(self) -> np.ndarray:
        """Publish-to-pose latency of every posed scan."""
        return np.array([self.got[k] - self.sent[k] for k in self.got if k in self.sent]) * 1e3


@contextlib.contextmanager
def fleet_link(endpoint: str, sessions: list[str], answers: Answers) -> Iterator[dict[str, Any]]:
    """A listener recording into ``answers`` and one Zenoh session per name in ``sessions`` (the
    publishers' sessions), all peers of ``endpoint``; closed at exit."""
    import zenoh

    from randt.wire.keys import ALL_ERRORS, ALL_POSES
    from randt.wire.zenoh_config import zenoh_config

    listener = zenoh.open(zenoh_config("peer", connect=(endpoint,)))
    subs = [
        listener.declare_subscriber(ALL_POSES, answers.on_pose),
        listener.declare_subscriber(ALL_ERRORS, answers.on_error),
    ]
    opened = {name: zenoh.open(zenoh_config("peer", connect=(endpoint,))) for name in sessions}
    try:
        time.sleep(1.0)  # let the peers connect
        yield opened
    finally:
        for sub in subs:
            sub.undeclare()
        for session in opened.values():
            session.close()
        listener.close()


def drive_fleet(
    vehicles: Mapping[str, tuple[Any, Callable[[int], bytes]]],
    n_scans: int,
    answers: Answers,
    rate_hz: float = RATE_HZ,
) -> float:
    """Publishes ``n_scans`` sweeps of every vehicle at ``rate_hz``, staggered over one period:
    ``vehicles`` maps a vehicle id to (its Zenoh session, the payload of its k-th sweep). As the
    vehicle library publishes (clients/publisher.py): block under congestion rather than drop, so
    every scan reaches the service. Returns when all are sent, with the first publication's time."""
    import zenoh

    from randt.wire.keys import scan_key

    def drive(vehicle: str, session: Any, payload_of: Callable[[int], bytes], start: float) -> None:
        pub = session.declare_publisher(
            scan_key(vehicle),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        for k in range(n_scans):
            payload = payload_of(k)
            delay = start + k / rate_hz - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            with answers.lock:
                answers.sent[(vehicle, k)] = time.monotonic()
            pub.put(payload)

    t0 = time.monotonic() + 0.5
    threads = [
        threading.Thread(target=drive, args=(v, session, payload_of, t0 + i / (rate_hz * len(vehicles))))
        for i, (v, (session, payload_of)) in enumerate(vehicles.items())
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return t0
