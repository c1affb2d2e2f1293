"""The vehicle publisher: what a vehicle computer imports to stream its LiDAR scans to the service.

::

    from randt.clients.publisher import VehiclePublisher

    with VehiclePublisher("car-07", connect=["tcp/10.0.0.5:7447"], on_pose=print) as pub:
        for xyz, stamp_ns in lidar:                  # (N,3) or (N,4) arrays, sensor frame
            pub.publish(xyz, stamp_ns)               # never blocks: queued, sent by a thread
        pub.flush(timeout=30)                        # optional: wait for the last answers

One Zenoh session per publisher (:class:`PublisherSettings`, prefix ``RANDT_VEHICLE_``). Each sweep
is validated with the wire format's own checks, reduced on the vehicle (:func:`encode_sweep`: the
first point of each voxel, sent as a compact v2 scan; ``raw`` sends every point as a v1 scan) and
queued; a full queue drops its oldest scan. A sender thread publishes the queue only while a
service listens, and a dispatcher thread matches the answers to the scans and calls ``on_pose`` /
``on_error`` (never on a Zenoh thread). Every published scan ends in exactly one of
``acknowledged`` (pose), ``rejected`` (error), ``dropped`` (local queue overflow) or ``lost`` (no
answer in time); until then it is ``queued`` or ``in_flight``. What it guarantees and what goes on
the link: docs/clients.md, "Integrating a vehicle".
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np
import zenoh
from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from randt.core.errors import BadMessageError
from randt.wire.codes import ErrorCode
from randt.wire.keys import error_key, pose_key, scan_key, tiles_near_selector
from randt.wire.messages import (
    ErrorMessage,
    GeoPrior,
    PoseMessage,
    ScanMessage,
    TileUpdateMessage,
    WireLimits,
    decode_error,
    decode_pose,
    decode_tile_update,
    encode,
    encode_scan_v2,
    scan_from_arrays,
)
from randt.wire.zenoh_config import check_endpoints, load_config_file, zenoh_config

__all__ = [
    "PublisherSettings",
    "PublisherStats",
    "VehiclePublisher",
    "default_session_id",
    "encode_sweep",
    "first_per_voxel",
    "map_tiles_near",
]

log = logging.getLogger(__name__)

#: What the service's embedded default listens on (``randt serve`` and ``randt demo``).
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


class PublisherSettings(BaseSettings):
    """How a publisher reaches the service; every field is also ``RANDT_VEHICLE_<NAME>``.

    Lists take JSON in the environment: ``RANDT_VEHICLE_CONNECT='["tcp/10.0.0.5:7447"]'``.
    """

    model_config = SettingsConfigDict(env_prefix="RANDT_VEHICLE_", extra="forbid", frozen=True)

    mode: Literal["client", "peer"] = Field(default="client", description="Zenoh mode of the vehicle")
    connect: tuple[str, ...] = Field(default=(DEFAULT_ENDPOINT,), description="routers or peers")
    listen: tuple[str, ...] = Field(default=(), description="endpoints to listen on (peer mode)")
    zenoh_config: Path | None = Field(
        default=None,
        description="native Zenoh JSON5 config file (TLS certificate, user/password: docs/security.md); "
        "mode, connect and listen still come from these settings",
    )
    queue_size: int = Field(default=8, ge=1, description="scans waiting to be sent; oldest dropped")
    answer_timeout_s: float = Field(default=120.0, gt=0, description="a sent scan unanswered is lost")
    retry_s: float = Field(default=1.0, gt=0, description="first wait before re-opening the session")
    # what goes on the link (docs/clients.md, "What goes on the link")
    raw: bool = Field(
        default=False,
        description="send every point as float32 in a v1 scan (for a service older than v2, or to "
        "compare); the reduction settings below are then unused",
    )
    voxel_m: float = Field(
        default=0.2,
        ge=0.0,
        le=100.0,
        description="keep the first point of each voxel of this edge (metres), in the sweep's order; the "
        "service's default map voxel, RANDT_MAP_VOXEL_M; 0 keeps every point",
    )
    xyz_quantum_m: float = Field(default=0.01, gt=0.0, le=1.0, description="coordinate step (metres)")
    time_quantum_s: float = Field(default=1e-5, gt=0.0, le=0.01, description="time-offset step (seconds)")
    codec: Literal["zstd", "none"] = Field(default="zstd", description="compression of the scan's bodies")
    zstd_level: int = Field(default=3, ge=1, le=22, description="zstd level (docs/clients.md)")

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        return check_endpoints(value)

    @field_validator("zenoh_config")
    @classmethod
    def _zenoh_config_file(cls, value: Path | None) -> Path | None:
        if value is not None:
            load_config_file(value)
        return value


@dataclass
class PublisherStats:
    """Counters of one publisher (module docstring: every scan ends in exactly one final state).

    Attributes
    ----------
    published:
        Scans accepted by :meth:`VehiclePublisher.publish`.
    sent:
        Scans handed to Zenoh.
    acknowledged, rejected, dropped, lost:
        The final states: a pose came back; an error came back (``rejected_codes`` counts them by
        code, the service's overload drop is ``dropped``); dropped from the full local queue; sent
        but not answered within ``answer_timeout_s`` (or still pending at :meth:`close`).
    late:
        Answers that arrived after their scan was counted as lost (not counted twice).
    queued, in_flight:
        Scans waiting to be sent, and sent but not answered yet.
    outages:
        Times the service stopped being reachable (no subscriber matched the scan key).
    """

    published: int = 0
    sent: int = 0
    acknowledged: int = 0
    rejected: int = 0
    dropped: int = 0
    lost: int = 0
    late: int = 0
    queued: int = 0
    in_flight: int = 0
    outages: int = 0
    rejected_codes: dict[str, int] = field(default_factory=dict)

    @property
    def settled(self) -> int:
        """Scans in a final state: acknowledged + rejected + dropped + lost."""
        return self.acknowledged + self.rejected + self.dropped + self.lost


def first_per_voxel(points_xyz: np.ndarray, voxel_m: float) -> np.ndarray:
    """Indices of the first point of each voxel, ascending (so the sweep's own order is kept).

    One sort of int64 values that hold each point's cell (as few bits per axis as the sweep's
    extent needs) above its index: the smallest value of each cell is its first point (cheaper than
    ``np.unique(..., return_index=True)``).

    Parameters
    ----------
    points_xyz : (N, 3) finite positions, metres.
    voxel_m : voxel edge, metres (> 0); voxels are ``floor(p / voxel_m)`` cells of the sensor frame.

    Returns
    -------
    (M,) int64 indices into ``points_xyz``, ``M`` the number of occupied voxels.
    """
    n = len(points_xyz)
    # cells in float32 (exact integers below 2**24 cells: 3355 km at 0.2 m), axis-major for speed
    cells = np.floor(np.ascontiguousarray(np.asarray(points_xyz).T, dtype=np.float32) / np.float32(voxel_m))
    lo = cells.min(axis=1, keepdims=True)
    spans = (cells.max(axis=1) - lo[:, 0]).astype(np.int64)
    bits = [int(s).bit_length() for s in spans]
    index_bits = max(1, (n - 1).bit_length())
    if max(abs(float(lo.min())), float(cells.max())) < 2**24 and sum(bits) + index_bits <= 62:
        c = (cells - lo).astype(np.int64)
        keys = (c[0] << (bits[1] + bits[2] + index_bits)) | (c[1] << (bits[2] + index_bits))
        keys |= (c[2] << index_bits) | np.arange(n, dtype=np.int64)
        keys.sort()
        cell = keys >> index_bits
        starts = np.flatnonzero(np.concatenate(([True], cell[1:] != cell[:-1])))
        first = keys[starts] & ((1 << index_bits) - 1)
    else:  # a sweep spanning more than the packed key holds: rows compared as they are
        wide = np.floor(np.asarray(points_xyz, dtype=np.float64) / voxel_m)
        _, first = np.unique(wide, axis=0, return_index=True)
    first.sort()
    return first


def _check_all(
    pts: np.ndarray,
    intensity: np.ndarray | None,
    time_offset_s: np.ndarray | None,
    limits: WireLimits,
) -> bool:
    """Whether the whole sweep would pass the wire checks (before reduction drops any point)."""
    n = pts.shape[0]
    if n == 0 or not np.isfinite(pts).all():
        return False
    if intensity is not None and (intensity.shape != (n,) or not np.isfinite(intensity).all()):
        return False
    if time_offset_s is not None:
        if time_offset_s.shape != (n,):
            return False
        t = time_offset_s.astype(np.float32)  # what v1 would send
        if not ((t >= 0.0) & (t <= limits.max_time_offset_s)).all():
            return False
    return True


def encode_sweep(
    vehicle: str,
    session: str,
    seq: int,
    stamp_ns: int,
    points: np.ndarray,
    *,
    intensity: np.ndarray | None = None,
    time_offset_s: np.ndarray | None = None,
    prior_pose: np.ndarray | None = None,
    prior_covariance: np.ndarray | None = None,
    geo_prior: GeoPrior | None = None,
    localize_only: bool = False,
    settings: PublisherSettings | None = None,
) -> bytes:
    """The payload :meth:`VehiclePublisher.publish` sends for one sweep.

    By default (``settings.raw`` false) the sweep is reduced to the first point of each
    ``settings.voxel_m`` voxel, in its own order, each kept point with its own time offset and
    intensity, and sent as a compact v2 scan (:func:`randt.wire.messages.encode_scan_v2`). With
    ``settings.raw`` it is a v1 scan of every point (float32), as before v2.

    Parameters
    ----------
    vehicle, session, seq, stamp_ns:
        The scan's addressing (``stamp_ns``: the sweep's first point, ns since the Unix epoch).
    points:
        (N, 3) x, y, z or (N, 4) x, y, z, intensity, metres, sensor frame.
    intensity, time_offset_s, prior_pose, prior_covariance, geo_prior:
        As :meth:`VehiclePublisher.publish`.
    localize_only:
        As :class:`VehiclePublisher`.
    settings:
        The link settings; ``None``: ``PublisherSettings()`` (the defaults, or ``RANDT_VEHICLE_*``).

    Returns
    -------
    bytes
        The msgpack payload for ``randt/fleet/<vehicle>/scan``.

    Raises
    ------
    BadMessageError
        The sweep would be rejected by the service (shape, NaN, offsets out of range, ids...), with
        the code it would answer; checked on every point, before the reduction.
    """
    settings = PublisherSettings() if settings is None else settings
    pts = np.asarray(points)
    if pts.ndim == 2 and pts.shape[1] == 4 and intensity is None:
        pts, intensity = pts[:, :3], pts[:, 3]
    elif pts.ndim != 2 or pts.shape[1] != 3:
        raise BadMessageError(
            f"points: expected shape (N, 3) or (N, 4), got {pts.shape}", code=ErrorCode.INVALID_POINTS
        )
    inten = None if intensity is None else np.asarray(intensity)
    offsets = None if time_offset_s is None else np.asarray(time_offset_s)
    limits = WireLimits()

    def scan(index: np.ndarray | None) -> ScanMessage:
        """The validated scan of the points at ``index`` (all of them for ``None``)."""
        sel = slice(None) if index is None else index
        return scan_from_arrays(
            vehicle,
            session,
            seq,
            stamp_ns,
            pts[sel],
            intensity=None if inten is None else inten[sel],
            time_offset_s=None if offsets is None else offsets[sel],
            prior_pose=prior_pose,
            prior_covariance=prior_covariance,
            geo_prior=geo_prior,
            localize_only=localize_only,
            limits=limits,
        )

    if settings.raw:
        return encode(scan(None))
    if not _check_all(pts, inten, offsets, limits):
        scan(None)  # raises the service's error for the whole sweep (index of the first bad point)
    keep = first_per_voxel(pts, settings.voxel_m) if settings.voxel_m > 0 else None
    return encode_scan_v2(
        scan(keep),
        voxel_m=settings.voxel_m,
        xyz_quantum_m=settings.xyz_quantum_m,
        time_quantum_s=settings.time_quantum_s,
        codec=settings.codec,
        level=settings.zstd_level,
    )


def default_session_id(now: datetime | None = None) -> str:
    """A session id from the UTC time, e.g. ``20260501-142233`` (a valid wire id)."""
    return (now or datetime.now(UTC)).strftime("%Y%m%d-%H%M%S")


def _settings_with(settings: PublisherSettings | None, **overrides: Any) -> PublisherSettings:
    """The arguments given (not None) first, then ``settings`` or RANDT_VEHICLE_*, then the defaults."""
    given = {k: v for k, v in overrides.items() if v is not None}
    if settings is None:
        return PublisherSettings(**given)
    return PublisherSettings.model_validate({**settings.model_dump(), **given})


@dataclass
class _Outgoing:
    seq: int
    payload: bytes


class VehiclePublisher:
    """Publish one vehicle's scans for one session and receive their poses (module docstring).

    Parameters
    ----------
    vehicle:
        The vehicle id (:mod:`randt.wire.ids`).
    session:
        The drive's session id; default :func:`default_session_id`.
    mode, connect, listen, queue_size, answer_timeout_s:
        Override :class:`PublisherSettings` (itself read from ``RANDT_VEHICLE_*``).
    settings:
        A complete settings object instead of the environment.
    on_pose, on_error:
        Called with each :class:`~randt.wire.messages.PoseMessage` /
        :class:`~randt.wire.messages.ErrorMessage` of this
        session, from the publisher's dispatcher thread (exceptions are logged, not raised).
    first_seq:
        Sequence number of the first scan (the service requires strictly increasing ``seq`` per
        session; resume a session with the next number).
    localize_only:
        The session only localizes on the shared map and never adds to it (docs/clients.md, "A
        session that only localizes"): its scans carry ``localize_only`` and need a prior pose
        until the vehicle is on the map; where the map holds too little the service answers
        ``not_on_map``.
    """

    def __init__(
        self,
        vehicle: str,
        session: str | None = None,
        *,
        mode: Literal["client", "peer"] | None = None,
        connect: list[str] | tuple[str, ...] | None = None,
        listen: list[str] | tuple[str, ...] | None = None,
        queue_size: int | None = None,
        answer_timeout_s: float | None = None,
        settings: PublisherSettings | None = None,
        on_pose: Callable[[PoseMessage], Any] | None = None,
        on_error: Callable[[ErrorMessage], Any] | None = None,
        first_seq: int = 0,
        localize_only: bool = False,
    ) -> None:
        self.localize_only = localize_only
        self.settings = _settings_with(
            settings,
            mode=mode,
            connect=tuple(connect) if connect is not None else None,
            listen=tuple(listen) if listen is not None else None,
            queue_size=queue_size,
            answer_timeout_s=answer_timeout_s,
        )
        self.vehicle = vehicle
        self.session = session or default_session_id()
        # fail early on ids the service would reject (raises BadMessageError with code invalid_id)
        scan_from_arrays(vehicle, self.session, 0, 0, np.zeros((1, 3), np.float32))
        self.on_pose, self.on_error = on_pose, on_error
        self.scan_key = scan_key(vehicle)
        self._next_seq = first_seq
        self._cond = threading.Condition()
        self._queue: deque[_Outgoing] = deque()
        self._in_flight: dict[int, float] = {}  # seq -> monotonic send time
        self._in_callback = 0  # answers whose callback is running (flush waits for them too)
        self._answers: deque[PoseMessage | ErrorMessage] = deque()
        self._stats = PublisherStats()
        self._closing = False
        self._stopped = False
        self._zsession: zenoh.Session | None = None
        self._publisher: zenoh.Publisher | None = None
        self._subs: list[Any] = []
        self._was_matching = False
        self._sender = threading.Thread(target=self._send_loop, name=f"pub-{vehicle}-send", daemon=True)
        self._dispatcher = threading.Thread(
            target=self._dispatch_loop, name=f"pub-{vehicle}-recv", daemon=True
        )
        self._try_open()
        self._sender.start()
        self._dispatcher.start()

    # ------------------------------------------------------------------ public API
    def publish(
        self,
        points: np.ndarray,
        stamp_ns: int | None = None,
        *,
        intensity: np.ndarray | None = None,
        time_offset_s: np.ndarray | None = None,
        prior_pose: np.ndarray | None = None,
        prior_covariance: np.ndarray | None = None,
        geo_prior: GeoPrior | None = None,
        seq: int | None = None,
    ) -> int:
        """Reduce and encode one sweep (:func:`encode_sweep`), queue it for sending and return its
        ``seq``; never waits for the network.

        Parameters
        ----------
        points:
            (N, 3) x, y, z or (N, 4) x, y, z, intensity, metres, sensor frame (any float dtype;
            sent as float32). Drop "no return" points first: NaN or Inf are rejected.
        stamp_ns:
            Time of the sweep's first point, ns since the Unix epoch (default: now).
        intensity:
            (N,) intensities, instead of a fourth column.
        time_offset_s:
            (N,) seconds after ``stamp_ns`` at which each point was measured (lets the service
            deskew); within [0, 1].
        prior_pose, prior_covariance:
            (4, 4) ``T_map_sensor`` from GNSS/INS and its (6, 6) covariance (tx ty tz rx ry rz),
            both or neither, at the moment the answer's pose refers to (``stamp_ns``, or the
            sweep's middle with ``time_offset_s``). A session whose first scan has a prior joins
            the shared map.
        geo_prior:
            The prior in WGS84 instead (:func:`randt.wire.messages.geo_prior`: latitude, longitude,
            ellipsoidal altitude, orientation and covariance in East-North-Up), as a GNSS/INS
            receiver gives it; the service places it through its map's geodetic origin, which the
            first such prior sets (docs/mapping.md, "Georeferenced maps").
        seq:
            A used number: a scan the service refused with ``retry_after_s``, sent again.

        Returns
        -------
        int
            The scan's ``seq``. A scan that raises still uses up its number, so ``seq`` stays equal
            to the number of ``publish`` calls before it.

        Raises
        ------
        BadMessageError
            The arrays would be rejected by the service (shape, NaN, too many points...).
        RuntimeError
            The publisher is closed.
        """
        with self._cond:
            if self._closing:
                raise RuntimeError("the publisher is closed")
            if seq is not None and not 0 <= seq < self._next_seq:
                raise ValueError(f"seq {seq} was never used: only a refused scan is sent again")
            seq = self._next_seq if seq is None else seq
            self._next_seq = max(self._next_seq, seq + 1)
        payload = encode_sweep(
            self.vehicle,
            self.session,
            seq,
            time.time_ns() if stamp_ns is None else int(stamp_ns),
            points,
            intensity=intensity,
            time_offset_s=time_offset_s,
            prior_pose=prior_pose,
            prior_covariance=prior_covariance,
            geo_prior=geo_prior,
            localize_only=self.localize_only,
            settings=self.settings,
        )
        with self._cond:
            self._stats.published += 1
            if len(self._queue) >= self.settings.queue_size:
                old = self._queue.popleft()
                self._stats.dropped += 1
                log.debug("%s: send queue full, dropped scan %d", self.vehicle, old.seq)
            self._queue.append(_Outgoing(seq, payload))
            self._cond.notify_all()
        return seq

    def stats(self) -> PublisherStats:
        """A snapshot of the counters."""
        with self._cond:
            s = self._stats
            return PublisherStats(
                published=s.published,
                sent=s.sent,
                acknowledged=s.acknowledged,
                rejected=s.rejected,
                dropped=s.dropped,
                lost=s.lost,
                late=s.late,
                queued=len(self._queue),
                in_flight=len(self._in_flight),
                outages=s.outages,
                rejected_codes=dict(s.rejected_codes),
            )

    @property
    def connected(self) -> bool:
        """Whether a service is subscribed to this vehicle's scans right now."""
        pub = self._publisher
        try:
            # zenoh's stub says bool; the property returns a MatchingStatus (eclipse-zenoh 1.10)
            return pub is not None and bool(pub.matching_status.matching)  # type: ignore[attr-defined]
        except Exception:  # the session is closing
            return False

    def wait_connected(self, timeout: float | None = None) -> bool:
        """Wait until a service subscribes to this vehicle's scans; False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self.connected:
            if self._stopped or (deadline is not None and time.monotonic() >= deadline):
                return False
            time.sleep(0.05)
        return True

    def wait_pending(self, max_pending: int = 0, timeout: float | None = None) -> bool:
        """Wait until at most ``max_pending`` scans are queued or unanswered; False on timeout.

        Flow control for callers that want every scan processed: publish, then
        ``wait_pending(window - 1)`` keeps at most ``window`` scans between the caller and the
        service's answer (the service drops the oldest scan of a full session queue).
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while len(self._queue) + len(self._in_flight) + self._in_callback > max_pending:
                if self._stopped:
                    return False
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._cond.wait(0.1 if left is None else min(left, 0.1))
        return True

    def map_tiles(
        self,
        x: float,
        y: float,
        radius_m: float,
        *,
        map_name: str = "default",
        have: dict[str, int] | None = None,
        timeout: float = 10.0,
    ) -> list[TileUpdateMessage]:
        """The map's tiles around ``(x, y)`` as the service last saved them (:func:`map_tiles_near`
        on this publisher's session): what a vehicle localizing on board loads; ``have`` (tile id
        -> version) leaves out the tiles it holds at their current version. Raises
        :class:`RuntimeError` while the session is not open."""
        zs = self._zsession
        if zs is None:
            raise RuntimeError("the publisher's Zenoh session is not open")
        return map_tiles_near(zs, map_name, x, y, radius_m, have=have, timeout=timeout)

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every published scan is answered (and its callback has returned), dropped
        or lost; False on timeout. Not to be called from a callback."""
        return self.wait_pending(0, timeout)

    def close(self, timeout: float = 2.0) -> PublisherStats:
        """Send what is queued and wait for answers (up to ``timeout`` s), then close the session.

        Scans still queued or in flight afterwards are counted as lost. Idempotent.
        """
        with self._cond:
            already = self._closing
            self._closing = True
        if not already:
            self.flush(timeout)
        with self._cond:
            self._stopped = True
            self._stats.lost += len(self._queue) + len(self._in_flight)
            self._queue.clear()
            self._in_flight.clear()
            self._cond.notify_all()
        for t in (self._sender, self._dispatcher):
            if t.is_alive() and t is not threading.current_thread():
                t.join(5.0)
        self._close_session()
        return self.stats()

    def __enter__(self) -> VehiclePublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ Zenoh session
    def _try_open(self) -> bool:
        """Open the Zenoh session, publisher and answer subscribers; False (logged) on failure."""
        s = self.settings
        try:
            zs = zenoh.open(
                zenoh_config(s.mode, listen=s.listen, connect=s.connect, config_file=s.zenoh_config)
            )
        except Exception as exc:  # zenoh raises ZError when no endpoint answers
            log.warning("%s: cannot open a Zenoh %s session (%s); retrying", self.vehicle, s.mode, exc)
            return False
        self._publisher = zs.declare_publisher(
            self.scan_key,
            congestion_control=zenoh.CongestionControl.BLOCK,  # the sender thread may wait, never drop
            reliability=zenoh.Reliability.RELIABLE,
        )
        self._subs = [
            zs.declare_subscriber(pose_key(self.vehicle), self._on_pose_sample),
            zs.declare_subscriber(error_key(self.vehicle), self._on_error_sample),
        ]
        self._zsession = zs
        log.info("%s: Zenoh %s session open (connect %s)", self.vehicle, s.mode, list(s.connect))
        return True

    def _close_session(self) -> None:
        zs, self._zsession = self._zsession, None
        if zs is None:
            return
        for h in [*self._subs, self._publisher]:
            try:
                if h is not None:
                    h.undeclare()
            except Exception:
                log.debug("undeclare failed", exc_info=True)
        self._subs, self._publisher = [], None
        try:
            zs.close()
        except Exception:
            log.debug("closing the Zenoh session failed", exc_info=True)

    def _on_pose_sample(self, sample: zenoh.Sample) -> None:
        # Zenoh thread: decode and hand over, nothing else
        try:
            msg: PoseMessage | ErrorMessage = decode_pose(sample.payload.to_bytes())
        except BadMessageError:
            log.warning("%s: undecodable pose message ignored", self.vehicle)
            return
        self._push_answer(msg)

    def _on_error_sample(self, sample: zenoh.Sample) -> None:
        try:
            msg: PoseMessage | ErrorMessage = decode_error(sample.payload.to_bytes())
        except BadMessageError:
            log.warning("%s: undecodable error message ignored", self.vehicle)
            return
        self._push_answer(msg)

    def _push_answer(self, msg: PoseMessage | ErrorMessage) -> None:
        if msg.session != self.session:
            return  # another session of the same vehicle
        with self._cond:
            self._answers.append(msg)
            self._cond.notify_all()

    # ------------------------------------------------------------------ threads
    def _send_loop(self) -> None:
        """Open the session if needed, then publish the queue while a service listens."""
        backoff = self.settings.retry_s
        while True:
            with self._cond:
                while not self._queue and not self._stopped:
                    self._cond.wait(0.2)
                if self._stopped:
                    return
            if self._zsession is None:
                if not self._try_open():
                    with self._cond:
                        self._cond.wait(backoff)
                    backoff = min(2 * backoff, 10.0)
                    continue
                backoff = self.settings.retry_s
            matching = self.connected
            if matching != self._was_matching:
                if matching:
                    log.info("%s: service reachable", self.vehicle)
                else:
                    with self._cond:
                        self._stats.outages += 1
                    log.warning("%s: no service subscribed (router or service down?)", self.vehicle)
                self._was_matching = matching
            if not matching:
                with self._cond:
                    self._cond.wait(0.05)
                continue
            with self._cond:
                if not self._queue:
                    continue
                item = self._queue.popleft()
                self._in_flight[item.seq] = time.monotonic()
                self._stats.sent += 1
            try:
                assert self._publisher is not None
                self._publisher.put(item.payload)
            except Exception:
                log.exception("%s: publishing scan %d failed; re-opening the session", self.vehicle, item.seq)
                self._close_session()

    def _dispatch_loop(self) -> None:
        """Match answers to scans in flight, expire unanswered scans, call the user's callbacks."""
        timeout = self.settings.answer_timeout_s
        while True:
            with self._cond:
                while not self._answers and not self._stopped:
                    self._expire(timeout)
                    self._cond.wait(0.2)
                if self._stopped and not self._answers:
                    return
                msg = self._answers.popleft()
                known = self._in_flight.pop(msg.seq, None) if msg.seq is not None else None
                if known is None:
                    self._stats.late += 1
                elif isinstance(msg, PoseMessage):
                    self._stats.acknowledged += 1
                else:
                    self._stats.rejected += 1
                    self._stats.rejected_codes[msg.code] = self._stats.rejected_codes.get(msg.code, 0) + 1
                # on_pose for a PoseMessage, on_error for an ErrorMessage
                callback: Callable[[Any], Any] | None = (
                    self.on_pose if isinstance(msg, PoseMessage) else self.on_error
                )
                if known is not None and callback is not None:
                    self._in_callback += 1
                self._cond.notify_all()
            if known is None or callback is None:
                continue
            try:
                callback(msg)
            except Exception:
                log.exception("%s: the %s callback raised", self.vehicle, type(msg).__name__)
            finally:
                with self._cond:
                    self._in_callback -= 1
                    self._cond.notify_all()

    def _expire(self, timeout: float) -> None:
        """Count scans in flight for longer than ``timeout`` as lost (caller holds the lock)."""
        if not self._in_flight:
            return
        now = time.monotonic()
        old = [seq for seq, t in self._in_flight.items() if now - t > timeout]
        for seq in old:
            del self._in_flight[seq]
            self._stats.lost += 1
            log.warning("%s: scan %d got no answer in %.0f s, counted as lost", self.vehicle, seq, timeout)
        if old:
            self._cond.notify_all()


def map_tiles_near(
    session: zenoh.Session,
    map_name: str,
    x: float,
    y: float,
    radius_m: float,
    *,
    have: dict[str, int] | None = None,
    timeout: float = 10.0,
) -> list[TileUpdateMessage]:
    """The tiles of ``map_name`` whose cell comes within ``radius_m`` of ``(x, y)`` (map frame, m),
    each with its version and digest, by a get on the service's tile queryable
    (:func:`randt.wire.keys.tiles_near_selector`; docs/wire-format.md): the tiles a vehicle holds at
    their current version (``have``) are left out, so asking again after driving on fetches only the
    new and the changed ones. Sorted by tile id; empty when the map has none there (or no service
    answered within ``timeout``).

    Raises
    ------
    BadMessageError
        The service refused the query (its code first in the message, e.g. ``invalid_field`` for a
        radius beyond 1 km), or a reply did not decode.
    """
    selector = tiles_near_selector(map_name, x, y, radius_m, have)
    tiles: dict[str, TileUpdateMessage] = {}
    for reply in session.get(selector, timeout=timeout):
        if reply.ok is None:
            assert reply.err is not None
            text = reply.err.payload.to_bytes().decode(errors="replace")
            code = text.split(":", 1)[0]
            raise BadMessageError(
                f"tiles near ({x}, {y}): {text}", code=code if code.isidentifier() else "error"
            )
        tile = decode_tile_update(reply.ok.payload.to_bytes())
        tiles[tile.tile] = tile
    return [tiles[k] for k in sorted(tiles)]
