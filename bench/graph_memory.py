"""The pose graph process's memory against map length (issue 33: bounded memory).

Run from the repository root (no test dependencies)::

    python bench/graph_memory.py [--km 20] [--mode disk|memory|both|breakdown] [--memory-km 5] [--markdown]

One simulated vehicle drives a random walk through the town's street grid (it comes back to the
same streets again and again: loops), with a GNSS fix at each keyframe (0.5 m). Its keyframes (a
sweep every 10 m, 70 m range, 1000 firings a turn, the matcher's 0.2 m points, its true pose
with 1 cm of noise as the live pose) go to a real :class:`randt.service.graph.ServiceGraph`, its
process, queue and log, as a session's would; after every kilometre the bench waits until the
graph has taken them all and reads the graph process's resident memory (``VmRSS``) and its spill
directory's size. ``disk``: the keyframes' points on disk under the graph log's directory, the
most recent in memory (the service's default); ``memory``: no log, every keyframe's points in
RAM (how the graph worked before), over the first ``--memory-km``. ``breakdown``: the graph
process's map code run in this process on the same keyframes, and at the end what its memory is
(RSS as the pose graph, the place index, then the loop records leave).
"""

from __future__ import annotations

import argparse
import datetime
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path

import common
import numpy as np
from common import git_line, heading, machine_line, progress, table

from randt.core.fleet_map import FleetMapSettings
from randt.core.voxel import voxel_downsample
from randt.service.graph import ServiceGraph
from randt.service.metrics import ServiceMetrics
from randt.sim.drive import Route, simulate
from randt.sim.lidar import Lidar64
from randt.sim.town import Town

del common

KEYFRAME_M = 10.0
SPEED_MPS = 10.0


def rss_mb(pid: int) -> float:
    """Resident memory of process ``pid`` (MB), from /proc."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"no VmRSS for {pid}")


def dir_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 2**20 if path.exists() else 0.0


def drive(km: float, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The keyframes: (true pose, points at 0.2 m) every 10 m of a ``km`` random walk."""
    town = Town.generate(2)
    route = Route.random_walk(town, seed, length_m=km * 1000.0 + 50.0)
    n = int(km * 1000.0 / KEYFRAME_M)
    lidar = Lidar64(n_azimuth=1000, max_range_m=70.0)
    out = []
    scans = simulate(
        town, route, n_scans=n, rate_hz=SPEED_MPS / KEYFRAME_M, speed_mps=SPEED_MPS, lidar=lidar, workers=2
    )
    for k, scan in enumerate(scans):
        out.append((scan.T_world_sensor, voxel_downsample(scan.points_xyz.astype(np.float64), 0.2)))
        if k % 100 == 99:
            progress(f"simulated {k + 1} of {n} keyframe sweeps")
    return out


def run(mode: str, keyframes: list[tuple[np.ndarray, np.ndarray]], seed: int) -> list[list[str]]:
    """Offer the keyframes; a row per km: keyframes, RSS, spill size, loops, seconds."""
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory(prefix="randt-graph-memory-") as tmp:
        log_dir = Path(tmp) / "graph" if mode == "disk" else None
        graph = ServiceGraph(
            FleetMapSettings(), lambda m: None, ServiceMetrics(), yield_to_matchers=False, log_dir=log_dir
        )
        rows = []
        t0 = time.perf_counter()
        try:
            for k, (T, points) in enumerate(keyframes):
                live = T.copy()
                live[:3, 3] += rng.normal(0.0, 0.01, 3)
                fix = T[:3, 3] + rng.normal(0.0, 0.5, 3)
                graph.offer(
                    "car", "d1", map_name="default", seq=k * 10, index=k * 10, stamp_s=float(k),
                    T_live=live, points=points.astype(np.float32), gnss=(fix, np.eye(3) * 0.25),
                )  # fmt: skip
                while graph.pending > 32:  # (a session's matcher is far slower than this loop)
                    time.sleep(0.02)
                if (k + 1) % 100 == 0:
                    if not graph.wait_idle(600):
                        raise RuntimeError("the graph did not catch up within 600 s")
                    pid = graph.pid
                    assert pid is not None
                    state = graph.snapshot("default")
                    loops = 0 if state is None else sum(lp.accepted for lp in state.loops)
                    spill = dir_mb(log_dir / "spill") if log_dir is not None else 0.0
                    rows.append(
                        [f"{(k + 1) * KEYFRAME_M / 1000:.0f}", str(k + 1), f"{rss_mb(pid):.0f}",
                         f"{spill:.0f}", str(loops), f"{time.perf_counter() - t0:.0f}"]
                    )  # fmt: skip
                    progress(f"{mode}: " + " ".join(rows[-1]))
        finally:
            graph.close()
    return rows


def breakdown(keyframes: list[tuple[np.ndarray, np.ndarray]], seed: int, spill: Path) -> list[list[str]]:
    """The graph process's map, run in this process on the same keyframes (its code: re-folds every
    20 keyframes, the freed heap given back); at the end, what leaves memory with the pose graph
    (gtsam's iSAM2), then with the place index, then with the loop records and sessions."""
    import gc

    from randt.service.graph_process import MapGeometry, ProcessMap, release_memory

    rng = np.random.default_rng(seed)
    graph = ProcessMap("default", FleetMapSettings(), MapGeometry(20, 0.2, 5), spill)

    def rss() -> float:
        gc.collect()
        release_memory()
        return rss_mb(os.getpid())

    rows = []
    for k, (T, points) in enumerate(keyframes):
        live = T.copy()
        live[:3, 3] += rng.normal(0.0, 0.01, 3)
        fix = T[:3, 3] + rng.normal(0.0, 0.5, 3)
        graph.add(
            ("keyframe", "default", "car", "d1", k * 10, k * 10, live, points.astype(np.float32), None,
             (fix, np.eye(3) * 0.25), None)
        )  # fmt: skip
        if k % 20 == 19:
            graph.refold()
            release_memory()
    keyframes.clear()  # (this process held the drive)
    whole = rss()
    graph.mapper.graph = None  # type: ignore[assignment]
    without_graph = rss()
    graph.mapper.index = None  # type: ignore[assignment]
    without_index = rss()
    graph.mapper.loops, graph.mapper.sessions = [], {}
    without_loops = rss()
    rows.append(["the map's state in this process", f"{whole:.0f}"])
    rows.append(["... without the pose graph (gtsam iSAM2)", f"{without_graph:.0f}"])
    rows.append(["... and without the place index", f"{without_index:.0f}"])
    rows.append(["... and without the loop records and sessions", f"{without_loops:.0f}"])
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--km", type=float, default=20.0)
    parser.add_argument("--mode", choices=("disk", "memory", "both", "breakdown"), default="both")
    parser.add_argument("--seed", type=int, default=4)
    parser.add_argument(
        "--memory-km",
        type=float,
        default=5.0,
        help="how far the in-memory mode drives (its points stay: ~80 MB a km)",
    )
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    print(f"Command: python bench/graph_memory.py {shlex.join(sys.argv[1:])}")
    print(machine_line({}))
    print(f"{git_line()}; run on {datetime.date.today().isoformat()}")
    print(f"1-min load average at start: {os.getloadavg()[0]:.2f}")
    keyframes = drive(args.km, args.seed)
    if args.mode == "breakdown":
        with tempfile.TemporaryDirectory(prefix="randt-graph-memory-") as tmp:
            rows = breakdown(keyframes, args.seed, Path(tmp) / "spill")
        print(heading(f"What the graph's memory is after {args.km:g} km", args.markdown))
        print(table(["", "RSS MB"], rows, args.markdown))
        return
    modes = ("disk", "memory") if args.mode == "both" else (args.mode,)
    for mode in modes:
        n = len(keyframes) if mode == "disk" else int(min(args.km, args.memory_km) * 1000 / KEYFRAME_M)
        rows = run(mode, keyframes[:n], args.seed)
        print(
            heading(
                f"Graph process, keyframe points {'on disk' if mode == 'disk' else 'in memory'}",
                args.markdown,
            )
        )
        print(table(["km", "keyframes", "RSS MB", "spill MB", "loops", "s"], rows, args.markdown))
        rss = np.array([float(r[2]) for r in rows])
        if len(rss) > 1:
            per_km = (rss[-1] - rss[0]) / (len(rss) - 1)
            print(
                f"\n{mode}: RSS {rss[0]:.0f} MB at 1 km, {rss[-1]:.0f} MB at {len(rss)} km: "
                f"{per_km:.1f} MB per km after the first "
                f"({100 * (rss[-1] / rss[0] - 1):.0f} % over {len(rss) - 1} km)"
            )


if __name__ == "__main__":
    main()
