"""rmw_zenoh's format (wire/rmw_zenoh.py) against what its design document and sources say
(docs/rmw_zenoh.md, where each example comes from), against rosbags' type hashes and against
zenoh's own serializer (zenoh.ext), the one rmw_zenoh's C++ attachment code uses."""

from __future__ import annotations

import struct

import pytest
import zenoh.ext as zext

from randt.core.errors import BadMessageError
from randt.wire.rmw_zenoh import (
    HUMBLE_TYPE_HASH,
    Attachment,
    LivelinessToken,
    Qos,
    dds_type_name,
    decode_attachment,
    encode_attachment,
    endpoint_tokens,
    liveliness_token,
    parse_liveliness_token,
    parse_topic_key,
    ros_type_name,
    topic_key,
)

POINTCLOUD2_HASH = "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"  # design.md


def test_topic_keys_are_rmw_zenohs() -> None:
    key = topic_key(0, "/robot1/lidar/points", "sensor_msgs/msg/PointCloud2", POINTCLOUD2_HASH)
    assert key == f"0/robot1/lidar/points/sensor_msgs::msg::dds_::PointCloud2_/{POINTCLOUD2_HASH}"
    # design.md's examples: a topic at the root, and Humble's placeholder for the hash
    assert topic_key(0, "/chatter", "std_msgs/msg/String", STRING_HASH) == (
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    )
    humble = parse_topic_key("0/chatter/std_msgs::msg::dds_::String_/TypeHashNotSupported")
    assert humble.type_hash == HUMBLE_TYPE_HASH and humble.topic == "/chatter"
    back = parse_topic_key(key)
    assert (back.domain, back.topic, back.ros_type, back.type_hash) == (
        0, "/robot1/lidar/points", "sensor_msgs/msg/PointCloud2", POINTCLOUD2_HASH,
    )  # fmt: skip
    assert str(back) == key
    assert ros_type_name(dds_type_name("nav_msgs/msg/Odometry")) == "nav_msgs/msg/Odometry"
    for bad in ("randt/fleet/car/scan", "x/a/sensor_msgs::msg::dds_::PointCloud2_/RIHS01_00", "0/a/b/c"):
        with pytest.raises(BadMessageError) as info:
            parse_topic_key(bad)
        assert info.value.code == "invalid_field"


def test_the_type_hashes_are_rosbags_own() -> None:
    """The hash chunk is REP-2011's RIHS01 of the type: computed by rosbags (independent of us)."""
    rosbags = pytest.importorskip("rosbags.typesys")
    store = rosbags.get_typestore(rosbags.Stores.ROS2_JAZZY)
    assert store.hash_rihs01("sensor_msgs/msg/PointCloud2") == POINTCLOUD2_HASH
    assert store.hash_rihs01("std_msgs/msg/String") == STRING_HASH


def test_the_attachment_is_zenohs_serialization_of_seq_timestamp_and_gid() -> None:
    gid = bytes(range(16))
    ours = encode_attachment(Attachment(1, 1_795_811_698_150_175_600, gid))
    theirs = zext.z_serialize((zext.Int64(1), zext.Int64(1_795_811_698_150_175_600), gid)).to_bytes()
    assert ours == theirs and len(ours) == 33 and ours[16] == 0x10
    assert decode_attachment(theirs) == Attachment(1, 1_795_811_698_150_175_600, gid)
    # Jazzy 0.2.0-0.2.3: string keys before each value (77 bytes)
    older = zext.z_serialize(
        ("sequence_number", zext.Int64(7), "source_timestamp", zext.Int64(-5), "source_gid", gid)
    ).to_bytes()
    assert len(older) == 77 and decode_attachment(older) == Attachment(7, -5, gid)
    with pytest.raises(BadMessageError) as info:
        decode_attachment(None)  # a ROS 2 subscriber drops such a sample
    assert info.value.code == "missing_field"
    renamed = older.replace(b"source_gid", b"source_xid")  # format B with a key out of place
    for bad in (b"", ours[:32], ours + b"\x00", struct.pack("<qqB", 1, 2, 15) + gid, renamed):
        with pytest.raises(BadMessageError, match="attachment"):
            decode_attachment(bad)


def test_liveliness_tokens_and_their_qos_chunk() -> None:
    # design.md's QoS examples: depth 10 (listener), sensor data, transient local depth 1
    assert Qos(depth=10).keyexpr() == "::,10:,:,:,,"
    assert Qos(reliability=2, depth=5).keyexpr() == "2::,5:,:,:,,"
    assert Qos(durability=1, depth=1).keyexpr() == ":1:,1:,:,:,,"
    assert Qos().keyexpr() == "::,:,:,:,,"
    zid = "aac3178e146ba6f1fc6e6a4085e77f21"
    token = liveliness_token(
        domain=0, zid=zid, node_id=0, entity_id=3, kind="MP", namespace="/robot1", node_name="lidar_driver",
        topic="/robot1/lidar/points", ros_type="sensor_msgs/msg/PointCloud2", type_hash=POINTCLOUD2_HASH,
        qos=Qos(reliability=2, depth=5),
    )  # fmt: skip
    assert token == (
        f"@ros2_lv/0/{zid}/0/3/MP/%/%robot1/lidar_driver/%robot1%lidar%points/"
        f"sensor_msgs::msg::dds_::PointCloud2_/{POINTCLOUD2_HASH}/2::,5:,:,:,,"
    )
    node = liveliness_token(
        domain=0, zid=zid, node_id=0, entity_id=0, kind="NN", namespace="/", node_name="n"
    )
    assert node == f"@ros2_lv/0/{zid}/0/0/NN/%/%/n"
    with pytest.raises(ValueError, match="needs its topic"):
        liveliness_token(domain=0, zid=zid, node_id=0, entity_id=1, kind="MS", namespace="/", node_name="n")


def test_liveliness_tokens_read_back_and_the_publishers_selector_matches_them() -> None:
    """design.md's PointCloud2 publisher token reads back into its parts (names unmangled); ours
    round-trip; Humble's placeholder hash reads; what is not a token is ``invalid_field``; the
    selector the service subscribes with matches every PointCloud2 publisher's token and only those."""
    import zenoh

    zid = "aac3178e146ba6f1fc6e6a4085e77f21"
    design = (
        f"@ros2_lv/0/{zid}/0/3/MP/%/%robot1/lidar_driver/%robot1%lidar%points/"
        f"sensor_msgs::msg::dds_::PointCloud2_/{POINTCLOUD2_HASH}/2::,5:,:,:,,"
    )
    token = parse_liveliness_token(design)
    assert token == LivelinessToken(
        0, zid, 0, 3, "MP", "/", "/robot1", "lidar_driver",
        "/robot1/lidar/points", "sensor_msgs/msg/PointCloud2", POINTCLOUD2_HASH, "2::,5:,:,:,,",
    )  # fmt: skip
    assert token.node == "/robot1/lidar_driver"
    ours = liveliness_token(
        domain=7, zid=zid, node_id=1, entity_id=9, kind="MS", namespace="/fleet/car_3", node_name="n",
        topic="/fleet/car_3/velodyne_points", ros_type="sensor_msgs/msg/PointCloud2",
        type_hash=HUMBLE_TYPE_HASH,
    )  # fmt: skip
    back = parse_liveliness_token(ours)
    assert (back.domain, back.kind, back.namespace, back.topic, back.type_hash) == (
        7, "MS", "/fleet/car_3", "/fleet/car_3/velodyne_points", HUMBLE_TYPE_HASH,
    )  # fmt: skip
    node = parse_liveliness_token(f"@ros2_lv/0/{zid}/0/0/NN/%/%/n")
    assert (node.kind, node.node, node.topic) == ("NN", "/n", None)
    for bad in (
        "@ros2_lv/0/z/0/0/NN/%/%",  # too few parts
        "@ros2_lv/x/z/0/0/NN/%/%/n",  # a domain that is not a number
        "@ros2_lv/0/z/0/0/XX/%/%/n",  # no such kind
        f"@ros2_lv/0/{zid}/0/3/MP/%/%robot1/lidar_driver/%robot1%lidar%points",  # an endpoint cut short
        design.replace(POINTCLOUD2_HASH, "RIHS01_00"),
        design.replace("@ros2_lv", "@other"),
    ):
        with pytest.raises(BadMessageError) as info:
            parse_liveliness_token(bad)
        assert info.value.code == "invalid_field"
    selector = zenoh.KeyExpr(endpoint_tokens(0, "MP", "sensor_msgs/msg/PointCloud2"))
    assert selector.intersects(zenoh.KeyExpr(design))
    for other in (design.replace("/MP/", "/MS/"), design.replace("@ros2_lv/0/", "@ros2_lv/1/"), ours):
        assert not selector.intersects(zenoh.KeyExpr(other)), other
    string = design.replace("sensor_msgs::msg::dds_::PointCloud2_", "std_msgs::msg::dds_::String_")
    assert not selector.intersects(zenoh.KeyExpr(string))
