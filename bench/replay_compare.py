"""The KITTI replay's poses from two installs of the service, run after run: are they the same?

Run from the repository root, one ``randt`` command per install (e.g. a virtual environment of an
earlier commit's checkout beside this one's)::

    python bench/replay_compare.py --randt /path/to/venv-before/bin/randt --randt .venv/bin/randt --runs 3

Each run starts ``randt serve`` (its own data directory and ports on loopback), replays the KITTI 00
frames of ``../shared/data/kitti00`` into it with ``randt replay --rate 0`` (the next scan when the
last is answered, none dropped) and reads the poses it answered (``poses_tum.txt``, full
precision). The runs alternate between the installs. Printed: the largest position difference
(m) between every two runs, so that the spread between installs can be held against the spread of
one install with itself: the service's poses are not bit-exact run to run (up to a few 1e-8 m on
these frames, with one compiled-kernel thread as well; ``randt map`` of the same frames is).
"""

from __future__ import annotations

import argparse
import itertools
import os
import signal
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np
from common import REPO, free_port, machine_line, progress, table


def one_run(randt: Path, data: Path, work: Path) -> np.ndarray:
    """(N, 3) positions the service answered for the KITTI frames, in the replay's order."""
    zenoh_port, http_port = free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{zenoh_port}"
    serve = subprocess.Popen(
        [
            str(randt),
            "serve",
            "--data-dir",
            str(work / "data"),
            "--listen",
            endpoint,
            "--http-port",
            str(http_port),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{http_port}/readyz", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                time.sleep(0.5)
        else:
            raise SystemExit(f"{randt}: the service did not get ready in 120 s")
        replay = [str(randt), "replay", str(data), "--vehicle", "kitti", "--session", "s1", "--rate", "0"]
        replay += ["--connect", endpoint, "--out", str(work / "poses"), "--no-progress"]
        subprocess.run(replay, check=True, capture_output=True, timeout=600)
    finally:
        serve.send_signal(signal.SIGINT)
        serve.wait(60)
    rows = np.loadtxt(work / "poses" / "poses_tum.txt")
    return rows[:, 1:4]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--randt", type=Path, action="append", required=True, help="a randt command (twice)")
    parser.add_argument("--runs", type=int, default=3, help="runs of each install, alternating")
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "kitti00")
    args = parser.parse_args()
    print(machine_line({}, single_threaded=False))
    labels = [f"{i}:{p.parent.parent.name}" for i, p in enumerate(args.randt)]
    runs: dict[str, list[np.ndarray]] = {label: [] for label in labels}
    with tempfile.TemporaryDirectory(prefix="randt-replay-") as tmp:
        for r, (label, randt) in itertools.product(range(args.runs), zip(labels, args.randt, strict=True)):
            progress(f"run {r + 1} of {label}")
            work = Path(tmp) / f"{label.replace(':', '_')}-{r}"
            work.mkdir()
            runs[label].append(one_run(randt, args.data, work))
    names = [f"{label} #{i + 1}" for label in labels for i in range(args.runs)]
    xyz = [p for label in labels for p in runs[label]]
    rows = [[a] + [f"{np.abs(p - q).max():.1e}" for q in xyz] for a, p in zip(names, xyz, strict=True)]
    print(table(["max |dp| m", *names], rows, markdown=True))
    within = [np.abs(p - q).max() for label in labels for p, q in itertools.combinations(runs[label], 2)]
    between = [np.abs(p - q).max() for p in runs[labels[0]] for q in runs[labels[-1]]]
    print(f"within an install: at most {max(within, default=0.0):.1e} m; between: {max(between):.1e} m")


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    main()
