"""Decode benchmark: a ROS 2 ``sensor_msgs/msg/PointCloud2`` against our raw v1 scan of the same sweep.

Run from the repository root (no test dependencies; ``rosbags``, the ``ros2`` extra, for CDR)::

    python bench/decode.py [--frames 11] [--repeat 30] [--markdown]

Each KITTI 00 sweep (frames 0-10, about 121k points, real; per-point times from the azimuth, as
``bench/link.py`` derives them) is encoded once both ways, as a vehicle would send it:

* **v1 raw**: our full scan message (float32 x, y, z, intensity, float32 time offsets;
  ``randt.wire.messages.scan_from_arrays`` + ``encode``), decoded as a matcher process does
  (``randt.service.matchers.decoded_sweep``: msgpack, validation, the float32 views).
* **PointCloud2**: the CDR bytes an rmw_zenoh publisher puts in a sample (4-byte encapsulation
  header, then the message; float32 x, y, z, intensity and an Ouster-style uint32 ``t`` in
  nanoseconds, 20 bytes a point; ``rosbags``' Jazzy type store), as the service's ROS 2 bridge
  hands it on (``randt.wire.ros2.Ros2Scan``), decoded as the service does: the matcher process's
  ``decoded_sweep`` (``randt.wire.ros2.sweep_arrays``: ``rosbags``' ``deserialize_cdr``, then
  ``randt.core.io.pointcloud2.pointcloud2_arrays``: float32 x, y, z as a view of the message's bytes,
  intensity, time offsets from the earliest point, what the matcher takes from a v1 scan).

Each is timed twice: the matcher's decode alone, and with the intake's header read before it
(``decode_scan_header``: a v1 scan validated whole; ``randt.wire.ros2.scan_header``: the CDR
deserialized and the cloud's layout checked), which every scan also costs.

The decodes are interleaved (one of each, sweep after sweep, ``--repeat`` rounds), single-threaded;
per decode: mean, median and max ms over all of them, and the ratio of the means. Issue 34's
target: the PointCloud2 decode costs no more than the v1 one (ratio <= 1). Both must give the same
points (checked: equal to the float32 bit).
"""

from __future__ import annotations

import argparse
import datetime
import shlex
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

import common
import numpy as np
from common import git_line, heading, machine_line, table, version

from randt.core.datasets import open_sequence
from randt.core.shared_data import data_root
from randt.service.matchers import decoded_sweep
from randt.wire.messages import WireLimits, decode_scan_header, encode, scan_from_arrays
from randt.wire.ros2 import Ros2Scan, scan_header

del common

PERIOD_S = 0.1


def _typestore() -> object:
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        sys.exit("bench/decode.py needs rosbags: pip install 'randt-fleet[ros2]'")
    return get_typestore(Stores.ROS2_JAZZY)


def pointcloud2_cdr(
    store: object, xyz: np.ndarray, intensity: np.ndarray, t_ns: np.ndarray, stamp_ns: int
) -> bytes:
    """The CDR bytes (with the encapsulation header) of a PointCloud2 of these columns."""
    types = store.types  # type: ignore[attr-defined]
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("t", "<u4")])
    rows = np.empty(len(xyz), dtype=dtype)
    rows["x"], rows["y"], rows["z"], rows["intensity"], rows["t"] = (
        xyz[:, 0],
        xyz[:, 1],
        xyz[:, 2],
        intensity,
        t_ns,
    )
    field = types["sensor_msgs/msg/PointField"]
    offsets = [0, 4, 8, 12, 16]  # (the packed dtype above)
    fields = [
        field(name=n, offset=o, datatype=d, count=1)
        for n, o, d in zip(("x", "y", "z", "intensity", "t"), offsets, (7, 7, 7, 7, 6), strict=True)
    ]
    sec, nsec = divmod(stamp_ns, 10**9)
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id="lidar"
    )
    msg = types["sensor_msgs/msg/PointCloud2"](
        header=header, height=1, width=len(xyz), fields=fields, is_bigendian=False,
        point_step=dtype.itemsize, row_step=dtype.itemsize * len(xyz),
        data=rows.view(np.uint8), is_dense=True,
    )  # fmt: skip
    return bytes(store.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))  # type: ignore[attr-defined]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="decode.py", description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=11, help="KITTI 00 frames (from 0)")
    parser.add_argument("--repeat", type=int, default=30, help="rounds over the frames")
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args(argv)
    store = _typestore()
    seq = open_sequence(data_root() / "kitti00")
    v1: list[bytes] = []
    cdr: list[bytes] = []
    n_points = []
    for i, cloud in enumerate(seq):
        if i >= args.frames:
            break
        xyz = np.ascontiguousarray(cloud.xyz, dtype=np.float32)
        assert cloud.intensity is not None  # KITTI's .bin has it
        intensity = cloud.intensity.astype(np.float32)
        t = PERIOD_S * 0.5 * (-np.arctan2(xyz[:, 1], xyz[:, 0]) / np.pi + 1.0)  # bench/link.py's
        t_ns = np.round(t * 1e9).astype(np.uint32)
        t_ns -= t_ns.min()
        stamp_ns = 1_000_000_000 + i * 100_000_000
        v1.append(
            encode(
                scan_from_arrays(
                    "car",
                    "d1",
                    i,
                    stamp_ns,
                    xyz,
                    intensity=intensity,
                    time_offset_s=(t_ns * 1e-9).astype(np.float32),
                )
            )
        )
        cdr.append(pointcloud2_cdr(store, xyz, intensity, t_ns, stamp_ns))
        n_points.append(len(xyz))

    ros = [Ros2Scan(c, "/robot7/lidar/points", "robot7", "ab" * 16, i) for i, c in enumerate(cdr)]
    limits = WireLimits()

    def decode_v1(payload: Any) -> np.ndarray:
        return decoded_sweep(payload, limits)[0]

    def decode_ros(scan: Any) -> np.ndarray:
        return decoded_sweep(scan, limits)[0]

    def both_v1(payload: Any) -> np.ndarray:
        decode_scan_header(payload, limits)
        return decoded_sweep(payload, limits)[0]

    def both_ros(scan: Any) -> np.ndarray:
        scan_header(scan, limits)
        return decoded_sweep(scan, limits)[0]

    for a, b in zip(v1, ros, strict=True):  # the same points both ways
        np.testing.assert_array_equal(decode_v1(a), decode_ros(b))
    decoders: list[tuple[str, Callable[[Any], np.ndarray], list[Any]]] = [
        ("v1 raw scan: the matcher's decode (decoded_sweep)", decode_v1, v1),
        (
            "PointCloud2 CDR: the matcher's decode (decoded_sweep: randt.wire.ros2.sweep_arrays)",
            decode_ros,
            ros,
        ),
        ("v1 raw scan: intake header + matcher decode", both_v1, v1),
        ("PointCloud2 CDR: intake header (randt.wire.ros2.scan_header) + matcher decode", both_ros, ros),
    ]
    times: dict[str, list[float]] = {name: [] for name, _, _ in decoders}
    for _ in range(args.repeat):
        for k in range(len(v1)):
            for name, decode, payloads in decoders:
                t0 = time.perf_counter()
                decode(payloads[k])
                times[name].append(time.perf_counter() - t0)
    rows = []
    for name, _, payloads in decoders:
        ms = [t * 1e3 for t in times[name]]
        size = statistics.fmean(len(p) for p in payloads) / 1e6  # (a Ros2Scan's len is its CDR's)
        rows.append(
            [
                name,
                f"{size:.2f}",
                f"{statistics.fmean(ms):.2f}",
                f"{statistics.median(ms):.2f}",
                f"{max(ms):.2f}",
            ]
        )
    ratio = statistics.fmean(times[decoders[1][0]]) / statistics.fmean(times[decoders[0][0]])
    ratio_both = statistics.fmean(times[decoders[3][0]]) / statistics.fmean(times[decoders[2][0]])
    title = (
        f"Decoding a sweep: PointCloud2 against our v1 scan ({len(v1)} KITTI 00 sweeps, "
        f"mean {statistics.fmean(n_points):,.0f} points, {args.repeat} rounds)"
    )
    print(heading(title, args.markdown))
    print(table(["decode", "MB a sweep", "mean ms", "median ms", "max ms"], rows, args.markdown))
    print(
        f"\nPointCloud2 / v1 mean: {ratio:.2f}x the matcher's decode, {ratio_both:.2f}x with the "
        "intake's (issue 34: at most 1)"
    )
    print(f"\n{machine_line({'rosbags': version('rosbags')})}")
    command = shlex.join(argv if argv is not None else sys.argv[1:])
    print(
        f"{git_line()}; run on {datetime.date.today().isoformat()}; command: python bench/decode.py {command}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
