"""Registration benchmark: accuracy and single-threaded time of RANDT against baselines and peers.

Run from the repository root::

    python bench/register.py [--quick] [--markdown]

Three experiments, one process, one thread (the thread limits are set before numpy is imported):

1. **Real pairs.** The shared pairs of ``core/shared_data.py`` (reference transforms from their data
   sets) and consecutive KITTI 00 frames (reference: KITTI ground truth, approximate on these
   frames, so the disagreement with small_gicp VGICP is reported as well). Every method starts
   from the identity; the timed region goes from raw (N,3) float64 arrays to the transform, so
   downsampling, normals / covariances and search structures are included. Median over repeats.
2. **Cycle consistency** on KITTI 00 frames 0-10, which needs no reference: for frames
   ``(i, i+g, i+2g)``, ``g`` = 1 and 2, the pose ``i <- i+2g`` registered directly against the
   product of ``i <- i+g`` and ``i+g <- i+2g``. It measures each method's precision on real
   sweeps (a bias shared by all three poses does not show).
3. **Robustness protocol** (:func:`randt.core.trials.make_trial`): seeded trials on the RANDT
   paper's Velodyne scans (random rigid transform up to 2 m / 10 deg, 50 % overlap, noise,
   10 % outliers); RANDT, RANDT --fast-svd, its two ablations, classic NDT and small_gicp VGICP.

Our methods run with their defaults (NDT voxel levels derived from the target's scale). The peers
(small_gicp, Open3D) need scale parameters; :data:`SCALES` lists them and the output repeats them.
A method that raises :class:`~randt.core.errors.RegistrationFailedError` has no pose: it counts as a
failure, and in the protocol statistics its error is that of the identity start.
"""

from __future__ import annotations

import argparse
import datetime
import os
import shlex
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import small_gicp
from common import git_line, heading, machine_line, progress, table, version, warm_up

from randt.core.config import FAST_SVD_STEP, Method, RegistrationSettings
from randt.core.errors import DegenerateProblemError, RegistrationFailedError
from randt.core.io import kitti_velodyne_poses, read_cloud, read_kitti_calib, read_kitti_poses
from randt.core.registration import auto_voxel_sizes, register
from randt.core.shared_data import PAIRS, data_root, kitti00_velodyne
from randt.core.transforms import transform_error
from randt.core.trials import make_trial

KITTI_FRAMES = (0, 4, 9)  # pairs k -> k+1
PROTOCOL_SEED = 20261122
SUCCESS_T_M = 0.05
SUCCESS_R_DEG = 0.5


@dataclass(frozen=True)
class Scale:
    """Peer parameters for one data scale (small_gicp ``align`` and Open3D point-to-plane ICP)."""

    name: str
    downsampling_m: float
    max_correspondence_m: float
    vgicp_voxel_m: float


SCALES = {
    "outdoor": Scale("outdoor LiDAR", 0.25, 1.0, 1.0),
    "indoor": Scale("indoor / short range", 0.1, 0.5, 0.5),
    "object": Scale("object scan", 0.002, 0.01, 0.01),
}

#: pair -> scale. The libpointmatcher car pair is outdoor but sparse (25k points, median range
#: about 6 m from the centre, like the indoor pair), so it gets the short-range parameters.
PAIR_SCALE = {"small_gicp": "indoor", "argoverse2": "outdoor", "bunny": "object", "car": "indoor"}


@dataclass(frozen=True)
class Outcome:
    T: np.ndarray | None  # None: the method raised and gave no pose
    note: str


Runner = Callable[[np.ndarray, np.ndarray, Scale], Outcome]


def ours(method: Method, **overrides: object) -> Runner:
    settings = RegistrationSettings.for_method(method, **overrides)

    def run(source: np.ndarray, target: np.ndarray, scale: Scale) -> Outcome:
        try:
            result = register(source, target, settings=settings)
        except DegenerateProblemError as exc:
            return Outcome(exc.result.T_target_source, "degenerate")
        except RegistrationFailedError:
            return Outcome(None, "failed")
        return Outcome(result.T_target_source, "" if result.converged else "not converged")

    return run


def small_gicp_runner(kind: str) -> Runner:
    def run(source: np.ndarray, target: np.ndarray, scale: Scale) -> Outcome:
        result = small_gicp.align(
            target,
            source,
            init_T_target_source=np.eye(4),
            registration_type=kind,
            voxel_resolution=scale.vgicp_voxel_m,
            downsampling_resolution=scale.downsampling_m,
            max_correspondence_distance=scale.max_correspondence_m,
            num_threads=1,
        )
        return Outcome(np.array(result.T_target_source), "" if result.converged else "not converged")

    return run


def open3d_point_to_plane(source: np.ndarray, target: np.ndarray, scale: Scale) -> Outcome:
    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source)).voxel_down_sample(scale.downsampling_m)
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target)).voxel_down_sample(scale.downsampling_m)
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=scale.max_correspondence_m, max_nn=30))
    result = reg.registration_icp(
        src,
        tgt,
        scale.max_correspondence_m,
        np.eye(4),
        reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(max_iteration=30),
    )
    return Outcome(np.array(result.transformation), "")


PAIR_METHODS: dict[str, Runner] = {
    "RANDT": ours("randt"),
    "RANDT --fast-svd": ours("randt", **FAST_SVD_STEP),
    "NDT (classic)": ours("ndt"),
    "ICP point (ours)": ours("icp-point"),
    "ICP plane (ours)": ours("icp-plane"),
    "small_gicp GICP": small_gicp_runner("GICP"),
    "small_gicp VGICP": small_gicp_runner("VGICP"),
    "Open3D ICP plane": open3d_point_to_plane,
}
VGICP = "small_gicp VGICP"
PAIR_HEADERS = ["pair", "method", "t err m", "r err deg", "time s", "x VGICP time"]
PROTOCOL_HEADERS = ["method", "success", "t mean m", "t p95 m", "r mean deg", "r p95 deg", "time s", "failed"]

PROTOCOL_METHODS: dict[str, Runner] = {
    "RANDT": ours("randt"),
    "RANDT --fast-svd": ours("randt", **FAST_SVD_STEP),
    "RANDT w/o outlier removal": ours("randt", outlier_removal="none", select_moving_points=False),
    "RANDT w/o SVD step": ours("randt", svd_refinement=False),
    "NDT (classic)": ours("ndt"),
    VGICP: small_gicp_runner("VGICP"),
}


def timed(runner: Runner, source: np.ndarray, target: np.ndarray, scale: Scale) -> tuple[Outcome, float]:
    t0 = time.perf_counter()
    outcome = runner(source, target, scale)
    return outcome, time.perf_counter() - t0


# ---------------------------------------------------------------------------------------------
# data


def missing(*relative: str) -> str | None:
    root = data_root()
    for rel in relative:
        if not (root / rel).exists():
            return f"{root / rel} does not exist"
    return None


def load_pairs() -> tuple[dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, str]], list[str]]:
    """name -> (source, target, T_reference, scale key); plus the reasons for skipped pairs."""
    needs = {
        "small_gicp": "pairs/small_gicp/source.ply",
        "argoverse2": "pairs/argoverse2/T_a_b.txt",
        "bunny": "objects/bunny/bun.conf",
        "car": "pairs/libpointmatcher_car/carCloudList.csv",
    }
    pairs, skipped = {}, []
    for name, loader in PAIRS.items():
        reason = missing(needs.get(name, name))
        if reason:
            skipped.append(f"{name}: {reason}")
            continue
        source, target, T_ref = loader()
        pairs[name] = (as_f64(source), as_f64(target), T_ref, PAIR_SCALE.get(name, "outdoor"))
    return pairs, skipped


def load_kitti() -> tuple[dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, str]], list[str]]:
    """KITTI 00 frames k -> k+1, reference ``inv(P_{k+1}) @ P_k`` in the Velodyne frame."""
    files = [f"kitti00/velodyne/{k:06d}.bin" for f in KITTI_FRAMES for k in (f, f + 1)]
    reason = missing("kitti00/poses.txt", "kitti00/calib.txt", *files)
    if reason:
        return {}, [f"kitti00: {reason}"]
    root = data_root() / "kitti00"
    Tr = read_kitti_calib(root / "calib.txt")["Tr"]
    poses = kitti_velodyne_poses(read_kitti_poses(root / "poses.txt"), Tr)
    pairs = {}
    for k in KITTI_FRAMES:
        T_ref = np.linalg.inv(poses[k + 1]) @ poses[k]
        pairs[f"kitti00 {k}->{k + 1}"] = (
            as_f64(kitti00_velodyne(k)),
            as_f64(kitti00_velodyne(k + 1)),
            T_ref,
            "outdoor",
        )
    return pairs, []


def as_f64(points: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(points[:, :3], dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# experiments


@dataclass(frozen=True)
class PairRun:
    pair: str
    method: str
    T: np.ndarray | None
    t_err_m: float
    r_err_deg: float
    time_s: float
    note: str


def run_pairs(
    pairs: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, str]], repeats: int
) -> list[PairRun]:
    runs = []
    for name, (source, target, T_ref, scale_key) in pairs.items():
        scale = SCALES[scale_key]
        for method, runner in PAIR_METHODS.items():
            times, outcome = [], None
            for _ in range(repeats):
                outcome, dt = timed(runner, source, target, scale)
                times.append(dt)
            assert outcome is not None
            t_err, r_err = transform_error(outcome.T, T_ref) if outcome.T is not None else (np.nan, np.nan)
            runs.append(
                PairRun(name, method, outcome.T, t_err, r_err, statistics.median(times), outcome.note)
            )
            progress(f"{name:16s} {method:18s} {t_err:.4g} m {r_err:.4g} deg {runs[-1].time_s:.3f} s")
    return runs


@dataclass(frozen=True)
class ProtocolStats:
    method: str
    n: int
    success: int
    failed: int
    t_mean: float
    t_p95: float
    r_mean: float
    r_p95: float
    time_mean: float


CYCLE_GAPS = (1, 2)
CYCLE_HEADERS = [
    "method", "cycles", "t mean cm", "t median cm", "t max cm", "r mean deg", "r max deg", "failed",
]  # fmt: skip


def run_cycles() -> tuple[list[list[str]], str | None]:
    """Cycle consistency on KITTI 00 frames 0-10 (module docstring, experiment 2): a row per
    method, or the reason it could not run."""
    files = [f"kitti00/velodyne/{k:06d}.bin" for k in range(11)]
    reason = missing(*files)
    if reason:
        return [], f"cycles: {reason}"
    frames = [as_f64(kitti00_velodyne(k)) for k in range(11)]
    cycles = [(i, i + g, i + 2 * g) for g in CYCLE_GAPS for i in range(11 - 2 * g)]
    needed = sorted({pair for a, b, c in cycles for pair in ((a, b), (b, c), (a, c))})
    rows = []
    for method, runner in PAIR_METHODS.items():
        progress(f"cycles: {method}")
        # p_a = poses[(a, b)] p_b, each pair registered once
        poses = {(a, b): runner(frames[b], frames[a], SCALES["outdoor"]).T for a, b in needed}
        errors, failed = [], 0
        for a, b, c in cycles:
            direct, first, second = poses[(a, c)], poses[(a, b)], poses[(b, c)]
            if direct is None or first is None or second is None:
                failed += 1
                continue
            errors.append(transform_error(direct, first @ second))
        e = np.array(errors).reshape(-1, 2)
        t_cm = 100 * e[:, 0]
        rows.append(
            [
                method,
                str(len(cycles)),
                *(f"{v:.2f}" for v in (t_cm.mean(), np.median(t_cm), t_cm.max())),
                f"{e[:, 1].mean():.4f}",
                f"{e[:, 1].max():.4f}",
                str(failed),
            ]
        )
    return rows, None


def run_protocol(n_trials: int) -> tuple[list[ProtocolStats], list[str], str]:
    rel = "randt_velodyne/velodyne"
    reason = missing(rel)
    scans = sorted((data_root() / rel).glob("*.bin")) if not reason else []
    if not scans:
        return [], [f"protocol: {reason or 'no .bin scans in ' + rel}"], ""
    clouds = [as_f64(read_cloud(p).xyz) for p in scans]
    scale = SCALES["outdoor"]
    errors: dict[str, list[tuple[float, float, float, bool]]] = {m: [] for m in PROTOCOL_METHODS}
    for i in range(n_trials):
        trial = make_trial(clouds[i % len(clouds)], np.random.default_rng(PROTOCOL_SEED + i))
        for method, runner in PROTOCOL_METHODS.items():
            outcome, dt = timed(runner, trial.source_xyz, trial.target_xyz, scale)
            T = outcome.T if outcome.T is not None else np.eye(4)
            t_err, r_err = transform_error(T, trial.T_true)
            errors[method].append((t_err, r_err, dt, outcome.T is None))
        progress(f"protocol trial {i + 1}/{n_trials} ({scans[i % len(scans)].name})")
    stats = []
    for method, rows in errors.items():
        a = np.array([r[:3] for r in rows])
        ok = (a[:, 0] <= SUCCESS_T_M) & (a[:, 1] <= SUCCESS_R_DEG)
        stats.append(
            ProtocolStats(
                method=method,
                n=len(rows),
                success=int(ok.sum()),
                failed=sum(r[3] for r in rows),
                t_mean=float(a[:, 0].mean()),
                t_p95=float(np.percentile(a[:, 0], 95)),
                r_mean=float(a[:, 1].mean()),
                r_p95=float(np.percentile(a[:, 1], 95)),
                time_mean=float(a[:, 2].mean()),
            )
        )
    source_note = f"{len(scans)} scans of {data_root() / rel}, trial i uses scan i mod {len(scans)}"
    return stats, [], source_note


# ---------------------------------------------------------------------------------------------
# output


def fmt_err(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{x:.3g}"


def pair_rows(runs: list[PairRun], with_vgicp: bool) -> list[list[str]]:
    vgicp = {r.pair: r for r in runs if r.method == VGICP}
    rows = []
    for r in runs:
        ref = vgicp.get(r.pair)
        ratio = r.time_s / ref.time_s if ref else np.nan
        row = [r.pair, r.method, fmt_err(r.t_err_m), fmt_err(r.r_err_deg), f"{r.time_s:.3f}", f"{ratio:.2f}"]
        if with_vgicp:
            if r.method == VGICP:
                row += ["(ref.)", "(ref.)"]
            elif ref is not None and ref.T is not None and r.T is not None:
                row += [fmt_err(x) for x in transform_error(r.T, ref.T)]
            else:
                row += ["n/a", "n/a"]
        row.append(r.note)
        rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 repeat per pair, 6 protocol trials")
    parser.add_argument("--markdown", action="store_true", help="print markdown tables")
    args = parser.parse_args()
    md = args.markdown
    repeats, n_trials = (1, 6) if args.quick else (3, 20)

    command = "python " + shlex.join(sys.argv)
    print(f"command: {command}")
    print(machine_line({"small_gicp": version("small_gicp"), "open3d": o3d.__version__}))
    print(f"{git_line()}; run on {datetime.date.today().isoformat()}; data: {data_root()}")
    print(f"1-min load average at start: {os.getloadavg()[0]:.2f} (other processes share the cores)")
    print(f"kernel warm-up (numba compile or cache load, not timed): {warm_up():.1f} s")

    pairs, skipped = load_pairs()
    kitti, skipped_kitti = load_kitti()
    skipped += skipped_kitti

    print(heading("Peer parameters (ours: defaults, NDT levels derived from the target)", md))
    param_rows = []
    for name, (_, target, _, key) in {**pairs, **kitti}.items():
        s = SCALES[key]
        levels = ", ".join(f"{v:g}" for v in auto_voxel_sizes(target))
        numbers = [f"{v:g}" for v in (s.downsampling_m, s.max_correspondence_m, s.vgicp_voxel_m)]
        param_rows.append([name, s.name, *numbers, levels])
    print(
        table(
            ["pair", "scale", "downsampling m", "max corr. m", "VGICP voxel m", "our NDT levels m"],
            param_rows,
            md,
        )
    )
    print(
        "Open3D: voxel_down_sample(downsampling), target normals from a hybrid search "
        "(radius = max corr., 30 nn), registration_icp point-to-plane, 30 iterations. "
        "All methods start from the identity; time includes all preprocessing; "
        f"median of {repeats} run(s)."
    )

    headers = [*PAIR_HEADERS, "note"]
    if pairs:
        print(heading("Shared pairs (reference transforms from the data sets)", md))
        print(table(headers, pair_rows(run_pairs(pairs, repeats), with_vgicp=False), md))
    if kitti:
        print(heading("KITTI 00 consecutive frames (reference: KITTI ground truth, approximate)", md))
        kitti_headers = [*PAIR_HEADERS, "t vs VGICP m", "r vs VGICP deg", "note"]
        kitti_runs = run_pairs(kitti, repeats)
        print(table(kitti_headers, pair_rows(kitti_runs, with_vgicp=True), md))
        vg = {r.pair: r.time_s for r in kitti_runs if r.method == VGICP}
        summary = []
        for method in PAIR_METHODS:
            ratios = [r.time_s / vg[r.pair] for r in kitti_runs if r.method == method]
            summary.append(f"{method} {statistics.median(ratios):.2f}x")
        print("\nmedian time ratio to small_gicp VGICP over the KITTI pairs: " + "; ".join(summary))

    cycle_rows, skipped_cycles = run_cycles()
    if cycle_rows:
        print(heading("KITTI 00 cycle consistency (no reference needed)", md))
        print(
            "Frames (i, i+g, i+2g) of KITTI 00 frames 0-10, g = 1 and 2: the pose i <- i+2g "
            "registered directly against the product of i <- i+g and i+g <- i+2g (each pair "
            "registered once, from the identity). A failed pair drops its cycles."
        )
        print(table(CYCLE_HEADERS, cycle_rows, md))
    if skipped_cycles:
        skipped.append(skipped_cycles)

    stats, skipped_protocol, source_note = run_protocol(n_trials)
    skipped += skipped_protocol
    if stats:
        print(heading(f"Robustness protocol: {n_trials} seeded trials (seed {PROTOCOL_SEED} + i)", md))
        print(
            f"{source_note}; up to 2 m / 10 deg, 50 % overlap, noise 1-5 cm, 10 % outliers; success = "
            f"t <= {SUCCESS_T_M * 100:g} cm and r <= {SUCCESS_R_DEG:g} deg; "
            "VGICP with the outdoor parameters; time is the mean per trial. "
            "A failed run (no pose) keeps the identity's error."
        )
        rows = [
            [
                s.method,
                f"{s.success}/{s.n} ({100 * s.success / s.n:.0f} %)",
                fmt_err(s.t_mean),
                fmt_err(s.t_p95),
                fmt_err(s.r_mean),
                fmt_err(s.r_p95),
                f"{s.time_mean:.3f}",
                str(s.failed),
            ]
            for s in stats
        ]
        print(table(PROTOCOL_HEADERS, rows, md))
    for reason in skipped:
        print(f"skipped (data missing): {reason}")
    print(f"\n1-min load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
