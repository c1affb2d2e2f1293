"""ROS ``sensor_msgs/PointCloud2`` messages to :class:`~randt.core.io.PointCloud`, vectorized.

A PointCloud2 is a table of points: ``fields`` name each column's byte offset, datatype and
count within a point of ``point_step`` bytes; rows of ``width`` points are ``row_step`` bytes apart
(padding allowed), ``height`` rows (1 for an unorganized cloud). Any object with those attributes
is accepted (a ``rosbags`` message, or :class:`PointCloud2Fields` built by hand): this module does
not import ROS or ``rosbags``.

The columns are read through one numpy structured dtype, no loop over points. Kept: ``x``, ``y``,
``z`` (required), ``intensity`` (optional) and a per-point time, the first of ``t``,
``timestamp``, ``time`` present, as KISS-ICP picks them: drivers differ (Ouster ``t`` uint32
nanoseconds from the sweep's start, Velodyne ``time`` float32 seconds from the message stamp,
often negative, Hesai ``timestamp`` float64 absolute seconds). Integer times are nanoseconds,
floating ones seconds; the offsets are taken from the sweep's earliest point. Rows with a
non-finite coordinate (an organized cloud's missing returns) are dropped.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from randt.core.errors import FormatError
from randt.core.io.clouds import PointCloud

__all__ = [
    "DATATYPES",
    "TIME_FIELDS",
    "PointCloud2Fields",
    "PointField",
    "check_pointcloud2",
    "decode_pointcloud2",
    "pointcloud2_arrays",
]

#: ``sensor_msgs/PointField`` datatype codes and their numpy types.
DATATYPES: dict[int, str] = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
#: The FLOAT32 datatype code.
FLOAT32 = 7
#: Per-point time fields, in the order they are looked for.
TIME_FIELDS = ("t", "timestamp", "time")
#: A sweep whose per-point times span more than this is refused (wrong units, or not one sweep).
MAX_SWEEP_SPAN_S = 1.0


class _Field(Protocol):
    name: str
    offset: int
    datatype: int
    count: int


class _Cloud(Protocol):
    height: int
    width: int
    is_bigendian: bool
    point_step: int
    row_step: int

    @property
    def fields(self) -> Sequence[_Field]: ...

    @property
    def data(self) -> np.ndarray | bytes | memoryview: ...


@dataclass(frozen=True)
class PointField:
    """One column of a PointCloud2 (``sensor_msgs/PointField``)."""

    name: str
    offset: int
    datatype: int
    count: int = 1


@dataclass(frozen=True)
class PointCloud2Fields:
    """A PointCloud2's layout and bytes, for callers without a ROS message object."""

    height: int
    width: int
    fields: tuple[PointField, ...]
    is_bigendian: bool
    point_step: int
    row_step: int
    data: bytes | np.ndarray


def decode_pointcloud2(msg: _Cloud) -> PointCloud:
    """The cloud's points (float64 x, y, z), intensity and per-point time offsets (module
    docstring); rows with a non-finite coordinate dropped.

    Raises
    ------
    FormatError
        As :func:`pointcloud2_arrays`.
    """
    points, _, time_name = _points(msg)
    xyz = np.column_stack([points["x"], points["y"], points["z"]]).astype(np.float64, copy=False)
    keep = np.isfinite(xyz[:, 0]) & np.isfinite(xyz[:, 1]) & np.isfinite(xyz[:, 2])
    if not keep.all():  # (np.compress: numpy's boolean index of an (N, 3) array is its slow path)
        xyz, points = np.compress(keep, xyz, axis=0), points[keep]
    intensity = points["intensity"].astype(np.float32) if "intensity" in (points.dtype.names or ()) else None
    offsets = _offsets(points[time_name], time_name) if time_name is not None else None
    return PointCloud(xyz=xyz, intensity=intensity, time_offset_s=offsets)


def pointcloud2_arrays(msg: _Cloud) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """``(xyz, time offsets, intensity)`` of every point, float32, as the service's matcher takes a
    scan (``randt.service.matchers.decoded_sweep``): non-finite rows kept (the matcher drops and counts
    them), ``xyz`` a view of the message's bytes when x, y, z are consecutive little-endian
    float32 (every driver's layout), the time offsets in seconds from the earliest point.

    Raises
    ------
    FormatError
        No ``x``/``y``/``z`` field, an unknown datatype, a field past the point's end, fewer bytes
        than the layout needs, or per-point times spanning more than :data:`MAX_SWEEP_SPAN_S`.
    """
    points, table, time_name = _points(msg)
    fields = points.dtype.fields
    assert fields is not None  # a structured dtype
    (tx, ox), (ty, oy), (tz, oz) = (fields[c][:2] for c in ("x", "y", "z"))
    f4 = np.dtype("<f4")
    if len(points) and tx == ty == tz == f4 and oy == ox + 4 and oz == ox + 8:
        step = points.dtype.itemsize
        xyz = np.ndarray((len(points), 3), dtype=f4, buffer=table, offset=ox, strides=(step, 4))
    else:
        xyz = np.column_stack([points["x"], points["y"], points["z"]]).astype(np.float32)
    intensity = points["intensity"].astype(np.float32, copy=False) if "intensity" in fields else None
    offsets = None
    if time_name is not None:
        times = points[time_name]
        if np.issubdtype(times.dtype, np.integer) and times.dtype.itemsize <= 4 and len(times):
            # nanoseconds of a sweep (Ouster's uint32 t) straight to float32: 8 ns at most off
            # at 0.1 s, the float32 seconds' own step, and cheaper than the float64 route
            ns = times.astype(np.float32)
            ns -= ns.min()
            _check_span(float(ns.max()) * 1e-9, times, time_name)
            ns *= np.float32(1e-9)
            offsets = ns
        else:
            offsets = _offsets(times, time_name).astype(np.float32)
    return xyz, offsets, intensity


def check_pointcloud2(msg: _Cloud) -> int:
    """The number of points of a cloud whose layout :func:`pointcloud2_arrays` can read (``x``,
    ``y``, ``z`` present, known datatypes, fields within a point, enough bytes), checked without
    reading a point: what the service's intake checks before it admits a ROS 2 scan.

    Raises
    ------
    FormatError
        As :func:`pointcloud2_arrays`, but for the per-point times' span (only reading them tells).
    """
    _columns(msg)
    n = int(msg.height) * int(msg.width)
    if n == 0:
        return 0
    _require_bytes(msg, msg.data.nbytes if isinstance(msg.data, np.ndarray) else memoryview(msg.data).nbytes)
    return n


def _require_bytes(msg: _Cloud, size: int) -> None:
    """FormatError unless ``size`` bytes hold the cloud's rows (``height`` rows ``row_step`` apart)."""
    height, width, step, row = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    if height < 0 or width < 0 or row < width * step or size < (height - 1) * row + width * step:
        raise FormatError(
            f"PointCloud2 of {height} x {width} points of {step} bytes (rows {row} bytes) "
            f"holds only {size} bytes"
        )


def _points(msg: _Cloud) -> tuple[np.ndarray, np.ndarray, str | None]:
    """The message's points as one structured array of the fields this module reads, over the
    points' bytes (returned too: a view of the message's when rows have no padding), and the name
    of its time field (or None)."""
    columns = _columns(msg)
    n = int(msg.height) * int(msg.width)
    table = _rows(msg, n)
    dtype = _dtype(columns, msg)
    points = np.ndarray(n, dtype=dtype, buffer=table) if n else np.zeros(0, dtype)
    return points, table, next((f for f in TIME_FIELDS if f in columns), None)


def _columns(msg: _Cloud) -> dict[str, _Field]:
    """The fields this module reads, by name, checked."""
    wanted = {"x", "y", "z", "intensity", *TIME_FIELDS}
    columns = {f.name: f for f in msg.fields if f.name in wanted}
    missing = [c for c in ("x", "y", "z") if c not in columns]
    if missing:
        names = ", ".join(f.name for f in msg.fields) or "none"
        raise FormatError(f"PointCloud2 without field(s) {', '.join(missing)} (fields: {names})")
    for f in columns.values():
        if int(f.datatype) not in DATATYPES:
            raise FormatError(f"PointCloud2 field {f.name!r}: unknown datatype {f.datatype}")
        size = np.dtype(DATATYPES[int(f.datatype)]).itemsize
        if int(f.offset) < 0 or int(f.offset) + size > int(msg.point_step):
            raise FormatError(
                f"PointCloud2 field {f.name!r} at byte {f.offset} does not fit a {msg.point_step}-byte point"
            )
    return columns


def _dtype(columns: dict[str, _Field], msg: _Cloud) -> np.dtype:
    order = ">" if msg.is_bigendian else "<"
    return np.dtype(
        {
            "names": list(columns),
            "formats": [order + DATATYPES[int(f.datatype)] for f in columns.values()],
            "offsets": [int(f.offset) for f in columns.values()],
            "itemsize": int(msg.point_step),
        }
    )


def _rows(msg: _Cloud, n: int) -> np.ndarray:
    """The points' bytes, rows' padding removed (a view when there is none)."""
    raw = np.frombuffer(msg.data, dtype=np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data
    raw = raw.reshape(-1).view(np.uint8)
    height, width, step, row = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    if n == 0:
        return raw[:0]
    _require_bytes(msg, raw.size)
    if row == width * step:
        return raw[: n * step]
    return np.ascontiguousarray(np.lib.stride_tricks.as_strided(raw, (height, width * step), (row, 1)))


def _offsets(times: np.ndarray, name: str) -> np.ndarray:
    """Per-point times (ns for integers, s for floats) as seconds from the earliest point."""
    if times.size == 0:
        return np.zeros(0)
    if np.issubdtype(times.dtype, np.integer):
        t0 = times.min()
        offsets = (times - t0).astype(np.float64) * 1e-9  # before widening: uint64 ns stay exact
    else:
        t = times.astype(np.float64)
        t0 = t.min()
        if not np.isfinite(t0):
            raise FormatError(f"PointCloud2 per-point time {name!r} has non-finite values")
        offsets = t - t0
    _check_span(float(offsets.max()), times, name)
    result: np.ndarray = offsets
    return result


def _check_span(span: float, times: np.ndarray, name: str) -> None:
    if not np.isfinite(span):
        raise FormatError(f"PointCloud2 per-point time {name!r} has non-finite values")
    if span > MAX_SWEEP_SPAN_S:
        raise FormatError(
            f"PointCloud2 per-point time {name!r} spans {span:.3g} s (read as "
            f"{'nanoseconds' if np.issubdtype(times.dtype, np.integer) else 'seconds'}): more than one "
            f"sweep ({MAX_SWEEP_SPAN_S:g} s), so its unit is not what this driver's field means"
        )
