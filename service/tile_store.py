"""The maps of the store: ``DATA/maps/<map>/`` (the Autoware divided map :mod:`randt.core.tiles`
writes, its projector info) and the version floors of deleted maps, ``DATA/map-versions/<map>``.

A map is written sidecar, changed tiles, metadata last (:meth:`TileGrid.write_tiles
<randt.core.tiles.TileGrid.write_tiles>`), each file atomically, so the metadata never names a tile
file that does not exist. Writes to one map are serialized by the map's lock.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path

from randt.core.errors import FormatError, NotFoundError, RandtError
from randt.core.io import atomic_write_bytes
from randt.core.io.atomic import fsync_directory
from randt.core.io.autoware import (
    AUTOWARE_METADATA_NAME,
    GRID_SIDECAR_NAME,
    make_directory,
    read_projector_info,
    read_sidecar,
    write_projector_info,
)
from randt.core.tiles import Tile, TileGrid, load_autoware
from randt.service.store_files import DELETED_PREFIX
from randt.wire.ids import validate_id

__all__ = ["MAPS_DIRNAME", "VERSIONS_DIRNAME", "TileStore"]

logger = logging.getLogger(__name__)

MAPS_DIRNAME = "maps"
VERSIONS_DIRNAME = "map-versions"


class TileStore:
    """The maps under ``maps`` and the version floors under ``versions``: save, load, delete, list.

    ``check_open`` raises when the store that owns the directories is closed; every read and write
    calls it first.
    """

    def __init__(self, maps: Path, versions: Path, check_open: Callable[[], None]) -> None:
        self._maps = maps
        self._versions = versions
        self._check_open = check_open
        self._guard = threading.Lock()
        self._map_locks: dict[str, threading.Lock] = {}

    @property
    def maps_dir(self) -> Path:
        """``DATA/maps``."""
        return self._maps

    def map_lock(self, map_name: str) -> threading.Lock:
        """The lock that serializes writes to ``map_name``."""
        with self._guard:
            return self._map_locks.setdefault(map_name, threading.Lock())

    def map_dir(self, map_name: str) -> Path:
        """``DATA/maps/<map_name>`` (not created).

        Raises
        ------
        ValueError
            ``map_name`` is not a valid name (:func:`randt.wire.ids.validate_id`).
        """
        return self._maps / validate_id(map_name, "map")

    def save_tiles(
        self, map_name: str, grid: TileGrid, changed_ids: Iterable[str], *, tiles: list[Tile] | None = None
    ) -> list[str]:
        """Persist a map after an update, rewriting only the tiles that changed.

        Uses :meth:`TileGrid.write_tiles <randt.core.tiles.TileGrid.write_tiles>`: sidecar, the changed
        tiles (and any tile whose file is missing), metadata last, each file atomically. An empty
        grid writes nothing.

        Parameters
        ----------
        map_name:
            The map's name (an id, :mod:`randt.wire.ids`).
        grid:
            The map.
        changed_ids:
            Ids of the tiles changed since the last save (what :meth:`TileGrid.insert` returned).
        tiles:
            The snapshot of ``grid`` to write (:meth:`TileGrid.tiles`); ``None``: the current one.

        Returns
        -------
        list[str]
            Ids of the tiles whose files were written.

        Raises
        ------
        ValueError
            Invalid ``map_name``.
        NotFoundError
            A changed id is not a tile of ``grid``.
        FormatError
            A file could not be written.
        """
        self._check_open()
        directory = self.map_dir(map_name)
        if len(grid) == 0 or tiles == []:
            logger.debug("map %s is empty: nothing to save", map_name)
            return []
        with self.map_lock(map_name):
            written = grid.write_tiles(directory, changed_ids, tiles=tiles)
        logger.debug("saved map %s: %d tiles written, %d in the map", map_name, len(written), len(grid))
        return written

    def load_map(self, map_name: str) -> TileGrid | None:
        """Restore a map saved by :meth:`save_tiles`, or ``None`` if there is none.

        Raises
        ------
        ValueError
            Invalid ``map_name``.
        FormatError
            The map's files are damaged (unreadable metadata or sidecar, a listed tile file that is
            missing or unreadable).
        """
        self._check_open()
        directory = self.map_dir(map_name)
        if not (directory / AUTOWARE_METADATA_NAME).is_file():
            return None
        with self.map_lock(map_name):
            try:
                return load_autoware(directory)
            except NotFoundError as exc:  # the metadata exists, so a missing tile is damage
                raise FormatError(f"map {map_name} is incomplete: {exc}") from exc

    def save_projection(self, map_name: str, info: dict[str, object]) -> None:
        """Write a map's ``map_projector_info.yaml`` (its geodetic origin, core/geo.py) into its
        folder, atomically and durably (the folder is created if the map has no tile yet): a
        pose answered in the map's frame is only as durable as the origin that defines it."""
        self._check_open()
        directory = make_directory(self.map_dir(map_name))
        fsync_directory(directory.parent)  # (a new map's folder: its name durable too)
        with self.map_lock(map_name):
            write_projector_info(directory, info)

    def load_projection(self, map_name: str) -> dict[str, object] | None:
        """A map's ``map_projector_info.yaml`` (``None``: the map has no geodetic origin).

        Raises
        ------
        FormatError
            The file is there but is not one Autoware's loader would take.
        """
        self._check_open()
        with self.map_lock(map_name):
            return read_projector_info(self.map_dir(map_name))

    def version_floor(self, map_name: str) -> int:
        """The highest tile version a deleted map of this name reached (0 if none was deleted):
        a new map of the name numbers its tiles above it (:meth:`delete_map`).

        Raises
        ------
        ValueError
            Invalid ``map_name``.
        FormatError
            The floor's file is unreadable.
        """
        self._check_open()
        path = self._versions / validate_id(map_name, "map")
        try:
            text = path.read_text(encoding="ascii").strip()
        except FileNotFoundError:
            return 0
        except OSError as exc:
            raise FormatError(f"cannot read {path}: {exc}") from exc
        if not text.isdigit():
            raise FormatError(f"{path}: not a version number: {text[:40]!r}")
        return int(text)

    def delete_map(self, map_name: str, *, version_floor: int = 0) -> bool:
        """Remove a saved map's directory; False if there was none.

        First the highest tile version the map reached (the larger of ``version_floor``, the
        versions on disk and an earlier floor) is recorded in ``map-versions/<map>``
        (:meth:`version_floor`), so that versions of a later map of the same name never repeat
        one served for this map's content.

        The directory is first renamed to ``maps/.deleted-<name>-<pid>-<ns>`` (one atomic step, so
        after a crash the map is either whole or gone) and then removed; a leftover ``.deleted-*``
        directory is removed when the store next opens.

        Raises
        ------
        ValueError
            Invalid ``map_name``.
        """
        self._check_open()
        directory = self.map_dir(map_name)
        with self.map_lock(map_name):
            floor = max(version_floor, self.version_floor(map_name))
            if directory.is_dir():
                with contextlib.suppress(RandtError, OSError):
                    saved = read_sidecar(directory, _sidecar_tile_size(directory))[1]
                    floor = max(floor, *saved.values(), 0)
            if floor > 0:
                self._versions.mkdir(exist_ok=True)
                atomic_write_bytes(self._versions / map_name, f"{floor}\n".encode("ascii"))
            if not directory.is_dir():
                return False
            trash = self._maps / f"{DELETED_PREFIX}{map_name}-{os.getpid()}-{time.time_ns()}"
            os.replace(directory, trash)
            fsync_directory(self._maps)
        shutil.rmtree(trash, ignore_errors=True)
        logger.info("deleted map %s", map_name)
        return True

    def list_maps(self) -> list[str]:
        """Names of the saved maps (those with a metadata file), sorted."""
        self._check_open()
        names = []
        for entry in sorted(self._maps.iterdir()):
            if not entry.is_dir():
                continue
            try:
                validate_id(entry.name, "map")
            except ValueError:
                logger.warning("ignoring %s: not a valid map directory name", entry)
                continue
            if (entry / AUTOWARE_METADATA_NAME).is_file():
                names.append(entry.name)
            else:
                logger.debug("ignoring %s: no %s (no save completed)", entry, AUTOWARE_METADATA_NAME)
        return names


def _sidecar_tile_size(directory: Path) -> int:
    """The tile size a map's sidecar states (so :func:`read_sidecar` accepts it)."""
    import yaml

    doc = yaml.safe_load((directory / GRID_SIDECAR_NAME).read_text(encoding="utf-8"))
    if not isinstance(doc, dict) or not isinstance(doc.get("tile_size_m"), int):
        raise FormatError(f"{directory / GRID_SIDECAR_NAME}: no tile_size_m")
    return int(doc["tile_size_m"])
