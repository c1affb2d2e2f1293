"""LiDAR sweeps from ROS bags: rosbag2 (sqlite3 or MCAP) and ROS 1 ``.bag`` files.

Reading is ``rosbags``' (pure Python, Apache-2.0; the optional extra ``randt-fleet[ros2]``):
:class:`~rosbags.highlevel.AnyReader` opens either kind, deserializes CDR or ROS 1 messages with
the type store the bag carries, and we decode each ``sensor_msgs/PointCloud2`` with
:func:`randt.core.io.pointcloud2.decode_pointcloud2` (points, intensity, per-point times).

A bag is given as its rosbag2 folder (the one with ``metadata.yaml``), a file inside it, or a
ROS 1 ``.bag`` file. The topic is ``topic`` or, when ``None``, the bag's only PointCloud2 topic.
A sweep's time is the bag's record time of its message (read once when the bag is opened; the
messages are deserialized only when read).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from randt.core.errors import FormatError, NotFoundError
from randt.core.io.clouds import PointCloud
from randt.core.io.pointcloud2 import decode_pointcloud2

__all__ = ["POINTCLOUD2", "BagSequence", "is_bag", "open_bag"]

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
_ROS1_SUFFIX = ".bag"
_ROS2_FILES = (".db3", ".mcap")


def is_bag(path: str | Path) -> bool:
    """Whether ``path`` is a ROS 1 bag file, a rosbag2 folder or a file of one."""
    p = Path(path)
    if p.is_file():
        return p.suffix.lower() == _ROS1_SUFFIX or (
            p.suffix.lower() in _ROS2_FILES and (p.parent / "metadata.yaml").is_file()
        )
    return p.is_dir() and (p / "metadata.yaml").is_file()


@dataclass(frozen=True)
class BagSequence:
    """One PointCloud2 topic of a bag, as a sequence of sweeps (like
    :class:`randt.core.datasets.ScanSequence`: ``len``, :meth:`read`, iteration, ``stamps_s``)."""

    root: Path
    layout: str  # "rosbag2" or "rosbag1"
    topic: str
    record_ns: np.ndarray  # (N,) int64 record times of the topic's messages, in bag order
    stamps_s: np.ndarray  # the same in seconds from the first
    #: messages recorded at ``record_ns[0]`` that come before the sequence (a slice's start)
    skip: int = 0

    def __len__(self) -> int:
        return int(self.record_ns.shape[0])

    def label(self, index: int) -> str:
        """How to name sweep ``index`` in a message."""
        return f"{self.topic} #{index}"

    def read(self, index: int) -> PointCloud:
        """Sweep ``index``: its message deserialized and decoded."""
        if not 0 <= index < len(self):
            raise IndexError(f"{self.root}: {self.topic} has {len(self)} sweeps, not {index + 1}")
        t = int(self.record_ns[index])
        rank = index - int(np.searchsorted(self.record_ns, t))  # messages recorded at the same time
        if t == int(self.record_ns[0]):
            rank += self.skip
        with _reader(self.root) as reader:
            connections = [c for c in reader.connections if c.topic == self.topic]
            for k, (conn, _, raw) in enumerate(reader.messages(connections, start=t, stop=t + 1)):
                if k == rank:
                    return _decoded(reader, conn, raw, self.label(index))
        raise FormatError(f"{self.root}: {self.label(index)} is no longer in the bag")

    def __iter__(self) -> Iterator[PointCloud]:
        """The sweeps in order, read in one pass (the bag opened once: :meth:`read` opens it for
        each sweep)."""
        first, last = int(self.record_ns[0]), int(self.record_ns[-1])
        with _reader(self.root) as reader:
            connections = [c for c in reader.connections if c.topic == self.topic]
            messages = reader.messages(connections, start=first, stop=last + 1)
            for k, (conn, _, raw) in enumerate(itertools.islice(messages, self.skip, self.skip + len(self))):
                yield _decoded(reader, conn, raw, self.label(k))


def open_bag(
    path: str | Path, *, topic: str | None = None, start: int = 0, end: int | None = None
) -> BagSequence:
    """The PointCloud2 sweeps of ``topic`` (default: the only PointCloud2 topic) in a bag.

    Raises
    ------
    NotFoundError
        No such path.
    FormatError
        Not a bag, unreadable, no such topic or a topic of another type, several PointCloud2
        topics and none chosen, or no sweep in ``start``/``end``.
        Also when ``rosbags`` is not installed (``pip install 'randt-fleet[ros2]'``).
    """
    root = _bag_root(Path(path))
    with _reader(root) as reader:
        chosen = _topic(reader, root, topic)
        connections = [c for c in reader.connections if c.topic == chosen]
        every_ns = np.fromiter((t for _, t, _ in reader.messages(connections)), dtype=np.int64)
    first = range(len(every_ns))[slice(start, end)].start  # the slice's first index in the bag
    record_ns = every_ns[slice(start, end)]
    if record_ns.size == 0:
        raise FormatError(f"{root}: no {chosen} message in the range start={start} end={end}")
    return BagSequence(
        root=root,
        layout="rosbag1" if root.suffix.lower() == _ROS1_SUFFIX else "rosbag2",
        topic=chosen,
        record_ns=record_ns,
        stamps_s=(record_ns - record_ns[0]) * 1e-9,
        skip=int(np.count_nonzero(every_ns[:first] == record_ns[0])),
    )


def _bag_root(path: Path) -> Path:
    if not path.exists():
        raise NotFoundError(f"{path}: no such file or directory")
    if not is_bag(path):
        raise FormatError(
            f"{path}: not a ROS bag (a rosbag2 folder with metadata.yaml, a .db3/.mcap file in one, "
            "or a ROS 1 .bag file)"
        )
    return path.parent if path.is_file() and path.suffix.lower() in _ROS2_FILES else path


def _reader(root: Path) -> Any:
    """An :class:`~rosbags.highlevel.AnyReader` of the bag (a context manager)."""
    try:
        from rosbags.highlevel import AnyReader
    except ImportError as exc:  # a format this installation cannot read: one line, not a traceback
        raise FormatError(
            f"{root}: reading ROS bags needs the rosbags package: pip install 'randt-fleet[ros2]'"
        ) from exc
    return _Opened(AnyReader([root]), root)


class _Opened:
    """Opens the reader on entry; a bag rosbags cannot read is a :class:`FormatError`."""

    def __init__(self, reader: Any, root: Path) -> None:
        self._reader, self._root = reader, root

    def __enter__(self) -> Any:
        try:
            self._reader.open()
        except Exception as exc:  # rosbags raises its own errors for unreadable bags
            raise FormatError(f"{self._root}: unreadable bag: {exc}") from exc
        return self._reader

    def __exit__(self, *exc: object) -> None:
        self._reader.close()


def _topic(reader: Any, root: Path, topic: str | None) -> str:
    clouds = sorted({c.topic for c in reader.connections if c.msgtype == POINTCLOUD2})
    if topic is not None:
        types = {c.msgtype for c in reader.connections if c.topic == topic}
        if not types:
            raise FormatError(f"{root}: no topic {topic} (PointCloud2 topics: {', '.join(clouds) or 'none'})")
        if POINTCLOUD2 not in types:
            raise FormatError(f"{root}: {topic} is {', '.join(sorted(types))}, not {POINTCLOUD2}")
        return topic
    if len(clouds) != 1:
        listed = ", ".join(clouds) if clouds else "none"
        raise FormatError(f"{root}: choose a PointCloud2 topic with --topic (PointCloud2 topics: {listed})")
    only: str = clouds[0]
    return only


def _decoded(reader: Any, conn: Any, raw: bytes, label: str) -> PointCloud:
    try:
        msg = reader.deserialize(raw, conn.msgtype)
    except Exception as exc:  # a message its own definition cannot read
        raise FormatError(f"{label}: undecodable {conn.msgtype}: {exc}") from exc
    try:
        return decode_pointcloud2(msg)
    except FormatError as exc:
        raise FormatError(f"{label}: {exc}") from exc
