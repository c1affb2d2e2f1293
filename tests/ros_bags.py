"""ROS bags for the tests, written with ``rosbags`` (not our code) from the real KITTI 00 sweeps.

Each sweep becomes a ``sensor_msgs/msg/PointCloud2`` as a driver would publish it: float32 x, y, z,
intensity, and optionally a per-point time in one driver's convention; recorded at the sweep's
time from ``times.txt``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from randt.core.io import read_cloud

KINDS = ("sqlite3", "mcap", "rosbag1")
TOPIC = "/robot7/lidar/points"
#: Per-point time fields by driver: name, PointField datatype, numpy type, seconds per unit.
TIMES = {
    "ouster": ("t", 6, "<u4", 1e-9),  # uint32 ns from the sweep's start
    "velodyne": ("time", 7, "<f4", 1.0),  # float32 s from the message stamp (end of sweep)
    "hesai": ("timestamp", 8, "<f8", 1.0),  # float64 absolute s
}


def azimuth_offsets(xyz: np.ndarray, period_s: float = 0.1) -> np.ndarray:
    """A spinning sensor's per-point time from the sweep's start, from the azimuth."""
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    return (np.pi - az) / (2 * np.pi) * period_s


def kitti_frames(root: Path, n: int) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """The first ``n`` KITTI sweeps (float32 xyz, intensity) and their times (s)."""
    clouds = [read_cloud(root / f"velodyne/{k:06d}.bin") for k in range(n)]
    xyz = [c.xyz.astype(np.float32) for c in clouds]
    intensity = [np.asarray(c.intensity, dtype=np.float32) for c in clouds]
    times = np.loadtxt(root / "times.txt")[:n]
    return xyz, intensity, times


def write_bag(
    dst: Path,
    kind: str,
    xyz: Sequence[np.ndarray],
    intensity: Sequence[np.ndarray],
    times_s: np.ndarray,
    *,
    time_field: str | None = None,
    offsets_s: Sequence[np.ndarray] | None = None,
    topic: str = TOPIC,
    extra_topics: Sequence[tuple[str, str]] = (),
) -> Path:
    """A bag of ``kind`` (:data:`KINDS`) at ``dst`` (a folder for rosbag2, ``dst.bag`` for ROS 1);
    with ``time_field``, per-point times in that driver's convention, from ``offsets_s`` (each
    sweep's points' seconds from its start; default: from the azimuth); ``extra_topics``: (topic,
    message type) connections with no messages, to choose among."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = kind == "rosbag1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_JAZZY)
    base_ns = 1_700_000_000 * 10**9
    messages = []
    for k, (p, i) in enumerate(zip(xyz, intensity, strict=True)):
        t_ns = base_ns + round(float(times_s[k]) * 1e9)  # integer ns: a float64 of 1.7e9 s holds 0.24 us
        offsets = None if offsets_s is None else offsets_s[k]
        messages.append((t_ns, _cloud_message(store, p, i, t_ns, time_field, ros1, offsets)))
    typename = "sensor_msgs/msg/PointCloud2"
    writer: Any
    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        path, serialize = dst.with_suffix(".bag"), store.serialize_ros1
        writer = Writer1(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        path, serialize = dst, store.serialize_cdr
        writer = Writer(dst, version=9, storage_plugin=plugin)
    with writer as w:
        conn = w.add_connection(topic, typename, typestore=store)
        for other, other_type in extra_topics:
            w.add_connection(other, other_type, typestore=store)
        for t_ns, msg in messages:
            w.write(conn, t_ns, serialize(msg, typename))
    return path


def _cloud_message(
    store: object,
    xyz: np.ndarray,
    intensity: np.ndarray,
    t_ns: int,
    time_field: str | None,
    ros1: bool,
    offsets: np.ndarray | None = None,
) -> object:
    types = store.types  # type: ignore[attr-defined]
    PointField, Header, Time = (
        types["sensor_msgs/msg/PointField"],
        types["std_msgs/msg/Header"],
        types["builtin_interfaces/msg/Time"],
    )
    columns: list[tuple[str, int, str, np.ndarray]] = [
        ("x", 7, "<f4", xyz[:, 0]),
        ("y", 7, "<f4", xyz[:, 1]),
        ("z", 7, "<f4", xyz[:, 2]),
        ("intensity", 7, "<f4", intensity),
    ]
    if time_field is not None:
        name, datatype, np_type, unit = TIMES[time_field]
        offsets = azimuth_offsets(xyz.astype(np.float64)) if offsets is None else offsets
        values = {"ouster": offsets, "velodyne": offsets - 0.1, "hesai": t_ns * 1e-9 - 0.1 + offsets}[
            time_field
        ]
        columns.append((name, datatype, np_type, values / unit))
    dtype = np.dtype([(c[0], c[2]) for c in columns])
    table = np.zeros(len(xyz), dtype=dtype)
    for name, _, _, values in columns:
        table[name] = values
    fields, offset = [], 0
    for name, datatype, np_type, _ in columns:
        fields.append(PointField(name=name, offset=offset, datatype=datatype, count=1))
        offset += np.dtype(np_type).itemsize
    sec, nsec = divmod(t_ns, 10**9)
    header = (
        Header(seq=0, stamp=Time(sec=sec, nanosec=nsec), frame_id="lidar")
        if ros1
        else Header(stamp=Time(sec=sec, nanosec=nsec), frame_id="lidar")
    )
    return types["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=1,
        width=len(xyz),
        fields=fields,
        is_bigendian=False,
        point_step=dtype.itemsize,
        row_step=dtype.itemsize * len(xyz),
        data=table.view(np.uint8).reshape(-1),
        is_dense=True,
    )
