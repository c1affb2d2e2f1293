"""The Ray executor on a 2-node Ray cluster on this machine (issue 16).

Ray binds the machine's external address, so the scenario (``tests/service/ray_scenario.py``)
runs in a private network namespace (``unshare -n``, loopback up), where Ray falls back to
127.0.0.1 and nothing leaves the machine. Needs root (or unprivileged user namespaces) and the
``ray`` package (in the test extra); without either the test skips, and fails under ``CI=true``.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from core.transforms import invert, transform_error

REPO = Path(__file__).resolve().parents[2]


def _unavailable() -> str | None:
    if importlib.util.find_spec("ray") is None:
        return 'ray is not installed (pip install -e ".[test]")'
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare or ip (util-linux, iproute2) not found"
    probe = subprocess.run(["unshare", "-n", "true"], capture_output=True, text=True)
    if probe.returncode != 0:
        return f"cannot make a private network namespace: {probe.stderr.strip()}"
    return None


@pytest.fixture(scope="module")
def scenario() -> dict:
    why = _unavailable()
    if why is not None:
        if os.environ.get("CI") == "true":
            pytest.fail(f"the Ray executor test cannot run: {why}")
        pytest.skip(why)
    done = subprocess.run(
        [
            "unshare",
            "-n",
            "sh",
            "-c",
            f"ip link set lo up && exec {sys.executable} -m tests.service.ray_scenario",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    assert done.returncode == 0 and lines, f"scenario failed ({done.returncode}):\n{done.stderr[-4000:]}"
    return json.loads(lines[-1][len("RESULT ") :])


def test_ray_hosts_give_the_local_matchers_poses_on_both_nodes(scenario) -> None:
    """Three sessions on the matcher hosts of both nodes (one host per node's CPU) give the
    in-process matcher's poses (measured: bit for bit), over the hosts' sockets (the default
    transport) and over Ray calls."""
    assert scenario["host_niceness"] == [0, 0]  # not Ray's default 15: the hosts are the work
    for transport in ("socket", "ray"):
        assert scenario["equality_max_abs"][transport] < 1e-6, transport
        assert set(scenario[f"equality_nodes_{transport}"].values()) == set(scenario["nodes"].values())


def test_a_dead_node_moves_its_sessions_without_losing_an_acknowledged_pose(scenario) -> None:
    """The worker node is removed halfway: the sessions on it are resumed from the store on the
    head node; only the scan in flight is refused (internal_error, never acknowledged), every
    acknowledged pose is in the session's final trajectory, and every pose is within 5 cm (and
    0.2 deg) of the simulator's truth."""
    worker, head = scenario["nodes"]["worker"], scenario["nodes"]["head"]
    moved = [name for name, node in scenario["placed"].items() if node == worker]
    assert moved, "no session ran on the worker node: the test lost its point"
    assert set(scenario["after"].values()) == {head}
    for name, traj in scenario["trajectories"].items():
        answers = [a for a in scenario["answers"] if a["vehicle"] == name]
        assert sorted(a["seq"] for a in answers) == list(range(len(scenario["truth"][name])))
        refused = [a for a in answers if a["kind"] != "pose"]
        if name in moved:
            assert [a["kind"] for a in refused] == ["internal_error"]  # the one in flight
        else:
            assert refused == []
        acked = [a for a in answers if a["kind"] == "pose"]
        poses = np.asarray(traj).reshape(-1, 4, 4)
        assert len(poses) == len(acked)
        truth = np.asarray(scenario["truth"][name]).reshape(-1, 4, 4)
        for a, T in zip(sorted(acked, key=lambda a: a["seq"]), poses, strict=True):
            np.testing.assert_allclose(np.reshape(a["pose"], (4, 4)), T, atol=1e-9)  # kept as acked
            dt, dr = transform_error(invert(T) @ truth[a["seq"]], np.eye(4))
            assert dt < 0.05 and dr < 0.2, f"{name} seq {a['seq']}: {dt:.3f} m, {dr:.3f} deg from the truth"
    # How long a moved session waits: its next scan after the refused one is answered within
    # this (measured 0.1-0.4 s: the state read from the store and opened on the head node's warm
    # host; 1.3-2.1 s when every session had an actor of its own, started then).
    assert max(scenario["waits_after_kill_s"]) < 5.0
