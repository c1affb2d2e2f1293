"""Point clouds as HTTP bodies: binary PCD and PLY, and LAS 1.4 (laspy), all streamed.

Every format carries float32 ``x y z intensity`` in the map frame, as the store's tiles do; a PCD
is the same bytes :func:`randt.core.io.write_pcd` writes for them. LAS keeps the exact intensity
in an extra dimension ``intensity_raw`` beside its uint16 ``intensity`` (docs/api.md,
"GET /maps/{map}/tiles/{ix}/{iy}").
"""

from __future__ import annotations

import io
from collections.abc import Iterator, Sequence
from typing import Literal

import laspy
import numpy as np

__all__ = ["CLOUD_MEDIA_TYPES", "CloudFormat", "cloud_bytes", "stream_cloud"]

CloudFormat = Literal["pcd", "ply", "las"]

#: Content-Type of each format (PCD and PLY have no registered type; LAS has ASPRS's).
CLOUD_MEDIA_TYPES: dict[str, str] = {
    "pcd": "application/x-pcd",
    "ply": "application/x-ply",
    "las": "application/vnd.las",
}

_LAS_SCALE = 1e-4  # metres per LAS integer unit
_LAS_INTENSITY_MAX = 65535
_CHUNK_POINTS = 65536
#: LAS pieces are smaller: a record is built (with float64 coordinates on the way) for each piece,
#: twice, and 20 concurrent downloads each hold one at a time.
_LAS_CHUNK_POINTS = 8192

Chunk = tuple[np.ndarray, np.ndarray]  # (N, 3) float32 xyz, (N,) float32 intensity


def _pcd_header(n_points: int) -> bytes:
    # Byte for byte the header pypcd4 writes for the store's tiles (randt.core.io.write_pcd), so a
    # downloaded tile equals the store's file.
    return (
        "VERSION 0.7\n"
        "FIELDS x y z intensity\n"
        "SIZE 4 4 4 4\n"
        "TYPE F F F F\n"
        "COUNT 1 1 1 1\n"
        f"WIDTH {n_points}\n"
        "HEIGHT 1\n"
        "VIEWPOINT 0.0 0.0 0.0 1.0 0.0 0.0 0.0\n"
        f"POINTS {n_points}\n"
        "DATA binary\n"
    ).encode("ascii")


def _ply_header(n_points: int) -> bytes:
    return (
        "ply\n"
        "format binary_little_endian 1.0\n"
        "comment randt-fleet map tile(s), map frame, metres\n"
        f"element vertex {n_points}\n"
        "property float x\n"
        "property float y\n"
        "property float z\n"
        "property float intensity\n"
        "end_header\n"
    ).encode("ascii")


def _rows(xyz: np.ndarray, intensity: np.ndarray) -> bytes:
    """(N, 4) little-endian float32 rows: the body of a binary PCD or PLY."""
    rows = np.empty((xyz.shape[0], 4), dtype="<f4")
    rows[:, :3] = xyz
    rows[:, 3] = intensity
    return rows.tobytes()


def stream_cloud(fmt: CloudFormat, n_points: int, chunks: Sequence[Chunk]) -> Iterator[bytes]:
    """Yield a binary PCD or PLY, or a LAS 1.4 file, of ``n_points`` points: the header, then the
    chunks' points (at most ``_CHUNK_POINTS`` at a time). The header holds the point count, known
    up front from immutable tile snapshots, so a merged export never holds a second copy of the
    map in memory.

    Parameters
    ----------
    fmt:
        ``"pcd"``, ``"ply"`` or ``"las"``.
    n_points:
        The total number of points the chunks hold (written in the header).
    chunks:
        ``(xyz (N, 3), intensity (N,))`` pieces, e.g. one per tile; large ones are split. LAS reads
        them twice (bounds first).

    Raises
    ------
    ValueError
        The chunks do not hold exactly ``n_points`` points (checked before a LAS header and after
        a PCD or PLY's last chunk; the body is then already incomplete, so callers compute
        ``n_points`` from the same snapshot).
    """
    if fmt == "las":
        yield from _stream_las(n_points, chunks)
        return
    yield _pcd_header(n_points) if fmt == "pcd" else _ply_header(n_points)
    sent = 0
    for xyz, intensity in _pieces(chunks):
        yield _rows(xyz, intensity)
        sent += xyz.shape[0]
    if sent != n_points:
        raise ValueError(f"stream_cloud: header says {n_points} points, chunks held {sent}")


def _pieces(chunks: Sequence[Chunk], size: int = _CHUNK_POINTS) -> Iterator[Chunk]:
    for xyz, intensity in chunks:
        for start in range(0, xyz.shape[0], size):
            yield xyz[start : start + size], intensity[start : start + size]


def _stream_las(n_points: int, chunks: Sequence[Chunk]) -> Iterator[bytes]:
    """LAS 1.4 point format 6: the header as laspy's writer leaves it at close (bounds, counts and
    the extra dimension's range grown with laspy's own ``LasHeader.grow`` over every record, built
    twice, one piece at a time), then the records: the bytes laspy writes."""
    lows = [xyz.min(axis=0) for xyz, _ in chunks if xyz.shape[0]]
    header = _las_header(np.min(lows, axis=0) if lows else np.zeros(3))
    header.partial_reset()
    for xyz, intensity in _pieces(chunks, _LAS_CHUNK_POINTS):
        header.grow(_las_points(header, xyz, intensity))
    if header.point_count != n_points:
        raise ValueError(f"stream_cloud: header says {n_points} points, chunks held {header.point_count}")
    if n_points == 0:
        header.maxs = header.mins = np.zeros(3)
    # The extra dimension's range as the LAS 1.4 spec means it: laspy 2.7's ExtraBytesStruct.grow
    # takes each record's *first* value as its min and max (``pts[..., 0]`` of a 1-D field)
    (raw,) = header.vlrs.get("ExtraBytesVlr")[0].extra_bytes_structs
    ranges = [(float(i.min()), float(i.max())) for _, i in chunks if i.shape[0]]
    raw._raw_min()[:] = min((lo for lo, _ in ranges), default=0.0)
    raw._raw_max()[:] = max((hi for _, hi in ranges), default=0.0)
    with io.BytesIO() as head:
        header.write_to(head)
        yield head.getvalue()
    for xyz, intensity in _pieces(chunks, _LAS_CHUNK_POINTS):
        yield _las_points(header, xyz, intensity).memoryview().tobytes()


def _las_header(lo: np.ndarray) -> laspy.LasHeader:
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.full(3, _LAS_SCALE)
    header.offsets = np.floor(lo)  # integer-metre offset near the data keeps the integers small
    header.generating_software = "randt-fleet"
    header.add_extra_dim(laspy.ExtraBytesParams(name="intensity_raw", type=np.float32))
    return header


def _las_points(
    header: laspy.LasHeader, xyz: np.ndarray, intensity: np.ndarray
) -> laspy.ScaleAwarePointRecord:
    """LAS records: coordinates on the ``_LAS_SCALE`` grid (far below float32's resolution at map
    coordinates), ``intensity`` as ``round(clip(i, 0, 1) * 65535)`` (the wire gives intensity no
    fixed scale: a 0-255 sensor saturates there, not in ``intensity_raw``, the exact value)."""
    record = laspy.ScaleAwarePointRecord.zeros(xyz.shape[0], header=header)
    xyz64 = xyz.astype(np.float64)
    record.x, record.y, record.z = xyz64[:, 0], xyz64[:, 1], xyz64[:, 2]
    record.intensity = np.rint(np.clip(intensity, 0.0, 1.0) * _LAS_INTENSITY_MAX).astype(np.uint16)
    record.intensity_raw = intensity.astype(np.float32)
    return record


def cloud_bytes(fmt: CloudFormat, xyz: np.ndarray, intensity: np.ndarray) -> bytes:
    """One cloud (say, a tile) as a complete file body in ``fmt``."""
    buffer = io.BytesIO()
    for part in stream_cloud(fmt, xyz.shape[0], [(xyz, intensity)]):
        buffer.write(part)
    return buffer.getvalue()
