"""Matcher benchmark: the service's session matcher on sweeps as the vehicle library sends them.

Run from the repository root::

    python bench/matcher.py [--markdown] [--sim-scans 300] [--repeats 3]

What a matcher process does per sweep in the service, timed in this process on one thread: the
payload decoded (``randt.service.matchers.decoded_sweep``: the v2 bodies decompressed), then
``IncrementalMatcher.register_scan`` and its keyframe model update, with the settings every
session gets (``ServiceSettings.session_matcher``, ``ServiceSettings.registration``). KISS-ICP
(one thread) registers the same decoded sweeps in the same run, beside it.

1. **KITTI 00 frames 0-10** (real), each reduced and encoded by ``randt.clients.publisher.encode_sweep``
   with the library's defaults (first point per 0.2 m voxel, 1 cm, zstd; no per-point times:
   KITTI's files have none). ``--repeats`` interleaved runs of both, every sweep pooled.
   Frame-to-frame error against the ground truth (approximate on these frames, data README).
2. **A simulated drive** (``--sim-scans`` sweeps at 10 m/s, 10 Hz): the first vehicle of
   ``bench/service.py``'s fleet (town seed 1, fleet seed 3), raw sweeps in their firing-time frames
   with per-point times, encoded as the vehicle library sends them: the same sweeps the service
   benchmark spools. Both odometries deskew with the times. Frame-to-frame error and ATE against
   the exact truth at mid-sweep.

Per-sweep time is the MEAN over every sweep (total / sweeps: keyframe model updates included),
the median and maximum beside it, and the ratio of RANDT's mean to KISS-ICP's from the same run.
Issue 31's target: at most 15 ms a reduced sweep, by the mean, on both.
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
from kiss_icp.config import KISSConfig
from kiss_icp.kiss_icp import KissICP
from offline import Run, service_matcher

from randt.clients.publisher import encode_sweep
from randt.core.datasets import open_sequence
from randt.core.metrics.trajectory import ate
from randt.core.shared_data import data_root
from randt.core.transforms import invert, transform_error
from randt.service.matchers import decoded_sweep

del common

RATE_HZ = 10.0


def randt(payloads: list[bytes]) -> Run:
    """The service's session matcher: decode, register, model update (one thread)."""
    return service_matcher(payloads)


def kiss_icp(payloads: list[bytes]) -> Run:
    """KISS-ICP 1.x (one thread) on the same decoded sweeps; deskewed when they carry times."""
    sweeps = [decoded_sweep(p, None) for p in payloads]
    deskew = sweeps[0][1] is not None
    cfg = KISSConfig()
    cfg.data.max_range = 100.0
    cfg.data.min_range = 2.0
    cfg.data.deskew = deskew
    cfg.mapping.voxel_size = 1.0
    cfg.registration.max_num_threads = 1
    odom = KissICP(cfg)
    run = Run("KISS-ICP")
    for xyz, offsets, _, _, _ in sweeps:
        pts = xyz.astype(np.float64)
        taus = np.zeros(len(pts)) if offsets is None else offsets.astype(np.float64) * RATE_HZ
        t0 = time.perf_counter()
        odom.register_frame(pts, taus)
        run.times_s.append(time.perf_counter() - t0)
        run.poses.append(np.array(odom.last_pose))
        run.points.append(len(pts))
    return run


def stats_ms(times_s: list[float]) -> tuple[float, float, float]:
    t = np.asarray(times_s) * 1e3
    return float(t.sum() / t.size), float(np.median(t)), float(t.max())


def f2f_error(poses: list[np.ndarray], truth: np.ndarray) -> tuple[float, float, float]:
    """Frame-to-frame error against ``truth``: mean translation (m), its p95, mean rotation (deg)."""
    P = np.asarray(poses)
    e = np.array(
        [transform_error(invert(P[i]) @ P[i + 1], invert(truth[i]) @ truth[i + 1]) for i in range(len(P) - 1)]
    )
    return float(e[:, 0].mean()), float(np.quantile(e[:, 0], 0.95)), float(e[:, 1].mean())


def section(
    title: str, payloads: list[bytes], truth: np.ndarray, repeats: int, markdown: bool, with_ate: bool
) -> list[str]:
    ours_runs, kiss_runs = [], []
    for _ in range(repeats):  # interleaved: a load swing hits both alike
        ours_runs.append(randt(payloads))
        kiss_runs.append(kiss_icp(payloads))
    rows = []
    for runs in (ours_runs, kiss_runs):
        run = runs[0]
        pooled = [t for r in runs for t in r.times_s]
        mean, median, worst = stats_ms(pooled)
        t_mean, t_p95, r_mean = f2f_error(run.poses, truth)
        G = np.array([invert(truth[0]) @ g for g in truth])
        P = np.array([invert(run.poses[0]) @ p for p in run.poses])
        rows.append(
            [
                run.name,
                f"{np.mean(run.points):.0f}",
                f"{t_mean * 100:.2f}",
                f"{t_p95 * 100:.2f}",
                f"{r_mean:.4f}",
                f"{ate(G, P).translation_m.rmse:.3f}" if with_ate else "n/a",
                f"{mean:.1f}",
                f"{median:.1f}",
                f"{worst:.1f}",
            ]
        )
    ours = [t for r in ours_runs for t in r.times_s]
    kiss = [t for r in kiss_runs for t in r.times_s]
    decode = stats_ms([t for r in ours_runs for t in r.decode_s])[0]
    model = stats_ms([t for r in ours_runs for t in r.model_s])[0]
    out = [heading(title, markdown)]
    out.append(
        table(
            [
                "odometry",
                "points / sweep",
                "f2f t err cm",
                "f2f t p95 cm",
                "f2f r err deg",
                "ATE m",
                "mean ms/sweep",
                "median ms",
                "max ms",
            ],
            rows,
            markdown,
        )
    )
    out.append(
        f"\nRANDT mean / KISS-ICP mean per sweep = {stats_ms(ours)[0]:.1f} / {stats_ms(kiss)[0]:.1f} ms = "
        f"{stats_ms(ours)[0] / stats_ms(kiss)[0]:.2f}x; of RANDT's mean, decoding {decode:.1f} ms and "
        f"keyframe model updates {model:.1f} ms ({repeats} run(s) of each, every sweep pooled; "
        "issue 31's target: at most 15 ms)"
    )
    return out


def kitti_payloads() -> tuple[list[bytes], np.ndarray]:
    seq = open_sequence(data_root() / "kitti00")
    truth = seq.reference_poses()
    assert truth is not None  # KITTI 00 ships its poses
    payloads = [
        encode_sweep("kitti", "00", i, int(i * 1e8), cloud.xyz.astype(np.float32))
        for i, cloud in enumerate(seq)
    ]
    return payloads, np.asarray(truth)


def sim_payloads(n_scans: int) -> tuple[list[bytes], np.ndarray]:
    """``bench/service.py``'s first vehicle: the raw sweeps encoded as the vehicle library sends them."""
    from randt.sim.drive import Motion, plan_fleet, simulate
    from randt.sim.lidar import Lidar64
    from randt.sim.town import Town

    town = Town.generate(1)
    lidar = Lidar64()
    v = plan_fleet(town, 1, seed=3)[0]
    motion = Motion(v.route, speed_mps=10.0, start_s_m=v.start_s_m, mount_height_m=lidar.mount_height_m)
    payloads, truth = [], []
    prior_cov = np.diag([1e-4] * 3 + [1e-5] * 3)
    for scan in simulate(
        town, v.route, n_scans=n_scans, rate_hz=RATE_HZ, speed_mps=10.0, seed=v.seed, lidar=lidar,
        deskewed=False, start_s_m=v.start_s_m, start_stamp_ns=v.stamp_offset_ns, workers=2,
    ):  # fmt: skip
        T_mid = motion.sensor_poses_at(scan.index / RATE_HZ + 0.5 / RATE_HZ)[0]
        prior = dict(prior_pose=T_mid, prior_covariance=prior_cov) if scan.index == 0 else {}
        payloads.append(
            encode_sweep(
                v.vehicle_id, "d1", scan.index, scan.stamp_ns, scan.points_xyz,
                intensity=scan.intensity, time_offset_s=scan.time_offset_s, **prior,
            )
        )  # fmt: skip
        truth.append(T_mid)
    return payloads, np.array(truth)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--markdown", action="store_true")
    parser.add_argument("--sim-scans", type=int, default=300, help="simulated sweeps (10 m/s, 10 Hz)")
    parser.add_argument("--repeats", type=int, default=3, help="KITTI runs of each odometry (pooled)")
    parser.add_argument("--no-kitti", action="store_true")
    args = parser.parse_args()
    print(f"Command: python bench/matcher.py {shlex.join(sys.argv[1:])}")
    print(machine_line({"kiss-icp": version("kiss-icp")}))
    print(f"{git_line()}; run on {datetime.date.today().isoformat()}; data: {data_root()}")
    print(f"1-min load average at start: {os.getloadavg()[0]:.2f}")
    print(f"kernel warm-up (numba compile or cache load, not timed): {warm_up():.1f} s")
    if not args.no_kitti:
        progress("KITTI 00 frames 0-10, reduced as the vehicle library sends them")
        payloads, truth = kitti_payloads()
        title = "KITTI 00 frames 0-10, reduced by the vehicle library (real; ground truth approximate)"
        for line in section(title, payloads, truth, args.repeats, args.markdown, with_ate=False):
            print(line)
    progress(f"simulating and encoding {args.sim_scans} sweeps")
    payloads, truth = sim_payloads(args.sim_scans)
    title = (
        f"Simulated drive, {args.sim_scans} sweeps at 10 m/s with per-point times, "
        "reduced by the vehicle library"
    )
    for line in section(title, payloads, truth, 1, args.markdown, with_ate=True):
        print(line)
    print(f"\n1-min load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
