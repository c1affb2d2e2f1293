"""``bench/paper.py`` in its tiny configuration (issue 18's smoke test): the command that
regenerates the paper section of docs/benchmarks.md runs end to end on the real data, writes its
section and figures, and its numbers are sane (RANDT places the protocol's trials within the
success bounds; the PDU reading on the equalization grid is 1 by construction).

It needs the bench peers (small_gicp, KISS-ICP, Open3D: the test extra carries them) and the
shared data (skipped when absent, failed under ``CI=true``).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.data import require_data

REPO = Path(__file__).resolve().parents[1]


def _rows(section: str, after: str) -> dict[str, list[str]]:
    """The rows of the first markdown table after the line starting with ``after``, by first cell."""
    lines = section.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(after))
    rows: dict[str, list[str]] = {}
    for line in lines[start + 1 :]:
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            if cells[0] not in ("method", "reading") and not set(cells[0]) <= {"-"}:
                rows[cells[0]] = cells
        elif rows:
            break
    return rows


def test_the_paper_benchmark_runs_in_its_tiny_configuration(tmp_path: Path) -> None:
    require_data(
        "randt_velodyne/velodyne",
        "kitti00/velodyne",
        "kitti00/poses.txt",
        "objects/modelnet40",
        "objects/bunny",
    )
    done = subprocess.run(
        [sys.executable, "bench/paper.py", "--tiny", "--out", str(tmp_path)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    section = (tmp_path / "paper.md").read_text()
    assert section.startswith("<!-- bench.paper:begin") and section.rstrip().endswith(
        "<!-- bench.paper:end -->"
    )
    for name in ("RANDT Velodyne (1 trials):", "KITTI 00 (1 trials):"):
        rows = _rows(section, name)
        assert {"RANDT", "small_gicp VGICP", "Open3D ICP plane"} <= rows.keys()
        randt = rows["RANDT"]
        assert randt[1] == "1/1", f"{name} RANDT failed the protocol trial: {randt}"
        assert float(randt[4]) < 0.05  # RMSE of the placement against the truth, metres
        assert float(rows["small_gicp VGICP"][8]) == 1.0  # the time ratio's reference
    readings = _rows(section, "#### PDU readings")
    on_grid = readings["occupied voxels at 0.2 m"]
    assert float(on_grid[1]) == 1.0  # the map on its own equalization grid: 1 by construction
    assert float(on_grid[2]) < 0.0  # the raw sweeps are far from uniform
    figures = sorted(p.name for p in tmp_path.glob("*.png"))
    assert figures == sorted(
        [
            "fig9_error_vs_pdu.png",
            "pdu_vs_voxel.png",
            "sweep_noise.png",
            "sweep_outlier.png",
            "sweep_overlap.png",
        ]
    )
    for name in figures:
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
