"""Session workers: threads against processes for the matcher's numeric work.

Run from the repository root::

    python bench/workers.py [--sessions 1 2 4] [--repeats 2] [--markdown]

Each session is one :class:`randt.core.odometry.IncrementalMatcher` fed the 11 real KITTI 00 sweeps
(``--repeats`` times over, as one long session) from memory. The same sessions run three ways in
one process tree: one after another in one thread (the baseline), one thread per session (what
``randt.service.sessions`` does), and one process per session (``concurrent.futures`` with the fork
start method, so the sweeps are not pickled). Reported: wall time, sweeps per second and the
speed-up over the sequential run. BLAS is single-threaded, so the only parallelism is the
workers'. The question it answers: does the GIL serialize the matcher? (Our kernels release it,
``core/kernels.py``; numpy and scipy's KD-tree release it inside their loops.)
"""

from __future__ import annotations

import argparse
import datetime
import multiprocessing
import os
import shlex
import sys
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

import numpy as np
from common import git_line, heading, machine_line, table, warm_up

from randt.core.io import read_cloud
from randt.core.shared_data import data_root

_SCANS: list[np.ndarray] = []


def _load(repeats: int) -> list[np.ndarray]:
    root = data_root() / "kitti00" / "velodyne"
    scans = [read_cloud(root / f"{k:06d}.bin").xyz.astype(np.float64) for k in range(11)]
    out = []
    for r in range(repeats):
        out.extend(scans if r % 2 == 0 else scans[::-1])  # drive back: one continuous session
    return out


def _session(_: int) -> int:
    from randt.core.odometry import IncrementalMatcher

    matcher = IncrementalMatcher()
    ok = 0
    for xyz in _SCANS:
        ok += matcher.register_scan(xyz).status != "fallback"
    return ok


def _run(mode: str, n: int) -> tuple[float, int]:
    t0 = time.perf_counter()
    if mode == "sequential":
        ok = sum(_session(i) for i in range(n))
    elif mode == "threads":
        with ThreadPoolExecutor(max_workers=n) as pool:
            ok = sum(pool.map(_session, range(n)))
    else:
        with ProcessPoolExecutor(max_workers=n, mp_context=multiprocessing.get_context("fork")) as pool:
            ok = sum(pool.map(_session, range(n)))
    return time.perf_counter() - t0, ok


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--repeats", type=int, default=2, help="passes over the 11 sweeps per session")
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    print(f"command: python bench/workers.py {shlex.join(sys.argv[1:])}")
    print(machine_line({}))
    print(f"{git_line()}; run on {datetime.date.today().isoformat()}; data: {data_root()}")
    print(f"1-min load average at start: {os.getloadavg()[0]:.2f}")
    print(f"kernel warm-up (not timed): {warm_up():.1f} s")
    _SCANS.extend(_load(args.repeats))
    rows = []
    for n in args.sessions:
        base = None
        for mode in ("sequential", "threads", "processes"):
            wall, ok = _run(mode, n)
            sweeps = n * len(_SCANS)
            base = base or wall
            rows.append(
                [
                    str(n),
                    mode,
                    f"{wall:.1f}",
                    f"{sweeps / wall:.2f}",
                    f"{base / wall:.2f}",
                    f"{ok}/{sweeps}",
                ]
            )
            print(f"  .. {n} sessions, {mode}: {wall:.1f} s", file=sys.stderr, flush=True)
    print(heading(f"{len(_SCANS)} KITTI 00 sweeps per session", args.markdown))
    headers = ["sessions", "workers", "wall s", "sweeps/s", "speed-up vs sequential", "matched"]
    print(table(headers, rows, args.markdown))
    print(f"\n1-min load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
