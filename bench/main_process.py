"""Main-process benchmark (issue 31): the sweeps per second the service process itself carries when
the matching is done elsewhere, and its CPU per sweep.

Run from the repository root::

    python bench/main_process.py --sweeps /tmp/spool --rates 100 200 300 400 600 --markdown

The service's matchers are replaced by a stand-in executor (``Service(executor=...)``) that answers
each sweep at once with what a matcher process answered for it: before the runs, each vehicle's
spooled sweeps (bench/service.py's spool, simulated there when ``--sweeps`` holds none) go through
the matcher processes' own code here (``randt.service.matchers._Sessions.register_payload`` with a
:class:`~randt.service.matchers.MapFrame`: decoded, matched, moved into the map frame, cut to the voxels
not sent before; a keyframe's points where the pose graph's rule asks for one). Everything else is
the real service in its own process: Zenoh intake and admission, the session threads, the pose
log's group commit, folding into the map, tile saves and snapshots, the pose graph (``--graph on``),
publishing. Its answers are the matcher's poses, so the poses are still checked against the truth.

Per offered rate (sweeps per second over all vehicles): ``rate / 10`` vehicles publish at 10 Hz for
``--seconds``, staggered, each replaying a spooled vehicle's sweeps under its own id (``sim000-r1``
...; one Zenoh session per spooled vehicle). Reported: poses per second of wall time, drops and other
errors, publish-to-pose latency, and the service process's CPU ms per sweep (user + system over the
run, divided by the poses) and cores busy. What a stand-in cannot show: the cost of the pipe to real matcher
processes (its answers are handed over in the same process; a matcher process's answer is about
50 kB of pickle) and corrections applied by the matcher (the stand-in's points were prepared with
none, so with the graph on the service moves them itself once the graph corrects a session).
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import os
import pickle
import shlex
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import common
import numpy as np
from common import REPO, THREAD_VARS, free_port, git_line, heading, machine_line, progress, table
from fleet_link import RATE_HZ, Answers, drive_fleet, fleet_link

del common

#: Issue 31: the service process with the matching elsewhere.
RATE_TARGET = 300.0
CPU_TARGET_MS = 3.0
#: Sweeps per vehicle in the spool (60 s at 10 Hz, as bench/service.py's done-means runs).
N_SCANS = 600


def _bench_service() -> Any:
    """bench/service.py as a module (its name would shadow the ``service`` package on sys.path)."""
    spec = importlib.util.spec_from_file_location("bench_service", Path(__file__).with_name("service.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# -- the matchers' answers, prepared once ------------------------------------------------------------
def prepare(spool_dir: Path, vehicles: list[str]) -> Path:
    """Every vehicle's sweeps through the matcher processes' code (:func:`offline.matcher_process`),
    pickled to ``answers-<n>.pkl`` in the spool directory (reused when present): per vehicle,
    the :class:`~randt.service.matchers.Registered` of each sweep, its final state for snapshots and
    its CPU ms per sweep."""
    from offline import matcher_process

    path = spool_dir / f"answers-{len(vehicles)}.pkl"
    if path.exists():
        return path
    spool = _bench_service().Spool.load(spool_dir)
    answers: dict[str, Any] = {}
    try:
        for v in vehicles:
            progress(f"preparing {v}'s answers: its sweeps through the matcher processes' code")
            run = matcher_process((spool.get(v, k) for k in range(spool.n_scans())), keep=True)
            answers[v] = {
                "registered": run.registered,
                "state": run.state,
                "cpu_ms": 1e3 * np.mean(run.cpu_s),
            }
    finally:
        spool.close()
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as f:
        pickle.dump(answers, f, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(tmp, path)
    return path


# -- the service process with the stand-in ----------------------------------------------------------
#: The service process's program (``python -c``; not this script, whose ``import common`` sets the
#: benchmarks' one-thread BLAS environment). argv: repository, bench directory, endpoint, data
#: directory, answers file, graph on/off. Prints its pid once started, runs until stdin closes,
#: then prints its stand-in's counts and stops (draining and saving, as on SIGTERM).
SERVE_PROGRAM = """
import json, os, sys
from pathlib import Path
sys.path.insert(0, sys.argv[1])
sys.path.append(sys.argv[2])  # (after the repository: bench/service.py is not the service package)
from stand_in import StandIn
from randt.service.runtime import Service
from randt.service.settings import ServiceSettings
stand_in = StandIn(Path(sys.argv[5]))
settings = ServiceSettings(
    data_dir=Path(sys.argv[4]), listen=(sys.argv[3],), http_port=0, graph=sys.argv[6] == "on",
    max_sessions=0, capacity_target=0,  # (this process's own limit is what is measured)
)
service = Service(settings, executor=stand_in)
service.start()
print(json.dumps({"pid": os.getpid()}), flush=True)
sys.stdin.read()
if service.sessions.graph is not None:
    service.sessions.graph.wait_idle(300)
service.stop()
print(json.dumps({"missing_keyframes": stand_in.missing_keyframes}), flush=True)
"""


# -- one offered rate ---------------------------------------------------------------------------------
def virtual_vehicles(rate: float, vehicles: list[str]) -> dict[str, str]:
    """``rate / 10`` vehicles at 10 Hz, each replaying a spooled vehicle's sweeps under its own
    id (``<spooled>-r<k>``): ``{vehicle: spooled vehicle}``."""
    n = max(1, round(rate / RATE_HZ))
    return {
        f"{vehicles[j % len(vehicles)]}-r{j // len(vehicles)}": vehicles[j % len(vehicles)] for j in range(n)
    }


def run_one(
    rate: float, spool_dir: Path, prepared: Path, vehicles: list[str], graph: bool, seconds: float
) -> dict[str, Any]:
    """``rate / 10`` vehicles publishing at 10 Hz for ``seconds`` (:func:`virtual_vehicles`)
    against a fresh service process with the stand-in; its flow, latency and CPU per sweep."""
    import msgpack

    bench_service = _bench_service()
    spool = bench_service.Spool.load(spool_dir)
    n_scans = min(spool.n_scans(), round(seconds * RATE_HZ))
    fleet = virtual_vehicles(rate, vehicles)

    def replayed(vehicle: str) -> Callable[[int], bytes]:
        def payload_of(k: int) -> bytes:
            message = msgpack.unpackb(spool.get(fleet[vehicle], k), raw=False)
            message["vehicle"] = vehicle  # the spooled sweep under this vehicle's id
            return bytes(msgpack.packb(message))

        return payload_of

    with tempfile.TemporaryDirectory(prefix="randt-bench-main-") as tmp:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS}
        service = subprocess.Popen(
            [
                sys.executable, "-c", SERVE_PROGRAM, str(REPO), str(Path(__file__).parent), endpoint,
                str(Path(tmp) / "data"), str(prepared), "on" if graph else "off",
            ],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
        )  # fmt: skip
        assert service.stdin is not None and service.stdout is not None
        pid = int(json.loads(service.stdout.readline())["pid"])
        answers = Answers()
        # one Zenoh session per spooled vehicle, shared by its replays
        with fleet_link(endpoint, vehicles, answers) as sessions:
            cpu0 = bench_service._proc_cpu_s(pid)
            t0 = drive_fleet({v: (sessions[fleet[v]], replayed(v)) for v in fleet}, n_scans, answers)
            answers.wait_all_answered(60.0)
            cpu = bench_service._proc_cpu_s(pid) - cpu0
            wall = answers.wall_s(t0)
        service.stdin.close()
        final = json.loads(service.stdout.readline())
        service.wait(120)
    truth = spool.truth
    spool.close()
    lat = answers.latencies_ms()
    err = np.array(
        [
            100 * np.linalg.norm(T[:3, 3] - truth[(fleet[v], k)][:3, 3])
            for (v, k), T in answers.pose_of.items()
        ]
    )
    errors = answers.errors
    poses = max(len(answers.got), 1)
    return {
        "rate": rate,
        "vehicles": len(fleet),
        "graph": graph,
        "sent": len(answers.sent),
        "poses": len(answers.got),
        "dropped": errors.get("dropped", 0),
        "other_errors": sum(v for k, v in errors.items() if k != "dropped"),
        "unanswered": len(answers.sent) - len(answers.got) - sum(errors.values()),
        "not_in_map": answers.not_in_map,
        "poses_per_s": len(answers.got) / wall,
        "mean_ms": float(lat.mean()) if lat.size else float("nan"),
        "p50_ms": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "p99_ms": float(np.percentile(lat, 99)) if lat.size else float("nan"),
        "max_ms": float(lat.max()) if lat.size else float("nan"),
        "cpu_main_ms": 1e3 * cpu / poses,
        "cores_main": cpu / wall,
        "err_max_cm": float(err.max()) if err.size else float("nan"),
        "missing_keyframes": final["missing_keyframes"],
        "error_codes": errors,
        "error_example": answers.example,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", type=float, nargs="+", default=[100, 200, 300, 400, 600])
    parser.add_argument(
        "--vehicles",
        type=int,
        default=4,
        help="vehicles of the spool (each replayed by rate / 10 / this vehicles)",
    )
    parser.add_argument(
        "--seconds", type=float, default=20.0, help="seconds each vehicle publishes (at most 60)"
    )
    parser.add_argument("--graph", choices=["on", "off"], default="on")
    parser.add_argument(
        "--sweeps",
        type=Path,
        required=True,
        help="bench/service.py's spool directory (--sweeps there); simulated into it when absent",
    )
    parser.add_argument("--markdown", action="store_true")
    parser.add_argument("--one", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args()
    bench_service = _bench_service()
    spool_dir: Path = args.sweeps
    meta = {"vehicles": args.vehicles, "scans": N_SCANS, "link": "default", "routes": "car-like"}
    if args.one is None and not bench_service._spool_fits(spool_dir / "meta.json", meta):
        spool_dir.mkdir(parents=True, exist_ok=True)
        (spool_dir / "meta.json").unlink(missing_ok=True)
        bench_service.simulate(args.vehicles, N_SCANS, "default", spool_dir)
        (spool_dir / "meta.json").write_text(json.dumps(meta))
    spool = bench_service.Spool.load(spool_dir)
    vehicles = spool.vehicles()[: args.vehicles]
    spool.close()
    if args.one is not None:
        answers = spool_dir / f"answers-{len(vehicles)}.pkl"
        print(json.dumps(run_one(args.one, spool_dir, answers, vehicles, args.graph == "on", args.seconds)))
        return
    print(f"Command: python bench/main_process.py {shlex.join(sys.argv[1:])}")
    print(machine_line({}, single_threaded=False))
    print(f"{git_line()}; run on {datetime.date.today().isoformat()}")
    answers = prepare(spool_dir, vehicles)
    with open(answers, "rb") as f:
        matcher_ms = {v: a["cpu_ms"] for v, a in pickle.load(f).items()}
    print(f"1-min load average at start: {os.getloadavg()[0]:.2f}")
    results = []
    for rate in args.rates:
        progress(f"{len(virtual_vehicles(rate, vehicles))} vehicles at 10 Hz, graph {args.graph}")
        command = [sys.executable, __file__, "--one", str(rate), "--sweeps", str(spool_dir)]
        command += ["--vehicles", str(args.vehicles), "--graph", args.graph, "--seconds", str(args.seconds)]
        out = subprocess.run(command, capture_output=True, text=True)
        if out.returncode != 0:
            sys.stderr.write(out.stderr)
            raise SystemExit(f"the run at {rate:g} sweeps/s failed (exit {out.returncode})")
        results.append(json.loads(out.stdout.strip().splitlines()[-1]))
    head = [
        "offered sweeps/s", "vehicles", "graph", "scans sent", "poses", "dropped", "other errors",
        "unanswered", "poses/s", "latency p50 / p99 / max ms", "service process CPU ms per sweep",
        "cores busy", "pose error max cm",
    ]  # fmt: skip
    rows = [
        [
            f"{r['rate']:g}", str(r["vehicles"]), "on" if r["graph"] else "off", str(r["sent"]),
            str(r["poses"]), str(r["dropped"]), str(r["other_errors"]), str(r["unanswered"]),
            f"{r['poses_per_s']:.0f}", f"{r['p50_ms']:.0f} / {r['p99_ms']:.0f} / {r['max_ms']:.0f}",
            f"{r['cpu_main_ms']:.2f}", f"{r['cores_main']:.2f}", f"{r['err_max_cm']:.1f}",
        ]
        for r in results
    ]  # fmt: skip
    print(
        heading("The service process with the matching elsewhere (a stand-in answers at once)", args.markdown)
    )
    print(table(head, rows, args.markdown))
    held = [r for r in results if r["dropped"] == r["other_errors"] == r["unanswered"] == 0]
    best = max(held, key=lambda r: float(r["poses_per_s"]), default=None)
    print(
        f"\nHighest rate carried with nothing dropped (issue 31: at least {RATE_TARGET:g} sweeps/s): "
        + ("none" if best is None else f"{best['poses_per_s']:.0f} sweeps/s, {best['cpu_main_ms']:.2f} ms")
        + f" of CPU per sweep in the service process (at most {CPU_TARGET_MS:g} ms)"
    )
    print(
        "Matcher CPU per sweep behind the answers (prepared here, one thread): "
        + ", ".join(f"{v} {ms:.1f} ms" for v, ms in matcher_ms.items())
    )
    if any(r["missing_keyframes"] for r in results):
        print(f"keyframes asked for where none was prepared: {[r['missing_keyframes'] for r in results]}")
    print(f"1-min load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
