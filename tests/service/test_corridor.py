"""One scan's way through the service, followed call by call as it runs (issue 56).

The session thread's per-sweep orchestrator (``SessionWorker._process``) calls each stage in the
module of its concern; no stage calls back into a module that is still below it on the stack (a
module the scan has left on its way down), nor up into the manager that holds the sessions.
Measured here with a profile hook on real scans through a real SessionManager: every call into a
``randt`` module while a ``_process`` runs, with the modules on the stack beneath it.
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path
from types import FrameType
from typing import Any

import numpy as np

from randt.service.metrics import ServiceMetrics
from randt.service.sessions import SessionManager
from randt.service.settings import ServiceSettings
from randt.service.store import Store
from randt.sim.drive import plan_fleet, simulate
from randt.sim.lidar import Lidar64
from randt.sim.town import Town
from randt.wire.messages import ErrorMessage, PoseMessage, encode, scan_from_arrays

N_SCANS = 12


class Corridor:
    """A profile hook: per ``_process`` call, the randt modules it entered (in order, nested
    calls flattened) and every call back into a module that was still on the stack."""

    def __init__(self) -> None:
        self.local = threading.local()
        self.walks: list[list[str]] = []
        self.returns: list[tuple[str, ...]] = []

    def __call__(self, frame: FrameType, event: str, arg: Any) -> None:
        st = self.local.__dict__
        if event == "call":
            module = frame.f_globals.get("__name__", "")
            if module == "randt.service.worker" and frame.f_code.co_name == "_process":
                st["stack"], st["walk"] = [], []
                self.walks.append(st["walk"])
            stack = st.get("stack")
            if stack is None:
                return
            mod = module if module.startswith("randt.") else None
            if mod is not None:
                below = [m for m in stack if m is not None]
                if below and mod != below[-1] and mod in below:
                    self.returns.append((*below[below.index(mod) :], mod))
                if not st["walk"] or st["walk"][-1] != mod:
                    st["walk"].append(mod)
            stack.append(mod)
        elif event == "return" and st.get("stack") is not None:
            stack = st["stack"]
            stack.pop()
            if not stack:
                st["stack"] = None


def _answered(out: list) -> int:
    return sum(isinstance(m, PoseMessage | ErrorMessage) for m in list(out))


def test_a_scan_never_comes_back_to_a_module_it_has_left(tmp_path: Path) -> None:
    plan = plan_fleet(Town.generate(0), 1, seed=0, route_length_m=300.0)[0]
    lidar = Lidar64(n_azimuth=500, max_range_m=60.0)
    scans = list(simulate(Town.generate(0), plan.route, n_scans=N_SCANS, seed=1, lidar=lidar, workers=1))
    s = ServiceSettings(data_dir=tmp_path, flush_interval_s=0.3, capacity_target=0, matcher_processes=0)
    out: list = []
    mgr = SessionManager(s, Store(tmp_path), out.append, ServiceMetrics())
    corridor = Corridor()
    threading.setprofile(corridor)  # (the session's thread starts with its first scan)
    try:
        assert mgr.wait_matchers(300)
        for scan in scans:
            n = _answered(out)
            mgr.submit(
                "car",
                encode(
                    scan_from_arrays(
                        "car",
                        "d1",
                        scan.index,
                        scan.stamp_ns,
                        scan.points_xyz,
                        prior_pose=scan.T_world_sensor,
                        prior_covariance=np.diag([1e-4] * 3 + [1e-5] * 3),
                    )
                ),
            )
            deadline = time.monotonic() + 60
            while _answered(out) < n + 1:
                assert time.monotonic() < deadline, "the service stopped answering"
                time.sleep(0.002)
    finally:
        threading.setprofile(None)  # type: ignore[arg-type]
        sys.setprofile(None)
        mgr.stop()
    poses = [m for m in out if isinstance(m, PoseMessage)]
    assert len(poses) == N_SCANS and [p.status for p in poses] == ["first"] + ["ok"] * (N_SCANS - 1)
    assert len(corridor.walks) == N_SCANS  # every scan followed
    entered = {m for walk in corridor.walks for m in walk}
    # the stages' modules were entered (the hook saw the corridor, not nothing)
    for stage in ("randt.service.worker", "randt.service.pose_log", "randt.service.tracking"):
        assert stage in entered, sorted(entered)
    assert any(m.startswith("randt.core.") for m in entered), sorted(entered)
    assert corridor.returns == [], sorted(set(corridor.returns))[:10]
    # nor up into what holds the sessions (the worker gets narrow collaborators, not the manager)
    above = {"randt.service." + m for m in ("sessions", "runtime", "routing", "opener", "intake", "app")}
    assert entered.isdisjoint(above), sorted(entered & above)
