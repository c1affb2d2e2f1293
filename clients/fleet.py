"""Simulated vehicles publishing to the service, and their errors against ground truth.

``randt simulate`` and ``randt demo`` are thin shells over :func:`run_fleet`: ``n_vehicles``
vehicles of :func:`sim.plan_fleet` drive their loops through a procedural town, each in its
own thread with its own :class:`~randt.clients.publisher.VehiclePublisher` (its own Zenoh session) and
session. Each has a GNSS mode (``FleetSettings.gnss``: ``exact``, ``noisy`` or ``none``, sent as
the scans' prior poses); by default each keeps at most ``window`` scans unanswered (flow control),
so the errors measure the matcher, not an overload. The sessions with GNSS share the map
``default`` in the town's frame and are compared directly with the simulator's exact poses; a
session without GNSS after one rigid fit (``aligned``). The GNSS modes, the pacing and the error
columns: docs/clients.md, "Simulated vehicles".
"""

from __future__ import annotations

import logging
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any, Literal, get_args

import numpy as np
from scipy.spatial.transform import Rotation

from randt.clients.publisher import PublisherSettings, PublisherStats, VehiclePublisher, default_session_id
from randt.sim import FleetVehicle, Lidar64, Town, plan_fleet, simulate
from randt.sim.gnss import GnssReceiver
from randt.wire.codes import ErrorCode
from randt.wire.messages import PoseMessage

__all__ = [
    "GNSS_MODES",
    "FleetGraph",
    "FleetSettings",
    "GnssMode",
    "GraphVehicle",
    "VehicleErrors",
    "VehicleGnss",
    "VehicleRun",
    "ate_m",
    "evaluate",
    "fleet_graph",
    "graph_table",
    "run_fleet",
    "summary_table",
]

log = logging.getLogger(__name__)

GnssMode = Literal["exact", "noisy", "none"]
#: The GNSS modes a simulated vehicle can have (docs/clients.md, "Simulated vehicles").
GNSS_MODES: tuple[str, ...] = get_args(GnssMode)


@dataclass(frozen=True)
class FleetSettings:
    """What to simulate and how fast.

    Attributes
    ----------
    n_vehicles:
        Vehicles, each its own thread, Zenoh session and service session.
    duration_s:
        Simulated driving time per vehicle (``duration_s * rate_hz`` sweeps each).
    speed_mps:
        Mean speed; 6 m/s (22 km/h, town traffic) keeps corners within the matcher's reach.
    rate_hz:
        Sweeps per simulated second.
    n_azimuth:
        Firings per revolution of the simulated HDL-64E: 2000 is the real sensor's 0.18 deg
        (about 120k points a sweep). Fewer firings simulate faster, but the matcher's default
        gates are tuned on full sweeps: with half of them a vehicle may fall back on a straight
        road.
    window:
        Most unanswered scans per vehicle (flow control); 0 = real time, no flow control.
    town_seed, fleet_seed:
        Seeds of the town and of the routes; the same seeds give the same drive.
    route_length_m:
        Length of each vehicle's closed loop.
    prior_sigma_m, prior_sigma_deg:
        Covariance announced with an ``exact`` GNSS's prior poses.
    gnss:
        GNSS mode per vehicle, cycled (docs/clients.md): ``exact``, ``noisy`` or ``none``.
    shared_routes:
        Every vehicle on the first one's loop from the same start (:func:`sim.plan_fleet`'s
        ``shared``), leaving one after another: vehicle ``v`` starts once vehicle ``v - 1`` has
        ``start_gap_scans`` scans answered. Streets revisited within a drive and shared between
        the sessions; a vehicle with GNSS starts where the map has points, which place its
        first sweep (docs/clients.md).
    gnss_noise_m, gnss_bias_m, gnss_outage_s, gnss_yaw_error_deg:
        The ``noisy`` GNSS (docs/clients.md).
    """

    n_vehicles: int = 3
    duration_s: float = 10.0
    speed_mps: float = 6.0
    rate_hz: float = 10.0
    n_azimuth: int = 2000
    window: int = 2
    town_seed: int = 2
    fleet_seed: int = 0
    route_length_m: float = 600.0
    prior_sigma_m: float = 0.02
    prior_sigma_deg: float = 0.1
    gnss: tuple[GnssMode, ...] = ("exact",)
    shared_routes: bool = False
    start_gap_scans: int = 30
    gnss_noise_m: float = 0.5
    gnss_bias_m: float = 1.0
    gnss_outage_s: float = 15.0
    gnss_yaw_error_deg: float = 0.3

    def __post_init__(self) -> None:
        if not self.gnss or any(g not in GNSS_MODES for g in self.gnss):
            raise ValueError(f"gnss: one or more of {', '.join(GNSS_MODES)}, got {self.gnss!r}")

    @property
    def n_scans(self) -> int:
        """Sweeps per vehicle."""
        return max(1, round(self.duration_s * self.rate_hz))

    def gnss_of(self, vehicle: int) -> GnssMode:
        """The GNSS mode of the fleet's ``vehicle``-th vehicle (``gnss`` cycled)."""
        return self.gnss[vehicle % len(self.gnss)]


class VehicleGnss:
    """One vehicle's prior poses as its GNSS mode gives them (docs/clients.md); the service bench's
    vehicles use it too (bench/service.py ``--gnss``)."""

    def __init__(self, mode: GnssMode, fleet: FleetSettings, seed: int) -> None:
        self.mode = mode
        self.fleet = fleet
        start = 0.3 * fleet.duration_s
        self.receiver = GnssReceiver(
            seed=seed,
            noise_sigma_m=fleet.gnss_noise_m,
            bias_sigma_m=fleet.gnss_bias_m,
            jump_probability=0.0,
            outages=((start, start + fleet.gnss_outage_s),),
        )
        yaw = np.random.default_rng([seed, 17]).normal(0.0, math.radians(fleet.gnss_yaw_error_deg))
        self.R_yaw = Rotation.from_euler("z", yaw).as_matrix()
        self.fixes = 0

    def prior(self, t_s: float, T_true: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """``(prior pose, 6x6 covariance)`` at simulated time ``t_s``, or ``None`` (no fix)."""
        f = self.fleet
        if self.mode == "none":
            return None
        if self.mode == "exact":
            self.fixes += 1
            return T_true, np.diag([f.prior_sigma_m**2] * 3 + [math.radians(f.prior_sigma_deg) ** 2] * 3)
        fix = self.receiver.fix(t_s, T_true[:3, 3])
        if fix is None:
            return None
        self.fixes += 1
        T = T_true.copy()
        T[:3, :3] = self.R_yaw @ T_true[:3, :3]
        T[:3, 3] = fix.position_xyz
        cov = np.zeros((6, 6))
        cov[:3, :3] = fix.covariance
        cov[3:, 3:] = np.eye(3) * math.radians(1.0) ** 2
        return T, cov


@dataclass(frozen=True)
class VehicleErrors:
    """Trajectory errors of one vehicle against the simulator's ground truth, over the scans that
    got a pose.

    ``ate_m``: RMS distance between estimated and true positions, no alignment (the shared frame),
    or after one rigid fit when ``aligned`` (a session in a frame of its own). ``rpe_cm``,
    ``rpe_deg``: RMS frame-to-frame error (``randt.core.metrics.trajectory.rpe``, delta 1).
    ``drift_pct``: KITTI's translation error over the whole drive as one segment,
    ``|t(inv(inv(E_0) E_n) inv(G_0) G_n)| / path length`` in percent; ``kitti_pct`` the devkit's
    average over 100-800 m segments when the drive is longer than 100 m.
    """

    aligned: bool
    n_poses: int
    n_ok: int
    n_fallback: int
    path_length_m: float
    ate_m: float
    rpe_cm: float
    rpe_deg: float
    drift_pct: float | None
    kitti_pct: float | None


@dataclass
class VehicleRun:
    """One simulated vehicle's drive: what it sent, the answers, the truth."""

    vehicle: str
    session: str
    gnss: GnssMode = "exact"
    gnss_fixes: int = 0
    truth: dict[int, np.ndarray] = field(default_factory=dict)
    stamps_ns: dict[int, int] = field(default_factory=dict)
    #: Set when the drive ended (the vehicles that follow it out of the depot stop waiting).
    done: threading.Event = field(default_factory=threading.Event, repr=False)
    poses: dict[int, PoseMessage] = field(default_factory=dict)
    stats: PublisherStats = field(default_factory=PublisherStats)
    points_per_scan: float = 0.0

    def keep_pose(self, msg: PoseMessage) -> None:
        """The publisher's ``on_pose``: the pose answered for scan ``msg.seq``."""
        self.poses[msg.seq] = msg

    def errors(self) -> VehicleErrors | None:
        """:func:`evaluate` of the received poses (None with fewer than 3 poses)."""
        estimate = {s: p.matrix() for s, p in self.poses.items()}
        return evaluate(self.truth, estimate, self.poses, align=self.gnss == "none")

    def _truth_rows(self) -> list[list[float]]:
        return [
            [seq, self.stamps_ns[seq] * 1e-9, *(round(float(v), 4) for v in T[:3, 3])]
            for seq, T in sorted(self.truth.items())
        ]

    def summary(self) -> dict[str, Any]:
        """JSON-ready: ids, GNSS, counters, errors, and the true positions (``truth``: rows
        ``seq, stamp_s, x, y, z``) to score the service's corrected trajectories against."""
        err = self.errors()
        stats = asdict(self.stats)
        return {
            "vehicle": self.vehicle,
            "session": self.session,
            "gnss": self.gnss,
            "gnss_fixes": self.gnss_fixes,
            "truth": self._truth_rows(),
            "scans": len(self.truth),
            "points_per_scan": self.points_per_scan,
            "stats": stats,
            "errors": None if err is None else asdict(err),
        }


def evaluate(
    truth: dict[int, np.ndarray],
    estimate: dict[int, np.ndarray],
    messages: dict[int, PoseMessage] | None = None,
    *,
    align: bool = False,
) -> VehicleErrors | None:
    """Errors of ``estimate`` against ``truth`` over the scans both have (:class:`VehicleErrors`).

    Parameters
    ----------
    truth, estimate:
        ``seq -> (4, 4) T_world_sensor``.
    messages:
        The pose messages, to count ``ok`` and ``fallback`` answers.
    align:
        The ATE after one rigid fit of the positions to the truth (an estimate in a frame of its
        own); the relative errors need none.

    Returns
    -------
    VehicleErrors or None
        None when fewer than 3 scans have both.
    """
    from randt.core.metrics.trajectory import kitti_relative_errors, rpe

    seqs = sorted(set(truth) & set(estimate))
    if len(seqs) < 3:
        return None
    G = np.stack([truth[s] for s in seqs])
    E = np.stack([estimate[s] for s in seqs])
    path = float(np.sum(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1)))
    ate = ate_m(E[:, :3, 3], G[:, :3, 3], align=align)
    r = rpe(G, E, delta=1)
    drift = None
    if path > 1.0:
        d_gt = np.linalg.inv(G[0]) @ G[-1]
        d_est = np.linalg.inv(E[0]) @ E[-1]
        drift = float(100.0 * np.linalg.norm((np.linalg.inv(d_est) @ d_gt)[:3, 3]) / path)
    kitti = kitti_relative_errors(G, E).translation_pct if path > 100.0 else None
    statuses = [messages[s].status for s in seqs] if messages else []
    return VehicleErrors(
        aligned=align,
        n_poses=len(seqs),
        n_ok=sum(st == "ok" for st in statuses),
        n_fallback=sum(st == "fallback" for st in statuses),
        path_length_m=path,
        ate_m=ate,
        rpe_cm=100.0 * r.translation_m.rmse,
        rpe_deg=r.rotation_deg.rmse,
        drift_pct=drift,
        kitti_pct=None if kitti is None or math.isnan(kitti) else float(kitti),
    )


def ate_m(estimate_xyz: np.ndarray, truth_xyz: np.ndarray, *, align: bool = False) -> float:
    """RMS distance between ``(N, 3)`` estimated and true positions; with ``align`` after the
    rigid fit of the estimate to the truth (:func:`randt.core.metrics.trajectory.ate` of the positions,
    ``"se3"`` or ``"none"``; N >= 3 to align)."""
    from randt.core.metrics.trajectory import ate

    def poses(xyz: np.ndarray) -> np.ndarray:
        P = np.tile(np.eye(4), (len(xyz), 1, 1))
        P[:, :3, 3] = xyz
        return P

    est, ref = (
        poses(np.asarray(estimate_xyz, dtype=np.float64)),
        poses(np.asarray(truth_xyz, dtype=np.float64)),
    )
    return ate(ref, est, align="se3" if align else "none").translation_m.rmse


def _drive(
    town: Town,
    plan: FleetVehicle,
    fleet: FleetSettings,
    lidar: Lidar64,
    pub: VehiclePublisher,
    run: VehicleRun,
    stop: threading.Event,
    answer_timeout_s: float,
    leader: VehicleRun | None = None,
) -> None:
    """One vehicle's thread: wait for its turn (``leader``: the vehicle it follows out of the
    depot, :attr:`FleetSettings.shared_routes`), simulate each sweep, publish it (with its GNSS
    prior), keep the flow-control window."""
    gnss = VehicleGnss(run.gnss, fleet, plan.seed)
    if leader is not None:
        deadline = time.monotonic() + answer_timeout_s
        while len(leader.poses) < min(fleet.start_gap_scans, fleet.n_scans) and not leader.done.is_set():
            if stop.wait(0.1) or time.monotonic() > deadline:
                break
    start_ns = time.time_ns() + plan.stamp_offset_ns
    t0 = time.monotonic()
    n_points = 0
    try:
        scans = simulate(
            town,
            plan.route,
            n_scans=fleet.n_scans,
            rate_hz=fleet.rate_hz,
            speed_mps=fleet.speed_mps,
            seed=plan.seed,
            lidar=lidar,
            start_s_m=plan.start_s_m,
            start_stamp_ns=start_ns,
        )
        for scan in scans:
            if stop.is_set():
                break
            run.truth[scan.index] = scan.T_world_sensor
            run.stamps_ns[scan.index] = scan.stamp_ns
            n_points += len(scan)
            prior = gnss.prior(scan.index / fleet.rate_hz, scan.T_world_sensor)
            run.gnss_fixes = gnss.fixes
            if fleet.window == 0:
                delay = t0 + scan.index / fleet.rate_hz - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            pub.publish(
                scan.points_xyz,
                scan.stamp_ns,
                intensity=scan.intensity,
                prior_pose=None if prior is None else prior[0],
                prior_covariance=None if prior is None else prior[1],
            )
            if fleet.window > 0:
                deadline = time.monotonic() + answer_timeout_s
                while not pub.wait_pending(fleet.window - 1, timeout=0.5):
                    if stop.is_set() or time.monotonic() > deadline:
                        break
        deadline = time.monotonic() + answer_timeout_s
        while not pub.flush(timeout=0.5) and not stop.is_set() and time.monotonic() < deadline:
            pass
    except Exception:  # a thread must not die silently: log it, the summary shows the gap
        log.exception("%s: the simulated drive failed", run.vehicle)
    finally:
        run.points_per_scan = n_points / max(1, len(run.truth))
        run.done.set()


def run_fleet(
    fleet: FleetSettings,
    publisher: PublisherSettings | None = None,
    *,
    session: str | None = None,
    progress: bool = True,
    connect_timeout_s: float = 30.0,
    answer_timeout_s: float = 180.0,
    stop: threading.Event | None = None,
    on_progress: Callable[[dict[str, PublisherStats]], None] | None = None,
) -> list[VehicleRun]:
    """Drive the fleet against the service and collect every vehicle's answers (module docstring).

    Parameters
    ----------
    fleet:
        What to simulate.
    publisher:
        How the vehicles reach the service (default ``PublisherSettings()``: ``RANDT_VEHICLE_*``).
    session:
        Session id for every vehicle (default: the UTC time).
    progress:
        A tqdm bar on stderr over all vehicles' scans: sent, acknowledged, rejected, dropped, lost.
    connect_timeout_s:
        How long to wait for a service to subscribe; ConnectionError after.
    answer_timeout_s:
        Longest wait for one answer under flow control, and for the last answers at the end.
    stop:
        Set it to end the drives early (Ctrl-C); the runs hold what was answered so far.
    on_progress:
        Called about twice a second with every vehicle's counters.

    Returns
    -------
    list[VehicleRun]
        One per vehicle, in fleet order.
    """
    from tqdm import tqdm

    publisher = publisher or PublisherSettings()
    stop = stop or threading.Event()
    session = session or default_session_id()
    town = Town.generate(fleet.town_seed)
    plans = plan_fleet(
        town,
        fleet.n_vehicles,
        seed=fleet.fleet_seed,
        route_length_m=fleet.route_length_m,
        rate_hz=fleet.rate_hz,
        shared=fleet.shared_routes,
    )
    lidar = Lidar64(n_azimuth=fleet.n_azimuth)
    runs = [VehicleRun(p.vehicle_id, session, fleet.gnss_of(v)) for v, p in enumerate(plans)]
    pubs: list[VehiclePublisher] = []
    try:
        for p, run in zip(plans, runs, strict=True):
            pubs.append(
                VehiclePublisher(
                    p.vehicle_id,
                    session,
                    settings=publisher,
                    queue_size=max(publisher.queue_size, fleet.window + 1),
                    answer_timeout_s=answer_timeout_s,
                    on_pose=run.keep_pose,
                )
            )
        deadline = time.monotonic() + connect_timeout_s
        for pub in pubs:
            if not pub.wait_connected(max(0.0, deadline - time.monotonic())):
                raise ConnectionError(
                    f"no service subscribed to {pub.scan_key} within {connect_timeout_s:g} s "
                    f"(Zenoh {publisher.mode}, connect {list(publisher.connect)}): is `randt serve` running?"
                )
        # (shared routes: each vehicle follows the one before it out of the depot)
        leaders = [None, *runs[:-1]] if fleet.shared_routes else [None] * len(runs)
        threads = [
            threading.Thread(
                target=_drive,
                args=(town, p, fleet, lidar, pub, run, stop, answer_timeout_s, leader),
                name=f"drive-{p.vehicle_id}",
                daemon=True,
            )
            for p, pub, run, leader in zip(plans, pubs, runs, leaders, strict=True)
        ]
        total = fleet.n_scans * fleet.n_vehicles
        bar = tqdm(
            total=total, unit="scan", desc="fleet", disable=not progress, file=sys.stderr, dynamic_ncols=True
        )
        for t in threads:
            t.start()
        try:
            while any(t.is_alive() for t in threads):
                for t in threads:
                    t.join(0.5 / len(threads))
                stats = {pub.vehicle: pub.stats() for pub in pubs}
                answered = sum(s.settled for s in stats.values())
                bar.update(answered - bar.n)
                bar.set_postfix(
                    sent=sum(s.sent for s in stats.values()),
                    ack=sum(s.acknowledged for s in stats.values()),
                    rejected=sum(s.rejected for s in stats.values()),
                    dropped=sum(s.dropped for s in stats.values()),
                    lost=sum(s.lost for s in stats.values()),
                    refresh=True,
                )
                if on_progress is not None:
                    on_progress(stats)
        except KeyboardInterrupt:
            stop.set()
            for t in threads:
                t.join(10)
            raise
        finally:
            bar.close()
    finally:
        for pub, run in zip(pubs, runs, strict=False):
            run.stats = pub.close(timeout=1.0)
    return runs


#: Column titles of :func:`summary_table`.
TABLE_HEADER = (
    f"{'vehicle':<10} {'gnss':<5} {'scans':>5} {'poses':>5} {'fallback':>8} {'rejected':>8} {'dropped':>7} "
    f"{'lost':>4} {'path_m':>7} {'ATE_m':>8} {'RPE_cm':>7} {'RPE_deg':>7} {'drift_%':>7}"
)


def summary_table(summaries: list[dict[str, Any]]) -> list[str]:
    """Lines of a per-vehicle table from :meth:`VehicleRun.summary` dicts (header first).

    ``dropped`` adds the publisher's own queue drops and the service's (error code ``dropped``);
    ``rejected`` counts the other errors. Errors print as ``-`` when a vehicle has under 3 poses;
    an ATE after a rigid fit (a session in its own frame) is marked ``*``.
    """
    lines = [TABLE_HEADER]
    for s in summaries:
        st = s["stats"]
        service_drops = st["rejected_codes"].get(ErrorCode.DROPPED, 0)
        e = s["errors"]

        def num(key: str, fmt: str, e: dict[str, Any] | None = e) -> str:
            return "-" if e is None or e[key] is None else format(e[key], fmt)

        ate = num("ate_m", ".3f") + ("*" if e is not None and e.get("aligned") else "")
        lines.append(
            f"{s['vehicle']:<10} {s.get('gnss', '-'):<5} {s['scans']:>5} {st['acknowledged']:>5} "
            f"{(e['n_fallback'] if e else 0):>8} {st['rejected'] - service_drops:>8} "
            f"{st['dropped'] + service_drops:>7} {st['lost']:>4} {num('path_length_m', '.1f'):>7} "
            f"{ate:>8} {num('rpe_cm', '.2f'):>7} {num('rpe_deg', '.3f'):>7} "
            f"{num('drift_pct', '.2f'):>7}"
        )
    return lines


# -- the fleet half: what the service's pose graph made of the drives ----------------------------


@dataclass(frozen=True)
class GraphVehicle:
    """One vehicle's drive as the pose graph corrected it (:func:`fleet_graph`).

    ``live_ate_m``: the ATE of the poses it was answered, in the shared map's frame (a session
    without GNSS: its own frame placed there by the graph's join, one rigid move; not joined:
    after a rigid fit, ``live_aligned``); ``corrected_ate_m``: of ``trajectory?corrected=true``,
    in the map the graph placed it in (``corrected_map``; after a rigid fit when that is not the
    shared map); ``loops``: loop closures of the graph that involve it; ``joined_at_seq`` /
    ``joined_after_m``: for a session without GNSS, its keyframe whose placement vote joined it
    to the shared map (the second that agreed), and how far it had driven then.
    """

    vehicle: str
    gnss: str
    live_ate_m: float | None
    live_aligned: bool
    corrected_ate_m: float | None
    corrected_map: str | None
    loops: int
    joined_at_seq: int | None
    joined_after_m: float | None


@dataclass(frozen=True)
class FleetGraph:
    """The shared map's pose graph after a fleet's drive: per vehicle, and the map's totals."""

    map: str
    vehicles: list[GraphVehicle]
    keyframes: int
    loops: int
    loops_between_sessions: int


def fleet_graph(client: Any, summaries: list[dict[str, Any]], map_name: str = "default") -> FleetGraph:
    """Score what the service's pose graph made of a simulated fleet's drives.

    Parameters
    ----------
    client:
        A :class:`randt.clients.rest.MapClient` of the service.
    summaries:
        :meth:`VehicleRun.summary` dicts (their ``truth`` rows).
    map_name:
        The shared map.
    """
    graph = client.graph(map_name)
    accepted = [lp for lp in graph["loops"] if lp["accepted"] and lp["source"] != "placement"]
    placements = [lp for lp in graph["loops"] if lp["accepted"] and lp["source"] == "placement"]
    out = []
    for s in summaries:
        v, session = s["vehicle"], s["session"]
        truth = np.array(s["truth"], dtype=np.float64).reshape(-1, 5)
        T_map_session = graph["joined"].get(f"{v}/{session}")
        live = client.trajectory_json(v, session)
        live_ate = _trajectory_ate(live, truth, None if T_map_session is None else np.asarray(T_map_session))
        in_shared = live.get("map") == map_name or T_map_session is not None
        corrected = client.trajectory_json(v, session, corrected=True)
        corrected_ate = None
        if corrected.get("corrected"):
            corrected_ate = _trajectory_ate(corrected, truth, align=corrected.get("map") != map_name)
        joined_seq = joined_m = None
        if T_map_session is not None:
            votes = [side[2] for lp in placements for side in (lp["a"], lp["b"]) if side[:2] == [v, session]]
            if votes:
                joined_seq = votes[min(1, len(votes) - 1)]
                upto = truth[truth[:, 0] <= joined_seq, 2:]
                joined_m = float(np.linalg.norm(np.diff(upto, axis=0), axis=1).sum())
        out.append(
            GraphVehicle(
                vehicle=v,
                gnss=s.get("gnss", "exact"),
                live_ate_m=live_ate if in_shared else _trajectory_ate(live, truth, align=True),
                live_aligned=not in_shared,
                corrected_ate_m=corrected_ate,
                corrected_map=corrected.get("map") if corrected.get("corrected") else None,
                loops=sum(v in (lp["a"][0], lp["b"][0]) for lp in accepted),
                joined_at_seq=joined_seq,
                joined_after_m=joined_m,
            )
        )
    return FleetGraph(
        map=map_name,
        vehicles=out,
        keyframes=len(graph["keyframes"]),
        loops=len(accepted),
        loops_between_sessions=sum(lp["a"][:2] != lp["b"][:2] for lp in accepted),
    )


def _matched(doc: dict[str, Any], truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A trajectory JSON's positions and the true ones of the same scans (``truth`` rows
    ``seq, stamp_s, x, y, z``, matched by stamp)."""
    stamps = np.array([p["stamp_s"] for p in doc["poses"]], dtype=np.float64)
    xyz = np.array([np.asarray(p["pose"])[:3, 3] for p in doc["poses"]], dtype=np.float64).reshape(-1, 3)
    rows = _rows_at(truth[:, 1], stamps)
    ok = rows >= 0
    return xyz[ok], truth[rows[ok], 2:]


def _trajectory_ate(
    doc: dict[str, Any], truth: np.ndarray, T: np.ndarray | None = None, *, align: bool = False
) -> float | None:
    """ATE of a trajectory JSON's poses against ``truth`` (:func:`_matched`), moved by ``T`` first
    or rigidly fitted (``align``); ``None`` with fewer than 3 scans matched."""
    xyz, ref = _matched(doc, truth)
    if T is not None:
        xyz = xyz @ T[:3, :3].T + T[:3, 3]
    return ate_m(xyz, ref, align=align) if len(xyz) >= 3 else None


def _rows_at(truth_stamps_s: np.ndarray, stamps_s: np.ndarray, tolerance_s: float = 1e-3) -> np.ndarray:
    """For each stamp, the row of the truth with the same stamp (within ``tolerance_s``), or -1."""
    order = np.argsort(truth_stamps_s)
    sorted_stamps = truth_stamps_s[order]
    i = np.clip(np.searchsorted(sorted_stamps, stamps_s), 1, max(1, len(sorted_stamps) - 1))
    lo = np.clip(i - 1, 0, len(sorted_stamps) - 1)
    hi = np.clip(i, 0, len(sorted_stamps) - 1)
    best = np.where(np.abs(sorted_stamps[lo] - stamps_s) <= np.abs(sorted_stamps[hi] - stamps_s), lo, hi)
    ok = np.abs(sorted_stamps[best] - stamps_s) <= tolerance_s
    return np.where(ok, order[best], -1)


def graph_table(result: FleetGraph) -> list[str]:
    """Lines of the per-vehicle table of :func:`fleet_graph` (header first), then the totals."""
    lines = [f"{'vehicle':<10} {'gnss':<5} {'live_ATE_m':>10} {'corrected_ATE_m':>15} {'loops':>5}  joined"]
    for g in result.vehicles:
        live = "-" if g.live_ate_m is None else f"{g.live_ate_m:.3f}" + ("*" if g.live_aligned else "")
        corr = "-" if g.corrected_ate_m is None else f"{g.corrected_ate_m:.3f}"
        if g.corrected_ate_m is not None and g.corrected_map != result.map:
            corr += "*"
        if g.joined_at_seq is not None:
            joined = f"{result.map}, at its scan {g.joined_at_seq} ({g.joined_after_m:.0f} m driven)"
        elif g.gnss == "none":
            joined = "not (yet): its own map"
        else:
            joined = "- (GNSS: in the shared map from its first scan)"
        lines.append(f"{g.vehicle:<10} {g.gnss:<5} {live:>10} {corr:>15} {g.loops:>5}  {joined}")
    lines.append(
        f"pose graph of map {result.map}: {result.keyframes} keyframes, {result.loops} loops closed "
        f"({result.loops_between_sessions} between sessions)"
    )
    pairs = np.array(
        [
            (g.live_ate_m, g.corrected_ate_m)
            for g in result.vehicles
            if g.live_ate_m is not None and not g.live_aligned and g.corrected_ate_m is not None
        ]
    ).reshape(-1, 2)
    if len(pairs) == len(result.vehicles):
        rms = np.sqrt(np.mean(np.square(pairs), axis=0))
        lines.append(
            f"fleet ATE in the shared map: live {rms[0]:.3f} m, corrected {rms[1]:.3f} m "
            "(RMS over the vehicles)"
        )
    return lines
