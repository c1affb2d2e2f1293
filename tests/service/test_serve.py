"""``randt serve`` as a user runs it: embedded peer mode, a scan in, a pose out, SIGTERM/SIGINT flush."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

import httpx
import numpy as np
import pytest
import zenoh

from randt.core.scenes import synthetic_room
from randt.wire.messages import decode_pose, encode, scan_from_arrays
from randt.wire.zenoh_config import zenoh_config
from tests.service.conftest import free_port


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_serve_answers_and_flushes_on_signal(tmp_path, sig) -> None:
    zport, hport = free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    data = tmp_path / "data"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cli",
            "serve",
            "--data-dir",
            str(data),
            "--listen",
            endpoint,
            "--http-port",
            str(hport),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"http://127.0.0.1:{hport}/readyz", timeout=1).json().get("ready"):
                    break
            except httpx.HTTPError:
                time.sleep(0.2)
        else:
            pytest.fail("randt serve did not become ready")
        vehicle = zenoh.open(zenoh_config("peer", connect=(endpoint,)))
        got = threading.Event()
        poses = []
        sub = vehicle.declare_subscriber(
            "randt/fleet/car7/pose", lambda s: (poses.append(decode_pose(s.payload.to_bytes())), got.set())
        )
        # Sent once the service's scan subscription is known here (a condition, not a clock: the
        # fixed 0.5 s wait lost the scan once, beside two CPU burners), with our answer
        # subscription declared before it.
        publisher = vehicle.declare_publisher("randt/fleet/car7/scan")
        deadline = time.monotonic() + 60
        while not publisher.matching_status.matching:
            assert time.monotonic() < deadline, "the service's scan subscription never reached the vehicle"
            time.sleep(0.05)
        room = synthetic_room(np.random.default_rng(0), 3000).astype(np.float32)
        publisher.put(encode(scan_from_arrays("car7", "d1", 0, 0, room)))
        if not got.wait(60):
            proc.kill()
            log = proc.communicate()[1][-4000:]
            pytest.fail(f"no pose came back over Zenoh in 60 s; the service's log:\n{log}")
        assert poses[0].seq == 0 and poses[0].status == "first"
        status = httpx.get(f"http://127.0.0.1:{hport}/status", timeout=5).json()
        assert status["sessions"][0]["vehicle"] == "car7" and status["sessions"][0]["frame"] == "session"
        sub.undeclare()
        vehicle.close()
        proc.send_signal(sig)
        # uvicorn shuts down cleanly, then re-raises SIGTERM so supervisors see the usual status
        assert proc.wait(30) in (0, -signal.SIGTERM), proc.stderr.read() if proc.stderr else ""
        log = proc.stderr.read() if proc.stderr else ""
        assert "service randt-1 stopped" in log and "store closed" in log
    finally:
        if proc.poll() is None:
            proc.kill()
    assert (data / "sessions/car7/d1/matcher.npz").is_file(), "the session was flushed on shutdown"
    assert (data / "maps/car7.d1/pointcloud_map_metadata.yaml").is_file(), "tiles were flushed"
