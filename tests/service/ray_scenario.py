"""The Ray executor's scenario, run by ``tests/service/test_ray_executor.py`` in a private network
namespace (Ray binds the machine's external address; alone in a namespace it falls back to
127.0.0.1). Prints one JSON object of measurements; the test asserts them.

    python -m tests.service.ray_scenario

A 2-node ``ray.cluster_utils.Cluster`` (one CPU each). Three simulated vehicles, no priors:

1. equality: each vehicle's sweeps through the Ray executor (``RayMatcherPool``: matcher hosts,
   one per node's CPU; over each transport, the hosts' sockets and Ray calls) and through an
   in-process matcher that rebuilds its model after every sweep (what a host does once the sweep
   is answered): the largest pose difference, and the nodes the sessions ran on;
2. a node dies: the same vehicles through a ``SessionManager`` with ``executor="ray"``; after
   half the sweeps (saved), the worker node is removed; the rest are sent. Reported: every
   acknowledged pose, the final trajectories, the truth, which sessions had to move, and how long
   a moved session went unanswered.
"""

from __future__ import annotations

import contextlib
import json
import os
import pickle
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    import ray
    from ray.cluster_utils import Cluster

    from randt.core.odometry import IncrementalMatcher, MatcherSettings
    from randt.core.tiles import TileGrid
    from randt.core.transforms import invert
    from randt.service.matchers import scan_payload
    from randt.service.metrics import ServiceMetrics
    from randt.service.ray_executor import RAY_ENV, RayMatcherPool
    from randt.service.sessions import SessionManager
    from randt.service.settings import ServiceSettings
    from randt.service.store import Store
    from randt.sim.drive import plan_fleet, simulate
    from randt.sim.lidar import Lidar64
    from randt.sim.town import Town
    from randt.wire.messages import ErrorMessage, PoseMessage, encode, scan_from_arrays

    n_scans = 24
    town = Town.generate(0)
    lidar = Lidar64(n_azimuth=900, max_range_m=60.0)
    fleet = plan_fleet(town, 3, seed=0, route_length_m=400.0)
    drives = {
        v.vehicle_id: list(
            simulate(town, v.route, n_scans=n_scans, seed=i, lidar=lidar, start_s_m=v.start_s_m)
        )
        for i, v in enumerate(fleet)
    }
    out: dict[str, object] = {}
    t0 = time.monotonic()
    os.environ.update(RAY_ENV)  # as on every node of a deployment (docs/deploy.md)
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    worker_node = cluster.add_node(num_cpus=1)
    ray.init(address=cluster.address, include_dashboard=False, logging_level="ERROR", log_to_driver=False)
    cluster.wait_for_nodes()
    out["cluster_start_s"] = time.monotonic() - t0
    head_id = next(n["NodeID"] for n in ray.nodes() if n["Alive"] and n["NodeID"] != worker_node.node_id)
    out["nodes"] = {"head": head_id, "worker": worker_node.node_id}
    with contextlib.ExitStack() as stack:
        stack.callback(cluster.shutdown)
        stack.callback(ray.shutdown)
        # 1. equality with the in-process matcher, over each transport (the hosts' sockets, and
        # a Ray call per sweep)
        out["equality_max_abs"] = {}
        for transport in ("socket", "ray"):
            pool = RayMatcherPool(transport=transport)
            pool.wait_ready(120)
            out["host_niceness"] = sorted(ray.get([h.actor.niceness.remote() for h in pool._hosts]))
            diffs, nodes = [], {}
            sent_bytes: list[int] = []
            back_bytes: list[int] = []
            n_points: list[int] = []
            # every session open at once, as a service's sessions are: spread over the nodes' hosts
            remotes = {
                name: pool.open((name, "eq"), grid=TileGrid(20, 0.2)) for name in drives
            }  # the map's sizes
            for name, scans in drives.items():
                local = IncrementalMatcher(MatcherSettings())
                remote = remotes[name]
                nodes[name] = pool.node_of((name, "eq"))
                for s in scans:
                    xyz = s.points_xyz.astype(np.float32)
                    a = local.register_scan(xyz.astype(np.float64), stamp_s=s.stamp_ns * 1e-9)
                    payload = scan_payload(xyz, stamp_ns=s.stamp_ns, seq=s.index)  # (read as stamp_ns * 1e-9)
                    registered = remote.register_payload(payload)
                    b = registered.result
                    # what moves per sweep: the call's arguments there (the payload as the vehicle
                    # sent it), the answer back (pickled; the answer carries the points the
                    # session's map can keep)
                    call = (payload, None, False, None, None)
                    sent_bytes.append(len(pickle.dumps(call, protocol=5)))
                    back_bytes.append(len(pickle.dumps(registered, protocol=5)))
                    n_points.append(len(xyz))
                    diffs.append(float(np.abs(a.T_world_sensor - b.T_world_sensor).max()))
                    assert a.status == b.status, (transport, name, s.index, a.status, b.status)
                remote.close()
            pool.close()
            out["equality_max_abs"][transport] = max(diffs)  # type: ignore[index]
            out["bytes_per_sweep"] = {
                "points": float(np.mean(n_points)),
                "to_actor": float(np.mean(sent_bytes)),
                "from_actor": float(np.mean(back_bytes)),
            }
            out[f"equality_nodes_{transport}"] = nodes

        # 2. a node dies under a running service
        data = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="randt-ray-")))
        # (capacity_target=0: three young sessions at once on this small cluster would be refused
        # one by admission's expected cost; the node's death is this scenario's subject)
        settings = ServiceSettings(
            data_dir=data, executor="ray", flush_interval_s=0.2, graph=False, capacity_target=0
        )
        answers: list[object] = []
        mgr = SessionManager(settings, Store(data), answers.append, ServiceMetrics())

        def answered() -> list[PoseMessage | ErrorMessage]:
            return [m for m in answers if isinstance(m, PoseMessage | ErrorMessage)]

        def send(seq: int, timeout: float = 120.0) -> float:
            """Send every vehicle's sweep ``seq``; wait for the answers; the wait in s."""
            t = time.monotonic()
            n = len(answered())
            for name, scans in drives.items():
                s = scans[seq]
                mgr.submit(name, encode(scan_from_arrays(name, "d1", seq, s.stamp_ns, s.points_xyz)))
            while len(answered()) < n + len(drives) and time.monotonic() - t < timeout:
                time.sleep(0.01)
            return time.monotonic() - t

        try:
            half = n_scans // 2
            for seq in range(half):
                send(seq)
            time.sleep(1.0)  # flushes save every session
            pool_ = mgr.pool
            assert isinstance(pool_, RayMatcherPool)
            placed = {name: pool_.node_of((name, "d1")) for name in drives}
            out["placed"] = placed
            t_kill = time.monotonic()
            cluster.remove_node(worker_node)
            out["remove_node_s"] = time.monotonic() - t_kill
            waits = []
            for seq in range(half, n_scans):
                waits.append(send(seq))
            out["waits_after_kill_s"] = waits
            out["answers"] = [
                {
                    "vehicle": m.vehicle,
                    "seq": m.seq,
                    "kind": "pose" if isinstance(m, PoseMessage) else m.code,
                    "pose": list(m.pose) if isinstance(m, PoseMessage) else None,
                }
                for m in answered()
            ]
            out["after"] = {name: pool_.node_of((name, "d1")) for name in drives}
            trajectories = {}
            for name in drives:
                traj = mgr.trajectory(name, "d1")
                assert traj is not None
                trajectories[name] = np.asarray(traj[1]).reshape(-1, 16).tolist()
            out["trajectories"] = trajectories
            out["truth"] = {
                name: [
                    (invert(scans[0].T_world_sensor) @ s.T_world_sensor).reshape(16).tolist() for s in scans
                ]
                for name, scans in drives.items()
            }
        finally:
            mgr.stop()
    print("RESULT " + json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
