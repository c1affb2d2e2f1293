"""A scan waiting for its session, and the overload policy that sheds waiting scans evenly.

``docs/architecture.md`` ("Overload") says why the policy drops what it drops.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from randt.wire.messages import ScanHeader
from randt.wire.ros2 import Ros2Scan

__all__ = ["YOUNG_SESSION_SCANS", "Job", "drop_index", "queue_label"]

#: Until a session has processed this many scans, overload drops its newest waiting scan rather
#: than shedding evenly: its first scans anchor it and teach its matcher the velocity.
YOUNG_SESSION_SCANS = 3


@dataclass
class Job:
    """A scan as the service process holds it: its header, and the payload's bytes, which only
    the session's matcher decodes (randt.wire.messages.decode_scan_header)."""

    scan: ScanHeader
    received_ns: int
    payload: bytes | Ros2Scan = b""


def queue_label(vehicle: str, session: str) -> str:
    """The ``session`` label of a session's queue-depth gauge: ``<vehicle>/<session>``."""
    return f"{vehicle}/{session}"


def drop_index(
    queue: deque[Job], *, n_processed: int, arriving_ns: int | None = None, taken_ns: int | None = None
) -> int:
    """Which waiting job the overload policy drops to make room for one arriving: while the
    session has processed fewer than :data:`YOUNG_SESSION_SCANS` scans, the newest waiting one;
    after that, the one whose removal leaves the shortest gap between the scans around it (the
    scan taken last for matching, ``taken_ns``, before the first; the arriving one,
    ``arriving_ns``, after the last), the oldest of equals. Repeated, this sheds evenly (every
    second scan, then every third...), so the gaps the matcher predicts over stay short."""
    n = len(queue)
    if n_processed < YOUNG_SESSION_SCANS:
        return n - 1
    stamps = [job.scan.stamp_ns for job in queue]
    left = [stamps[0] if taken_ns is None else taken_ns, *stamps[:-1]]
    right = [*stamps[1:], stamps[-1] if arriving_ns is None else arriving_ns]
    gaps = [r - lo for lo, r in zip(left, right, strict=True)]  # (at most queue_size of them)
    return gaps.index(min(gaps))
