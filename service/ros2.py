"""The ROS 2 bridge: robots on rmw_zenoh feed the service and hear its answers, with no code on
the robot. With :mod:`randt.service.transport`, the only code of the service that talks to Zenoh.

:class:`Ros2Bridge` is a Zenoh client of the robots' router. Its callback reads a PointCloud2
sample's key and attachment (:mod:`randt.wire.rmw_zenoh`), no point, and hands a
:class:`randt.wire.ros2.Ros2Scan` to the intake as our own scans go (vehicle: the namespace;
session: the publisher's GID; seq: the attachment's). One sender thread answers a ROS 2 session
on its robot's topics as rmw_zenoh publishes, so neither the callback nor a session worker waits
on it (docs/ros2.md; the keys and tokens: docs/rmw_zenoh.md).
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import logging
import queue
import struct
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
import zenoh

from randt.core.errors import BadMessageError
from randt.core.transforms import invert
from randt.service.metrics import ServiceMetrics
from randt.service.settings import Ros2Settings
from randt.wire.codes import ErrorCode
from randt.wire.ids import is_valid_id
from randt.wire.messages import CorrectionMessage, ErrorMessage, GnssFix, PoseMessage, WireMessage
from randt.wire.rmw_zenoh import (
    Attachment,
    Qos,
    dds_type_name,
    decode_attachment,
    encode_attachment,
    endpoint_tokens,
    liveliness_token,
    parse_liveliness_token,
    parse_topic_key,
    topic_key,
)
from randt.wire.ros2 import (
    NAV_SAT_FIX,
    ODOMETRY,
    POINT_STAMPED,
    POINTCLOUD2,
    STRING,
    TRANSFORM_STAMPED,
    Ros2Scan,
    odometry_cdr,
    pointcloud2_cdr,
    read_navsatfix,
    read_point_stamped,
    string_cdr,
    transform_cdr,
    type_hash,
)
from randt.wire.zenoh_config import zenoh_config

__all__ = ["NODE_NAME", "Ros2Bridge", "topics_to_take", "vehicle_of_topic"]

log = logging.getLogger(__name__)

#: The node the service appears as in the ROS graph.
NODE_NAME = "randt_fleet"
#: ROS 2 sessions whose answer route is remembered (the oldest forgotten beyond).
MAX_ROUTES = 4096
#: Distinct topics counted by name in ``randt_ros2_samples_total``; beyond, as ``other``.
MAX_TOPIC_LABELS = 64
#: Longest frame_id read from a PointCloud2's header for the answers' child frame.
MAX_FRAME_ID = 256
#: NavSatFix messages kept per vehicle to find the one nearest a scan's stamp.
FIXES_KEPT = 64
#: Vehicles whose fixes are kept (the oldest forgotten beyond).
MAX_GNSS_VEHICLES = 4096
#: PointCloud2 topics not taken that are named in the log (once each; beyond, no more are).
MAX_TOPICS_NAMED = 4096


def vehicle_of_topic(topic: str, settings: Ros2Settings) -> tuple[str, str] | None:
    """``(vehicle, namespace)`` of a PointCloud2 topic, or ``None`` when it is not one of
    ``settings.topics``. :class:`~randt.core.errors.BadMessageError` when it is one but names no vehicle
    (no namespace and none given in ``settings.vehicles``, or a namespace that is not an id)."""
    for wanted in settings.topics:
        if wanted.startswith("/"):
            if topic != wanted:
                continue
            namespace = ""
            vehicle = settings.vehicles.get(topic)
        else:
            suffix = "/" + wanted
            if not topic.endswith(suffix):
                continue
            namespace = topic[: -len(suffix)]
            vehicle = settings.vehicles.get(topic) or settings.vehicles.get(namespace or "/")
            if vehicle is None and namespace:
                vehicle = namespace.strip("/").replace("/", ".")
        if vehicle is None:
            raise BadMessageError(
                f"topic {topic}: no vehicle id (no namespace): name one in RANDT_ROS2__VEHICLES",
                code=ErrorCode.INVALID_ID,
            )
        if not is_valid_id(vehicle):
            raise BadMessageError(
                f"topic {topic}: namespace {namespace!r} is not a vehicle id (letters, digits, _ . -): "
                "name one in RANDT_ROS2__VEHICLES",
                code=ErrorCode.INVALID_ID,
            )
        return vehicle, namespace
    return None


def topics_to_take(topic: str, namespace: str | None, settings: Ros2Settings) -> str:
    """The ``RANDT_ROS2__...`` setting(s) that would take ``topic`` (one none of ``settings.topics``
    matches): the topics as they are plus ``topic`` relative to its robot's ``namespace`` (the
    publishing node's; ``None`` when unknown: the first name of the topic is taken for it), or
    ``topic`` absolute with its vehicle to name when it has no namespace."""
    if namespace is None:
        head, _, rest = topic.strip("/").partition("/")
        namespace = f"/{head}" if rest else "/"
    prefix = namespace.rstrip("/") + "/"
    relative = namespace not in ("", "/") and topic.startswith(prefix) and topic != prefix
    wanted = topic[len(prefix) :] if relative else topic
    setting = f"RANDT_ROS2__TOPICS='{json.dumps([*settings.topics, wanted])}'"
    if relative:
        return setting
    vehicles = json.dumps({**settings.vehicles, topic: "<vehicle id>"})
    return f"{setting} RANDT_ROS2__VEHICLES='{vehicles}'"


def _peek_header(cdr: bytes) -> tuple[int | None, str | None]:
    """``(stamp ns, frame_id)`` of a CDR message that starts with a ``std_msgs/Header`` (after the
    4-byte encapsulation header: int32 sec, uint32 nanosec, a uint32 length and the frame_id's
    characters with their NUL), without decoding the message: the callback decodes no scan.
    ``None`` for what does not read (the intake's decode then says why)."""
    if len(cdr) < 16 or cdr[0] != 0 or cdr[1] not in (0, 1):
        return None, None
    sec, nanosec, n = struct.unpack_from("<iII" if cdr[1] == 1 else ">iII", cdr, 4)
    stamp = sec * 1_000_000_000 + nanosec if sec >= 0 and nanosec < 1_000_000_000 else None
    if not 1 <= n <= MAX_FRAME_ID or len(cdr) < 16 + n:
        return stamp, None
    try:
        return stamp, cdr[16 : 16 + n - 1].decode("utf-8")
    except UnicodeDecodeError:
        return stamp, None


_Answer = PoseMessage | ErrorMessage | CorrectionMessage
_T = TypeVar("_T")

#: ``map_near(vehicle, session, x, y, radius_m)``: the saved points of the map the session folds
#: into within ``radius_m`` (tiles, XY) of ``(x, y)``: ``(xyz, intensity, in the shared map)``, or
#: ``None`` (no such running session).
MapNear = Callable[[str, str, float, float, float], "tuple[np.ndarray, np.ndarray | None, bool] | None"]


@dataclass(frozen=True)
class _Listen:
    """Announce our subscription to a scan topic (its ``MS`` token), from the sender thread."""

    topic: str
    hash_like: str


@dataclass(frozen=True)
class _MapRequest:
    vehicle: str
    session: str
    stamp_ns: int
    point: np.ndarray


@dataclass
class _Route:
    """Where a ROS 2 session's answers go."""

    domain: int
    namespace: str
    hash_like: str
    frame_id: str
    last_stamp_ns: int = 0


@dataclass
class _Publisher:
    key: str
    gid: bytes
    token: Any
    seq: itertools.count[int] = field(default_factory=lambda: itertools.count(1))


class Ros2Bridge:
    """The Zenoh session to the robots' router, the PointCloud2 subscriber and the answers (module
    docstring). ``on_scan(vehicle, scan, received_ns)`` is the session manager's ``submit``."""

    def __init__(
        self,
        settings: Ros2Settings,
        on_scan: Callable[[str, Ros2Scan, int], None],
        metrics: ServiceMetrics,
        *,
        map_near: MapNear | None = None,
        max_outbound: int = 10_000,
    ) -> None:
        self.settings = settings
        self._map_near = map_near
        self._on_scan = on_scan
        self._metrics = metrics
        self._session: zenoh.Session | None = None
        self._zid = ""
        self._handles: list[Any] = []
        self._routes: OrderedDict[tuple[str, str], _Route] = OrderedDict()
        self._publishers: dict[str, _Publisher] = {}
        self._listening: dict[str, Any] = {}  # topic -> its subscription's liveliness token (or None: queued)
        self._entities = itertools.count(1)
        self._lock = threading.Lock()
        self._out: queue.Queue[_Answer | _MapRequest | _Listen | None] = queue.Queue(max_outbound)
        self._sender: threading.Thread | None = None
        self._topics: set[str] = set()
        self._fixes: OrderedDict[str, deque[tuple[int, GnssFix]]] = OrderedDict()
        self._warned: dict[tuple[str, str], int] = {}
        self._named: set[str] = set()  # PointCloud2 topics named in the log (not taken, or no vehicle)
        self.dropped_outbound = 0
        #: the settings with the NavSatFix (map request) topic as the only topic, for vehicle_of_topic
        self._gnss_topics = settings.model_copy(update={"topics": (settings.gnss_topic or "gnss/fix",)})
        self._request_topics = settings.model_copy(update={"topics": (settings.map_request_topic,)})

    @property
    def is_open(self) -> bool:
        return self._session is not None

    def open(self) -> None:
        s = self.settings
        try:
            self._session = zenoh.open(zenoh_config("client", (), s.routers, config_file=s.zenoh_config))
        except zenoh.ZError as exc:
            reason = str(exc).split(" at /", 1)[0]
            raise ValueError(
                f"Zenoh cannot open the ROS 2 session (router {', '.join(s.routers)}): {reason}"
            ) from exc
        self._zid = str(self._session.info.zid())
        self._sender = threading.Thread(target=self._send_loop, name="ros2-sender", daemon=True)
        self._sender.start()
        node = liveliness_token(
            domain=s.domain,
            zid=self._zid,
            node_id=0,
            entity_id=0,
            kind="NN",
            namespace="/",
            node_name=NODE_NAME,
        )
        self._handles = [
            self._session.declare_subscriber(
                f"{s.domain}/**/{dds_type_name(POINTCLOUD2)}/*", self._on_sample
            ),
            self._session.liveliness().declare_token(node),
            self._session.liveliness().declare_subscriber(
                endpoint_tokens(s.domain, "MP", POINTCLOUD2), self._on_publisher, history=True
            ),
        ]
        if s.gnss_topic is not None:
            gnss = f"{s.domain}/**/{dds_type_name(NAV_SAT_FIX)}/*"
            self._handles.append(self._session.declare_subscriber(gnss, self._on_fix))
        if self._map_near is not None:
            requests = f"{s.domain}/**/{dds_type_name(POINT_STAMPED)}/*"
            self._handles.append(self._session.declare_subscriber(requests, self._on_map_request))
        log.info(
            "ROS 2: client of %s, domain %d, topics %s", ", ".join(s.routers), s.domain, ", ".join(s.topics)
        )

    # -- in (Zenoh's callback thread: no decoding, no waiting) ---------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            self._take(str(sample.key_expr), sample.payload.to_bytes(), sample.attachment)
        except Exception:  # never let an exception escape into Zenoh's thread
            log.exception("ROS 2 sample on %s failed", sample.key_expr)

    def _take(self, key: str, cdr: bytes, attachment: zenoh.ZBytes | None) -> None:
        topic = key
        try:
            parsed = parse_topic_key(key)
            topic = parsed.topic
            found = vehicle_of_topic(topic, self.settings)
            if found is None:
                self._count(topic, "ignored")
                if key not in self._publishers:  # (not our own map answers)
                    self._not_taken(topic, None, "a sample")
                return
            vehicle, namespace = found
            att: Attachment = decode_attachment(None if attachment is None else attachment.to_bytes())
        except BadMessageError as exc:
            self._count(topic, exc.code)
            self._warn(topic, exc.code, str(exc))
            return
        session = att.gid.hex()
        stamp_ns, frame_id = _peek_header(cdr)
        with self._lock:
            fix = None if stamp_ns is None else self._fix_at(vehicle, stamp_ns)
            route = self._routes.get((vehicle, session))
            if route is None:
                frame = self.settings.sensor_frame or frame_id or "lidar"
                route = self._routes[(vehicle, session)] = _Route(
                    parsed.domain, namespace, parsed.type_hash, frame
                )
                while len(self._routes) > MAX_ROUTES:
                    self._routes.popitem(last=False)
                log.info(
                    "ROS 2: %s (publisher %s) is vehicle %s, session %s", topic, session, vehicle, session
                )
            else:
                self._routes.move_to_end((vehicle, session))
        self._listen_soon(topic, parsed.type_hash)
        self._count(topic, "accepted")
        only = vehicle in self.settings.localize_only or "*" in self.settings.localize_only
        scan = Ros2Scan(cdr, topic, vehicle, session, att.sequence_number, fix, localize_only=only)
        self._on_scan(vehicle, scan, time.time_ns())

    def _on_publisher(self, sample: zenoh.Sample) -> None:
        """A PointCloud2 publisher's liveliness token (a put: it appeared; a delete: it went): on a
        topic we take, our subscription is announced now, before any sample; another topic is
        named once in the log."""
        try:
            if sample.kind != zenoh.SampleKind.PUT:
                return
            token = parse_liveliness_token(str(sample.key_expr))
            topic = token.topic
            if token.zid == self._zid or topic is None:  # (our own map answers)
                return
            try:
                found = vehicle_of_topic(topic, self.settings)
            except BadMessageError as exc:
                if self._first_naming(topic):
                    log.warning(
                        "ROS 2: PointCloud2 publisher %s on %s cannot be taken: %s", token.node, topic, exc
                    )
                return
            if found is None:
                self._not_taken(topic, token.namespace, f"publisher {token.node}")
            else:
                self._listen_soon(topic, token.type_hash or "")
        except BadMessageError as exc:  # (a token that does not parse: not rmw_zenoh's)
            log.debug("ROS 2: %s", exc)
        except Exception:  # never let an exception escape into Zenoh's thread
            log.exception("ROS 2 liveliness token %s failed", sample.key_expr)

    def _not_taken(self, topic: str, namespace: str | None, seen_by: str) -> None:
        """Name a PointCloud2 topic none of ``topics`` matches, once, with the setting that takes it."""
        if not self._first_naming(topic):
            return
        wanted = ", ".join(self.settings.topics)
        fix = topics_to_take(topic, namespace, self.settings)
        log.info(
            "ROS 2: PointCloud2 topic %s (%s) is not taken: it matches none of the topics (%s); "
            "to take it: %s", topic, seen_by, wanted, fix,
        )  # fmt: skip

    def _first_naming(self, topic: str) -> bool:
        """Whether ``topic`` is named in the log now (the first time, and while few have been)."""
        with self._lock:
            if topic in self._named or len(self._named) >= MAX_TOPICS_NAMED:
                return False
            self._named.add(topic)
            return True

    def _listen_soon(self, topic: str, hash_like: str) -> None:
        """Have the sender thread announce our subscription to ``topic`` (once per topic)."""
        with self._lock:
            listen = topic not in self._listening and len(self._listening) < MAX_ROUTES
            if listen:
                self._listening[topic] = None  # (declared by the sender thread)
        if listen:
            with contextlib.suppress(queue.Full):
                self._out.put_nowait(_Listen(topic, hash_like))

    def _read_small(
        self, sample: zenoh.Sample, topics: Ros2Settings, read: Callable[[bytes], _T]
    ) -> tuple[str, str, _T] | None:
        """``(topic, vehicle, message)`` of a small sample (a fix, a request: decoded here, in
        Zenoh's callback) on one of ``topics``' topics; ``None`` for another topic, or for one that
        does not read (counted and logged per topic, never raised into Zenoh's thread)."""
        key = topic = str(sample.key_expr)
        try:
            topic = parse_topic_key(key).topic
            found = vehicle_of_topic(topic, topics)
            return None if found is None else (topic, found[0], read(sample.payload.to_bytes()))
        except BadMessageError as exc:
            self._count(topic, exc.code)
            self._warn(topic, exc.code, str(exc))
        except Exception:
            log.exception("ROS 2 sample on %s failed", key)
        return None

    def _on_fix(self, sample: zenoh.Sample) -> None:
        """A NavSatFix: kept for the vehicle's next scans (a few hundred bytes)."""
        got = self._read_small(sample, self._gnss_topics, read_navsatfix)
        if got is None:
            return
        topic, vehicle, (stamp_ns, fix) = got
        if fix is None:
            self._count(topic, "no_fix")
            return
        with self._lock:
            kept = self._fixes.get(vehicle)
            if kept is None:
                kept = self._fixes[vehicle] = deque(maxlen=FIXES_KEPT)
                while len(self._fixes) > MAX_GNSS_VEHICLES:
                    self._fixes.popitem(last=False)
            kept.append((stamp_ns, fix))
        self._count(topic, "accepted")

    def _on_map_request(self, sample: zenoh.Sample) -> None:
        """A PointStamped on ``<namespace>/randt/map_request``: the map around its point, queued for
        the sender thread (the tiles are read and serialized there, not here)."""
        got = self._read_small(sample, self._request_topics, read_point_stamped)
        if got is None:
            return
        topic, vehicle, (stamp_ns, _, point) = got
        with self._lock:  # the vehicle's newest session (routes are kept in order of use)
            session = next((s for v, s in reversed(self._routes) if v == vehicle), None)
        if session is None:
            self._count(topic, "no_session")
            self._warn(topic, "no_session", f"no session of vehicle {vehicle} to send a map to")
            return
        self._count(topic, "accepted")
        try:
            self._out.put_nowait(_MapRequest(vehicle, session, stamp_ns, point))
        except queue.Full:
            self.dropped_outbound += 1

    def _fix_at(self, vehicle: str, stamp_ns: int) -> GnssFix | None:
        """The vehicle's fix nearest ``stamp_ns``, within ``gnss_max_gap_s`` (under the lock)."""
        kept = self._fixes.get(vehicle)
        if not kept:
            return None
        gap, fix = min(((abs(t - stamp_ns), f) for t, f in kept), key=lambda c: c[0])
        return fix if gap <= self.settings.gnss_max_gap_s * 1e9 else None

    def _listen(self, request: _Listen) -> None:
        """Announce our subscription to a topic (an ``MS`` token: ``ros2 topic info`` lists us)."""
        if self._session is None:
            return
        s = self.settings
        token = liveliness_token(
            domain=s.domain, zid=self._zid, node_id=0, entity_id=next(self._entities), kind="MS",
            namespace="/", node_name=NODE_NAME, topic=request.topic, ros_type=POINTCLOUD2,
            type_hash=type_hash(POINTCLOUD2, request.hash_like), qos=Qos(reliability=2, depth=5),
        )  # fmt: skip
        declared = self._session.liveliness().declare_token(token)
        with self._lock:
            self._listening[request.topic] = declared

    def _count(self, topic: str, outcome: str) -> None:
        with self._lock:
            if topic not in self._topics and len(self._topics) < MAX_TOPIC_LABELS:
                self._topics.add(topic)
            label = topic if topic in self._topics else "other"
        self._metrics.ros2_samples.labels(label, outcome).inc()

    def _warn(self, topic: str, code: str, reason: str) -> None:
        """Logged per topic and reason: the first time, then every 100th."""
        with self._lock:
            if len(self._warned) > MAX_ROUTES:  # (a flood of topics: counting starts again)
                self._warned.clear()
            n = self._warned[(topic, code)] = self._warned.get((topic, code), 0) + 1
        if n == 1 or n % 100 == 0:
            log.warning("ROS 2 sample on %s refused (%s, %d so far): %s", topic, code, n, reason)

    # -- out (the outbox's tap; serialized and published by the sender thread) -----------------
    def owns(self, vehicle: str, session: str) -> bool:
        with self._lock:
            return (vehicle, session) in self._routes

    def send(self, message: WireMessage) -> None:
        """Queue an answer for a ROS 2 session (others are ignored; dropped, counted, when full)."""
        if not isinstance(message, PoseMessage | ErrorMessage | CorrectionMessage):
            return
        if not self.owns(message.vehicle, message.session):
            return
        try:
            self._out.put_nowait(message)
        except queue.Full:
            self.dropped_outbound += 1

    def _send_loop(self) -> None:
        while True:
            message = self._out.get()
            if message is None:
                return
            try:
                self._publish(message)
            except Exception:
                log.exception("ROS 2: sending %s failed", type(message).__name__)

    def _publish(self, message: _Answer | _MapRequest | _Listen) -> None:
        s = self.settings
        if isinstance(message, _Listen):
            self._listen(message)
            return
        with self._lock:
            route = self._routes.get((message.vehicle, message.session))
        if route is None:
            return
        if isinstance(message, _MapRequest):
            self._send_map(route, message)
            return
        if isinstance(message, PoseMessage):
            route.last_stamp_ns = max(route.last_stamp_ns, message.stamp_ns)
            if message.status in ("first", "ok"):
                frame = s.sensor_frame or route.frame_id
                payload = odometry_cdr(message, frame_id=s.odom_frame, child_frame_id=frame)
                self._put(route, s.odometry_topic, ODOMETRY, payload)
                return
            status: dict[str, Any] = {
                "seq": message.seq,
                "status": message.status,
                "stamp_ns": message.stamp_ns,
            }
        elif isinstance(message, ErrorMessage):
            status = {"seq": message.seq, "status": message.code, "reason": message.reason}
            if message.retry_after_s is not None:
                status["retry_after_s"] = message.retry_after_s
        else:
            poses, live = message.poses(), message.live_poses()
            newest = int(np.argmax(message.seqs()))
            C = poses[newest] @ invert(live[newest])
            payload = transform_cdr(
                route.last_stamp_ns or time.time_ns(), C, frame_id=s.map_frame, child_frame_id=s.odom_frame
            )
            self._put(route, s.correction_topic, TRANSFORM_STAMPED, payload)
            return
        status.update(vehicle=message.vehicle, session=message.session)
        self._put(route, s.status_topic, STRING, string_cdr(status))

    def _send_map(self, route: _Route, request: _MapRequest) -> None:
        """The saved map around the requested point as one PointCloud2 on ``map_topic``: in
        ``map_frame`` for a session in the shared map, else in its own frame (``odom_frame``)."""
        s = self.settings
        assert self._map_near is not None
        x, y = float(request.point[0]), float(request.point[1])
        found = self._map_near(request.vehicle, request.session, x, y, s.map_radius_m)
        if found is None:
            return
        xyz, intensity, shared = found
        frame = s.map_frame if shared else s.odom_frame
        self._put(route, s.map_topic, POINTCLOUD2, pointcloud2_cdr(request.stamp_ns, frame, xyz, intensity))

    def _put(self, route: _Route, name: str, ros_type: str, payload: bytes) -> None:
        """Publish on ``name`` (relative: under the robot's namespace) as rmw_zenoh does."""
        if self._session is None:
            return
        topic = name if name.startswith("/") else f"{route.namespace}/{name}"
        publisher = self._publisher(route, topic, ros_type)
        attachment = encode_attachment(Attachment(next(publisher.seq), time.time_ns(), publisher.gid))
        self._session.put(publisher.key, payload, attachment=attachment)

    def _publisher(self, route: _Route, topic: str, ros_type: str) -> _Publisher:
        """The publisher of ``topic`` (declared on first use: its liveliness token and GID)."""
        hash_ = type_hash(ros_type, route.hash_like)
        key = topic_key(route.domain, topic, ros_type, hash_)
        found = self._publishers.get(key)
        if found is not None:
            return found
        assert self._session is not None
        token = liveliness_token(
            domain=route.domain, zid=self._zid, node_id=0, entity_id=next(self._entities), kind="MP",
            namespace="/", node_name=NODE_NAME, topic=topic, ros_type=ros_type, type_hash=hash_,
            qos=Qos(depth=10),
        )  # fmt: skip
        gid = hashlib.blake2b(token.encode(), digest_size=16).digest()
        while len(self._publishers) >= 4 * MAX_ROUTES:  # (the oldest robots' answer topics go)
            oldest = self._publishers.pop(next(iter(self._publishers)))
            with contextlib.suppress(Exception):
                oldest.token.undeclare()
        publisher = self._publishers[key] = _Publisher(
            key, gid, self._session.liveliness().declare_token(token)
        )
        return publisher

    def close(self) -> None:
        """Publish what is queued, then close the session (its tokens go with it)."""
        if self._sender is not None:
            self._out.put(None)
            self._sender.join(10)
        listening = [t for t in self._listening.values() if t is not None]
        tokens = [*self._handles, *listening, *(p.token for p in self._publishers.values())]
        for handle in tokens:
            with contextlib.suppress(Exception):
                handle.undeclare()
        if self._session is not None:
            self._session.close()
            self._session = None
