"""Fleet map benchmark: one map from several sessions, with and without GNSS, against ground truth.

Run from the repository root (no test dependencies)::

    python bench/fleet_map.py [--markdown] [--vehicles 3] [--laps 1.8] [--seed 0]

A simulated fleet (``randt.sim.scenarios.run_mapping_fleet``): vehicles on overlapping closed routes
of the town's street grid, each more than one lap (loops within a session, streets shared between
sessions), one of them without GNSS, the others with a GNSS receiver of 1 m noise, a 2 m wandering
bias (4 m vertically), 1 % multipath jumps of 15 m and a 15 s outage. Each vehicle's sweeps go
through its own incremental matcher; a keyframe every 10 m enters ``randt.core.fleet_map.FleetMapper``
(place recognition, global registration to verify loops, the iSAM2 pose graph). Reported:

- the shared map's ATE after one rigid alignment (its shape) and absolute (bounded by the GNSS
  bias), for the graph and for odometry only (each GNSS session placed by its first fixes, as the
  mapper places it; a session without GNSS cannot be in an odometry-only shared map);
- the sessions in the shared map;
- every loop verification: accepted, correct (within 1 m / 3 deg of the true relative pose),
  precision and recall (true places: keyframes within 10 m);
- time spent simulating, in odometry and in mapping (keyframes, place recognition, verification,
  graph), per keyframe.

The issue's criterion: the graph's ATE at least 5x lower than odometry-only, every session in the
shared map, no false loop accepted.
"""

from __future__ import annotations

import argparse
import datetime
import os
import shlex
import sys
import time

import common
import numpy as np
from common import git_line, heading, machine_line, progress, table, version, warm_up

from randt.sim.lidar import Lidar64
from randt.sim.scenarios import MappingRun, run_mapping_fleet

del common


def per_session(run: MappingRun, poses: dict, name: str) -> str:
    err = [np.linalg.norm(T[:3, 3] - run.truth[k][:3, 3]) for k, T in poses.items() if k[0] == name]
    return f"{np.sqrt(np.mean(np.square(err))):.2f}" if err else "not in map"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--markdown", action="store_true")
    parser.add_argument("--vehicles", type=int, default=3)
    parser.add_argument("--laps", type=float, default=1.8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--azimuth", type=int, default=1000, help="LiDAR columns per sweep")
    args = parser.parse_args()
    print(f"Command: python bench/fleet_map.py {shlex.join(sys.argv[1:])}")
    print(machine_line({"gtsam": version("gtsam")}))
    print(f"{git_line()}; run on {datetime.date.today().isoformat()}")
    print(f"1-min load average at start: {os.getloadavg()[0]:.2f}")
    print(f"kernel warm-up (numba compile or cache load, not timed): {warm_up():.1f} s")
    progress(f"{args.vehicles} vehicles, {args.laps} laps")
    t0 = time.perf_counter()
    run = run_mapping_fleet(
        n_vehicles=args.vehicles, laps=args.laps, seed=args.seed, lidar=Lidar64(n_azimuth=args.azimuth)
    )
    wall = time.perf_counter() - t0
    ate_g, ate_o = run.ate_graph_m, run.ate_odometry_m
    abs_g = run.ate_m(run.graph, run.truth, align=False)
    abs_o = run.ate_m(run.odometry_only, run.truth, align=False)
    print(heading("Shared map against ground truth", args.markdown))
    rows = [
        ["pose graph", f"{ate_g:.2f}", f"{abs_g:.2f}", f"{len(run.placed)} of {len(run.sessions)}",
         *(per_session(run, run.graph, n) for n in run.sessions)],
        ["odometry only", f"{ate_o:.2f}", f"{abs_o:.2f}",
         f"{len({k[0] for k in run.odometry_only})} of {len(run.sessions)}",
         *(per_session(run, run.odometry_only, n) for n in run.sessions)],
    ]  # fmt: skip
    names = [n + (" (no GNSS)" if n in run.without_gnss else "") for n in run.sessions]
    print(
        table(
            ["map", "ATE aligned m", "ATE absolute m", "sessions in map", *(f"{n} RMS m" for n in names)],
            rows,
            args.markdown,
        )
    )
    correct = sum(r.accepted and ok for r, ok in zip(run.loops, run.loop_correct, strict=True))
    by_source: dict[str, list[int]] = {}
    for r, ok in zip(run.loops, run.loop_correct, strict=True):
        c = by_source.setdefault(r.source, [0, 0, 0, 0])
        c[0] += 1
        c[1] += r.confident
        c[2] += r.accepted
        c[3] += r.accepted and not ok
    print(heading("Loop verifications", args.markdown))
    print(
        table(
            ["candidates from", "verified", "confident", "into the graph", "into the graph but wrong"],
            [[k, *(str(x) for x in v)] for k, v in sorted(by_source.items())],
            args.markdown,
        )
    )
    print(
        f"\nAll: {len(run.loops)} verified, {run.accepted} accepted ({correct} correct), precision "
        f"{run.precision:.3f}, recall {run.recall:.3f} (true places among the verified: "
        f"{sum(run.loop_truth)})"
    )
    kf = max(run.n_keyframes, 1)
    print(
        f"\nFleet: {len(run.sessions)} vehicles, {run.travel_m:.0f} m in all, {run.n_keyframes} keyframes. "
        f"Time: {wall:.0f} s wall; sweeps waited for {run.times_s['simulate']:.0f} s, odometry "
        f"{run.times_s['odometry']:.0f} s, mapping {run.times_s['mapping']:.0f} s "
        f"({run.times_s['mapping'] / kf * 1e3:.0f} ms per keyframe)"
    )
    ok = (
        ate_o >= 5 * ate_g
        and len(run.placed) == len(run.sessions)
        and run.false_accepted == 0
        and run.travel_m >= 2000
    )
    print(
        f"\nCriterion (>= 2 km, ATE >= 5x lower than odometry-only, every session in the map, no false "
        f"loop): {'met' if ok else 'NOT met'} (ratio {ate_o / ate_g:.1f}x)"
    )


if __name__ == "__main__":
    main()
