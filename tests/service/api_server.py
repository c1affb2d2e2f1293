"""A real uvicorn server on loopback around ``create_app``, and a small simulated fleet to feed it.

Shared by ``test_api.py`` and ``test_viewer.py``. The fleet goes straight into the session manager
(``Service.sessions.submit`` with wire-encoded scans, ``with_zenoh=False``): Zenoh is not what these
tests are about (``test_e2e.py`` and ``test_serve.py`` cover it). Scans come from the simulator with
a 1000-column LiDAR (about 60k points, a sixth of the matcher's time of a full sweep) so a fleet
runs in seconds.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench.harness import start_server, stop_server
from randt.service.app import create_app
from randt.service.runtime import Service
from randt.service.settings import ServiceSettings
from randt.sim.drive import Route, SimScan, simulate, simulate_fleet
from randt.sim.lidar import Lidar64
from randt.sim.town import Town
from randt.wire.messages import ErrorMessage, PoseMessage, encode, scan_from_arrays
from tests.service.conftest import free_port

TOKEN = "test-token-0123456789abcdef"
PRIOR_COV = np.diag([0.05**2] * 3 + [np.radians(0.2) ** 2] * 3)


@dataclass
class LiveServer:
    """A running app: its base URL and the Service behind it."""

    url: str
    service: Service
    settings: ServiceSettings


@contextmanager
def live_server(data_dir: Path, *, with_zenoh: bool = False, **overrides: object) -> Iterator[LiveServer]:
    """Serve ``create_app(settings, with_zenoh=with_zenoh)`` with uvicorn on a free loopback port
    (without Zenoh by default: the test feeds the session manager and reads ``service._sent``)."""
    settings = ServiceSettings(data_dir=data_dir, flush_interval_s=0.3, queue_size=64, **overrides)
    app = create_app(settings, with_zenoh=with_zenoh)
    server, thread = start_server(app, free_port(), "uvicorn-test")
    # Ready as a deployment's probe sees it: the matcher processes have loaded their kernels.
    assert app.state.service.sessions.wait_matchers(300), "matcher processes did not warm up"
    try:
        yield LiveServer(f"http://127.0.0.1:{server.config.port}", app.state.service, settings)
    finally:
        stop_server(server, thread)


@dataclass
class Fleet:
    """What was driven: the scans per vehicle and which vehicles had a prior (map frame)."""

    scans: dict[str, list[SimScan]] = field(default_factory=dict)
    with_prior: set[str] = field(default_factory=set)
    session: str = "drive1"

    @property
    def n_scans(self) -> int:
        return sum(len(v) for v in self.scans.values())


def _payload(vehicle: str, session: str, scan: SimScan, *, prior: bool) -> bytes:
    extra = {}
    if prior:
        extra = {"prior_pose": scan.T_world_sensor, "prior_covariance": PRIOR_COV}
    return encode(
        scan_from_arrays(
            vehicle, session, scan.index, scan.stamp_ns, scan.points_xyz, intensity=scan.intensity, **extra
        )
    )


def answers(service: Service) -> list[PoseMessage | ErrorMessage]:
    """Poses and errors the service has sent so far."""
    return [m for m in list(service._sent) if isinstance(m, PoseMessage | ErrorMessage)]


def wait_answers(service: Service, n: int, timeout: float = 120.0) -> list[PoseMessage | ErrorMessage]:
    """Wait until the service has sent ``n`` poses and errors; returns all it has sent."""
    deadline = time.monotonic() + timeout
    while len(answers(service)) < n:
        if time.monotonic() > deadline:
            raise TimeoutError(f"{len(answers(service))} of {n} scans answered")
        time.sleep(0.05)
    return answers(service)


def drive_fleet(service: Service, *, n_vehicles: int = 2, n_scans: int = 5, solo_scans: int = 3) -> Fleet:
    """``n_vehicles`` with a GNSS prior on their first scan (shared map ``default``) and one vehicle
    ``solo`` without priors (its own map ``solo.drive1``); returns when every scan is answered and
    the maps are flushed to the store."""
    town = Town.generate(2)
    lidar = Lidar64(n_azimuth=1000)
    fleet = Fleet()
    for vehicle, scan in simulate_fleet(
        town, n_vehicles, n_scans=n_scans, seed=5, speed_mps=8.0, lidar=lidar
    ):
        fleet.scans.setdefault(vehicle, []).append(scan)
        fleet.with_prior.add(vehicle)
    route = Route.loop(town, 1, length_m=600.0)
    fleet.scans["solo"] = list(simulate(town, route, n_scans=solo_scans, speed_mps=8.0, seed=2, lidar=lidar))
    before = len(answers(service))
    for k in range(max(n_scans, solo_scans)):  # round-robin, as vehicles publishing at once
        for vehicle, scans in fleet.scans.items():
            if k < len(scans):
                payload = _payload(
                    vehicle, fleet.session, scans[k], prior=vehicle in fleet.with_prior and k == 0
                )
                service.sessions.submit(vehicle, payload)
    wait_answers(service, before + fleet.n_scans)
    service.sessions.flush()
    return fleet
