"""kill -9 and the durable pose graph (issue 33): what the graph showed survives every crash.

Run from the repository root::

    python -m bench.graph_crash [--cycles 10] [--scans 400] [--seed 0]

Two simulated vehicles drive a 400 m loop of the simulator's town 0 (``--scans`` sweeps each,
simulated once and kept in a spool): ``gnss`` with a prior on its first sweep (it makes the
shared map ``default``), ``nognss`` without priors, starting 100 m behind (it joins the shared map
through the graph), so the run has keyframes, loops and a join. Each cycle starts a worker process
(``--worker``: a real :class:`randt.service.runtime.Service` with its pose graph, without Zenoh; its
outbox is lines on stdout, written before a message would go out) that sends the vehicles' next
sweeps from where the store says they are, each once the one before is answered. The parent
kills it with SIGKILL at a random moment (2-10 s after it is ready; every other cycle 0-1.5 s
after the graph published its next correction, waiting up to ``CORRECTION_WAIT_S`` for one, so
that there is something shown to check) and checks:

* every keyframe a correction named (a keyframe the graph showed moved) is in the graph's
  durable log (``DATA/graph/keyframes.log``): saved before seen;
* per map, every revision published after a restart is higher than every one published before
  the kill: revisions only increase.

After the cycles one worker drives to the end without a kill and writes each session's corrected
trajectory; so does a worker on a fresh data directory that was never killed. Reported: the
largest distance between the two (issue 33: within 5 cm), the keyframes and loops each graph
holds, and whether the join survived.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from bench/
    sys.path.insert(0, str(REPO))

__all__ = ["GraphCrashReport", "run_graph_kill_cycles"]

#: Every other cycle is killed just after a correction: how long it waits for one, at most (s).
CORRECTION_WAIT_S = 120.0

VEHICLES = ("gnss", "nognss")
PRIOR_COV = np.diag([1e-4] * 3 + [1e-5] * 3)


@dataclass
class GraphCrashReport:
    """What :func:`run_graph_kill_cycles` found."""

    cycles: int
    corrections_seen: int  # corrections published over all killed cycles
    keyframes_shown: int  # distinct keyframes named by them
    shown_not_durable: int  # of those, missing from the log after the kill
    revisions_back: int  # revisions published after a restart not above those before the kill
    corrected_max_diff_m: float  # killed run against the uninterrupted one, over both sessions
    keyframes: tuple[int, int]  # keyframes in the graph: killed run, uninterrupted run
    loops_accepted: tuple[int, int]
    joined: tuple[bool, bool]
    seconds: float
    problems: list[str] = field(default_factory=list)


# ---------------------------------------------------------------------------------- the drive


def make_spool(path: Path, n_scans: int) -> None:
    """Simulate both vehicles once (randt.sim.drive), into an npz the workers read."""
    from randt.sim.drive import plan_fleet, simulate
    from randt.sim.lidar import Lidar64
    from randt.sim.town import Town

    town = Town.generate(0)
    plan = plan_fleet(town, 1, seed=0, route_length_m=400.0)[0]
    lidar = Lidar64(n_azimuth=1000, max_range_m=70.0)
    arrays: dict[str, np.ndarray] = {}
    for v, seed, back, t0 in (("gnss", 1, 0.0, 0), ("nognss", 2, 100.0, 50_000_000)):
        start = (plan.start_s_m - back) % plan.route.length_m
        scans = list(
            simulate(
                town, plan.route, n_scans=n_scans, seed=seed, lidar=lidar, start_s_m=start,
                start_stamp_ns=t0, workers=2,
            )
        )  # fmt: skip
        arrays[f"{v}_n"] = np.array([len(s.points_xyz) for s in scans])
        arrays[f"{v}_xyz"] = np.concatenate([s.points_xyz for s in scans]).astype(np.float32)
        arrays[f"{v}_stamp"] = np.array([s.stamp_ns for s in scans], dtype=np.int64)
        arrays[f"{v}_pose"] = np.stack([s.T_world_sensor for s in scans])
    np.savez(path, **arrays)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------- worker


def _worker(data_dir: str, spool: str, out_path: str | None) -> None:
    """The crashing side: a Service with its graph, fed the spooled drive from where the store
    says each vehicle is; its outbox is stdout (one JSON line per pose or correction)."""
    from randt.service.runtime import Service
    from randt.service.settings import ServiceSettings
    from randt.wire.messages import (
        CorrectionMessage,
        ErrorMessage,
        PoseMessage,
        WireMessage,
        encode,
        scan_from_arrays,
    )

    drive = np.load(spool)
    out_lock = threading.Lock()
    answered = threading.Semaphore(0)

    def line(obj: dict[str, Any]) -> None:
        with out_lock:
            sys.stdout.write(json.dumps(obj) + "\n")
            sys.stdout.flush()

    def emit(msg: WireMessage) -> None:
        if isinstance(msg, CorrectionMessage):
            line({"k": "correction", "map": msg.map, "veh": msg.vehicle, "ses": msg.session,
                  "rev": msg.revision, "seqs": [int(q) for q in msg.seqs()]})  # fmt: skip
        if isinstance(msg, PoseMessage | ErrorMessage):
            answered.release()

    settings = ServiceSettings(
        data_dir=Path(data_dir), flush_interval_s=0.5, capacity_target=0, idle_expiry_s=3600
    )

    class Outbox(list[WireMessage]):
        """The service's outbox without Zenoh (``Service._sent``): every message it sends, the
        graph's corrections included, goes through ``emit`` as it goes out."""

        def append(self, msg: WireMessage) -> None:
            emit(msg)

    service = Service(settings, with_zenoh=False)
    service._sent = Outbox()  # (bound by start(): the sessions' and the graph's outbox)
    service.start()
    mgr = service.sessions
    assert mgr is not None and mgr.graph is not None
    mgr.wait_matchers(600)
    records = mgr.records()
    offsets = {v: np.r_[0, np.cumsum(drive[f"{v}_n"])] for v in VEHICLES}
    n = len(drive["gnss_n"])
    nxt = {v: 0 if records.get((v, "d1")) is None else records[(v, "d1")].last_seq + 1 for v in VEHICLES}
    line({"k": "ready"})
    for k in range(min(nxt.values()), n):
        for v in VEHICLES:
            if k < nxt[v]:
                continue
            xyz = drive[f"{v}_xyz"][offsets[v][k] : offsets[v][k + 1]]
            prior = (
                {"prior_pose": drive[f"{v}_pose"][k], "prior_covariance": PRIOR_COV}
                if v == "gnss" and k == 0
                else {}
            )
            mgr.submit(v, encode(scan_from_arrays(v, "d1", k, int(drive[f"{v}_stamp"][k]), xyz, **prior)))
            answered.acquire(timeout=60)
    if out_path is not None:
        mgr.graph.wait_idle(600)
        result: dict[str, Any] = {}
        for v in VEHICLES:
            live = mgr.trajectory(v, "d1")  # (None when the kills left nothing to drive: stored)
            poses = live[1] if live is not None else mgr.store.load_session(v, "d1").poses
            corrected, map_name = mgr.graph.corrected(v, "d1", poses)
            result[v] = {"map": map_name, "xyz": corrected[:, :3, 3].tolist()}
        state = mgr.graph.snapshot("default")
        result["keyframes"] = 0 if state is None else sum(len(k) for k in state.keyframes.values())
        result["loops"] = 0 if state is None else sum(loop.accepted for loop in state.loops)
        result["joined"] = mgr.graph.joined("nognss", "d1") is not None
        Path(out_path).write_text(json.dumps(result))
    service.stop()


# ---------------------------------------------------------------------------------- parent


def _start(data: Path, spool: Path, out: Path | None = None) -> subprocess.Popen[str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    cmd = [sys.executable, "-m", "bench.graph_crash", "--worker", str(data), "--spool", str(spool)]
    if out is not None:
        cmd += ["--out", str(out)]
    return subprocess.Popen(
        cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env
    )


def _read_lines(stream: Any, into: list[str]) -> None:
    for text in stream:
        into.append(text)


def _to_end(data: Path, spool: Path, out: Path) -> dict[str, Any]:
    proc = _start(data, spool, out)
    assert proc.stdout is not None
    for _ in proc.stdout:
        pass
    if proc.wait(1800) != 0 or not out.is_file():
        raise RuntimeError(f"the worker on {data} did not finish (exit code {proc.returncode})")
    return json.loads(out.read_text())


def run_graph_kill_cycles(
    work: Path, *, cycles: int = 10, n_scans: int = 400, seed: int = 0
) -> GraphCrashReport:
    """``cycles`` kill -9 cycles on one data directory, then the rest of the drive; the same drive
    uninterrupted on another (module docstring)."""
    from randt.service.graph_log import GRAPH_DIRNAME, GraphLog

    t0 = time.perf_counter()
    rnd = random.Random(seed)
    spool = work / "drive.npz"
    if not spool.is_file():
        make_spool(spool, n_scans)
    data = work / "killed"
    problems: list[str] = []
    seen: set[tuple[str, str, int]] = set()
    n_corrections = not_durable = back = 0
    highest: dict[str, int] = {}
    for cycle in range(cycles):
        proc = _start(data, spool)
        assert proc.stdout is not None
        lines: list[str] = []
        reader = threading.Thread(target=_read_lines, args=(proc.stdout, lines), daemon=True)
        reader.start()
        deadline = time.monotonic() + 300
        while not any('"ready"' in s for s in lines) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        wait = rnd.uniform(2.0, 10.0)
        if cycle % 2 == 1:  # (every other cycle: just after the graph has shown something)
            n_seen = sum('"correction"' in s for s in lines)
            deadline = time.monotonic() + CORRECTION_WAIT_S
            while sum('"correction"' in s for s in lines) == n_seen and time.monotonic() < deadline:
                time.sleep(0.01)
            wait = rnd.uniform(0.0, 1.5)
        time.sleep(wait)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
        reader.join(30)
        records = GraphLog(data / GRAPH_DIRNAME).read()
        logged = {(item[2], item[3], item[4]) for _, item in records if item[0] == "keyframe"}
        before = dict(highest)
        for text in lines:
            if not text.endswith("\n"):
                continue
            msg = json.loads(text)
            if msg["k"] != "correction":
                continue
            n_corrections += 1
            if msg["rev"] <= before.get(msg["map"], 0):
                back += 1
                problems.append(
                    f"cycle {cycle}: {msg['map']} revision {msg['rev']} after {before[msg['map']]}"
                )
            highest[msg["map"]] = max(highest.get(msg["map"], 0), msg["rev"])
            for q in msg["seqs"]:
                key = (msg["veh"], msg["ses"], q)
                seen.add(key)
                if key not in logged:
                    not_durable += 1
                    problems.append(f"cycle {cycle}: keyframe {key} shown, not in the log after the kill")
    killed = _to_end(data, spool, work / "killed.json")
    clean = _to_end(work / "clean", spool, work / "clean.json")
    diff = 0.0
    for v in VEHICLES:
        a, b = np.asarray(killed[v]["xyz"]), np.asarray(clean[v]["xyz"])
        if a.shape != b.shape or killed[v]["map"] != clean[v]["map"]:
            problems.append(f"{v}: {a.shape} in {killed[v]['map']} against {b.shape} in {clean[v]['map']}")
            diff = float("inf")
            continue
        diff = max(diff, float(np.linalg.norm(a - b, axis=1).max()))
    return GraphCrashReport(
        cycles=cycles,
        corrections_seen=n_corrections,
        keyframes_shown=len(seen),
        shown_not_durable=not_durable,
        revisions_back=back,
        corrected_max_diff_m=diff,
        keyframes=(killed["keyframes"], clean["keyframes"]),
        loops_accepted=(killed["loops"], clean["loops"]),
        joined=(killed["joined"], clean["joined"]),
        seconds=time.perf_counter() - t0,
        problems=problems[:20],
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="graph_crash.py", description=__doc__.split("\n")[0])
    parser.add_argument("--cycles", type=int, default=10, help="kill -9 cycles (default 10)")
    parser.add_argument("--scans", type=int, default=400, help="sweeps per vehicle (default 400)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill moments (default 0)")
    parser.add_argument("--work", type=Path, default=None, help="work directory (default: a fresh temp)")
    parser.add_argument("--worker", metavar="DATA", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--spool", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--out", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker is not None:
        _worker(args.worker, args.spool, args.out)
        return
    with tempfile.TemporaryDirectory(prefix="randt-graph-crash-") as tmp:
        work = args.work if args.work is not None else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        report = run_graph_kill_cycles(work, cycles=args.cycles, n_scans=args.scans, seed=args.seed)
    print(json.dumps(dataclasses.asdict(report), indent=2))


if __name__ == "__main__":
    main()
