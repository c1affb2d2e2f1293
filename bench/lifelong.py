"""Days of the same fleet on the same streets: what grows once the streets are mapped.

Run from the repository root::

    python bench/lifelong.py --days 10 --vehicles 2 --seconds 30 --markdown

Each day is a fresh service process (bench/service.py's ``--one``: a real
:class:`~randt.service.runtime.Service`, the vehicles on Zenoh over loopback at 10 Hz, the pose
graph on) started on the data directory the day before left, ``RANDT_LOCALIZE=true``. The fleet
is bench/service.py's (town seed 1, fleet seed 3): every day the same routes, with other sensor
noise (``noise seed = 1000 (day - 1)``) and that day's session ids. Day 1 finds no map and maps
it, a survey: each vehicle's first sweep with the exact prior of a surveyed start, every session
admitted (a session refused at its first scan would open on a later one without a prior, in its
own frame). The days after, the fleet as it drives every day: a GNSS fix on every sweep
(``--gnss``: bench/service.py's ``noisy``, 0.5 m noise and a 1 m bias), admission on; they
localize on the map.

Printed per day: poses, localized, shed; the graph's keyframes and loops (totals); the data
directory on disk (MB: the graph's log and keyframe spill, the sessions' records, the map's
tiles); tiles and map points; each process's peak RSS (main, largest matcher, graph); CPU per sweep
of the service's processes; the live pose error against the simulator's truth (max, p99). Then
days 2 to N against day 1 (issue 57: within 10 %).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from common import git_line, machine_line, progress, run_json, table

HERE = Path(__file__).resolve().parent
SERVICE_BENCH = HERE / "service.py"


def _day_sweeps(sweeps: Path, day: int, args: argparse.Namespace) -> Path:
    """Day ``day``'s spool (simulated once, kept in ``sweeps``)."""
    spool = sweeps / f"day{day:02d}"
    gnss = "first" if day == 1 else args.gnss
    meta = {"vehicles": args.vehicles, "seconds": args.seconds, "link": args.link, "day": day, "gnss": gnss}
    meta_path = spool / "lifelong.json"
    if meta_path.exists() and json.loads(meta_path.read_text()) == meta:
        return spool
    progress(f"simulating day {day}: {args.vehicles} vehicle(s), {args.seconds:g} s")
    command = [
        sys.executable,
        str(SERVICE_BENCH),
        "--simulate-to",
        str(spool),
        "--vehicles",
        str(args.vehicles),
    ]
    command += ["--seconds", str(args.seconds), "--link", args.link, "--noise-seed", str(1000 * (day - 1))]
    command += ["--session", f"day{day:02d}", "--gnss", gnss]
    subprocess.run(command, check=True)
    meta_path.write_text(json.dumps(meta))
    return spool


def _drive_day(spool: Path, before: Path | None, after: Path, args: argparse.Namespace) -> dict[str, Any]:
    """One day's drive on a fresh service started on ``before`` (none: an empty one, the survey
    with every session admitted), its data directory kept in ``after``."""
    command = [sys.executable, str(SERVICE_BENCH), "--one", str(args.vehicles), "--spool", str(spool)]
    command += ["--link", args.link, "--graph", "on", "--localize", "on", "--keep-data", str(after)]
    if before is not None:
        command += ["--data-from", str(before)]
    else:
        command += ["--no-admission"]
    return run_json(command, "the day's run")


def _mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 1e6 if path.exists() else 0.0


def _on_disk(data: Path) -> dict[str, float]:
    """The data directory's size by part (MB) and the default map's tiles."""
    parts = {name: _mb(data / name) for name in ("graph", "sessions", "maps")}
    parts["total"] = _mb(data)
    parts["tiles"] = float(len(list((data / "maps" / "default").glob("*.pcd"))))
    return parts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--days", type=int, default=10)
    parser.add_argument("--vehicles", type=int, default=2)
    parser.add_argument(
        "--seconds", type=float, default=30.0, help="each vehicle's drive a day (10 Hz, 10 m/s)"
    )
    parser.add_argument("--link", choices=["default", "raw"], default="default")
    parser.add_argument(
        "--gnss",
        choices=["first", "noisy"],
        default="noisy",
        help="the priors of days 2 to N (bench/service.py's --gnss); day 1 has first",
    )
    parser.add_argument("--sweeps", type=Path, help="keep each day's simulated sweeps here and reuse them")
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    print(f"Command: python bench/lifelong.py {' '.join(sys.argv[1:])}")
    print(machine_line({}, single_threaded=False))
    print(git_line())
    rows, days = [], []
    with tempfile.TemporaryDirectory(prefix="randt-lifelong-") as tmp:
        sweeps = args.sweeps or Path(tmp) / "sweeps"
        before: Path | None = None
        for day in range(1, args.days + 1):
            spool = _day_sweeps(sweeps, day, args)
            after = Path(tmp) / f"data-day{day:02d}"
            progress(f"day {day}: the fleet drives")
            r = _drive_day(spool, before, after, args)
            r["disk"] = _on_disk(after)
            days.append(r)
            if before is not None:
                subprocess.run(["rm", "-rf", str(before)], check=True)  # (only the last day's is needed)
            before = after
            d = r["disk"]
            rows.append(
                [
                    str(day),
                    f"{r['poses']} / {r['sent']}",
                    str(r["localized"]),
                    f"{r['dropped']} / {r['refused']} / {r['other_errors'] - r['refused']}",
                    f"{r['graph_total_keyframes']} / {r['graph_total_loops']}",
                    f"{d['total']:.0f} ({d['graph']:.0f} / {d['sessions']:.0f} / {d['maps']:.0f})",
                    f"{d['tiles']:.0f} / {r['map_points']:,}",
                    f"{r['rss_main_mib']:.0f} / {r['rss_matcher_mib']:.0f} / {r['rss_graph_mib']:.0f}",
                    f"{r['cpu_total_ms']:.1f}",
                    f"{r['err_max_cm']:.1f} / {r['err_p99_cm']:.1f}",
                ]
            )
            print(" | ".join(rows[-1]), flush=True)
    headers = [
        "day",
        "poses / sent",
        "localized",
        "shed / refused / other errors",
        "graph keyframes / loops",
        "data dir MB (graph / sessions / maps)",
        "tiles / map points",
        "peak RSS MiB (main / matcher / graph)",
        "CPU ms a sweep",
        "error cm max / p99",
    ]
    print(table(headers, rows, args.markdown))
    _growth(days)


def _growth(days: list[dict[str, Any]]) -> None:
    """Days 2 to N against day 1: the largest ratio of each measure (issue 57: within 1.1)."""
    if len(days) < 2:
        return
    first, later = days[0], days[1:]
    measures = {
        "graph keyframes": lambda r: r["graph_total_keyframes"],
        "graph on disk (log, spill)": lambda r: r["disk"]["graph"],
        "tile bytes": lambda r: r["disk"]["maps"],
        "main RSS": lambda r: r["rss_main_mib"],
        "matcher RSS": lambda r: r["rss_matcher_mib"],
        "graph RSS": lambda r: r["rss_graph_mib"],
        "sessions on disk": lambda r: r["disk"]["sessions"],
    }
    print("\nDays 2 to N against day 1 (largest ratio; issue 57: within 1.10 but the sessions' records):")
    for name, of in measures.items():
        base = float(of(first))
        worst = max(float(of(r)) for r in later)
        ratio = worst / base if base else float("nan")
        print(f"- {name}: day 1 {base:.1f}, days 2-{len(days)} at most {worst:.1f} = {ratio:.2f}x")
    grown = (later[-1]["disk"]["sessions"] - first["disk"]["sessions"]) * 1e6
    poses = sum(r["poses"] for r in later)
    points = later[-1]["map_points"] / first["map_points"] - 1.0
    print(
        f"- the sessions' records: +{grown / 1e6:.1f} MB over days 2-{len(days)} for their {poses:,} poses, "
        f"{grown / max(poses, 1):.0f} B a pose; the map's points +{100 * points:.2f} % (what the map lacked)"
    )


if __name__ == "__main__":
    main()
