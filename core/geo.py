"""Georeferenced maps: a map's geodetic origin and the projection of its frame, as Autoware reads it.

A map's frame is Autoware's ``LocalCartesianUTM``: x east and y north on the UTM grid of the
origin's zone, in metres, less the origin's UTM coordinates; z is the height above the WGS84
ellipsoid less the origin's. :class:`GeoOrigin` (an origin on the map's tile grid, so that the
same map can be written as ``MGRS`` by whole tiles), :class:`LocalCartesianUTM` (a GNSS fix's
position through the projection, its orientation and covariance turned by the meridian
convergence) and :func:`write_mgrs_map`. The projection is PROJ's (``pyproj``) and the MGRS
square's name the ``mgrs`` package's, both in the ``geo`` extra. Why this frame, UTM's scale and
convergence: docs/mapping.md, "Georeferenced maps".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from randt.core.errors import FormatError, InvalidRequestError
from randt.core.io.autoware import (
    PROJECTOR_INFO_NAME,
    make_directory,
    read_metadata,
    read_projector_info,
    remove_stale_tile_files,
    tile_file_name,
    write_metadata,
    write_projector_info,
)
from randt.core.io.clouds import read_cloud, write_pcd

__all__ = [
    "GeoOrigin",
    "LocalCartesianUTM",
    "ProjectorType",
    "origin_of",
    "read_map_projection",
    "write_mgrs_map",
]

#: The projector types a map can be written in (Autoware's names).
ProjectorType = Literal["LocalCartesianUTM", "MGRS"]
#: Side of an MGRS square (m).
MGRS_SQUARE_M = 100_000.0
#: UTM's latitude limits (beyond them UPS, which Autoware's projectors do not take).
UTM_SOUTH_DEG, UTM_NORTH_DEG = -80.0, 84.0


def _libraries() -> tuple[Any, Any]:
    """``pyproj`` and ``mgrs``, or a one-line error naming the extra."""
    try:
        import mgrs
        import pyproj
    except ImportError as exc:  # pragma: no cover - exercised with the extra absent
        raise FormatError(f"georeferenced maps need {exc.name}: pip install 'randt-fleet[geo]'") from None
    return pyproj, mgrs


@dataclass(frozen=True)
class GeoOrigin:
    """A map's geodetic origin: WGS84 latitude and longitude (degrees), height above the
    ellipsoid (m)."""

    latitude_deg: float
    longitude_deg: float
    altitude_m: float

    def __post_init__(self) -> None:
        values = (self.latitude_deg, self.longitude_deg, self.altitude_m)
        if not all(math.isfinite(v) for v in values):
            raise InvalidRequestError(f"geodetic origin: not finite: {values}")
        if not UTM_SOUTH_DEG <= self.latitude_deg <= UTM_NORTH_DEG:
            raise InvalidRequestError(
                f"geodetic origin: latitude {self.latitude_deg} is outside UTM's "
                f"{UTM_SOUTH_DEG:g}..{UTM_NORTH_DEG:g} degrees (the polar regions need UPS, which "
                "Autoware's map projectors do not take)"
            )
        if not -180.0 <= self.longitude_deg <= 180.0:
            raise InvalidRequestError(f"geodetic origin: longitude {self.longitude_deg} outside -180..180")

    @classmethod
    def on_grid(
        cls, latitude_deg: float, longitude_deg: float, altitude_m: float, grid_m: float
    ) -> GeoOrigin:
        """The origin for a map first placed by a fix at these coordinates: the point of the fix's
        UTM zone whose easting and northing are the nearest multiples of ``grid_m`` (the map's
        tile size) at or below the fix's, at the fix's height rounded down to a whole metre. On
        that grid, the map's MGRS coordinates (:meth:`LocalCartesianUTM.mgrs_offset`) are its own
        shifted by whole tiles."""
        fix = LocalCartesianUTM(cls(latitude_deg, longitude_deg, altitude_m))
        east, north = fix.utm_origin
        snapped = np.array(
            [[math.floor(east / grid_m) * grid_m - east, math.floor(north / grid_m) * grid_m - north, 0.0]]
        )
        lat, lon, _ = fix.to_geodetic(snapped)
        return cls(float(lat[0]), float(lon[0]), float(math.floor(altitude_m)))

    def as_dict(self) -> dict[str, float]:
        """Autoware's ``map_origin`` mapping."""
        return {"latitude": self.latitude_deg, "longitude": self.longitude_deg, "altitude": self.altitude_m}


class LocalCartesianUTM:
    """The projection of a map with geodetic ``origin`` (the module docstring): geodetic
    coordinates to map coordinates and back, vectorized (PROJ), and the files that say so."""

    def __init__(self, origin: GeoOrigin) -> None:
        pyproj, mgrs = _libraries()
        self.origin = origin
        #: The origin's MGRS 100 km square, e.g. ``54SUE``; its first digits are the UTM zone,
        #: with the Norway and Svalbard exceptions applied (as GeographicLib's standard zone).
        self.mgrs_grid: str = mgrs.MGRS().toMGRS(origin.latitude_deg, origin.longitude_deg, MGRSPrecision=0)
        self.zone = int(self.mgrs_grid[:-3])
        self.south = origin.latitude_deg < 0
        epsg = (32700 if self.south else 32600) + self.zone
        self._forward = pyproj.Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True)
        self._inverse = pyproj.Transformer.from_crs(f"EPSG:{epsg}", "EPSG:4326", always_xy=True)
        east, north = self._forward.transform(origin.longitude_deg, origin.latitude_deg, errcheck=True)
        #: The origin's UTM easting and northing (m).
        self.utm_origin = (float(east), float(north))

    def to_map(self, latitude_deg: Any, longitude_deg: Any, altitude_m: Any) -> np.ndarray:
        """(N, 3) map coordinates of WGS84 positions (arrays or scalars, degrees and metres)."""
        lat, lon, alt = (
            np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in (latitude_deg, longitude_deg, altitude_m)
        )
        if not (np.isfinite(lat).all() and np.isfinite(lon).all() and np.isfinite(alt).all()):
            raise InvalidRequestError("geodetic position: not finite")
        east, north = self._forward.transform(lon, lat, errcheck=True)
        e0, n0 = self.utm_origin
        return np.column_stack([np.asarray(east) - e0, np.asarray(north) - n0, alt - self.origin.altitude_m])

    def to_geodetic(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Latitudes, longitudes (degrees) and heights (m) of (N, 3) map coordinates."""
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        e0, n0 = self.utm_origin
        lon, lat = self._inverse.transform(xyz[:, 0] + e0, xyz[:, 1] + n0, errcheck=True)
        return np.asarray(lat), np.asarray(lon), xyz[:, 2] + self.origin.altitude_m

    def enu_to_map_rotation(self, latitude_deg: float, longitude_deg: float) -> np.ndarray:
        """(3, 3) rotation from the local East-North-Up frame at a position to the map frame: a
        turn about up by the meridian convergence there (grid north is not true north).

        Measured on the projection itself (the grid direction of a step north), not taken from a
        sign convention."""
        step = 1e-6  # degrees of latitude: about 0.11 m
        a = self.to_map(latitude_deg, longitude_deg, 0.0)[0]
        b = self.to_map(latitude_deg + step, longitude_deg, 0.0)[0]
        theta = math.atan2(-(b[0] - a[0]), b[1] - a[1])
        c, s = math.cos(theta), math.sin(theta)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def pose_to_map(
        self,
        latitude_deg: float,
        longitude_deg: float,
        altitude_m: float,
        R_enu_sensor: np.ndarray,
        covariance_enu: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """A GNSS/INS pose in the map frame: the 4x4 ``T_map_sensor`` of a sensor at a WGS84
        position with orientation ``R_enu_sensor`` (3x3, in the East-North-Up frame there), and its
        6x6 covariance (left perturbation ``tx ty tz rx ry rz``, as :mod:`randt.core.transforms`) turned
        from ENU axes to the map's, when given. Lengths are not rescaled: a fix's metre-level
        uncertainty does not see UTM's 0.04 % scale."""
        R_map_enu = self.enu_to_map_rotation(latitude_deg, longitude_deg)
        T = np.eye(4)
        T[:3, :3] = R_map_enu @ np.asarray(R_enu_sensor, dtype=np.float64).reshape(3, 3)
        T[:3, 3] = self.to_map(latitude_deg, longitude_deg, altitude_m)[0]
        if covariance_enu is None:
            return T, None
        A = np.zeros((6, 6))
        A[:3, :3] = A[3:, 3:] = R_map_enu  # a turn of the world frame: both blocks turn with it
        cov = np.asarray(covariance_enu, dtype=np.float64).reshape(6, 6)
        return T, A @ cov @ A.T

    def mgrs_offset(self) -> np.ndarray:
        """(3,) what is added to map coordinates to give MGRS ones (Autoware's ``MGRS`` projector:
        the position in the origin's 100 km square, height above the ellipsoid)."""
        e0, n0 = self.utm_origin
        return np.array([e0 % MGRS_SQUARE_M, n0 % MGRS_SQUARE_M, self.origin.altitude_m])

    def projector_info(self, projector: ProjectorType = "LocalCartesianUTM") -> dict[str, Any]:
        """The content of Autoware's ``map_projector_info.yaml`` for the map written in ``projector``
        (:func:`randt.core.io.autoware.write_projector_info`)."""
        if projector == "LocalCartesianUTM":
            return {
                "projector_type": projector,
                "vertical_datum": "WGS84",
                "map_origin": self.origin.as_dict(),
            }
        if projector == "MGRS":
            return {"projector_type": projector, "vertical_datum": "WGS84", "mgrs_grid": self.mgrs_grid}
        raise InvalidRequestError(f"projector {projector!r}: expected LocalCartesianUTM or MGRS")


def origin_of(info: dict[str, Any] | None, where: str) -> GeoOrigin | None:
    """The geodetic origin a ``map_projector_info.yaml``'s content gives (``None`` for none: a
    local frame); :class:`FormatError` naming ``where`` for a projector other than
    ``LocalCartesianUTM``, the only one a map is kept in."""
    if info is None:
        return None
    origin = info.get("map_origin")
    if info.get("projector_type") != "LocalCartesianUTM" or not isinstance(origin, dict):
        raise FormatError(f"{where}: the projection is {info.get('projector_type')!r}, not LocalCartesianUTM")
    return GeoOrigin(float(origin["latitude"]), float(origin["longitude"]), float(origin["altitude"]))


def read_map_projection(directory: Path) -> LocalCartesianUTM | None:
    """The projection of an Autoware map folder in ``LocalCartesianUTM`` (``None``: no
    ``map_projector_info.yaml``, a local frame); :class:`FormatError` for another projector."""
    origin = origin_of(read_projector_info(directory), str(directory / PROJECTOR_INFO_NAME))
    return None if origin is None else LocalCartesianUTM(origin)


def write_mgrs_map(source: Path, destination: Path) -> int:
    """Write the georeferenced map folder ``source`` (tiles, metadata and a LocalCartesianUTM
    ``map_projector_info.yaml``, as the service and ``randt tiles download`` write it) into
    ``destination`` as Autoware's ``MGRS`` projection: every point moved by
    :meth:`LocalCartesianUTM.mgrs_offset` (whole tiles: the tiles are renamed, not cut again),
    the metadata's corners and the yaml (``mgrs_grid``) to match; stale tile files removed.
    Returns the number of tiles written.

    MGRS coordinates run to 100 km: float32 PCD points keep about 8 mm there (Autoware's own MGRS
    maps share the limit). Raises :class:`InvalidRequestError` when the map has no geodetic origin
    or an origin off its tile grid (a given one: the tiles would have to be cut again)."""
    projection = read_map_projection(source)
    if projection is None:
        raise InvalidRequestError(
            f"{source}: the map has no geodetic origin (no {PROJECTOR_INFO_NAME}): no MGRS"
        )
    tile_size, files = read_metadata(source)
    offset = projection.mgrs_offset()
    shift = offset[:2] / tile_size
    if not np.allclose(shift, np.round(shift), atol=1e-6):
        raise InvalidRequestError(
            f"{source}: the map's origin is {offset[0] % tile_size:.3f}, {offset[1] % tile_size:.3f} m off "
            f"its {tile_size} m tile grid in MGRS, so its tiles would have to be cut again: keep "
            "LocalCartesianUTM"
        )
    dix, diy = (int(v) for v in np.round(shift))
    make_directory(destination)
    corners: dict[str, tuple[int, int]] = {}
    for name, (ix, iy) in files.items():
        cloud = read_cloud(source / name)
        tid = f"{ix + dix}_{iy + diy}"
        write_pcd(destination / tile_file_name(tid), replace(cloud, xyz=cloud.xyz + offset))
        corners[tid] = ((ix + dix) * tile_size, (iy + diy) * tile_size)
    remove_stale_tile_files(destination, {tile_file_name(t): None for t in corners})
    write_projector_info(destination, projection.projector_info("MGRS"))
    write_metadata(destination, tile_size, corners)
    return len(corners)
