"""Autoware's divided point-cloud map on disk: tile PCD files, ``pointcloud_map_metadata.yaml``
and our sidecar ``randt_tile_grid.yaml``.

Autoware's ``pointcloud_map_loader`` reads (and ``pointcloud_divider`` writes) one binary PCD per
tile, ``<ix>_<iy>.pcd``, and a metadata file::

    x_resolution: 20.0
    y_resolution: 20.0
    -1_0.pcd: [-20, 0]      # file name -> integer [x_min, y_min] of its cell, metres
    0_0.pcd: [0, 0]

The loader skips the two resolution keys and parses every other value as a list of two integers,
so nothing else may go into that file. The grid's own settings and tile versions go into the
sidecar (:data:`GRID_SIDECAR_NAME`), which Autoware ignores. Every file is written atomically
(:func:`randt.core.io.atomic_open`).
:class:`randt.core.tiles.TileGrid` decides what to write and in which order;
this module only knows the files.
"""

from __future__ import annotations

import functools
import logging
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from randt.core.errors import FormatError, NotFoundError
from randt.core.io.atomic import atomic_open
from randt.core.io.clouds import PointCloud, write_pcd, write_pcd_xyzi

__all__ = [
    "AUTOWARE_METADATA_NAME",
    "GRID_SIDECAR_NAME",
    "PROJECTOR_INFO_NAME",
    "SIDECAR_FORMAT",
    "make_directory",
    "read_metadata",
    "read_projector_info",
    "read_sidecar",
    "remove_stale_tile_files",
    "tile_file_name",
    "write_metadata",
    "write_projector_info",
    "write_sidecar",
    "write_tile_file",
    "write_tile_table",
]

logger = logging.getLogger(__name__)

#: File name Autoware's map loader expects next to the divided PCD files.
AUTOWARE_METADATA_NAME = "pointcloud_map_metadata.yaml"
#: Autoware's map projection loader reads the map's projection from this file beside the tiles
#: (``autoware_map_projection_loader``; written for a georeferenced map, core/geo.py).
PROJECTOR_INFO_NAME = "map_projector_info.yaml"
#: Its ``projector_type`` values and the keys each needs (Autoware's loader refuses a file
#: without them).
_PROJECTOR_KEYS = {
    "local": (),
    "MGRS": ("vertical_datum", "mgrs_grid"),
    "LocalCartesianUTM": ("vertical_datum", "map_origin"),
    "TransverseMercator": ("vertical_datum", "map_origin"),
    "LocalCartesian": ("vertical_datum", "map_origin"),
}
#: Our sidecar: grid settings and tile versions (Autoware does not read it).
GRID_SIDECAR_NAME = "randt_tile_grid.yaml"
#: The sidecar's ``format`` value.
SIDECAR_FORMAT = "randt-tile-grid/1"

_TILE_FILE_RE = re.compile(r"^(-?\d+)_(-?\d+)\.pcd$")
_RESOLUTION_KEYS = ("x_resolution", "y_resolution")


def tile_file_name(tid: str) -> str:
    """The PCD file name of tile ``"<ix>_<iy>"``: ``"<ix>_<iy>.pcd"``."""
    return f"{tid}.pcd"


def make_directory(directory: str | os.PathLike[str]) -> Path:
    """Create ``directory`` (and parents) if missing; :class:`FormatError` when it cannot be."""
    path = Path(directory)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FormatError(f"cannot create {path}: {exc}") from exc
    return path


def write_tile_file(directory: Path, tid: str, cloud: PointCloud) -> Path:
    """Write one tile as binary PCD (float32 ``x y z intensity``), atomically; returns its path."""
    path = directory / tile_file_name(tid)
    write_pcd(path, cloud)
    return path


def write_tile_table(directory: Path, tid: str, xyzi: np.ndarray) -> Path:
    """:func:`write_tile_file` from an (N, 4) float32 ``x y z intensity`` table, the same bytes
    without a copy or a check (``randt.core.io.clouds.write_pcd_xyzi``); returns its path."""
    path = directory / tile_file_name(tid)
    write_pcd_xyzi(path, xyzi)
    return path


def write_metadata(
    directory: Path, tile_size_m: int, corners: Mapping[str, tuple[int, int]]
) -> dict[str, list[int]]:
    """Write :data:`AUTOWARE_METADATA_NAME` for tiles ``tile id -> (x_min, y_min)`` (integer metres,
    in the order given); returns its tile entries, PCD file name -> ``[x_min, y_min]``."""
    entries = {tile_file_name(tid): [int(x), int(y)] for tid, (x, y) in corners.items()}
    resolution = float(tile_size_m)
    _write_yaml(
        directory / AUTOWARE_METADATA_NAME,
        {"x_resolution": resolution, "y_resolution": resolution, **entries},
    )
    return entries


def read_metadata(directory: Path) -> tuple[int, dict[str, tuple[int, int]]]:
    """Tile size and ``file name -> (ix, iy)`` from a directory's :data:`AUTOWARE_METADATA_NAME`.

    Raises
    ------
    NotFoundError
        No metadata file.
    FormatError
        Not YAML, non-square or fractional tiles, a key that is not a PCD file name, a corner that
        is not two integers on the tile grid, or no PCD file listed.
    """
    path = directory / AUTOWARE_METADATA_NAME
    document = _read_yaml_mapping(path)
    resolutions = []
    for key in _RESOLUTION_KEYS:
        value = document.get(key)
        if not isinstance(value, int | float) or isinstance(value, bool):
            raise FormatError(f"{path}: {key} must be a number, got {value!r}")
        resolutions.append(float(value))
    x_res, y_res = resolutions
    if x_res != y_res or not x_res.is_integer() or x_res <= 0:
        raise FormatError(
            f"{path}: a TileGrid needs square tiles of whole metres, got x_resolution={x_res:g}, "
            f"y_resolution={y_res:g}"
        )
    tile = int(x_res)
    files: dict[str, tuple[int, int]] = {}
    for key, value in document.items():
        if key in _RESOLUTION_KEYS:
            continue
        name = str(key)
        if Path(name).name != name or not name.lower().endswith(".pcd"):
            raise FormatError(f"{path}: key {name!r} is not a PCD file name")
        if not (isinstance(value, list) and len(value) == 2 and all(_is_int(v) for v in value)):
            raise FormatError(f"{path}: {name} must map to [x_min, y_min] integers, got {value!r}")
        x_min, y_min = value
        if x_min % tile or y_min % tile:
            raise FormatError(f"{path}: {name} corner {value} is not a multiple of the {tile} m tile size")
        files[name] = (x_min // tile, y_min // tile)
    if not files:
        raise FormatError(f"{path}: lists no PCD files")
    return tile, files


def write_sidecar(
    directory: Path,
    *,
    tile_size_m: int,
    voxel_size_m: float,
    max_points_per_voxel: int,
    versions: Mapping[str, int],
) -> None:
    """Write :data:`GRID_SIDECAR_NAME`: the grid's settings and every tile's version, atomically."""
    _write_yaml(
        directory / GRID_SIDECAR_NAME,
        {
            "format": SIDECAR_FORMAT,
            "tile_size_m": tile_size_m,
            "voxel_size_m": voxel_size_m,
            "max_points_per_voxel": max_points_per_voxel,
            "versions": dict(versions),
        },
    )


def read_sidecar(directory: Path, tile_size_m: int) -> tuple[dict[str, Any], dict[str, int]]:
    """The sidecar's document and its ``tile id -> version`` map; ``({}, {})`` when there is none.

    Raises
    ------
    FormatError
        An unknown format, a tile size other than the metadata's ``tile_size_m``, or versions that
        are not integers >= 1.
    """
    path = directory / GRID_SIDECAR_NAME
    if not path.is_file():
        return {}, {}
    saved = _read_yaml_mapping(path)
    if saved.get("format") != SIDECAR_FORMAT:
        raise FormatError(f"{path}: unknown format {saved.get('format')!r}")
    if saved.get("tile_size_m") != tile_size_m:
        raise FormatError(
            f"{path}: tile_size_m {saved.get('tile_size_m')!r} disagrees with the "
            f"metadata's {tile_size_m} m resolution"
        )
    raw_versions = saved.get("versions") or {}
    if not isinstance(raw_versions, dict) or not all(_is_int(v) and v >= 1 for v in raw_versions.values()):
        raise FormatError(f"{path}: versions must map tile ids to integers >= 1")
    return saved, {str(k): int(v) for k, v in raw_versions.items()}


def write_projector_info(directory: Path, info: Mapping[str, Any]) -> Path:
    """Write :data:`PROJECTOR_INFO_NAME` (``info``: :meth:`randt.core.geo.LocalCartesianUTM.projector_info`),
    atomically; returns its path. Checked as :func:`read_projector_info` reads it."""
    document = _checked_projector_info(dict(info), "projector info")
    path = directory / PROJECTOR_INFO_NAME
    with atomic_open(path, "w") as fh:
        fh.write(yaml.safe_dump(document, sort_keys=False, default_flow_style=False))
    return path


def read_projector_info(directory: Path) -> dict[str, Any] | None:
    """A directory's :data:`PROJECTOR_INFO_NAME` (``None`` when it has none: a map in a local
    frame); :class:`FormatError` when it is not one Autoware's loader would take."""
    path = directory / PROJECTOR_INFO_NAME
    if not path.is_file():
        return None
    return _checked_projector_info(_read_yaml_mapping(path), str(path))


def _checked_projector_info(document: dict[Any, Any], where: str) -> dict[str, Any]:
    kind = document.get("projector_type")
    if kind not in _PROJECTOR_KEYS:
        raise FormatError(f"{where}: projector_type {kind!r}, expected one of {', '.join(_PROJECTOR_KEYS)}")
    missing = [key for key in _PROJECTOR_KEYS[kind] if key not in document]
    if missing:
        raise FormatError(f"{where}: a {kind} projection needs {', '.join(missing)}")
    origin = document.get("map_origin")
    if "map_origin" in _PROJECTOR_KEYS[kind]:
        keys = ("latitude", "longitude", "altitude")
        if not isinstance(origin, dict) or not all(
            isinstance(origin.get(k), int | float) and not isinstance(origin.get(k), bool) for k in keys
        ):
            raise FormatError(f"{where}: map_origin needs numbers latitude, longitude and altitude")
    return document


def remove_stale_tile_files(directory: Path, keep: Mapping[str, object]) -> None:
    """Remove ``<ix>_<iy>.pcd`` files not named in ``keep`` (Autoware globs every ``*.pcd`` of the
    directory); other ``.pcd`` files are left alone with a warning."""
    for path in sorted(directory.glob("*.pcd")):
        if path.name in keep:
            continue
        if _TILE_FILE_RE.match(path.name):
            logger.info("removing stale tile file %s (tile no longer in the map)", path)
            path.unlink(missing_ok=True)
        else:
            logger.warning(
                "%s is not one of this map's tiles; Autoware would load it too (not in %s)",
                path,
                AUTOWARE_METADATA_NAME,
            )


#: libyaml's emitter and parser when PyYAML was built with it (same text, much faster: the service
#: rewrites a map's metadata, which lists every tile, at each save).
_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _write_yaml(path: Path, document: dict[str, Any]) -> None:
    with atomic_open(path, "w") as fh:
        fh.write(_yaml_text(document))


def _yaml_text(document: dict[str, Any]) -> str:
    """``yaml.dump(document)`` as this module writes it (block style, lists of scalars in flow
    style, keys in order), with the entries of a long mapping rendered from a cache: the metadata
    and the sidecar list every tile and are rewritten at every save, so PyYAML's Python
    representer over all of them grew with the map.
    Mappings of scalars or of ``[int, int]`` lists with string keys take the fast path; the text
    is exactly PyYAML's for them (tests); anything else goes to PyYAML."""
    lines = []
    for key, value in document.items():
        if isinstance(value, dict) and value and all(_flat_entry(k, v) for k, v in value.items()):
            lines.append(f"{_yaml_key(key)}:\n")
            lines.extend(f"  {_yaml_key(k)}: {_yaml_value(v)}\n" for k, v in value.items())
        elif _flat_entry(key, value):
            lines.append(f"{_yaml_key(key)}: {_yaml_value(value)}\n")
        else:  # alone, a mapping of scalars would come out in flow style: scalars go in block style
            flow = None if isinstance(value, list | dict) else False
            lines.append(yaml.dump({key: value}, Dumper=_DUMPER, sort_keys=False, default_flow_style=flow))
    return "".join(lines)


def _flat_entry(key: object, value: object) -> bool:
    if not isinstance(key, str):
        return False
    if isinstance(value, list):
        return len(value) == 2 and all(type(v) is int for v in value)
    return type(value) is int


def _yaml_value(value: int | list[int]) -> str:
    return f"[{value[0]}, {value[1]}]" if isinstance(value, list) else str(value)


@functools.lru_cache(maxsize=65536)
def _yaml_key(key: str) -> str:
    """How PyYAML writes ``key`` as a mapping key (quoted when it would read as another type:
    ``'0_0'`` is an integer in YAML 1.1)."""
    return yaml.dump({key: 0}, Dumper=_DUMPER, default_flow_style=False)[: -len(": 0\n")]


def _read_yaml_mapping(path: Path) -> dict[Any, Any]:
    if not path.is_file():
        raise NotFoundError(f"{path}: no such file")
    try:
        document = yaml.load(path.read_text(encoding="utf-8"), Loader=_LOADER)  # a safe loader
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise FormatError(f"{path}: cannot read YAML: {exc}") from exc
    if not isinstance(document, dict):
        raise FormatError(f"{path}: expected a mapping at the top level")
    return document


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)
