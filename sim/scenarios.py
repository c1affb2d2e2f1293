"""End-to-end scenarios on the simulator with exact ground truth: a mapping fleet.

:func:`run_mapping_fleet` drives a fleet through a town on overlapping closed routes (each
vehicle more than one lap: loops within a session, and streets shared between sessions), runs one
incremental matcher (randt.core.odometry) per vehicle on its sweeps, feeds a keyframe every
``keyframe_distance_m`` with a GNSS fix (randt.sim.gnss; some vehicles have none) into
:class:`randt.core.fleet_map.FleetMapper`, and scores the result against the simulator's poses:

- the shared map's ATE: the RMS keyframe position error after one rigid alignment of the whole
  map to the truth (the map's own consistency, as evo's ``--align``; a GNSS bias common to the
  fleet is not the map's shape), and without alignment (absolute, bounded by the GNSS bias), for
  the graph and for odometry only, where each GNSS session is placed by the same first-fixes fit
  the mapper uses and a session without GNSS is not in the map at all;
- every loop verification: correct when the relative pose found is within 1 m / 3 deg of the
  true one; a candidate is a true place when the keyframes are within ``true_loop_m``. Precision:
  correct among accepted; recall: accepted and correct among the true places verified.

``bench/fleet_map.py`` runs the issue's full-size fleet; ``tests/sim/test_scenarios.py`` a small one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from randt.core.fleet_map import FleetMapper, FleetMapSettings, Key, LoopRecord, level
from randt.core.odometry import MATCHER_REGISTRATION, IncrementalMatcher, MatcherSettings
from randt.core.transforms import invert, transform_error, umeyama
from randt.core.voxel import voxel_downsample
from randt.sim.drive import Motion, plan_fleet, simulate_fleet
from randt.sim.gnss import GnssReceiver
from randt.sim.lidar import Lidar64
from randt.sim.town import Town

__all__ = ["MappingRun", "run_mapping_fleet"]


@dataclass
class MappingRun:
    """What :func:`run_mapping_fleet` measured."""

    sessions: list[str]
    without_gnss: list[str]
    placed: list[str]
    travel_m: float
    n_keyframes: int
    truth: dict[Key, np.ndarray]
    graph: dict[Key, np.ndarray]
    odometry_only: dict[Key, np.ndarray]
    loops: list[LoopRecord]
    loop_truth: list[bool]
    loop_correct: list[bool]
    mapper: FleetMapper
    times_s: dict[str, float] = field(default_factory=dict)

    @staticmethod
    def ate_m(poses: dict[Key, np.ndarray], truth: dict[Key, np.ndarray], *, align: bool = True) -> float:
        """RMS position error of ``poses`` (after one rigid fit of all of them when ``align``)."""
        if not poses:
            return float("nan")
        est = np.array([T[:3, 3] for T in poses.values()])
        ref = np.array([truth[k][:3, 3] for k in poses])
        if align and len(est) >= 3:
            T, _ = umeyama(est, ref)
            est = est @ T[:3, :3].T + T[:3, 3]
        return float(np.sqrt(np.mean(np.sum((est - ref) ** 2, axis=1))))

    @property
    def ate_graph_m(self) -> float:
        return self.ate_m(self.graph, self.truth)

    @property
    def ate_odometry_m(self) -> float:
        return self.ate_m(self.odometry_only, self.truth)

    @property
    def accepted(self) -> int:
        return sum(r.accepted for r in self.loops)

    @property
    def false_accepted(self) -> int:
        return sum(r.accepted and not ok for r, ok in zip(self.loops, self.loop_correct, strict=True))

    @property
    def precision(self) -> float:
        return 1.0 - self.false_accepted / self.accepted if self.accepted else float("nan")

    @property
    def recall(self) -> float:
        true = sum(self.loop_truth)
        hits = sum(
            r.accepted and t and ok
            for r, t, ok in zip(self.loops, self.loop_truth, self.loop_correct, strict=True)
        )
        return hits / true if true else float("nan")


def run_mapping_fleet(
    *,
    n_vehicles: int = 3,
    laps: float = 1.3,
    route_length_m: float = 400.0,
    without_gnss: tuple[int, ...] = (2,),
    speed_mps: float = 10.0,
    rate_hz: float = 10.0,
    lidar: Lidar64 | None = None,
    seed: int = 0,
    keyframe_distance_m: float = 10.0,
    sweep_voxel_m: float = 0.2,
    gnss_noise_m: float = 1.0,
    gnss_bias_m: float = 2.0,
    gnss_outage_s: tuple[float, float] | None = (20.0, 35.0),
    true_loop_m: float = 10.0,
    settings: FleetMapSettings | None = None,
    sim_workers: int = 1,
) -> MappingRun:
    """Simulate, map and score a fleet (module docstring). Vehicle ``v`` has no GNSS when ``v`` is
    in ``without_gnss``; the others have ``gnss_noise_m`` white noise, a ``gnss_bias_m`` wandering
    bias, 1 % multipath jumps and one outage ``gnss_outage_s`` (seconds after their start).
    ``sim_workers``: processes per vehicle that ray cast its sweeps ahead, beside the odometry and
    the mapping (:func:`randt.sim.drive.simulate`'s ``workers``; 0: in this process, one at a time)."""
    town = Town.generate(seed)
    fleet = plan_fleet(town, n_vehicles, seed=seed, route_length_m=route_length_m, rate_hz=rate_hz)
    n_scans = int(np.ceil(laps * min(Motion(v.route, speed_mps).lap_time_s for v in fleet) * rate_hz))
    names = [v.vehicle_id for v in fleet]
    no_gnss = [names[i] for i in without_gnss if i < n_vehicles]
    outages = () if gnss_outage_s is None else (gnss_outage_s,)
    receivers = {
        name: GnssReceiver(
            seed=seed * 1000 + i, noise_sigma_m=gnss_noise_m, bias_sigma_m=gnss_bias_m, outages=outages
        )
        for i, name in enumerate(names)
        if name not in no_gnss
    }
    levels = (16.0, 8.0, 4.0, 2.0, 1.0)  # the service's, tied to a 0.2 m map
    matchers = {
        n: IncrementalMatcher(MatcherSettings(voxel_sizes_m=levels), MATCHER_REGISTRATION) for n in names
    }
    mapper = FleetMapper(settings)
    truth: dict[Key, np.ndarray] = {}
    last_kf: dict[str, np.ndarray] = {}
    odo_poses: dict[Key, np.ndarray] = {}
    fixes: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {n: [] for n in names}
    times = {"simulate": 0.0, "odometry": 0.0, "mapping": 0.0}
    t0 = time.perf_counter()
    for name, scan in simulate_fleet(
        town, n_vehicles, n_scans=n_scans, seed=seed, route_length_m=route_length_m,
        rate_hz=rate_hz, speed_mps=speed_mps, lidar=lidar, deskewed=True, workers=sim_workers,
    ):  # fmt: skip
        t1 = time.perf_counter()
        times["simulate"] += t1 - t0
        pts = voxel_downsample(scan.points_xyz.astype(np.float64), sweep_voxel_m)
        T = matchers[name].register_scan(pts).T_world_sensor
        t2 = time.perf_counter()
        times["odometry"] += t2 - t1
        prev = last_kf.get(name)
        if prev is None or np.linalg.norm(T[:3, 3] - prev[:3, 3]) >= keyframe_distance_m:
            last_kf[name] = T
            fix = None
            if name in receivers:
                got = receivers[name].fix(scan.index / rate_hz, scan.T_world_sensor[:3, 3])
                fix = None if got is None else (got.position_xyz, got.covariance)
            key = mapper.add_keyframe(name, T, pts, fix)
            truth[key] = scan.T_world_sensor
            odo_poses[key] = T
            if fix is not None:
                fixes[name].append((T[:3, 3], fix[0]))
        t0 = time.perf_counter()
        times["mapping"] += t0 - t2
    odometry_only: dict[Key, np.ndarray] = {}
    s = mapper.settings
    for name in names:
        pairs = _first_fixes(fixes[name], s.gnss_alignment_m, s.gnss_min_fixes)
        if pairs is None:
            continue
        Tw, _ = umeyama(pairs[0], pairs[1])
        Tw = level(Tw)  # the mapper's own GNSS placement
        odometry_only.update({k: Tw @ T for k, T in odo_poses.items() if k[0] == name})
    graph = mapper.poses()
    loop_truth = [
        bool(np.linalg.norm(truth[r.a][:3, 3] - truth[r.b][:3, 3]) < true_loop_m) for r in mapper.loops
    ]
    loop_correct = []
    for r in mapper.loops:
        dt, dr = transform_error(r.T_b_a, invert(truth[r.b]) @ truth[r.a])
        loop_correct.append(bool(dt < 1.0 and dr < 3.0))
    travel = sum(
        float(
            np.sum(
                np.linalg.norm(np.diff([truth[k][:3, 3] for k in sorted(truth) if k[0] == n], axis=0), axis=1)
            )
        )
        for n in names
    )
    return MappingRun(
        sessions=names, without_gnss=no_gnss, placed=mapper.placed_sessions(), travel_m=travel,
        n_keyframes=len(truth), truth=truth, graph=graph, odometry_only=odometry_only,
        loops=list(mapper.loops), loop_truth=loop_truth, loop_correct=loop_correct, mapper=mapper,
        times_s=times,
    )  # fmt: skip


def _first_fixes(
    fixes: list[tuple[np.ndarray, np.ndarray]], span_m: float, min_fixes: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """The first fixes whose odometry positions span ``span_m`` (the mapper's placement rule)."""
    for n in range(min_fixes, len(fixes) + 1):
        odo = np.array([f[0] for f in fixes[:n]])
        if float(np.linalg.norm(odo.max(axis=0) - odo.min(axis=0))) >= span_m:
            return odo, np.array([f[1] for f in fixes[:n]])
    return None
