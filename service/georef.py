"""Georeferenced maps in the service: each map's geodetic origin, and WGS84 priors placed in it.

A map's origin lives in its folder as Autoware's ``map_projector_info.yaml`` (``LocalCartesianUTM``,
core/geo.py), beside its tiles, so the service's own data directory is a map Autoware and GIS
tools can place. The first scan whose ``geo_prior`` (randt.wire.messages.GeoPrior) reaches a map without
an origin sets it: the fix's point on the map's tile grid (:meth:`randt.core.geo.GeoOrigin.on_grid`),
written durably before that scan is matched (an answer in the map's frame is only as durable as
the origin that defines it). A map that already holds points but has no origin was built in a
local frame: a WGS84 prior cannot be placed in it, and the scan is refused ``invalid_prior`` with
that reason (the vehicle may send map-frame priors instead).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Protocol

import numpy as np

from randt.core.errors import BadMessageError, InvalidRequestError, RandtError
from randt.core.geo import GeoOrigin, LocalCartesianUTM, origin_of, read_map_projection
from randt.core.io.autoware import AUTOWARE_METADATA_NAME
from randt.core.odometry import PosePrior
from randt.core.tiles import TileGrid
from randt.wire.codes import ErrorCode
from randt.wire.messages import GeoPrior, GnssFix

__all__ = ["MapProjections", "check_map_origin", "origin_conflict"]

log = logging.getLogger(__name__)


class _ProjectionStore(Protocol):
    def save_projection(self, map_name: str, info: dict[str, object]) -> None: ...

    def load_projection(self, map_name: str) -> dict[str, object] | None: ...


class MapProjections:
    """The projections of the service's maps, read from the store once and kept."""

    def __init__(self, store: _ProjectionStore) -> None:
        self._store = store
        self._lock = threading.Lock()
        self._known: dict[str, LocalCartesianUTM | None] = {}

    def prior_in_map(self, map_name: str, grid: TileGrid, prior: GeoPrior) -> PosePrior:
        """``prior`` as a pose in ``map_name``'s frame (its origin set from it if the map has
        none and no points). Raises :class:`~randt.core.errors.BadMessageError` ``invalid_prior`` with
        the reason when it cannot be placed."""
        projection = self._projection(map_name, grid, prior)
        T, cov = projection.pose_to_map(
            prior.latitude, prior.longitude, prior.altitude, prior.rotation_enu(), prior.covariance_matrix()
        )
        assert cov is not None
        return PosePrior(T, cov)

    def fix_in_map(self, map_name: str, grid: TileGrid, fix: GnssFix) -> tuple[np.ndarray, np.ndarray]:
        """A position-only fix as ``(position (3,), covariance (3, 3))`` in ``map_name``'s frame (its
        origin set from it if the map has none and no points; raises as :meth:`prior_in_map`)."""
        projection = self._projection(map_name, grid, fix)
        xyz = projection.to_map(fix.latitude, fix.longitude, fix.altitude)[0]
        R = projection.enu_to_map_rotation(fix.latitude, fix.longitude)
        return xyz, R @ fix.covariance_matrix() @ R.T

    def give(self, map_name: str, has_points: bool, origin: GeoOrigin) -> None:
        """Set ``map_name``'s origin as configured (``RANDT_MAP_ORIGIN``), writing its file if the
        map has none; :class:`~randt.core.errors.InvalidRequestError` when the map already has another
        origin, or holds points in a local frame (moving it would move every pose answered)."""
        with self._lock:
            known = self._load(map_name)
            problem = origin_conflict(map_name, None if known is None else known.origin, has_points, origin)
            if problem is not None:
                raise InvalidRequestError(problem)
            if known is not None:
                return
            projection = LocalCartesianUTM(origin)
            self._store.save_projection(map_name, projection.projector_info())
            self._known[map_name] = projection
            log.info("map %s: geodetic origin %s (RANDT_MAP_ORIGIN)", map_name, origin.as_dict())

    def projection(self, map_name: str) -> LocalCartesianUTM | None:
        """``map_name``'s projection, ``None`` when it has no geodetic origin (raises
        :class:`~randt.core.errors.FormatError` when its file cannot be read)."""
        with self._lock:
            return self._load(map_name)

    def forget(self, map_name: str) -> None:
        """The map was deleted: its origin goes with it."""
        with self._lock:
            self._known.pop(map_name, None)

    def _projection(self, map_name: str, grid: TileGrid, fix: GeoPrior | GnssFix) -> LocalCartesianUTM:
        with self._lock:
            try:
                known = self._load(map_name)
            except RandtError as exc:  # a damaged file, or no pyproj (the geo extra)
                raise BadMessageError(
                    f"geo_prior: map {map_name!r}'s geodetic origin cannot be read: {exc}",
                    code=ErrorCode.INVALID_PRIOR,
                ) from exc
            if known is not None:
                return known
            if len(grid):
                raise BadMessageError(
                    f"geo_prior: map {map_name!r} has no geodetic origin (it was built in a local "
                    "frame), so a WGS84 prior cannot be placed in it: send the prior in the map's "
                    "frame (prior) or map into a map that has an origin",
                    code=ErrorCode.INVALID_PRIOR,
                )
            try:
                origin = GeoOrigin.on_grid(fix.latitude, fix.longitude, fix.altitude, float(grid.tile_size_m))
                projection = LocalCartesianUTM(origin)
                self._store.save_projection(map_name, projection.projector_info())
            except RandtError as exc:  # no pyproj (the geo extra), a polar fix, a write that failed
                raise BadMessageError(
                    f"geo_prior: map {map_name!r} cannot take a geodetic origin: {exc}",
                    code=ErrorCode.INVALID_PRIOR,
                ) from exc
            self._known[map_name] = projection
            log.info(
                "map %s: geodetic origin %.9f, %.9f, %.3f m (WGS84; UTM zone %d, MGRS %s), from its "
                "first WGS84 prior",
                map_name,
                origin.latitude_deg,
                origin.longitude_deg,
                origin.altitude_m,
                projection.zone,
                projection.mgrs_grid,
            )
            return projection

    def _load(self, map_name: str) -> LocalCartesianUTM | None:
        """From the cache, else the store (under the lock)."""
        if map_name in self._known:
            return self._known[map_name]
        origin = origin_of(self._store.load_projection(map_name), f"map {map_name}")
        projection = None if origin is None else LocalCartesianUTM(origin)
        self._known[map_name] = projection
        return projection


def origin_conflict(map_name: str, known: GeoOrigin | None, has_points: bool, given: GeoOrigin) -> str | None:
    """Why ``given`` cannot be ``map_name``'s origin (``None``: it can): the map has another one,
    or holds points in a local frame."""
    if known is not None:
        same = (
            abs(known.latitude_deg - given.latitude_deg) < 1e-9
            and abs(known.longitude_deg - given.longitude_deg) < 1e-9
            and abs(known.altitude_m - given.altitude_m) < 1e-3
        )
        if same:
            return None
        return (
            f"map_origin {given.as_dict()}: map {map_name!r} already has the geodetic origin "
            f"{known.as_dict()} (its poses and tiles are in that frame): unset RANDT_MAP_ORIGIN or "
            "give that one"
        )
    if has_points:
        return (
            f"map_origin: map {map_name!r} holds points in a local frame; a geodetic origin cannot be "
            "given to it afterwards (start a new map: RANDT_DEFAULT_MAP)"
        )
    return None


def check_map_origin(data_dir: Path, map_name: str, origin: tuple[float, float, float] | None) -> None:
    """The configured origin (``RANDT_MAP_ORIGIN``) against the map's folder, read only, before
    anything starts (``randt serve``): one clear error instead of a failed startup. Raises
    :class:`~randt.core.errors.InvalidRequestError` (a bad value or a conflict) or
    :class:`~randt.core.errors.FormatError` (no ``geo`` extra, an unreadable projection file)."""
    if origin is None:
        return
    given = GeoOrigin(*origin)
    LocalCartesianUTM(given)  # (the geo extra is there)
    folder = data_dir / "maps" / map_name
    known = read_map_projection(folder) if folder.is_dir() else None
    problem = origin_conflict(
        map_name, None if known is None else known.origin, (folder / AUTOWARE_METADATA_NAME).is_file(), given
    )
    if problem is not None:
        raise InvalidRequestError(problem)
