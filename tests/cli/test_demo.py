"""``randt demo`` as a new user runs it: a subprocess, the printed summary, the tiles, the REST API.

The demo is shortened to 2 simulated seconds per vehicle (20 sweeps each); it then keeps serving,
so the test queries the endpoints it advertised, uses ``randt tiles`` against them, and stops it
with Ctrl-C (SIGINT) as a user would.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from cli.errors import ExitCode
from clients.rest import MapClient
from core.io import read_cloud
from tests.service.conftest import free_port

VEHICLES = 3
DURATION_S = 2.0
ROW = re.compile(
    r"^(sim\d{3})\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)$"
)


def _read_until(proc: subprocess.Popen[str], marker: str, timeout_s: float) -> list[str]:
    """Lines of ``proc``'s stdout up to the one containing ``marker`` (fails on timeout or exit)."""
    lines: list[str] = []
    deadline = time.monotonic() + timeout_s
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            if proc.poll() is not None:
                break
            continue
        lines.append(line.rstrip("\n"))
        if marker in line:
            return lines
    pytest.fail(f"no {marker!r} within {timeout_s} s; output so far:\n" + "\n".join(lines))


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The running demo: (process, printed lines, data dir, base URL); SIGINT at the end."""
    data = tmp_path_factory.mktemp("demo") / "data"
    hport, zport = free_port(), free_port()
    proc = subprocess.Popen(
        [
            sys.executable, "-m", "cli", "demo",
            "--vehicles", str(VEHICLES), "--duration", str(DURATION_S),
            "--data-dir", str(data), "--http-port", str(hport), "--zenoh-port", str(zport), "--no-progress",
        ],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1, start_new_session=True,
    )  # fmt: skip
    try:
        lines = _read_until(proc, "serving until Ctrl-C", 240)
        yield proc, lines, data, f"http://127.0.0.1:{hport}"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)


def test_demo_summary_meets_thresholds(demo) -> None:
    _, lines, data, base = demo
    rows = [m.groups() for line in lines if (m := ROW.match(line))]
    assert [r[0] for r in rows] == ["sim000", "sim001", "sim002"], "\n".join(lines)
    n_scans = round(DURATION_S * 10)
    for vehicle, scans, poses, fallback, rejected, dropped, lost, path, ate, rpe_cm, rpe_deg, drift in rows:
        assert int(scans) == n_scans and int(poses) == n_scans, f"{vehicle}: every scan got a pose"
        assert int(rejected) == int(dropped) == int(lost) == 0, f"{vehicle}: flow control, nothing dropped"
        assert int(fallback) <= 1, f"{vehicle}: {fallback} fallbacks"
        assert abs(float(path) - 6.0 * DURATION_S * (n_scans - 1) / n_scans) < 0.5, f"{vehicle}: 6 m/s"
        # against exact ground truth: a few cm over ~11 m (the first pose is the 2 cm prior itself)
        assert float(ate) < 0.10, f"{vehicle}: ATE {ate} m"
        assert float(rpe_cm) < 3.0 and float(rpe_deg) < 0.1, f"{vehicle}: RPE {rpe_cm} cm {rpe_deg} deg"
        assert float(drift) < 1.5, f"{vehicle}: drift {drift} %"
    text = "\n".join(lines)
    m = re.search(r"map default: (\d+) tiles, (\d+) points, PDU (-?[\d.]+)", text)
    assert m, text
    n_tiles, n_points, map_pdu = int(m[1]), int(m[2]), float(m[3])
    assert n_tiles > 20 and n_points > 100_000
    assert 0.0 < map_pdu <= 1.0, "density equalization makes the map far more uniform than raw sweeps"
    tiles_dir = data / "maps" / "default"
    assert f"tiles (Autoware layout): {tiles_dir}" in text
    assert f"viewer: {base}/" in text
    # the tiles on disk are what the summary counted
    pcds = sorted(tiles_dir.glob("*.pcd"))
    assert len(pcds) == n_tiles
    assert sum(read_cloud(p).n_points for p in pcds) == n_points
    meta = yaml.safe_load((tiles_dir / "pointcloud_map_metadata.yaml").read_text())
    assert meta["x_resolution"] == meta["y_resolution"] == 20
    assert {k for k in meta if k.endswith(".pcd")} == {p.name for p in pcds}


def test_demo_rest_endpoints_it_advertised(demo) -> None:
    _, lines, _, base = demo
    advertised = next(line for line in lines if line.startswith("REST: ")).split()[1:]
    assert f"{base}/status" in advertised and f"{base}/maps/default/tiles" in advertised
    with MapClient(base) as api:
        status = api.status()
        assert len(status["sessions"]) == VEHICLES
        assert all(s["scans"] == round(DURATION_S * 10) for s in status["sessions"])
        sessions = api.sessions()
        assert sorted(s["vehicle"] for s in sessions) == ["sim000", "sim001", "sim002"]
        assert all(s["map"] == "default" and s["frame"] == "map" for s in sessions)
        s0 = sessions[0]
        stamps, poses = api.trajectory(s0["vehicle"], s0["session"])
        assert poses.shape == (round(DURATION_S * 10), 4, 4)
        assert np.all(np.diff(stamps) > 0)
        index = api.tiles("default")
        assert all(0.0 < t["pdu"] <= 1.0 for t in index["tiles"] if t["points"] > 1000)


def test_randt_tiles_download_and_export_against_the_demo(demo, tmp_path) -> None:
    _, _, data, base = demo
    store = data / "maps" / "default"

    def tiles(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "cli", "tiles", *args, "--url", base],
            capture_output=True,
            text=True,
            timeout=120,
        )

    out = tmp_path / "map"
    first = tiles("download", "default", str(out))
    assert first.returncode == 0, first.stderr
    n_store = len(list(store.glob("*.pcd")))
    assert f"{n_store} tiles ({n_store} downloaded, 0 unchanged)" in first.stdout
    for p in sorted(store.glob("*.pcd")):
        got, want = read_cloud(out / p.name), read_cloud(p)
        np.testing.assert_array_equal(got.xyz, want.xyz)
    meta = yaml.safe_load((out / "pointcloud_map_metadata.yaml").read_text())
    assert {k for k in meta if k.endswith(".pcd")} == {p.name for p in store.glob("*.pcd")}
    again = tiles("download", "default", str(out))
    assert f"({0} downloaded, {n_store} unchanged)" in again.stdout, "ETags: nothing changed"
    ply = tmp_path / "default.ply"
    export = tiles("export", "default", str(ply))
    assert export.returncode == 0, export.stderr
    n = sum(read_cloud(p).n_points for p in store.glob("*.pcd"))
    assert export.stdout.startswith(f"{n} points") and read_cloud(ply).n_points == n
    missing = tiles("trajectory", "nobody", "nothing")
    assert missing.returncode == 2 and "404" in missing.stderr


def test_randt_tiles_listings_against_the_demo(demo, tmp_path) -> None:
    from typer.testing import CliRunner

    from cli.main import app
    from core.io import read_kitti_poses

    _, _, data, base = demo
    run = CliRunner().invoke
    sessions = run(app, ["tiles", "sessions", "--url", base])
    assert sessions.exit_code == 0, sessions.output
    rows = [line.split() for line in sessions.output.splitlines()[1:]]
    assert [r[0].split("/")[0] for r in rows] == ["sim000", "sim001", "sim002"]
    assert all(r[2] == "default" and int(r[3]) == round(DURATION_S * 10) for r in rows)
    vehicle, session = rows[0][0].split("/")
    out = tmp_path / "sim000.txt"
    traj = run(app, ["tiles", "trajectory", vehicle, session, "--out", str(out), "--url", base])
    assert traj.exit_code == 0, traj.output
    assert read_kitti_poses(out).shape == (round(DURATION_S * 10), 4, 4)
    maps = run(app, ["tiles", "maps", "--url", base])
    n_pcd = len(list((data / "maps/default").glob("*.pcd")))
    assert re.search(rf"^default\s+{n_pcd}\s+\d+$", maps.output, flags=re.M), maps.output
    listing = run(app, ["tiles", "list", "default", "--url", base])
    assert len(listing.output.splitlines()) == 1 + n_pcd


def test_demo_stops_cleanly_on_ctrl_c(demo) -> None:
    """Last in this module: the other tests use the running demo. Ctrl-C in a terminal signals the
    whole process group (the matcher processes too): one line, no traceback, the data kept."""
    proc, _, data, _ = demo
    os.killpg(proc.pid, signal.SIGINT)
    assert proc.wait(60) == ExitCode.INTERRUPTED == 130  # as the README's table says
    err = proc.stderr.read() if proc.stderr else ""
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert "randt demo: stopping" in err
    assert (data / "sessions").is_dir() and len(list(Path(data, "sessions").iterdir())) == VEHICLES


def test_demo_shows_the_viewer_first_and_removes_its_temporary_data(tmp_path: Path) -> None:
    """Without --data-dir: the viewer's URL comes before the fleet starts, and nothing is left behind."""
    hport, zport = free_port(), free_port()
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    proc = subprocess.run(
        [
            sys.executable, "-m", "cli", "demo", "--vehicles", "1", "--duration", "0.5", "--exit",
            "--http-port", str(hport), "--zenoh-port", str(zport), "--no-progress",
        ],
        capture_output=True, text=True, timeout=300, env={**os.environ, "TMPDIR": str(tmp)},
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    base = f"http://127.0.0.1:{hport}"
    viewer = next(i for i, line in enumerate(lines) if line.startswith(f"viewer: {base}/"))
    fleet = next(i for i, line in enumerate(lines) if line.startswith("simulating 1 vehicles"))
    assert viewer < fleet, "the viewer's URL is printed before the fleet starts"
    warm = next(i for i, line in enumerate(lines) if line.startswith("warming up the matcher processes"))
    assert viewer < warm < fleet and re.search(r"\.\.\. ready in \d+ s$", lines[warm]), lines[warm]
    # --exit: the service stops after the summary, so no link to it and no removed folder is shown
    summary = lines[next(i for i, line in enumerate(lines) if line.startswith("map default:")) :]
    assert not [line for line in summary if base in line or "REST" in line], summary
    assert "tiles: removed with the temporary folder at exit (keep them with --data-dir)" in summary
    data = re.search(r"data in (\S+) \(temporary, removed at exit", proc.stdout)
    assert data and Path(data[1]).parent == tmp, proc.stdout
    rows = [m.groups() for line in lines if (m := ROW.match(line))]
    assert [(r[0], int(r[1]), int(r[2])) for r in rows] == [("sim000", 5, 5)], proc.stdout
    assert list(tmp.iterdir()) == [], "the temporary data directory is removed at exit"
