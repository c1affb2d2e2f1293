"""A drive on mapped streets, mapped against localized, through the service's session path.

Run from the repository root::

    python bench/localizing.py --scans 120 --markdown

A first vehicle maps a route of the simulator's town (its first prior exact); the service stops and
starts again on the same data directory twice, and a second vehicle drives the same route with other
noise, its first prior 1.5 m off: once with ``localize`` off (it maps, as every drive did before issue
57), once with it on (it localizes on the first drive's map). Each run is a real
:class:`~randt.service.sessions.SessionManager` with its matchers in the session thread
(``matcher_processes=0``: the figure is the matcher's own CPU, no pipe) and no pose graph; every scan
waits for its answer (none shed).

Printed per run: poses and how many localized, the matcher's CPU per sweep (``Registered.cpu_s``:
decoding, matching, the map points, model rebuilds billed to the next sweep; mean, median, max over
all sweeps but the first) and the pose error against the simulator's truth (max, p99).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from common import machine_line, progress, table

from randt.core.transforms import transform_error
from randt.service import worker as worker_module
from randt.service.metrics import ServiceMetrics
from randt.service.sessions import SessionManager
from randt.service.settings import ServiceSettings
from randt.service.store import Store
from randt.sim.drive import SimScan, plan_fleet, simulate
from randt.sim.lidar import Lidar64
from randt.sim.town import Town
from randt.wire.messages import ErrorMessage, PoseMessage, encode, scan_from_arrays

EXACT = np.diag([1e-4] * 3 + [1e-6] * 3)
GNSS = np.diag([1.0] * 3 + [np.radians(5.0) ** 2] * 3)

#: (vehicle, cpu_s, localized) of every registered sweep
SWEEPS: list[tuple[str, float, bool]] = []


def _recording() -> None:
    """Record each sweep's matcher CPU as the worker's register stage returns it."""
    register = worker_module.SessionWorker._register

    def recorded(self, job, prior, behind, voxel):  # type: ignore[no-untyped-def]
        out = register(self, job, prior, behind, voxel)
        if not isinstance(out, worker_module.Refusal):
            SWEEPS.append((self.key[0], out.cpu_s, out.result.localized))
        return out

    worker_module.SessionWorker._register = recorded  # type: ignore[method-assign]


def drive(seed: int, n_scans: int) -> list[SimScan]:
    town = Town.generate(0)
    plan = plan_fleet(town, 1, seed=0, route_length_m=800.0)[0]
    lidar = Lidar64(n_azimuth=1000, max_range_m=70.0)
    start = plan.start_s_m
    return list(
        simulate(town, plan.route, n_scans=n_scans, seed=seed, lidar=lidar, start_s_m=start, workers=2)
    )


def send(data: Path, localize: bool, vehicle: str, scans: list[SimScan], first_T: np.ndarray, cov) -> list:
    settings = ServiceSettings(
        data_dir=data,
        flush_interval_s=0.3,
        capacity_target=0,
        graph=False,
        localize=localize,
        matcher_processes=0,
    )  # type: ignore[call-arg]
    out: list = []
    store = Store(data)
    mgr = SessionManager(settings, store, out.append, ServiceMetrics())
    try:
        assert mgr.wait_matchers(300)
        for k, scan in enumerate(scans):
            n = len(out)
            extra = {"prior_pose": first_T, "prior_covariance": cov} if k == 0 else {}
            payload = scan_from_arrays(vehicle, "d1", k, scan.stamp_ns, scan.points_xyz, **extra)
            mgr.submit(vehicle, encode(payload))
            deadline = time.monotonic() + 60
            while not any(isinstance(m, PoseMessage | ErrorMessage) for m in out[n:]):
                assert time.monotonic() < deadline, "the service stopped answering"
                time.sleep(0.001)
        mgr.close(vehicle, "d1")
        mgr.flush()
    finally:
        mgr.stop()
        store.close()
    return [m for m in out if isinstance(m, PoseMessage)]


def row(name: str, poses: list, truth: list[SimScan], vehicle: str) -> list[str]:
    cpu = np.array([c for v, c, _ in SWEEPS if v == vehicle][1:]) * 1000
    localized = sum(1 for v, _, loc in SWEEPS if v == vehicle and loc)
    err = np.array([transform_error(p.matrix(), truth[p.seq].T_world_sensor)[0] for p in poses]) * 100
    return [
        name,
        f"{len(poses)} / {len(truth)}",
        str(localized),
        f"{cpu.mean():.1f} / {np.median(cpu):.1f} / {cpu.max():.1f}",
        f"{err.max():.1f} / {np.percentile(err, 99):.1f}",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", type=int, default=120, help="sweeps of each drive (10 Hz, 10 m/s)")
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    print(machine_line({}, single_threaded=False))
    _recording()
    progress("simulating the two drives")
    first, second = drive(1, args.scans), drive(2, args.scans)
    T0 = second[0].T_world_sensor.copy()
    T0[:2, 3] += (1.5, -1.0)
    rows = []
    with tempfile.TemporaryDirectory(prefix="randt-localizing-") as tmp:
        for localize in (False, True):
            data = Path(tmp) / f"localize-{localize}"
            progress(f"the first drive maps; the second {'localizes' if localize else 'maps'}")
            poses = send(data, False, "first", first, first[0].T_world_sensor, EXACT)
            if not localize:
                rows.append(row("first drive, mapping", poses, first, "first"))
            SWEEPS[:] = [s for s in SWEEPS if s[0] != "first"]
            poses = send(data, localize, "second", second, T0, GNSS)
            name = "second drive, " + ("localizing (RANDT_LOCALIZE=true)" if localize else "mapping")
            rows.append(row(name, poses, second, "second"))
            SWEEPS.clear()
    headers = [
        "drive",
        "poses",
        "localized",
        "matcher CPU ms a sweep mean / median / max",
        "error cm max / p99",
    ]
    print(table(headers, rows, args.markdown))


if __name__ == "__main__":
    main()
