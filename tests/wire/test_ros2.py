"""randt.wire.ros2: a PointCloud2 sample as a scan, and the answers as ROS 2 messages, checked with
rosbags (the CDR) and against our own v1 scan of the same sweep (the points the matcher gets)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from randt.core.errors import BadMessageError
from randt.service.matchers import decoded_sweep
from randt.wire.messages import PoseMessage, WireLimits, encode, matrix_to_pose, scan_from_arrays
from randt.wire.rmw_zenoh import HUMBLE_TYPE_HASH
from randt.wire.ros2 import (
    NAV_SAT_FIX,
    ODOMETRY,
    POINTCLOUD2,
    Ros2Scan,
    odometry_cdr,
    read_navsatfix,
    scan_header,
    string_cdr,
    transform_cdr,
    type_hash,
    typestore,
)
from tests.ros2_sdk import cloud_fields, header

pytest.importorskip("rosbags")  # (the test extra has it: CI fails on a skip there)


def _cloud_cdr(
    xyz: np.ndarray, intensity: np.ndarray, offsets: np.ndarray, stamp_ns: int, **over: object
) -> bytes:
    types = typestore().types
    fields = {"header": header(types, stamp_ns, "lidar"), **cloud_fields(types, xyz, intensity, offsets)}
    fields.update(over)
    return bytes(typestore().serialize_cdr(types[POINTCLOUD2](**fields), POINTCLOUD2))


@pytest.fixture
def sweep() -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-40, 40, (5000, 3)).astype(np.float32)
    intensity = rng.uniform(0, 1, 5000).astype(np.float32)
    offsets = np.sort(rng.uniform(0, 0.1, 5000)).astype(np.float32)
    offsets -= offsets.min()
    return xyz, intensity, offsets, 1_700_000_000_123_456_789


def test_a_pointcloud2_decodes_to_the_points_of_our_v1_scan(sweep) -> None:
    """The matcher gets the same float32 points, offsets, intensity and stamp either way."""
    xyz, intensity, offsets, stamp_ns = sweep
    scan = Ros2Scan(_cloud_cdr(xyz, intensity, offsets, stamp_ns), "/r7/lidar/points", "r7", "ab" * 16, 4)
    header = scan_header(scan, WireLimits())
    assert (header.vehicle, header.session, header.seq, header.stamp_ns, header.n_points) == (
        "r7", "ab" * 16, 4, stamp_ns, 5000,
    )  # fmt: skip
    ours = decoded_sweep(encode(scan_from_arrays("r7", "d", 4, stamp_ns, xyz, intensity, offsets)), None)
    theirs = decoded_sweep(scan, None)
    for a, b in zip(ours, theirs, strict=True):
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
        else:
            assert a == b
    assert len(scan) == len(scan.cdr)


@pytest.mark.parametrize(
    ("change", "code", "words"),
    [
        ({"cdr": b"\x01\x02\x03"}, "malformed", "not CDR"),
        ({"cdr": b"\x00\x01\x00\x00" + b"\x07" * 30}, "malformed", "does not decode"),
        ({"fields": []}, "invalid_points", "without field(s) x, y, z"),
        ({"data": np.zeros(100, np.uint8)}, "invalid_points", "holds only 100 bytes"),
        ({"width": 0, "row_step": 0, "data": np.zeros(0, np.uint8)}, "empty_scan", "without points"),
        ({"fields": "big-endian"}, "", ""),
    ],
)
def test_a_bad_pointcloud2_is_refused_with_its_code(sweep, change, code, words) -> None:
    xyz, intensity, offsets, stamp_ns = sweep
    if change.get("fields") == "big-endian":  # (a valid variant: read, not refused)
        cdr = _cloud_cdr(xyz, intensity, offsets, stamp_ns, is_bigendian=True)
        assert scan_header(Ros2Scan(cdr, "/t", "v", "s", 1), WireLimits()).n_points == 5000
        return
    cdr = change.pop("cdr", None) or _cloud_cdr(xyz, intensity, offsets, stamp_ns, **change)
    with pytest.raises(BadMessageError, match=words.replace("(", r"\(").replace(")", r"\)")) as err:
        scan_header(Ros2Scan(cdr, "/t", "v", "s", 1), WireLimits())
    assert err.value.code == code


def test_too_many_points_and_a_sweep_of_wrong_time_units_are_refused(sweep) -> None:
    xyz, intensity, offsets, stamp_ns = sweep
    scan = Ros2Scan(_cloud_cdr(xyz, intensity, offsets, stamp_ns), "/t", "v", "s", 1)
    with pytest.raises(BadMessageError, match="more than the service takes") as err:
        scan_header(scan, WireLimits(max_points=4999))
    assert err.value.code == "too_many_points"
    slow = Ros2Scan(_cloud_cdr(xyz, intensity, offsets * 1000, stamp_ns), "/t", "v", "s", 1)
    scan_header(slow, WireLimits())  # (the layout is fine: only reading the times tells)
    with pytest.raises(BadMessageError, match="spans 100 s") as err:
        decoded_sweep(slow, None)
    assert err.value.code == "invalid_points"


def test_odometry_and_corrections_read_back_with_rosbags() -> None:
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 deg about z
    T[:3, 3] = [1.5, -2.0, 0.25]
    cov = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6])
    pose = PoseMessage(
        vehicle="r7", session="s1", seq=3, stamp_ns=1_700_000_001_000_000_002, pose=matrix_to_pose(T),
        fitness=1.0, inlier_ratio=0.9, converged=True, status="ok", covariance=tuple(cov.reshape(-1)),
        latency_ms=5.0, map="m",
    )  # fmt: skip
    msg = typestore().deserialize_cdr(odometry_cdr(pose, frame_id="odom", child_frame_id="lidar"), ODOMETRY)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_001, 2)
    assert (msg.header.frame_id, msg.child_frame_id) == ("odom", "lidar")
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    np.testing.assert_allclose([p.x, p.y, p.z], [1.5, -2.0, 0.25])
    np.testing.assert_allclose([q.x, q.y, q.z, q.w], [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_array_equal(msg.pose.covariance, cov.reshape(-1))
    assert msg.twist.covariance[0] == -1.0  # (no velocity estimated: REP 145's unknown)
    tf = typestore().deserialize_cdr(
        transform_cdr(5, T, frame_id="map", child_frame_id="odom"), "geometry_msgs/msg/TransformStamped"
    )
    assert (tf.header.frame_id, tf.child_frame_id, tf.header.stamp.nanosec) == ("map", "odom", 5)
    np.testing.assert_allclose([tf.transform.translation.x, tf.transform.rotation.w], [1.5, np.sqrt(0.5)])
    text = typestore().deserialize_cdr(string_cdr({"seq": 3, "status": "lost"}), "std_msgs/msg/String")
    assert json.loads(text.data) == {"seq": 3, "status": "lost"}


def test_answers_use_the_type_hash_the_robot_used() -> None:
    assert type_hash(ODOMETRY) == typestore().hash_rihs01(ODOMETRY)
    assert type_hash(ODOMETRY, like="RIHS01_" + "0" * 64) == type_hash(ODOMETRY)
    assert type_hash(ODOMETRY, like=HUMBLE_TYPE_HASH) == HUMBLE_TYPE_HASH


def _navsatfix(stamp_ns: int, *, status: int = 0, cov_type: int = 2, cov: np.ndarray | None = None) -> bytes:
    types = typestore().types
    sec, nanosec = divmod(stamp_ns, 10**9)
    msg = types["sensor_msgs/msg/NavSatFix"](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id="gnss"
        ),
        status=types["sensor_msgs/msg/NavSatStatus"](status=status, service=1),
        latitude=48.137,
        longitude=11.575,
        altitude=520.5,
        position_covariance=np.diag([0.04, 0.09, 0.25]).ravel() if cov is None else cov.ravel(),
        position_covariance_type=cov_type,
    )
    return bytes(typestore().serialize_cdr(msg, NAV_SAT_FIX))


def test_a_navsatfix_is_a_position_with_its_covariance_or_none() -> None:
    stamp, fix = read_navsatfix(_navsatfix(1_700_000_000_500_000_000))
    assert stamp == 1_700_000_000_500_000_000 and fix is not None
    assert (fix.latitude, fix.longitude, fix.altitude) == (48.137, 11.575, 520.5)
    np.testing.assert_array_equal(fix.covariance_matrix(), np.diag([0.04, 0.09, 0.25]))
    assert read_navsatfix(_navsatfix(1, status=-1))[1] is None  # STATUS_NO_FIX
    assert read_navsatfix(_navsatfix(1, cov_type=0))[1] is None  # COVARIANCE_TYPE_UNKNOWN
    with pytest.raises(BadMessageError, match="not positive definite") as err:
        read_navsatfix(_navsatfix(1, cov=np.zeros((3, 3))))
    assert err.value.code == "invalid_field"
    with pytest.raises(BadMessageError, match="does not decode"):
        read_navsatfix(b"\x00\x01\x00\x00\x01")
