"""The soak's sampler, CSV and plot on a short run (bench/soak.py; the report's run is 10 min)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
from PIL import Image

from bench.soak import COLUMNS, run_soak


@pytest.mark.slow
def test_a_short_soak_samples_memory_latency_and_answers(tmp_path: Path) -> None:
    result = run_soak(
        0.4, vehicles=2, rate_hz=4.0, sample_s=4.0, lap_scans=12,
        csv_path=tmp_path / "soak.csv", plot_path=tmp_path / "soak.png",
    )  # fmt: skip
    assert len(result.rows) >= 5
    assert result.sent >= 2 * 4 * 20, result.sent  # two vehicles, 4 Hz, about 24 s
    assert result.poses > 0.8 * result.sent, (result.poses, result.sent, result.errors)
    assert result.unanswered == 0
    assert all(r["service_rss_mib"] > 50 for r in result.rows)  # a Python service with numpy: > 50 MiB
    assert sum(r["poses"] for r in result.rows) <= result.poses
    later = [r for r in result.rows[1:] if r["poses"]]
    assert later and all(0 < r["p50_ms"] <= r["p99_ms"] <= r["max_ms"] < 10_000 for r in later)
    # a session per lap: 12 scans at 4 Hz, so the 24 s run drove two laps per vehicle
    with open(tmp_path / "soak.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == COLUMNS and len(rows) == len(result.rows)
    with Image.open(tmp_path / "soak.png") as img:
        assert img.width > 400 and img.height > 400
