"""Localization on a fixed map, on real KITTI 00 revisits: RANDT's map localizer and small_gicp
VGICP scan-to-map on the same inputs, in the same run.

Run from the repository root::

    python bench/localize.py --markdown

The map: the first-pass sweeps of ``../shared/data/kitti00_loops`` (frames below 1000) placed by
KITTI's ground truth and folded into density-equalized 20 m tiles at 0.2 m (as the service folds
them). Each second-pass sweep of a revisit whose ICP reference is good (inlier fraction at least
0.6: 10 of the 21) is localized from six priors 2 m and 10 deg off (headings 0, 45, 90, 180, 225,
270 deg; yaw +-10 deg): the far start a vehicle's GNSS fix gives. The reference is the first
pass's ground truth x ``T_icp`` (good to about 7 cm and 0.45 deg; the two or three references of
one sweep differ by up to 10.9 cm). Then, from the pose found moved 0.3 m and 1 deg (a motion
prediction), the next sweep's way: RANDT with its coarse levels skipped.

Methods, each against the map's points within 80 m of the prior:

- **RANDT localizer** (``randt.core.localizer.MapLocalizer``: 3,000 stratified sweep points, NDT
  4/2/1 m, the SVD step, yaw retries only after a weak match).
- **small_gicp VGICP**, its documented defaults (``small_gicp.align``: downsampling 0.25 m, voxels
  1 m, 20 iterations), and with 100 iterations (from these priors 20 stop it short; the best of
  voxels of 1, 2 and 3 m with 100 iterations, and of downsampling at 0.25 and 0.5 m, on half of
  these starts: 25, 16, 17 and 21 of 30 within the bound).

Printed: how many land within 10 cm and 0.5 deg of the reference, the position and rotation error
(mean, median, max) and the time per localization (mean, median, max; one thread each), and the
time RANDT takes to prepare a window (once per 20 m of travel; VGICP prepares the map at each call).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from common import heading, machine_line, progress, table, version, warm_up

from randt.core.localizer import MapLocalizer
from randt.core.shared_data import kitti00_loop_pairs, kitti00_loops_poses, kitti00_loops_velodyne
from randt.core.tiles import TileGrid
from randt.core.transforms import transform_error

FIRST_PASS_BELOW = 1000
MIN_INLIER_FRACTION = 0.6
OFFSETS = [(0, 10), (90, -10), (180, 10), (270, -10), (45, -10), (225, 10)]
WITHIN_M, WITHIN_DEG = 0.10, 0.5


def offset(T: np.ndarray, shift_m: float, heading_deg: float, yaw_deg: float) -> np.ndarray:
    a, h = np.radians(yaw_deg), np.radians(heading_deg)
    P = np.eye(4)
    P[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    P[:3, 3] = (shift_m * np.cos(h), shift_m * np.sin(h), 0.0)
    return T @ P


@dataclass
class Tally:
    errors_m: list[float]
    errors_deg: list[float]
    times_s: list[float]

    def row(self, name: str) -> list[str]:
        t, r, s = np.array(self.errors_m), np.array(self.errors_deg), np.array(self.times_s)
        within = int(np.sum((t < WITHIN_M) & (r < WITHIN_DEG)))
        return [
            name,
            f"{within} / {len(t)}",
            f"{100 * t.mean():.1f} / {100 * np.median(t):.1f} / {100 * t.max():.1f}",
            f"{r.mean():.2f} / {np.median(r):.2f} / {r.max():.2f}",
            f"{1000 * s.mean():.0f} / {1000 * np.median(s):.0f} / {1000 * s.max():.0f}",
        ]


def vgicp(max_iterations: int) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    import small_gicp

    def run(sweep: np.ndarray, map_xyz: np.ndarray, T0: np.ndarray) -> np.ndarray:
        result = small_gicp.align(
            map_xyz,
            sweep,
            init_T_target_source=T0,
            registration_type="VGICP",
            max_iterations=max_iterations,
            num_threads=1,
        )
        return np.array(result.T_target_source)

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    print(machine_line({"small_gicp": version("small_gicp")}))
    warm_up()
    poses = kitti00_loops_poses()
    grid = TileGrid(20, 0.2, 1)
    for frame in sorted(f for f in poses if f < FIRST_PASS_BELOW):
        T = poses[frame]
        grid.insert(kitti00_loops_velodyne(frame) @ T[:3, :3].T + T[:3, 3])
    revisits = [p for p in kitti00_loop_pairs() if p.icp_inlier_fraction >= MIN_INLIER_FRACTION]
    peers = {"small_gicp VGICP, defaults": vgicp(20), "small_gicp VGICP, 100 iterations": vgicp(100)}
    far, predicted = Tally([], [], []), Tally([], [], [])
    loads_s: list[float] = []
    peer_tally = {name: Tally([], [], []) for name in peers}
    loc = MapLocalizer()
    r = loc.settings.window_radius_m
    for n, loop in enumerate(revisits):
        progress(f"revisit {n + 1} of {len(revisits)}: {loop.i} -> {loop.j}")
        T_ref = poses[loop.i] @ loop.T_icp
        sweep = kitti00_loops_velodyne(loop.j)
        for heading_deg, yaw_deg in OFFSETS:
            T0 = offset(T_ref, 2.0, heading_deg, yaw_deg)
            window_xyz = grid.points_in_bbox(T0[:2, 3] - r, T0[:2, 3] + r).xyz
            window_xyz = window_xyz[np.sum((window_xyz[:, :2] - T0[:2, 3]) ** 2, axis=1) <= r * r]
            t0 = time.perf_counter()
            loc.load(T0[:2, 3], window_xyz, ("kitti", loop.j, heading_deg))
            loads_s.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            found = loc.localize(sweep, T0, predicted=False)
            far.times_s.append(time.perf_counter() - t0)
            dt, dr = transform_error(found.T_map_sensor, T_ref)
            far.errors_m.append(dt)
            far.errors_deg.append(dr)
            t0 = time.perf_counter()
            tracked = loc.localize(sweep, offset(found.T_map_sensor, 0.3, heading_deg, 1.0), predicted=True)
            predicted.times_s.append(time.perf_counter() - t0)
            dt, dr = transform_error(tracked.T_map_sensor, T_ref)
            predicted.errors_m.append(dt)
            predicted.errors_deg.append(dr)
            for name, run in peers.items():
                t0 = time.perf_counter()
                T = run(sweep.astype(np.float64), window_xyz.astype(np.float64), T0)
                peer_tally[name].times_s.append(time.perf_counter() - t0)
                dt, dr = transform_error(T, T_ref)
                peer_tally[name].errors_m.append(dt)
                peer_tally[name].errors_deg.append(dr)
    title = f"KITTI 00 revisits on the first-pass map ({len(revisits)} sweeps x 6 priors)"
    print(heading(title, args.markdown))
    rows = [
        far.row("RANDT localizer, from 2 m / 10 deg"),
        *[peer_tally[name].row(f"{name}, from 2 m / 10 deg") for name in peers],
        predicted.row("RANDT localizer, from a prediction (0.3 m / 1 deg)"),
    ]
    headers = ["method", f"within {100 * WITHIN_M:.0f} cm and {WITHIN_DEG} deg"]
    headers += ["error cm mean / median / max", "error deg mean / median / max", "ms mean / median / max"]
    print(table(headers, rows, args.markdown))
    load = np.array(loads_s)
    print(
        f"RANDT's window (the map within 80 m, prepared once per {loc.settings.reload_m:.0f} m of travel; "
        f"VGICP's time above includes preparing it at each call): {1000 * load.mean():.0f} / "
        f"{1000 * np.median(load):.0f} / {1000 * load.max():.0f} ms mean / median / max"
    )


if __name__ == "__main__":
    main()
