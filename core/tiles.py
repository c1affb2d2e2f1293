"""The tiled, density-equalized global map, updated incrementally from registered scans.

:class:`TileGrid`: XY tiles with integer-metre origins, each a cap of points per voxel aligned to
its corner, filled by the policy *keep the first arrivals* (stable under revisits, bounded, real
measurements only); versioned tiles, immutable :class:`Tile` snapshots for readers while inserts
go on, Autoware divided-map export and in-place updates. Layout, the policy and why, precision,
the files and thread safety: docs/mapping.md, "The tiled map".
"""

from __future__ import annotations

import itertools
import logging
import math
import os
import re
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from randt.core.errors import FormatError, InvalidCloudError, NotFoundError
from randt.core.io import PointCloud, read_cloud, write_cloud
from randt.core.io.autoware import (
    make_directory,
    read_metadata,
    read_sidecar,
    remove_stale_tile_files,
    tile_file_name,
    write_metadata,
    write_sidecar,
    write_tile_table,
)
from randt.core.kernels import (
    first_per_voxel_pair,
    group_int_keys,
    group_min,
    tile_voxel_keys,
    voxel_table_admit,
    voxel_table_forget,
    voxel_table_grow,
    voxel_table_near,
)
from randt.core.metrics.cloud import pdu
from randt.core.voxel import pack_keys, voxel_coords

__all__ = [
    "COLUMN_M",
    "Agreement",
    "SentVoxels",
    "Tile",
    "TileBounds",
    "TileGrid",
    "above_ground",
    "load_autoware",
    "parse_tile_id",
    "tile_id",
]

logger = logging.getLogger(__name__)

_TILE_ID_RE = re.compile(r"^(-?\d+)_(-?\d+)$")

# Tile indices are packed into one int64 (31 bits each) to group points by tile; coordinates beyond
# this are not a map frame (and float32 would hold them to metres, not centimetres).
_MAX_ABS_XY_M = 1.0e8
_TILE_OFFSET = 1 << 30

#: Numbers for :attr:`TileGrid.content_token` (a grid replaced by another with the same name,
#: e.g. a map deleted and mapped again, is another grid).
_grid_uids = itertools.count(1)

_VoxelTable = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]

#: Edge (m) of the map's columns (:meth:`TileGrid.agreement`): a column holding any map point is
#: a place the map has seen; only there can a sweep agree or disagree with it.
COLUMN_M = 2.0


def _empty_voxel_table(cap: int, size: int = 1024) -> _VoxelTable:
    """An empty :func:`randt.core.kernels.voxel_table_admit` table: tile keys (-1 empty), voxel keys,
    counts, and the kept points when ``cap > 1`` (with one, a voxel is full at its first)."""
    return (
        np.full(size, -1, dtype=np.int64),
        np.empty(size, dtype=np.int64),
        np.zeros(size, dtype=np.int32),
        np.empty((size, cap if cap > 1 else 0, 3), dtype=np.float32),
    )


def _admitted(
    table: _VoxelTable, used: int, tkeys: np.ndarray, vkeys: np.ndarray, xyz: np.ndarray, cap: int
) -> tuple[np.ndarray, _VoxelTable, int]:
    """``(accept, table, used)``: which points the equalization policy keeps, in arrival order,
    against the voxels ``table`` holds, which records them (grown when it would pass half full)."""
    accept = np.zeros(tkeys.size, dtype=bool)
    xyz = np.ascontiguousarray(xyz, dtype=np.float32)
    i = 0
    while True:
        i, used = voxel_table_admit(*table, used, tkeys, vkeys, xyz, cap, i, accept)
        if i >= tkeys.size:
            return accept, table, used
        size = table[0].size * 2
        while size < 2 * (used + tkeys.size - i):
            size *= 2
        table = voxel_table_grow(*table, size)


@dataclass(frozen=True)
class Agreement:
    """What :meth:`TileGrid.agreement` found: ``checked`` points fell where the map has content,
    ``near`` of them close to the map's points."""

    checked: int
    near: int

    @property
    def share(self) -> float:
        """``near / checked`` (NaN when nothing was checked)."""
        return self.near / self.checked if self.checked else float("nan")


def above_ground(points_xyz: np.ndarray, height_m: float = 0.3, column_m: float = COLUMN_M) -> np.ndarray:
    """The rows of ``points_xyz`` (N, 3) more than ``height_m`` above the lowest point of their
    ``column_m`` square column (in the same cloud): the ground, and whatever lies flat on it,
    dropped without assuming where the sensor is or that the ground is level across columns."""
    xyz = np.asarray(points_xyz, dtype=np.float64)
    if xyz.shape[0] == 0:
        return xyz.reshape(0, 3)
    cells = np.floor(xyz[:, :2] / column_m).astype(np.int64)
    keys = pack_keys(np.c_[cells, np.zeros(len(cells), np.int64)])
    _, inverse = np.unique(keys, return_inverse=True)
    n = int(inverse.max()) + 1
    lowest = group_min(xyz[:, 2], inverse, n, np.zeros(len(xyz), dtype=bool))
    return xyz[xyz[:, 2] > lowest[inverse] + height_m]


def tile_id(ix: int, iy: int) -> str:
    """The id ``"<ix>_<iy>"`` of tile ``(ix, iy)`` (also its PCD file stem and wire-key suffix)."""
    return f"{int(ix)}_{int(iy)}"


def parse_tile_id(tid: str) -> tuple[int, int]:
    """Inverse of :func:`tile_id`.

    Raises
    ------
    ValueError
        ``tid`` is not two integers joined by ``_``.
    """
    match = _TILE_ID_RE.match(tid)
    if match is None:
        raise ValueError(f"not a tile id (expected '<ix>_<iy>'): {tid!r}")
    return int(match.group(1)), int(match.group(2))


# --------------------------------------------------------------------------------------------
# snapshots
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TileBounds:
    """Where a tile is: its nominal cell and the box around its points (map frame, metres).

    Attributes
    ----------
    cell_min_xy:
        ``(ix * tile, iy * tile)``: the cell's lower corner, inclusive, integer metres (the corner
        Autoware's metadata lists).
    cell_max_xy:
        ``((ix + 1) * tile, (iy + 1) * tile)``: the upper corner, exclusive.
    min_xyz, max_xyz:
        Per-axis minimum and maximum of the tile's points (float32 values widened to float).
    """

    cell_min_xy: tuple[int, int]
    cell_max_xy: tuple[int, int]
    min_xyz: tuple[float, float, float]
    max_xyz: tuple[float, float, float]


@dataclass(frozen=True, eq=False)
class Tile:
    """An immutable snapshot of one tile.

    Attributes
    ----------
    ix, iy:
        Tile indices: the tile covers ``[ix * tile, (ix + 1) * tile)`` in x, likewise in y.
    version:
        Incremented on every change of the tile's content; 1 for a tile's first content.
    points:
        (N, 3) float32 positions in the map frame, metres; a read-only view (columns 0-2 of the
        tile's (N, 4) x,y,z,intensity buffer). Sorted by voxel, first arrivals first within a
        voxel.
    intensity:
        (N,) float32 return intensity (zeros where scans had none); a read-only view (column 3).
    bounds:
        The nominal cell and the box around ``points``.
    table:
        (N, 4) float32 ``x y z intensity``, read-only, that ``points`` and ``intensity`` view (a
        grid's tiles share it with their buffer); ``None``: :attr:`xyzi` builds one.
    """

    ix: int
    iy: int
    version: int
    points: np.ndarray
    intensity: np.ndarray
    bounds: TileBounds
    table: np.ndarray | None = field(default=None, repr=False)

    @property
    def xyzi(self) -> np.ndarray:
        """(N, 4) float32 ``x y z intensity``: what a tile's PCD file and tile update hold, with
        no copy for a grid's tiles."""
        if self.table is not None:
            return self.table
        xyzi = np.empty((self.n_points, 4), dtype=np.float32)
        xyzi[:, :3] = self.points
        xyzi[:, 3] = self.intensity
        return xyzi

    @property
    def id(self) -> str:
        """``"<ix>_<iy>"``."""
        return tile_id(self.ix, self.iy)

    @property
    def n_points(self) -> int:
        """Number of points ``N``."""
        return int(self.points.shape[0])

    def to_cloud(self) -> PointCloud:
        """The tile's points as a :class:`~randt.core.io.PointCloud` (xyz widened to float64)."""
        return PointCloud(xyz=self.points, intensity=self.intensity)


@dataclass(frozen=True)
class _TileState:
    """A tile and the buffer behind it: ``buf`` (capacity, 4) float32 x,y,z,intensity, whose
    first ``tile.n_points`` rows are the tile's points in arrival order. Rows past them are free:
    an insert appends there (a snapshot's read-only views of the first rows never change) and
    allocates a larger buffer when it is full (older snapshots keep the old one)."""

    tile: Tile
    buf: np.ndarray


def _readonly(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


def _tile_with_bounds(
    ix: int, iy: int, version: int, xyzi: np.ndarray, t: int, lo: Sequence[float], hi: Sequence[float]
) -> Tile:
    bounds = TileBounds(
        cell_min_xy=(ix * t, iy * t),
        cell_max_xy=((ix + 1) * t, (iy + 1) * t),
        min_xyz=(float(lo[0]), float(lo[1]), float(lo[2])),
        max_xyz=(float(hi[0]), float(hi[1]), float(hi[2])),
    )
    return Tile(
        ix=ix,
        iy=iy,
        version=version,
        points=_readonly(xyzi[:, :3]),
        intensity=_readonly(xyzi[:, 3]),
        bounds=bounds,
        table=_readonly(xyzi),
    )


def _appended(state: _TileState | None, rows: np.ndarray) -> np.ndarray:
    """The buffer that holds ``state``'s rows and ``rows`` after them (the same buffer while it
    has room; else one 1.5x larger, or exactly large enough for a new tile's first rows)."""
    n = 0 if state is None else state.tile.n_points
    need = n + rows.shape[0]
    if state is not None and need <= state.buf.shape[0]:
        buf = state.buf
    else:
        capacity = need if state is None else max(need, int(1.5 * state.buf.shape[0]) + 64)
        buf = np.empty((capacity, 4), dtype=np.float32)
        if state is not None:
            buf[:n] = state.buf[:n]
    buf[n:need] = rows
    return buf


# --------------------------------------------------------------------------------------------
# the grid
# --------------------------------------------------------------------------------------------


def _tile_keys(tile_ids: Iterable[str]) -> np.ndarray:
    """The grid's packed tile keys of tile ids (as :meth:`TileGrid._keys` computes them)."""
    wanted = np.array(sorted(parse_tile_id(tid) for tid in tile_ids), dtype=np.int64).reshape(-1, 2)
    return ((wanted[:, 0] + _TILE_OFFSET) << 31) | (wanted[:, 1] + _TILE_OFFSET)


class TileGrid:
    """A tiled, density-equalized global map (see the module docstring for the policy).

    Parameters
    ----------
    tile_size_m:
        Edge of the square tiles, whole metres (integer-metre tile origins), > 0.
    voxel_size_m:
        Edge of the equalization voxels, metres, > 0. Voxels are aligned to each tile's corner;
        choose a divisor of ``tile_size_m`` to keep them all whole.
    max_points_per_voxel:
        The density cap: points kept per voxel, >= 1.

    Raises
    ------
    ValueError
        A parameter is out of range (or ``tile_size_m`` is not a whole number).

    Examples
    --------
    >>> grid = TileGrid(tile_size_m=20, voxel_size_m=0.5)
    >>> grid.insert(np.array([[1.0, 2.0, 0.0], [25.0, -3.0, 1.0]]))
    ['0_0', '1_-1']
    >>> grid.tile(1, -1).bounds.cell_min_xy
    (20, -20)
    """

    def __init__(
        self, tile_size_m: int = 20, voxel_size_m: float = 0.2, max_points_per_voxel: int = 1
    ) -> None:
        if isinstance(tile_size_m, bool) or not float(tile_size_m).is_integer() or tile_size_m <= 0:
            raise ValueError(f"tile_size_m must be a positive whole number of metres, got {tile_size_m!r}")
        if not (math.isfinite(voxel_size_m) and voxel_size_m > 0):
            raise ValueError(f"voxel_size_m must be positive, got {voxel_size_m!r}")
        if voxel_size_m > tile_size_m:
            raise ValueError(f"voxel_size_m ({voxel_size_m}) must not exceed tile_size_m ({tile_size_m})")
        if isinstance(max_points_per_voxel, bool) or int(max_points_per_voxel) != max_points_per_voxel:
            raise ValueError(f"max_points_per_voxel must be an integer, got {max_points_per_voxel!r}")
        if max_points_per_voxel < 1:
            raise ValueError(f"max_points_per_voxel must be >= 1, got {max_points_per_voxel}")
        self._tile_size = int(tile_size_m)
        self._voxel = float(voxel_size_m)
        self._cap = int(max_points_per_voxel)
        self._lock = threading.Lock()
        self._tiles: dict[tuple[int, int], _TileState] = {}
        #: Every occupied (tile, voxel) with its count (randt.core.kernels.voxel_table_admit): the
        #: equalization's memory, so an insert costs its own points, not the tiles' (O(new)).
        self._table = _empty_voxel_table(self._cap)
        self._used = 0
        #: Every (tile, column of :data:`COLUMN_M`) holding a point, the same way (a count of one):
        #: where the map has content, for :meth:`agreement`.
        self._columns = _empty_voxel_table(1)
        self._n_columns = 0
        #: This grid (:attr:`uid`, unique in the process) and how often voxels left it
        #: (:attr:`generation`, advanced by :meth:`refold`): :attr:`content_token`.
        self._uid = next(_grid_uids)
        self._generation = 0
        #: A new tile's first version is ``version_floor + 1`` (0: versions start at 1). A store
        #: sets it for a map whose name an earlier, deleted map had, so versions never repeat.
        self.version_floor = 0

    def __repr__(self) -> str:
        return (
            f"TileGrid(tile_size_m={self._tile_size}, voxel_size_m={self._voxel:g}, "
            f"max_points_per_voxel={self._cap}; {len(self._tiles)} tiles, {self.n_points} points)"
        )

    # ---------------------------------------------------------------------------- settings

    @property
    def tile_size_m(self) -> int:
        """Edge of the square tiles, metres."""
        return self._tile_size

    @property
    def voxel_size_m(self) -> float:
        """Edge of the equalization voxels, metres."""
        return self._voxel

    @property
    def max_points_per_voxel(self) -> int:
        """The density cap."""
        return self._cap

    @property
    def content_token(self) -> tuple[int, int]:
        """``(uid, generation)``: equal for two reads only if no voxel left this grid between
        them (inserts only add). :class:`SentVoxels` of a session start over when it changes."""
        with self._lock:
            return self._uid, self._generation

    # ---------------------------------------------------------------------------- insert

    def insert(
        self,
        points_xyz: np.ndarray,
        intensity: np.ndarray | None = None,
        *,
        only_tiles: Iterable[str] | None = None,
    ) -> list[str]:
        """Fold registered points into the map, keeping at most the cap per voxel.

        Parameters
        ----------
        points_xyz:
            (N, 3) positions in the map frame, metres (any real dtype; rounded to float32).
            Points with a non-finite coordinate are dropped.
        intensity:
            (N,) return intensity, or ``None`` (stored as zeros).
        only_tiles:
            Ids of the only tiles points may go to (the others' points are ignored): inserting
            batches one after another into an empty grid with the same ``only_tiles`` gives what
            one :meth:`refold` of their concatenation gives, without holding all of them at once.

        Returns
        -------
        list[str]
            Ids of the tiles whose content changed (each got ``version + 1``), sorted by
            ``(ix, iy)``. Tiles whose voxels were already full are not listed.

        Raises
        ------
        InvalidCloudError
            Wrong shapes, or coordinates too far from the origin to be a map frame.
        """
        xyz, inten = _validated_float32(points_xyz, intensity)
        if xyz.shape[0] == 0:
            return []
        tkeys, vkeys = self._keys(xyz)
        if only_tiles is not None:
            keep = np.flatnonzero(np.isin(tkeys, _tile_keys(only_tiles)))
            xyz, inten, tkeys, vkeys = xyz[keep], inten[keep], tkeys[keep], vkeys[keep]
            if xyz.shape[0] == 0:
                return []
        with self._lock:
            accept = self._admit(tkeys, vkeys, xyz)
            changed = self._append(np.flatnonzero(accept), tkeys, xyz, inten)
            self._add_columns(xyz[accept])
        logger.debug(
            "insert: %d points, %d kept, %d tiles changed", xyz.shape[0], int(accept.sum()), len(changed)
        )
        return [tile_id(ix, iy) for ix, iy in sorted(changed)]

    def _keys(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tile keys and tile-local voxel keys of float32 points (randt.core.kernels.tile_voxel_keys)."""
        tkeys, vkeys, ok = tile_voxel_keys(
            np.ascontiguousarray(xyz, dtype=np.float32), float(self._tile_size), self._voxel, _TILE_OFFSET
        )
        if not ok:
            raise InvalidCloudError(
                f"points span more than {(1 << 21) - 1} voxels along an axis; use a larger voxel size"
            )
        return tkeys, vkeys

    def _admit(self, tkeys: np.ndarray, vkeys: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """Which points the policy keeps, in arrival order, against the voxels held (under the
        lock; the table records them)."""
        accept, self._table, self._used = _admitted(self._table, self._used, tkeys, vkeys, xyz, self._cap)
        return accept

    def _append(
        self, rows: np.ndarray, tkeys: np.ndarray, xyz: np.ndarray, inten: np.ndarray
    ) -> list[tuple[int, int]]:
        """Append the admitted ``rows`` to their tiles (under the lock); returns the tiles changed."""
        if rows.size == 0:
            return []
        order, uniq, starts = group_int_keys(tkeys[rows])
        grouped = rows[order]  # tile by tile, arrival order within each
        xyzi = np.empty((rows.size, 4), dtype=np.float32)
        xyzi[:, :3] = xyz[grouped]
        xyzi[:, 3] = inten[grouped]
        # every touched tile's new bounds in two calls, not two per tile
        firsts = starts[:-1]
        los = np.minimum.reduceat(xyzi[:, :3], firsts, axis=0).tolist()
        his = np.maximum.reduceat(xyzi[:, :3], firsts, axis=0).tolist()
        t = self._tile_size
        changed = []
        for g, key in enumerate(uniq.tolist()):
            ix, iy = (key >> 31) - _TILE_OFFSET, (key & ((1 << 31) - 1)) - _TILE_OFFSET
            new_rows = xyzi[starts[g] : starts[g + 1]]
            old = self._tiles.get((ix, iy))
            buf = _appended(old, new_rows)
            n = new_rows.shape[0] + (0 if old is None else old.tile.n_points)
            lo, hi = los[g], his[g]
            if old is None:
                version = self.version_floor + 1
            else:
                version = old.tile.version + 1
                lo = [min(a, b) for a, b in zip(lo, old.tile.bounds.min_xyz, strict=True)]
                hi = [max(a, b) for a, b in zip(hi, old.tile.bounds.max_xyz, strict=True)]
            tile = _tile_with_bounds(ix, iy, version, buf[:n], t, lo, hi)
            self._tiles[(ix, iy)] = _TileState(tile, buf)
            changed.append((ix, iy))
        return changed

    def refold(
        self, tile_ids: Iterable[str], points_xyz: np.ndarray, intensity: np.ndarray | None = None
    ) -> list[str]:
        """Replace the content of the tiles ``tile_ids`` by the points given that fall in them,
        equalized as an insert into empty tiles would (the pose graph moved the keyframes whose
        points make these tiles: the service re-folds them, docs/mapping.md).

        Each replaced tile's version advances by one. A listed tile that no given point falls in
        keeps its content (an empty tile is never written); points outside the listed tiles are
        ignored. Returns the ids of the tiles replaced, sorted by ``(ix, iy)``.

        Raises
        ------
        InvalidCloudError
            As :meth:`insert`; a malformed tile id is a ``ValueError``.
        """
        wanted = {parse_tile_id(tid) for tid in tile_ids}
        xyz, inten = _validated_float32(points_xyz, intensity)
        if not wanted or xyz.shape[0] == 0:
            return []
        tkeys, vkeys = self._keys(xyz)
        keep = np.flatnonzero(np.isin(tkeys, _tile_keys(tile_id(ix, iy) for ix, iy in wanted)))
        if keep.size == 0:
            return []
        xyz, inten, tkeys, vkeys = xyz[keep], inten[keep], tkeys[keep], vkeys[keep]
        hit = np.unique(tkeys)  # the listed tiles some point falls in: replaced
        with self._lock:
            versions: dict[tuple[int, int], int] = {}
            for key in hit.tolist():
                ix, iy = (key >> 31) - _TILE_OFFSET, (key & ((1 << 31) - 1)) - _TILE_OFFSET
                old = self._tiles.pop((ix, iy), None)
                if old is None:
                    continue
                versions[(ix, iy)] = old.tile.version
                old_tk, old_vk = self._keys(old.tile.points)
                self._used -= voxel_table_forget(*self._table, old_tk, old_vk)
                self._n_columns -= voxel_table_forget(*self._columns, *self._column_keys(old.tile.points))
            self._generation += bool(versions)  # voxels left the map (SentVoxels start over)
            accept = self._admit(tkeys, vkeys, xyz)
            changed = self._append(np.flatnonzero(accept), tkeys, xyz, inten)
            self._add_columns(xyz[accept])
            for key in changed:
                if key in versions:  # a replaced tile's version goes on from its own
                    state = self._tiles[key]
                    self._tiles[key] = _TileState(replace(state.tile, version=versions[key] + 1), state.buf)
        return [tile_id(ix, iy) for ix, iy in sorted(changed)]

    def _column_keys(self, xyz32: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tile keys and tile-local column keys (:data:`COLUMN_M`, z = 0) of float32 points."""
        flat = np.array(xyz32, dtype=np.float32)
        flat[:, 2] = 0.0
        tkeys, ckeys, _ = tile_voxel_keys(flat, float(self._tile_size), COLUMN_M, _TILE_OFFSET)
        return tkeys, ckeys  # (in range wherever the voxel keys were)

    def _add_columns(self, xyz32: np.ndarray) -> None:
        """Record the columns of points just admitted (under the lock)."""
        if xyz32.shape[0]:
            tkeys, ckeys = self._column_keys(xyz32)
            _, self._columns, self._n_columns = _admitted(
                self._columns, self._n_columns, tkeys, ckeys, xyz32, 1
            )

    def agreement(self, points_xyz: np.ndarray, reach_m: float = 0.5) -> Agreement:
        """How well points (a registered sweep, map frame) agree with the map where it has content.

        A point is *checked* when the map holds a point in its column (:data:`COLUMN_M` square,
        any height): a place the map has seen. A checked point *agrees* when the map holds a
        voxel within ``reach_m`` of it in x and y (whole voxels, at least one) and within one
        voxel in z. Both are hashed lookups in the tables the map keeps for its equalization
        (no pass over the map's points): a few milliseconds for a sweep's ten thousand points.
        Ground points agree with almost any place; drop them first (:func:`above_ground`).
        """
        xyz = np.asarray(points_xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InvalidCloudError(f"points_xyz must be (N, 3), got shape {xyz.shape}")
        xyz = np.ascontiguousarray(xyz[np.all(np.isfinite(xyz), axis=1)])
        flat = xyz.copy()
        flat[:, 2] = 0.0
        reach = max(1, round(reach_m / self._voxel))
        t = float(self._tile_size)
        with self._lock:
            cols, vox = self._columns, self._table
            seen = voxel_table_near(cols[0], cols[1], flat, t, COLUMN_M, _TILE_OFFSET, 0, 0)
            near = voxel_table_near(vox[0], vox[1], xyz[seen], t, self._voxel, _TILE_OFFSET, reach, 1)
        return Agreement(int(seen.sum()), int(near.sum()))

    def near_numpy(self, points_xyz: np.ndarray, reach_xy: int, reach_z: int) -> np.ndarray:
        """Numpy reference of :func:`randt.core.kernels.voxel_table_near` against this map's voxels:
        for each point (float64, map frame), whether the map holds a point in a voxel within
        ``reach_xy`` voxel steps in x and y and ``reach_z`` in z (structured-row ``np.isin``)."""
        pair = [("t", "<i8"), ("v", "<i8")]
        tiles = self.tiles()
        held = np.concatenate([t.points for t in tiles]) if tiles else np.empty((0, 3), np.float32)
        _, _, tk, vk = self._candidate_keys(held, compiled=False) or (None, None, np.empty(0), np.empty(0))
        have = np.ascontiguousarray(np.c_[tk, vk].astype(np.int64)).view(pair).ravel()
        xyz = np.asarray(points_xyz, dtype=np.float64)
        out = np.zeros(xyz.shape[0], dtype=bool)
        t, v = float(self._tile_size), self._voxel
        steps = np.arange(-reach_xy, reach_xy + 1)
        for dx, dy, dz in itertools.product(steps, steps, np.arange(-reach_z, reach_z + 1)):
            moved = xyz + np.array([dx, dy, dz]) * v
            txy = np.floor(moved[:, :2] / t).astype(np.int64)
            local = moved.copy()
            local[:, :2] -= txy * t
            tkeys = ((txy[:, 0] + _TILE_OFFSET) << 31) | (txy[:, 1] + _TILE_OFFSET)
            keys = np.c_[tkeys, pack_keys(voxel_coords(local, v))]
            out |= np.isin(np.ascontiguousarray(keys).view(pair).ravel(), have)
        return out

    def candidate_mask(self, points_xyz: np.ndarray) -> np.ndarray:
        """Which of a scan's points :meth:`insert` could keep, whatever the map already holds.

        True for the first ``max_points_per_voxel`` distinct points of each (tile, voxel) in
        arrival order (non-finite rows are False). Inserting only these points leaves the map
        exactly as inserting them all would, because :meth:`insert` keeps first arrivals and never
        more than the cap per voxel. Depends only on the grid's sizes and cap, not its content, so
        it can run elsewhere (the service's matcher processes do it, cutting the points the service
        process inserts about fourfold on a KITTI sweep with a cap of 1). One compiled hashed pass
        (:func:`randt.core.kernels.first_per_voxel_pair`); :meth:`candidate_mask_numpy` is the tested
        reference.
        """
        mask = np.zeros(np.asarray(points_xyz).shape[0], dtype=bool)
        keys = self._candidate_keys(points_xyz, compiled=True)
        if keys is None:
            return mask
        finite, f32, tkeys, vkeys = keys
        mask[finite[first_per_voxel_pair(tkeys, vkeys, f32, self._cap)]] = True
        return mask

    def _candidate_keys(
        self, points_xyz: np.ndarray, *, compiled: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """(finite row indices, their float32 positions, tile keys, tile-local voxel keys): exactly
        :meth:`insert`'s keys, by :func:`randt.core.kernels.tile_voxel_keys` or (``compiled=False``) by
        insert's numpy formulation. None when no row is finite."""
        xyz = np.asarray(points_xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InvalidCloudError(f"points_xyz must be (N, 3), got shape {xyz.shape}")
        finite = np.flatnonzero(np.all(np.isfinite(xyz), axis=1))
        if finite.size == 0:
            return None
        f32 = np.ascontiguousarray(xyz[finite].astype(np.float32))
        if compiled:
            tkeys, vkeys, ok = tile_voxel_keys(f32, float(self._tile_size), self._voxel, _TILE_OFFSET)
            if not ok:
                raise InvalidCloudError(
                    f"points span more than {(1 << 21) - 1} voxels along an axis; use a larger voxel size"
                )
            return finite, f32, tkeys, vkeys
        t = float(self._tile_size)
        local = f32.astype(np.float64)
        txy = np.floor(local[:, :2] / t).astype(np.int64)
        local[:, :2] -= txy * t
        vkeys = pack_keys(voxel_coords(local, self._voxel))
        tkeys = ((txy[:, 0] + _TILE_OFFSET) << 31) | (txy[:, 1] + _TILE_OFFSET)
        return finite, f32, tkeys, vkeys

    def candidate_mask_numpy(self, points_xyz: np.ndarray) -> np.ndarray:
        """Vectorized numpy reference of :meth:`candidate_mask` (two ``np.lexsort`` calls)."""
        mask = np.zeros(np.asarray(points_xyz).shape[0], dtype=bool)
        keys = self._candidate_keys(points_xyz, compiled=False)
        if keys is None:
            return mask
        finite, f32, tkeys, vkeys = keys
        arrival = np.arange(finite.size)
        if self._cap > 1:
            # Exact duplicates within a voxel count once (insert drops them): keep first arrivals.
            o = np.lexsort((arrival, f32[:, 2], f32[:, 1], f32[:, 0], vkeys, tkeys))
            dup = (
                (tkeys[o][1:] == tkeys[o][:-1])
                & (vkeys[o][1:] == vkeys[o][:-1])
                & np.all(f32[o][1:] == f32[o][:-1], axis=1)
            )
            distinct = np.ones(finite.size, dtype=bool)
            distinct[o[1:][dup]] = False
        else:
            distinct = np.ones(finite.size, dtype=bool)
        o = np.lexsort((arrival, vkeys, tkeys))
        o = o[distinct[o]]
        tk, vk = tkeys[o], vkeys[o]
        position = np.arange(o.size)
        first = np.r_[True, (tk[1:] != tk[:-1]) | (vk[1:] != vk[:-1])] if o.size else np.zeros(0, bool)
        rank = position - np.maximum.accumulate(np.where(first, position, 0))
        mask[finite[o[rank < self._cap]]] = True
        return mask

    # ---------------------------------------------------------------------------- accessors

    def _snapshot(self) -> list[Tile]:
        """The current tiles sorted by ``(ix, iy)`` (a consistent set, taken under the lock)."""
        with self._lock:
            states = list(self._tiles.items())
        return [state.tile for _, state in sorted(states, key=lambda item: item[0])]

    def __len__(self) -> int:
        return len(self._tiles)

    def __contains__(self, tid: object) -> bool:
        if not isinstance(tid, str):
            return False
        try:
            return parse_tile_id(tid) in self._tiles
        except ValueError:
            return False

    def tile_ids(self) -> list[str]:
        """Ids of the non-empty tiles, sorted by ``(ix, iy)``."""
        return [t.id for t in self._snapshot()]

    def tiles(self) -> list[Tile]:
        """Snapshots of every non-empty tile, sorted by ``(ix, iy)``."""
        return self._snapshot()

    def tile(self, ix: int, iy: int) -> Tile:
        """The snapshot of tile ``(ix, iy)``.

        Raises
        ------
        NotFoundError
            The tile holds no points.
        """
        state = self._tiles.get((int(ix), int(iy)))
        if state is None:
            raise NotFoundError(f"tile {tile_id(ix, iy)} does not exist (holds no points)")
        return state.tile

    def get(self, tid: str) -> Tile:
        """The snapshot of the tile with id ``"<ix>_<iy>"``.

        Raises
        ------
        NotFoundError
            No such tile (or ``tid`` is not a tile id).
        """
        try:
            ix, iy = parse_tile_id(tid)
        except ValueError as exc:
            raise NotFoundError(str(exc)) from exc
        return self.tile(ix, iy)

    def tile_of(self, x: float, y: float) -> tuple[int, int]:
        """Indices ``(ix, iy)`` of the tile owning the map-frame point ``(x, y)`` (after float32 rounding)."""
        xy = np.array([x, y], dtype=np.float32).astype(np.float64)
        ix, iy = np.floor(xy / self._tile_size).astype(np.int64)
        return int(ix), int(iy)

    @property
    def n_points(self) -> int:
        """Total number of points over all tiles."""
        return sum(t.n_points for t in self._snapshot())

    @property
    def extent(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(min_xyz, max_xyz)``, each (3,) float64 metres, of all points; ``None`` when empty."""
        tiles = self._snapshot()
        if not tiles:
            return None
        lo = np.min([t.bounds.min_xyz for t in tiles], axis=0).astype(np.float64)
        hi = np.max([t.bounds.max_xyz for t in tiles], axis=0).astype(np.float64)
        return lo, hi

    # ---------------------------------------------------------------------------- queries

    def _cell_corners(self, tiles: list[Tile]) -> np.ndarray:
        """(T, 2) float64 lower cell corners of ``tiles``, metres."""
        ij = np.array([(t.ix, t.iy) for t in tiles], dtype=np.float64).reshape(-1, 2)
        return ij * self._tile_size

    def _tiles_in_bbox(self, min_xy: Iterable[float], max_xy: Iterable[float]) -> list[Tile]:
        lo = np.asarray(tuple(min_xy), dtype=np.float64)
        hi = np.asarray(tuple(max_xy), dtype=np.float64)
        if lo.shape != (2,) or hi.shape != (2,):
            raise ValueError("min_xy and max_xy must be (x, y) pairs")
        if np.any(lo > hi):
            raise ValueError(f"min_xy {tuple(lo)} exceeds max_xy {tuple(hi)}")
        tiles = self._snapshot()
        corner = self._cell_corners(tiles)
        # Half-open cell [c, c + tile) meets the closed box [lo, hi] on both axes.
        hit = np.all((corner <= hi) & (corner + self._tile_size > lo), axis=1)
        return [t for t, h in zip(tiles, hit, strict=True) if h]

    def tiles_in_bbox(self, min_xy: Iterable[float], max_xy: Iterable[float]) -> list[str]:
        """Ids of the non-empty tiles whose cell meets the closed box ``[min_xy, max_xy]``.

        A cell is half-open, so a box ending exactly at ``x = 20`` reaches tile 1 (which owns
        ``x = 20``) and a box starting at ``x = 20`` does not reach tile 0.

        Parameters
        ----------
        min_xy, max_xy:
            (x, y) corners of the box in the map frame, metres, ``min_xy <= max_xy``.

        Raises
        ------
        ValueError
            Malformed or inverted box.
        """
        return [t.id for t in self._tiles_in_bbox(min_xy, max_xy)]

    def points_in_bbox(self, min_xy: Iterable[float], max_xy: Iterable[float]) -> PointCloud:
        """The points with ``min_xy <= (x, y) <= max_xy`` (any z), tile by tile in ``(ix, iy)`` order.

        Returns
        -------
        PointCloud
            ``xyz`` (M, 3) float64 (float32 values widened), ``intensity`` (M,) float32; M may be 0.
        """
        lo = np.asarray(tuple(min_xy), dtype=np.float64)
        hi = np.asarray(tuple(max_xy), dtype=np.float64)
        xyz_parts: list[np.ndarray] = [np.empty((0, 3), dtype=np.float32)]
        int_parts: list[np.ndarray] = [np.empty(0, dtype=np.float32)]
        for t in self._tiles_in_bbox(lo, hi):
            xy = t.points[:, :2].astype(np.float64)
            inside = np.all((xy >= lo) & (xy <= hi), axis=1)
            xyz_parts.append(t.points[inside])
            int_parts.append(t.intensity[inside])
        return PointCloud(xyz=np.concatenate(xyz_parts), intensity=np.concatenate(int_parts))

    def tiles_within_radius(self, center_xy: Iterable[float], radius_m: float) -> list[str]:
        """Ids of the non-empty tiles whose cell comes within ``radius_m`` of ``center_xy`` in XY.

        This is the cylinder query of Autoware's partial map loading: a tile counts when the
        nearest point of its (closed) cell is at most ``radius_m`` from the centre.

        Parameters
        ----------
        center_xy:
            (x, y) in the map frame, metres.
        radius_m:
            Radius, metres, >= 0.

        Raises
        ------
        ValueError
            Negative or non-finite radius, or a malformed centre.
        """
        c = np.asarray(tuple(center_xy), dtype=np.float64)
        if c.shape != (2,):
            raise ValueError("center_xy must be an (x, y) pair")
        if not (math.isfinite(radius_m) and radius_m >= 0):
            raise ValueError(f"radius_m must be finite and >= 0, got {radius_m!r}")
        return [t.id for t in self.tiles_near(c, radius_m)]

    def tiles_near(self, center_xy: Iterable[float], radius_m: float) -> list[Tile]:
        """The snapshots of :meth:`tiles_within_radius` (same order), taken together."""
        c = np.asarray(tuple(center_xy), dtype=np.float64)
        tiles = self._snapshot()
        corner = self._cell_corners(tiles)
        gap = np.maximum(np.maximum(corner - c, c - (corner + self._tile_size)), 0.0)
        hit = np.hypot(gap[:, 0], gap[:, 1]) <= radius_m
        return [t for t, h in zip(tiles, hit, strict=True) if h]

    # ---------------------------------------------------------------------------- metrics

    def tile_pdu(self, voxel_size_m: float | None = None) -> dict[str, float]:
        """Point Density Uniformity of every tile: ``1 - std / mean`` of its voxel point counts.

        :func:`randt.core.metrics.cloud.pdu` of each tile's points: counts over the tile's occupied voxels,
        population standard deviation. The points are shifted to the tile's corner first, so the
        voxels are aligned to it as the equalization voxels are. With the default voxel size
        and a cap of 1 every tile scores exactly 1; pass a coarser voxel to see how evenly the
        equalized points cover a tile.

        Parameters
        ----------
        voxel_size_m:
            Voxel edge, metres; ``None`` uses the grid's ``voxel_size_m``.

        Returns
        -------
        dict[str, float]
            Tile id -> PDU (<= 1; 1 is perfectly uniform).
        """
        v = self._voxel if voxel_size_m is None else float(voxel_size_m)
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"voxel_size_m must be positive, got {voxel_size_m!r}")
        out: dict[str, float] = {}
        for t in self._snapshot():
            local = t.points.astype(np.float64)
            local[:, :2] -= np.array(t.bounds.cell_min_xy, dtype=np.float64)
            out[t.id] = pdu(local, v)
        return out

    # ---------------------------------------------------------------------------- export

    def to_cloud(self) -> PointCloud:
        """All points, tile by tile in ``(ix, iy)`` order, as one :class:`~randt.core.io.PointCloud`."""
        tiles = self._snapshot()
        return PointCloud(
            xyz=np.concatenate([np.empty((0, 3), np.float32)] + [t.points for t in tiles]),
            intensity=np.concatenate([np.empty(0, np.float32)] + [t.intensity for t in tiles]),
        )

    def export_merged(self, path: str | os.PathLike[str]) -> None:
        """Write the whole map as one ``.pcd`` or ``.ply`` (float32 ``x y z intensity``), atomically.

        Raises
        ------
        InvalidCloudError
            The map is empty.
        FormatError
            Unsupported suffix or the write failed.
        """
        cloud = self.to_cloud()
        if cloud.n_points == 0:
            raise InvalidCloudError("the map is empty: nothing to export")
        write_cloud(path, cloud)
        logger.info("exported %d points in %d tiles to %s", cloud.n_points, len(self._tiles), path)

    def export_autoware(self, directory: str | os.PathLike[str]) -> dict[str, list[int]]:
        """Write the map as an Autoware divided point-cloud map.

        Writes, each file atomically, ``<ix>_<iy>.pcd`` per non-empty tile (binary PCD, float32
        ``x y z intensity``), then :data:`~randt.core.io.autoware.GRID_SIDECAR_NAME`, then
        :data:`~randt.core.io.autoware.AUTOWARE_METADATA_NAME` last, so the metadata never names a
        missing file. Stale ``<ix>_<iy>.pcd`` files of tiles no longer in the map are removed
        afterwards (Autoware globs every ``*.pcd`` of the directory); other ``.pcd`` files are
        left alone with a warning.

        Parameters
        ----------
        directory:
            Target directory; created if missing.

        Returns
        -------
        dict[str, list[int]]
            The tile entries of the metadata: PCD file name -> ``[x_min, y_min]`` integer metres.

        Raises
        ------
        InvalidCloudError
            The map is empty.
        FormatError
            A file could not be written.
        """
        tiles = self._snapshot()
        if not tiles:
            raise InvalidCloudError("the map is empty: nothing to export")
        directory = make_directory(directory)
        for t in tiles:
            write_tile_table(directory, t.id, t.xyzi)
        self._write_sidecar(directory, tiles)
        entries = write_metadata(directory, self._tile_size, _corners(tiles))
        remove_stale_tile_files(directory, entries)
        logger.info(
            "exported %d tiles (%d points) to %s", len(tiles), sum(t.n_points for t in tiles), directory
        )
        return entries

    def write_tiles(
        self, directory: str | os.PathLike[str], tile_ids: Iterable[str], *, tiles: list[Tile] | None = None
    ) -> list[str]:
        """Update an Autoware divided map in place: sidecar, the named tiles, metadata last.

        The incremental counterpart of :meth:`export_autoware` for a directory that holds an
        earlier save of this map. From one snapshot of the map it writes, each file atomically:

        1. :data:`~randt.core.io.autoware.GRID_SIDECAR_NAME` (settings and the version of every tile);
        2. ``<ix>_<iy>.pcd`` of every named tile, and of every tile whose file is missing (a first
           save, or a tile the caller forgot), so the directory always holds every tile;
        3. :data:`~randt.core.io.autoware.AUTOWARE_METADATA_NAME` last, listing every tile of the map.

        Other tile files are neither rewritten nor removed. A reader (or a restart after a crash at
        any point) therefore sees whole files only, and a metadata file that names only existing
        tile files. The sidecar goes first so that recorded versions are never *older* than the
        content on disk: after a crash between steps 1 and 3 a tile may be restored with the new
        version and its previous content (its next change bumps the version again, and a
        subscriber at worst refetches a tile it had), never with new content under an old version
        that subscribers would take for the one they already hold.

        Parameters
        ----------
        directory:
            Target directory; created if missing.
        tile_ids:
            Ids ``"<ix>_<iy>"`` of the tiles whose content changed since the last save (as
            :meth:`insert` returns them); may be empty.
        tiles:
            The snapshot to write (what :meth:`tiles` returned); ``None``: take one now. A caller
            that serves exactly what it saved passes the snapshot it keeps.

        Returns
        -------
        list[str]
            Ids of the tiles whose PCD files were written, sorted by ``(ix, iy)``.

        Raises
        ------
        TypeError
            ``tile_ids`` is a single string instead of a collection of ids.
        NotFoundError
            A named tile is not in the map.
        InvalidCloudError
            The map is empty.
        FormatError
            A file could not be written.
        """
        if isinstance(tile_ids, str):
            raise TypeError(f"tile_ids must be a collection of tile ids, not the string {tile_ids!r}")
        tiles = self._snapshot() if tiles is None else sorted(tiles, key=lambda t: (t.ix, t.iy))
        if not tiles:
            raise InvalidCloudError("the map is empty: nothing to write")
        present = {t.id for t in tiles}
        wanted = set()
        for tid in tile_ids:
            if tid not in present:
                raise NotFoundError(f"tile {tid!r} is not in the map (holds no points)")
            wanted.add(tid)
        directory = make_directory(directory)
        self._write_sidecar(directory, tiles)
        written: list[str] = []
        for t in tiles:
            if t.id in wanted or not (directory / tile_file_name(t.id)).is_file():
                write_tile_table(directory, t.id, t.xyzi)
                written.append(t.id)
        write_metadata(directory, self._tile_size, _corners(tiles))
        logger.debug("wrote %d of %d tiles to %s", len(written), len(tiles), directory)
        return written

    def _write_sidecar(self, directory: Path, tiles: list[Tile]) -> None:
        """Write :data:`~randt.core.io.autoware.GRID_SIDECAR_NAME` for the snapshot ``tiles``."""
        write_sidecar(
            directory,
            tile_size_m=self._tile_size,
            voxel_size_m=self._voxel,
            max_points_per_voxel=self._cap,
            versions={t.id: t.version for t in tiles},
        )

    def _restore_version(self, key: tuple[int, int], version: int) -> None:
        with self._lock:
            state = self._tiles[key]
            tile = state.tile
            self._tiles[key] = _TileState(replace(tile, version=version), state.buf)


# --------------------------------------------------------------------------------------------
# Autoware divided maps (the files: randt.core.io.autoware)
# --------------------------------------------------------------------------------------------


class SentVoxels:
    """The voxels one session has already sent to its map, so that it sends only what the map
    could still keep.

    The map's own admission policy (:meth:`TileGrid.insert`: the first ``max_points_per_voxel``
    distinct points of each voxel, in arrival order) run against the points sent, without
    storing tiles. Every point sent reached the map, and inserts only add, so a point this
    refuses the map would refuse too: sending only the admitted ones leaves the map exactly as
    sending every point would. The service's matcher processes keep one per session, cutting
    what crosses to the service process, and what its insert handles, to the sweep's new voxels
    (docs/architecture.md).

    :meth:`admitted` starts over (forgets every voxel) when the map's ``token`` changes, i.e.
    voxels may have left the map (:attr:`TileGrid.content_token`: a re-fold) or the points go
    to another map or frame; and when more than ``max_voxels`` voxels are held (the memory
    bound, about 10 MB a session with the default 262,144 and a cap of 1: a vehicle adding about
    3,000 new voxels a sweep starts over every 8 s or so, and starting over only means sending
    one sweep's candidates once).
    """

    def __init__(
        self,
        tile_size_m: int = 20,
        voxel_size_m: float = 0.2,
        max_points_per_voxel: int = 1,
        max_voxels: int = 1 << 18,
    ) -> None:
        self._keys_of = TileGrid(tile_size_m, voxel_size_m, max_points_per_voxel)  # sizes, keys
        self._cap = int(max_points_per_voxel)
        self._max = int(max_voxels)
        self._token: object = None
        self._table = _empty_voxel_table(self._cap)
        self._used = 0

    def __len__(self) -> int:
        """Voxels held (sent since the last start)."""
        return self._used

    def admitted(self, points_xyz: np.ndarray, token: object) -> np.ndarray:
        """Which of ``points_xyz`` (map frame; any real dtype, rounded to float32 as the map
        stores them) the map could still keep, given everything admitted since the last start
        (non-finite rows: False); they are recorded as sent. ``token`` names the map's content
        and frame (compared with ``==``)."""
        if token != self._token or self._used > self._max:
            self._token, self._table, self._used = token, _empty_voxel_table(self._cap), 0
        mask = np.zeros(np.asarray(points_xyz).shape[0], dtype=bool)
        keys = self._keys_of._candidate_keys(points_xyz, compiled=True)
        if keys is None:
            return mask
        finite, f32, tkeys, vkeys = keys
        accept, self._table, self._used = _admitted(self._table, self._used, tkeys, vkeys, f32, self._cap)
        mask[finite[accept]] = True
        return mask


def _corners(tiles: list[Tile]) -> dict[str, tuple[int, int]]:
    """``tile id -> (x_min, y_min)`` integer metres of each tile's cell, for Autoware's metadata."""
    return {t.id: (int(t.bounds.cell_min_xy[0]), int(t.bounds.cell_min_xy[1])) for t in tiles}


def load_autoware(
    directory: str | os.PathLike[str],
    *,
    voxel_size_m: float | None = None,
    max_points_per_voxel: int | None = None,
) -> TileGrid:
    """Restore a :class:`TileGrid` from an Autoware divided map (ours or another tool's).

    The tile size comes from the metadata's resolutions. Voxel size, cap and tile versions come
    from :data:`~randt.core.io.autoware.GRID_SIDECAR_NAME` when present, else from the arguments, else the
    defaults of :class:`TileGrid`. A map exported by :meth:`TileGrid.export_autoware` and loaded with its own
    settings comes back identical: same points in the same order, same versions. Other settings
    re-equalize the points (and such tiles get ``version + 1`` so subscribers see the change).

    Parameters
    ----------
    directory:
        Holds ``pointcloud_map_metadata.yaml`` and the PCD files it names.
    voxel_size_m, max_points_per_voxel:
        Override the sidecar's settings.

    Raises
    ------
    NotFoundError
        The metadata or a PCD file it names does not exist.
    FormatError
        Malformed metadata (non-square or fractional tiles, bad corners) or sidecar, or an
        unreadable PCD file.
    """
    directory = Path(directory)
    tile, files = read_metadata(directory)
    saved, versions = read_sidecar(directory, tile)

    voxel = voxel_size_m if voxel_size_m is not None else saved.get("voxel_size_m", 0.2)
    cap = max_points_per_voxel if max_points_per_voxel is not None else saved.get("max_points_per_voxel", 1)
    try:
        grid = TileGrid(tile_size_m=tile, voxel_size_m=voxel, max_points_per_voxel=cap)
    except (TypeError, ValueError) as exc:
        raise FormatError(f"{directory}: invalid grid settings: {exc}") from exc
    saved_settings = (saved.get("voxel_size_m"), saved.get("max_points_per_voxel"))
    same_settings = bool(saved) and (voxel, cap) == saved_settings

    for name, (ix, iy) in sorted(files.items(), key=lambda item: item[1]):
        cloud = read_cloud(directory / name)
        xyz32 = cloud.xyz.astype(np.float32)
        owner = np.floor(xyz32[:, :2].astype(np.float64) / tile).astype(np.int64)
        outside = int(np.count_nonzero(np.any(owner != (ix, iy), axis=1)))
        if outside:
            logger.warning(
                "%s: %d of %d points lie outside its cell %s; they go to the tiles owning them",
                directory / name,
                outside,
                cloud.n_points,
                tile_id(ix, iy),
            )
        grid.insert(xyz32, cloud.intensity)

    for tid in grid.tile_ids():
        if tid in versions:
            grid._restore_version(parse_tile_id(tid), versions[tid] + (0 if same_settings else 1))
    logger.info("loaded %s: %s", directory, grid)
    return grid


def _validated_float32(points_xyz: np.ndarray, intensity: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) float32 finite points and (M,) float32 intensity; M <= N after dropping non-finite."""
    xyz = np.asarray(points_xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InvalidCloudError(f"points_xyz must be (N, 3), got shape {xyz.shape}")
    if xyz.dtype.kind not in "fiu":
        raise InvalidCloudError(f"points_xyz must be real numbers, got dtype {xyz.dtype}")
    n = xyz.shape[0]
    if intensity is None:
        inten = np.zeros(n, dtype=np.float32)
    else:
        inten = np.asarray(intensity, dtype=np.float32)
        if inten.shape != (n,):
            raise InvalidCloudError(
                f"intensity must have shape ({n},) to match points_xyz, got {inten.shape}"
            )
    if xyz.dtype == np.float32 and np.isfinite(xyz).all():  # what the matchers send: no widening
        lo, hi = (float(v) for v in (xyz.min(), xyz.max())) if n else (0.0, 0.0)
        # (z too first: cheaper than the x-y columns alone)
        if max(-lo, hi) > _MAX_ABS_XY_M and np.abs(xyz[:, :2]).max() > _MAX_ABS_XY_M:
            raise InvalidCloudError(
                f"coordinates up to {np.abs(xyz[:, :2]).max():.3g} m are not a local map frame "
                f"(limit {_MAX_ABS_XY_M:.0e} m)"
            )
        return np.ascontiguousarray(xyz), np.ascontiguousarray(inten)
    xyz64 = xyz.astype(np.float64, copy=False)
    finite = np.all(np.isfinite(xyz64), axis=1)
    if not np.all(finite):
        logger.debug("insert: dropping %d points with non-finite coordinates", n - int(finite.sum()))
        xyz64, inten = xyz64[finite], inten[finite]
    if xyz64.size and np.abs(xyz64[:, :2]).max() > _MAX_ABS_XY_M:
        raise InvalidCloudError(
            f"coordinates up to {np.abs(xyz64[:, :2]).max():.3g} m are not a local map frame "
            f"(limit {_MAX_ABS_XY_M:.0e} m)"
        )
    return xyz64.astype(np.float32), np.ascontiguousarray(inten)
