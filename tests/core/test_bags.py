"""ROS bags (randt.core.io.bags) and PointCloud2 decoding (randt.core.io.pointcloud2), against bags that
``rosbags`` wrote from the real KITTI 00 sweeps (tests/ros_bags.py)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from randt.core.datasets import open_scans
from randt.core.errors import FormatError
from randt.core.io import read_cloud
from randt.core.io.bags import open_bag
from randt.core.io.pointcloud2 import PointCloud2Fields, PointField, decode_pointcloud2
from tests.data import require_data
from tests.ros_bags import KINDS, TOPIC, azimuth_offsets, kitti_frames, write_bag

N = 11


@pytest.fixture(scope="module")
def kitti() -> tuple[Path, list[np.ndarray], list[np.ndarray], np.ndarray]:
    root = require_data("kitti00/velodyne/000010.bin", "kitti00/times.txt") / "kitti00"
    return (root, *kitti_frames(root, N))


@pytest.mark.parametrize("kind", KINDS)
def test_a_bag_gives_back_the_sweeps_it_was_written_from(kind, kitti, tmp_path) -> None:
    """Every sweep's points and intensities bit for bit (float32 both ways), and the record times
    as the sequence's stamps, within a nanosecond of KITTI's times.txt."""
    root, xyz, intensity, times = kitti
    bag = write_bag(tmp_path / "drive", kind, xyz, intensity, times)
    seq = open_scans(bag)
    assert len(seq) == N and seq.layout == ("rosbag1" if kind == "rosbag1" else "rosbag2")
    assert seq.stamps_s is not None
    np.testing.assert_allclose(seq.stamps_s, times - times[0], atol=2e-9)
    for k in (0, 5, 10):
        cloud = seq.read(k)
        reference = read_cloud(root / f"velodyne/{k:06d}.bin")
        np.testing.assert_array_equal(cloud.xyz, reference.xyz)
        np.testing.assert_array_equal(cloud.intensity, reference.intensity)
        assert cloud.time_offset_s is None
    assert [len(c.xyz) for c in seq] == [len(p) for p in xyz]  # one pass, in order
    part = open_bag(bag, start=3, end=7)
    assert len(part) == 4
    np.testing.assert_array_equal(part.read(0).xyz, seq.read(3).xyz)
    assert [len(c.xyz) for c in part] == [len(p) for p in xyz[3:7]]  # the slice, in one pass


@pytest.mark.parametrize("driver", ["ouster", "velodyne", "hesai"])
def test_per_point_times_in_each_drivers_convention(driver, kitti, tmp_path) -> None:
    """Ouster's ``t`` (uint32 ns), Velodyne's ``time`` (float32 s, negative: from the stamp at
    the sweep's end) and Hesai's ``timestamp`` (float64 absolute s) all give the offsets from the
    sweep's first point: within 1 ns, 8 ns (float32 near -0.1 s: a 7.5 ns step) and 0.3 us
    (float64 near 1.7e9 s)."""
    _, xyz, intensity, times = kitti
    bag = write_bag(tmp_path / "drive", "mcap", xyz[:2], intensity[:2], times[:2], time_field=driver)
    cloud = open_bag(bag).read(1)
    expected = azimuth_offsets(xyz[1].astype(np.float64))
    expected -= expected.min()
    assert cloud.time_offset_s is not None
    tolerance = {"ouster": 1e-9, "velodyne": 8e-9, "hesai": 3e-7}[driver]
    np.testing.assert_allclose(cloud.time_offset_s, expected, atol=tolerance)
    assert 0.099 < cloud.time_offset_s.max() <= 0.1


@pytest.mark.parametrize("driver", ["ouster", "velodyne", "hesai"])
def test_argoverse2_sweeps_keep_their_per_point_offsets_through_a_bag(driver, tmp_path) -> None:
    """Argoverse 2's two real sweeps with their own per-point times (``<ts>_offset_ns.bin``, int64
    ns from the sweep's stamp), written in each driver's convention: read back as offsets from
    each sweep's first point, to the convention's resolution, with every point."""
    root = require_data("pairs/argoverse2/315966265259836000.bin") / "pairs/argoverse2"
    stamps = (315966265259836000, 315966265360032000)
    clouds = [read_cloud(root / f"{ts}.bin") for ts in stamps]
    offsets = [np.fromfile(root / f"{ts}_offset_ns.bin", "<i8") for ts in stamps]
    seconds = [(o - o.min()) * 1e-9 for o in offsets]
    assert all(0.09 < s.max() < 0.11 for s in seconds)  # (one 10 Hz sweep each)
    bag = write_bag(
        tmp_path / "av2", "mcap",
        [c.xyz.astype(np.float32) for c in clouds],
        [np.asarray(c.intensity, np.float32) for c in clouds],
        np.array([(ts - stamps[0]) * 1e-9 for ts in stamps]),
        time_field=driver, offsets_s=seconds,
    )  # fmt: skip
    tolerance = {"ouster": 1e-9, "velodyne": 8e-9, "hesai": 3e-7}[driver]
    for cloud, expected, read in zip(clouds, seconds, open_bag(bag), strict=True):
        assert read.time_offset_s is not None and len(read.xyz) == cloud.n_points > 90_000
        np.testing.assert_array_equal(read.xyz, cloud.xyz)
        np.testing.assert_allclose(read.time_offset_s, expected, atol=tolerance)


def test_the_topic_is_chosen_or_the_only_pointcloud2(kitti, tmp_path) -> None:
    _, xyz, intensity, times = kitti
    two = write_bag(
        tmp_path / "two",
        "sqlite3",
        xyz[:2],
        intensity[:2],
        times[:2],
        extra_topics=[
            ("/robot7/front/points", "sensor_msgs/msg/PointCloud2"),
            ("/imu", "sensor_msgs/msg/Imu"),
        ],
    )
    with pytest.raises(FormatError, match=r"choose a PointCloud2 topic with --topic .*/robot7/front/points"):
        open_scans(two)
    assert len(open_scans(two, topic=TOPIC)) == 2
    with pytest.raises(FormatError, match=r"/imu is sensor_msgs/msg/Imu, not sensor_msgs/msg/PointCloud2"):
        open_scans(two, topic="/imu")
    with pytest.raises(FormatError, match="no topic /nope"):
        open_scans(two, topic="/nope")
    one = write_bag(tmp_path / "one", "sqlite3", xyz[:1], intensity[:1], times[:1])
    assert open_scans(next(one.glob("*.db3"))).root == one  # a file of the bag: its folder
    with pytest.raises(FormatError, match="--topic is for ROS bags"):
        open_scans(tmp_path, topic=TOPIC)
    not_a_bag = tmp_path / "x.bag"
    not_a_bag.write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 64)
    with pytest.raises(FormatError, match="unreadable bag"):
        open_scans(not_a_bag)


def test_without_rosbags_a_bag_is_refused_with_what_to_install(kitti, tmp_path, monkeypatch) -> None:
    _, xyz, intensity, times = kitti
    bag = write_bag(tmp_path / "drive", "sqlite3", xyz[:1], intensity[:1], times[:1])
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # import fails, as when not installed
    with pytest.raises(FormatError, match=r"needs the rosbags package: pip install 'randt-fleet\[ros2\]'"):
        open_scans(bag)


def _cloud(
    fields, rows: np.ndarray, *, big: bool = False, pad: int = 0, height: int = 1
) -> PointCloud2Fields:
    step = rows.dtype.itemsize
    width = len(rows) // height
    data = rows.view(np.uint8).reshape(height, width * step)
    data = np.hstack([data, np.full((height, pad), 0xAB, np.uint8)]).reshape(-1)
    return PointCloud2Fields(height, width, tuple(fields), big, step, width * step + pad, data)


def test_decoding_reads_the_layout_not_a_fixed_one() -> None:
    """Big-endian words, padding inside a point and at each row's end, an organized cloud's
    missing returns (NaN) dropped with their intensities and times, x after y in the point."""
    rng = np.random.default_rng(3)
    n = 12
    for big in (False, True):
        e = ">" if big else "<"
        names, types = ["y", "x", "z", "intensity", "t"], ["f4", "f4", "f8", "u2", "u4"]
        offsets = [0, 4, 12, 20, 24]
        dtype = np.dtype(
            {"names": names, "formats": [e + t for t in types], "offsets": offsets, "itemsize": 32}
        )
        rows = np.zeros(n, dtype)
        xyz = rng.normal(size=(n, 3)) * 10
        rows["x"], rows["y"], rows["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        rows["intensity"] = np.arange(n)
        rows["t"] = 1000 + 100 * np.arange(n)
        rows["x"][[2, 7]] = np.nan
        codes = [7, 7, 8, 4, 6]  # sensor_msgs/PointField datatypes of the types above
        fields = [PointField(name, at, code) for name, at, code in zip(names, offsets, codes, strict=True)]
        cloud = decode_pointcloud2(_cloud(fields, rows, big=big, pad=8, height=3))
        keep = np.setdiff1d(np.arange(n), [2, 7])
        written = np.c_[xyz[:, 0].astype(np.float32), xyz[:, 1].astype(np.float32), xyz[:, 2]]
        np.testing.assert_array_equal(cloud.xyz, written[keep])
        np.testing.assert_array_equal(cloud.intensity, keep.astype(np.float32))
        assert cloud.time_offset_s is not None
        np.testing.assert_allclose(cloud.time_offset_s, 100e-9 * keep, atol=1e-15)


def test_the_services_arrays_are_float32_views_with_every_row() -> None:
    """``pointcloud2_arrays`` (what the ROS 2 ingest hands the matcher, as a v1 scan's decode):
    float32, x/y/z a view of the message's bytes in the drivers' packed layout (no copy of a
    120k-point sweep), non-finite rows kept for the matcher to drop and count, time offsets from
    the earliest point; any other layout is read as well, as a copy."""
    from randt.core.io.pointcloud2 import pointcloud2_arrays

    n = 10
    packed = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("t", "<u4")])
    rows = np.zeros(n, packed)
    rng = np.random.default_rng(5)
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    rows["x"], rows["y"], rows["z"] = xyz.T
    rows["x"][3] = np.nan
    rows["intensity"], rows["t"] = np.arange(n), 5_000 + 1_000 * np.arange(n)
    fields = [
        PointField(name, int(packed.fields[name][1]), code)
        for name, code in zip(packed.names or (), (7, 7, 7, 7, 6), strict=True)
    ]
    msg = _cloud(fields, rows)
    got, offsets, intensity = pointcloud2_arrays(msg)
    assert got.dtype == np.float32 and np.shares_memory(got, msg.data)
    np.testing.assert_array_equal(got[[0, 1, 2, 4]], xyz[[0, 1, 2, 4]])
    assert np.isnan(got[3, 0]) and len(got) == n
    assert offsets is not None and offsets.dtype == np.float32 and intensity is not None
    np.testing.assert_allclose(offsets, 1e-6 * np.arange(n), atol=1e-12)
    np.testing.assert_array_equal(intensity, np.arange(n, dtype=np.float32))
    # the file reader's view of the same message: float64, the NaN row dropped
    cloud = decode_pointcloud2(msg)
    np.testing.assert_array_equal(cloud.xyz, got[np.arange(n) != 3].astype(np.float64))
    # another layout (y before x, padding): the same values, copied
    other = np.dtype({"names": ["y", "x", "z"], "formats": ["<f4"] * 3, "offsets": [0, 4, 8], "itemsize": 16})
    rows2 = np.zeros(n, other)
    rows2["x"], rows2["y"], rows2["z"] = xyz.T
    msg2 = _cloud(
        [PointField("y", 0, 7), PointField("x", 4, 7), PointField("z", 8, 7)], rows2, pad=4, height=2
    )
    got2, no_times, no_intensity = pointcloud2_arrays(msg2)
    np.testing.assert_array_equal(got2, xyz)
    assert not np.shares_memory(got2, msg2.data) and no_times is None and no_intensity is None


def test_decoding_refuses_what_it_cannot_read_with_the_reason() -> None:
    rows = np.zeros(4, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("time", "<f4")]))
    xyz_fields = [PointField("x", 0, 7), PointField("y", 4, 7), PointField("z", 8, 7)]
    with pytest.raises(FormatError, match=r"without field\(s\) z \(fields: x, y\)"):
        decode_pointcloud2(_cloud(xyz_fields[:2], rows))
    with pytest.raises(FormatError, match="unknown datatype 9"):
        decode_pointcloud2(_cloud([*xyz_fields[:2], PointField("z", 8, 9)], rows))
    with pytest.raises(FormatError, match="at byte 14 does not fit a 16-byte point"):
        decode_pointcloud2(_cloud([*xyz_fields[:2], PointField("z", 14, 7)], rows))
    short = _cloud(xyz_fields, rows)
    with pytest.raises(FormatError, match="holds only 48 bytes"):
        decode_pointcloud2(PointCloud2Fields(1, 4, short.fields, False, 16, 64, bytes(short.data)[:48]))
    rows["time"] = [0.0, 0.05, 2.0, 0.1]  # seconds where the driver meant something else
    with pytest.raises(FormatError, match=r"'time' spans 2 s .*more than one sweep"):
        decode_pointcloud2(_cloud([*xyz_fields, PointField("time", 12, 7)], rows))


def test_randt_map_of_a_bag_equals_randt_map_of_the_kitti_folder(kitti, tmp_path) -> None:
    """The same 11 sweeps (float32 both), the same matcher: the same poses to the bit, and the same map."""
    from typer.testing import CliRunner

    from randt.cli.main import app

    root, xyz, intensity, times = kitti
    bag = write_bag(tmp_path / "drive", "mcap", xyz, intensity, times)
    runner = CliRunner()
    for src, out in ((root, tmp_path / "folder"), (bag, tmp_path / "bag")):
        r = runner.invoke(app, ["map", str(src), "--out", str(out), "--no-progress"])
        assert r.exit_code == 0, r.output
    a, b = np.loadtxt(tmp_path / "folder/poses_kitti.txt"), np.loadtxt(tmp_path / "bag/poses_kitti.txt")
    assert a.shape == (N, 12)
    np.testing.assert_array_equal(a, b)
    sa, sb = (json.loads((tmp_path / d / "summary.json").read_text())["map"] for d in ("folder", "bag"))
    assert sa["points"] == sb["points"] > 50_000 and sa["pdu"] == sb["pdu"]
