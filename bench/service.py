"""Service benchmark: a simulated fleet at 10 Hz per vehicle against a real service process.

Run from the repository root::

    python bench/service.py --vehicles 1 2 4 6 8 --seconds 20 --markdown --plot docs/img/fleet.png
    python bench/service.py --vehicles 4 --seconds 60 --markdown

First, the largest fleet's raw sweeps are simulated (HDL-64E-like, about 120k points, in their
firing-time frames with per-point time offsets, as a real LiDAR gives them) and encoded as the
vehicle library would send them: ``--link default`` with ``randt.clients.publisher.encode_sweep`` and the
library's default :class:`~randt.clients.publisher.PublisherSettings` (reduced, quantized, compressed),
``--link raw`` as full v1 messages (``randt.wire.messages.scan_from_arrays`` + ``encode``). They are
spooled to a file (a long run would otherwise hold gigabytes of sweeps in memory); a smaller fleet
drives the largest one's first vehicles. The simulation is the slow part of a run (about 0.2 s a
sweep on this machine).

For each fleet size, a fresh subprocess (the *bench*) starts a fresh *service process*
(:class:`randt.service.runtime.Service`, a Zenoh peer on loopback, data in a temporary directory, its
environment without the benchmarks' one-thread BLAS settings: the service sets its own), waits
for its matcher processes to warm up, and publishes every vehicle's sweeps at 10 Hz from one Zenoh
session per vehicle for ``--seconds``, the vehicles staggered over one period as unsynchronised
sensors are.

Reported per fleet size: poses per second of wall time; scans sent, poses, drops (overload
policy), other errors and unanswered scans; publish-to-pose latency p50/p90/p99/max (publish call
to the pose's arrival at a subscriber); CPU per sweep of the service's main process, of its
matcher processes and their sum (user + system time over the run, divided by the poses); bytes on
the wire per sweep and Mbit/s per vehicle at 10 Hz; pose error against the simulator's ground truth
(position max and RMSE, rotation max; with per-point time offsets a pose refers to mid-sweep,
core/odometry.py, so the truth is the sensor pose at stamp + 50 ms); peak RSS of the service's
main process and of its largest matcher process.

**Offline reference** (issue 31): before the fleets run, every vehicle's spooled sweeps go through
a matcher process's own code in this process, one thread, none dropped
(``bench/offline.py``'s ``matcher_process``: decoding, matching, the map points, a keyframe's
points where the pose graph asks, the model update; only the pipe and the service are missing).
Per vehicle, its pose error p95 and its CPU per sweep (mean, median, max) are printed; each
fleet size then gives its worst vehicle's error p95 against that
vehicle's offline p95 (the service must add no error) and its matchers' CPU per sweep against the
offline CPU of the same vehicles' sweeps (issue 31: at most 1.1x). A fleet size *holds* when every
scan got a pose (none dropped, refused or unanswered), p99 < 200 ms, and every vehicle's error p95
is within 1 cm of its offline p95 (``--no-offline``: every pose within 5 cm of the truth, issue 14).

``--graph both`` runs each fleet size twice, the service's pose graph off then on (service/graph.py,
``RANDT_GRAPH``), and prints the ratio of their latencies (issue 15: at most +10 % by the mean);
the cost table then also gives the graph process's CPU per sweep, its keyframes and loops.

``--repeat N`` runs each such pair N times, interleaved, and adds the ratio over all of them (a
single run's ratio moves by about 5 %).

``--plot`` draws latency percentiles and drops against fleet size (matplotlib, the bench extra)
and writes the same figures as CSV beside the image. Every figure comes from this run.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import datetime
import functools
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import common
import numpy as np
from common import REPO, THREAD_VARS, free_port, git_line, heading, machine_line, progress, run_json, table
from fleet_link import RATE_HZ, Answers, drive_fleet, fleet_link

del common

#: Targets of issue 14 (a fleet size holds when it meets all of them).
P99_TARGET_MS = 200.0
ERROR_TARGET_CM = 5.0
#: Issue 31: each vehicle's pose error p95 in the service within this of the same sweeps offline.
ADDED_P95_TARGET_CM = 1.0
#: Issue 31: the matchers' CPU per sweep in the service at most this times offline.
CPU_RATIO_TARGET = 1.1


def _encoder(link: str, session: str = "bench") -> Callable[..., bytes]:
    """``f(vehicle, seq, stamp_ns, xyz, intensity, offsets, **prior) -> bytes``: the payload the
    vehicle library sends (``randt.clients.publisher.encode_sweep``), with its defaults (``default``) or
    every point as a v1 scan (``raw``)."""
    from randt.clients.publisher import PublisherSettings, encode_sweep

    settings = PublisherSettings(raw=link == "raw")

    def encoder(
        vehicle: str,
        seq: int,
        stamp_ns: int,
        xyz: np.ndarray,
        intensity: np.ndarray,
        offsets: np.ndarray,
        **prior: Any,
    ) -> bytes:
        return encode_sweep(
            vehicle, session, seq, stamp_ns, xyz,
            intensity=intensity, time_offset_s=offsets, settings=settings, **prior,
        )  # fmt: skip

    return encoder


class Spool:
    """Encoded sweeps in one file (``sweeps.bin``) with their index and ground truth beside it:
    written once for the largest fleet, read back by every fleet size's run at publication."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self._where: dict[tuple[str, int], tuple[int, int]] = {}
        self.truth: dict[tuple[str, int], np.ndarray] = {}
        self._file: IO[bytes] | None = None

    @classmethod
    def load(cls, directory: Path) -> Spool:
        spool = cls(directory)
        index = json.loads((directory / "index.json").read_text())
        truth = np.load(directory / "truth.npy")
        for (vehicle, seq, start, size), T in zip(index, truth, strict=True):
            spool._where[(vehicle, seq)] = (start, size)
            spool.truth[(vehicle, seq)] = T
        spool._file = open(directory / "sweeps.bin", "rb")  # noqa: SIM115 (closed by close())
        return spool

    def get(self, vehicle: str, seq: int) -> bytes:
        assert self._file is not None
        start, size = self._where[(vehicle, seq)]
        return os.pread(self._file.fileno(), size, start)

    def vehicles(self) -> list[str]:
        return sorted({v for v, _ in self._where})

    def n_scans(self) -> int:
        return 1 + max(k for _, k in self._where)

    def sizes(self, vehicles: list[str]) -> np.ndarray:
        return np.array([size for (v, _), (_, size) in self._where.items() if v in vehicles], dtype=float)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()


def simulate(
    n_vehicles: int,
    n_scans: int,
    link: str,
    directory: Path,
    *,
    noise_seed: int = 0,
    rate_hz: float = RATE_HZ,
    session: str = "bench",
    plan_size: int | None = None,
    gnss: str = "first",
) -> None:
    """Simulate every vehicle's raw sweeps, encode them for ``link`` and write a :class:`Spool`.

    The fleet is :func:`randt.sim.drive.plan_fleet`'s for ``n_vehicles`` (town seed 1, fleet seed 3);
    a smaller fleet's run uses its first vehicles. The ground truth of each sweep is the sensor
    pose at mid-sweep (with per-point time offsets the matcher's pose refers to it,
    core/odometry.py); each vehicle's first sweep carries it as its prior, as GNSS/INS would.
    ``noise_seed`` is added to each vehicle's sensor noise seed (another drive of the same routes:
    the mapping drive of ``--mapped``, another day of bench/lifelong.py); ``rate_hz``: the sweeps'
    rate (the vehicles drive 10 m/s); ``session``: the sessions' id; ``plan_size``: the fleet
    planned (its first ``n_vehicles`` simulated: the routes of a larger fleet's spool); ``gnss``:
    ``first`` (the true pose on each vehicle's first sweep only, a survey's start) or ``noisy``
    (every sweep carries a fix of the vehicle library's ``noisy`` GNSS, 0.5 m noise and a 1 m bias,
    no outage: a vehicle refused at its first scans still has a prior on the scan admitted).
    """
    from randt.clients.fleet import FleetSettings, VehicleGnss
    from randt.sim.drive import Motion, plan_fleet
    from randt.sim.drive import simulate as drive
    from randt.sim.lidar import Lidar64
    from randt.sim.town import Town

    town = Town.generate(1)
    encode = _encoder(link, session)
    lidar = Lidar64()
    half = 0.5 / rate_hz
    index: list[tuple[str, int, int, int]] = []
    truth: list[np.ndarray] = []
    end = 0
    with open(directory / "sweeps.bin", "wb") as out:
        for v in plan_fleet(town, plan_size or n_vehicles, seed=3)[:n_vehicles]:
            progress(f"simulating and encoding {n_scans} sweeps of {v.vehicle_id} ({link} link)")
            receiver = VehicleGnss(
                "noisy", FleetSettings(duration_s=n_scans / rate_hz, gnss_outage_s=0.0), v.seed + noise_seed
            )
            motion = Motion(
                v.route, speed_mps=10.0, start_s_m=v.start_s_m, mount_height_m=lidar.mount_height_m
            )
            scans = drive(
                town,
                v.route,
                n_scans=n_scans,
                rate_hz=rate_hz,
                speed_mps=10.0,
                seed=v.seed + noise_seed,
                lidar=lidar,
                deskewed=False,
                start_s_m=v.start_s_m,
                start_stamp_ns=v.stamp_offset_ns,
                workers=2,  # (the same sweeps, cast on both cores)
            )
            for scan in scans:
                T_mid = motion.sensor_poses_at(scan.index / rate_hz + half)[0]
                prior: dict[str, Any] = {}
                if gnss == "noisy":
                    fix = receiver.prior(scan.index / rate_hz + half, T_mid)
                    if fix is not None:
                        prior = dict(prior_pose=fix[0], prior_covariance=fix[1])
                elif scan.index == 0:
                    prior = dict(prior_pose=T_mid, prior_covariance=np.diag([1e-4] * 3 + [1e-5] * 3))
                payload = encode(
                    v.vehicle_id,
                    scan.index,
                    scan.stamp_ns,
                    scan.points_xyz,
                    scan.intensity,
                    scan.time_offset_s,
                    **prior,
                )
                out.write(payload)
                index.append((v.vehicle_id, scan.index, end, len(payload)))
                truth.append(T_mid)
                end += len(payload)
    (directory / "index.json").write_text(json.dumps(index))
    np.save(directory / "truth.npy", np.array(truth))


# -- the service process ---------------------------------------------------------------------------
#: The service process's program (``python -c``): not this script, whose ``import common`` would set
#: the benchmarks' one-thread BLAS environment before the service could show what it sets itself.
#: It prints its pid and its matcher processes' once they are warm, runs until stdin closes, then
#: prints how many scans it received and stops (draining and saving, as on SIGTERM).
SERVE_PROGRAM = """
import json, os, sys
from pathlib import Path
sys.path.insert(0, sys.argv[1])
from randt.service.runtime import Service
from randt.service.settings import ServiceSettings
service = Service(ServiceSettings(data_dir=Path(sys.argv[3]), listen=(sys.argv[2],), http_port=0))
service.start()
if not service.sessions.wait_matchers(600):
    raise SystemExit("matcher processes not warm after 600 s")
pool = service.sessions.pool
pids = [p for p in pool.pids() if p] if hasattr(pool, "pids") else []  # (Ray: its actors' processes)
graph = service.sessions.graph
if graph is not None and hasattr(graph, "replaying"):  # ready as /readyz says: the log replayed
    import time
    while graph.replaying:
        time.sleep(0.1)
    graph.wait_idle(300)
graph_cpu0 = graph.cpu_s() if graph is not None and hasattr(graph, "cpu_s") else 0.0
print(json.dumps({"pid": os.getpid(), "matchers": pids}), flush=True)
sys.stdin.read()
value = service.metrics.registry.get_sample_value
received = value("randt_scans_received_total") or 0
stats = {}
if graph is not None:
    graph.wait_idle(300)
    proc = graph.supervisor.proc
    if proc is not None and proc.pid:
        with open(f"/proc/{proc.pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        stats["cpu_s"] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        if hasattr(graph, "cpu_s"):  # (since the fleet started: not the log's replay)
            stats["cpu_s"] = graph.cpu_s() - graph_cpu0
        with open(f"/proc/{proc.pid}/status") as f:
            hwm = [line.split()[1] for line in f if line.startswith("VmHWM:")]
        stats["rss_mib"] = int(hwm[0]) / 1024 if hwm else 0.0
    stats["keyframes"] = value("randt_graph_keyframes_total", {"result": "added"}) or 0
    stats["loops"] = value("randt_graph_loops_total", {"result": "accepted"}) or 0
    stats["verified"] = stats["loops"] + (value("randt_graph_loops_total", {"result": "refused"}) or 0)
    stats["dropped"] = value("randt_graph_queue_dropped_total") or 0
    gate = getattr(graph, "gate", None)  # (YieldGate; a service before it has none)
    stats["held_s"] = gate.held_s if gate is not None else 0.0
    snap = graph.snapshot("default")  # sessions without priors it placed: T_map_session
    stats["joined"] = {f"{v}/{s}": T.tolist() for (v, s), T in getattr(snap, "joined", {}).items()}
    stats["total_keyframes"] = sum(len(k) for k in snap.keyframes.values()) if snap is not None else 0
    stats["total_loops"] = len(snap.loops) if snap is not None else 0
service.stop()
print(json.dumps({"received": int(received), "graph": stats}), flush=True)
"""


def _proc_cpu_s(pid: int) -> float:
    """User + system CPU seconds of one process (all its threads), from /proc."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


def _ray_processes() -> tuple[list[int], list[int]]:
    """The Ray processes of this machine: (workers, the rest). A worker's title is ``ray::<actor
    class>`` (``ray::IDLE`` before it holds one); the rest are Ray's own (GCS, raylet, agents)."""
    workers, own = [], []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if cmd.startswith("ray::"):
            workers.append(int(entry))
        elif "/ray/" in cmd and (
            "gcs_server" in cmd
            or "raylet" in cmd
            or "ray/_private" in cmd
            or "ray/dashboard" in cmd
            or "ray/autoscaler" in cmd
        ):
            own.append(int(entry))
    return workers, own


def _rss_mib(pid: int) -> float:
    """Current resident memory of a process (0 if it is gone)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def _cpu_or_zero(pid: int) -> float:
    try:
        return _proc_cpu_s(pid)
    except OSError:
        return 0.0


def _peak_rss_mib(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


# -- one fleet size --------------------------------------------------------------------------------
def _spool_fits(meta_path: Path, meta: dict[str, Any]) -> bool:
    """Whether a spool's sweeps serve a run: the same duration, link and routes, and at least as
    many vehicles (a run with fewer takes the first ones of the spool's fleet, as every fleet
    size of one run does)."""
    if not meta_path.exists():
        return False
    held = json.loads(meta_path.read_text())
    others = {k: v for k, v in held.items() if k != "vehicles"}
    same = others == {k: v for k, v in meta.items() if k != "vehicles"}
    return same and int(held.get("vehicles", 0)) >= int(meta["vehicles"])


def write_timeline(
    path: Path,
    sent: dict[tuple[str, int], float],
    got: dict[tuple[str, int], float],
    pose_of: dict[tuple[str, int], np.ndarray],
    truth: dict[tuple[str, int], np.ndarray],
) -> None:
    """One row per scan sent: vehicle, seq, seconds since the first scan was sent, publish-to-pose
    latency (ms, empty when not posed) and position error (cm; empty for a pose in another map's
    frame: a session answered in its own), to see when a run stalled."""
    t0 = min(sent.values(), default=0.0)
    with path.open("w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(["vehicle", "seq", "sent_s", "latency_ms", "error_cm"])
        for key in sorted(sent, key=sent.__getitem__):
            row: list[object] = [key[0], key[1], f"{sent[key] - t0:.3f}", "", ""]
            if key in got:
                row[3] = f"{1e3 * (got[key] - sent[key]):.1f}"
            if key in pose_of:
                row[4] = f"{100 * float(np.linalg.norm(pose_of[key][:3, 3] - truth[key][:3, 3])):.2f}"
            out.writerow(row)


def join_errors(
    joined: dict[str, list[list[float]]],
    pose_own: dict[tuple[str, int], np.ndarray],
    truth: dict[tuple[str, int], np.ndarray],
) -> dict[str, tuple[float, float]]:
    """Per vehicle the graph joined into the shared map (a session answered in its own frame:
    no prior on its first admitted scan), how far its ``T_map_session`` is from the truth (m,
    deg): the truth's is ``T_true @ inv(T_session)`` of each of its answered scans, the median
    scan's taken (they differ by the session's own drift)."""
    from randt.core.transforms import invert, rotation_angle_deg

    out: dict[str, tuple[float, float]] = {}
    for sid, T_list in joined.items():
        vehicle = sid.split("/", 1)[0]
        keys = sorted(k for k in pose_own if k[0] == vehicle and k in truth)
        if not keys:
            continue
        k = keys[len(keys) // 2]
        T_true = truth[k] @ invert(pose_own[k])
        D = invert(T_true) @ np.asarray(T_list)
        out[vehicle] = (float(np.linalg.norm(D[:3, 3])), rotation_angle_deg(D[:3, :3]))
    return out


def map_quality(data_dir: Path, map_name: str = "default") -> dict[str, float]:
    """The shared map as the service saved it, against the simulated town's true surfaces (town
    seed 1, the spool's): its points and their distance to the nearest surface (p50, p90 cm) and
    how many lie more than 0.3 m off (what a wrong pose folds in)."""
    from randt.core.io import read_cloud
    from randt.sim.town import Town

    tiles = sorted((data_dir / "maps" / map_name).glob("*.pcd"))
    if not tiles:
        return {"map_points": 0, "map_p50_cm": float("nan"), "map_p90_cm": float("nan"), "map_off": 0}
    xyz = np.concatenate([read_cloud(t).xyz for t in tiles])
    d = Town.generate(1).surface_distance(xyz.astype(np.float64))
    return {
        "map_points": int(xyz.shape[0]),
        "map_p50_cm": float(100 * np.percentile(d, 50)),
        "map_p90_cm": float(100 * np.percentile(d, 90)),
        "map_off": int(np.count_nonzero(d > 0.3)),
    }


def run_one(
    n_vehicles: int,
    spool_dir: Path,
    link: str,
    service_repo: Path = REPO,
    graph: bool = True,
    executor: str = "local",
    timeline: Path | None = None,
    rate_hz: float = RATE_HZ,
    first: int = 0,
    localize: bool | None = None,
    data_from: Path | None = None,
    keep_data: Path | None = None,
    admission: bool = True,
) -> dict[str, Any]:
    """One fleet size, in this process (a fresh subprocess of :func:`main`), the service's pose
    graph on or off (``RANDT_GRAPH``), its matchers in local worker processes or Ray actors
    (``RANDT_EXECUTOR``); each vehicle publishes its 10 Hz sweeps at ``rate_hz``; the fleet is the
    spool's ``n_vehicles`` vehicles from its ``first``. ``localize``: ``RANDT_LOCALIZE`` (``None``:
    the service's default); ``data_from``: the service starts on a copy of this data directory (a
    map made before); ``keep_data``: the data directory is copied there after the service stopped;
    ``admission`` false: ``RANDT_CAPACITY_TARGET=0`` (every session admitted: a map made before)."""
    from randt.core.transforms import invert
    from randt.wire.codes import ErrorCode

    spool = Spool.load(spool_dir)
    vehicles = spool.vehicles()[first : first + n_vehicles]
    n_scans = spool.n_scans()
    truth = spool.truth
    sizes = spool.sizes(vehicles)
    with tempfile.TemporaryDirectory(prefix="randt-bench-") as tmp:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS}  # the service sets its own
        env["RANDT_GRAPH"] = "true" if graph else "false"
        env["RANDT_EXECUTOR"] = executor
        if localize is not None:
            env["RANDT_LOCALIZE"] = "true" if localize else "false"
        if not admission:
            env["RANDT_CAPACITY_TARGET"] = "0"
        if data_from is not None:
            shutil.copytree(data_from, Path(tmp) / "data")
        service = subprocess.Popen(
            [sys.executable, "-c", SERVE_PROGRAM, str(service_repo), endpoint, str(Path(tmp) / "data")],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )
        assert service.stdin is not None and service.stdout is not None
        started = json.loads(service.stdout.readline())
        main_pid = int(started["pid"])
        matcher_pids = [int(p) for p in started["matchers"]]

        answers = Answers()
        with fleet_link(endpoint, vehicles, answers) as sessions:
            cpu0 = _proc_cpu_s(main_pid), sum(_proc_cpu_s(p) for p in matcher_pids)
            ray_workers0, ray_own0 = _ray_processes() if executor == "ray" else ([], [])
            ray_cpu0 = {p: _cpu_or_zero(p) for p in ray_workers0 + ray_own0}
            fleet = {v: (sessions[v], functools.partial(spool.get, v)) for v in vehicles}
            t0 = drive_fleet(fleet, n_scans, answers, rate_hz)
            answers.wait_all_answered(120.0)
            cpu_main = _proc_cpu_s(main_pid) - cpu0[0]
            cpu_matchers = sum(_proc_cpu_s(p) for p in matcher_pids) - cpu0[1]
            rss_main = _peak_rss_mib(main_pid)
            rss_matcher = max((_peak_rss_mib(p) for p in matcher_pids), default=float("nan"))
            cpu_ray_own = rss_ray_own = 0.0
            if executor == "ray":  # the actors' processes are the matchers; Ray's own are its cost
                ray_workers, ray_own = _ray_processes()
                cpu_matchers = sum(_cpu_or_zero(p) - ray_cpu0.get(p, 0.0) for p in ray_workers)
                cpu_ray_own = sum(_cpu_or_zero(p) - ray_cpu0.get(p, 0.0) for p in ray_own)
                actors = [p for p in ray_workers if _rss_mib(p) > 0]
                rss_matcher = max((_peak_rss_mib(p) for p in actors), default=float("nan"))
                rss_ray_own = sum(_rss_mib(p) for p in ray_own)
            wall = answers.wall_s(t0)
        service.stdin.close()
        final = json.loads(service.stdout.readline())
        received, graph_stats = final["received"], final["graph"]
        service.wait(120)
        spool.close()
        quality = map_quality(Path(tmp) / "data")
        if keep_data is not None:
            shutil.rmtree(keep_data, ignore_errors=True)
            shutil.copytree(Path(tmp) / "data", keep_data)

    sent, got, pose_of, errors = answers.sent, answers.got, answers.pose_of, answers.errors
    lat_ms = answers.latencies_ms()
    pct = {p: float(np.percentile(lat_ms, p)) if lat_ms.size else float("nan") for p in (50, 90, 99)}
    pos_cm, rot_deg = [], []
    by_vehicle: dict[str, list[float]] = {v: [] for v in vehicles}
    for k, T in pose_of.items():
        D = invert(truth[k]) @ T
        pos_cm.append(100 * float(np.linalg.norm(T[:3, 3] - truth[k][:3, 3])))
        by_vehicle[k[0]].append(pos_cm[-1])
        rot_deg.append(float(np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1.0, 1.0)))))
    pos = np.array(pos_cm)
    if timeline is not None:
        write_timeline(timeline, sent, got, pose_of, truth)
    n_answered = len(got) + sum(errors.values())
    poses = max(len(got), 1)
    dropped = errors.get(ErrorCode.DROPPED, 0)
    other = sum(v for k, v in errors.items() if k != ErrorCode.DROPPED)
    unanswered = len(sent) - n_answered
    err_max = float(pos.max()) if pos.size else float("nan")
    not_in_map = answers.not_in_map
    flows = (  # every scan posed in time (the error criterion is main()'s: it has the offline run)
        dropped == 0 and other == 0 and unanswered == 0 and not_in_map == 0 and pct[99] < P99_TARGET_MS
    )

    def status_err_max(status: str) -> float:
        errs = [
            100 * float(np.linalg.norm(T[:3, 3] - truth[k][:3, 3]))
            for k, T in pose_of.items()
            if answers.status_of.get(k) == status
        ]
        return max(errs, default=float("nan"))

    # Admitted vehicles (a pose at least) and the share of their scans answered ok (issue 32:
    # shedding keeps them tracking: at least a third); refused ones (never a pose) and whether
    # every refusal said when to retry.
    joins = join_errors(graph_stats.get("joined", {}), answers.pose_own, truth)
    admitted = {k[0] for k in got}
    admitted_sent = sum(1 for k in sent if k[0] in admitted)
    admitted_ok = sum(1 for k, st in answers.status_of.items() if st == "ok" and k[0] in admitted)
    refused_vehicles = sorted(set(vehicles) - admitted)
    return {
        **quality,
        "admitted_vehicles": len(admitted),
        "admitted_names": sorted(admitted),
        "refused_vehicles": len(refused_vehicles),
        "refused_told_retry": all(v in answers.retry_after for v in refused_vehicles),
        "admitted_ok_share": admitted_ok / admitted_sent if admitted_sent else float("nan"),
        "ok_err_max_cm": status_err_max("ok"),
        "fallback_err_max_cm": status_err_max("fallback"),
        "lost": errors.get(ErrorCode.LOST, 0),
        "refused": errors.get(ErrorCode.SESSIONS_FULL, 0) + errors.get(ErrorCode.VEHICLE_SESSIONS_FULL, 0),
        "vehicles": n_vehicles,
        "graph": graph,
        "graph_keyframes": int(graph_stats.get("keyframes", 0)),
        "graph_loops": int(graph_stats.get("loops", 0)),
        "graph_verified": int(graph_stats.get("verified", 0)),
        "graph_dropped": int(graph_stats.get("dropped", 0)),
        "graph_held_s": float(graph_stats.get("held_s", 0.0)),
        "graph_total_keyframes": int(graph_stats.get("total_keyframes", 0)),
        "graph_total_loops": int(graph_stats.get("total_loops", 0)),
        "rss_graph_mib": float(graph_stats.get("rss_mib", 0.0)),
        "joins": joins,
        "cpu_graph_ms": 1e3 * graph_stats.get("cpu_s", 0.0) / poses,
        "mean_ms": float(lat_ms.mean()) if lat_ms.size else float("nan"),
        "seconds": n_scans / RATE_HZ,
        "link": link,
        "sent": len(sent),
        "received": received,
        "poses": len(got),
        "fallbacks": answers.statuses.get("fallback", 0),
        "localized": answers.localized,
        "localize": localize,
        "not_in_map": not_in_map,
        "dropped": dropped,
        "other_errors": other,
        "other_codes": ", ".join(f"{k} {v}" for k, v in sorted(errors.items()) if k != ErrorCode.DROPPED),
        "unanswered": unanswered,
        "poses_per_s": len(got) / wall,
        "p50_ms": pct[50],
        "p90_ms": pct[90],
        "p99_ms": pct[99],
        "max_ms": float(lat_ms.max()) if lat_ms.size else float("nan"),
        "executor": executor,
        "cpu_ray_own_ms": 1e3 * cpu_ray_own / poses,
        "rss_ray_own_mib": rss_ray_own,
        "cpu_main_ms": 1e3 * cpu_main / poses,
        "cpu_matchers_ms": 1e3 * cpu_matchers / poses,
        "cpu_total_ms": 1e3 * (cpu_main + cpu_matchers) / poses,
        "cpu_cores_busy": (cpu_main + cpu_matchers) / wall,
        "bytes_per_sweep": float(sizes.mean()),
        "mbit_per_vehicle": float(sizes.mean()) * 8 * RATE_HZ / 1e6,
        "err_max_cm": err_max,
        "err_rmse_cm": float(np.sqrt(np.mean(pos**2))) if pos.size else float("nan"),
        "err_p99_cm": float(np.percentile(pos, 99)) if pos.size else float("nan"),
        "rot_max_deg": float(max(rot_deg)) if rot_deg else float("nan"),
        "rss_main_mib": rss_main,
        "rss_matcher_mib": rss_matcher,
        "p95_cm_by_vehicle": {
            v: float(np.percentile(e, 95)) if e else float("nan") for v, e in by_vehicle.items()
        },
        "flows": flows,
        "holds": flows and err_max < ERROR_TARGET_CM,  # main() replaces it when it ran the offline reference
    }


# -- the same sweeps offline ------------------------------------------------------------------------
def offline(
    spool_dir: Path, n_vehicles: int, graph: bool = True, first: int = 0
) -> dict[str, dict[str, Any]]:
    """``n_vehicles`` vehicles' spooled sweeps (from the ``first``) through a matcher process's
    code in this process, one thread, none dropped (:func:`offline.matcher_process`: decoding,
    matching, the map points cut to the voxels not sent before, a keyframe's points where the pose
    graph would ask for them when ``graph``, the model update): per vehicle its pose error p95
    and max against the truth (cm, as :func:`run_one` measures the service's) and its CPU ms per
    sweep."""
    from offline import matcher_process

    spool = Spool.load(spool_dir)
    try:
        n = spool.n_scans()
        vehicles = spool.vehicles()[first : first + n_vehicles]
        matcher_process(spool.get(vehicles[0], k) for k in range(3))  # kernels compiled or loaded: untimed
        out: dict[str, dict[str, Any]] = {}
        for v in vehicles:
            progress(f"offline: {v}'s {n} sweeps through a matcher process's code, one thread")
            run = matcher_process((spool.get(v, k) for k in range(n)), graph=graph)
            err = np.array(
                [100 * np.linalg.norm(P[:3, 3] - spool.truth[(v, k)][:3, 3]) for k, P in enumerate(run.poses)]
            )
            out[v] = {
                "sweeps": n,
                "p95_cm": float(np.percentile(err, 95)),
                "max_cm": float(err.max()),
                "cpu_ms": [1e3 * c for c in run.cpu_s],
            }
        return out
    finally:
        spool.close()


def compare_offline(r: dict[str, Any], ref: dict[str, dict[str, Any]]) -> None:
    """Add to one fleet size's result its worst vehicle's error p95 above offline, its matchers'
    CPU per sweep against offline (the same vehicles' sweeps) and issue 31's verdict."""
    added = [r["p95_cm_by_vehicle"][v] - ref[v]["p95_cm"] for v in r["p95_cm_by_vehicle"]]
    r["added_p95_cm"] = float(max(added)) if added else float("nan")
    cpu = [c for v in r["p95_cm_by_vehicle"] for c in ref[v]["cpu_ms"]]
    r["offline_cpu_ms"] = float(np.mean(cpu))
    r["cpu_ratio"] = r["cpu_matchers_ms"] / r["offline_cpu_ms"]
    r["holds"] = bool(r["flows"] and r["added_p95_cm"] <= ADDED_P95_TARGET_CM)


def offline_table(ref: dict[str, dict[str, Any]], markdown: bool) -> str:
    head = ["vehicle", "sweeps", "pose error p95 / max cm", "CPU ms per sweep: mean / median / max"]
    rows = [
        [
            v,
            str(x["sweeps"]),
            f"{x['p95_cm']:.2f} / {x['max_cm']:.2f}",
            " / ".join(f"{f(x['cpu_ms']):.1f}" for f in (np.mean, np.median, np.max)),
        ]
        for v, x in ref.items()
    ]
    return table(head, rows, markdown)


# -- report ------------------------------------------------------------------------------------------
def _rows(results: list[dict[str, Any]]) -> tuple[list[str], list[list[str]], list[str], list[list[str]]]:
    flow_head = [
        "vehicles",
        "graph",
        "matchers",
        "scans sent",
        "poses",
        "dropped",
        "other errors",
        "unanswered",
        "poses/s",
        "latency mean / p50 / p90 / p99 / max ms",
        "pose error max / RMSE cm",
        "rotation error max deg",
        "error p95 above offline, worst vehicle cm",
        "holds",
    ]
    flow = [
        [
            str(r["vehicles"]),
            "on" if r["graph"] else "off",
            r["executor"],
            str(r["sent"]),
            str(r["poses"]) + (f" ({r['fallbacks']} fallbacks)" if r["fallbacks"] else ""),
            str(r["dropped"]),
            str(r["other_errors"]) + (f" ({r['other_codes']})" if r["other_codes"] else ""),
            str(r["unanswered"]),
            f"{r['poses_per_s']:.1f}",
            " / ".join(f"{r[k]:.0f}" for k in ("mean_ms", "p50_ms", "p90_ms", "p99_ms", "max_ms")),
            f"{r['err_max_cm']:.2f} / {r['err_rmse_cm']:.2f}",
            f"{r['rot_max_deg']:.3f}",
            f"{r['added_p95_cm']:+.2f}" if "added_p95_cm" in r else "",
            "yes" if r["holds"] else "no",
        ]
        for r in results
    ]
    cost_head = [
        "vehicles",
        "graph",
        "matchers",
        "CPU ms per sweep: service main / matchers / sum",
        "matchers / offline CPU per sweep",
        "graph process: CPU ms per sweep, keyframes, loops accepted / verified, dropped, s held",
        "cores busy",
        "bytes per sweep",
        "Mbit/s per vehicle",
        "peak RSS MiB: main / largest matcher",
    ]
    cost = [
        [
            str(r["vehicles"]),
            "on" if r["graph"] else "off",
            r["executor"]
            + (
                f" (Ray's own: {r['cpu_ray_own_ms']:.1f} ms, {r['rss_ray_own_mib']:.0f} MiB)"
                if r["executor"] == "ray"
                else ""
            ),
            f"{r['cpu_main_ms']:.1f} / {r['cpu_matchers_ms']:.1f} / {r['cpu_total_ms']:.1f}",
            f"{r['cpu_matchers_ms']:.1f} / {r['offline_cpu_ms']:.1f} = {r['cpu_ratio']:.2f}x"
            if "cpu_ratio" in r
            else "",
            f"{r['cpu_graph_ms']:.1f}, {r['graph_keyframes']}, {r['graph_loops']} / {r['graph_verified']}, "
            f"{r['graph_dropped']}, {r['graph_held_s']:.0f}"
            if r["graph"]
            else "",
            f"{r['cpu_cores_busy']:.2f}",
            f"{r['bytes_per_sweep']:,.0f}",
            f"{r['mbit_per_vehicle']:.1f}",
            f"{r['rss_main_mib']:.0f} / {r['rss_matcher_mib']:.0f}",
        ]
        for r in results
    ]
    return flow_head, flow, cost_head, cost


def _err(cm: float) -> str:
    return "" if np.isnan(cm) else f" ({cm:.1f})"


def status_rows(results: list[dict[str, Any]]) -> tuple[list[str], list[list[str]]]:
    """Every scan by its answer, the error of the poses answered by status, and the shared map's
    points against the true surfaces (issue 32: what overload does to the answers and the map)."""
    head = [
        "vehicles",
        "graph",
        "scans sent",
        "ok (error max cm)",
        "fallback (error max cm)",
        "lost",
        "dropped",
        "refused",
        "vehicles admitted / refused (told when to retry)",
        "admitted vehicles' scans ok",
        "map points",
        "map to true surfaces p50 / p90 cm",
        "map points > 0.3 m off",
        "answered in their own frame; joined: placement error m / deg",
    ]
    rows = [
        [
            str(r["vehicles"]),
            "on" if r["graph"] else "off",
            str(r["sent"]),
            f"{r['poses'] - r['fallbacks']}" + _err(r["ok_err_max_cm"]),
            f"{r['fallbacks']}" + _err(r["fallback_err_max_cm"]),
            str(r["lost"]),
            str(r["dropped"]),
            str(r["refused"]),
            f"{r['admitted_vehicles']} / {r['refused_vehicles']}"
            + (f" ({', '.join(r['admitted_names'])} admitted)" if r["refused_vehicles"] else "")
            + (
                " (yes)"
                if r["refused_vehicles"] and r["refused_told_retry"]
                else " (no)"
                if r["refused_vehicles"]
                else ""
            ),
            f"{100 * r['admitted_ok_share']:.0f} %",
            f"{r['map_points']:,}",
            f"{r['map_p50_cm']:.1f} / {r['map_p90_cm']:.1f}",
            f"{r['map_off']:,}",
            f"{r['not_in_map']}"
            + "".join(f"; {v} {m:.2f} / {deg:.2f}" for v, (m, deg) in sorted(r.get("joins", {}).items())),
        ]
        for r in results
    ]
    return head, rows


def plot(results: list[dict[str, Any]], path: Path) -> None:
    """Latency percentiles and drops against fleet size (``path``), the figures as CSV beside it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fields = [
        "vehicles",
        "sent",
        "poses",
        "dropped",
        "other_errors",
        "unanswered",
        "poses_per_s",
        "p50_ms",
        "p90_ms",
        "p99_ms",
        "max_ms",
        "cpu_main_ms",
        "cpu_matchers_ms",
        "cpu_total_ms",
        "bytes_per_sweep",
        "mbit_per_vehicle",
        "err_max_cm",
        "err_rmse_cm",
        "rot_max_deg",
        "holds",
    ]
    with open(path.with_suffix(".csv"), "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(fields)
        for r in results:
            writer.writerow([f"{r[k]:.3f}" if isinstance(r[k], float) else r[k] for k in fields])
    n = [r["vehicles"] for r in results]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    for key, style in (("p50_ms", "o-"), ("p90_ms", "s-"), ("p99_ms", "^-"), ("max_ms", "x--")):
        ax1.plot(n, [r[key] for r in results], style, label=key.removesuffix("_ms"))
    ax1.axhline(P99_TARGET_MS, color="red", linewidth=0.8, linestyle=":", label="p99 target")
    ax1.set_yscale("log")
    ax1.set_xlabel("vehicles at 10 Hz")
    ax1.set_ylabel("publish-to-pose latency (ms)")
    ax1.legend()
    ax1.grid(True, which="both", alpha=0.3)
    dropped_pct = [100 * r["dropped"] / max(r["sent"], 1) for r in results]
    ax2.bar(n, dropped_pct, color="tab:orange")
    ax2.set_ylim(0.0, max(1.0, 1.1 * max(dropped_pct, default=0.0)))  # none dropped: an empty axis at 0
    ax2.set_xlabel("vehicles at 10 Hz")
    ax2.set_ylabel("scans dropped (%)")
    ax2.set_xticks(n)
    ax2.grid(True, axis="y", alpha=0.3)
    link = results[0]["link"] if results else ""
    seconds = results[0]["seconds"] if results else 0
    fig.suptitle(f"Service on this machine: {seconds:g} s per fleet size, {link} link")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _pooled(results: list[dict[str, Any]], what: str, repeat: int) -> None:
    """With ``repeat`` > 1: per fleet size, the second runs' mean latency over all their sweeps
    against the first runs' (each run's mean weighted by its poses)."""
    if repeat < 2:
        return
    for n in sorted({r["vehicles"] for r in results}):
        runs = [r for r in results if r["vehicles"] == n]
        first, second = runs[0::2], runs[1::2]

        def pooled(rs: list[dict[str, Any]]) -> float:
            return sum(r["mean_ms"] * r["poses"] for r in rs) / sum(r["poses"] for r in rs)

        ratios = ", ".join(f"{b['mean_ms'] / a['mean_ms']:.3f}x" for a, b in zip(first, second, strict=True))
        print(
            f"- {n} vehicle(s), {what} over {len(first)} interleaved pairs: mean "
            f"{pooled(second):.1f} / {pooled(first):.1f} ms = {pooled(second) / pooled(first):.3f}x "
            f"(pairs: {ratios})"
        )


def _run(command: list[str], n: int) -> dict[str, Any]:
    """One fleet size's run (``--one``) in a fresh subprocess: its result."""
    return run_json(command, f"the run with {n} vehicle(s)")


#: The mapping drive of ``--mapped``: the seed added to each vehicle's sensor noise (another drive
#: of the same routes).
MAPPING_NOISE_SEED = 7919


def _mapping_drive(
    spool: Path, n_fleet: int, plan_size: int, args: argparse.Namespace, keep: Path
) -> dict[str, Any]:
    """``--mapped``: the fleet's routes driven once before (other noise, the 10 Hz sweeps published
    at ``--map-rate``, every session admitted), the service's data directory kept in ``keep``."""
    spool.mkdir(parents=True, exist_ok=True)
    meta = {"vehicles": n_fleet, "scans": round(args.seconds * RATE_HZ), "link": args.link}
    meta.update(routes="car-like", noise_seed=MAPPING_NOISE_SEED, plan_size=plan_size)
    meta_path = spool / "meta.json"
    if not _spool_fits(meta_path, meta):
        meta_path.unlink(missing_ok=True)
        (spool / "run.json").unlink(missing_ok=True)  # (a map kept by --reuse-map is of other sweeps)
        simulate(
            n_fleet,
            meta["scans"],
            args.link,
            spool,
            noise_seed=MAPPING_NOISE_SEED,
            session="mapping",
            plan_size=plan_size,
        )
        meta_path.write_text(json.dumps(meta))
    kept, kept_run = spool / "data", spool / "run.json"
    if args.reuse_map and kept_run.exists() and (kept / "maps").is_dir():
        progress(f"reusing the map made before in {kept} (--reuse-map)")
        shutil.rmtree(keep, ignore_errors=True)
        shutil.copytree(kept, keep)
        return dict(json.loads(kept_run.read_text()))
    progress(f"the mapping drive: {n_fleet} vehicle(s), {meta['scans']} sweeps each at {args.map_rate:g} Hz")
    command = [sys.executable, __file__, "--one", str(n_fleet), "--spool", str(spool), "--link", args.link]
    command += ["--service-repo", str(args.service_repo), "--graph", "on", "--rate", str(args.map_rate)]
    command += ["--localize", "off", "--keep-data", str(keep), "--no-admission"]
    run = _run(command, n_fleet)
    if args.reuse_map:  # (kept beside the sweeps for the next run)
        shutil.rmtree(kept, ignore_errors=True)
        shutil.copytree(keep, kept)
        kept_run.write_text(json.dumps(run))
    return run


def _mapped_summary(mapping_run: dict[str, Any] | None, results: list[dict[str, Any]]) -> None:
    """``--mapped``: the mapping drive, then per fleet size localizing against mapping the same
    streets again: CPU per sweep (the service's processes, the graph's beside), poses localized."""
    if mapping_run is not None:
        m = mapping_run
        print(
            f"\nThe map made before: {m['sent']} sweeps sent, {m['poses']} poses, {m['dropped']} dropped, "
            f"{m['map_points']} map points ({m['map_off']} more than 0.3 m off the town's surfaces), "
            f"{m['graph_keyframes']} graph keyframes"
        )
    print("\nOn the mapped streets, localizing (RANDT_LOCALIZE=true) against mapping them again (issue 57: "
          "CPU per sweep at most a third):")  # fmt: skip
    for off, on in zip(results[0::2], results[1::2], strict=True):
        ratio = on["cpu_total_ms"] / off["cpu_total_ms"]
        print(
            f"- {on['vehicles']} vehicle(s): CPU per sweep {on['cpu_total_ms']:.1f} / "
            f"{off['cpu_total_ms']:.1f} ms = {ratio:.2f}x (matchers {on['cpu_matchers_ms']:.1f} / "
            f"{off['cpu_matchers_ms']:.1f}, graph {on['cpu_graph_ms']:.1f} / {off['cpu_graph_ms']:.1f}); "
            f"localized {on['localized']} of {on['poses']} poses; p99 {on['p99_ms']:.0f} / "
            f"{off['p99_ms']:.0f} ms; error max {on['err_max_cm']:.1f} / {off['err_max_cm']:.1f} cm; "
            f"graph keyframes {on['graph_keyframes']} / {off['graph_keyframes']}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, nargs="+", default=[1, 2, 4, 6, 8])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument(
        "--link",
        choices=["default", "raw"],
        default="default",
        help="default: the vehicle library's encoding with its default settings; raw: full v1 sweeps",
    )
    parser.add_argument(
        "--graph",
        choices=["on", "off", "both"],
        default="on",
        help="the service's pose graph (RANDT_GRAPH); both: each fleet size with it off, then on, "
        "and the ratio of their latencies",
    )
    parser.add_argument(
        "--executor",
        choices=["local", "ray", "both"],
        default="local",
        help="where the matchers run (RANDT_EXECUTOR); both: each fleet size with local worker processes, "
        "then Ray actors, and the ratio of their latencies (issue 16: at most +15 %%). Ray binds the "
        "machine's external address: run it in a private network namespace (docs/benchmarks.md)",
    )
    parser.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="with --graph both or --executor both: run each pair this many times, interleaved "
        "(off, on, off, on...), and report the ratio of the mean latencies over all of them beside "
        "each pair's (one run's ratio moves by about 5 %%)",
    )
    parser.add_argument(
        "--gnss",
        choices=["first", "noisy"],
        default="first",
        help="the vehicles' priors: first, the true pose on each one's first sweep only; noisy, a fix "
        "on every sweep (0.5 m noise, 1 m bias: the vehicle library's noisy GNSS). A --mapped run's "
        "mapping drive has first",
    )
    parser.add_argument("--markdown", action="store_true")
    parser.add_argument("--plot", type=Path, help="latency and drops against fleet size (PNG; CSV beside it)")
    parser.add_argument(
        "--service-repo",
        type=Path,
        default=REPO,
        help="run the service from this checkout (a before/after comparison); default: this one",
    )
    parser.add_argument(
        "--sweeps",
        type=Path,
        help="keep the simulated sweeps in this directory and reuse them when a later run asks for "
        "as many vehicles or fewer (the first ones of its fleet), the same duration and link "
        "(default: a temporary directory)",
    )
    parser.add_argument(
        "--no-offline",
        action="store_true",
        help="skip the offline reference (the same sweeps through the session matcher here, one thread)",
    )
    parser.add_argument(
        "--timeline",
        type=Path,
        help="write each run's per-scan latency and pose error to this directory "
        "(timeline-<vehicles>-<graph>-<executor>.csv), to see when a run stalled",
    )
    parser.add_argument(
        "--rate",
        type=float,
        default=RATE_HZ,
        help="publish each vehicle's 10 Hz sweeps at this rate (Hz; default 10): a slower rate carries "
        "more vehicles within capacity, the same sweeps (a reference for the map of a larger fleet)",
    )
    parser.add_argument(
        "--first",
        type=int,
        default=0,
        help="the fleet's vehicles from this one on (0: sim000, the default): e.g. `--vehicles 1 --first 2` "
        "runs sim002 alone, the vehicle a run past capacity admitted, for a like-for-like reference",
    )
    parser.add_argument(
        "--mapped",
        action="store_true",
        help="the fleet on streets mapped beforehand (issue 57): a mapping drive of the same routes "
        "(other sensor noise, published at --map-rate, every session admitted) makes the map first; "
        "each fleet size then runs twice on a copy of it, RANDT_LOCALIZE off (it maps the streets "
        "again) and on (it localizes on the map), and the ratio of their CPU per sweep is printed",
    )
    parser.add_argument(
        "--map-rate", type=float, default=2.0, help="with --mapped: the mapping drive's publish rate (Hz)"
    )
    parser.add_argument(
        "--reuse-map",
        action="store_true",
        help="with --mapped and --sweeps: keep the mapping drive's data directory beside the sweeps and "
        "start from it again in a later run (the map as the code of that run made it)",
    )
    parser.add_argument("--localize", choices=["on", "off"], help=argparse.SUPPRESS)
    parser.add_argument("--data-from", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--keep-data", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--no-admission", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--simulate-to", type=Path, help=argparse.SUPPRESS)  # (bench/lifelong.py's days)
    parser.add_argument("--noise-seed", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--session", default="bench", help=argparse.SUPPRESS)
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--spool", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.simulate_to:
        args.simulate_to.mkdir(parents=True, exist_ok=True)
        n_scans = round(args.seconds * RATE_HZ)
        simulate(
            max(args.vehicles),
            n_scans,
            args.link,
            args.simulate_to,
            noise_seed=args.noise_seed,
            session=args.session,
            gnss=args.gnss,
        )
        return
    if args.one:
        timeline = None
        if args.timeline is not None:
            args.timeline.mkdir(parents=True, exist_ok=True)
            timeline = args.timeline / f"timeline-{args.one}-{args.graph}-{args.executor}.csv"
        localize = None if args.localize is None else args.localize == "on"
        result = run_one(
            args.one, args.spool, args.link, args.service_repo, args.graph == "on", args.executor, timeline,
            args.rate, args.first, localize, args.data_from, args.keep_data, not args.no_admission,
        )  # fmt: skip
        print(json.dumps(result))
        return
    print(f"Command: python bench/service.py {shlex.join(sys.argv[1:])}")
    print(machine_line({}, single_threaded=False))
    print(f"{git_line()}; run on {datetime.date.today().isoformat()}")
    results = []
    with contextlib.ExitStack() as stack:
        spool = args.sweeps or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="randt-sweeps-")))
        spool.mkdir(parents=True, exist_ok=True)
        n_fleet = args.first + max(args.vehicles)
        meta = {"vehicles": n_fleet, "scans": round(args.seconds * RATE_HZ), "link": args.link}
        meta["routes"] = "car-like"  # randt.sim.drive since 2026-11-26: clothoids, slower in corners
        if args.gnss != "first":
            meta["gnss"] = args.gnss
        meta_path = spool / "meta.json"
        if not _spool_fits(meta_path, meta):
            meta_path.unlink(missing_ok=True)
            simulate(meta["vehicles"], meta["scans"], args.link, spool, gnss=args.gnss)
            meta_path.write_text(json.dumps(meta))
        else:
            progress(f"reusing the sweeps in {spool}")
        mapped, mapping_run = None, None
        if args.mapped:
            mapped = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="randt-mapped-"))) / "data"
            plan_size = json.loads(meta_path.read_text())["vehicles"]  # (the routes of the spool's fleet)
            mapping_run = _mapping_drive(spool / "mapping", n_fleet, plan_size, args, mapped)
        print(f"1-min load average at start: {os.getloadavg()[0]:.2f}")
        ref = None
        if not args.no_offline and not args.mapped:
            ref = offline(spool, max(args.vehicles), graph=args.graph != "off", first=args.first)
        graphs = ["off", "on"] if args.graph == "both" else [args.graph]
        executors = ["local", "ray"] if args.executor == "both" else [args.executor]
        pairs: list[tuple[str, str, str | None]] = [(g, e, None) for g in graphs for e in executors]
        if args.mapped:
            pairs = [(g, e, loc) for g, e, _ in pairs for loc in ("off", "on")]
        for n in args.vehicles:
            for graph, executor, loc in pairs * (args.repeat if len(pairs) == 2 else 1):
                what = "" if loc is None else f", on the map made before, localize {loc}"
                progress(f"{n} vehicle(s), {args.seconds:g} s, graph {graph}, matchers {executor}{what}")
                command = [sys.executable, __file__, "--one", str(n), "--spool", str(spool)]
                command += ["--link", args.link, "--service-repo", str(args.service_repo), "--graph", graph]
                command += ["--executor", executor, "--rate", str(args.rate), "--first", str(args.first)]
                if loc is not None:
                    command += ["--localize", loc, "--data-from", str(mapped)]
                if args.timeline is not None:
                    command += ["--timeline", str(args.timeline.resolve())]
                results.append(_run(command, n))
    title = f"{args.seconds:g} s of 10 Hz sweeps per vehicle, {args.link} link"
    if args.rate != RATE_HZ:
        title += f", published at {args.rate:g} Hz"
    if ref is not None:
        for r in results:
            compare_offline(r, ref)
        print(heading(f"{title}: the same sweeps offline (one thread, none dropped)", args.markdown))
        print(offline_table(ref, args.markdown))
    flow_head, flow, cost_head, cost = _rows(results)
    print(heading(f"{title}: flow, latency and accuracy", args.markdown))
    print(table(flow_head, flow, args.markdown))
    print(heading(f"{title}: cost", args.markdown))
    print(table(cost_head, cost, args.markdown))
    print(heading(f"{title}: answers by status, and the shared map", args.markdown))
    print(table(*status_rows(results), args.markdown))
    if args.graph == "both" and args.executor != "both":
        print("\nPer-sweep latency, pose graph on against off (issue 15: at most +10 % by the mean):")
        for off, on in zip(results[0::2], results[1::2], strict=True):
            print(
                f"- {on['vehicles']} vehicle(s): mean {on['mean_ms']:.1f} / {off['mean_ms']:.1f} ms = "
                f"{on['mean_ms'] / off['mean_ms']:.3f}x; p50 {on['p50_ms'] / off['p50_ms']:.3f}x, "
                f"p99 {on['p99_ms'] / off['p99_ms']:.3f}x"
            )
        _pooled(results, "on against off", args.repeat)
    if args.executor == "both":
        print("\nPer-sweep latency, Ray actors against local worker processes (issue 16: at most +15 %):")
        for local, ray in zip(results[0::2], results[1::2], strict=True):
            print(
                f"- {ray['vehicles']} vehicle(s), graph {'on' if ray['graph'] else 'off'}: mean "
                f"{ray['mean_ms']:.1f} / {local['mean_ms']:.1f} ms = "
                f"{ray['mean_ms'] / local['mean_ms']:.3f}x; "
                f"p50 {ray['p50_ms'] / local['p50_ms']:.3f}x, p99 {ray['p99_ms'] / local['p99_ms']:.3f}x; "
                f"poses/s {ray['poses_per_s']:.1f} / {local['poses_per_s']:.1f}"
            )
        _pooled(results, "Ray against local", args.repeat)
    if args.mapped:
        _mapped_summary(mapping_run, results)
    holding = [r["vehicles"] for r in results if r["holds"] and r.get("localize") is not False]
    error_rule = (
        f"every pose within {ERROR_TARGET_CM:g} cm"
        if ref is None
        else f"each vehicle's error p95 within {ADDED_P95_TARGET_CM:g} cm of offline"
    )
    print(
        f"\nLargest fleet that holds (no drop, p99 < {P99_TARGET_MS:.0f} ms, {error_rule}): "
        f"{max(holding) if holding else 'none'}"
    )
    if ref is not None:
        ratios = ", ".join(f"{r['vehicles']}: {r['cpu_ratio']:.2f}x" for r in results)
        print(
            f"Matchers' CPU per sweep in the service against offline (at most {CPU_RATIO_TARGET}x): {ratios}"
        )
    print(f"1-min load average at end: {os.getloadavg()[0]:.2f}")
    if args.plot:
        plot(results, args.plot)
        print(f"plot: {args.plot} (figures in {args.plot.with_suffix('.csv')})")


if __name__ == "__main__":
    main()
