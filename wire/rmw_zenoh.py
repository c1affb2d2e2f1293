"""rmw_zenoh's format on Zenoh, as pure functions: topic key expressions, the per-sample attachment,
liveliness tokens and their QoS chunk (docs/rmw_zenoh.md has the sources, section by section).

What a ROS 2 robot running rmw_zenoh (Jazzy, Kilted, Rolling; Humble with its hash placeholder)
puts on Zenoh, so that the service can read its topics and answer on them with no bridge:

* data on ``<domain>/<topic without its outer slashes>/<DDS type name>/<type hash>``, e.g.
  ``0/robot1/lidar/points/sensor_msgs::msg::dds_::PointCloud2_/RIHS01_9198...``;
* each sample with a 33-byte attachment: int64 LE sequence number, int64 LE source timestamp (ns),
  the LEB128 length 16 and the publisher's 16-byte GID (a ROS 2 subscriber drops a sample
  without it); the 77-byte layout of Jazzy 0.2.0-0.2.3 is read too;
* endpoints announced by liveliness tokens under ``@ros2_lv/<domain>/...`` with ``/`` mangled to
  ``%`` and the QoS in one chunk, empty where it equals rmw_zenoh's default: written by
  :func:`liveliness_token`, read by :func:`parse_liveliness_token` (the service learns of a
  robot's publishers from them, before and without any sample: :func:`endpoint_tokens`).

No Zenoh here (``wire`` does not import it): the transport builds on these.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass, replace
from typing import Literal

from randt.core.errors import BadMessageError
from randt.wire.codes import ErrorCode

__all__ = [
    "ADMIN_SPACE",
    "HUMBLE_TYPE_HASH",
    "Attachment",
    "LivelinessToken",
    "Qos",
    "TopicKey",
    "dds_type_name",
    "decode_attachment",
    "encode_attachment",
    "endpoint_tokens",
    "liveliness_token",
    "mangle",
    "parse_liveliness_token",
    "parse_topic_key",
    "ros_type_name",
    "topic_key",
    "unmangle",
]

#: The liveliness tokens' first chunk (a hermetic chunk: ``**`` never matches it).
ADMIN_SPACE = "@ros2_lv"
#: What Humble's rmw_zenoh writes where a type hash goes (Humble has no type hashes).
HUMBLE_TYPE_HASH = "TypeHashNotSupported"
#: A GID is 16 bytes (rmw_zenoh on Jazzy and later; Humble's is hard-coded to 16 too).
GID_SIZE = 16
_ATTACHMENT_C = struct.Struct("<qqB")  # seq, timestamp, LEB128 length of the GID (16 < 128)
_ATTACHMENT_B_KEYS = (b"sequence_number", b"source_timestamp", b"source_gid")
_HASH_RE = re.compile(r"^(RIHS01_[0-9a-f]{64}|" + HUMBLE_TYPE_HASH + r")$")
_DDS_RE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)::(msg|srv|action)::dds_::([A-Za-z][A-Za-z0-9_]*)_$")
_ROS_RE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(msg|srv|action)/([A-Za-z][A-Za-z0-9_]*)$")


def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/PointCloud2`` -> ``sensor_msgs::msg::dds_::PointCloud2_`` (the key's type chunk)."""
    m = _ROS_RE.match(ros_type)
    if m is None:
        raise ValueError(f"not a ROS 2 type name (pkg/msg/Name): {ros_type!r}")
    return f"{m.group(1)}::{m.group(2)}::dds_::{m.group(3)}_"


def ros_type_name(dds_type: str) -> str:
    """The inverse of :func:`dds_type_name`."""
    m = _DDS_RE.match(dds_type)
    if m is None:
        raise ValueError(f"not an rmw_zenoh DDS type name (pkg::msg::dds_::Name_): {dds_type!r}")
    return f"{m.group(1)}/{m.group(2)}/{m.group(3)}"


@dataclass(frozen=True)
class TopicKey:
    """A data key expression's parts: ``topic`` is the ROS name with its leading slash."""

    domain: int
    topic: str
    ros_type: str
    type_hash: str

    def __str__(self) -> str:
        return topic_key(self.domain, self.topic, self.ros_type, self.type_hash)


def topic_key(domain: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The key expression rmw_zenoh publishes ``topic`` of ``ros_type`` on."""
    if not 0 <= domain <= 232:  # (ROS_DOMAIN_ID's range)
        raise ValueError(f"ROS domain id {domain} outside 0..232")
    name = topic.strip("/")
    if not name or "//" in name:
        raise ValueError(f"not a ROS topic name: {topic!r}")
    if not _HASH_RE.match(type_hash):
        raise ValueError(f"not a type hash (RIHS01_<64 hex> or {HUMBLE_TYPE_HASH}): {type_hash!r}")
    return f"{domain}/{name}/{dds_type_name(ros_type)}/{type_hash}"


def parse_topic_key(key: str) -> TopicKey:
    """The parts of a data key expression (:class:`~randt.core.errors.BadMessageError` ``invalid_field``
    when ``key`` is not one: the service logs and counts such samples)."""
    chunks = str(key).split("/")
    if len(chunks) < 4 or not chunks[0].isdigit():
        raise BadMessageError(
            f"key {key!r}: not <domain>/<topic>/<type>/<hash>", code=ErrorCode.INVALID_FIELD
        )
    type_hash, dds_type = chunks[-1], chunks[-2]
    try:
        ros_type = ros_type_name(dds_type)
    except ValueError as exc:
        raise BadMessageError(f"key {key!r}: {exc}", code=ErrorCode.INVALID_FIELD) from None
    if not _HASH_RE.match(type_hash):
        raise BadMessageError(f"key {key!r}: {type_hash!r} is not a type hash", code=ErrorCode.INVALID_FIELD)
    return TopicKey(int(chunks[0]), "/" + "/".join(chunks[1:-2]), ros_type, type_hash)


@dataclass(frozen=True)
class Attachment:
    """A sample's attachment: the publisher's sequence number (from 1 in rmw_zenoh), the source
    timestamp (ns since the Unix epoch) and the publisher's 16-byte GID."""

    sequence_number: int
    source_timestamp_ns: int
    gid: bytes


def encode_attachment(attachment: Attachment) -> bytes:
    """The 33 bytes rmw_zenoh attaches to a sample (Jazzy >= 0.2.4, Kilted, Rolling >= 0.6)."""
    if len(attachment.gid) != GID_SIZE:
        raise ValueError(f"a GID is {GID_SIZE} bytes, got {len(attachment.gid)}")
    head = _ATTACHMENT_C.pack(attachment.sequence_number, attachment.source_timestamp_ns, GID_SIZE)
    return head + bytes(attachment.gid)


def decode_attachment(data: bytes | None) -> Attachment:
    """A sample's attachment, in the current 33-byte layout or the 77-byte one of Jazzy 0.2.0-0.2.3
    (keys, then values); :class:`~randt.core.errors.BadMessageError` ``missing_field`` without one, as a
    ROS 2 subscriber drops it, ``invalid_field`` for any other bytes."""
    if data is None:
        raise BadMessageError("attachment: none (rmw_zenoh samples carry one)", code=ErrorCode.MISSING_FIELD)
    raw = bytes(data)
    if len(raw) == _ATTACHMENT_C.size + GID_SIZE:
        seq, stamp, n = _ATTACHMENT_C.unpack_from(raw)
        if n == GID_SIZE:
            return Attachment(seq, stamp, raw[_ATTACHMENT_C.size :])
    if len(raw) == 77 and raw[0] == len(
        _ATTACHMENT_B_KEYS[0]
    ):  # (format B: key, int64, key, int64, key, gid)
        values, at = [], 0
        for key, size in zip(_ATTACHMENT_B_KEYS, (8, 8, 1 + GID_SIZE), strict=True):
            if raw[at] != len(key) or raw[at + 1 : at + 1 + len(key)] != key:
                break
            at += 1 + len(key)
            values.append(raw[at : at + size])
            at += size
        else:
            if values[2][0] == GID_SIZE:
                return Attachment(
                    struct.unpack("<q", values[0])[0], struct.unpack("<q", values[1])[0], values[2][1:]
                )
    raise BadMessageError(
        f"attachment: {len(raw)} bytes are neither rmw_zenoh's 33-byte (seq, timestamp, GID) layout "
        "nor its older 77-byte one",
        code=ErrorCode.INVALID_FIELD,
    )


def mangle(name: str) -> str:
    """A name in a liveliness token: every ``/`` as ``%``; empty or ``/`` alone as ``%``."""
    return "%" if name in ("", "/") else name.replace("/", "%")


def unmangle(chunk: str) -> str:
    """The inverse of :func:`mangle` (``%`` alone is ``/``)."""
    return chunk.replace("%", "/")


@dataclass(frozen=True)
class Qos:
    """The QoS of an endpoint, in rmw's enum values (``rmw/types.h``); the defaults are rmw_zenoh's:
    RELIABLE (1), VOLATILE (2), KEEP_LAST (1) depth 42, infinite deadline, lifespan and lease,
    AUTOMATIC liveliness (1)."""

    reliability: int = 1
    durability: int = 2
    history: int = 1
    depth: int = 42

    def keyexpr(self) -> str:
        """The token's QoS chunk: ``<rel>:<dur>:<hist>,<depth>:<deadline>:<lifespan>:<liveliness>``,
        each field empty where it is the default (deadline, lifespan and liveliness always are here)."""
        d = Qos()

        def part(value: int, default: int) -> str:
            return "" if value == default else str(value)

        return (
            f"{part(self.reliability, d.reliability)}:{part(self.durability, d.durability)}:"
            f"{part(self.history, d.history)},{part(self.depth, d.depth)}:,:,:,,"
        )


def liveliness_token(
    *,
    domain: int,
    zid: str,
    node_id: int,
    entity_id: int,
    kind: Literal["NN", "MP", "MS", "SS", "SC"],
    namespace: str,
    node_name: str,
    enclave: str = "",
    topic: str | None = None,
    ros_type: str | None = None,
    type_hash: str | None = None,
    qos: Qos | None = None,
) -> str:
    """The liveliness token of a node (``NN``) or of one of its endpoints (``MP`` publisher, ``MS``
    subscription, ...): ``@ros2_lv/<domain>/<zid>/<node>/<entity>/<kind>/<enclave>/<namespace>/
    <node name>[/<topic>/<type>/<hash>/<qos>]``, names mangled (:func:`mangle`)."""
    names = f"{mangle(enclave)}/{mangle(namespace)}/{node_name}"
    head = f"{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{entity_id}/{kind}/{names}"
    if kind == "NN":
        return head
    if topic is None or ros_type is None or type_hash is None:
        raise ValueError(f"an endpoint's token ({kind}) needs its topic, type and type hash")
    return f"{head}/{mangle(topic)}/{dds_type_name(ros_type)}/{type_hash}/{(qos or Qos()).keyexpr()}"


#: The kinds of endpoint a token announces (``NN`` is a node, with no topic).
EndpointKind = Literal["MP", "MS", "SS", "SC"]
_KINDS = ("NN", "MP", "MS", "SS", "SC")


@dataclass(frozen=True)
class LivelinessToken:
    """A liveliness token's parts (:func:`liveliness_token`'s arguments), names unmangled:
    ``namespace`` ``/`` or ``/robot1``, ``topic`` with its leading slash, ``ros_type`` as
    ``pkg/msg/Name``; the four endpoint fields are ``None`` for a node (``NN``). ``qos`` is the
    QoS chunk as written (not parsed: the service does not need it)."""

    domain: int
    zid: str
    node_id: int
    entity_id: int
    kind: str
    enclave: str
    namespace: str
    node_name: str
    topic: str | None = None
    ros_type: str | None = None
    type_hash: str | None = None
    qos: str | None = None

    @property
    def node(self) -> str:
        """The node's fully qualified name (``/robot1/lidar_driver``)."""
        return f"{self.namespace.rstrip('/')}/{self.node_name}"


def parse_liveliness_token(key: str) -> LivelinessToken:
    """The parts of a liveliness token (:class:`~randt.core.errors.BadMessageError` ``invalid_field``
    when ``key`` is not one). Chunks past the thirteenth (Rolling's buffer backends, whose place
    docs/rmw_zenoh.md could not confirm) are not read; neither is the QoS chunk's content."""
    chunks = str(key).split("/")

    def bad(why: str) -> BadMessageError:
        return BadMessageError(f"liveliness token {key!r}: {why}", code=ErrorCode.INVALID_FIELD)

    if len(chunks) < 9 or chunks[0] != ADMIN_SPACE or not all(chunks[1:9]):
        raise bad(f"not {ADMIN_SPACE}/<domain>/<zid>/<node>/<entity>/<kind>/<enclave>/<namespace>/<name>")
    domain, zid, node_id, entity_id, kind, enclave, namespace, node_name = chunks[1:9]
    if not (domain.isdigit() and node_id.isdigit() and entity_id.isdigit()) or kind not in _KINDS:
        raise bad("domain, node and entity ids must be decimal, the kind one of " + ", ".join(_KINDS))
    node = LivelinessToken(
        int(domain),
        zid,
        int(node_id),
        int(entity_id),
        kind,
        unmangle(enclave),
        unmangle(namespace),
        node_name,
    )
    if kind == "NN":
        return node
    if len(chunks) < 13 or not all(chunks[9:13]):
        raise bad(f"an endpoint's token ({kind}) ends with <topic>/<type>/<hash>/<qos>")
    try:
        ros_type = ros_type_name(chunks[10])
    except ValueError as exc:
        raise bad(str(exc)) from None
    if not _HASH_RE.match(chunks[11]):
        raise bad(f"{chunks[11]!r} is not a type hash")
    return replace(node, topic=unmangle(chunks[9]), ros_type=ros_type, type_hash=chunks[11], qos=chunks[12])


def endpoint_tokens(domain: int, kind: EndpointKind, ros_type: str) -> str:
    """The key expression of every ``kind`` endpoint's token of ``ros_type`` in ``domain``
    (a liveliness subscriber's; ``@ros2_lv`` is written out: ``**`` never matches it)."""
    return f"{ADMIN_SPACE}/{domain}/*/*/*/{kind}/*/*/*/*/{dds_type_name(ros_type)}/**"
