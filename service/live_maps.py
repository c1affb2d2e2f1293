"""The live maps: each map's tile grid, its tiles as last saved (what the outside sees), their
digests, the tiles waiting to be saved, and the map lifecycle (re-fold, merge, delete).

Tiles are served as saved (:class:`DurableMap`), so a version seen outside is on disk and never
goes back or repeats with other content after a crash (``docs/architecture.md``, "The store").
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from randt.core.errors import NotFoundError, RandtError
from randt.core.tiles import Tile, TileGrid
from randt.service.answers import Outbox
from randt.service.metrics import ServiceMetrics
from randt.service.store import Store
from randt.wire.messages import (
    TileUpdateMessage,
    points_digest,
    tile_update_from_arrays,
    tile_update_from_table,
)

__all__ = ["DurableMap", "LiveMaps", "tile_digest", "tile_message"]

log = logging.getLogger(__name__)

#: Digests kept at most (by map, tile and version: versions never repeat, so none goes stale).
DIGEST_CACHE = 100_000


@dataclass(frozen=True)
class DurableMap:
    """What the outside may see of a map: the tiles as last saved (every version in it is on
    disk, so it never goes back after a crash), with the live grid for its settings and cell
    geometry only (bbox and radius queries)."""

    name: str
    grid: TileGrid
    by_id: dict[str, Tile]

    @property
    def tile_size_m(self) -> int:
        return self.grid.tile_size_m

    @property
    def voxel_size_m(self) -> float:
        return self.grid.voxel_size_m

    def tiles(self) -> list[Tile]:
        """The saved tiles sorted by ``(ix, iy)``."""
        return sorted(self.by_id.values(), key=lambda t: (t.ix, t.iy))


class LiveMaps(Mapping[str, TileGrid]):
    """The service's maps by name (a read-only mapping of their live grids), what of them is saved,
    and what waits to be saved. Thread-safe; it calls nothing of the sessions."""

    def __init__(
        self,
        store: Store,
        loaded: dict[str, TileGrid],
        *,
        tile_size_m: int,
        voxel_size_m: float,
        default_map: str,
        metrics: ServiceMetrics,
        outbox: Outbox,
    ) -> None:
        self.store = store
        self.tile_size_m, self.voxel_size_m, self.default_map = tile_size_m, voxel_size_m, default_map
        self.metrics, self.outbox = metrics, outbox
        self._lock = threading.RLock()
        self._grids: dict[str, TileGrid] = dict(loaded)
        #: Per map, the tiles as last saved: what HTTP, the queryable and tile updates serve.
        self._durable: dict[str, dict[str, Tile]] = {}
        self._digests: dict[tuple[str, str, int], str] = {}
        for name, grid in self._grids.items():
            tiles = grid.tiles()
            try:
                grid.version_floor = self._version_floor(name)
            except RandtError as exc:  # damaged: continue above every version the map holds
                log.error("%s", exc)
                grid.version_floor = max((t.version for t in tiles), default=0)
            self._durable[name] = {t.id: t for t in tiles}
        #: Tiles the store held at start (and when the graph process was last restarted): points of
        #: sessions the (in-memory) pose graph never saw, so it never re-folds them (refold).
        self._before_graph: dict[str, set[str]] = {name: set(g.tile_ids()) for name, g in self._grids.items()}
        self._dirty: dict[str, set[str]] = {}
        #: Own maps of sessions that joined another map, merged into it: name -> (map, session).
        self._merged: dict[str, tuple[str, str]] = {}

    # -- the mapping of live grids ----------------------------------------------------------------
    def __getitem__(self, name: str) -> TileGrid:
        with self._lock:
            return self._grids[name]

    def __iter__(self) -> Iterator[str]:
        with self._lock:
            return iter(list(self._grids))

    def __len__(self) -> int:
        with self._lock:
            return len(self._grids)

    def grid(self, name: str) -> TileGrid:
        """The tiles of ``name``, an empty map with the settings' sizes if it is new."""
        with self._lock:
            grid = self._grids.get(name)
            if grid is None:
                grid = self._grids[name] = TileGrid(
                    tile_size_m=self.tile_size_m, voxel_size_m=self.voxel_size_m
                )
                grid.version_floor = self._version_floor(name)
                self._durable[name] = {}
            return grid

    def _version_floor(self, name: str) -> int:
        """The store's version floor of ``name`` (a deleted map's highest version)."""
        try:
            return self.store.version_floor(name)
        except (OSError, RandtError) as exc:
            # Unreadable: versions from 1 could repeat a deleted map's; refuse rather than lie.
            raise RandtError(f"map {name}: cannot read its version floor: {exc}") from exc

    def forget_if_empty(self, name: str, *, in_use: bool) -> None:
        """Drop ``name`` if it holds no tile and no session uses it (a frame left unused)."""
        with self._lock:
            grid = self._grids.get(name)
            if grid is not None and not grid.tile_ids() and not in_use and name != self.default_map:
                del self._grids[name]

    # -- what the outside sees ----------------------------------------------------------------------
    def durable(self, name: str) -> DurableMap | None:
        """The map as last saved, ``None`` if there is no such map."""
        with self._lock:
            grid = self._grids.get(name)
            if grid is None:
                return None
            return DurableMap(name, grid, dict(self._durable.get(name, {})))

    def all_durable(self) -> dict[str, DurableMap]:
        """Every map as last saved, by name."""
        with self._lock:
            return {n: DurableMap(n, g, dict(self._durable.get(n, {}))) for n, g in self._grids.items()}

    def tile_digest(self, name: str, tile: Tile) -> str:
        """:func:`tile_digest` of a tile, cached by ``(map, tile, version)`` (versions never repeat)."""
        digest = self._cached_digest(name, tile)
        if digest is None:
            digest = tile_digest(tile)
            self._remember_digest(name, tile, digest)
        return digest

    def _cached_digest(self, name: str, tile: Tile) -> str | None:
        with self._lock:
            return self._digests.get((name, tile.id, tile.version))

    def _remember_digest(self, name: str, tile: Tile, digest: str) -> None:
        with self._lock:
            if len(self._digests) > DIGEST_CACHE:
                self._digests.clear()
            self._digests[(name, tile.id, tile.version)] = digest

    def tile_message(self, name: str, tile: Tile) -> TileUpdateMessage:
        """The :class:`~randt.wire.messages.TileUpdateMessage` of a saved tile, with its digest (which
        its ETag names too: computed once, cached). The grid checked its points when they were
        inserted, so the message is built from its table without checking them again."""
        message = tile_update_from_table(
            name,
            tile.ix,
            tile.iy,
            tile.version,
            tile.xyzi,
            (tile.bounds.min_xyz, tile.bounds.max_xyz),
            self._cached_digest(name, tile),
        )
        if message.digest is not None:
            self._remember_digest(name, tile, message.digest)
        return message

    def merged_into(self, name: str) -> tuple[str, str] | None:
        """``(map, session)`` when ``name`` was merged into ``map`` as ``session`` joined it
        (since this service started), else None."""
        with self._lock:
            return self._merged.get(name)

    def note_merged(self, own: str, into: str, session: str) -> None:
        """``own`` was merged into ``into`` before this service started (the graph's log says so)."""
        with self._lock:
            self._merged.setdefault(own, (into, session))

    # -- changes and saves ----------------------------------------------------------------------------
    def mark_dirty(self, name: str, tile_ids: list[str]) -> None:
        with self._lock:
            self._dirty.setdefault(name, set()).update(tile_ids)

    def insert(
        self, name: str, xyz: np.ndarray, intensity: np.ndarray | None, grid: TileGrid | None = None
    ) -> None:
        """Fold points into a map (``grid``: the session's handle on it) and mark what changed."""
        changed = (self.grid(name) if grid is None else grid).insert(xyz, intensity)
        if changed:
            self.mark_dirty(name, changed)

    def refold(self, name: str, tile_ids: list[str], xyz: np.ndarray, intensity: np.ndarray) -> None:
        """Replace tiles of ``name`` by the pose graph's re-fold of them (its keyframes' points at
        their optimized poses, equalized in the graph process: service/graph.py); saved and
        published by the next save like any change. Tiles the store held when the service started
        are left as they are (the graph never saw their points)."""
        with self._lock:
            grid = self._grids.get(name)
            frozen = self._before_graph.get(name, set())
        if grid is None:
            return
        changed = grid.refold([t for t in tile_ids if t not in frozen], xyz, intensity)
        if changed:
            self.metrics.graph_tiles_refolded.inc(len(changed))
            self.mark_dirty(name, changed)

    def graph_restarted(self) -> None:
        """The pose graph process started again with an empty graph: the tiles made so far hold
        points of keyframes it never saw, so it no longer re-folds them, as after a restart."""
        with self._lock:
            for name, grid in self._grids.items():
                self._before_graph.setdefault(name, set()).update(grid.tile_ids())

    def save_dirty(self) -> None:
        """Save every dirty tile and publish each saved version once (after the sessions folded
        what they hold: the caller's part)."""
        with self._lock:
            dirty, self._dirty = self._dirty, {}
        for name, ids in dirty.items():
            grid = self._grids.get(name)
            if grid is None:  # deleted since its tiles changed
                continue
            snapshot = grid.tiles()  # what is written, then served: one consistent set
            try:
                written = self.store.save_tiles(name, grid, sorted(ids), tiles=snapshot)
                self.metrics.tiles_written.inc(len(ids))
            except (OSError, ValueError, RandtError):
                self.metrics.store_errors.inc()
                log.exception("saving %d tiles of map %s failed", len(ids), name)
                self.mark_dirty(name, list(ids))
                continue  # nothing of it is served before it is on disk
            on_disk = set(written)
            saved = [t for t in snapshot if t.id in on_disk]
            with self._lock:
                if self._grids.get(name) is grid:  # not deleted meanwhile
                    durable = self._durable.setdefault(name, {})
                    # A tile changed after this save took its dirty set but before the snapshot is
                    # dirty again: the next save writes the same version once more. Publish each
                    # version once (a client sees every tile's versions strictly increase).
                    saved = [t for t in saved if t.id not in durable or t.version > durable[t.id].version]
                    durable.update({t.id: t for t in saved})
            for tile in saved:
                self.outbox(self.tile_message(name, tile))

    def merge(self, own: str, into: str, T_into_own: np.ndarray, session: str) -> int | None:
        """Merge map ``own`` into ``into`` (its points moved by ``T_into_own``, equalized like any
        insert: where ``into`` holds a voxel, its point stays) and remove it, its highest version
        kept as the floor of any later map of that name. Returns the tiles merged (``None``: no
        such map). The caller holds off saves meanwhile."""
        with self._lock:
            grid = self._grids.get(own)
        if grid is None:
            return None
        tiles = grid.tiles()
        if tiles:
            xyz = np.concatenate([t.points for t in tiles]).astype(np.float64)
            moved = (xyz @ T_into_own[:3, :3].T + T_into_own[:3, 3]).astype(np.float32)
            self.insert(into, moved, np.concatenate([t.intensity for t in tiles]))
        floor = max([grid.version_floor, *(t.version for t in tiles)])
        self.store.delete_map(own, version_floor=floor)
        with self._lock:
            if self._grids.get(own) is grid:
                del self._grids[own]
            self._durable.pop(own, None)
            self._dirty.pop(own, None)
            self._merged[own] = (into, session)
        return len(tiles)

    def delete(self, name: str) -> int:
        """Delete a map from memory and the store; returns how many tiles it held (raises
        :class:`~randt.core.errors.NotFoundError`). Its highest version becomes the floor of a
        later map of the same name."""
        with self._lock:
            grid = self._grids.get(name)
            if grid is None:
                raise NotFoundError(f"map {name!r} not found", resource="map", ident=name)
            n_tiles = len(grid)
            floor = max([grid.version_floor, *(t.version for t in grid.tiles())])
            self.store.delete_map(name, version_floor=floor)
            del self._grids[name]
            self._durable.pop(name, None)
            self._dirty.pop(name, None)
        return n_tiles

    def check_exists(self, name: str) -> None:
        """Raise :class:`~randt.core.errors.NotFoundError` unless ``name`` is a live map."""
        if name not in self:
            raise NotFoundError(f"map {name!r} not found", resource="map", ident=name)


def tile_message(map_name: str, grid: TileGrid, tile_id: str) -> TileUpdateMessage:
    """The current :class:`~randt.wire.messages.TileUpdateMessage` of one tile of a grid (offline use;
    the service publishes saved tiles only: :meth:`LiveMaps.tile_message`)."""
    tile = grid.get(tile_id)
    return tile_update_from_arrays(map_name, tile.ix, tile.iy, tile.version, tile.points, tile.intensity)


def tile_digest(tile: Tile) -> str:
    """The digest of a tile's content: :func:`randt.wire.messages.points_digest` of its float32
    ``x y z intensity`` table, as its tile update carries it and its ETag names it."""
    return points_digest(np.ascontiguousarray(tile.xyzi, dtype="<f4").tobytes())
