"""Issue 32's unmapped-town case: a session that drives where the shared map says something else.

Run from the repository root::

    python bench/unmapped_town.py [--good 120] [--bad 60] [--markdown]

One simulated vehicle (randt.sim.drive, the 64-beam LiDAR with 1000 firings per revolution) sends
``--good`` sweeps of town 0 along a 400 m loop, its true pose as the prior of its first sweep
(the shared map ``default``), then ``--bad`` sweeps of town 5 along the same route: a town the map
never saw, where the map holds town 0's surfaces. A real session manager (matcher processes, the
pose graph off) answers each sweep before the next is sent (none shed).

Reported: every answer from five sweeps before the switch on (status and position error against
the truth), the ``ok`` poses after the switch and their largest error, and the shared map's
points more than 0.3 m from town 0's true surfaces before the switch and at the end (issue 32's
done-means: no ``ok`` pose more than 0.5 m off, none of them added).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import common
import numpy as np
from common import git_line, heading, machine_line, progress, table

del common

TOWN_MAPPED, TOWN_NEVER_MAPPED = 0, 5
OFF_M = 0.3


def run(n_good: int, n_bad: int) -> dict[str, object]:
    from randt.service.metrics import ServiceMetrics
    from randt.service.sessions import SessionManager
    from randt.service.settings import ServiceSettings
    from randt.service.store import Store
    from randt.sim.drive import plan_fleet, simulate
    from randt.sim.lidar import Lidar64
    from randt.sim.town import Town
    from randt.wire.messages import ErrorMessage, PoseMessage, encode, scan_from_arrays

    mapped, other = Town.generate(TOWN_MAPPED), Town.generate(TOWN_NEVER_MAPPED)
    plan = plan_fleet(mapped, 1, seed=0, route_length_m=400.0)[0]
    lidar = Lidar64(n_azimuth=1000, max_range_m=70.0)
    progress(f"simulating {n_good} sweeps of town {TOWN_MAPPED} and {n_bad} of town {TOWN_NEVER_MAPPED}")

    def drive(town: Town) -> list:
        return list(
            simulate(
                town,
                plan.route,
                n_scans=n_good + n_bad,
                seed=1,
                lidar=lidar,
                start_s_m=plan.start_s_m,
                workers=2,
            )
        )

    scans = drive(mapped)[:n_good] + drive(other)[n_good:]
    truth = {s.index: s.T_world_sensor for s in scans}
    prior_cov = np.diag([1e-4] * 3 + [1e-5] * 3)
    with tempfile.TemporaryDirectory(prefix="randt-unmapped-") as tmp:
        out: list[object] = []
        settings = ServiceSettings(data_dir=Path(tmp), flush_interval_s=0.3, graph=False, capacity_target=0)
        mgr = SessionManager(settings, Store(Path(tmp)), out.append, ServiceMetrics())
        try:
            mgr.wait_matchers(300)

            def answered() -> int:
                return sum(isinstance(m, PoseMessage | ErrorMessage) for m in list(out))

            def map_off() -> int:
                mgr.flush()
                xyz = np.concatenate([t.points for t in mgr.maps["default"].tiles()]).astype(np.float64)
                return int((mapped.surface_distance(xyz) > OFF_M).sum())

            off_before = 0
            for s in scans:
                if s.index == n_good:
                    off_before = map_off()
                first = s.index == 0
                message = scan_from_arrays(
                    "car", "d1", s.index, s.stamp_ns, s.points_xyz,
                    prior_pose=s.T_world_sensor if first else None,
                    prior_covariance=prior_cov if first else None,
                )  # fmt: skip
                n = answered()
                mgr.submit("car", encode(message))
                while answered() < n + 1:
                    time.sleep(0.005)
            off_after = map_off()
        finally:
            mgr.stop()
    rows: list[tuple[int, str, float | None]] = []
    for m in out:
        if isinstance(m, PoseMessage) and m.seq >= n_good - 5:
            err = float(np.linalg.norm(np.reshape(m.pose, (4, 4))[:3, 3] - truth[m.seq][:3, 3]))
            rows.append((m.seq, m.status, err))
        elif isinstance(m, ErrorMessage) and m.seq is not None and m.seq >= n_good - 5:
            rows.append((m.seq, m.code, None))
    ok_after = [e for seq, st, e in rows if st == "ok" and seq >= n_good and e is not None]
    return {
        "rows": rows,
        "ok_after": len(ok_after),
        "ok_after_err_max_m": max(ok_after, default=float("nan")),
        "off_before": off_before,
        "off_after": off_after,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--good", type=int, default=120, help="sweeps of the mapped town first")
    parser.add_argument("--bad", type=int, default=60, help="then sweeps of a town never mapped")
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    print(machine_line({}, single_threaded=False))
    print(git_line())
    r = run(args.good, args.bad)
    print(heading("Answers from five sweeps before the switch", args.markdown))
    answers = r["rows"]
    assert isinstance(answers, list)
    print(
        table(
            ["seq", "answer", "position error m"],
            [[str(q), st, "" if e is None else f"{e:.2f}"] for q, st, e in answers],
            args.markdown,
        )
    )
    print(heading("Summary", args.markdown))
    print(
        table(
            ["ok poses after the switch", "their error max m", f"map points > {OFF_M} m off: before / after"],
            [
                [
                    str(r["ok_after"]),
                    f"{r['ok_after_err_max_m']:.2f}",
                    f"{r['off_before']:,} / {r['off_after']:,}",
                ]
            ],
            args.markdown,
        )
    )


if __name__ == "__main__":
    main()
