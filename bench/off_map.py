"""A drive off the map and back, through the service's session path (issue 57: no jump over 10 cm
at either switch, the new street in the map, the old ones not mapped again).

Run from the repository root::

    python bench/off_map.py --markdown

Two earlier sessions map the first 15 m and the last 55 m of a 160 m route of the simulator's town,
without what they saw of the street between (their points within 25 m of it are left out: a street
the map never saw). A vehicle then drives the whole route with ``localize`` on, its first prior 1.5 m
off: it localizes, maps the street between, and localizes again. One real
:class:`~randt.service.sessions.SessionManager` (matchers in the session thread, no pose graph, windows
of 20 m so the map's edge is where the test's map ends); every scan waits for its answer.

Printed: the answers' modes as a string (``L`` localized, ``m`` mapped), the pose error against the
simulator's truth by stretch (max, and where), the step at each switch against the true step (the
jump), and the map's points around the street between and around the mapped stretches before and
after the drive.
"""

from __future__ import annotations

import argparse
import itertools
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from common import git_line, machine_line, progress, table

from randt.core.transforms import transform_error
from randt.service.metrics import ServiceMetrics
from randt.service.sessions import SessionManager
from randt.service.settings import ServiceSettings
from randt.service.store import Store
from randt.sim.drive import SimScan, plan_fleet, simulate
from randt.sim.lidar import Lidar64
from randt.sim.town import Town
from randt.wire.messages import ErrorMessage, PoseMessage, encode, scan_from_arrays

N_SCANS = 160
EXACT = np.diag([1e-4] * 3 + [1e-6] * 3)
GNSS = np.diag([1.0] * 3 + [np.radians(5.0) ** 2] * 3)


def drive(seed: int, n_scans: int) -> list[SimScan]:
    town = Town.generate(0)
    plan = plan_fleet(town, 1, seed=0, route_length_m=400.0)[0]
    lidar = Lidar64(n_azimuth=1000, max_range_m=70.0)
    return list(
        simulate(
            town, plan.route, n_scans=n_scans, seed=seed, lidar=lidar, start_s_m=plan.start_s_m, workers=2
        )
    )


def away_from(scan: SimScan, places: np.ndarray, reach_m: float) -> SimScan:
    """The sweep without its points within ``reach_m`` (XY) of ``places`` (world frame)."""
    T = scan.T_world_sensor
    world = scan.points_xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    d = np.linalg.norm(world[:, None, :2] - places[None, :, :2], axis=2).min(axis=1)
    return replace(scan, points_xyz=scan.points_xyz[d > reach_m])


def send(
    mgr: SessionManager, out: list, vehicle: str, scans: list[SimScan], first_T: np.ndarray, cov
) -> None:
    for k, scan in enumerate(scans):
        extra = {"prior_pose": first_T, "prior_covariance": cov} if k == 0 else {}
        mgr.submit(
            vehicle, encode(scan_from_arrays(vehicle, "d1", k, scan.stamp_ns, scan.points_xyz, **extra))
        )
        deadline = time.monotonic() + 60
        while sum(isinstance(m, PoseMessage | ErrorMessage) and m.vehicle == vehicle for m in list(out)) <= k:
            if time.monotonic() > deadline:
                raise RuntimeError("the service stopped answering")
            time.sleep(0.002)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    print("Command: python bench/off_map.py" + (" --markdown" if args.markdown else ""))
    print(machine_line({}, single_threaded=False))
    print(git_line())
    progress("simulating the two drives")
    mapper, second = drive(1, N_SCANS), drive(2, N_SCANS)
    with tempfile.TemporaryDirectory(prefix="randt-off-map-") as tmp:
        settings = ServiceSettings(  # type: ignore[call-arg]
            data_dir=Path(tmp), flush_interval_s=0.3, capacity_target=0, localize=True, graph=False,
            localize_radius_m=20.0, localize_first_radius_m=20.0, localize_reload_m=10.0,
        )  # fmt: skip
        out: list = []
        mgr = SessionManager(settings, Store(Path(tmp)), out.append, ServiceMetrics())
        try:
            mgr.wait_matchers(300)
            gap = np.array([s.T_world_sensor[:3, 3] for s in mapper[40:80]])
            progress("mapping the two ends")
            for name, part in (("head", mapper[:15]), ("tail", mapper[105:])):
                send(mgr, out, name, [away_from(s, gap, 25.0) for s in part], part[0].T_world_sensor, EXACT)
                mgr.close(name, "d1")
            mgr.flush()
            grid = mgr.maps.grid("default")

            def points_near(scans: list[SimScan]) -> int:
                ids = {t for s in scans for t in grid.tiles_within_radius(s.T_world_sensor[:2, 3], 3.0)}
                return sum(grid.get(t).n_points for t in ids)

            ends, between = second[:10] + second[140:], second[55:65]
            before = points_near(ends), points_near(between)
            T0 = second[0].T_world_sensor.copy()
            T0[:2, 3] += (1.5, -1.0)
            progress("the vehicle drives off the map and back")
            send(mgr, out, "second", second, T0, GNSS)
            mgr.close("second", "d1")
            mgr.flush()
            after = points_near(ends), points_near(between)
        finally:
            mgr.stop()
    answers = {m.seq: m for m in out if isinstance(m, PoseMessage) and m.vehicle == "second"}
    modes = "".join("L" if k in answers and answers[k].mode == "localizing" else "m" for k in range(N_SCANS))
    P = [answers[k].matrix() for k in range(N_SCANS)]
    errors = np.array([transform_error(P[k], s.T_world_sensor)[0] for k, s in enumerate(second)]) * 100
    truth = [s.T_world_sensor for s in second]
    steps = [
        100 * float(np.linalg.norm((np.linalg.inv(P[k - 1]) @ P[k])[:3, 3] - (np.linalg.inv(a) @ b)[:3, 3]))
        for k, (a, b) in enumerate(itertools.pairwise(truth), start=1)
    ]
    print(f"\nanswers ({len(answers)} of {N_SCANS} poses): {modes}\n")
    switches = [k for k in range(1, N_SCANS) if modes[k] != modes[k - 1]]
    rows = []
    bounds = [0, *switches, N_SCANS]
    for a, b in itertools.pairwise(bounds):
        worst = a + int(np.argmax(errors[a:b]))
        jump = f"{steps[a - 1]:.1f}" if a > 0 else ""
        rows.append(
            [f"{a}-{b - 1}", modes[a], jump, f"{errors[a:b].max():.1f} (at {worst})", f"{errors[b - 1]:.1f}"]
        )
    headers = [
        "sweeps",
        "mode",
        "step at the switch into it, cm off the true step",
        "error max cm",
        "error at its end cm",
    ]
    print(table(headers, rows, args.markdown))
    print(
        f"\nmap points around the street between: {before[1]:,} before, {after[1]:,} after; around the "
        f"mapped stretches: {before[0]:,} before, {after[0]:,} after ({after[0] / max(before[0], 1):.3f}x)"
    )


if __name__ == "__main__":
    main()
