"""Exports stream in every format: 20 concurrent LAS downloads of a 1.1 M-point map hold about one
tile's worth of output each, not the map's (issue 32: each LAS export held the whole map, 410 ->
1306 MB for 20 of them).

The service is a real one in a subprocess (uvicorn, the store's map loaded at start), so its
resident memory is its own; the 20 clients stream slowly from threads here, all in flight at once,
while a sampler reads the service's VmRSS.
"""

from __future__ import annotations

import io
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import laspy
import numpy as np

from randt.core.tiles import TileGrid
from randt.service.api.encoding import stream_cloud
from randt.service.store import Store
from tests.service.conftest import free_port

REPO = Path(__file__).resolve().parents[2]
LAS_RECORD_BYTES = 34  # point format 6 (30) + the float32 intensity_raw extra dimension

SERVE = """
import sys, uvicorn
sys.path.insert(0, sys.argv[1])
from randt.service.app import create_app
from randt.service.settings import ServiceSettings
app = create_app(ServiceSettings(data_dir=sys.argv[2], matcher_processes=1), with_zenoh=False)
uvicorn.run(app, host="127.0.0.1", port=int(sys.argv[3]), log_level="warning")
"""


def _rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for {pid}")


def _big_map(data: Path) -> TileGrid:
    """1.1 M points over 4 x 4 tiles of 20 m (about 70k points, 2.3 MB of LAS records a tile)."""
    rng = np.random.default_rng(7)
    grid = TileGrid(tile_size_m=20, voxel_size_m=0.2)
    points = rng.uniform((0.0, 0.0, 0.0), (80.0, 80.0, 12.0), (1_150_000, 3)).astype(np.float32)
    grid.insert(points, rng.uniform(0, 1, points.shape[0]).astype(np.float32))
    with Store(data) as store:
        store.save_tiles("big", grid, grid.tile_ids())
    return grid


def test_twenty_concurrent_las_exports_hold_about_a_tile_each(tmp_path: Path) -> None:
    grid = _big_map(tmp_path / "data")
    assert grid.n_points > 1_000_000
    tile_mib = max(grid.get(t).n_points for t in grid.tile_ids()) * LAS_RECORD_BYTES / 2**20
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-c", SERVE, str(REPO), str(tmp_path / "data"), str(port)])
    url = f"http://127.0.0.1:{port}/maps/big/export?format=las"
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline and proc.poll() is None, "the service did not start"
            time.sleep(0.2)
        # one download alone first: the same file laspy reads back, every point
        whole = httpx.get(url, timeout=120)
        las = laspy.read(io.BytesIO(whole.content))
        assert las.header.point_count == grid.n_points
        time.sleep(1.0)
        baseline = _rss_mib(proc.pid)
        peak = [baseline]
        sizes: list[int] = []
        started = threading.Barrier(21)
        stop = threading.Event()

        def sample() -> None:
            while not stop.is_set():
                peak[0] = max(peak[0], _rss_mib(proc.pid))
                time.sleep(0.01)

        def download() -> None:
            n = 0
            with httpx.stream("GET", url, timeout=120) as r:
                assert r.status_code == 200
                for k, block in enumerate(r.iter_raw(1 << 16)):
                    n += len(block)
                    if k == 0:
                        started.wait(60)  # all 20 in flight before any finishes
                    time.sleep(0.002)
            sizes.append(n)

        sampler = threading.Thread(target=sample)
        sampler.start()
        clients = [threading.Thread(target=download) for _ in range(20)]
        for c in clients:
            c.start()
        started.wait(60)
        for c in clients:
            c.join(300)
        stop.set()
        sampler.join()
    finally:
        proc.terminate()
        proc.wait(60)
    assert sizes == [len(whole.content)] * 20
    grown = peak[0] - baseline
    print(
        f"\n20 LAS exports of {grid.n_points} points ({len(whole.content) / 2**20:.1f} MiB each): service"
        f" RSS {baseline:.0f} -> peak {peak[0]:.0f} MiB (+{grown:.1f}; a tile's LAS {tile_mib:.1f} MiB)"
    )
    assert grown < 20 * tile_mib, (grown, tile_mib)


def test_streamed_las_is_the_file_laspys_writer_writes() -> None:
    """What ``laspy.open(mode="w")`` writes for the same chunks: the public header byte for byte
    (bounds, per-return counts, the point data's offset) and every point record, in pieces of any
    size and with an empty chunk; the extra dimension's range in its VLR is the true one (laspy's
    own writer records the first record's value of each write)."""
    rng = np.random.default_rng(3)
    chunks = [
        (rng.uniform(-50, 50, (n, 3)).astype(np.float32), rng.uniform(0, 1, n).astype(np.float32))
        for n in (70_000, 0, 5, 140_001)
    ]
    from randt.service.api.encoding import _las_header, _las_points

    for used in (chunks, chunks[1:2]):
        n_points = sum(c[0].shape[0] for c in used)
        streamed = b"".join(stream_cloud("las", n_points, used))
        lows = [c[0].min(axis=0) for c in used if c[0].shape[0]]
        header = _las_header(np.min(lows, axis=0) if lows else np.zeros(3))
        out = io.BytesIO()
        with laspy.open(out, mode="w", header=header, closefd=False) as writer:
            for xyz, intensity in used:
                if xyz.shape[0]:
                    writer.write_points(_las_points(header, xyz, intensity))
        reference = out.getvalue()
        back, ref = laspy.read(io.BytesIO(streamed)), laspy.read(io.BytesIO(reference))
        size, offset = 375, ref.header.offset_to_point_data  # LAS 1.4's public header: 375 bytes
        assert len(streamed) == len(reference) and streamed[:size] == reference[:size], n_points
        assert streamed[offset:] == reference[offset:], n_points
        assert back.header.point_count == n_points
        (extra,) = back.header.vlrs[0].extra_bytes_structs
        if n_points:
            xyz, intensity = np.concatenate([c[0] for c in used]), np.concatenate([c[1] for c in used])
            np.testing.assert_allclose(np.c_[back.x, back.y, back.z], xyz, atol=6e-5)
            np.testing.assert_array_equal(np.asarray(back.intensity_raw), intensity)
            np.testing.assert_allclose(
                [extra.min[0], extra.max[0]], [intensity.min(), intensity.max()], rtol=1e-6
            )
