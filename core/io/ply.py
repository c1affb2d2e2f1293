"""PLY (Stanford polygon file format) in numpy: read the ``vertex`` element, write binary vertices.

A PLY file is an ASCII header followed by the data of its elements, in header order::

    ply
    format binary_little_endian 1.0      (or: ascii 1.0, binary_big_endian 1.0)
    comment any text                     (comment / obj_info lines may appear anywhere)
    element vertex 69792                 element <name> <number of rows>
    property float x                     property <type> <name>
    property float y
    property float z
    element face 1024
    property list uchar int vertex_indices    property list <count type> <item type> <name>
    end_header
    <vertex rows> <face rows>

Types: ``char uchar short ushort int uint float double`` and their aliases ``int8 uint8 int16
uint16 int32 uint32 float32 float64`` (1, 1, 2, 2, 4, 4, 4, 8 bytes). In ASCII files every row
is one line of whitespace-separated numbers; a list row starts with its item count. In binary
files the rows are packed records with no padding, in the declared byte order.

How the vertices are found without parsing every row in Python:

* **binary** — the vertex rows start at the end of the header plus the sizes of the elements
  before ``vertex`` (usually none). That sum is known only when those elements have scalar
  properties only; a list element before ``vertex`` (rare) raises
  :class:`~randt.core.errors.FormatError`. The rows are read in one call into a numpy structured array.
* **ascii** — the lines of the elements before ``vertex`` are skipped by count (lists included,
  one line a row), then exactly the vertex rows are parsed by :func:`numpy.loadtxt`; elements
  after ``vertex`` (the Stanford scans' 204,800-row ``range_grid``) are never read.

Every problem with a file — malformed or unknown header lines, unknown types, a missing
``vertex`` element, truncated or non-numeric data — raises :class:`~randt.core.errors.FormatError`
naming the path and what is wrong. The writer goes through :func:`randt.core.io.atomic.atomic_open`.
"""

from __future__ import annotations

import io
import itertools
import logging
import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from randt.core.errors import FormatError, NotFoundError
from randt.core.io.atomic import atomic_open

__all__ = [
    "PlyElement",
    "PlyHeader",
    "PlyProperty",
    "read_ply_header",
    "read_ply_vertices",
    "write_ply_binary",
]

logger = logging.getLogger(__name__)

# PLY type name (both spellings) -> numpy type code without byte order.
_PLY_TYPES: dict[str, str] = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
# numpy type code -> the name the writer uses (the original spelling: every reader knows it).
_WRITE_TYPE_NAMES: dict[str, str] = {
    "i1": "char",
    "u1": "uchar",
    "i2": "short",
    "u2": "ushort",
    "i4": "int",
    "u4": "uint",
    "f4": "float",
    "f8": "double",
}
_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
_MAX_HEADER_LINES = 1000
_MAX_HEADER_LINE_BYTES = 8192


@dataclass(frozen=True)
class PlyProperty:
    """One property of a PLY element.

    Attributes
    ----------
    name:
        Property name, e.g. ``"x"`` or ``"vertex_indices"``.
    type_code:
        numpy type code without byte order (``"f4"``, ``"u1"``...) of the value, or of the
        items for a list property.
    count_code:
        numpy type code of a list property's item count, ``None`` for a scalar property.
    """

    name: str
    type_code: str
    count_code: str | None = None

    @property
    def is_list(self) -> bool:
        """Whether this is a ``property list``."""
        return self.count_code is not None


@dataclass(frozen=True)
class PlyElement:
    """One ``element`` of a PLY header: a name, a row count and its properties in file order."""

    name: str
    count: int
    properties: tuple[PlyProperty, ...]

    @property
    def has_lists(self) -> bool:
        """Whether any property is a list (then rows differ in size)."""
        return any(p.is_list for p in self.properties)

    def record_dtype(self, byte_order: str) -> np.dtype:
        """Return the packed structured dtype of one row; scalar properties only.

        Parameters
        ----------
        byte_order:
            ``"<"`` or ``">"``.
        """
        return np.dtype([(p.name, byte_order + p.type_code) for p in self.properties])


@dataclass(frozen=True)
class PlyHeader:
    """A parsed PLY header.

    Attributes
    ----------
    format:
        ``"ascii"``, ``"binary_little_endian"`` or ``"binary_big_endian"``.
    elements:
        The elements in file order.
    data_offset:
        Bytes from the start of the file to the first data byte (just after ``end_header``
        and its line ending).
    """

    format: str
    elements: tuple[PlyElement, ...]
    data_offset: int

    def element_index(self, name: str) -> int | None:
        """Return the position of the element called ``name``, or ``None``."""
        for i, element in enumerate(self.elements):
            if element.name == name:
                return i
        return None


# --------------------------------------------------------------------------------------------
# header
# --------------------------------------------------------------------------------------------


def _type_code(type_name: str, path: Path, line_no: int) -> str:
    if type_name not in _PLY_TYPES:
        raise FormatError(
            f"{path}: PLY header line {line_no}: unknown type {type_name!r} (known: {' '.join(_PLY_TYPES)})"
        )
    return _PLY_TYPES[type_name]


def _parse_header(fh: BinaryIO, path: Path) -> PlyHeader:
    """Parse the header from the start of ``fh``; leave ``fh`` at the first data byte."""
    if fh.readline(_MAX_HEADER_LINE_BYTES).rstrip(b"\r\n") != b"ply":
        raise FormatError(f"{path}: not a PLY file (the first line is not 'ply')")
    data_format: str | None = None
    # (name, count, properties) of each element; the properties list grows while parsing.
    elements: list[tuple[str, int, list[PlyProperty]]] = []
    for line_no in range(2, _MAX_HEADER_LINES + 1):
        raw = fh.readline(_MAX_HEADER_LINE_BYTES)
        if not raw:
            raise FormatError(f"{path}: PLY header ends at line {line_no} without 'end_header'")
        if not raw.endswith(b"\n") and len(raw) >= _MAX_HEADER_LINE_BYTES:
            raise FormatError(
                f"{path}: PLY header line {line_no} is longer than {_MAX_HEADER_LINE_BYTES} bytes"
            )
        tokens = raw.decode("ascii", errors="replace").split()
        if not tokens or tokens[0] in ("comment", "obj_info"):
            continue
        keyword = tokens[0]
        where = f"{path}: PLY header line {line_no}"
        if keyword == "format":
            if data_format is not None or elements:
                raise FormatError(f"{where}: 'format' must come once, before the elements")
            if len(tokens) != 3 or tokens[1] not in _FORMATS:
                raise FormatError(
                    f"{where}: expected 'format <{'|'.join(_FORMATS)}> 1.0', got {' '.join(tokens)!r}"
                )
            if tokens[2] != "1.0":
                raise FormatError(f"{where}: unsupported PLY version {tokens[2]!r} (only 1.0)")
            data_format = tokens[1]
        elif keyword == "element":
            if len(tokens) != 3 or not tokens[2].isdecimal():
                raise FormatError(f"{where}: expected 'element <name> <count>', got {' '.join(tokens)!r}")
            if any(name == tokens[1] for name, _, _ in elements):
                raise FormatError(f"{where}: element {tokens[1]!r} is declared twice")
            elements.append((tokens[1], int(tokens[2]), []))
        elif keyword == "property":
            if not elements:
                raise FormatError(f"{where}: 'property' before any 'element'")
            if len(tokens) >= 2 and tokens[1] == "list":
                if len(tokens) != 5:
                    raise FormatError(
                        f"{where}: expected 'property list <count type> <item type> <name>', "
                        f"got {' '.join(tokens)!r}"
                    )
                count_code = _type_code(tokens[2], path, line_no)
                if count_code[0] not in "iu":
                    raise FormatError(f"{where}: list count type {tokens[2]!r} is not an integer type")
                prop = PlyProperty(tokens[4], _type_code(tokens[3], path, line_no), count_code)
            elif len(tokens) == 3:
                prop = PlyProperty(tokens[2], _type_code(tokens[1], path, line_no))
            else:
                raise FormatError(f"{where}: expected 'property <type> <name>', got {' '.join(tokens)!r}")
            name, _, properties = elements[-1]
            if any(p.name == prop.name for p in properties):
                raise FormatError(f"{where}: element {name!r} declares property {prop.name!r} twice")
            properties.append(prop)
        elif keyword == "end_header":
            if data_format is None:
                raise FormatError(f"{path}: PLY header has no 'format' line")
            return PlyHeader(
                format=data_format,
                elements=tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements),
                data_offset=fh.tell(),
            )
        else:
            raise FormatError(f"{where}: unknown header keyword {keyword!r}")
    raise FormatError(f"{path}: PLY header has no 'end_header' in its first {_MAX_HEADER_LINES} lines")


def read_ply_header(path: str | os.PathLike[str]) -> PlyHeader:
    """Read and check the header of a PLY file.

    Raises
    ------
    NotFoundError
        ``path`` does not exist.
    FormatError
        The header is malformed (see :func:`read_ply_vertices`) or the file cannot be read.
    """
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return _parse_header(fh, path)
    except FileNotFoundError as exc:
        raise NotFoundError(f"{path}: no such file") from exc
    except OSError as exc:
        raise FormatError(f"{path}: cannot read: {exc}") from exc


# --------------------------------------------------------------------------------------------
# vertex data
# --------------------------------------------------------------------------------------------


def _read_binary_vertices(
    fh: io.BufferedReader, header: PlyHeader, index: int, path: Path
) -> dict[str, np.ndarray]:
    byte_order = "<" if header.format == "binary_little_endian" else ">"
    offset = header.data_offset
    for element in header.elements[:index]:
        if element.has_lists:
            raise FormatError(
                f"{path}: binary PLY element {element.name!r} comes before 'vertex' and has list "
                "properties, so the vertices' byte offset is unknown without decoding every row; "
                "this rare layout is not supported (write the vertex element first)"
            )
        offset += element.count * element.record_dtype(byte_order).itemsize
    vertex = header.elements[index]
    dtype = vertex.record_dtype(byte_order)
    # The header's count is checked against the file's size before anything is allocated: a header
    # announcing 10^12 vertices is a truncated file, not a request for 11 TiB of memory.
    available = max(os.fstat(fh.fileno()).st_size - offset, 0)
    if vertex.count * dtype.itemsize > available:
        raise FormatError(
            f"{path}: truncated PLY: the header announces {vertex.count} vertices of "
            f"{dtype.itemsize} bytes ({vertex.count * dtype.itemsize} bytes from offset {offset}), "
            f"the file holds {available}"
        )
    table = np.empty(vertex.count, dtype=dtype)
    fh.seek(offset)
    # numpy's stubs give ndarray the buffer protocol (__buffer__) only for Python >= 3.12
    n_read = fh.readinto(table.view(np.uint8))  # type: ignore[arg-type]
    if n_read != table.nbytes:
        raise FormatError(
            f"{path}: truncated PLY: the header announces {vertex.count} vertices of "
            f"{table.dtype.itemsize} bytes ({table.nbytes} bytes from offset {offset}), "
            f"the file holds {n_read}"
        )
    return {
        name: table[name].astype(table.dtype[name].newbyteorder("="))  # a contiguous copy
        for name in table.dtype.names or ()
    }


def _read_ascii_vertices(fh: BinaryIO, header: PlyHeader, index: int, path: Path) -> dict[str, np.ndarray]:
    n_before = sum(element.count for element in header.elements[:index])
    n_skipped = sum(1 for _ in itertools.islice(fh, n_before))
    if n_skipped != n_before:
        raise FormatError(
            f"{path}: truncated PLY: the elements before 'vertex' announce {n_before} lines, "
            f"the file holds {n_skipped}"
        )
    vertex = header.elements[index]
    n_properties = len(vertex.properties)
    if vertex.count == 0:
        table = np.empty((0, n_properties))
    else:
        try:
            with warnings.catch_warnings():
                # numpy warns "input contained no data" on an empty body; counted below instead.
                warnings.simplefilter("ignore", UserWarning)
                table = np.loadtxt(fh, dtype=np.float64, max_rows=vertex.count, comments=None, ndmin=2)
        except ValueError as exc:
            raise FormatError(f"{path}: malformed ASCII PLY vertex rows: {exc}") from exc
        if table.shape[0] != vertex.count:
            raise FormatError(
                f"{path}: truncated PLY: the header announces {vertex.count} vertices, "
                f"the file holds {table.shape[0]}"
            )
        if table.shape[1] != n_properties:
            raise FormatError(
                f"{path}: ASCII PLY vertex rows have {table.shape[1]} values, the header declares "
                f"{n_properties} properties ({' '.join(p.name for p in vertex.properties)})"
            )
    columns: dict[str, np.ndarray] = {}
    for i, prop in enumerate(vertex.properties):  # a handful of properties, vectorised each
        column = table[:, i]
        dtype = np.dtype(prop.type_code)
        if dtype.kind in "iu" and column.size:
            info = np.iinfo(dtype)
            if not (
                np.all(column == np.trunc(column)) and column.min() >= info.min and column.max() <= info.max
            ):
                raise FormatError(
                    f"{path}: ASCII PLY vertex property {prop.name!r} holds values that are not "
                    f"{dtype.name} integers"
                )
        columns[prop.name] = column.astype(dtype)
    return columns


def read_ply_vertices(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Read the ``vertex`` element of an ASCII or binary PLY file.

    Parameters
    ----------
    path:
        A PLY file (``format ascii 1.0``, ``binary_little_endian 1.0`` or
        ``binary_big_endian 1.0``). Other elements (faces, range grids...) are skipped.

    Returns
    -------
    dict[str, np.ndarray]
        One (V,) contiguous array a vertex property, in header order, keyed by property name,
        with the declared type in native byte order (``float`` -> float32, ``uchar`` -> uint8...).

    Raises
    ------
    NotFoundError
        ``path`` does not exist.
    FormatError
        Malformed header (not ``ply``, unknown keyword, format or type, bad element or property
        line, no ``end_header``), no ``vertex`` element, a list property on ``vertex``, a binary
        file with a list element before ``vertex``, truncated data, non-numeric or ragged ASCII
        rows, or an unreadable file.
    """
    path = Path(path)
    try:
        with path.open("rb") as fh:
            header = _parse_header(fh, path)
            index = header.element_index("vertex")
            if index is None:
                names = " ".join(e.name for e in header.elements) or "none"
                raise FormatError(f"{path}: PLY has no 'vertex' element (elements: {names})")
            vertex = header.elements[index]
            if vertex.has_lists:
                lists = " ".join(p.name for p in vertex.properties if p.is_list)
                raise FormatError(f"{path}: PLY vertex element has list properties ({lists}); not supported")
            if not vertex.properties:
                raise FormatError(f"{path}: PLY vertex element has no properties")
            if header.format == "ascii":
                columns = _read_ascii_vertices(fh, header, index, path)
            else:
                columns = _read_binary_vertices(fh, header, index, path)
    except FileNotFoundError as exc:
        raise NotFoundError(f"{path}: no such file") from exc
    except OSError as exc:
        raise FormatError(f"{path}: cannot read: {exc}") from exc
    logger.debug("read %s (%s): %d vertices", path, header.format, vertex.count)
    return columns


# --------------------------------------------------------------------------------------------
# writer
# --------------------------------------------------------------------------------------------


def write_ply_binary(path: str | os.PathLike[str], fields: Mapping[str, np.ndarray]) -> None:
    """Write one ``vertex`` element as a binary little-endian PLY, atomically.

    Parameters
    ----------
    path:
        Target file (replaced if it exists).
    fields:
        Property name -> (N,) array, in the order to write. Each property's PLY type follows
        the array's dtype: int8/uint8/int16/uint16/int32/uint32/float32/float64 are written as
        char/uchar/short/ushort/int/uint/float/double. Cast other dtypes (int64, bool,
        float16) first.

    Raises
    ------
    FormatError
        No fields, a name that is empty or holds whitespace or non-ASCII characters, an array
        that is not 1-D, arrays of different lengths, a dtype with no PLY type, or the file
        could not be written. Nothing is written in the first cases.
    """
    path = Path(path)
    if not fields:
        raise FormatError(f"cannot write {path}: no vertex fields given")
    columns = {name: np.asarray(values) for name, values in fields.items()}
    record: list[tuple[str, str]] = []
    property_lines: list[str] = []
    for name, column in columns.items():
        if not name or not name.isascii() or any(c.isspace() for c in name):
            raise FormatError(f"cannot write {path}: {name!r} is not a valid PLY property name")
        if column.ndim != 1:
            raise FormatError(f"cannot write {path}: field {name!r} must be 1-D, got shape {column.shape}")
        code = f"{column.dtype.kind}{column.dtype.itemsize}"
        if code not in _WRITE_TYPE_NAMES:
            raise FormatError(
                f"cannot write {path}: field {name!r} has dtype {column.dtype}, which has no PLY type "
                "(use int8/uint8/int16/uint16/int32/uint32/float32/float64)"
            )
        record.append((name, "<" + code))
        property_lines.append(f"property {_WRITE_TYPE_NAMES[code]} {name}\n")
    lengths = {name: len(column) for name, column in columns.items()}
    if len(set(lengths.values())) != 1:
        raise FormatError(f"cannot write {path}: fields differ in length: {lengths}")
    n = next(iter(lengths.values()))
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n{''.join(property_lines)}end_header\n"
    )
    table = np.empty(n, dtype=record)
    for name, column in columns.items():
        table[name] = column
    with atomic_open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(table.view(np.uint8))
    logger.debug("wrote %s: %d vertices", path, n)
