"""Plumbing shared by the benchmarks: one-thread set-up, machine and git lines, plain/markdown tables.

Import this module first in a benchmark script: it limits BLAS/OpenMP to one thread before numpy is
imported, so every figure is single-threaded.
"""

from __future__ import annotations

import os

#: The environment variables that limit BLAS/OpenMP libraries to one thread.
THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "BLIS_NUM_THREADS",
)
for _var in THREAD_VARS:
    os.environ[_var] = "1"

import json  # noqa: E402
import platform  # noqa: E402
import socket  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from importlib import metadata  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
# The benchmarks run as scripts from bench/: make the repository's packages importable.
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def free_port() -> int:
    """A TCP port on the loopback interface that is free right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def progress(message: str) -> None:
    print(f"  .. {message}", file=sys.stderr, flush=True)


def table(headers: list[str], rows: list[list[str]], markdown: bool) -> str:
    if markdown:
        lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines)
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(headers)]
    out = ["  ".join(h.ljust(w) for h, w in zip(headers, widths, strict=True))]
    out.append("  ".join("-" * w for w in widths))
    out += ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
    return "\n".join(out)


def version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "?"


def machine_line(peers: dict[str, str], *, single_threaded: bool = True) -> str:
    """One line naming CPU, cores, OS, Python, numpy, scipy and the given peer versions."""
    model = platform.processor() or platform.machine()
    try:
        lscpu = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
        model = next(
            (ln.split(":", 1)[1].strip() for ln in lscpu.splitlines() if ln.startswith("Model name")), model
        )
    except OSError:
        pass
    libs = ", ".join(
        [f"python {platform.python_version()}", f"numpy {np.__version__}", f"scipy {version('scipy')}"]
        + [f"{k} {v}" for k, v in peers.items()]
    )
    threads = (
        "single-threaded (OMP/OPENBLAS/MKL_NUM_THREADS=1)" if single_threaded else "BLAS single-threaded"
    )
    system = f"{platform.system()} {platform.release()}"
    return f"machine: {model}, {os.cpu_count()} logical cores ({system}); {libs}; {threads}"


def git_line() -> str:
    repo = REPO
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True, check=True
        ).stdout.strip()
        status = subprocess.run(
            ["git", "status", "--porcelain", "--", "core"],
            cwd=repo,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return "git: unknown"
    dirty = sorted(line[3:] for line in status.splitlines() if line.strip())
    return f"git: {sha}" + (f" + uncommitted changes to {', '.join(dirty)}" if dirty else " (core clean)")


def run_json(command: list[str], what: str) -> dict[str, Any]:
    """Run a benchmark's inner run in a fresh subprocess and return the JSON its last line prints;
    its stderr and ``what`` failed on a non-zero exit."""
    out = subprocess.run(command, capture_output=True, text=True)
    if out.returncode != 0:
        sys.stderr.write(out.stderr)
        raise SystemExit(f"{what} failed (exit {out.returncode})")
    result: dict[str, Any] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def heading(text: str, markdown: bool) -> str:
    return f"\n### {text}\n" if markdown else f"\n== {text} =="


def warm_up() -> float:
    """Compile our numba kernels (core/kernels.py) before anything is timed; returns seconds taken.

    The peers ship compiled code, so their first call costs nothing extra; ours compiles on first
    use (or loads numba's on-disk cache, which is per source path: a fresh clone or worktree
    compiles). One registration of a small synthetic room, and an incremental matcher over a few
    sweeps of it (features, the keyframe model, the gates), run every kernel once: with the
    registration alone, the first KITTI sweep of a fresh worktree took 3 s.
    """
    import time

    from randt.core.odometry import IncrementalMatcher
    from randt.core.registration import register
    from randt.core.scenes import synthetic_room
    from randt.core.transforms import make_transform, transform_points

    t0 = time.perf_counter()
    room = synthetic_room(np.random.default_rng(0))
    register(room + [0.2, 0.1, 0.0], room)
    matcher = IncrementalMatcher()
    for k in range(4):
        matcher.register_scan(transform_points(make_transform(translation=[-0.7 * k, 0.0, -1.7]), room))
    return time.perf_counter() - t0
