"""End to end on loopback: a Zenoh router, the service as a client, three simulated vehicles."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zenoh

from randt.clients.publisher import map_tiles_near
from randt.core.errors import BadMessageError
from randt.core.transforms import transform_error
from randt.service.runtime import Service
from randt.service.settings import ServiceSettings
from randt.sim.drive import simulate_fleet
from randt.sim.town import Town
from randt.wire.messages import decode_error, decode_pose, decode_tile_update, encode, scan_from_arrays
from randt.wire.zenoh_config import zenoh_config

N_VEHICLES = 3
N_SCANS = 10


@pytest.fixture(scope="module")
def fleet_scans():
    town = Town.generate(2)
    scans: dict[str, list] = {}
    for vehicle, scan in simulate_fleet(town, N_VEHICLES, n_scans=N_SCANS, seed=5, speed_mps=8.0):
        scans.setdefault(vehicle, []).append(scan)
    return scans


def _payload(vehicle: str, scan, *, prior: bool) -> bytes:
    rng = np.random.default_rng(scan.index)
    prior_pose = None
    if prior:  # GNSS-like: 5 cm, 0.2 deg of noise, and its covariance
        prior_pose = scan.T_world_sensor.copy()
        prior_pose[:3, 3] += rng.normal(0, 0.05, 3)
    return encode(
        scan_from_arrays(
            vehicle,
            "drive1",
            scan.index,
            scan.stamp_ns,
            scan.points_xyz,
            intensity=scan.intensity,
            prior_pose=prior_pose,
            prior_covariance=np.diag([0.05**2] * 3 + [np.radians(0.2) ** 2] * 3) if prior else None,
        )
    )


def test_three_vehicles_get_one_answer_per_scan_and_share_one_map(router, tmp_path, fleet_scans) -> None:
    settings = ServiceSettings(
        data_dir=tmp_path / "data",
        zenoh_mode="client",
        listen=(),
        connect=(router,),
        queue_size=64,
        flush_interval_s=0.5,
    )
    service = Service(settings)
    service.start()
    answers: dict[str, dict[int, list]] = {v: {} for v in fleet_scans}
    tiles: dict[str, int] = {}
    lock = threading.Lock()

    def on_pose(sample: zenoh.Sample) -> None:
        msg = decode_pose(sample.payload.to_bytes())
        with lock:
            answers[msg.vehicle].setdefault(msg.seq, []).append(msg)

    def on_error(sample: zenoh.Sample) -> None:
        msg = decode_error(sample.payload.to_bytes())
        with lock:
            answers[msg.vehicle].setdefault(msg.seq, []).append(msg)

    def on_tile(sample: zenoh.Sample) -> None:
        msg = decode_tile_update(sample.payload.to_bytes())
        with lock:
            tiles[msg.tile] = max(tiles.get(msg.tile, 0), msg.version)

    listener = zenoh.open(zenoh_config("client", connect=(router,)))
    subs = [listener.declare_subscriber("randt/map/default/tile/*", on_tile)]
    time.sleep(1.0)

    def drive(vehicle: str) -> None:
        # Each vehicle listens for its answers on its own session, as the vehicle library does:
        # its subscriber declarations then reach the service ahead of its first scan (same link,
        # in order). Answers for a separate listener session were dropped at the service's side
        # when that session's declarations had not arrived yet (a loaded machine lost pose 0).
        # A put made before this session has heard of the service's subscriber is dropped at the
        # source too: wait for the service first, and stay until this vehicle's answers are in.
        session = zenoh.open(zenoh_config("client", connect=(router,)))
        own = [
            session.declare_subscriber(f"randt/fleet/{vehicle}/pose", on_pose),
            session.declare_subscriber(f"randt/fleet/{vehicle}/error", on_error),
        ]
        # BLOCK, as the vehicle library sends: the default (DROP) may discard a 1.9 MB put
        pub = session.declare_publisher(
            f"randt/fleet/{vehicle}/scan", congestion_control=zenoh.CongestionControl.BLOCK
        )
        wait_until = time.monotonic() + 30
        while not pub.matching_status.matching and time.monotonic() < wait_until:
            time.sleep(0.05)
        for scan in fleet_scans[vehicle]:
            pub.put(_payload(vehicle, scan, prior=scan.index == 0))
            time.sleep(0.2)
        wait_until = time.monotonic() + 120
        while time.monotonic() < wait_until:
            with lock:
                if len(answers[vehicle]) >= N_SCANS:
                    break
            time.sleep(0.1)
        for sub in own:
            sub.undeclare()
        session.close()

    threads = [threading.Thread(target=drive, args=(v,)) for v in fleet_scans]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        with lock:
            done = sum(len(a) for a in answers.values())
        if done >= N_VEHICLES * N_SCANS:
            break
        time.sleep(0.5)
    time.sleep(settings.tile_save_s + settings.flush_interval_s + 0.5)  # the last tiles saved and published
    try:
        for vehicle, by_seq in answers.items():
            assert sorted(by_seq) == list(range(N_SCANS)), f"{vehicle}: answers for {sorted(by_seq)}"
            assert all(len(v) == 1 for v in by_seq.values()), f"{vehicle}: a scan got two answers"
            for seq, (msg,) in by_seq.items():
                assert msg.__class__.__name__ == "PoseMessage", f"{vehicle} seq {seq}: {msg}"
                assert msg.map == "default", "sessions with a prior pose fold into the shared map"
                truth = fleet_scans[vehicle][seq].T_world_sensor
                err_m, err_deg = transform_error(np.array(msg.pose).reshape(4, 4), truth)
                # the first pose is the prior (5 cm noise); registration keeps within that
                assert err_m < 0.15 and err_deg < 0.5, f"{vehicle} seq {seq}: {err_m:.3f} m {err_deg:.3f} deg"
        assert len(tiles) > 10, "tile updates were published"
        grid = service.sessions.maps["default"]
        assert set(tiles) <= set(grid.tile_ids())
        # a tile can be fetched through the queryable; it answers the tile as saved, so save
        # what may still be waiting (a flush under load can take longer than the sleep above)
        service.sessions.flush()
        tid = sorted(tiles)[0]
        replies = list(listener.get(f"randt/map/default/tile/{tid}"))
        got = decode_tile_update(replies[0].ok.payload.to_bytes())
        assert got.tile == tid and got.n_points == grid.get(tid).n_points
        # the tiles around a point, as a vehicle loads the map it localizes on: each saved tile
        # within the radius once, at its saved version; asked again holding them, none
        x, y = next(iter(fleet_scans.values()))[0].T_world_sensor[:2, 3]
        saved = service.sessions.maps.durable("default")
        assert saved is not None
        wanted = {t for t in grid.tiles_within_radius((x, y), 40.0) if t in saved.by_id}
        near = map_tiles_near(listener, "default", x, y, 40.0)
        assert {t.tile for t in near} == wanted and len(near) == len(wanted) > 3
        assert all(t.version == saved.by_id[t.tile].version and t.digest for t in near)
        held = {t.tile: t.version for t in near}
        assert map_tiles_near(listener, "default", x, y, 40.0, have=held) == []
        del held[near[0].tile]
        assert [t.tile for t in map_tiles_near(listener, "default", x, y, 40.0, have=held)] == [near[0].tile]
        with pytest.raises(BadMessageError, match="radius") as info:
            map_tiles_near(listener, "default", x, y, 5000.0)
        assert info.value.code == "invalid_field"
        assert (tmp_path / "data/maps/default/pointcloud_map_metadata.yaml").is_file()
    finally:
        for s in subs:
            s.undeclare()
        listener.close()
        service.stop()
