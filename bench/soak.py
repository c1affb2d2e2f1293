"""Soak: simulated vehicles stream to a service over loopback Zenoh for minutes; memory, latency and
drops sampled over time, written as a CSV and a plot.

Run from the repository root::

    python -m bench.soak --minutes 10 [--vehicles 3] [--rate-hz 2] [--sample-s 5]
        [--csv docs/img/soak.csv] [--plot docs/img/soak.png]

The service is ``randt serve`` in a child process (its own RSS, Zenoh peer on a free 127.0.0.1
port, data in a temporary directory, ``RANDT_MAX_SESSIONS=0`` and ``RANDT_IDLE_EXPIRY_S=10`` so
finished laps free their sessions). Each vehicle drives the simulator's town (``randt.sim.drive``, an
HDL-64E-like LiDAR with 500 columns, about 30k points a sweep) at ``--rate-hz``, one lap of
``--lap-scans`` sweeps per session with its true pose as the prior of the lap's first sweep (shared
map ``default``), then starts a new session and drives the lap again, until ``--minutes`` are up.
The default load (3 vehicles at 2 Hz, 6 sweeps a second) leaves the 2-core machine headroom, so the
soak shows drift over time (memory, latency) rather than saturation; overload is the flood fault's
subject (``bench/faults.py``).
Every ``--sample-s`` seconds a row: elapsed time, RSS of the service process and of its matcher
processes (MiB, from /proc), and of the scans answered in that window: poses, drops, other errors,
latency p50/p99/max (publish to the pose's arrival), and scans sent but not yet answered.
"""

from __future__ import annotations

import argparse
import csv
import logging
import os
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import Listener, free_port, http_raw

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
COLUMNS = [
    "t_s",
    "service_rss_mib",
    "matchers_rss_mib",
    "poses",
    "dropped",
    "errors",
    "p50_ms",
    "p99_ms",
    "max_ms",
    "in_flight",
]


@dataclass
class SoakResult:
    rows: list[dict[str, float]] = field(default_factory=list)
    sent: int = 0
    poses: int = 0
    dropped: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    unanswered: int = 0
    minutes: float = 0.0
    vehicles: int = 0
    rate_hz: float = 0.0


def _rss_mib(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def _children(pid: int) -> list[int]:
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as fh:
            return [int(x) for x in fh.read().split()]
    except OSError:
        return []


def _descendants(pid: int) -> list[int]:
    out, todo = [], _children(pid)
    while todo:
        p = todo.pop()
        out.append(p)
        todo += _children(p)
    return out


def _laps(
    n_vehicles: int, lap_scans: int, rate_hz: float
) -> dict[str, list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]]:
    """Per vehicle: (stamp offset ns, xyz float32, intensity float32, T_world_sensor) of one lap."""
    from randt.sim.drive import simulate_fleet
    from randt.sim.lidar import Lidar64
    from randt.sim.town import Town

    town = Town.generate(1)
    out: dict[str, list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]] = {}
    for vehicle, scan in simulate_fleet(
        town,
        n_vehicles,
        n_scans=lap_scans,
        seed=11,
        rate_hz=rate_hz,
        speed_mps=8.0,
        lidar=Lidar64(n_azimuth=500),
    ):
        out.setdefault(vehicle, []).append(
            (
                int(scan.stamp_ns),
                np.asarray(scan.points_xyz, np.float32),
                np.asarray(scan.intensity, np.float32),
                np.asarray(scan.T_world_sensor),
            )
        )
    return out


def run_soak(
    minutes: float,
    *,
    vehicles: int = 3,
    rate_hz: float = 2.0,
    sample_s: float = 5.0,
    lap_scans: int = 50,
    csv_path: Path | None = None,
    plot_path: Path | None = None,
    progress: bool = False,
) -> SoakResult:
    """Run the soak (module docstring) and write the CSV and the plot if paths are given."""
    import zenoh

    from randt.wire.keys import scan_key
    from randt.wire.messages import encode, scan_from_arrays
    from randt.wire.zenoh_config import zenoh_config

    laps = _laps(vehicles, lap_scans, rate_hz)
    lap_ns = int(lap_scans / rate_hz * 1e9)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    http_port = free_port()
    result = SoakResult(minutes=minutes, vehicles=vehicles, rate_hz=rate_hz)
    with tempfile.TemporaryDirectory(prefix="randt-soak-") as tmp:
        env = {
            **os.environ,
            "PYTHONPATH": str(REPO),
            "RANDT_MAX_SESSIONS": "0",
            "RANDT_IDLE_EXPIRY_S": "10",
        }
        server = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "cli",
                "serve",
                "--data-dir",
                tmp,
                "--listen",
                endpoint,
                "--http-port",
                str(http_port),
            ],
            env=env,
            cwd=REPO,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        stderr_lines: list[str] = []
        threading.Thread(
            target=lambda: stderr_lines.extend(server.stderr or []), name="soak-stderr", daemon=True
        ).start()
        try:
            deadline = time.monotonic() + 600
            while True:
                try:
                    status, _ = http_raw(http_port, "GET", "/readyz", timeout=5)
                except OSError:
                    status = 0
                if status == 200:
                    break
                if server.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"the service did not become ready: {''.join(stderr_lines[-5:])}")
                time.sleep(0.5)
            listener = Listener((endpoint,))
            sent: dict[tuple[str, str, int], float] = {}
            lock = threading.Lock()
            stop = threading.Event()

            def drive(vehicle: str) -> None:
                session = zenoh.open(zenoh_config("peer", connect=(endpoint,)))
                pub = session.declare_publisher(
                    scan_key(vehicle),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    reliability=zenoh.Reliability.RELIABLE,
                )
                start = time.monotonic()
                k = 0
                try:
                    while not stop.is_set():
                        lap, i = divmod(k, lap_scans)
                        stamp, xyz, inten, T = laps[vehicle][i]
                        prior: dict[str, Any] = (
                            {"prior_pose": T, "prior_covariance": np.diag([1e-4] * 3 + [1e-5] * 3)}
                            if i == 0
                            else {}
                        )
                        sess = f"lap{lap}"
                        payload = encode(
                            scan_from_arrays(
                                vehicle,
                                sess,
                                i,
                                1_700_000_000_000_000_000 + lap * lap_ns + stamp,
                                xyz,
                                inten,
                                **prior,
                            )
                        )
                        delay = start + k / rate_hz - time.monotonic()
                        if delay > 0 and stop.wait(delay):
                            break
                        with lock:
                            sent[(vehicle, sess, i)] = time.monotonic()
                        pub.put(payload)
                        k += 1
                finally:
                    time.sleep(0.5)
                    session.close()

            threads = [threading.Thread(target=drive, args=(v,), daemon=True) for v in laps]
            t0 = time.monotonic()
            for t in threads:
                t.start()
            end = t0 + minutes * 60
            seen = 0
            while time.monotonic() < end:
                time.sleep(min(sample_s, max(end - time.monotonic(), 0.0)))
                answers = listener.snapshot()
                window, seen = answers[seen:], len(answers)
                with lock:
                    lat = [
                        (a.t - sent[(a.vehicle, a.session, a.seq)]) * 1e3
                        for a in window
                        if a.kind == "pose" and a.seq is not None and (a.vehicle, a.session, a.seq) in sent
                    ]
                    answered = {(a.vehicle, a.session, a.seq) for a in answers}
                    in_flight = sum(1 for key in sent if key not in answered)
                row = {
                    "t_s": time.monotonic() - t0,
                    "service_rss_mib": _rss_mib(server.pid),
                    "matchers_rss_mib": sum(_rss_mib(p) for p in _descendants(server.pid)),
                    "poses": sum(a.kind == "pose" for a in window),
                    "dropped": sum(a.kind == "error" and a.code == "dropped" for a in window),
                    "errors": sum(a.kind == "error" and a.code != "dropped" for a in window),
                    "p50_ms": float(np.percentile(lat, 50)) if lat else float("nan"),
                    "p99_ms": float(np.percentile(lat, 99)) if lat else float("nan"),
                    "max_ms": float(max(lat)) if lat else float("nan"),
                    "in_flight": in_flight,
                }
                result.rows.append(row)
                if progress:
                    print(
                        "  " + "  ".join(f"{k} {v:.0f}" for k, v in row.items()), file=sys.stderr, flush=True
                    )
            stop.set()
            for t in threads:
                t.join(30)
            with lock:
                n_sent = len(sent)
            listener.wait(
                lambda: len({(a.vehicle, a.session, a.seq) for a in listener.snapshot()}) >= n_sent, 60.0
            )
            answers = listener.snapshot()
            listener.close()
            answered = {(a.vehicle, a.session, a.seq) for a in answers}
            result.sent = n_sent
            result.poses = sum(a.kind == "pose" for a in answers)
            result.dropped = sum(a.kind == "error" and a.code == "dropped" for a in answers)
            for a in answers:
                if a.kind == "error" and a.code != "dropped":
                    result.errors[str(a.code)] = result.errors.get(str(a.code), 0) + 1
            result.unanswered = sum(1 for key in sent if key not in answered)
        finally:
            server.terminate()
            try:
                server.wait(60)
            except subprocess.TimeoutExpired:
                server.kill()
                server.wait(10)
    if csv_path is not None:
        write_csv(result, csv_path)
    if plot_path is not None:
        plot(result, plot_path)
    return result


def write_csv(result: SoakResult, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        for row in result.rows:
            w.writerow({k: f"{row[k]:.3f}" if isinstance(row[k], float) else row[k] for k in COLUMNS})


def plot(result: SoakResult, path: Path) -> None:
    """Three panels over time: RSS, latency, answers per window (matplotlib, Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([r["t_s"] for r in result.rows]) / 60
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    axes[0].plot(t, [r["service_rss_mib"] for r in result.rows], label="service")
    axes[0].plot(t, [r["matchers_rss_mib"] for r in result.rows], label="matcher processes")
    axes[0].set_ylabel("RSS (MiB)")
    axes[0].legend(loc="upper left")
    for key in ("p50_ms", "p99_ms", "max_ms"):
        axes[1].plot(t, [r[key] for r in result.rows], label=key.replace("_ms", ""))
    axes[1].set_ylabel("publish to pose (ms)")
    axes[1].set_yscale("log")
    axes[1].legend(loc="upper left")
    for key in ("poses", "dropped", "errors"):
        axes[2].plot(t, [r[key] for r in result.rows], label=key)
    axes[2].set_ylabel("per window")
    axes[2].set_xlabel("minutes")
    axes[2].legend(loc="upper left")
    fig.suptitle(f"soak: {result.vehicles} vehicles at {result.rate_hz:g} Hz, {result.minutes:g} min")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(prog="soak.py", description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--vehicles", type=int, default=3)
    parser.add_argument("--rate-hz", type=float, default=2.0)
    parser.add_argument("--sample-s", type=float, default=5.0)
    parser.add_argument("--lap-scans", type=int, default=50)
    parser.add_argument("--csv", type=Path, default=REPO / "docs" / "img" / "soak.csv")
    parser.add_argument("--plot", type=Path, default=REPO / "docs" / "img" / "soak.png")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    r = run_soak(
        args.minutes,
        vehicles=args.vehicles,
        rate_hz=args.rate_hz,
        sample_s=args.sample_s,
        lap_scans=args.lap_scans,
        csv_path=args.csv,
        plot_path=args.plot,
        progress=True,
    )
    print(
        f"sent {r.sent}, poses {r.poses}, dropped {r.dropped}, errors {r.errors}, unanswered {r.unanswered}"
    )


if __name__ == "__main__":
    main()
