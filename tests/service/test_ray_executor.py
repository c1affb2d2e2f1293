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

from randt.core.transforms import invert, transform_error

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
    head node; only the scan in flight and those queued behind it are refused (internal_error,
    never acknowledged: consecutive scans, usually one, two when the next had arrived already, as
    a slow hour gave), every acknowledged pose is in the session's final trajectory, and every
    pose is within 5 cm (and 0.2 deg) of the simulator's truth."""
    worker, head = scenario["nodes"]["worker"], scenario["nodes"]["head"]
    moved = [name for name, node in scenario["placed"].items() if node == worker]
    assert moved, "no session ran on the worker node: the test lost its point"
    assert set(scenario["after"].values()) == {head}
    for name, traj in scenario["trajectories"].items():
        answers = [a for a in scenario["answers"] if a["vehicle"] == name]
        assert sorted(a["seq"] for a in answers) == list(range(len(scenario["truth"][name])))
        refused = [a for a in answers if a["kind"] != "pose"]
        if name in moved:
            kinds, seqs = [a["kind"] for a in refused], sorted(a["seq"] for a in refused)
            assert 1 <= len(kinds) <= 3 and set(kinds) == {"internal_error"}, kinds
            assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), seqs  # in flight and queued behind
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


def test_a_node_whose_host_died_gets_no_session_while_another_can_take_it(monkeypatch) -> None:
    """Ray may report a node alive for seconds after its machine died: a session resumed then was
    placed on a fresh host there and failed a second time (CI, under load). After a host dies,
    its node gets no new host and no session for SUSPECT_NODE_S while another node can take them,
    and again once that time has passed (a crashed actor on a sound node). Placement only, with
    stand-ins for Ray's actors (the scenario above runs a real cluster)."""
    pytest.importorskip("ray")
    import threading

    from randt.service import ray_executor as rx

    class Call:
        def remote(self) -> str:
            return "ready"

    class Actor:
        ready = Call()

        def __init__(self, node: str) -> None:
            self.node = node

    class HostClass:
        class _Options:
            def __init__(self, node: str) -> None:
                self.node = node

            def remote(self) -> Actor:
                return Actor(self.node)

        def options(self, scheduling_strategy) -> _Options:
            return self._Options(scheduling_strategy.node_id)

    A, B = "a" * 56, "b" * 56  # node ids as Ray writes them (28 bytes in hex)

    class Ray:  # both nodes alive, as Ray says for a while after one's machine died
        def nodes(self) -> list[dict]:
            return [{"NodeID": n, "Alive": True, "Resources": {"CPU": 1}} for n in (A, B)]

    pool = object.__new__(rx.RayMatcherPool)
    pool._ray, pool.transport, pool._host_class = Ray(), "ray", HostClass()
    pool._lock, pool._hosts, pool._placed, pool._suspect = threading.Lock(), [], {}, {}
    opened: list[str] = []
    monkeypatch.setattr(rx.RayMatcher, "_call", lambda self, op, *a: opened.append(self._host.node))
    with pool._lock:
        pool._refresh()
    assert sorted(h.node for h in pool._hosts) == [A, B]
    pool.open(("first", "1"))
    pool.open(("second", "1"))
    assert sorted(opened) == [A, B]  # one each while both are sound
    pool._died(next(h for h in pool._hosts if h.node == A))
    for i in range(3):  # resumed and new sessions: all on node B, and no new host on node A
        pool.open(("v", str(i)))
    assert opened[2:] == [B] * 3
    assert [h.node for h in pool._hosts] == [B]
    # Once SUSPECT_NODE_S has passed, node A (alive all along) gets a host and the next session.
    monkeypatch.setattr(rx, "SUSPECT_NODE_S", 0.0)
    pool.open(("later", "1"))
    assert opened[-1] == A and sorted(h.node for h in pool._hosts) == [A, B]
