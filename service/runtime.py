"""The service instance: store, session manager and Zenoh transport, started and stopped together.

``Service.start()`` opens the store (restoring every map and session it holds), the session
manager and the Zenoh transport; ``Service.stop()`` stops intake, drains the session queues,
flushes tiles and session state to the store and closes Zenoh. The FastAPI app's lifespan
(``randt.service.app``) calls both, so ``randt serve`` stops cleanly on SIGTERM and SIGINT.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from randt.service.matchers import MatcherExecutor, single_threaded_blas
from randt.service.metrics import ServiceMetrics
from randt.service.ros2 import Ros2Bridge
from randt.service.sessions import SessionManager
from randt.service.settings import ServiceSettings
from randt.service.store import Store
from randt.service.transport import ZenohTransport
from randt.wire.keys import TilesNear
from randt.wire.messages import WireMessage, encode
from randt.wire.ros2 import Ros2Scan

__all__ = ["Service"]

log = logging.getLogger(__name__)


class Service:
    """One running instance (module docstring)."""

    def __init__(
        self,
        settings: ServiceSettings,
        *,
        with_zenoh: bool = True,
        executor: MatcherExecutor | None = None,
        outbox: Callable[[WireMessage], None] | None = None,
    ) -> None:
        """``executor``: where the sessions' matchers run, instead of the one the settings name
        (bench/main_process.py's stand-in that answers at once measures this process alone);
        ``outbox``: where the messages go without Zenoh (else a list, ``_sent``)."""
        self.settings = settings
        self._executor = executor
        self._outbox = outbox
        self.metrics = ServiceMetrics()
        self.started_at = time.time()
        self.store: Store | None = None
        self.sessions: SessionManager | None = None
        self.transport: ZenohTransport | None = None
        self.ros2: Ros2Bridge | None = None  # ROS 2 robots on rmw_zenoh (settings.ros2)
        self._with_zenoh = with_zenoh
        self._sent: list[WireMessage] = []  # outbound messages when running without Zenoh (tests)

    def start(self) -> None:
        s = self.settings
        single_threaded_blas()  # its threads and the matcher processes share the cores
        self.store = Store(s.data_dir)
        outbox: Callable[[WireMessage], None]
        if self._with_zenoh:
            self.transport = ZenohTransport(s, self._on_scan, self.tile_payload, tiles_near=self.tiles_near)
            outbox = self.transport.send
            if s.ros2.enabled:
                self.ros2 = Ros2Bridge(s.ros2, self._on_scan, self.metrics, map_near=self.map_near)
                outbox = self._answer_both
        else:
            outbox = self._outbox or self._sent.append
        self.sessions = SessionManager(s, self.store, outbox, self.metrics, self._executor)
        self.metrics.watch(self.map_stats, instance=s.instance)
        if self.transport is not None:
            self.transport.open()
        if self.ros2 is not None:
            self.ros2.open()
        log.info("service %s started, data in %s", s.instance, s.data_dir)

    def _on_scan(self, vehicle: str, payload: bytes | Ros2Scan, received_ns: int) -> None:
        if self.sessions is not None:
            self.sessions.submit(vehicle, payload, received_ns)

    def _answer_both(self, message: WireMessage) -> None:
        """Every answer on our keys; a ROS 2 session's also on its robot's topics."""
        if self.transport is not None:
            self.transport.send(message)
        if self.ros2 is not None:
            self.ros2.send(message)

    def tile_payload(self, map_name: str, tile_id: str) -> bytes | None:
        """The tile update message of one tile as last saved (the Zenoh queryable's answer)."""
        if self.sessions is None:
            return None
        saved = self.sessions.maps.durable(map_name)
        tile = None if saved is None else saved.by_id.get(tile_id)
        if tile is None:
            return None
        return encode(self.sessions.maps.tile_message(map_name, tile))

    def tiles_near(self, map_name: str, near: TilesNear) -> list[tuple[str, bytes]]:
        """The tile update messages of the tiles around a point as last saved (the Zenoh
        tiles-near query's answer), but those the asker holds at their saved version: ``(tile id,
        payload)`` by tile; none for a map that does not exist."""
        saved = None if self.sessions is None else self.sessions.maps.durable(map_name)
        if saved is None or self.sessions is None:
            return []
        out = []
        for tile_id in saved.grid.tiles_within_radius((near.x, near.y), near.radius_m):
            tile = saved.by_id.get(tile_id)
            if tile is not None and near.have.get(tile_id) != tile.version:
                out.append((tile_id, encode(self.sessions.maps.tile_message(map_name, tile))))
        return out

    def map_near(
        self, vehicle: str, session: str, x: float, y: float, radius_m: float
    ) -> tuple[np.ndarray, np.ndarray | None, bool] | None:
        """The saved points of the map a running session folds into, in the tiles within
        ``radius_m`` of ``(x, y)`` (a ROS 2 robot's map request): ``(xyz, intensity, whether it is
        the shared map)``; ``None`` when the session is not running."""
        sessions = self.sessions
        name = None if sessions is None else sessions.fold_map(vehicle, session)
        saved = None if sessions is None or name is None else sessions.maps.durable(name)
        if saved is None:
            return None
        wanted = set(saved.grid.tiles_within_radius((x, y), radius_m))
        tiles = [t for t in saved.tiles() if t.id in wanted]
        if not tiles:
            return np.zeros((0, 3), np.float32), None, name == self.settings.default_map
        xyz = np.concatenate([t.points for t in tiles])
        intensity = np.concatenate([t.intensity for t in tiles])
        return xyz, intensity, name == self.settings.default_map

    def map_stats(self) -> dict[str, tuple[int, int]]:
        """``{map name: (tiles, points)}`` of the live maps (read by ``/metrics`` at each scrape)."""
        maps = dict(self.sessions.maps) if self.sessions is not None else {}
        return {name: (len(grid), grid.n_points) for name, grid in maps.items()}

    def stop(self) -> None:
        """Stop intake, drain and save everything, close Zenoh (idempotent)."""
        if self.sessions is not None:
            self.sessions.stop()
        if self.ros2 is not None:  # (after the sessions: their last answers go out)
            self.ros2.close()
            self.ros2 = None
        if self.transport is not None:
            self.transport.close()
            self.transport = None
        if self.store is not None and self.store.is_open:
            self.store.close()
        log.info("service %s stopped", self.settings.instance)

    @property
    def with_zenoh(self) -> bool:
        """Whether this instance runs the Zenoh transport (False in tests that feed scans directly)."""
        return self._with_zenoh

    @property
    def ready(self) -> bool:
        return (
            self.sessions is not None
            and (not self._with_zenoh or (self.transport is not None and self.transport.is_open))
            and (
                not self._with_zenoh
                or not self.settings.ros2.enabled
                or (self.ros2 is not None and self.ros2.is_open)
            )
            and self.store is not None
            and self.store.writable()
        )
