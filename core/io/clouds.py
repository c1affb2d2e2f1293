"""Point-cloud files: one :class:`PointCloud` type, one reader, two writers.

Which library handles which format, and why:

=========================  ==========================================================
suffix                     handled by
=========================  ==========================================================
``.bin``                   :func:`numpy.fromfile` (raw little-endian float32 records)
``.pcd``                   pypcd4 (ascii, binary, binary_compressed/LZF; BSD-3)
``.ply``                   :mod:`randt.core.io.ply` (numpy; ascii, binary little/big-endian)
``.csv`` ``.txt`` ``.xyz``  :func:`numpy.loadtxt` after sniffing delimiter and header
``.npy``                   :func:`numpy.load` (``allow_pickle=False``)
``.off``                   :mod:`randt.core.io.mesh` (read, then area-weighted sampling)
=========================  ==========================================================

Readers do not drop non-finite points (registration drops and counts them); they raise
:class:`~randt.core.errors.FormatError` naming the path and the problem for empty files, files without
points, wrong shapes and malformed headers, and :class:`~randt.core.errors.NotFoundError` for a path
that does not exist. Writers go through :func:`randt.core.io.atomic.atomic_open`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pypcd4

from randt.core.errors import FormatError, InvalidCloudError, NotFoundError
from randt.core.io.atomic import atomic_open
from randt.core.io.mesh import read_off, sample_surface
from randt.core.io.ply import read_ply_vertices, write_ply_binary

__all__ = [
    "SUPPORTED_READ_SUFFIXES",
    "SUPPORTED_WRITE_SUFFIXES",
    "PointCloud",
    "read_cloud",
    "write_cloud",
    "write_pcd",
    "write_ply",
]

logger = logging.getLogger(__name__)

SUPPORTED_READ_SUFFIXES: tuple[str, ...] = (
    ".bin",
    ".pcd",
    ".ply",
    ".csv",
    ".txt",
    ".xyz",
    ".npy",
    ".off",
)
SUPPORTED_WRITE_SUFFIXES: tuple[str, ...] = (".pcd", ".ply")

# float32 has a 24-bit mantissa: beyond 1e5 m its resolution is coarser than about 1 cm.
_FLOAT32_SAFE_RANGE_M = 1.0e5

# Column / property names recognised in headers (compared lower-case).
_INTENSITY_NAMES = ("intensity", "scalar_intensity", "i")
_NORMAL_NAMES = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"))

_PCD_MAX_HEADER_LINES = 64


@dataclass(frozen=True, eq=False)
class PointCloud:
    """A point cloud with optional per-point attributes.

    The fields are frozen; the arrays are not copied and not made read-only, so treat them as
    immutable. Inputs are converted to the dtypes below (no copy when they already match).

    Attributes
    ----------
    xyz:
        (N, 3) float64 positions in metres, in the sensor or map frame the caller knows.
    intensity:
        (N,) float32 return intensity, or ``None``.
    normals:
        (N, 3) float64 unit normals, or ``None``.
    time_offset_s:
        (N,) float64 per-point time offset within the sweep in seconds, or ``None``.

    Raises
    ------
    InvalidCloudError
        A field has the wrong shape or its length differs from ``xyz``.
    """

    xyz: np.ndarray
    intensity: np.ndarray | None = None
    normals: np.ndarray | None = None
    time_offset_s: np.ndarray | None = None

    def __post_init__(self) -> None:
        xyz = np.ascontiguousarray(self.xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InvalidCloudError(f"xyz must be (N, 3), got shape {xyz.shape}")
        object.__setattr__(self, "xyz", xyz)
        n = xyz.shape[0]
        for name, dtype, tail in (
            ("intensity", np.float32, ()),
            ("normals", np.float64, (3,)),
            ("time_offset_s", np.float64, ()),
        ):
            value = getattr(self, name)
            if value is None:
                continue
            array = np.ascontiguousarray(value, dtype=dtype)
            if array.shape != (n, *tail):
                raise InvalidCloudError(
                    f"{name} must have shape {(n, *tail)} to match xyz, got {array.shape}"
                )
            object.__setattr__(self, name, array)

    @property
    def n_points(self) -> int:
        """Number of points ``N``."""
        return int(self.xyz.shape[0])

    def select(self, mask_or_index: np.ndarray | slice | int | list[int]) -> PointCloud:
        """Return the subset of points chosen by a boolean mask, indices or a slice.

        Parameters
        ----------
        mask_or_index:
            (N,) bool mask, integer indices (any order, repeats allowed), a single index or a
            slice. Every present field is subset the same way.

        Returns
        -------
        PointCloud
            A new cloud; a mask or indices copy, a contiguous slice may share memory.

        Raises
        ------
        InvalidCloudError
            A boolean mask whose length is not ``N``, or indices that are not integers.
        """
        if isinstance(mask_or_index, slice):
            index: Any = mask_or_index
        else:
            index = np.asarray(mask_or_index)
            if index.dtype == bool:
                if index.shape != (self.n_points,):
                    raise InvalidCloudError(
                        f"boolean mask must have shape ({self.n_points},), got {index.shape}"
                    )
            elif index.size == 0:
                index = index.astype(np.intp)  # np.asarray([]) is float
            elif not np.issubdtype(index.dtype, np.integer):
                raise InvalidCloudError(f"select needs a bool mask or integers, got {index.dtype}")
            elif index.ndim == 0:
                index = index.reshape(1)

        def pick(array: np.ndarray | None) -> np.ndarray | None:
            return None if array is None else array[index]

        return PointCloud(
            xyz=self.xyz[index],
            intensity=pick(self.intensity),
            normals=pick(self.normals),
            time_offset_s=pick(self.time_offset_s),
        )


# --------------------------------------------------------------------------------------------
# readers
# --------------------------------------------------------------------------------------------


def _find_normals(names: list[str]) -> tuple[str, str, str] | None:
    lowered = [n.lower() for n in names]
    for candidate in _NORMAL_NAMES:
        if all(c in lowered for c in candidate):
            return tuple(names[lowered.index(c)] for c in candidate)  # type: ignore[return-value]
    return None


def _find_intensity(names: list[str]) -> str | None:
    lowered = [n.lower() for n in names]
    for candidate in _INTENSITY_NAMES:
        if candidate in lowered:
            return names[lowered.index(candidate)]
    return None


def _read_bin(path: Path, bin_fields: int | None) -> PointCloud:
    """Raw float32 records: x,y,z,intensity (KITTI, 16 bytes) or x,y,z (12 bytes)."""
    size = path.stat().st_size
    if size == 0:
        raise FormatError(f"{path}: empty file")
    if bin_fields is None:
        if size % 16 == 0:
            n_fields = 4
            if size % 12 == 0:
                logger.debug(
                    "%s: %d bytes divide by both 12 and 16; reading x,y,z,intensity "
                    "(pass bin_fields=3 for x,y,z-only files)",
                    path,
                    size,
                )
        elif size % 12 == 0:
            n_fields = 3
        else:
            raise FormatError(
                f"{path}: size {size} bytes is a multiple of neither 16 (float32 x,y,z,intensity)"
                " nor 12 (float32 x,y,z)"
            )
    else:
        n_fields = bin_fields
        if size % (4 * n_fields) != 0:
            raise FormatError(
                f"{path}: size {size} bytes is not a multiple of {4 * n_fields} "
                f"(bin_fields={n_fields} float32 values a point)"
            )
    records = np.fromfile(path, dtype="<f4").reshape(-1, n_fields)
    intensity = records[:, 3].copy() if n_fields == 4 else None
    return PointCloud(xyz=records[:, :3].astype(np.float64), intensity=intensity)


def _read_pcd_table(path: Path) -> np.ndarray:
    """Return a PCD file's points as a structured array (one named field per PCD field).

    The header and the binary / binary_compressed (LZF) bodies are decoded by pypcd4. ASCII
    bodies are parsed here with :func:`numpy.loadtxt` on any whitespace, because pypcd4 splits
    on single spaces and so rejects the trailing space Open3D writes on every ASCII line.
    """
    header: list[str] = []
    with path.open("rb") as fh:
        for raw in fh:
            line = raw.decode("utf-8", errors="replace").strip()
            if line and not line.startswith("#"):
                header.append(line)
            if line.upper().startswith("DATA") or len(header) > _PCD_MAX_HEADER_LINES:
                break
        if not header or not header[-1].upper().startswith("DATA"):
            raise FormatError(f"{path}: PCD header has no DATA line")
        try:
            metadata = pypcd4.MetaData.parse_header(header)
        except Exception as exc:  # pydantic.ValidationError, KeyError, ValueError...
            raise FormatError(f"{path}: malformed PCD header: {exc}") from exc
        try:
            if metadata.data == pypcd4.Encoding.ASCII:
                table = np.loadtxt(fh, dtype=metadata.build_dtype(), comments=None, ndmin=1)
            else:
                fh.seek(0)  # pypcd4 parses the header again, then the body
                table = pypcd4.PointCloud.from_fileobj(fh).pc_data
        except Exception as exc:  # numpy, struct, lzf and pypcd4 errors
            raise FormatError(f"{path}: PCD data does not match its header: {exc}") from exc
    if len(table) != metadata.points:
        raise FormatError(
            f"{path}: PCD header announces {metadata.points} points, the data holds {len(table)}"
        )
    return table


def _cloud_from_fields(path: Path, fields: Any, names: list[str], what: str) -> PointCloud:
    """PointCloud from named columns (a PCD table or PLY vertex element): xyz, intensity, normals."""
    if not {"x", "y", "z"} <= set(names):
        raise FormatError(f"{path}: {what} has no x, y, z fields (has {' '.join(names)})")
    intensity_name = _find_intensity(names)
    normal_names = _find_normals(names)
    return PointCloud(
        xyz=np.column_stack([fields["x"], fields["y"], fields["z"]]).astype(np.float64),
        intensity=(None if intensity_name is None else fields[intensity_name].astype(np.float32)),
        normals=(
            None
            if normal_names is None
            else np.column_stack([fields[n] for n in normal_names]).astype(np.float64)
        ),
    )


def _read_pcd(path: Path) -> PointCloud:
    table = _read_pcd_table(path)
    return _cloud_from_fields(path, table, list(table.dtype.names or ()), "PCD")


def _read_ply(path: Path) -> PointCloud:
    vertex = read_ply_vertices(path)
    return _cloud_from_fields(path, vertex, list(vertex), "PLY vertex element")


def _parses_as_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _read_text(path: Path) -> PointCloud:
    """Delimited text: comma or whitespace separated, optional one-line header.

    With a header, columns are found by name (x/y/z, intensity, nx/ny/nz, case-insensitive);
    without one, the first three columns are x, y, z and a fourth, if any, is intensity.
    """
    header_line: str | None = None
    first_data: str | None = None
    n_before = 0
    with path.open("r", encoding="utf-8", errors="replace") as fh:
        for line in fh:
            stripped = line.strip()
            if stripped and not stripped.startswith("#"):
                if (
                    header_line is None
                    and first_data is None
                    and not all(_parses_as_float(t) for t in stripped.replace(",", " ").split())
                ):
                    header_line = stripped
                else:
                    first_data = stripped
                    break
            n_before += 1
    if first_data is None:
        what = "a header but no points" if header_line else "no points"
        raise FormatError(f"{path}: text file has {what}")
    delimiter = "," if "," in first_data else None

    if header_line is None:
        skiprows, names = 0, None
    else:
        # n_before counts the lines before the first data line; the header is the last of them.
        skiprows = n_before
        header_line = header_line.lstrip("/")  # CloudCompare writes "//X,Y,Z,..."
        split = header_line.split(",") if delimiter == "," else header_line.split()
        names = [t.strip().strip("\"'") for t in split]

    try:
        table = np.loadtxt(
            path, dtype=np.float64, delimiter=delimiter, skiprows=skiprows, comments="#", ndmin=2
        )
    except ValueError as exc:
        raise FormatError(f"{path}: malformed delimited text: {exc}") from exc
    n_columns = table.shape[1]

    if names is None:
        if n_columns < 3:
            raise FormatError(f"{path}: {n_columns} columns, need at least x, y, z")
        return PointCloud(xyz=table[:, :3], intensity=table[:, 3] if n_columns >= 4 else None)

    if len(names) != n_columns:
        raise FormatError(f"{path}: header has {len(names)} names but rows have {n_columns} values")
    lowered = [n.lower() for n in names]
    if not {"x", "y", "z"} <= set(lowered):
        raise FormatError(f"{path}: header {header_line!r} has no x, y, z columns")
    column = {name: i for i, name in enumerate(lowered)}
    intensity_name = _find_intensity(names)
    normal_names = _find_normals(names)
    return PointCloud(
        xyz=table[:, [column["x"], column["y"], column["z"]]],
        intensity=None if intensity_name is None else table[:, column[intensity_name.lower()]],
        normals=(None if normal_names is None else table[:, [column[n.lower()] for n in normal_names]]),
    )


def _read_npy(path: Path) -> PointCloud:
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, EOFError, OSError) as exc:
        raise FormatError(f"{path}: cannot load as .npy: {exc}") from exc
    if not isinstance(array, np.ndarray):
        if hasattr(array, "close"):  # an .npz archive keeps its file open
            array.close()
        raise FormatError(f"{path}: expected a single array, got {type(array).__name__}")
    if array.dtype.kind not in "fiu":
        raise FormatError(f"{path}: expected a numeric array, got dtype {array.dtype}")
    if array.ndim != 2 or array.shape[1] < 3:
        raise FormatError(f"{path}: expected an (N, 3) or (N, >=4) array, got {array.shape}")
    return PointCloud(xyz=array[:, :3], intensity=array[:, 3] if array.shape[1] >= 4 else None)


def _read_off_sampled(path: Path, n_mesh_samples: int, seed: int) -> PointCloud:
    if n_mesh_samples < 1:
        raise ValueError(f"n_mesh_samples must be >= 1, got {n_mesh_samples}")
    vertices, faces = read_off(path)
    try:
        points = sample_surface(vertices, faces, n_mesh_samples, seed=seed)
    except InvalidCloudError as exc:
        raise FormatError(f"{path}: cannot sample the mesh: {exc}") from exc
    return PointCloud(xyz=points)


def read_cloud(
    path: str | os.PathLike[str],
    *,
    n_mesh_samples: int = 10_000,
    seed: int = 0,
    bin_fields: int | None = None,
) -> PointCloud:
    """Read a point cloud, choosing the format by the file's suffix (case-insensitive).

    Parameters
    ----------
    path:
        A file with one of :data:`SUPPORTED_READ_SUFFIXES`.
    n_mesh_samples:
        ``.off`` only: number of points sampled on the mesh surface.
    seed:
        ``.off`` only: seed of the surface sampler.
    bin_fields:
        ``.bin`` only: float32 values a point, 4 (x,y,z,intensity; KITTI) or 3 (x,y,z).
        ``None`` decides by the file size: a multiple of 16 bytes is read as 4 fields, else a
        multiple of 12 as 3 fields. That rule is ambiguous for sizes divisible by 48 — e.g.
        ``kitti07_keyframes/000004.bin`` is x,y,z-only but 238464 = 16 x 14904 bytes — so pass
        ``bin_fields=3`` whenever you know a file holds x,y,z only.

    Returns
    -------
    PointCloud
        ``xyz`` always; ``intensity`` when the file has it (``.bin`` with 4 fields, PCD
        ``intensity``, PLY ``intensity``/``scalar_intensity``, a text/npy 4th column or an
        ``intensity`` header column); ``normals`` when the file has nx/ny/nz or normal_x/y/z.
        Non-finite points are kept.

    Raises
    ------
    NotFoundError
        ``path`` does not exist.
    FormatError
        Unsupported suffix, unreadable or empty file, malformed header, wrong shape, no points.
    ValueError
        ``bin_fields`` not in ``{3, 4}`` or ``n_mesh_samples < 1``.
    """
    path = Path(path)
    if bin_fields not in (None, 3, 4):
        raise ValueError(f"bin_fields must be 3, 4 or None, got {bin_fields!r}")
    suffix = path.suffix.lower()
    readers: dict[str, Callable[[], PointCloud]] = {
        ".bin": lambda: _read_bin(path, bin_fields),
        ".pcd": lambda: _read_pcd(path),
        ".ply": lambda: _read_ply(path),
        ".csv": lambda: _read_text(path),
        ".txt": lambda: _read_text(path),
        ".xyz": lambda: _read_text(path),
        ".npy": lambda: _read_npy(path),
        ".off": lambda: _read_off_sampled(path, n_mesh_samples, seed),
    }
    if suffix not in readers:
        raise FormatError(
            f"{path}: unsupported suffix {suffix!r} (supported: {', '.join(SUPPORTED_READ_SUFFIXES)})"
        )
    if not path.exists():
        raise NotFoundError(f"{path}: no such file")
    try:
        if path.stat().st_size == 0:
            raise FormatError(f"{path}: empty file")
        cloud = readers[suffix]()
    except InvalidCloudError as exc:  # a field of the wrong shape built from file content
        raise FormatError(f"{path}: {exc}") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: cannot read: {exc}") from exc
    if cloud.n_points == 0:
        raise FormatError(f"{path}: file contains no points")
    logger.debug("read %s: %d points", path, cloud.n_points)
    return cloud


# --------------------------------------------------------------------------------------------
# writers
# --------------------------------------------------------------------------------------------


_PCD_FIELDS = ("x", "y", "z", "intensity")


def _xyzi_float32(cloud: PointCloud, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Return (N, 3) float32 positions and (N,) float32 intensity (zeros when absent)."""
    if cloud.n_points == 0:
        raise InvalidCloudError(f"refusing to write an empty cloud to {path}")
    finite = cloud.xyz[np.isfinite(cloud.xyz)]
    if finite.size and np.abs(finite).max() > _FLOAT32_SAFE_RANGE_M:
        logger.warning(
            "%s: coordinates up to %.3g m stored as float32 lose centimetre precision; "
            "shift the cloud to a local origin first",
            path,
            np.abs(finite).max(),
        )
    intensity = (
        np.zeros(cloud.n_points, dtype=np.float32)
        if cloud.intensity is None
        else cloud.intensity.astype(np.float32, copy=False)
    )
    return cloud.xyz.astype(np.float32), intensity


def write_pcd(path: str | os.PathLike[str], cloud: PointCloud) -> None:
    """Write a binary PCD v0.7 file with float32 fields ``x y z intensity``, atomically.

    The header has ``WIDTH N``, ``HEIGHT 1`` and the identity ``VIEWPOINT``, which PCL, Open3D,
    CloudCompare and Autoware read. Intensity is written as zeros when the cloud has none.

    Parameters
    ----------
    path:
        Target ``.pcd`` file (replaced if it exists).
    cloud:
        The cloud; ``normals`` and ``time_offset_s`` are not written.

    Raises
    ------
    InvalidCloudError
        The cloud is empty.
    FormatError
        The file could not be written.
    """
    path = Path(path)
    xyz, intensity = _xyzi_float32(cloud, path)
    table = np.empty((cloud.n_points, 4), dtype="<f4")
    table[:, :3] = xyz
    table[:, 3] = intensity
    write_pcd_xyzi(path, table)


def write_pcd_xyzi(path: str | os.PathLike[str], xyzi: np.ndarray) -> None:
    """Write an (N, 4) float32 ``x y z intensity`` table as the binary PCD :func:`write_pcd`
    writes (the same bytes), atomically, without copying the table into records or checking its
    values again: a map tile's buffer, whose points were checked when they were inserted. The
    header is pypcd4's; the body is the table's bytes.

    Raises
    ------
    InvalidCloudError
        Not an (N, 4) float32 table, or empty.
    FormatError
        The file could not be written.
    """
    path = Path(path)
    if xyzi.ndim != 2 or xyzi.shape[1] != 4 or xyzi.dtype != np.dtype("<f4"):
        raise InvalidCloudError(
            f"{path}: expected an (N, 4) little-endian float32 table, got {xyzi.shape} {xyzi.dtype}"
        )
    n = int(xyzi.shape[0])
    if n == 0:
        raise InvalidCloudError(f"refusing to write an empty cloud to {path}")
    metadata = pypcd4.MetaData(
        fields=_PCD_FIELDS,
        size=(4, 4, 4, 4),
        type=("F", "F", "F", "F"),
        count=(1, 1, 1, 1),
        width=n,
        points=n,
    )
    with atomic_open(path, "wb") as fh:
        fh.write(metadata.compose_header(data=pypcd4.Encoding.BINARY).encode())
        fh.write(np.ascontiguousarray(xyzi).data.cast("B"))
    logger.debug("wrote %s: %d points", path, n)


def write_ply(path: str | os.PathLike[str], cloud: PointCloud) -> None:
    """Write a binary little-endian PLY with float32 ``x y z intensity``, atomically.

    Parameters
    ----------
    path:
        Target ``.ply`` file (replaced if it exists).
    cloud:
        The cloud; intensity is written as zeros when absent, normals are not written.

    Raises
    ------
    InvalidCloudError
        The cloud is empty.
    FormatError
        The file could not be written.
    """
    path = Path(path)
    xyz, intensity = _xyzi_float32(cloud, path)
    write_ply_binary(path, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "intensity": intensity})
    logger.debug("wrote %s: %d points", path, cloud.n_points)


def write_cloud(path: str | os.PathLike[str], cloud: PointCloud) -> None:
    """Write ``cloud`` as PCD or PLY, chosen by the suffix (case-insensitive).

    Raises
    ------
    FormatError
        The suffix is not one of :data:`SUPPORTED_WRITE_SUFFIXES`, or the write failed.
    InvalidCloudError
        The cloud is empty.
    """
    path = Path(path)
    writers: dict[str, Callable[[Path, PointCloud], None]] = {
        ".pcd": write_pcd,
        ".ply": write_ply,
    }
    suffix = path.suffix.lower()
    if suffix not in writers:
        raise FormatError(
            f"{path}: cannot write suffix {suffix!r} (supported: {', '.join(SUPPORTED_WRITE_SUFFIXES)})"
        )
    writers[suffix](path, cloud)
