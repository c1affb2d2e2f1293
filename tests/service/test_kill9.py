"""kill -9 of the service in the middle of ingest, 10 times: no torn file, tiles intact, sessions resume.

The worker (``python -m tests.service.test_kill9 DATA``) is a real :class:`randt.service.runtime.Service`
(without Zenoh: the kill is about the store) ingesting a moving synthetic room; it resumes its
session from the store at every start, so each run continues the previous one's sequence numbers.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from randt.core.io import read_cloud, read_tum
from randt.service.store import Store

REPO = Path(__file__).resolve().parents[2]


def _worker(data_dir: str) -> None:
    from randt.core.scenes import synthetic_room
    from randt.core.transforms import make_transform, transform_points
    from randt.service.runtime import Service
    from randt.service.settings import ServiceSettings
    from randt.wire.messages import encode, scan_from_arrays

    service = Service(ServiceSettings(data_dir=data_dir, flush_interval_s=0.05), with_zenoh=False)
    service.start()
    assert service.sessions is not None and service.sessions.wait_matchers(600)
    record = next((r for r in service.sessions.records().values()), None)
    seq = 0 if record is None else record.last_seq + 1
    room = synthetic_room(np.random.default_rng(0), 2500)
    print("ready", flush=True)
    while True:
        T = make_transform(translation=(0.05 * seq, 0.0, 0.0))
        pts = transform_points(np.linalg.inv(T), room).astype(np.float32)
        service.sessions.submit("v1", encode(scan_from_arrays("v1", "d1", seq, seq * 100_000_000, pts)))
        seq += 1
        time.sleep(0.02)


def _check_readable(data: Path) -> dict[str, int]:
    """Every file opens with its reader; metadata lists only tiles that exist. Returns tile versions."""
    leftovers = [p for p in data.rglob("*.tmp")]
    store = Store(data)  # removes leftover temp files of interrupted writes
    assert not [p for p in leftovers if p.exists()], "temp files are cleaned on open"
    contents = store.load_all()
    assert contents.problems == [], contents.problems
    versions: dict[str, int] = {}
    for name, grid in contents.maps.items():
        map_dir = data / "maps" / name
        meta = yaml.safe_load((map_dir / "pointcloud_map_metadata.yaml").read_text())
        for tile_file in (k for k in meta if k.endswith(".pcd")):
            assert (map_dir / tile_file).is_file(), f"metadata lists {tile_file} which does not exist"
            assert read_cloud(map_dir / tile_file).n_points > 0
        versions.update({f"{name}/{tid}": grid.get(tid).version for tid in grid.tile_ids()})
    for loaded in contents.sessions.values():
        # trajectory.tum is the snapshot's view; the poses logged since (poses.log) come on top
        _, poses = read_tum(data / "sessions/v1/d1/trajectory.tum")
        assert loaded.record.n_scans == loaded.poses.shape[0] >= poses.shape[0]
        np.testing.assert_allclose(loaded.poses[: poses.shape[0]], poses, rtol=0, atol=1e-6)
    store.close()
    return versions


def test_kill9_during_ingest_ten_times(tmp_path) -> None:
    rng = np.random.default_rng(20261122)
    data = tmp_path / "data"
    last_versions: dict[str, int] = {}
    last_seq = -1
    for _ in range(10):
        proc = subprocess.Popen(
            [sys.executable, "-m", "tests.service.test_kill9", str(data)],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            start_new_session=True,  # (its group: killed whole below if the test stops early)
        )
        try:
            assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
            time.sleep(rng.uniform(0.5, 2.0))
        except BaseException:  # interrupted (a Ctrl-C on the suite left the service and matchers)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
            raise
        # Only the service: its matcher processes must die with it (service/matchers.py).
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        versions = _check_readable(data)
        for tid, v in last_versions.items():
            assert versions.get(tid, 0) >= v, f"tile {tid} went back from version {v}"
        last_versions = versions
        store = Store(data)
        records = store.list_sessions()
        # the snapshot's record plus the poses logged since (here mostly the first snapshot's:
        # one is due every 30 s or 20 m, and each run lasts 0.5-2 s at 2.5 m/s)
        stored = store.load_session(records[0].vehicle, records[0].session)[0] if records else None
        store.close()
        if stored is not None:
            assert stored.last_seq >= last_seq, "a session never loses scans it acknowledged"
            last_seq = stored.last_seq
    assert last_seq > 20, "the runs resumed each other's session and went on"
    assert last_versions, "tiles were written"


if __name__ == "__main__":
    _worker(sys.argv[1])
