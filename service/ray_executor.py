"""The Ray executor: each session's matcher as a Ray actor, placed by Ray across a cluster's nodes.

Why Ray: a fleet outgrows one machine's cores long before it outgrows one map, and the matcher is
the expensive, stateful part. Ray places stateful actors on a cluster's nodes, notices dead nodes
and actors, and runs on one machine for tests (``ray.cluster_utils.Cluster``), so the service uses
it instead of a protocol of its own. Zenoh stays the data plane between vehicles and the service;
Ray only carries each sweep from the service to its session's actor and the result back.

The shape, next to the local executor (:class:`service.matchers.MatcherPool`)::

    open      -> RayMatcherPool.open(key, state, grid, settings, registration): one actor per
                 session (``_MatcherActor``), 0 CPUs reserved, on the live node with fewest of the
                 service's sessions (node affinity), never restarted by Ray (max_restarts=0)
    register  -> RayMatcher.register: one remote call per sweep, waited for, the sweep inline in
                 the call (RAY_INLINE_ENV); unless the session is behind, the actor rebuilds a
                 keyframe's model on a thread once the answer is out, and the next sweep waits
                 for it (as a matcher process rebuilds right after replying)
    errors    -> an exception raised in the actor is raised again as itself (Ray's wrapper
                 removed); a dead actor or node is a MatcherProcessDiedError, which the session
                 layer already handles: the session is dropped unsaved and resumed from the store
                 with its next scan, on a new actor, on a live node

Nothing here is imported unless ``executor="ray"`` (``pip install "randt-fleet[ray]"``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
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
)

__all__ = ["RayMatcher", "RayMatcherPool"]

log = logging.getLogger(__name__)

Key = tuple[str, str]


class ConfigurationError(RandtError):
    """The Ray executor cannot start as configured (Ray missing, or the cluster unreachable)."""


#: Ray settings (environment variables) under which calls carry a sweep inline.
RAY_INLINE_ENV = {
    "RAY_max_direct_call_object_size": str(8 << 20),
    "RAY_task_rpc_inlined_bytes_limit": str(16 << 20),
}

#: Ray's namespace for the service's actors.
RAY_NAMESPACE = "randt"


class _MatcherActor:
    """One session's :class:`~core.odometry.IncrementalMatcher` in a Ray worker (wrapped by
    ``ray.remote`` in :class:`RayMatcherPool`, so that importing this module needs no Ray)."""

    def __init__(
        self,
        state: dict[str, np.ndarray] | None,
        grid_params: tuple[int, float, int] | None,
        settings: MatcherSettings | None,
        registration: RegistrationSettings | None,
    ) -> None:
        single_threaded_blas()
        self.matcher = IncrementalMatcher(settings, registration)
        if state:
            self.matcher.load_state_dict(state)
        self.grid = None if grid_params is None else TileGrid(*grid_params)
        self._rebuild: threading.Thread | None = None

    def _rebuilt(self) -> None:
        """Wait for the model rebuild started after the previous answer, if one runs."""
        if self._rebuild is not None:
            self._rebuild.join()
            self._rebuild = None

    def register(
        self,
        xyz: np.ndarray,
        offsets: np.ndarray | None,
        prior: PosePrior | None,
        stamp_s: float | None,
        keyframe_voxel_m: float | None,
        behind: bool,
    ) -> Registered:
        """One sweep. Unless ``behind``, a keyframe's model is rebuilt on a thread of the actor
        once this answer is on its way (as a matcher process rebuilds after replying), and the
        next sweep waits for it: one remote call per sweep."""
        self._rebuilt()
        result = self.matcher.register_scan(
            xyz, time_offset_s=offsets, prior=prior, stamp_s=stamp_s, defer_model=True
        )
        if not behind and self.matcher.model_pending:
            self._rebuild = threading.Thread(target=self.matcher.update_model, daemon=True)
            self._rebuild.start()
        return _registered(result, self.grid, keyframe_voxel_m)

    def state(self) -> dict[str, np.ndarray]:
        self._rebuilt()
        return self.matcher.state_dict()

    def node_id(self) -> str:
        import ray

        return str(ray.get_runtime_context().get_node_id())


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
                # A sweep (0.3-0.5 MB of float32 points) and its answer travel inline in the call
                # rather than through the shared object store: Ray's own CPU 4.8 -> 1.2 ms per
                # sweep, mean latency 96 -> 88 ms (bench/service.py, 2 vehicles). A cluster
                # started with `ray start` takes the same variables (docs/deploy.md).
                for name, value in RAY_INLINE_ENV.items():
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
        self._actor_class = ray.remote(num_cpus=0, max_restarts=0)(_MatcherActor)
        self._lock = threading.Lock()
        self._open: dict[Key, Any] = {}
        self._node: dict[Key, str] = {}  # where each open session's actor was placed

    def __len__(self) -> int:
        """The cluster's live nodes."""
        return sum(1 for n in self._ray.nodes() if n.get("Alive"))

    @property
    def ready(self) -> bool:
        return self._ray.is_initialized()

    def wait_ready(self, timeout: float | None = None) -> bool:
        del timeout
        return self.ready

    def open(
        self,
        key: Key,
        state: dict[str, np.ndarray] | None = None,
        grid: TileGrid | None = None,
        settings: MatcherSettings | None = None,
        registration: RegistrationSettings | None = None,
    ) -> RayMatcher:
        """A matcher for session ``key`` (restored from ``state``) in a new actor, placed by Ray."""
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        params = None if grid is None else (grid.tile_size_m, grid.voxel_size_m, grid.max_points_per_voxel)
        alive = [str(n["NodeID"]) for n in self._ray.nodes() if n.get("Alive")]
        with self._lock:
            # The live node with fewest of our sessions (as the local pool places on the process
            # with fewest). Hard affinity: a soft one spilled over to the other node whenever this
            # one's worker was still starting; should the node die first, the actor's first call
            # fails and the session resumes on another (MatcherProcessDiedError).
            load = dict.fromkeys(alive, 0)
            for placed in self._node.values():
                if placed in load:
                    load[placed] += 1
            target = min(alive, key=lambda n: load[n]) if alive else None
            self._node[key] = target or ""
        options = (
            {}
            if target is None
            else {"scheduling_strategy": NodeAffinitySchedulingStrategy(target, soft=False)}
        )
        actor = self._actor_class.options(**options).remote(state, params, settings, registration)
        matcher = RayMatcher(self, actor, key, state)
        with self._lock:
            self._open[key] = actor
        return matcher

    def node_of(self, key: Key) -> str | None:
        """The Ray node id of the session's actor (None if it is not open or its node is gone)."""
        with self._lock:
            actor = self._open.get(key)
        if actor is None:
            return None
        try:
            return str(self._ray.get(actor.node_id.remote(), timeout=30))
        except self._ray.exceptions.RayError:
            return None

    def _release(self, key: Key, actor: Any) -> None:
        with self._lock:
            if self._open.get(key) is actor:
                del self._open[key]
                self._node.pop(key, None)
        with contextlib.suppress(self._ray.exceptions.RayError):
            self._ray.kill(actor, no_restart=True)

    def close(self) -> None:
        """Kill the actors still open (the sessions were saved first)."""
        with self._lock:
            actors, self._open, self._node = list(self._open.values()), {}, {}
        for actor in actors:
            with contextlib.suppress(self._ray.exceptions.RayError):
                self._ray.kill(actor, no_restart=True)


class RayMatcher(ForwardingMatcher):
    """A session's matcher in a Ray actor: the interface of :class:`service.matchers.RemoteMatcher`."""

    def __init__(
        self, pool: RayMatcherPool, actor: Any, key: Key, state: dict[str, np.ndarray] | None
    ) -> None:
        self._pool, self._actor, self._key = pool, actor, key
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
            raise MatcherProcessDiedError(
                f"the Ray actor of session {self._key[0]}/{self._key[1]} is gone: {type(exc).__name__}"
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
            self._actor.register.remote(points_xyz, time_offset_s, prior, stamp_s, keyframe_voxel_m, behind)
        )
        self.poses.append(registered.result.T_world_sensor)
        return registered

    def state_dict(self) -> dict[str, np.ndarray]:
        state: dict[str, np.ndarray] = self._get(self._actor.state.remote())
        return state

    def close(self) -> None:
        """Forget the session: its actor is killed (its state should have been saved first)."""
        self._pool._release(self._key, self._actor)
