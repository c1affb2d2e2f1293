"""Which scans may open a session: the limits on sessions (all, and per vehicle), the measured
capacity (service/capacity.py), and the idle sessions that give up their slot.

A scan that would open a session is refused ``sessions_full`` at ``max_sessions`` running (and
opening) sessions, ``vehicle_sessions_full`` at ``max_sessions_per_vehicle`` of its vehicle,
unless a running session has been idle for ``slot_idle_s`` (``vehicle_slot_idle_s`` for the
per-vehicle limit): the idlest such session then gives up its slot and resumes from the store
with its next scan, so sessions that sent one scan and went quiet cannot squat the service.
"""

from __future__ import annotations

import os
import time
from collections.abc import Collection, Mapping

from randt.service.capacity import Capacity
from randt.service.settings import ServiceSettings
from randt.service.worker import SessionWorker
from randt.wire.codes import ErrorCode

__all__ = ["SESSIONS_PER_CORE", "Admission", "Refused"]

#: ``max_sessions=-1``: this many running sessions per core (ServiceSettings.max_sessions).
SESSIONS_PER_CORE = 4

#: A refusal to open a session: ``(code, reason, retry_after_s)``.
Refused = tuple[str, str, float]


class Admission:
    """The admission rules; called under the session manager's lock with its running sets."""

    def __init__(self, settings: ServiceSettings, capacity: Capacity | None) -> None:
        self.settings = settings
        self.capacity = capacity
        #: Running sessions at most (0: no limit); see ServiceSettings.max_sessions.
        self.max_sessions = settings.max_sessions
        if self.max_sessions < 0:
            self.max_sessions = SESSIONS_PER_CORE * (os.cpu_count() or 1)

    def refusal_on_header(self, running: list[tuple[str, str]], *, localizing: bool = False) -> str | None:
        """Why the node cannot carry one more session now (measured capacity), judged on a scan's
        header alone: a vehicle refused at 10 Hz must cost no body decoding. ``localizing``: the
        session is expected to localize on the map (service/localizing.py, ``expects_to_localize``)."""
        return None if self.capacity is None else self.capacity.refusal(running, localizing=localizing)

    def admit(
        self,
        key: tuple[str, str],
        workers: Mapping[tuple[str, str], SessionWorker],
        opening: Collection[tuple[str, str]],
        closing: Collection[tuple[str, str]],
        *,
        localizing: bool = False,
    ) -> SessionWorker | Refused | None:
        """May ``key`` open a session? ``None``: yes; a worker: yes, after that idle session gives
        up its slot; ``(code, reason, retry_after_s)``: refused. ``localizing``: as
        :meth:`refusal_on_header`."""
        s, vehicle = self.settings, key[0]
        evict: SessionWorker | None = None
        per_vehicle = s.max_sessions_per_vehicle
        if per_vehicle > 0:
            mine = [w for k, w in workers.items() if k[0] == vehicle]
            if len(mine) + sum(1 for k in opening if k[0] == vehicle) >= per_vehicle:
                evict = idlest(mine, s.vehicle_slot_idle_s, closing)
                if evict is None:
                    return (
                        ErrorCode.VEHICLE_SESSIONS_FULL,
                        f"vehicle {vehicle!r} runs its maximum of {per_vehicle} sessions "
                        "(RANDT_MAX_SESSIONS_PER_VEHICLE), none idle for "
                        f"{s.vehicle_slot_idle_s:g} s: close one or send again later",
                        s.vehicle_slot_idle_s,
                    )
        if evict is None and 0 < self.max_sessions <= len(workers) + len(opening):
            evict = idlest(list(workers.values()), s.slot_idle_s, closing)
            if evict is None:
                return (
                    ErrorCode.SESSIONS_FULL,
                    f"the service runs its maximum of {self.max_sessions} sessions (RANDT_MAX_SESSIONS), "
                    f"none idle for {s.slot_idle_s:g} s: send again later, close a session "
                    "or add capacity",
                    s.slot_idle_s,
                )
        if self.capacity is not None:  # before the session costs anything
            excluded = () if evict is None else (evict.key,)
            why = self.capacity.refusal([*workers, *opening], exclude=excluded, localizing=localizing)
            if why is not None:
                return (ErrorCode.SESSIONS_FULL, why, self.capacity.retry_after_s)
            self.capacity.opening(key, localizing=localizing)
        return evict


def idlest(
    candidates: list[SessionWorker], idle_s: float, closing: Collection[tuple[str, str]]
) -> SessionWorker | None:
    """The running session idle longest, if one has been idle for ``idle_s``: nothing queued, not
    matching, no scan received for that long."""
    limit = time.monotonic() - idle_s
    idle = [
        w
        for w in candidates
        if w.depth() == 0 and not w.lock.locked() and w.info.last_activity <= limit and w.key not in closing
    ]
    return min(idle, key=lambda w: w.info.last_activity, default=None)
