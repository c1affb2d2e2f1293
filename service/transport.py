"""Zenoh transport: with service/ros2.py, the only code of the service that talks to Zenoh.

A scan subscriber whose callback only hands the payload to ``SessionManager.submit`` (the
vehicle's intake queue: service/intake.py), one sender thread publishing everything outbound from
a bounded queue (answers before tile updates), a liveliness token ``randt/service/<instance>`` and
a tile queryable: one tile by its key, or every tile around a point
(``randt/map/<map>/tile/*?x=..;y=..;radius=..``, :func:`randt.wire.keys.parse_tiles_near`), answered on
a thread of its own (at most :data:`TILES_NEAR_AT_ONCE` at once). Keys come from
:mod:`randt.wire.keys`, the session's config from :mod:`randt.wire.zenoh_config`
(docs/architecture.md, "Packages"; docs/security.md).
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
import time
from collections.abc import Callable

import zenoh

from randt.core.errors import BadMessageError
from randt.service.settings import ServiceSettings
from randt.wire.keys import (
    ALL_SCANS,
    ALL_TILES,
    TilesNear,
    key_for,
    parse_tiles_near,
    service_token_key,
    tile_key,
    tile_of_key,
    vehicle_of_scan_key,
)
from randt.wire.messages import ErrorMessage, PoseMessage, WireMessage, encode
from randt.wire.zenoh_config import zenoh_config

__all__ = ["TILES_NEAR_AT_ONCE", "ZenohTransport"]

log = logging.getLogger(__name__)

#: Tiles-near queries answered at once (each on a thread of its own: a reply of many tiles is
#: encoded there, not on Zenoh's callback thread); one more is answered with an error.
TILES_NEAR_AT_ONCE = 4


class ZenohTransport:
    """Zenoh session, scan subscriber, outbound sender, liveliness token and tile queryable."""

    def __init__(
        self,
        settings: ServiceSettings,
        on_scan: Callable[[str, bytes, int], None],
        tile_provider: Callable[[str, str], bytes | None],
        *,
        tiles_near: Callable[[str, TilesNear], list[tuple[str, bytes]]] | None = None,
        max_outbound: int = 10_000,
    ) -> None:
        self.settings = settings
        self._on_scan = on_scan
        self._tile_provider = tile_provider
        self._tiles_near = tiles_near
        self._near_slots = threading.BoundedSemaphore(TILES_NEAR_AT_ONCE)
        # (rank, order, item): answers (rank 0) before tile updates (1), each in order, so a pose
        # never waits behind a flush's burst of tile updates; the stop mark (2) after everything
        # queued before it.
        self._out: queue.PriorityQueue[tuple[int, int, tuple[str, bytes, bool] | None]] = queue.PriorityQueue(
            max_outbound
        )
        self._order = itertools.count()
        self._session: zenoh.Session | None = None
        self._sender: threading.Thread | None = None
        self._handles: list[object] = []
        self.dropped_outbound = 0

    @property
    def is_open(self) -> bool:
        return self._session is not None

    def open(self) -> None:
        s = self.settings
        config = zenoh_config(s.zenoh_mode, s.listen, s.connect, config_file=s.zenoh_config)
        try:
            self._session = zenoh.open(config)
        except zenoh.ZError as exc:  # e.g. a certificate file that does not read: Zenoh's reason, one line
            reason = str(exc).split(" at /", 1)[0]  # without the Rust source location
            raise ValueError(f"Zenoh cannot open the service's session: {reason}") from exc
        self._sender = threading.Thread(target=self._send_loop, name="zenoh-sender", daemon=True)
        self._sender.start()
        sess = self._session
        self._handles = [
            sess.declare_subscriber(ALL_SCANS, self._scan_callback),
            sess.liveliness().declare_token(service_token_key(s.instance)),
            sess.declare_queryable(ALL_TILES, self._tile_query),
        ]
        log.info(
            "zenoh %s session open (listen %s, connect %s, config file %s)",
            s.zenoh_mode, s.listen, s.connect, s.zenoh_config,
        )  # fmt: skip

    def _scan_callback(self, sample: zenoh.Sample) -> None:
        try:
            self._on_scan(
                vehicle_of_scan_key(str(sample.key_expr)), sample.payload.to_bytes(), time.time_ns()
            )
        except Exception:  # never let an exception escape into Zenoh's thread
            log.exception("scan callback failed")

    def _tile_query(self, query: zenoh.Query) -> None:
        try:
            tile = tile_of_key(str(query.key_expr))
            parameters = str(query.parameters)
            if tile is not None and tile[1] == "*" and parameters and self._tiles_near is not None:
                return self._start_tiles_near(query, tile[0], parameters)
            payload = None if tile is None else self._tile_provider(*tile)
            if payload is not None:
                query.reply(query.key_expr, payload)
        except Exception:
            log.exception("tile query %s failed", query.key_expr)
        return None

    def _start_tiles_near(self, query: zenoh.Query, map_name: str, parameters: str) -> None:
        """A tiles-near query to a thread of its own, or refused when :data:`TILES_NEAR_AT_ONCE`
        are being answered."""
        try:
            near = parse_tiles_near(parameters)
        except BadMessageError as exc:
            query.reply_err(f"{exc.code}: {exc}".encode())
            return
        if not self._near_slots.acquire(blocking=False):
            query.reply_err(
                f"busy: {TILES_NEAR_AT_ONCE} tiles-near queries are being answered; ask again".encode()
            )
            return
        threading.Thread(
            target=self._answer_tiles_near, args=(query, map_name, near), name="randt-tiles-near", daemon=True
        ).start()

    def _answer_tiles_near(self, query: zenoh.Query, map_name: str, near: TilesNear) -> None:
        try:
            assert self._tiles_near is not None
            for tile_id, payload in self._tiles_near(map_name, near):
                query.reply(tile_key(map_name, tile_id), payload)
        except Exception:
            log.exception("tiles-near query %s?%s failed", query.key_expr, query.parameters)
        finally:
            query.drop()  # (the reply is complete: the asker's get ends here, not at its timeout)
            self._near_slots.release()

    def send(self, message: WireMessage) -> None:
        """Queue a message for publication (drops it, counted, if the outbound queue is full)."""
        answer = isinstance(message, PoseMessage | ErrorMessage)
        try:
            item = (key_for(message), encode(message), answer)
            self._out.put_nowait((0 if answer else 1, next(self._order), item))
        except queue.Full:
            self.dropped_outbound += 1

    def _send_loop(self) -> None:
        while True:
            _, _, item = self._out.get()
            if item is None:
                return
            key, payload, answer = item
            try:
                if self._session is not None:
                    # Every scan is promised exactly one answer: poses and errors wait out
                    # congestion (this thread, never a callback or a worker, is the one that
                    # waits). Tile updates may be dropped under congestion: a subscriber that
                    # misses one gets the tile by the queryable or with its next version.
                    self._session.put(
                        key,
                        payload,
                        congestion_control=zenoh.CongestionControl.BLOCK
                        if answer
                        else zenoh.CongestionControl.DROP,
                        priority=zenoh.Priority.INTERACTIVE_HIGH if answer else zenoh.Priority.DATA,
                    )
            except Exception:
                log.exception("publishing on %s failed", key)

    def close(self) -> None:
        """Publish what is queued, then close the Zenoh session."""
        if self._sender is not None:
            self._out.put((2, next(self._order), None))
            self._sender.join(10)
        for h in self._handles:
            undeclare = getattr(h, "undeclare", None)
            if undeclare is not None:
                try:
                    undeclare()
                except Exception:
                    log.debug("undeclare failed", exc_info=True)
        if self._session is not None:
            self._session.close()
            self._session = None
