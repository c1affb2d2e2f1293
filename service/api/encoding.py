"""Point clouds as HTTP bodies: binary PCD and PLY (streamed), and LAS 1.4 (laspy).

Every format carries float32 ``x y z intensity`` in the map frame, as the store's tiles do:

* **PCD** v0.7 binary, the same bytes :func:`core.io.write_pcd` writes for the store's tiles
  (PCL, Open3D, Autoware, CloudCompare);
* **PLY** binary little-endian with ``float x, y, z, intensity`` (Open3D, CloudCompare, MeshLab);
* **LAS** 1.4, point format 6 (QGIS, PDAL, CloudCompare, LAStools), written by laspy. LAS stores
  integer coordinates with a scale: 0.1 mm here, far below float32's resolution at map
  coordinates, so a point comes back within 0.05 mm. The wire gives intensity no fixed scale, so
  the exact float32 value goes into an extra dimension ``intensity_raw``, and LAS's own uint16
  ``intensity`` holds ``round(clip(i, 0, 1) * 65535)``: the full range for reflectance-scaled
  sensors (KITTI, the simulator); a sensor reporting 0-255 saturates there but not in
  ``intensity_raw``.

PCD and PLY headers hold the point count, which is known up front from immutable tile
snapshots, so :func:`stream_cloud` yields the header and then one chunk per tile: a merged export
never holds a second copy of the map in memory. LAS headers also hold bounds and per-return
counts that laspy fills in when the file closes, so LAS is written to a temporary file first.
"""

from __future__ import annotations

import io
import tempfile
from collections.abc import Iterable, Iterator
from typing import Literal

import laspy
import numpy as np

__all__ = ["CLOUD_MEDIA_TYPES", "CloudFormat", "cloud_bytes", "las_file", "stream_cloud"]

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

Chunk = tuple[np.ndarray, np.ndarray]  # (N, 3) float32 xyz, (N,) float32 intensity


def _pcd_header(n_points: int) -> bytes:
    # Byte for byte the header pypcd4 writes for the store's tiles (core.io.write_pcd), so a
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


def stream_cloud(fmt: Literal["pcd", "ply"], n_points: int, chunks: Iterable[Chunk]) -> Iterator[bytes]:
    """Yield a binary PCD or PLY of ``n_points`` points: the header, then the chunks' rows.

    Parameters
    ----------
    fmt:
        ``"pcd"`` or ``"ply"``.
    n_points:
        The total number of points the chunks hold (written in the header).
    chunks:
        ``(xyz (N, 3), intensity (N,))`` pieces, e.g. one per tile; large ones are split.

    Raises
    ------
    ValueError
        The chunks do not hold exactly ``n_points`` points (checked after the last one; the
        body is then already incomplete, so callers compute ``n_points`` from the same snapshot).
    """
    yield _pcd_header(n_points) if fmt == "pcd" else _ply_header(n_points)
    sent = 0
    for xyz, intensity in chunks:
        for start in range(0, xyz.shape[0], _CHUNK_POINTS):
            stop = start + _CHUNK_POINTS
            yield _rows(xyz[start:stop], intensity[start:stop])
        sent += xyz.shape[0]
    if sent != n_points:
        raise ValueError(f"stream_cloud: header says {n_points} points, chunks held {sent}")


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
    record = laspy.ScaleAwarePointRecord.zeros(xyz.shape[0], header=header)
    xyz64 = xyz.astype(np.float64)
    record.x, record.y, record.z = xyz64[:, 0], xyz64[:, 1], xyz64[:, 2]
    record.intensity = np.rint(np.clip(intensity, 0.0, 1.0) * _LAS_INTENSITY_MAX).astype(np.uint16)
    record.intensity_raw = intensity.astype(np.float32)
    return record


def las_file(chunks: Iterable[Chunk], lo_xyz: np.ndarray) -> tempfile.SpooledTemporaryFile[bytes]:
    """Write the chunks as one LAS 1.4 file (point format 6) into a rewound temporary file.

    ``lo_xyz`` (3,) is a lower corner of the data (it sets the integer offset). Files up to
    64 MiB stay in memory; the caller closes the file.
    """
    out: tempfile.SpooledTemporaryFile[bytes] = tempfile.SpooledTemporaryFile(max_size=64 << 20)  # noqa: SIM115
    header = _las_header(np.asarray(lo_xyz, dtype=np.float64))
    with laspy.open(out, mode="w", header=header, closefd=False) as writer:
        for xyz, intensity in chunks:
            if xyz.shape[0]:
                writer.write_points(_las_points(header, xyz, intensity))
    out.seek(0)
    return out


def cloud_bytes(fmt: CloudFormat, xyz: np.ndarray, intensity: np.ndarray) -> bytes:
    """One cloud (say, a tile) as a complete file body in ``fmt``."""
    if fmt == "las":
        lo = xyz.min(axis=0) if xyz.shape[0] else np.zeros(3)
        with las_file([(xyz, intensity)], lo) as fh:
            return fh.read()
    buffer = io.BytesIO()
    for part in stream_cloud(fmt, xyz.shape[0], [(xyz, intensity)]):
        buffer.write(part)
    return buffer.getvalue()
