"""ROS 2 messages in and out of the service: a ``sensor_msgs/msg/PointCloud2`` sample as a scan,
and the answers as ``nav_msgs/msg/Odometry``, ``geometry_msgs/msg/TransformStamped`` and
``std_msgs/msg/String`` (docs/ros2.md).

A robot running rmw_zenoh puts its LiDAR topic on Zenoh as CDR (:mod:`randt.wire.rmw_zenoh` has the
keys and the attachment). The service's ROS 2 bridge (service/ros2.py) turns each sample into a
:class:`Ros2Scan`: the CDR bytes as they came, the vehicle (the robot's namespace), the session
(the publisher's GID, so a restarted driver is a new session) and the sequence number of the
attachment. From there it follows our own scans' path: :func:`scan_header` is what the intake
reads of it (the layout checked, no point read: ``randt.wire.messages.decode_scan_header`` for ours),
:func:`sweep_arrays` what the matcher process decodes (``randt.service.matchers.decoded_sweep``).

CDR is ``rosbags``' (pure Python, Apache-2.0; the ``ros2`` extra), with its Jazzy type store:
the five message types used here have the same definition in Humble, Jazzy, Kilted and Rolling
(their RIHS01 hashes are equal in rosbags' stores; Humble sends no hash). ``import randt.wire.ros2``
needs neither rosbags nor Zenoh; the first decode or encode loads rosbags.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from randt.core.errors import BadMessageError, FormatError
from randt.core.io.pointcloud2 import check_pointcloud2, pointcloud2_arrays
from randt.wire.codes import ErrorCode
from randt.wire.messages import SCHEMA_VERSION, GnssFix, PoseMessage, ScanHeader, WireLimits
from randt.wire.rmw_zenoh import HUMBLE_TYPE_HASH

__all__ = [
    "NAV_SAT_FIX",
    "ODOMETRY",
    "POINTCLOUD2",
    "POINT_STAMPED",
    "STRING",
    "TRANSFORM_STAMPED",
    "Ros2Scan",
    "odometry_cdr",
    "pointcloud2_cdr",
    "read_navsatfix",
    "read_point_stamped",
    "read_pointcloud2",
    "scan_header",
    "string_cdr",
    "sweep_arrays",
    "transform_cdr",
    "type_hash",
    "typestore",
]

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
STRING = "std_msgs/msg/String"
NAV_SAT_FIX = "sensor_msgs/msg/NavSatFix"
POINT_STAMPED = "geometry_msgs/msg/PointStamped"


@functools.cache
def typestore() -> Any:
    """rosbags' ROS 2 Jazzy type store (:class:`~randt.core.errors.FormatError` naming the extra when
    rosbags is not installed)."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise FormatError("ROS 2 messages need rosbags: pip install 'randt-fleet[ros2]'") from None
    return get_typestore(Stores.ROS2_JAZZY)


@functools.cache
def type_hash(ros_type: str, like: str = "") -> str:
    """The type hash to put in a key for ``ros_type``: ``RIHS01_<hex>``, or Humble's placeholder
    when ``like`` (the hash chunk of the robot's own key) is it, so a Humble robot hears us."""
    if like == HUMBLE_TYPE_HASH:
        return HUMBLE_TYPE_HASH
    return str(typestore().hash_rihs01(ros_type))


@dataclass(frozen=True)
class Ros2Scan:
    """A PointCloud2 sample of a ROS 2 robot, as the service holds it before decoding: its CDR
    bytes (with the 4-byte encapsulation header), the ROS topic it came on, the vehicle and
    session it was assigned (the robot's namespace and the publisher's GID, in hex), and the
    attachment's sequence number. ``len()`` is the payload's size (the intake's byte limits)."""

    cdr: bytes
    topic: str
    vehicle: str
    session: str
    seq: int
    #: the robot's NavSatFix nearest the scan's stamp, when it publishes one (service/ros2.py)
    fix: GnssFix | None = None
    #: its session only localizes on the map (``Ros2Settings.localize_only``)
    localize_only: bool = False

    def __len__(self) -> int:
        return len(self.cdr)


def read_pointcloud2(cdr: bytes) -> Any:
    """The PointCloud2 message of CDR bytes (:class:`~randt.core.errors.BadMessageError` ``malformed``
    when they are not one)."""
    typestore()  # (without rosbags: the error naming the extra comes first)
    if len(cdr) < 4 or cdr[0] != 0 or cdr[1] not in (0, 1):
        raise BadMessageError(
            "PointCloud2: not CDR (no plain CDR encapsulation header 00 00 or 00 01)",
            code=ErrorCode.MALFORMED,
        )
    return _deserialize(cdr, POINTCLOUD2)


def _deserialize(cdr: bytes, ros_type: str) -> Any:
    """rosbags' message of CDR bytes, :class:`~randt.core.errors.BadMessageError` ``malformed`` when
    they do not decode (rosbags raises plain exceptions on short or bad bytes). From a memoryview
    an array field (a cloud's ``data``) is a view of the bytes: 0.01 ms, not a 0.25 ms copy of a
    2.5 MB sweep."""
    try:
        return typestore().deserialize_cdr(memoryview(cdr), ros_type)
    except Exception as exc:
        name = ros_type.rsplit("/", 1)[-1]
        raise BadMessageError(
            f"{name}: the CDR does not decode ({type(exc).__name__}: {exc})", code=ErrorCode.MALFORMED
        ) from None


def _stamp_ns(msg: Any) -> int:
    sec, nanosec = int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)
    if sec < 0 or not 0 <= nanosec < 1_000_000_000:
        raise BadMessageError(
            f"header.stamp {sec} s {nanosec} ns: not a time since the Unix epoch",
            code=ErrorCode.INVALID_FIELD,
        )
    return sec * 1_000_000_000 + nanosec


def scan_header(scan: Ros2Scan, limits: WireLimits) -> ScanHeader:
    """What the intake reads of a ROS 2 scan: ids, seq, stamp and point count, with the cloud's
    layout checked (fields, datatypes, bytes) but no point read. Raises
    :class:`~randt.core.errors.BadMessageError`: ``malformed`` (not a PointCloud2), ``invalid_points``
    (a layout that cannot be read), ``empty_scan``, ``too_many_points``, ``invalid_field`` (the stamp)."""
    msg = read_pointcloud2(scan.cdr)
    try:
        n = check_pointcloud2(msg)
    except FormatError as exc:
        raise BadMessageError(str(exc), code=ErrorCode.INVALID_POINTS) from None
    if n == 0:
        raise BadMessageError("PointCloud2 without points", code=ErrorCode.EMPTY_SCAN)
    if n > limits.max_points:
        raise BadMessageError(
            f"PointCloud2 of {n} points: more than the service takes ({limits.max_points})",
            code=ErrorCode.TOO_MANY_POINTS,
        )
    return ScanHeader(
        SCHEMA_VERSION,
        scan.vehicle,
        scan.session,
        scan.seq,
        _stamp_ns(msg),
        n,
        gnss_fix=scan.fix,
        localize_only=scan.localize_only,
    )


def sweep_arrays(scan: Ros2Scan) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, float]:
    """What the matcher takes of a ROS 2 scan: ``(xyz float32, time offsets float32 s or None,
    intensity float32 or None, stamp s)`` (:func:`randt.core.io.pointcloud2.pointcloud2_arrays`)."""
    msg = read_pointcloud2(scan.cdr)
    try:
        xyz, offsets, intensity = pointcloud2_arrays(msg)
    except FormatError as exc:
        raise BadMessageError(str(exc), code=ErrorCode.INVALID_POINTS) from None
    return xyz, offsets, intensity, _stamp_ns(msg) * 1e-9


def read_navsatfix(cdr: bytes) -> tuple[int, GnssFix | None]:
    """``(stamp ns, fix)`` of a ``sensor_msgs/msg/NavSatFix``; the fix is ``None`` when the
    receiver has none (``status.status`` < 0, STATUS_NO_FIX) or gives no covariance
    (``position_covariance_type`` 0, COVARIANCE_TYPE_UNKNOWN: the graph weighs a fix by it).
    :class:`~randt.core.errors.BadMessageError` ``malformed`` or ``invalid_field`` for what cannot be one."""
    msg = _deserialize(cdr, NAV_SAT_FIX)
    stamp_ns = _stamp_ns(msg)
    if int(msg.status.status) < 0 or int(msg.position_covariance_type) == 0:
        return stamp_ns, None
    lat, lon, alt = float(msg.latitude), float(msg.longitude), float(msg.altitude)
    cov = np.asarray(msg.position_covariance, dtype=np.float64).reshape(3, 3)
    cov = 0.5 * (cov + cov.T)
    if not (abs(lat) <= 90 and abs(lon) <= 180 and np.isfinite(alt) and np.all(np.isfinite(cov))):
        raise BadMessageError(
            f"NavSatFix at {lat}, {lon}, {alt}: not a position", code=ErrorCode.INVALID_FIELD
        )
    if np.linalg.eigvalsh(cov).min() <= 0:
        raise BadMessageError(
            "NavSatFix: position_covariance is not positive definite", code=ErrorCode.INVALID_FIELD
        )
    return stamp_ns, GnssFix(lat, lon, alt, tuple(cov.ravel().tolist()))


def read_point_stamped(cdr: bytes) -> tuple[int, str, np.ndarray]:
    """``(stamp ns, frame_id, point (3,))`` of a ``geometry_msgs/msg/PointStamped``
    (:class:`~randt.core.errors.BadMessageError` for what cannot be one)."""
    msg = _deserialize(cdr, POINT_STAMPED)
    point = np.array([msg.point.x, msg.point.y, msg.point.z], dtype=np.float64)
    if not np.all(np.isfinite(point)):
        raise BadMessageError("PointStamped: the point is not finite", code=ErrorCode.INVALID_FIELD)
    return _stamp_ns(msg), str(msg.header.frame_id), point


def pointcloud2_cdr(stamp_ns: int, frame_id: str, xyz: np.ndarray, intensity: np.ndarray | None) -> bytes:
    """``sensor_msgs/msg/PointCloud2`` CDR of points (float32 x, y, z and intensity, 16 bytes a
    point, unorganized, little-endian): the layout every ROS 2 point cloud consumer reads."""
    types = typestore().types
    n = len(xyz)
    rows = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    rows["x"], rows["y"], rows["z"] = np.asarray(xyz, dtype=np.float32).T
    rows["intensity"] = 0.0 if intensity is None else intensity
    field = types["sensor_msgs/msg/PointField"]
    msg = types[POINTCLOUD2](
        header=_header(stamp_ns, frame_id),
        height=1,
        width=n,
        fields=[
            field(name=c, offset=4 * i, datatype=7, count=1)
            for i, c in enumerate(("x", "y", "z", "intensity"))
        ],
        is_bigendian=False,
        point_step=16,
        row_step=16 * n,
        data=rows.view(np.uint8),
        is_dense=True,
    )
    return bytes(typestore().serialize_cdr(msg, POINTCLOUD2))


def _header(stamp_ns: int, frame_id: str) -> Any:
    types = typestore().types
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


def _pose(T: np.ndarray) -> Any:
    types = typestore().types
    x, y, z = (float(v) for v in T[:3, 3])
    qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )


def odometry_cdr(pose: PoseMessage, *, frame_id: str, child_frame_id: str) -> bytes:
    """A pose answer as ``nav_msgs/msg/Odometry`` CDR: the scan's stamp, the pose of
    ``child_frame_id`` (the sensor) in ``frame_id``, the matcher's covariance (x, y, z, rotation
    about x, y, z, as ROS orders it; all zero when the matcher gave none) and a zero twist with an
    unknown covariance (-1 first, REP 145's convention: the service estimates no velocity)."""
    types = typestore().types
    T = np.asarray(pose.pose, dtype=np.float64).reshape(4, 4)
    cov = np.zeros(36) if pose.covariance is None else np.asarray(pose.covariance, dtype=np.float64)
    twist_cov = np.zeros(36)
    twist_cov[0] = -1.0
    zero = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    msg = types[ODOMETRY](
        header=_header(pose.stamp_ns, frame_id),
        child_frame_id=child_frame_id,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(T), covariance=cov),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=twist_cov
        ),
    )
    return bytes(typestore().serialize_cdr(msg, ODOMETRY))


def transform_cdr(stamp_ns: int, T: np.ndarray, *, frame_id: str, child_frame_id: str) -> bytes:
    """``geometry_msgs/msg/TransformStamped`` CDR: ``child_frame_id`` in ``frame_id`` is ``T``."""
    types = typestore().types
    p = _pose(np.asarray(T, dtype=np.float64))
    msg = types[TRANSFORM_STAMPED](
        header=_header(stamp_ns, frame_id),
        child_frame_id=child_frame_id,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=p.position.x, y=p.position.y, z=p.position.z),
            rotation=p.orientation,
        ),
    )
    return bytes(typestore().serialize_cdr(msg, TRANSFORM_STAMPED))


def string_cdr(payload: dict[str, Any]) -> bytes:
    """``std_msgs/msg/String`` CDR holding ``payload`` as one line of JSON."""
    text = json.dumps(payload, separators=(",", ":"), sort_keys=True)
    return bytes(typestore().serialize_cdr(typestore().types[STRING](data=text), STRING))
