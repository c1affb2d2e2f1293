"""The vehicle example of docs/clients.md, run as written against a real router and service."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

from randt.service.runtime import Service
from randt.service.settings import ServiceSettings
from tests.clients.conftest import Router

DOC = Path(__file__).resolve().parents[2] / "docs" / "clients.md"
MARKER = "<!-- tested: tests/clients/test_docs_example.py"


def example_code() -> str:
    """The first ```python block after the marker comment."""
    text = DOC.read_text()
    after = text[text.index(MARKER) :]
    m = re.search(r"```python\n(.*?)```", after, flags=re.S)
    assert m is not None, "the marked example has a python block"
    return m[1]


def test_the_example_is_short() -> None:
    code = [line for line in example_code().splitlines() if line.strip() and not line.startswith("#")]
    assert len(code) <= 20, f"{len(code)} lines: keep the vehicle example short"


def test_the_vehicle_example_runs_against_the_service(restartable_router: Router, tmp_path) -> None:
    service = Service(
        ServiceSettings(
            data_dir=tmp_path / "data", zenoh_mode="client", listen=(), connect=(restartable_router.endpoint,)
        )
    )
    service.start()
    try:
        proc = subprocess.run(
            [sys.executable, "-c", example_code()],
            env={**os.environ, "RANDT_VEHICLE_CONNECT": json.dumps([restartable_router.endpoint])},
            capture_output=True,
            text=True,
            timeout=180,
        )
    finally:
        service.stop()
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    poses = [
        re.match(r"scan (\d+): (\w+) at \((-?[\d.]+), (-?[\d.]+)\) m in map car-07\.\S+$", x) for x in lines
    ]
    poses = [m for m in poses if m]
    assert [int(m[1]) for m in poses] == [0, 1, 2, 3, 4], proc.stdout
    assert [m[2] for m in poses] == ["first", "ok", "ok", "ok", "ok"], "no prior: the session's own frame"
    x_end, y_end = float(poses[-1][3]), float(poses[-1][4])
    # 4 sweeps at 6 m/s and 10 Hz: 2.4 m from the first pose (the frame's origin)
    assert abs((x_end**2 + y_end**2) ** 0.5 - 2.4) < 0.05, proc.stdout
    assert "acknowledged=5" in lines[-1] and "dropped=0" in lines[-1] and "lost=0" in lines[-1]
