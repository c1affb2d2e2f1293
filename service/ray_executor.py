"""The Ray executor: each session's matcher as a Ray actor, placed by Ray across a cluster's nodes.

Why Ray: a fleet outgrows one machine's cores long before it outgrows one map, and the matcher is
the expensive, stateful part. Ray places stateful actors on a cluster's nodes, notices dead nodes
and actors, and runs on one machine for tests (``ray.cluster_utils.Cluster``), so the service uses
it instead of a protocol of its own. Zenoh stays the data plane between vehicles and the service;
Ray only carries each sweep from the service to its session's actor and the result back.

The shape, next to the local executor (:class:`service.matchers.MatcherPool`)::

    hosts     -> RayMatcherPool(): one matcher host actor (``_MatcherHost``) per CPU of every live
                 node that has CPUs, 0 CPUs reserved, pinned to its node (node affinity), never
                 restarted by Ray (max_restarts=0), warmed up when it starts (the kernels loaded),
                 as the local pool's worker processes are; a node that joins gets its hosts at
                 the next session's open
    open      -> RayMatcherPool.open(key, state, grid, settings, registration): the session's
                 matcher on the host with fewest sessions, on the node with fewest per CPU
    register  -> RayMatcher.register: one remote call per sweep, waited for, the sweep inline in
                 the call (RAY_ENV); unless the session is behind, the host rebuilds a
                 keyframe's model on a thread once the answer is out, and its next request waits
                 for it (as a matcher process rebuilds right after replying)
    errors    -> an exception raised in the host is raised again as itself (Ray's wrapper
                 removed); a dead host or node is a MatcherProcessDiedError, which the session
                 layer already handles: the session is dropped unsaved and resumed from the store
                 with its next scan, on a live host

Why hosts rather than one actor per session: a new actor is a new process that loads the kernels,
and the session's first sweeps queue behind it for a second or two (bench/service.py: the
largest latency of a Ray run was that wait).

Nothing here is imported unless ``executor="ray"`` (``pip install "randt-fleet[ray]"``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.config import RegistrationSettings
from core.errors import RandtError
from core.odometry import IncrementalMatcher, MatcherSettings, PosePrior
from core.tiles import TileGrid
from service.matchers import (
    ForwardingMatcher,
    MatcherProcessDiedError,
    Registered,
    _registered,
    single_threaded_blas,
    warm_up,
)

__all__ = ["RayMatcher", "RayMatcherPool"]

log = logging.getLogger(__name__)

Key = tuple[str, str]


class ConfigurationError(RandtError):
    """The Ray executor cannot start as configured (Ray missing, or the cluster unreachable)."""


#: Ray settings (environment variables) for the per-sweep call: the sweep and its answer travel
#: inline in the call rather than through Ray's object store (Ray's own CPU 4.8 -> 1.2 ms per
#: sweep), and no task events or metrics are recorded per call (the service has its own; the
#: call's CPU in the service 1.57 -> 1.18 ms, measured with a 630 kB sweep and a 448 kB answer).
RAY_ENV = {
    "RAY_max_direct_call_object_size": str(8 << 20),
    "RAY_task_rpc_inlined_bytes_limit": str(16 << 20),
    "RAY_task_events_report_interval_ms": "0",
    "RAY_enable_metrics_collection": "0",
}

#: Ray's namespace for the service's actors.
RAY_NAMESPACE = "randt"


class _MatcherHost:
    """Several sessions' :class:`~core.odometry.IncrementalMatcher` in one Ray worker process,
    one request at a time (wrapped by ``ray.remote`` in :class:`RayMatcherPool`, so that importing
    this module needs no Ray): the actor counterpart of a local matcher process
    (:func:`service.matchers._serve`), warmed up the same way when it starts."""

    def __init__(self) -> None:
        single_threaded_blas()
        try:
            warm_up()
        except Exception:  # a failed warm-up only costs the first sweep its compile time
            log.exception("matcher host warm-up failed")
        self.matchers: dict[Key, IncrementalMatcher] = {}
        self.grids: dict[Key, TileGrid | None] = {}
        self._rebuilds: list[threading.Thread] = []

    def _rebuilt(self) -> None:
        """Wait for the model rebuilds started after the previous answers: a request runs only
        once its host's rebuilds are done (as a matcher process rebuilds between requests)."""
        for thread in self._rebuilds:
            thread.join()
        self._rebuilds.clear()

    def ready(self) -> str:
        """The node this host runs on, once warmed up."""
        import ray

        return str(ray.get_runtime_context().get_node_id())

    def open(
        self,
        key: Key,
        state: dict[str, np.ndarray] | None,
        grid_params: tuple[int, float, int] | None,
        settings: MatcherSettings | None,
        registration: RegistrationSettings | None,
    ) -> None:
        self._rebuilt()
        matcher = IncrementalMatcher(settings, registration)
        if state:
            matcher.load_state_dict(state)
        self.matchers[key] = matcher
        self.grids[key] = None if grid_params is None else TileGrid(*grid_params)

    def register(
        self,
        key: Key,
        xyz: np.ndarray,
        offsets: np.ndarray | None,
        prior: PosePrior | None,
        stamp_s: float | None,
        keyframe_voxel_m: float | None,
        behind: bool,
    ) -> Registered:
        """One sweep of session ``key``. Unless ``behind``, a keyframe's model is rebuilt on a
        thread once this answer is on its way (as a matcher process rebuilds after replying), and
        the host's next request waits for it: one remote call per sweep."""
        self._rebuilt()
        matcher = self.matchers[key]
        result = matcher.register_scan(
            xyz, time_offset_s=offsets, prior=prior, stamp_s=stamp_s, defer_model=True
        )
        if not behind and matcher.model_pending:
            thread = threading.Thread(target=matcher.update_model, daemon=True)
            thread.start()
            self._rebuilds.append(thread)
        return _registered(result, self.grids[key], keyframe_voxel_m)

    def state(self, key: Key) -> dict[str, np.ndarray]:
        self._rebuilt()
        return self.matchers[key].state_dict()

    def drop(self, key: Key) -> bool:
        self._rebuilt()
        self.grids.pop(key, None)
        return self.matchers.pop(key, None) is not None


@dataclass(eq=False)
class _Host:
    """The service's handle on one :class:`_MatcherHost` actor."""

    actor: Any
    node: str  # the Ray node it was placed on
    ready: Any  # the reference of its ``ready`` call (resolves once warmed up)
    sessions: set[Key] = field(default_factory=set)
    dead: bool = False


class RayMatcherPool:
    """The Ray executor (module docstring): the same interface as
    :class:`service.matchers.MatcherPool`.

    ``address``: a running cluster's (``ray://`` or ``host:port``); None starts a local Ray (or
    joins the one this process already initialized)."""

    def __init__(self, address: str | None = None) -> None:
        try:
            import ray
        except ImportError as exc:
            raise ConfigurationError(
                'executor "ray" needs the ray package: pip install "randt-fleet[ray]"'
            ) from exc

        self._ray = ray
        if not ray.is_initialized():
            if address is None:
                # RAY_ENV: sweeps inline in the calls, no per-call task events. A cluster started
                # with `ray start` takes the same variables (docs/deploy.md, docker/compose.yaml).
                for name, value in RAY_ENV.items():
                    os.environ.setdefault(name, value)
            try:
                ray.init(
                    address=address,
                    namespace=RAY_NAMESPACE,
                    include_dashboard=False,
                    logging_level=logging.WARNING,
                    log_to_driver=False,
                )
            except (ConnectionError, RuntimeError, ValueError) as exc:
                where = f"the Ray cluster at {address}" if address else "a local Ray"
                raise ConfigurationError(f"executor ray: cannot start or join {where}: {exc}") from exc
        self._host_class = ray.remote(num_cpus=0, max_restarts=0)(_MatcherHost)
        self._lock = threading.Lock()
        self._hosts: list[_Host] = []
        self._placed: dict[Key, _Host] = {}
        with self._lock:
            self._refresh()

    # -- hosts ------------------------------------------------------------------------------------
    def _nodes(self) -> dict[str, int]:
        """The live nodes that run matchers, with their CPUs (a node started with 0 CPUs, such as
        a head that only coordinates, gets none)."""
        nodes = {}
        for n in self._ray.nodes():
            cpus = int(n.get("Resources", {}).get("CPU", 0))
            if n.get("Alive") and cpus > 0:
                nodes[str(n["NodeID"])] = cpus
        return nodes

    def _refresh(self) -> None:
        """Forget the hosts of dead nodes and dead actors; start hosts up to one per CPU on every
        live node (so a node that joins the cluster gets its share of the next sessions). Called
        with the lock held."""
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        nodes = self._nodes()
        self._hosts = [h for h in self._hosts if not h.dead and h.node in nodes]
        for node, cpus in nodes.items():
            for _ in range(cpus - sum(1 for h in self._hosts if h.node == node)):
                # Hard affinity: a soft one spilled over to another node while this one's worker
                # was starting. Should the node die first, the first call fails and the session
                # resumes on another (MatcherProcessDiedError).
                actor: Any = self._host_class.options(
                    scheduling_strategy=NodeAffinitySchedulingStrategy(node, soft=False)
                ).remote()
                self._hosts.append(_Host(actor, node, actor.ready.remote()))

    def _died(self, host: _Host) -> None:
        """A call on ``host`` found its actor or node gone: place no one there again."""
        with self._lock:
            host.dead = True

    def __len__(self) -> int:
        """The cluster's live nodes."""
        return sum(1 for n in self._ray.nodes() if n.get("Alive"))

    @property
    def ready(self) -> bool:
        with self._lock:
            refs = [h.ready for h in self._hosts]
        done, _ = self._ray.wait(refs, num_returns=len(refs), timeout=0) if refs else ([], [])
        return self._ray.is_initialized() and len(done) == len(refs)

    def wait_ready(self, timeout: float | None = None) -> bool:
        """Wait until every host has warmed up (loaded the kernels), as the local pool's processes."""
        with self._lock:
            refs = [h.ready for h in self._hosts]
        if not refs:
            return self._ray.is_initialized()
        done, _ = self._ray.wait(refs, num_returns=len(refs), timeout=timeout)
        return len(done) == len(refs)

    def open(
        self,
        key: Key,
        state: dict[str, np.ndarray] | None = None,
        grid: TileGrid | None = None,
        settings: MatcherSettings | None = None,
        registration: RegistrationSettings | None = None,
    ) -> RayMatcher:
        """A matcher for session ``key`` (restored from ``state``) on the host with fewest
        sessions, on the node with fewest sessions per CPU (as the local pool places on the
        process with fewest)."""
        params = None if grid is None else (grid.tile_size_m, grid.voxel_size_m, grid.max_points_per_voxel)
        with self._lock:
            self._refresh()
            if not self._hosts:
                raise MatcherProcessDiedError("the Ray cluster has no live node with CPUs for a matcher")
            per_node: dict[str, list[_Host]] = {}
            for h in self._hosts:
                per_node.setdefault(h.node, []).append(h)
            load = {n: sum(len(h.sessions) for h in hs) / len(hs) for n, hs in per_node.items()}
            node = min(per_node, key=lambda n: load[n])
            host = min(per_node[node], key=lambda h: len(h.sessions))
            host.sessions.add(key)
            self._placed[key] = host
        matcher = RayMatcher(self, host, key, state)
        try:
            matcher._get(host.actor.open.remote(key, state, params, settings, registration))
        except BaseException:
            self._release(key, host)
            raise
        return matcher

    def node_of(self, key: Key) -> str | None:
        """The Ray node id of the session's host (None if it is not open or its node is gone)."""
        with self._lock:
            host = self._placed.get(key)
        if host is None:
            return None
        try:
            return str(self._ray.get(host.actor.ready.remote(), timeout=30))
        except self._ray.exceptions.RayError:
            return None

    def _release(self, key: Key, host: _Host) -> None:
        with self._lock:
            host.sessions.discard(key)
            if self._placed.get(key) is host:
                del self._placed[key]

    def close(self) -> None:
        """Kill the hosts (the sessions were saved first)."""
        with self._lock:
            hosts, self._hosts, self._placed = self._hosts, [], {}
        for host in hosts:
            with contextlib.suppress(self._ray.exceptions.RayError):
                self._ray.kill(host.actor, no_restart=True)


class RayMatcher(ForwardingMatcher):
    """A session's matcher in a Ray actor: the interface of :class:`service.matchers.RemoteMatcher`."""

    def __init__(
        self, pool: RayMatcherPool, host: _Host, key: Key, state: dict[str, np.ndarray] | None
    ) -> None:
        self._pool, self._host, self._key = pool, host, key
        self.poses: list[np.ndarray] = [] if not state else list(np.asarray(state["poses"]).reshape(-1, 4, 4))

    def _get(self, ref: Any) -> Any:
        """The call's value; its exception raised as itself; a dead actor or node is a
        :class:`MatcherProcessDiedError`."""
        ray = self._pool._ray
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as exc:
            cause = exc.cause if isinstance(exc.cause, BaseException) else None
            if cause is None:
                raise
            raise cause from None
        except (
            ray.exceptions.RayActorError,
            ray.exceptions.ActorUnschedulableError,
            ray.exceptions.ObjectLostError,
        ) as exc:
            self._pool._died(self._host)
            raise MatcherProcessDiedError(
                f"the Ray matcher host of session {self._key[0]}/{self._key[1]} is gone: {type(exc).__name__}"
            ) from exc

    def register(
        self,
        points_xyz: np.ndarray,
        *,
        time_offset_s: np.ndarray | None = None,
        prior: PosePrior | None = None,
        stamp_s: float | None = None,
        behind: bool = False,
        keyframe_voxel_m: float | None = None,
    ) -> Registered:
        """:meth:`service.matchers.RemoteMatcher.register`, in the session's actor."""
        registered: Registered = self._get(
            self._host.actor.register.remote(
                self._key, points_xyz, time_offset_s, prior, stamp_s, keyframe_voxel_m, behind
            )
        )
        self.poses.append(registered.result.T_world_sensor)
        return registered

    def state_dict(self) -> dict[str, np.ndarray]:
        state: dict[str, np.ndarray] = self._get(self._host.actor.state.remote(self._key))
        return state

    def close(self) -> None:
        """Forget the session in its host (its state should have been saved first)."""
        self._pool._release(self._key, self._host)
        if not self._host.dead:
            self._host.actor.drop.remote(self._key)  # not waited for: the host's next request follows it
