"""The HTTP API against a real uvicorn server on loopback (httpx), after a small simulated fleet ran.

One server (module scope) serves a service that mapped two vehicles with GNSS priors (map
``default``) and one without (map ``solo.drive1``). Tests compare what the API says with the live
service and the store's files, and check the error answers (404 bodies, 422, 401, 403, 304).
Tests that mutate (closing a session, growing a tile) come last in this file.
"""

from __future__ import annotations

import hashlib
import io
import itertools
import json
import math
import time

import httpx
import laspy
import numpy as np
import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families
from pydantic import ValidationError

from randt.core.io import read_cloud
from randt.core.scenes import synthetic_room
from randt.core.transforms import transform_error
from randt.service.settings import ServiceSettings
from randt.wire.messages import ErrorMessage, encode, scan_from_arrays
from tests.service.api_server import TOKEN, Fleet, LiveServer, answers, drive_fleet, live_server, wait_answers

AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> tuple[LiveServer, Fleet, httpx.Client]:
    data = tmp_path_factory.mktemp("api") / "data"
    with live_server(data, api_token=TOKEN) as server:
        fleet = drive_fleet(server.service)
        # Two rejected scans, so /metrics has reasons to count: a duplicate seq and garbage bytes.
        last = fleet.scans["sim000"][-1]
        dup = encode(scan_from_arrays("sim000", fleet.session, last.index, last.stamp_ns, last.points_xyz))
        server.service.sessions.submit("sim000", dup)
        server.service.sessions.submit("sim000", b"\x93not a scan")
        wait_answers(server.service, fleet.n_scans + 2)
        with httpx.Client(base_url=server.url, timeout=30) as client:
            yield server, fleet, client


def _open3d_points(path) -> np.ndarray:
    import open3d as o3d

    return np.asarray(o3d.io.read_point_cloud(str(path)).points)


# ------------------------------------------------------------------------------ health and status


def test_health_ready_docs_and_openapi(served) -> None:
    _, _, client = served
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200
    assert ready.json() == {
        "ready": True,
        "zenoh": True,
        "store_writable": True,
        "workers": True,
        "matchers_warm": True,
        "graph": True,
    }
    schema = client.get("/openapi.json").json()
    paths = set(schema["paths"])
    assert {
        "/healthz",
        "/readyz",
        "/status",
        "/sessions",
        "/sessions/{vehicle}/{session}",
        "/sessions/{vehicle}/{session}/trajectory",
        "/sessions/{vehicle}/{session}/close",
        "/metrics",
        "/maps",
        "/maps/{map}",
        "/maps/{map}/tiles",
        "/maps/{map}/tiles/{ix}/{iy}",
        "/maps/{map}/metadata.yaml",
        "/maps/{map}/map_projector_info.yaml",
        "/maps/{map}/export",
    } <= paths
    assert "SessionDetail" in schema["components"]["schemas"]
    assert schema["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"
    docs = client.get("/docs")
    assert docs.status_code == 200 and "swagger" in docs.text.lower()


def test_status_counts_sessions_and_maps(served) -> None:
    server, fleet, client = served
    status = client.get("/status").json()
    mgr = server.service.sessions
    assert status["instance"] == "randt-1" and status["ready"] is True and status["uptime_s"] > 0
    assert status["scans_received"] == fleet.n_scans + 2
    assert status["scans_processed"] == fleet.n_scans
    assert status["scans_rejected"] == 2
    assert status["scans_dropped"] == 0
    assert sorted(s["id"] for s in status["sessions"]) == ["sim000/drive1", "sim001/drive1", "solo/drive1"]
    assert status["queue_depths"] == {"sim000/drive1": 0, "sim001/drive1": 0, "solo/drive1": 0}
    assert set(status["maps"]) == {"default", "solo.drive1"}
    for name, summary in status["maps"].items():
        grid = mgr.maps[name]
        assert summary["tiles"] == len(grid) > 0
        assert summary["points"] == grid.n_points
        lo, hi = grid.extent
        np.testing.assert_allclose(summary["extent"]["min_xyz"], lo)
        np.testing.assert_allclose(summary["extent"]["max_xyz"], hi)
    assert status["maps"]["default"]["sessions"] == ["sim000/drive1", "sim001/drive1"]


# ------------------------------------------------------------------------------ sessions


def test_sessions_list_and_detail(served) -> None:
    _, fleet, client = served
    listed = {s["id"]: s for s in client.get("/sessions").json()}
    assert set(listed) == {"sim000/drive1", "sim001/drive1", "solo/drive1"}
    assert listed["solo/drive1"]["map"] == "solo.drive1" and listed["solo/drive1"]["frame"] == "session"
    assert listed["sim001/drive1"]["map"] == "default" and listed["sim001/drive1"]["frame"] == "map"
    assert client.get("/sessions", params={"state": "closed"}).json() == []

    for vehicle in ("sim000", "sim001"):
        scans = fleet.scans[vehicle]
        detail = client.get(f"/sessions/{vehicle}/drive1").json()
        assert detail["vehicle"] == vehicle and detail["state"] == "active"
        assert detail["scans"] == len(scans) and detail["last_seq"] == len(scans) - 1
        assert detail["errors"] == (1 if vehicle == "sim000" else 0)  # the duplicate seq
        err_m, err_deg = transform_error(np.array(detail["last_pose"]), scans[-1].T_world_sensor)
        assert err_m < 0.15 and err_deg < 0.5, (err_m, err_deg)
        np.testing.assert_allclose(detail["position"], np.array(detail["last_pose"])[:3, 3])
        true_path = sum(
            np.linalg.norm(b.T_world_sensor[:3, 3] - a.T_world_sensor[:3, 3])
            for a, b in itertools.pairwise(scans)
        )
        assert detail["distance_m"] == pytest.approx(true_path, abs=0.3)
        assert detail["fitness"] > 0
        # the prior's 5 cm per axis is the floor of the drift estimate
        assert math.sqrt(3 * 0.05**2) <= detail["drift_m"] < 0.5
        assert detail["lag"]["queue_depth"] == 0 and detail["lag"]["last_latency_ms"] > 0
        assert detail["lag"]["idle_s"] >= 0
        assert detail["created"] is not None  # flushed to the store


def test_trajectory_json_kitti_tum(served) -> None:
    server, fleet, client = served
    stamps, poses = server.service.sessions.trajectory("sim001", "drive1")
    js = client.get("/sessions/sim001/drive1/trajectory").json()
    assert js["id"] == "sim001/drive1" and js["frame"] == "map" and js["map"] == "default"
    assert len(js["poses"]) == len(fleet.scans["sim001"]) == len(poses)
    np.testing.assert_allclose([p["pose"] for p in js["poses"]], poses, atol=1e-12)
    np.testing.assert_allclose([p["stamp_s"] for p in js["poses"]], stamps)

    kitti = client.get("/sessions/sim001/drive1/trajectory", params={"format": "kitti"})
    assert kitti.status_code == 200 and kitti.headers["content-type"].startswith("text/plain")
    rows = np.loadtxt(io.StringIO(kitti.text)).reshape(-1, 12)
    np.testing.assert_allclose(rows.reshape(-1, 3, 4), poses[:, :3, :], atol=1e-8)

    tum = client.get("/sessions/sim001/drive1/trajectory", params={"format": "tum"}).text
    assert tum.startswith("# timestamp tx ty tz qx qy qz qw")
    table = np.loadtxt(io.StringIO(tum), comments="#")
    assert table.shape == (len(poses), 8)
    np.testing.assert_allclose(table[:, 0], stamps, atol=1e-9)
    np.testing.assert_allclose(table[:, 1:4], poses[:, :3, 3], atol=1e-9)

    assert client.get("/sessions/sim001/drive1/trajectory", params={"format": "csv"}).status_code == 422


def test_unknown_session_and_invalid_ids(served) -> None:
    _, _, client = served
    for path in ("/sessions/nobody/drive1", "/sessions/nobody/drive1/trajectory"):
        r = client.get(path)
        assert r.status_code == 404
        assert r.json() == {
            "detail": "session 'nobody/drive1' not found",
            "resource": "session",
            "id": "nobody/drive1",
        }
    r = client.post("/sessions/nobody/drive1/close", headers=AUTH)
    assert r.status_code == 404 and r.json()["id"] == "nobody/drive1"
    # names the store would refuse never reach a handler
    for bad in ("-dash", ".hidden", "a" * 65, "sp%20ace", "semi;colon"):
        assert client.get(f"/sessions/{bad}/drive1").status_code == 422, bad
    # an encoded slash or dot-dot cannot name a file: no route matches, or the name is refused
    for path in ("/sessions/..%2F..%2Fetc/passwd", "/maps/..%2F..%2Fetc/tiles", "/maps/../tiles"):
        assert client.get(path).status_code in (404, 422), path
    # the viewer's static files stay inside service/static
    for path in ("/static/%2e%2e/app.py", "/static/..%2Fapp.py", "/static/%2e%2e/%2e%2e/pyproject.toml"):
        r = client.get(path)
        assert r.status_code == 404 and "create_app" not in r.text and "[project]" not in r.text, path
    assert client.get("/static/viewer.js").status_code == 200


# ------------------------------------------------------------------------------ metrics


def test_metrics_parsed_by_prometheus_client(served) -> None:
    server, fleet, client = served
    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    samples: dict[tuple[str, tuple], float] = {}
    for family in text_string_to_metric_families(r.text):
        for s in family.samples:
            samples[(s.name, tuple(sorted(s.labels.items())))] = s.value
    n = fleet.n_scans
    assert samples[("randt_scans_received_total", ())] == n + 2
    processed = {k[1]: v for k, v in samples.items() if k[0] == "randt_scans_processed_total"}
    assert sum(processed.values()) == n
    assert processed[(("status", "first"),)] == len(fleet.scans)  # every session's first scan
    rejected = {dict(k[1])["reason"]: v for k, v in samples.items() if k[0] == "randt_scans_rejected_total"}
    assert rejected["duplicate_seq"] == 1 and sum(rejected.values()) == 2
    assert samples[("randt_scans_dropped_total", ())] == 0
    assert samples[("randt_registration_seconds_count", ())] == n
    assert 0 < samples[("randt_registration_seconds_sum", ())] < 60
    assert samples[("randt_scan_to_pose_latency_seconds_count", ())] == n
    assert samples[("randt_registration_seconds_bucket", (("le", "+Inf"),))] == n
    for sid in ("sim000/drive1", "sim001/drive1", "solo/drive1"):
        assert samples[("randt_session_queue_depth", (("session", sid),))] == 0
    assert samples[("randt_sessions_active", ())] == 3
    grid = server.service.sessions.maps["default"]
    assert samples[("randt_tiles_written_total", ())] >= len(grid)
    assert samples[("randt_store_errors_total", ())] == 0
    assert samples[("randt_map_tiles", (("map", "default"),))] == len(grid)
    assert samples[("randt_map_points", (("map", "default"),))] == grid.n_points
    assert samples[("randt_service_info", (("instance", "randt-1"),))] == 1


# ------------------------------------------------------------------------------ maps and tiles


def test_maps_and_tile_index(served) -> None:
    server, _, client = served
    maps = client.get("/maps").json()["maps"]
    assert [m["name"] for m in maps] == ["default", "solo.drive1"]
    grid = server.service.sessions.maps["default"]
    summary = client.get("/maps/default").json()
    assert summary["tiles"] == len(grid) and summary["tile_size_m"] == 20 and summary["voxel_size_m"] == 0.2

    index = client.get("/maps/default/tiles").json()
    assert index["query"] is None and index["pdu_voxel_m"] == 0.5
    tiles = {t["id"]: t for t in index["tiles"]}
    assert list(tiles) == grid.tile_ids()
    expected_pdu = grid.tile_pdu(0.5)
    for tid, t in tiles.items():
        tile = grid.get(tid)
        assert (t["ix"], t["iy"], t["version"], t["points"]) == (
            tile.ix,
            tile.iy,
            tile.version,
            tile.n_points,
        )
        assert t["bounds"]["cell_min_xy"] == [tile.ix * 20, tile.iy * 20]
        assert t["pdu"] == pytest.approx(expected_pdu[tid], abs=1e-12)
        assert t["url"] == f"/maps/default/tiles/{tile.ix}/{tile.iy}"
    assert all(t["pdu"] <= 1 for t in tiles.values()) and len({t["pdu"] for t in tiles.values()}) > 1

    box = client.get("/maps/default/tiles", params={"bbox": "-30,-30,30,10"}).json()
    assert [t["id"] for t in box["tiles"]] == grid.tiles_in_bbox((-30, -30), (30, 10))
    assert box["query"] == {"x_min": -30, "y_min": -30, "x_max": 30, "y_max": 10}
    assert 0 < len(box["tiles"]) < len(tiles)
    near = client.get("/maps/default/tiles", params={"x": 5, "y": -7.5, "radius": 25}).json()
    assert [t["id"] for t in near["tiles"]] == grid.tiles_within_radius((5, -7.5), 25)
    assert 0 < len(near["tiles"]) < len(tiles)

    for params in (
        {"bbox": "1,2,3"},
        {"bbox": "0,0,nan,1"},
        {"bbox": "10,0,0,10"},  # inverted
        {"bbox": "a,b,c,d"},
        {"x": 1, "y": 2},  # radius missing
        {"x": 1, "y": 2, "radius": -1},
        {"x": "inf", "y": 2, "radius": 1},
        {"bbox": "0,0,1,1", "x": 0, "y": 0, "radius": 1},
        {"pdu_voxel_m": 0},
    ):
        r = client.get("/maps/default/tiles", params=params)
        assert r.status_code == 422, params
    r = client.get("/maps/nowhere/tiles")
    assert r.status_code == 404 and r.json() == {
        "detail": "map 'nowhere' not found",
        "resource": "map",
        "id": "nowhere",
    }


def test_tile_pcd_matches_the_store_and_opens_in_open3d(served, tmp_path) -> None:
    server, _, client = served
    grid = server.service.sessions.maps["default"]
    tile = max(grid.tiles(), key=lambda t: t.n_points)
    r = client.get(f"/maps/default/tiles/{tile.ix}/{tile.iy}")
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-pcd"
    # strong, named by the content: version, the SHA-256 of the float32 x y z intensity table, format
    table = np.c_[tile.points, tile.intensity].astype("<f4").tobytes()
    assert r.headers["etag"] == f'"{tile.version}-{hashlib.sha256(table).hexdigest()[:16]}-pcd"'
    assert r.headers["x-randt-tile-version"] == str(tile.version)
    downloaded = tmp_path / f"{tile.id}.pcd"
    downloaded.write_bytes(r.content)
    got = _open3d_points(downloaded)  # Open3D, an independent reader
    stored_file = server.settings.data_dir / "maps/default" / f"{tile.id}.pcd"
    stored = _open3d_points(stored_file)
    assert got.shape == (tile.n_points, 3)
    np.testing.assert_array_equal(got, stored)  # the same points, in the same order
    assert r.content == stored_file.read_bytes()  # indeed the same file
    ours = read_cloud(downloaded)
    np.testing.assert_array_equal(ours.intensity, read_cloud(stored_file).intensity)

    # HEAD wherever GET: the same status and headers, no body
    head = client.head(f"/maps/default/tiles/{tile.ix}/{tile.iy}")
    assert head.status_code == 200 and head.content == b""
    for name in ("etag", "content-type", "content-length", "x-randt-tile-version"):
        assert head.headers[name] == r.headers[name], name
    assert client.head("/maps/default/tiles/999/999").status_code == 404
    assert client.head("/status").status_code == 200 and client.head("/").status_code == 200

    # conditional GET: the current ETag -> 304 without a body; another one -> 200
    again = client.get(
        f"/maps/default/tiles/{tile.ix}/{tile.iy}", headers={"If-None-Match": r.headers["etag"]}
    )
    assert again.status_code == 304 and again.content == b"" and again.headers["etag"] == r.headers["etag"]
    star = client.get(f"/maps/default/tiles/{tile.ix}/{tile.iy}", headers={"If-None-Match": "*"})
    assert star.status_code == 304
    stale = client.get(f"/maps/default/tiles/{tile.ix}/{tile.iy}", headers={"If-None-Match": 'W/"0-pcd"'})
    assert stale.status_code == 200 and stale.content == r.content
    # the old weak form of the same version names no content: never a 304
    weak = client.get(
        f"/maps/default/tiles/{tile.ix}/{tile.iy}", headers={"If-None-Match": f'W/"{tile.version}-pcd"'}
    )
    assert weak.status_code == 200


def test_tile_ply_and_las(served, tmp_path) -> None:
    import open3d as o3d

    server, _, client = served
    tile = server.service.sessions.maps["default"].tiles()[0]
    ply = client.get(f"/maps/default/tiles/{tile.ix}/{tile.iy}", params={"format": "ply"})
    assert ply.status_code == 200 and ply.headers["etag"].startswith(f'"{tile.version}-')
    assert ply.headers["etag"].endswith('-ply"')
    (tmp_path / "t.ply").write_bytes(ply.content)
    np.testing.assert_array_equal(
        np.asarray(o3d.io.read_point_cloud(str(tmp_path / "t.ply")).points), tile.points
    )

    las = client.get(f"/maps/default/tiles/{tile.ix}/{tile.iy}", params={"format": "las"})
    assert las.status_code == 200 and las.headers["content-type"] == "application/vnd.las"
    f = laspy.read(io.BytesIO(las.content))
    assert f.header.version.minor == 4 and f.header.point_count == tile.n_points
    np.testing.assert_allclose(np.c_[f.x, f.y, f.z], tile.points, atol=6e-5)  # 0.1 mm integer grid
    np.testing.assert_array_equal(np.asarray(f.intensity_raw), tile.intensity)


def test_tile_errors(served) -> None:
    _, _, client = served
    r = client.get("/maps/default/tiles/9999/-9999")
    assert r.status_code == 404
    assert r.json() == {
        "detail": "tile '9999_-9999' of map 'default' not found (holds no points, or not saved yet)",
        "resource": "tile",
        "id": "9999_-9999",
    }
    assert client.get("/maps/nowhere/tiles/0/0").json()["resource"] == "map"
    for path in (
        "/maps/default/tiles/abc/0",
        "/maps/default/tiles/0/1.5",
        f"/maps/default/tiles/{2**40}/0",
        # only the integers tile_id writes (docs/api.md): pydantic's lax int took each of these
        *(f"/maps/default/tiles/0/{bad}" for bad in ("1.0", "+1", "%20%31", "0_0", "01", "-0", "--1")),
        "/maps/default/tiles/0/0?format=xyz",
        "/maps/bad%20name/tiles/0/0",
    ):
        assert client.get(path).status_code == 422, path


def test_metadata_yaml_has_integer_corners(served) -> None:
    server, _, client = served
    r = client.get("/maps/default/metadata.yaml")
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/yaml")
    doc = yaml.safe_load(r.text)
    assert doc.pop("x_resolution") == 20.0 and doc.pop("y_resolution") == 20.0
    grid = server.service.sessions.maps["default"]
    assert sorted(doc) == sorted(f"{tid}.pcd" for tid in grid.tile_ids())
    for name, corner in doc.items():
        ix, iy = (int(v) for v in name.removesuffix(".pcd").split("_"))
        assert all(type(v) is int for v in corner) and corner == [ix * 20, iy * 20]
    stored = yaml.safe_load(
        (server.settings.data_dir / "maps/default/pointcloud_map_metadata.yaml").read_text()
    )
    assert yaml.safe_load(r.text) == stored


def test_a_map_in_a_local_frame_has_no_projector_info(served) -> None:
    """Its fleet's priors are in the map frame: no geodetic origin, 404 saying so (a georeferenced
    map's file: tests/service/test_georef.py); a map that does not exist is a 404 of its own."""
    _, _, client = served
    r = client.get("/maps/default/map_projector_info.yaml")
    assert r.status_code == 404 and "has no geodetic origin" in r.json()["detail"], r.text
    r = client.get("/maps/nowhere/map_projector_info.yaml")
    assert r.status_code == 404 and "nowhere" in r.json()["detail"], r.text


def test_export_streams_the_merged_map(served, tmp_path) -> None:
    import open3d as o3d

    server, _, client = served
    grid = server.service.sessions.maps["default"]
    with client.stream("GET", "/maps/default/export") as r:
        assert r.status_code == 200 and r.headers["x-randt-points"] == str(grid.n_points)
        assert "content-length" not in r.headers  # streamed, tile by tile
        body = b"".join(r.iter_bytes())
    (tmp_path / "all.pcd").write_bytes(body)
    merged = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "all.pcd")).points)
    np.testing.assert_array_equal(merged, grid.to_cloud().xyz)

    ply = client.get("/maps/default/export", params={"format": "ply", "bbox": "-20,-20,20,20"})
    (tmp_path / "box.ply").write_bytes(ply.content)
    inside = grid.points_in_bbox((-20, -20), (20, 20))
    assert 0 < inside.n_points < grid.n_points
    np.testing.assert_array_equal(
        np.asarray(o3d.io.read_point_cloud(str(tmp_path / "box.ply")).points), inside.xyz
    )

    las = laspy.read(io.BytesIO(client.get("/maps/solo.drive1/export", params={"format": "las"}).content))
    assert las.header.point_count == server.service.sessions.maps["solo.drive1"].n_points
    assert client.get("/maps/default/export", params={"format": "e57"}).status_code == 422
    assert client.get("/maps/default/export", params={"bbox": "1,1,0,0"}).status_code == 422


# ------------------------------------------------------------------------------ mutations (last)


def test_tile_etag_changes_when_the_tile_grows(served) -> None:
    server, _, client = served
    grid = server.service.sessions.maps["default"]
    tile = grid.tiles()[0]
    first = client.get(f"/maps/default/tiles/{tile.ix}/{tile.iy}")
    # a point in an empty voxel of the same tile (as a worker's insert would add it)
    x0, y0 = tile.bounds.cell_min_xy
    changed = grid.insert(np.array([[x0 + 0.1, y0 + 0.1, 40.0]], dtype=np.float32))
    assert changed == [tile.id]
    # not saved yet: the saved tile is still served (a version seen outside is always on disk)
    r = client.get(
        f"/maps/default/tiles/{tile.ix}/{tile.iy}", headers={"If-None-Match": first.headers["etag"]}
    )
    assert r.status_code == 304 and r.headers["x-randt-tile-version"] == str(tile.version)
    server.service.sessions.maps.mark_dirty("default", changed)
    server.service.sessions.flush()
    r = client.get(
        f"/maps/default/tiles/{tile.ix}/{tile.iy}", headers={"If-None-Match": first.headers["etag"]}
    )
    assert r.status_code == 200 and r.headers["etag"].startswith(f'"{tile.version + 1}-')
    # one more float32 x y z intensity row (16 bytes) and a header counting one more point
    before, after = _pcd_header_and_body(first.content), _pcd_header_and_body(r.content)
    assert int(after[0]["POINTS"]) == int(before[0]["POINTS"]) + 1
    assert len(after[1]) == len(before[1]) + 16


def _pcd_header_and_body(content: bytes) -> tuple[dict[str, str], bytes]:
    """A binary PCD's header fields and its data bytes."""
    head, _, body = content.partition(b"DATA binary\n")
    fields = dict(line.split(" ", 1) for line in head.decode().splitlines() if " " in line)
    return fields, body


def test_close_session_needs_the_token(served) -> None:
    server, _, client = served
    r = client.post("/sessions/solo/drive1/close")
    assert r.status_code == 401 and r.headers["www-authenticate"].startswith("Bearer")
    assert "missing bearer token" in r.json()["detail"]
    r = client.post("/sessions/solo/drive1/close", headers={"Authorization": "Bearer wrong-token-0123456789"})
    assert r.status_code == 401 and r.json()["detail"] == "wrong bearer token"
    assert client.post("/sessions/solo/drive1/close", headers={"Authorization": TOKEN}).status_code == 401
    assert server.service.sessions.worker("solo", "drive1") is not None, "refused requests changed nothing"

    r = client.post("/sessions/solo/drive1/close", headers=AUTH)
    assert r.status_code == 200
    assert r.json() == {"id": "solo/drive1", "state": "closed", "scans": 3, "changed": True}
    assert server.service.sessions.worker("solo", "drive1") is None
    detail = client.get("/sessions/solo/drive1").json()
    assert detail["state"] == "closed" and detail["scans"] == 3 and detail["drift_m"] is None
    assert len(client.get("/sessions/solo/drive1/trajectory").json()["poses"]) == 3  # from the store
    again = client.post("/sessions/solo/drive1/close", headers=AUTH).json()
    assert again["changed"] is False and again["state"] == "closed"
    assert [s["id"] for s in client.get("/sessions", params={"state": "closed"}).json()] == ["solo/drive1"]
    stored = json.loads((server.settings.data_dir / "sessions/solo/drive1/session.json").read_text())
    assert stored["state"] == "closed"
    metrics = client.get("/metrics").text
    assert 'randt_session_queue_depth{session="solo/drive1"}' not in metrics


# ------------------------------------------------------------------------------ auth variants


def test_mutations_are_refused_without_a_configured_token(tmp_path) -> None:
    with live_server(tmp_path / "data") as server, httpx.Client(base_url=server.url, timeout=10) as client:
        room = synthetic_room(np.random.default_rng(0), 3000).astype(np.float32)
        server.service.sessions.submit("car7", encode(scan_from_arrays("car7", "d1", 0, 0, room)))
        wait_answers(server.service, 1)
        assert not isinstance(answers(server.service)[0], ErrorMessage)
        for headers in ({}, {"Authorization": "Bearer anything-at-all-000"}):
            r = client.post("/sessions/car7/d1/close", headers=headers)
            assert r.status_code == 403 and "no RANDT_API_TOKEN" in r.json()["detail"]
        assert server.service.sessions.worker("car7", "d1") is not None
        assert client.get("/sessions/car7/d1").status_code == 200  # reads stay open


def test_protect_reads_puts_reads_behind_the_token(tmp_path) -> None:
    with (
        live_server(tmp_path / "data", api_token=TOKEN, protect_reads=True) as server,
        httpx.Client(base_url=server.url, timeout=10) as client,
    ):
        for path in ("/status", "/sessions", "/maps", "/metrics", "/maps/default/tiles"):
            assert client.get(path).status_code == 401, path
        assert client.get("/status", headers=AUTH).status_code == 200
        assert client.get("/metrics", headers=AUTH).status_code == 200
        assert client.get("/maps/default/tiles", headers=AUTH).status_code == 404  # no such map yet
        assert client.get("/healthz").status_code == 200 and client.get("/readyz").status_code == 200
        assert client.get("/").status_code == 200  # the page itself; it asks for the token


def test_settings_refuse_protected_reads_without_a_token(tmp_path) -> None:
    with pytest.raises(ValidationError, match="protect_reads needs api_token"):
        ServiceSettings(data_dir=tmp_path, protect_reads=True)
    with pytest.raises(ValidationError):
        ServiceSettings(data_dir=tmp_path, api_token="short")


def test_after_a_restart_stored_sessions_are_idle_and_can_be_closed(tmp_path) -> None:
    room = synthetic_room(np.random.default_rng(0), 3000).astype(np.float32)
    with live_server(tmp_path / "data", api_token=TOKEN) as first:
        for seq in (0, 1):
            first.service.sessions.submit(
                "car7", encode(scan_from_arrays("car7", "d1", seq, seq * 10**8, room))
            )
        wait_answers(first.service, 2)
        poses_before = first.service.sessions.trajectory("car7", "d1")[1]
    with (
        live_server(tmp_path / "data", api_token=TOKEN) as second,
        httpx.Client(base_url=second.url) as client,
    ):
        (listed,) = client.get("/sessions").json()
        assert listed["id"] == "car7/d1" and listed["state"] == "idle" and listed["scans"] == 2
        detail = client.get("/sessions/car7/d1").json()
        np.testing.assert_allclose(detail["last_pose"], poses_before[-1], atol=1e-12)
        assert detail["drift_m"] is None and detail["lag"]["idle_s"] is None
        traj = client.get("/sessions/car7/d1/trajectory").json()
        np.testing.assert_allclose([p["stamp_s"] for p in traj["poses"]], [0.0, 0.1])
        assert [m["name"] for m in client.get("/maps").json()["maps"]] == ["car7.d1"]
        closed = client.post("/sessions/car7/d1/close", headers=AUTH).json()
        assert closed == {"id": "car7/d1", "state": "closed", "scans": 2, "changed": True}
        assert client.get("/sessions/car7/d1").json()["state"] == "closed"
        stored = json.loads((tmp_path / "data/sessions/car7/d1/session.json").read_text())
        assert stored["state"] == "closed"


def test_delete_map_needs_the_token_refuses_a_map_in_use_and_survives_a_restart(tmp_path) -> None:
    data = tmp_path / "data"
    room = synthetic_room(np.random.default_rng(5), 3000).astype(np.float32)
    auth = {"Authorization": f"Bearer {TOKEN}"}
    metadata = data / "maps/van.d1/pointcloud_map_metadata.yaml"
    with live_server(data, api_token=TOKEN) as server, httpx.Client(base_url=server.url) as client:
        mgr = server.service.sessions
        for seq in range(2):  # no prior: the session's own map, "van.d1"
            mgr.submit("van", encode(scan_from_arrays("van", "d1", seq, seq * 100_000_000, room)))
        wait_answers(server.service, 2)
        deadline = time.monotonic() + 20
        while not metadata.is_file() and time.monotonic() < deadline:
            time.sleep(0.1)
        n_tiles = len(mgr.maps["van.d1"])
        assert n_tiles > 0

        assert client.delete("/maps/van.d1").status_code == 401
        r = client.delete("/maps/van.d1", headers=auth)
        assert r.status_code == 409 and "van/d1" in r.json()["detail"], "a running session writes into it"
        assert client.delete("/maps/nowhere", headers=auth).json() == {
            "detail": "map 'nowhere' not found",
            "resource": "map",
            "id": "nowhere",
        }
        assert client.delete("/maps/.deleted-van.d1-1-2", headers=auth).status_code == 422  # not a name

        assert client.post("/sessions/van/d1/close", headers=auth).status_code == 200
        r = client.delete("/maps/van.d1", headers=auth)
        assert r.status_code == 200 and r.json() == {"map": "van.d1", "tiles": n_tiles, "deleted": True}
        assert client.get("/maps/van.d1").status_code == 404
        assert "van.d1" not in [m["name"] for m in client.get("/maps").json()["maps"]]
        assert not (data / "maps/van.d1").exists()
        assert len(client.get("/sessions/van/d1/trajectory").json()["poses"]) == 2, "trajectories stay"
    with live_server(data, api_token=TOKEN) as server, httpx.Client(base_url=server.url) as client:
        assert client.get("/maps/van.d1").status_code == 404, "a deleted map does not come back"
        assert not list((data / "maps").iterdir())
