"""A map's geodetic origin and projection (core/geo.py), checked against PROJ's own UTM and the
MGRS reference coordinates of the mgrs package: positions round-trip to a millimetre, an origin
set from a fix sits on the tile grid of its MGRS square, and the convergence turns headings."""

from __future__ import annotations

import math

import numpy as np
import pytest

pyproj = pytest.importorskip("pyproj")
mgrs = pytest.importorskip("mgrs")

from randt.core.errors import InvalidRequestError  # noqa: E402
from randt.core.geo import GeoOrigin, LocalCartesianUTM  # noqa: E402

#: Places in both hemispheres, both sides of a central meridian, and in Norway's zone exception.
PLACES = [(35.6762, 139.6503), (-33.8688, 151.2093), (48.137, 11.575), (60.39, 5.32), (0.5, -78.5)]


@pytest.mark.parametrize(("lat", "lon"), PLACES)
def test_positions_go_to_the_map_and_back_within_a_millimetre(lat: float, lon: float) -> None:
    proj = LocalCartesianUTM(GeoOrigin(lat, lon, 50.0))
    rng = np.random.default_rng(7)
    dlat, dlon = rng.uniform(-0.02, 0.02, 100), rng.uniform(-0.02, 0.02, 100)  # +-2 km
    alt = rng.uniform(0.0, 100.0, 100)
    xyz = proj.to_map(lat + dlat, lon + dlon, alt)
    back_lat, back_lon, back_alt = proj.to_geodetic(xyz)
    geod = pyproj.Geod(ellps="WGS84")
    _, _, dist = geod.inv(lon + dlon, lat + dlat, back_lon, back_lat)
    assert np.max(dist) < 1e-3 and np.max(np.abs(back_alt - alt)) < 1e-9
    # the map frame is the UTM grid less the origin: distances on it are the ground's times UTM's
    # scale factor (0.9996 on the central meridian, up to about 1.001 at a zone's edge)
    _, _, ground = geod.inv(np.full(100, lon), np.full(100, lat), lon + dlon, lat + dlat)
    grid = np.hypot(xyz[:, 0], xyz[:, 1])
    assert np.all(np.abs(grid / ground - 1.0) < 1.2e-3)


def test_the_frame_is_the_mgrs_square_shifted_and_the_origin_sits_on_the_tile_grid() -> None:
    origin = GeoOrigin.on_grid(35.6762, 139.6503, 40.7, grid_m=20.0)
    proj = LocalCartesianUTM(origin)
    assert origin.altitude_m == 40.0 and proj.mgrs_grid == "54SUE" and proj.zone == 54
    east, north = proj.utm_origin
    assert abs(east / 20 - round(east / 20)) < 1e-6 and abs(north / 20 - round(north / 20)) < 1e-6
    # a point 123.4 m east and 56.7 m north of the origin, in MGRS (1 m precision) by the mgrs package
    offset = proj.mgrs_offset()
    assert np.allclose(offset[:2] / 20.0, np.round(offset[:2] / 20.0), atol=1e-6)  # whole tiles
    lat, lon, _ = proj.to_geodetic(np.array([[123.4, 56.7, 0.0]]))
    ref = mgrs.MGRS().toMGRS(float(lat[0]), float(lon[0]), MGRSPrecision=5)
    assert ref[:5] == "54SUE"
    ref_e, ref_n = int(ref[5:10]), int(ref[10:15])  # truncated to the metre, as MGRS is
    assert math.floor(offset[0] + 123.4) == ref_e and math.floor(offset[1] + 56.7) == ref_n
    assert proj.projector_info("MGRS") == {
        "projector_type": "MGRS",
        "vertical_datum": "WGS84",
        "mgrs_grid": "54SUE",
    }
    info = proj.projector_info()
    assert info["projector_type"] == "LocalCartesianUTM" and info["map_origin"]["altitude"] == 40.0


def test_norway_takes_the_zone_exception() -> None:
    # Bergen (5.32 E) is in zone 31 by longitude, 32 by the Norway exception (as GeographicLib)
    assert LocalCartesianUTM(GeoOrigin(60.39, 5.32, 0.0)).zone == 32


@pytest.mark.parametrize(("lat", "lon"), PLACES)
def test_headings_turn_by_the_meridian_convergence(lat: float, lon: float) -> None:
    proj = LocalCartesianUTM(GeoOrigin(lat, lon, 0.0))
    R = proj.enu_to_map_rotation(lat, lon)
    turn = math.degrees(math.atan2(R[1, 0], R[0, 0]))
    # PROJ's meridian convergence, same sign: west of a central meridian in the north, meridians
    # lean east as they go north (they meet at the pole), so the turn is clockwise (negative)
    factors = pyproj.Proj(proj="utm", zone=proj.zone, south=proj.south, ellps="WGS84").get_factors(lon, lat)
    assert turn == pytest.approx(factors.meridian_convergence, abs=1e-4)
    if lat > 0 and lon < (proj.zone - 1) * 6 - 180 + 3:
        assert turn < 0
    assert np.allclose(R @ R.T, np.eye(3))


def test_bad_origins_are_refused_with_the_reason() -> None:
    with pytest.raises(InvalidRequestError, match="UPS"):
        GeoOrigin(85.0, 0.0, 0.0)
    with pytest.raises(InvalidRequestError, match="longitude"):
        GeoOrigin(10.0, 190.0, 0.0)
    with pytest.raises(InvalidRequestError, match="finite"):
        GeoOrigin(float("nan"), 0.0, 0.0)


def test_the_projector_info_file_is_autowares_and_reads_back(tmp_path) -> None:
    from randt.core.errors import FormatError
    from randt.core.io.autoware import PROJECTOR_INFO_NAME, read_projector_info, write_projector_info

    proj = LocalCartesianUTM(GeoOrigin.on_grid(35.6762, 139.6503, 40.7, grid_m=20.0))
    assert read_projector_info(tmp_path) is None  # a map in a local frame has none
    for kind in ("LocalCartesianUTM", "MGRS"):
        path = write_projector_info(tmp_path, proj.projector_info(kind))  # type: ignore[arg-type]
        assert path.name == PROJECTOR_INFO_NAME
        text = path.read_text(encoding="utf-8")
        assert text.startswith(f"projector_type: {kind}\nvertical_datum: WGS84\n"), text
        info = read_projector_info(tmp_path)
        assert info == proj.projector_info(kind)  # type: ignore[arg-type]
    # the latitude keeps every digit (a 1e-9 degree is 0.1 mm)
    write_projector_info(tmp_path, proj.projector_info())
    info = read_projector_info(tmp_path)
    assert info is not None and info["map_origin"]["latitude"] == proj.origin.latitude_deg
    # Autoware's own example files read as they are (map_projection_loader's README)
    (tmp_path / PROJECTOR_INFO_NAME).write_text(
        "projector_type: LocalCartesianUTM\nvertical_datum: WGS84\nmap_origin:\n"
        "  latitude: 35.6762 # [deg]\n  longitude: 139.6503 # [deg]\n  altitude: 0.0 # [m]\n"
    )
    assert read_projector_info(tmp_path)["map_origin"]["longitude"] == 139.6503  # type: ignore[index]
    (tmp_path / PROJECTOR_INFO_NAME).write_text("projector_type: local\n")
    assert read_projector_info(tmp_path) == {"projector_type": "local"}
    for bad, why in [
        ("projector_type: UTM\n", "projector_type 'UTM'"),
        ("projector_type: MGRS\nvertical_datum: WGS84\n", "needs mgrs_grid"),
        ("projector_type: LocalCartesianUTM\nvertical_datum: WGS84\nmap_origin: {latitude: 1}\n", "numbers"),
    ]:
        (tmp_path / PROJECTOR_INFO_NAME).write_text(bad)
        with pytest.raises(FormatError, match=why):
            read_projector_info(tmp_path)
    with pytest.raises(FormatError, match="projector_type"):
        write_projector_info(tmp_path, {"projector_type": "nope"})


def test_a_gnss_pose_lands_in_the_map_frame_with_its_heading_and_covariance_turned() -> None:
    """A vehicle heading true north 2 km east of an origin in Tokyo (zone 54, west of its central
    meridian at 141 E, so true north leans east on the grid): the pose's position is the
    projection's, its heading is true north as seen on the grid, and a covariance long along true
    north stays long along the heading."""
    origin = GeoOrigin(35.6762, 139.6503, 40.0)
    proj = LocalCartesianUTM(origin)
    lat, lon = proj.to_geodetic(np.array([[2000.0, 500.0, 0.0]]))[:2]
    yaw_north = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # sensor x -> north
    cov = np.diag([0.01, 1.0, 0.04, 1e-4, 1e-4, 1e-3])  # long along north
    T, C = proj.pose_to_map(float(lat[0]), float(lon[0]), 43.0, yaw_north, cov)
    assert C is not None
    assert np.allclose(T[:3, 3], [2000.0, 500.0, 3.0], atol=1e-6)
    # the sensor's x axis points where a step north goes on the grid
    step = proj.to_map(float(lat[0]) + 1e-4, float(lon[0]), 43.0)[0] - T[:3, 3]
    heading = T[:3, 0]
    assert np.degrees(np.arccos(heading[:2] @ step[:2] / np.linalg.norm(step[:2]))) < 1e-4
    assert step[0] > 0  # west of the central meridian: true north leans east
    # the long axis of the position covariance follows true north on the grid
    w, V = np.linalg.eigh(C[:3, :3])
    assert w[-1] == pytest.approx(1.0) and abs(V[:2, -1] @ heading[:2]) == pytest.approx(1.0, abs=1e-9)
    assert np.allclose(C, C.T) and np.allclose(np.linalg.eigvalsh(C), np.sort(np.diag(cov)))
