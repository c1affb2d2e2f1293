"""The ``randt`` command as a user runs it: a real subprocess, real files, real exit codes."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from core.io import read_cloud
from core.transforms import transform_error
from tests.data import require_data
from tests.pairs import car


def _randt(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "service.cli", *args], capture_output=True, text=True, timeout=300
    )


def test_register_json_on_the_car_pair(tmp_path) -> None:
    root = require_data("pairs/libpointmatcher_car")
    d = root / "pairs/libpointmatcher_car"
    out = tmp_path / "aligned.ply"
    proc = _randt(
        "register", str(d / "car_cloud401.csv"), str(d / "car_cloud400.csv"), "--json", "--output", str(out)
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 1, "--json prints exactly one JSON object"
    doc = json.loads(lines[0])
    assert {"T_target_source", "converged", "iterations", "fitness", "inlier_ratio", "time_s"} <= doc.keys()
    _, _, T_ref = car()
    err_m, err_deg = transform_error(np.array(doc["T_target_source"]), T_ref)
    assert err_m < 0.10 and err_deg < 0.3
    aligned = read_cloud(out)
    source = read_cloud(d / "car_cloud401.csv")
    assert aligned.n_points == source.n_points
    moved = source.xyz @ T_ref[:3, :3].T + T_ref[:3, 3]
    assert np.median(np.linalg.norm(aligned.xyz - moved, axis=1)) < 0.05


def test_register_with_init_file_and_icp_method(tmp_path) -> None:
    root = require_data("pairs/small_gicp")
    d = root / "pairs/small_gicp"
    proc = _randt(
        "register",
        str(d / "source.ply"),
        str(d / "target.ply"),
        "--init",
        str(d / "T_target_source.txt"),
        "--method",
        "icp-plane",
        "--json",
    )
    assert proc.returncode == 0, proc.stderr
    err_m, err_deg = transform_error(
        np.array(json.loads(proc.stdout)["T_target_source"]), np.loadtxt(d / "T_target_source.txt")
    )
    assert err_m < 0.03 and err_deg < 0.3


def test_errors_exit_nonzero_with_one_line(tmp_path) -> None:
    missing = _randt("register", str(tmp_path / "nope.pcd"), str(tmp_path / "nope2.pcd"))
    assert missing.returncode == 2
    assert missing.stderr.strip().count("\n") == 0 and "nope.pcd" in missing.stderr
    bad = tmp_path / "bad.xyz"
    bad.write_text("1 2\n3 4\n")
    proc = _randt("register", str(bad), str(bad))
    assert proc.returncode == 3, proc.stderr
    assert proc.stderr.startswith("randt: error:") and proc.stderr.strip().count("\n") == 0
    tiny = tmp_path / "tiny.npy"
    np.save(tiny, np.zeros((4, 3)))
    proc = _randt("register", str(tiny), str(tiny))
    assert proc.returncode == 4 and "need at least" in proc.stderr


def test_config_dumps_defaults() -> None:
    proc = _randt("config")
    assert proc.returncode == 0
    doc = json.loads(proc.stdout)
    assert doc["method"] == "randt" and doc["iqr_k"] == 1.5 and doc["n_neighbors"] == 7


def test_demo_main_job_reports_small_errors(tmp_path) -> None:
    """The README's first command: every method recovers the synthetic room's known transform."""
    import re

    proc = _randt("demo", "--data-dir", str(tmp_path / "no-data-here"))
    assert proc.returncode == 0, proc.stderr
    rows = re.findall(r"^\s+(\S+)\s+error\s+([\d.]+) cm\s+([\d.]+) deg", proc.stdout, flags=re.M)
    assert [r[0] for r in rows] == ["randt", "ndt", "icp-point", "icp-plane"]
    for method, cm, deg in rows:
        assert float(cm) < 2.0 and float(deg) < 0.2, f"{method}: {cm} cm {deg} deg"
    assert "no real data" in proc.stdout
