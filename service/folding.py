"""A session's map points between its matches and the map: held for the map agreement check
(service/agreement.py), then folded into the map's tiles ``fold_scans`` sweeps at a time.

An insert pays per point and per tile touched (a tile is an immutable version, copied), and a
vehicle's consecutive sweeps touch the same tiles, so folding several sweeps together copies each
tile once instead of once a sweep (``docs/architecture.md``, "Map folding").
"""

from __future__ import annotations

import logging
import threading
from typing import Protocol

import numpy as np

from randt.core.tiles import TileGrid
from randt.service.agreement import AgreementGate, Held
from randt.service.live_maps import LiveMaps
from randt.service.matchers import Registered
from randt.service.metrics import ServiceMetrics
from randt.service.session_info import SessionInfo

__all__ = ["MapPoints", "SessionMap"]

log = logging.getLogger(__name__)


class SessionMap(Protocol):
    """The session's own map as it stands: its tiles and its name (``info.map_name``), read
    under the session's lock (the session changes them with its frame)."""

    grid: TileGrid
    info: SessionInfo


class MapPoints:
    """One session's map points waiting to be folded, and its agreement gate.

    ``session_lock`` is the session's own lock: the points are taken under it, never inserted
    under it, so a fold by the flusher does not hold up the session's matching. Folds are
    serialized, so points enter the map in arrival order."""

    def __init__(
        self,
        session: SessionMap,
        gate: AgreementGate,
        session_lock: threading.Lock,
        maps: LiveMaps,
        metrics: ServiceMetrics,
    ) -> None:
        self._session = session
        self.gate = gate
        self._session_lock = session_lock
        self._maps, self._metrics = maps, metrics
        self._waiting: list[Held] = []  # map, xyz, intensity
        self._fold_lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._waiting)

    def take(
        self,
        registered: Registered,
        correction: np.ndarray | None,
        fold_map: str,
    ) -> tuple[str | None, float | None]:
        """A matched sweep's map points (none for a fallback) wait to be folded into ``fold_map``,
        moved by the session's newest ``correction``; first through the agreement check when the
        matcher returned the sweep's thinned points, whose verdict folds or drops the points held
        since the last check, its own included (called under the session's lock).
        Returns ``(why the session is lost, or None; the check's share of points near the map, or
        None when none ran)``."""
        gate, info = self.gate, self._session.info
        vehicle, session_id, own_map = info.vehicle, info.session, info.map_name
        if registered.result.localized:  # (its pose is the map's: no session correction moves it)
            correction = None
        checked = gate.enabled and registered.keyframe_xyz is not None
        on_map = gate.enabled and not checked and registered.result.localized
        if gate.disagreeing and not checked and not on_map:
            gate.matched()
            return gate.lost_reason(own_map), None
        if registered.map_xyz.shape[0]:
            points = (fold_map, registered.map_points_under(correction), registered.map_intensity)
            self._waiting.extend(gate.hold(points))
        if on_map:  # (the match on the map was the check)
            self._waiting.extend(gate.localized())
            return (gate.lost_reason(own_map) if gate.disagreeing else None), None
        if not gate.enabled or not checked:
            if gate.enabled:
                gate.matched()
            return None, None
        assert registered.keyframe_xyz is not None
        T = registered.result.T_world_sensor
        T = T if correction is None else correction @ T
        was_lost = gate.disagreeing
        grid = self._session.grid if fold_map == own_map else self._maps.grid(fold_map)
        self._waiting.extend(gate.check(grid, T, registered.keyframe_xyz))
        last = gate.last
        assert last is not None
        if gate.disagreeing and not was_lost:
            self._metrics.map_disagreements.inc()
            log.warning(
                "session %s/%s: scan %d disagrees with map %s (%.0f%% of %d points near it): lost",
                vehicle, session_id, registered.result.index, fold_map, 100 * last.share, last.checked,
            )  # fmt: skip
        elif was_lost and not gate.disagreeing:
            log.info("session %s/%s agrees with map %s again", vehicle, session_id, fold_map)
        return (gate.lost_reason(own_map) if gate.disagreeing else None), last.share

    def fold(self, *, release: bool = False) -> None:
        """Insert the waiting points into their maps and mark the tiles that changed for the next
        save. ``release`` (the session ends or merges its map): the points the agreement check
        holds too, unless its last check disagreed. The session's own map is read with the
        points."""
        with self._fold_lock:
            with self._session_lock:
                batch, self._waiting = self._waiting + (self.gate.release() if release else []), []
                own_grid, own_map = self._session.grid, self._session.info.map_name
            # (a session without priors folds into the shared map once it joined it)
            for map_name in dict.fromkeys(name for name, _, _ in batch):
                part = [(x, i) for name, x, i in batch if name == map_name]
                xyz = np.concatenate([x for x, _ in part]) if len(part) > 1 else part[0][0]
                inten = None
                if any(i is not None for _, i in part):
                    inten = np.concatenate(
                        [np.zeros(len(x), np.float32) if i is None else i for x, i in part]
                    )
                self._maps.insert(map_name, xyz, inten, grid=own_grid if map_name == own_map else None)
