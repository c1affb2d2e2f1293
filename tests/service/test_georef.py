"""Georeferenced maps (issue 34): a vehicle sends its GNSS/INS poses in WGS84 (``geo_prior``); the
service sets the map's geodetic origin from the first, writes Autoware's ``map_projector_info.yaml``
beside the tiles, and answers in that frame. Checked with pyproj alone, from the files: the tiles'
points and the answered poses, taken back to WGS84, land where the fixes say.

The simulated town's frame is made a place on Earth: its coordinates are read as the UTM grid of a
point in Munich (zone 32) less that point's UTM coordinates, so each true pose has a latitude,
longitude and height (the fixes, exact), and each true surface too.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import yaml

pyproj = pytest.importorskip("pyproj")
mgrs = pytest.importorskip("mgrs")

from randt.clients.rest import MapClient  # noqa: E402
from randt.core.errors import BadMessageError  # noqa: E402
from randt.core.geo import GeoOrigin, LocalCartesianUTM  # noqa: E402
from randt.core.io import read_cloud  # noqa: E402
from randt.service.metrics import ServiceMetrics  # noqa: E402
from randt.service.sessions import SessionManager  # noqa: E402
from randt.service.settings import ServiceSettings  # noqa: E402
from randt.service.store import Store  # noqa: E402
from randt.sim.drive import plan_fleet, simulate  # noqa: E402
from randt.sim.lidar import Lidar64  # noqa: E402
from randt.sim.town import Town  # noqa: E402
from randt.wire.codes import ErrorCode  # noqa: E402
from randt.wire.messages import ErrorMessage, PoseMessage, encode, geo_prior, scan_from_arrays  # noqa: E402
from tests.service.api_server import live_server  # noqa: E402

#: Where the simulated town is on Earth (its frame's origin), WGS84.
MUNICH = GeoOrigin(48.137, 11.575, 520.0)
N_SCANS = 40
COV_ENU = np.diag([1e-4, 1e-4, 1e-4, 1e-6, 1e-6, 1e-6])


def _answered(out: list) -> int:
    return sum(isinstance(m, PoseMessage | ErrorMessage) for m in list(out))


def _send(mgr: SessionManager, out: list, payload: bytes, vehicle: str = "car") -> None:
    n = _answered(out)
    mgr.submit(vehicle, payload)
    deadline = time.monotonic() + 60
    while _answered(out) < n + 1:
        assert time.monotonic() < deadline, "the service stopped answering"
        time.sleep(0.002)


def _to_wgs84_with_pyproj(xyz: np.ndarray, info: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Map coordinates to latitude, longitude, height with pyproj alone, from the yaml's origin."""
    o = info["map_origin"]
    zone = int((o["longitude"] + 180) // 6) + 1  # (no zone exception near Munich)
    to_utm = pyproj.Transformer.from_crs("EPSG:4326", f"EPSG:{32600 + zone}", always_xy=True)
    e0, n0 = to_utm.transform(o["longitude"], o["latitude"])
    lon, lat = to_utm.transform(xyz[:, 0] + e0, xyz[:, 1] + n0, direction="INVERSE")
    return np.asarray(lat), np.asarray(lon), xyz[:, 2] + o["altitude"]


def _drive(n: int) -> tuple[Town, list]:
    """The simulated town 0 and ``n`` sweeps of one car's drive through it."""
    town = Town.generate(0)
    plan = plan_fleet(town, 1, seed=0, route_length_m=400.0)[0]
    lidar = Lidar64(n_azimuth=1000, max_range_m=70.0)
    return town, list(
        simulate(town, plan.route, n_scans=n, seed=3, lidar=lidar, start_s_m=plan.start_s_m, workers=2)
    )


def test_a_map_built_with_wgs84_priors_is_where_the_fixes_say(tmp_path: Path) -> None:
    town, scans = _drive(N_SCANS)
    earth = LocalCartesianUTM(MUNICH)  # the town's frame on Earth
    fixes = []
    with live_server(tmp_path / "data", capacity_target=0, graph=False) as server:
        mgr, out = server.service.sessions, server.service._sent
        assert mgr is not None
        for s in scans:
            lat, lon, alt = (float(v[0]) for v in earth.to_geodetic(s.T_world_sensor[:3, 3]))
            R_enu = earth.enu_to_map_rotation(lat, lon).T @ s.T_world_sensor[:3, :3]
            fixes.append((lat, lon, alt))
            g = geo_prior(lat, lon, alt, R_enu, COV_ENU)
            _send(
                mgr,
                out,
                encode(scan_from_arrays("car", "d1", s.index, s.stamp_ns, s.points_xyz, geo_prior=g)),
            )
        mgr.flush()
        # the map as `randt tiles download` fetches it: the projection comes with the tiles
        with MapClient(server.url) as api:
            api.download_map("default", tmp_path / "download")
            api.download_map("default", tmp_path / "mgrs", projector="MGRS")
            served = api.projector_info_yaml("default")
        # and as `randt tiles export` writes one file: the projection beside it, as Autoware's map folder
        from typer.testing import CliRunner

        from randt.cli.main import app

        exported = CliRunner().invoke(
            app, ["tiles", "export", "default", str(tmp_path / "export/map.pcd"), "--url", server.url]
        )
        assert exported.exit_code == 0, exported.output
        assert "its projection -> " in exported.output
    poses = {m.seq: np.reshape(m.pose, (4, 4)) for m in out if isinstance(m, PoseMessage)}
    assert sorted(poses) == list(range(N_SCANS)), [m for m in out if isinstance(m, ErrorMessage)][:3]
    # the map folder, as Autoware reads it: the projection beside the tiles
    folder = tmp_path / "data" / "maps" / "default"
    info = yaml.safe_load((folder / "map_projector_info.yaml").read_text(encoding="utf-8"))
    assert info["projector_type"] == "LocalCartesianUTM" and info["vertical_datum"] == "WGS84"
    assert served is not None and yaml.safe_load(served) == info
    assert yaml.safe_load((tmp_path / "download" / "map_projector_info.yaml").read_text()) == info
    assert yaml.safe_load((tmp_path / "export" / "map_projector_info.yaml").read_text()) == info
    geod = pyproj.Geod(ellps="WGS84")
    # the answered poses, taken to WGS84 with pyproj: on the fixes
    xyz = np.array([poses[k][:3, 3] for k in range(N_SCANS)])
    lat, lon, alt = _to_wgs84_with_pyproj(xyz, info)
    flat, flon, falt = (np.array(c) for c in zip(*fixes, strict=True))
    _, _, horizontal = geod.inv(lon, lat, flon, flat)
    error = np.hypot(horizontal, alt - falt)
    assert error.max() < 0.05, error
    # the origin was set from the first fix: on the tile grid, within a tile of it
    _, _, to_origin = geod.inv(
        flon[0], flat[0], info["map_origin"]["longitude"], info["map_origin"]["latitude"]
    )
    assert to_origin < 20.0 * np.sqrt(2) and info["map_origin"]["altitude"] == np.floor(falt[0])
    # the tiles' points, taken to WGS84 with pyproj and into the town's frame: on its surfaces
    points = np.concatenate([read_cloud(p).xyz for p in sorted(folder.glob("*.pcd"))])
    plat, plon, palt = _to_wgs84_with_pyproj(points.astype(np.float64), info)
    in_town = earth.to_map(plat, plon, palt)
    distance = town.surface_distance(in_town)
    assert len(points) > 10_000 and np.percentile(distance, 90) < 0.05, np.percentile(distance, [50, 90, 99])
    # the same map downloaded in MGRS: its square's corner from the mgrs package, the rest pyproj's
    mgrs_info = yaml.safe_load((tmp_path / "mgrs" / "map_projector_info.yaml").read_text(encoding="utf-8"))
    assert mgrs_info["projector_type"] == "MGRS" and mgrs_info["vertical_datum"] == "WGS84"
    grid = mgrs_info["mgrs_grid"]
    zone, _, east, north = mgrs.MGRS().MGRSToUTM(grid + "5000050000")  # the square's middle metre
    corner = np.array([east, north]) - 50_000.5
    to_utm = pyproj.Transformer.from_crs("EPSG:4326", f"EPSG:{32600 + zone}", always_xy=True)
    mgrs_points = np.concatenate([read_cloud(p).xyz for p in sorted((tmp_path / "mgrs").glob("*.pcd"))])
    assert (
        len(mgrs_points) == len(points) and mgrs_points[:, :2].min() >= 0 and mgrs_points[:, :2].max() < 1e5
    )
    mlon, mlat = to_utm.transform(
        mgrs_points[:, 0] + corner[0], mgrs_points[:, 1] + corner[1], direction="INVERSE"
    )
    distance = town.surface_distance(earth.to_map(mlat, mlon, mgrs_points[:, 2]))
    assert np.percentile(distance, 90) < 0.05, np.percentile(
        distance, [50, 90, 99]
    )  # (float32: 8 mm at 100 km)
    meta = yaml.safe_load((tmp_path / "mgrs" / "pointcloud_map_metadata.yaml").read_text(encoding="utf-8"))
    assert len(meta) - 2 == len(list((tmp_path / "mgrs").glob("*.pcd")))


def test_a_wgs84_prior_into_a_map_built_without_an_origin_is_refused_with_the_reason(tmp_path: Path) -> None:
    """A map that holds points but no origin was built in a local frame: a WGS84 prior cannot be
    placed in it (``invalid_prior``, saying so); a map-frame prior still can."""
    town = Town.generate(0)
    plan = plan_fleet(town, 1, seed=0, route_length_m=400.0)[0]
    scans = list(
        simulate(town, plan.route, n_scans=3, seed=3, lidar=Lidar64(n_azimuth=500), start_s_m=plan.start_s_m)
    )
    out: list = []
    settings = ServiceSettings(data_dir=tmp_path, flush_interval_s=0.3, capacity_target=0, graph=False)
    mgr = SessionManager(settings, Store(tmp_path), out.append, ServiceMetrics())
    try:
        assert mgr.wait_matchers(300)
        cov = np.diag([1e-4] * 3 + [1e-5] * 3)
        first = scan_from_arrays(
            "car", "d1", 0, 0, scans[0].points_xyz, prior_pose=scans[0].T_world_sensor, prior_covariance=cov
        )
        _send(mgr, out, encode(first))
        mgr.flush()
        g = geo_prior(48.137, 11.575, 520.0, np.eye(3), COV_ENU)
        _send(mgr, out, encode(scan_from_arrays("van", "d1", 0, 0, scans[1].points_xyz, geo_prior=g)), "van")
    finally:
        mgr.stop()
    refused = [m for m in out if isinstance(m, ErrorMessage)]
    assert len(refused) == 1 and refused[0].vehicle == "van" and refused[0].code == ErrorCode.INVALID_PRIOR
    assert "has no geodetic origin" in refused[0].reason, refused[0].reason
    assert not (tmp_path / "maps" / "default" / "map_projector_info.yaml").exists()
    with pytest.raises(BadMessageError):  # (the same check, without a service)
        mgr.projections.prior_in_map("default", mgr.maps["default"], g)
    assert mgr.projections.projection("default") is None


def test_a_given_origin_is_the_maps_and_a_conflicting_one_stops_the_service(tmp_path: Path) -> None:
    """``RANDT_MAP_ORIGIN``: written as the shared map's origin at start (the first WGS84 prior
    then lands in that frame); a restart with another origin, or one given to a map that holds
    points in a local frame, is refused before anything starts, saying why."""
    from randt.core.errors import InvalidRequestError

    def manager(data: Path, origin: tuple[float, float, float] | None) -> SessionManager:
        settings = ServiceSettings(data_dir=data, capacity_target=0, graph=False, map_origin=origin)
        return SessionManager(settings, Store(data), [].append, ServiceMetrics())

    given = (48.137, 11.575, 520.0)
    mgr = manager(tmp_path / "a", given)
    try:
        g = geo_prior(48.1375, 11.576, 521.0, np.eye(3), COV_ENU)
        placed = mgr.projections.prior_in_map("default", mgr.maps.grid("default"), g)
    finally:
        mgr.stop()
    info = yaml.safe_load((tmp_path / "a/maps/default/map_projector_info.yaml").read_text())
    assert info["map_origin"] == {"latitude": 48.137, "longitude": 11.575, "altitude": 520.0}
    expected = LocalCartesianUTM(GeoOrigin(*given)).to_map(48.1375, 11.576, 521.0)[0]
    assert np.allclose(placed.T_world_sensor[:3, 3], expected, atol=1e-6) and abs(expected[2] - 1.0) < 1e-9
    manager(tmp_path / "a", given).stop()  # the same origin again: fine
    with pytest.raises(InvalidRequestError, match="already has the geodetic origin"):
        manager(tmp_path / "a", (48.2, 11.5, 500.0))
    # a map built in a local frame (map-frame priors) cannot be given an origin afterwards
    mgr = manager(tmp_path / "b", None)
    try:
        assert mgr.wait_matchers(300)
        town = Town.generate(0)
        plan = plan_fleet(town, 1, seed=0, route_length_m=400.0)[0]
        scan = next(
            iter(
                simulate(
                    town,
                    plan.route,
                    n_scans=1,
                    seed=3,
                    lidar=Lidar64(n_azimuth=500),
                    start_s_m=plan.start_s_m,
                )
            )
        )
        cov = np.diag([1e-4] * 3 + [1e-5] * 3)
        mgr.submit(
            "car",
            encode(
                scan_from_arrays(
                    "car", "d1", 0, 0, scan.points_xyz, prior_pose=scan.T_world_sensor, prior_covariance=cov
                )
            ),
        )
        deadline = time.monotonic() + 60
        while not (tmp_path / "b/maps/default/pointcloud_map_metadata.yaml").exists():
            assert time.monotonic() < deadline, "the map was not saved"
            mgr.flush()
            time.sleep(0.1)
    finally:
        mgr.stop()
    with pytest.raises(InvalidRequestError, match="local frame"):
        manager(tmp_path / "b", given)
    # randt serve checks the same from the files before anything starts (one line, exit code 8)
    from randt.service.georef import check_map_origin

    check_map_origin(tmp_path / "a", "default", given)
    check_map_origin(tmp_path / "new", "default", given)
    with pytest.raises(InvalidRequestError, match="already has the geodetic origin"):
        check_map_origin(tmp_path / "a", "default", (48.2, 11.5, 500.0))
    with pytest.raises(InvalidRequestError, match="local frame"):
        check_map_origin(tmp_path / "b", "default", given)
    with pytest.raises(InvalidRequestError, match="UPS"):
        manager(tmp_path / "c", (88.0, 0.0, 0.0))


def test_a_ros2_robot_with_navsatfix_joins_the_shared_map_where_its_fixes_say(tmp_path: Path) -> None:
    """A ROS 2 robot's PointCloud2 with its NavSatFix (position only, with covariance) and no
    other session: its session runs in its own frame, its keyframes' fixes go to the shared map's
    pose graph, which places it by a fit of its fixes once they span 40 m (issue 34: "NavSatFix
    becomes the GNSS prior"); then its corrected trajectory, taken to WGS84 with pyproj from the
    map's yaml, lies on the fixes, and its points are folded into the shared map."""
    rosbags = pytest.importorskip("rosbags")  # noqa: F841
    from randt.wire.messages import GnssFix
    from randt.wire.ros2 import Ros2Scan, typestore

    n = 75
    town, scans = _drive(n)
    earth = LocalCartesianUTM(MUNICH)
    types = typestore().types
    field = types["sensor_msgs/msg/PointField"]
    fields = [field(name=c, offset=4 * i, datatype=7, count=1) for i, c in enumerate("xyz")]
    cov = np.diag([0.02**2, 0.02**2, 0.05**2])
    rng = np.random.default_rng(7)
    fixes = []
    with live_server(tmp_path / "data", capacity_target=0) as server:
        mgr, out = server.service.sessions, server.service._sent
        assert mgr is not None and mgr.graph is not None
        for s in scans:
            lat, lon, alt = (float(v[0]) for v in earth.to_geodetic(s.T_world_sensor[:3, 3]))
            fixes.append((lat, lon, alt))
            noisy = earth.to_geodetic(s.T_world_sensor[:3, 3] + rng.normal(0, [0.02, 0.02, 0.05]))
            fix = GnssFix(*(float(v[0]) for v in noisy), tuple(cov.ravel().tolist()))
            sec, nanosec = divmod(s.stamp_ns, 10**9)
            cloud = types["sensor_msgs/msg/PointCloud2"](
                header=types["std_msgs/msg/Header"](
                    stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id="lidar"
                ),
                height=1, width=len(s.points_xyz), fields=fields, is_bigendian=False, point_step=12,
                row_step=12 * len(s.points_xyz),
                data=np.frombuffer(s.points_xyz.astype("<f4").tobytes(), np.uint8),
                is_dense=True,
            )  # fmt: skip
            cdr = bytes(typestore().serialize_cdr(cloud, "sensor_msgs/msg/PointCloud2"))
            n_answered = _answered(out)
            mgr.submit("robot7", Ros2Scan(cdr, "/robot7/lidar/points", "robot7", "ab" * 16, s.index + 1, fix))
            deadline = time.monotonic() + 60
            while _answered(out) < n_answered + 1:
                assert time.monotonic() < deadline, "the service stopped answering"
                time.sleep(0.002)
        assert mgr.graph.wait_idle(120)
        joined = mgr.graph.joined("robot7", "ab" * 16)
        live = mgr.trajectory("robot7", "ab" * 16)
        assert live is not None
        corrected, graph_map = mgr.graph.corrected("robot7", "ab" * 16, live[1])
        mgr.flush()
    poses = [m for m in out if isinstance(m, PoseMessage)]
    assert len(poses) == n and all(p.status in ("first", "ok") for p in poses)
    assert joined is not None and joined[0] == "default", "not placed by its fixes"
    assert graph_map == "default"
    info = yaml.safe_load((tmp_path / "data/maps/default/map_projector_info.yaml").read_text())
    lat, lon, alt = _to_wgs84_with_pyproj(np.asarray(corrected)[:, :3, 3], info)
    flat, flon, falt = (np.array(c) for c in zip(*fixes, strict=True))
    _, _, horizontal = pyproj.Geod(ellps="WGS84").inv(lon, lat, flon, flat)
    error = np.hypot(horizontal, alt - falt)
    assert error.max() < 0.15, (  # measured: median 2.0 cm, max 4.7 cm (the fixes: 2 cm, 5 cm up)
        f"corrected trajectory: median {np.median(error):.3f} m, max {error.max():.3f} m"
    )
    # its sweeps are in the shared map, where the town's surfaces are
    points = np.concatenate(
        [read_cloud(p).xyz for p in sorted((tmp_path / "data/maps/default").glob("*.pcd"))]
    )
    in_town = earth.to_map(*_to_wgs84_with_pyproj(points.astype(np.float64), info))
    distance = town.surface_distance(in_town)
    assert len(points) > 10_000 and np.percentile(distance, 90) < 0.1, np.percentile(distance, [50, 90, 99])
