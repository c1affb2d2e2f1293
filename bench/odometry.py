"""Odometry benchmark: the incremental RANDT matcher (Algorithm 2) against KISS-ICP.

Run from the repository root::

    python bench/odometry.py [--quick] [--markdown] [--repeats 3] [--sim-scans N] [--sim-speed M_PER_S]

1. **KITTI 00, frames 0-10** (real): both odometries on the same 11 sweeps, scored frame to frame
   against the ground truth (approximate on these frames: see the data README) and against each
   other; travelled distance; PDU of our density-equalized map against the raw accumulated
   sweeps. Run without deskewing and with deskewing (per-point times from the azimuth, as
   KISS-ICP derives them for KITTI).
2. **Simulated drive** (``sim``): a procedural town, an HDL-64E-like sensor at 10 Hz,
   exact ground truth, at least 500 sweeps and 1 km by default; KITTI relative translation and
   rotation errors (when the drive is at least one 100 m segment long), ATE, per-sweep time, and
   the matcher's memory (model points, map points and the process's peak RSS) as the drive goes on.

Per-sweep time is the MEAN over every sweep (total time / sweeps: keyframe model updates
included, which a median would hide), with the median and the maximum beside it, and the ratio of
RANDT's mean to KISS-ICP's measured in the same run. KITTI runs ``--repeats`` interleaved runs of
both odometries and pools every sweep of every run (no best-of-N). RANDT's time is the matcher's
own (``ScanResult.time_s``, the whole of ``register_scan``); KISS-ICP's is ``register_frame``.
Both odometries run in this process, one thread each (KISS-ICP's C++ core included).
"""

from __future__ import annotations

import argparse
import datetime
import os
import resource
import shlex
import sys
import time
from dataclasses import dataclass

import common
import numpy as np
from common import git_line, heading, machine_line, progress, table, version, warm_up
from kiss_icp.config import KISSConfig
from kiss_icp.kiss_icp import KissICP

from randt.core.datasets import open_sequence
from randt.core.mapping import MapBuilder
from randt.core.metrics.cloud import pdu
from randt.core.metrics.trajectory import KITTI_LENGTHS_M, ate, kitti_relative_errors
from randt.core.shared_data import data_root
from randt.core.transforms import invert, transform_error, transform_points

del common


@dataclass
class Run:
    name: str
    poses: np.ndarray
    times_s: list[float]


def kiss_icp(scans: list[np.ndarray], taus: list[np.ndarray] | None, voxel_m: float) -> Run:
    """KISS-ICP 1.x on (N,3) sweeps; ``taus`` in [0, 1] per point turn its deskewing on."""
    odom = KissICP(_kiss_config(voxel_m, deskew=taus is not None))
    poses, times = [], []
    for i, scan in enumerate(scans):
        t = taus[i] if taus is not None else np.zeros(scan.shape[0])
        t0 = time.perf_counter()
        odom.register_frame(scan, t)
        times.append(time.perf_counter() - t0)
        poses.append(np.array(odom.last_pose))
    return Run("KISS-ICP", np.array(poses), times)


def randt(scans: list[np.ndarray], taus_s: list[np.ndarray] | None) -> tuple[Run, MapBuilder]:
    builder = MapBuilder()
    times = []
    for i, scan in enumerate(scans):
        u = builder.add_scan(scan, time_offset_s=None if taus_s is None else taus_s[i])
        times.append(u.scan.time_s)
    return Run("RANDT", np.array(builder.poses), times), builder


def time_stats(times_s: list[float]) -> tuple[float, float, float]:
    """Mean (total / sweeps), median and maximum per-sweep time, milliseconds."""
    t = np.asarray(times_s) * 1e3
    return float(t.sum() / t.size), float(np.median(t)), float(t.max())


def time_cells(times_s: list[float]) -> list[str]:
    return [f"{v:.1f}" for v in time_stats(times_s)]


def ratio_line(section: str, ours: list[float], kiss: list[float]) -> str:
    return (
        f"{section}: RANDT mean / KISS-ICP mean per sweep = {time_stats(ours)[0]:.1f} / "
        f"{time_stats(kiss)[0]:.1f} ms = {time_stats(ours)[0] / time_stats(kiss)[0]:.2f}x"
    )


def f2f(poses: np.ndarray) -> np.ndarray:
    return np.array([invert(poses[i]) @ poses[i + 1] for i in range(len(poses) - 1)])


def f2f_error(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    e = np.array([transform_error(x, y) for x, y in zip(f2f(a), f2f(b), strict=True)])
    return float(e[:, 0].mean()), float(e[:, 1].mean())


def kitti_section(markdown: bool, repeats: int = 3) -> list[str]:
    seq = open_sequence(data_root() / "kitti00")
    gt = seq.reference_poses()
    assert gt is not None  # KITTI 00 ships its poses
    scans = [c.xyz for c in seq]
    azimuth_t = [0.5 * (-np.arctan2(s[:, 1], s[:, 0]) / np.pi + 1.0) for s in scans]
    out = [heading("KITTI 00 frames 0-10 (real; ground truth approximate)", markdown)]
    rows, ratios = [], []
    for deskew in (False, True):
        progress(f"KITTI 00, deskew={deskew}")
        # Interleaved repeats, every sweep of every run pooled (a load swing then hits both
        # odometries alike; a best-of-N would hide the load). Poses are deterministic and must
        # agree across repeats.
        ours_runs, kiss_runs = [], []
        for _ in range(repeats):
            ours, builder = randt(scans, [t * 0.1 for t in azimuth_t] if deskew else None)
            kiss = kiss_icp(scans, azimuth_t if deskew else None, voxel_m=1.0)
            ours_runs.append(ours)
            kiss_runs.append(kiss)
        for runs in (ours_runs, kiss_runs):
            for run in runs[1:]:
                np.testing.assert_allclose(run.poses, runs[0].poses, atol=1e-9)
        ours.times_s = [t for r in ours_runs for t in r.times_s]
        kiss.times_s = [t for r in kiss_runs for t in r.times_s]
        ratios.append(ratio_line(f"deskew={'yes' if deskew else 'no'}", ours.times_s, kiss.times_s))
        for run in (ours, kiss):
            t_gt, r_gt = f2f_error(run.poses, gt)
            other = kiss if run is ours else ours
            t_o, r_o = f2f_error(run.poses, other.poses)
            rows.append(
                [
                    run.name,
                    "yes" if deskew else "no",
                    f"{t_gt:.4f}",
                    f"{r_gt:.4f}",
                    f"{t_o:.4f}",
                    f"{r_o:.4f}",
                    f"{np.linalg.norm(run.poses[-1][:3, 3]):.3f}",
                    *time_cells(run.times_s),
                ]
            )
        if not deskew:
            raw = np.vstack([transform_points(T, s) for T, s in zip(ours.poses, scans, strict=True)])
            map_xyz = builder.tiles.to_cloud().xyz.astype(np.float64)
            pdu_map, pdu_raw = pdu(map_xyz, 0.5), pdu(raw, 0.5)
    out.append(
        table(
            [
                "odometry",
                "deskew",
                "f2f t err vs GT m",
                "f2f r err vs GT deg",
                "f2f t vs other m",
                "f2f r vs other deg",
                "travel m (GT 8.599)",
                "mean ms/sweep",
                "median ms",
                "max ms",
            ],
            rows,
            markdown,
        )
    )
    out.append("\nPer-sweep time, " + repeats_note(repeats) + "\n" + "\n".join(ratios))
    out.append(
        f"\nPDU at 0.5 m voxels: RANDT map {pdu_map:.3f}, raw accumulated sweeps (same poses) {pdu_raw:.3f}; "
        f"map {map_xyz.shape[0]} points in {len(builder.tiles)} tiles, raw {raw.shape[0]} points."
    )
    return out


def repeats_note(repeats: int) -> str:
    return f"all 11 sweeps of {repeats} interleaved run(s) of each odometry pooled:"


def sim_section(
    n_scans: int, speed_mps: float, markdown: bool, modes: tuple[bool, ...] = (False, True)
) -> list[str]:
    """Simulated drive: RANDT (perfect and raw sweeps) and KISS-ICP, scored on exact ground truth."""
    from randt.sim.drive import Motion, Route, simulate
    from randt.sim.town import Town

    town = Town.generate(1)
    route = Route.loop(town, 3, length_m=1000.0)
    out = [
        heading(
            f"Simulated drive: {n_scans} sweeps at {speed_mps:g} m/s, 10 Hz, "
            f"{n_scans * speed_mps / 10:.0f} m on a {route.length_m:.0f} m loop (town seed 1, route seed 3)",
            markdown,
        )
    ]
    rows, memory, ratios = [], [], []
    for raw in modes:
        progress(f"simulated drive, raw sweeps={raw}")
        builder = MapBuilder()
        kiss = None if raw else KissICP(_kiss_config(1.0, deskew=False))
        ours_t, kiss_t, gt, kiss_poses = [], [], [], []
        motion = Motion(route, speed_mps=speed_mps)
        for scan in simulate(town, route, n_scans=n_scans, speed_mps=speed_mps, seed=1, deskewed=not raw):
            xyz = scan.points_xyz.astype(np.float64)
            u = builder.add_scan(xyz, time_offset_s=scan.time_offset_s if raw else None)
            ours_t.append(u.scan.time_s)
            # With per-point times the matcher's poses refer to mid-sweep (core/odometry.py).
            t_ref = scan.index * 0.1 + (0.05 if raw else 0.0)
            gt.append(motion.sensor_poses_at(t_ref)[0])
            if kiss is not None:
                t0 = time.perf_counter()
                kiss.register_frame(xyz, np.zeros(xyz.shape[0]))
                kiss_t.append(time.perf_counter() - t0)
                kiss_poses.append(np.array(kiss.last_pose))
            if scan.index % 100 == 99:
                memory.append(
                    [
                        "raw + deskew" if raw else "perfect",
                        str(scan.index + 1),
                        str(builder.matcher.model_size),
                        str(builder.tiles.n_points),
                        f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f}",
                    ]
                )
        G = np.array([invert(gt[0]) @ g for g in gt])
        runs = [("RANDT", np.array(builder.poses), ours_t)]
        if kiss is not None:
            runs.append(("KISS-ICP", np.array(kiss_poses), kiss_t))
        if kiss is not None:
            ratios.append(ratio_line("perfect sweeps" if not raw else "raw sweeps", ours_t, kiss_t))
        path_m = float(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1).sum())
        for name, P, times in runs:
            if path_m > min(KITTI_LENGTHS_M):
                k = kitti_relative_errors(G, P)
                rel = [f"{k.translation_pct:.3f}", f"{k.rotation_deg_per_100m:.4f}"]
            else:
                rel = ["n/a", "n/a"]
            rows.append(
                [
                    name,
                    "raw, deskewed by the matcher" if raw else "perfect (no distortion)",
                    *rel,
                    f"{ate(G, P).translation_m.rmse:.3f}",
                    *time_cells(times),
                ]
            )
    out.append(
        table(
            [
                "odometry",
                "sweeps",
                "KITTI t err %",
                "KITTI r err deg/100m",
                "ATE m",
                "mean ms/sweep",
                "median ms",
                "max ms",
            ],
            rows,
            markdown,
        )
    )
    if any(r[2] == "n/a" for r in rows):
        out.append(
            f"\nKITTI relative errors n/a: the drive is shorter than the shortest KITTI segment "
            f"({min(KITTI_LENGTHS_M):.0f} m); ATE covers it."
        )
    out.append("\nPer-sweep time, every sweep of one run:\n" + "\n".join(ratios))
    out.append("\nMemory as the drive goes on (model and map points; process peak RSS):\n")
    out.append(
        table(["sweeps", "after scan", "model points", "map points", "peak RSS MiB"], memory, markdown)
    )
    return out


def _kiss_config(voxel_m: float, *, deskew: bool) -> KISSConfig:
    cfg = KISSConfig()
    cfg.data.max_range = 100.0
    cfg.data.min_range = 2.0
    cfg.data.deskew = deskew
    cfg.mapping.voxel_size = voxel_m
    # One thread, as ours: KISS-ICP's default (0) runs its TBB registration on every core.
    cfg.registration.max_num_threads = 1
    return cfg


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="one KITTI run; a short (120 m) drive, perfect sweeps"
    )
    parser.add_argument("--markdown", action="store_true")
    parser.add_argument("--sim-scans", type=int, default=850)
    parser.add_argument("--sim-speed", type=float, default=12.0, help="m/s (850 x 1.2 m = 1.02 km)")
    parser.add_argument("--no-sim", action="store_true")
    parser.add_argument(
        "--repeats", type=int, default=3, help="KITTI runs of each odometry (every sweep of every run pooled)"
    )
    parser.add_argument("--no-raw", action="store_true", help="skip the raw (distorted, deskewed) drive")
    args = parser.parse_args()
    print(f"Command: python bench/odometry.py {shlex.join(sys.argv[1:])}")
    print(machine_line({"kiss-icp": version("kiss-icp")}))
    print(f"{git_line()}; run on {datetime.date.today().isoformat()}; data: {data_root()}")
    print(f"1-min load average at start: {os.getloadavg()[0]:.2f}")
    print(f"kernel warm-up (numba compile or cache load, not timed): {warm_up():.1f} s")
    for line in kitti_section(args.markdown, 1 if args.quick else args.repeats):
        print(line)
    if not args.no_sim:
        # Quick: 100 sweeps at 12 m/s, 120 m, one KITTI segment (100 m) long.
        n = 100 if args.quick else args.sim_scans
        modes = (False,) if args.no_raw or args.quick else (False, True)
        for line in sim_section(n, args.sim_speed, args.markdown, modes):
            print(line)
    print(
        f"\npeak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB; "
        f"1-min load average at end: {os.getloadavg()[0]:.2f}"
    )


if __name__ == "__main__":
    main()
