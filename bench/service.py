"""Service benchmark: simulated vehicles at 10 Hz with KITTI-sized sweeps against a real service.

Run from the repository root::

    python bench/service.py [--vehicles 1 2 4 8] [--seconds 6] [--markdown]

For each vehicle count, a fresh subprocess starts a :class:`service.runtime.Service` (Zenoh peer
on loopback, data in a temporary directory), pre-simulates every vehicle's sweeps (HDL-64E-like,
about 120k points each), then publishes them at 10 Hz per vehicle from one Zenoh session per
vehicle, for ``--seconds``. It reports sustained scans per second (poses received per second of
wall time), publish-to-pose latency p50/p99 (publish time to the pose's arrival at a subscriber),
scans dropped by the overload policy, other errors, and the subprocess's peak RSS.

The target of issue 4 is 8 vehicles at 10 Hz with p99 under 200 ms and no drops on this 2-core
machine. Every figure comes from this run: see docs/benchmarks.md for the reading.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import resource
import shlex
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import common
import numpy as np
from common import free_port, git_line, heading, machine_line, progress, table

del common


def run_one(n_vehicles: int, seconds: float) -> dict[str, float | str]:
    """One configuration, in this process (called in a fresh subprocess by :func:`main`)."""
    import zenoh

    from service.runtime import Service
    from service.settings import ServiceSettings
    from sim.drive import simulate_fleet
    from sim.town import Town
    from wire.codes import ErrorCode
    from wire.keys import ALL_ERRORS, ALL_POSES, scan_key
    from wire.messages import decode_error, decode_pose, encode, scan_from_arrays
    from wire.zenoh_config import zenoh_config

    n_scans = int(seconds * 10)
    town = Town.generate(1)
    scans: dict[str, list[bytes]] = {}
    truth: dict[tuple[str, int], np.ndarray] = {}
    for vehicle, scan in simulate_fleet(town, n_vehicles, n_scans=n_scans, seed=3, speed_mps=10.0):
        prior: dict[str, Any] = {}  # prior_pose and prior_covariance on the first scan
        truth[(vehicle, scan.index)] = scan.T_world_sensor
        if scan.index == 0:
            prior = dict(prior_pose=scan.T_world_sensor, prior_covariance=np.diag([1e-4] * 3 + [1e-5] * 3))
        scans.setdefault(vehicle, []).append(
            encode(
                scan_from_arrays(
                    vehicle,
                    "bench",
                    scan.index,
                    scan.stamp_ns,
                    scan.points_xyz,
                    intensity=scan.intensity,
                    **prior,
                )
            )
        )
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory() as data:
        service = Service(ServiceSettings(data_dir=Path(data), listen=(endpoint,), http_port=0))
        service.start()
        assert service.sessions is not None and service.sessions.wait_matchers(600), "matchers not warm"
        sent: dict[tuple[str, int], float] = {}
        got: dict[tuple[str, int], float] = {}
        errors: dict[str, int] = {}
        statuses: dict[str, int] = {}
        status_of: dict[tuple[str, int], str] = {}
        pose_of: dict[tuple[str, int], np.ndarray] = {}  # poses in the shared map's frame
        own_frame = [0]  # poses of sessions that could not be placed (their anchor was lost)
        lock = threading.Lock()

        def on_pose(sample: zenoh.Sample) -> None:
            t = time.monotonic()
            m = decode_pose(sample.payload.to_bytes())
            with lock:
                got[(m.vehicle, m.seq)] = t
                statuses[m.status] = statuses.get(m.status, 0) + 1
                status_of[(m.vehicle, m.seq)] = m.status
                if m.map == "default":
                    pose_of[(m.vehicle, m.seq)] = np.reshape(m.pose, (4, 4))
                else:
                    own_frame[0] += 1

        last_answer = [0.0]

        def on_error(sample: zenoh.Sample) -> None:
            m = decode_error(sample.payload.to_bytes())
            with lock:
                errors[m.code] = errors.get(m.code, 0) + 1
                last_answer[0] = time.monotonic()

        listener = zenoh.open(zenoh_config("peer", connect=(endpoint,)))
        subs = [
            listener.declare_subscriber(ALL_POSES, on_pose),
            listener.declare_subscriber(ALL_ERRORS, on_error),
        ]
        time.sleep(1.0)

        def drive(vehicle: str) -> None:
            session = zenoh.open(zenoh_config("peer", connect=(endpoint,)))
            # As the vehicle library publishes (clients/publisher.py): block under congestion
            # rather than drop, so every scan reaches the service.
            pub = session.declare_publisher(
                scan_key(vehicle),
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
            start = time.monotonic()
            for k, payload in enumerate(scans[vehicle]):
                delay = start + 0.1 * k - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                with lock:
                    sent[(vehicle, k)] = time.monotonic()
                pub.put(payload)
            time.sleep(1.0)  # puts are asynchronous: let the last ones leave before closing
            session.close()

        matcher_pids = [p for p in service.sessions.pool.pids() if p] if service.sessions.pool else []
        cpu0 = _cpu_seconds([os.getpid()]), _cpu_seconds(matcher_pids)
        t0 = time.monotonic()
        threads = [threading.Thread(target=drive, args=(v,)) for v in scans]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            with lock:
                answered = len(got) + sum(errors.values())
            if answered >= len(sent):
                break
            time.sleep(0.1)
        with lock:
            end = max([*got.values(), last_answer[0], t0])
        wall = end - t0  # first publication to last answer
        cpu_main = _cpu_seconds([os.getpid()]) - cpu0[0]
        cpu_matchers = _cpu_seconds(matcher_pids) - cpu0[1]
        received = int(service.metrics.registry.get_sample_value("randt_scans_received_total") or 0)
        for s in subs:
            s.undeclare()
        listener.close()
        service.stop()
    lat = np.array([got[k] - sent[k] for k in got if k in sent])
    # Each vehicle's first sweep carries its true pose as a prior, so poses in the shared map are
    # in the simulator's world frame: their position error against the ground truth, in cm.
    err_cm = np.array([100 * np.linalg.norm(pose_of[k][:3, 3] - truth[k][:3, 3]) for k in pose_of])
    if os.environ.get("RANDT_BENCH_SLOWEST"):
        slow = sorted(((got[k] - sent[k]) * 1e3, k) for k in got if k in sent)[-12:]
        print("slowest (ms, scan):", [(round(ms), k) for ms, k in slow], file=sys.stderr)
        for v in sorted(scans):
            seqs = sorted(k[1] for k in status_of if k[0] == v)
            marks = [f"{q}{'F' if status_of[(v, q)] == 'fallback' else ''}" for q in seqs]
            print(f"{v} answered with poses (F: fallback):", " ".join(marks), file=sys.stderr)
    return {
        "vehicles": n_vehicles,
        "sent": len(sent),
        "poses": len(got),
        "fallbacks": statuses.get("fallback", 0),
        "own_frame": own_frame[0],
        "dropped": errors.get(ErrorCode.DROPPED, 0),
        "other_errors": sum(v for k, v in errors.items() if k != ErrorCode.DROPPED),
        "other_codes": ", ".join(f"{k} {v}" for k, v in sorted(errors.items()) if k != ErrorCode.DROPPED),
        "received": received,
        "unanswered": len(sent) - len(got) - sum(errors.values()),
        "scans_per_s": len(got) / wall,
        "err_p50_cm": float(np.percentile(err_cm, 50)) if err_cm.size else float("nan"),
        "err_max_cm": float(err_cm.max()) if err_cm.size else float("nan"),
        "p50_ms": float(np.percentile(lat, 50) * 1e3) if lat.size else float("nan"),
        "p99_ms": float(np.percentile(lat, 99) * 1e3) if lat.size else float("nan"),
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        # CPU per answered scan: the service process (which also runs the bench's publishers and
        # subscriber) and the matcher processes, from /proc over the publishing and answering.
        "cpu_main_ms": 1e3 * cpu_main / max(len(got) + sum(errors.values()), 1),
        "cpu_matchers_ms": 1e3 * cpu_matchers / max(len(got), 1),
    }


def _cpu_seconds(pids: list[int]) -> float:
    """User + system CPU seconds of these processes (all their threads), from /proc."""
    total = 0.0
    tick = os.sysconf("SC_CLK_TCK")
    for pid in pids:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        total += (int(fields[11]) + int(fields[12])) / tick  # utime, stime (fields 14, 15)
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--seconds", type=float, default=6.0)
    parser.add_argument("--markdown", action="store_true")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(args.one, args.seconds)))
        return
    print(f"Command: python bench/service.py {shlex.join(sys.argv[1:])}")
    print(machine_line({}, single_threaded=False))
    print(f"{git_line()}; run on {datetime.date.today().isoformat()}")
    print(f"1-min load average at start: {os.getloadavg()[0]:.2f}")
    rows = []
    for n in args.vehicles:
        progress(f"{n} vehicle(s)")
        out = (
            subprocess.run(
                [sys.executable, __file__, "--one", str(n), "--seconds", str(args.seconds)],
                capture_output=True,
                text=True,
                check=True,
            )
            .stdout.strip()
            .splitlines()[-1]
        )
        r = json.loads(out)
        rows.append(
            [
                str(r["vehicles"]),
                str(r["sent"]),
                str(r["poses"]),
                str(r["fallbacks"]),
                str(r["own_frame"]),
                str(r["dropped"]),
                str(r["other_errors"]) + (f" ({r['other_codes']})" if r["other_codes"] else ""),
                str(r["received"]),
                str(r["unanswered"]),
                f"{r['scans_per_s']:.2f}",
                f"{r['p50_ms']:.0f}",
                f"{r['p99_ms']:.0f}",
                f"{r['err_p50_cm']:.1f} / {r['err_max_cm']:.1f}",
                f"{r['peak_rss_mib']:.0f}",
                f"{r['cpu_main_ms']:.0f} / {r['cpu_matchers_ms']:.0f}",
            ]
        )
    print(heading(f"{args.seconds:g} s of 10 Hz sweeps per vehicle (about 120k points each)", args.markdown))
    print(
        table(
            [
                "vehicles",
                "scans sent",
                "poses",
                "of which fallbacks",
                "in own frame",
                "dropped",
                "other errors",
                "received by service",
                "unanswered",
                "poses/s",
                "p50 ms",
                "p99 ms",
                "position error p50 / max cm",
                "peak RSS MiB",
                "CPU ms per scan: service / matchers",
            ],
            rows,
            args.markdown,
        )
    )
    print(f"\n1-min load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
