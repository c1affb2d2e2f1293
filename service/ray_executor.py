"""The Ray executor: each session's matcher as a Ray actor, placed by Ray across a cluster's nodes.

Why Ray: a fleet outgrows one machine's cores long before it outgrows one map, and the matcher is
the expensive, stateful part. Ray places stateful actors on a cluster's nodes, notices dead nodes
and actors, and runs on one machine for tests (``ray.cluster_utils.Cluster``), so the service uses
it to place and supervise the matchers. Zenoh stays the data plane between vehicles and the
service; each sweep goes from the service to its session's host and back over the host's socket
(or, with transport ``"ray"``, in a Ray call).

The shape, next to the local executor (:class:`randt.service.matcher_pool.MatcherPool`)::

    hosts     -> RayMatcherPool(): one matcher host actor (``_MatcherHost``) per CPU of every live
                 node that has CPUs, 0 CPUs reserved, pinned to its node (node affinity), never
                 restarted by Ray (max_restarts=0), warmed up when it starts (the kernels loaded),
                 as the local pool's worker processes are; a node that joins gets its hosts at
                 the next session's open
    connect   -> (transport "socket", the default) each host listens on its node's address with a
                 secret the service gave it through Ray; the service connects at the host's first
                 use and speaks the local executor's protocol (service/matcher_host.py)
    open      -> RayMatcherPool.open(key, state, grid, settings, registration): the session's
                 matcher on the host with fewest sessions, on the node with fewest per CPU
    register  -> RayMatcher.register_payload: one request per sweep (the payload's bytes; the
                 host decodes them), waited for; unless the session is behind, the host rebuilds
                 a keyframe's model on a thread beside the answer, and the session's next request
                 waits for it (as in a matcher process)
    errors    -> an exception raised in the host is raised again as itself; a closed connection,
                 or a late answer from a host that Ray reports dead (a node whose machine died
                 cannot close its sockets), is a MatcherProcessDiedError, which the session layer
                 already handles: the session is dropped unsaved and resumed from the store with
                 its next scan, on a live host: not on the dead host's node for SUSPECT_NODE_S
                 while another node can take it (Ray may report a dead machine's node alive
                 for seconds, and a fresh host there fails too)

Why hosts rather than one actor per session: a new actor is a new process that loads the kernels,
and the session's first sweeps would queue behind it. Why a socket rather than a Ray call per
sweep: the socket costs a fraction of a Ray call's time and CPU (bench/ray_call.py), on the cores
the matchers need; Ray's compiled graphs were as fast but spin a core per idle host.

Nothing here is imported unless ``executor="ray"`` (``pip install "randt-fleet[ray]"``).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import socket
import threading
import time
from dataclasses import dataclass, field
from multiprocessing import AuthenticationError
from multiprocessing.connection import Connection, answer_challenge, deliver_challenge
from typing import Any, Literal

import numpy as np

from randt.core.config import RegistrationSettings
from randt.core.errors import RandtError
from randt.core.odometry import MatcherSettings
from randt.core.tiles import TileGrid
from randt.service.matcher_host import READY, _Sessions, serve_requests, warm_up
from randt.service.matcher_io import Key, MatcherProcessDiedError
from randt.service.matcher_pool import Channel, ForwardingMatcher
from randt.service.processes import single_threaded_blas

__all__ = ["RayMatcher", "RayMatcherPool"]

log = logging.getLogger(__name__)


class ConfigurationError(RandtError):
    """The Ray executor cannot start as configured (Ray missing, or the cluster unreachable)."""


#: Ray settings (environment variables) for the per-sweep call: the sweep and its answer travel
#: inline in the call rather than through Ray's object store (less of Ray's own CPU per sweep),
#: and no task events or metrics are recorded per call (the service has its own).
RAY_ENV = {
    "RAY_max_direct_call_object_size": str(8 << 20),
    "RAY_task_rpc_inlined_bytes_limit": str(16 << 20),
    "RAY_task_events_report_interval_ms": "0",
    "RAY_enable_metrics_collection": "0",
    # Ray starts its workers at nice 15: a matcher host then yields its core to the service and
    # every other process, and the sweeps wait. The matchers are the work; they run at the
    # service's priority.
    "RAY_worker_niceness": "0",
}

#: Ray's namespace for the service's actors.
RAY_NAMESPACE = "randt"


class _MatcherHost:
    """Several sessions' :class:`~randt.core.odometry.IncrementalMatcher` in one Ray worker process,
    one request at a time (wrapped by ``ray.remote`` in :class:`RayMatcherPool`, so that importing
    this module needs no Ray): the actor counterpart of a local matcher process
    (:func:`randt.service.matcher_host.serve_process`), warmed up the same way when it starts.

    Two ways in, one per pool (``transport``): the service's socket (:meth:`listen`: the local
    executor's protocol, :func:`randt.service.matcher_host.serve_requests`, on a connection of its
    own), or a Ray call per request (:meth:`call`, the same requests)."""

    def __init__(self) -> None:
        single_threaded_blas()
        _normal_priority()
        try:
            warm_up()
        except Exception:  # a failed warm-up only costs the first sweep its compile time
            log.exception("matcher host warm-up failed")
        self.sessions = _Sessions()  # (with the CPU each sweep costs, as the local executor measures it)

    def ready(self) -> str:
        """The node this host runs on, once warmed up."""
        import ray

        return str(ray.get_runtime_context().get_node_id())

    def niceness(self) -> int:
        """This host's nice value (0 unless the node starts workers niced and we may not undo it)."""
        return os.nice(0)

    # -- the socket ---------------------------------------------------------------------------------
    def listen(self, authkey: bytes) -> tuple[str, int]:
        """Listen on this node's address for the service (``authkey``: the connection's secret,
        handed over through Ray) and serve each connection that proves it knows the secret as a
        matcher process serves its pipe. Returns the address to connect to."""
        import ray

        ip = ray.util.get_node_ip_address()
        server = socket.create_server((ip, 0), family=socket.AF_INET6 if ":" in ip else socket.AF_INET)
        threading.Thread(
            target=self._accept, args=(server, authkey), name="randt-host-listen", daemon=True
        ).start()
        host, port = server.getsockname()[:2]
        return str(host), int(port)

    def _accept(self, server: socket.socket, authkey: bytes) -> None:
        """Each connection on a thread of its own, so one that never completes the handshake
        cannot keep the service's out."""
        while True:
            try:
                sock, _ = server.accept()
            except OSError:
                return
            threading.Thread(
                target=self._serve_connection, args=(sock, authkey), name="randt-host-conn", daemon=True
            ).start()

    def _serve_connection(self, sock: socket.socket, authkey: bytes) -> None:
        sock.settimeout(None)  # blocking (a default timeout would make the descriptor non-blocking)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn = Connection(sock.detach())
        try:
            deliver_challenge(conn, authkey)
            answer_challenge(conn, authkey)
        except (AuthenticationError, EOFError, OSError) as exc:
            log.warning("matcher host: refused a connection without the service's key (%s)", exc)
            conn.close()
            return
        try:
            conn.send(READY)
            serve_requests(conn, self.sessions)
        except (EOFError, OSError):
            pass
        finally:
            conn.close()

    # -- Ray calls ----------------------------------------------------------------------------------
    def call(self, op: str, key: Key, *args: Any) -> Any:
        """One request of :func:`randt.service.matcher_host.serve_requests`' protocol as a Ray call
        (transport "ray"): a keyframe's model is rebuilt on a thread beside the answer, and the
        session's next request waits for it, as in a matcher process. One remote call per sweep."""
        return self.sessions.handle(op, key, args)


def _normal_priority() -> None:
    """Run this matcher host at nice 0 if Ray started it niced (a node without
    ``RAY_worker_niceness=0``: Ray's default is 15). Lowering a nice value needs root or
    CAP_SYS_NICE; without them the host stays niced and says so."""
    if os.nice(0) <= 0:
        return
    try:
        os.setpriority(os.PRIO_PROCESS, 0, 0)
    except OSError:
        log.warning(
            "matcher host runs at nice %d (Ray's worker niceness) and may not change it: set "
            "RAY_worker_niceness=0 in the environment of `ray start` on every node (docs/deploy.md)",
            os.nice(0),
        )


def _no_delay(conn: Connection) -> None:
    """Send small writes at once on ``conn``'s socket (``multiprocessing.connection`` writes a
    message's length and its body separately: Nagle's algorithm would hold the body back)."""
    with socket.socket(fileno=os.dup(conn.fileno())) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class _SocketChannel(Channel):
    """The service's connection to a matcher host's socket. A host on another machine that dies
    with its machine cannot close the connection: while an answer is late, the host is asked
    through Ray whether it still lives (Ray notices dead nodes)."""

    def __init__(self, conn: Connection, name: str, ray: Any, actor: Any) -> None:
        super().__init__(conn, name)
        self._ray, self._actor = ray, actor

    def _wait_answer(self) -> None:
        ping = None
        while not self._conn.poll(ANSWER_CHECK_S):
            if ping is None:
                ping = self._actor.ready.remote()
            done, _ = self._ray.wait([ping], timeout=0)
            if done:
                try:
                    self._ray.get(ping)
                except self._ray.exceptions.RayError as exc:
                    raise EOFError(f"its Ray actor is gone ({type(exc).__name__})") from exc
                ping = None


#: How long an answer over a host's socket may take before the host is asked through Ray whether
#: it still lives (and again every as long after).
ANSWER_CHECK_S = 2.0

#: How long the service tries to connect to a matcher host's socket.
CONNECT_TIMEOUT_S = 10.0
#: After a host dies, its node gets no new host and no session for this long while another node
#: can take them: Ray may still report a node alive for seconds after its machine died, and a
#: session resumed on a new host there would fail a second time.
SUSPECT_NODE_S = 60.0


@dataclass(eq=False)
class _Host:
    """The service's handle on one :class:`_MatcherHost` actor."""

    actor: Any
    node: str  # the Ray node it was placed on
    ready: Any  # the reference of its ``ready`` (or ``listen``) call: resolves once warmed up
    authkey: bytes = b""  # the socket's secret (transport "socket")
    sessions: set[Key] = field(default_factory=set)
    dead: bool = False
    channel: _SocketChannel | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)


Transport = Literal["socket", "ray"]


class RayMatcherPool:
    """The Ray executor (module docstring): the same interface as
    :class:`randt.service.matcher_pool.MatcherPool`.

    ``address``: a running cluster's (``ray://`` or ``host:port``); None starts a local Ray (or
    joins the one this process already initialized). A cluster that does not answer yet (its head
    still starting) is tried again for ``join_timeout_s``.

    ``transport``: how a sweep reaches its host. ``"socket"`` (the default): over a TCP connection
    from the service to each host (the local executor's protocol, authenticated with a secret
    handed over through Ray; Ray places and supervises the hosts): a fraction of a Ray call's
    cost (bench/ray_call.py), and the service must reach the nodes' addresses on ephemeral ports.
    ``"ray"``: every sweep a Ray actor call (only Ray's own ports needed)."""

    def __init__(
        self, address: str | None = None, transport: Transport = "socket", join_timeout_s: float = 60.0
    ) -> None:
        try:
            import ray
        except ImportError as exc:
            raise ConfigurationError(
                'executor "ray" needs the ray package: pip install "randt-fleet[ray]"'
            ) from exc
        if transport not in ("socket", "ray"):
            raise ConfigurationError(f'executor ray: transport must be "socket" or "ray", got {transport!r}')

        self._ray = ray
        self.transport = transport
        if not ray.is_initialized():
            if address is None:
                # RAY_ENV: sweeps inline in the calls, no per-call task events. A cluster started
                # with `ray start` takes the same variables (docs/deploy.md, docker/compose.yaml).
                for name, value in RAY_ENV.items():
                    os.environ.setdefault(name, value)
            self._join(address, join_timeout_s)
        self._host_class = ray.remote(num_cpus=0, max_restarts=0)(_MatcherHost)
        self._lock = threading.Lock()
        self._hosts: list[_Host] = []
        self._placed: dict[Key, _Host] = {}
        #: node -> when (monotonic) a host on it was last found dead (SUSPECT_NODE_S).
        self._suspect: dict[str, float] = {}
        with self._lock:
            self._refresh()

    def _join(self, address: str | None, timeout_s: float) -> None:
        """``ray.init``, tried again every 2 s for ``timeout_s`` while a cluster at ``address``
        does not answer (a head started with the service takes a few seconds to serve clients)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self._ray.init(
                    address=address,
                    namespace=RAY_NAMESPACE,
                    include_dashboard=False,
                    logging_level=logging.WARNING,
                    log_to_driver=False,
                )
                return
            except (ConnectionError, RuntimeError, ValueError) as exc:
                where = f"the Ray cluster at {address}" if address else "a local Ray"
                if address is None or isinstance(exc, ValueError) or time.monotonic() > deadline:
                    raise ConfigurationError(f"executor ray: cannot start or join {where}: {exc}") from exc
                log.warning("executor ray: %s does not answer yet (%s): trying again", where, exc)
                with contextlib.suppress(Exception):
                    self._ray.shutdown()
                time.sleep(2.0)

    def cpus(self) -> float:
        """The CPUs of the live nodes that run matchers (admission's capacity: service/capacity.py)."""
        try:
            return float(sum(self._nodes().values()))
        except Exception:  # Ray unreachable for a moment: say none rather than fail an admission
            log.warning("executor ray: could not read the cluster's CPUs", exc_info=True)
            return 0.0

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
        trusted = {n: c for n, c in nodes.items() if not self._is_suspect(n)}
        for node, cpus in (trusted or nodes).items():
            for _ in range(cpus - sum(1 for h in self._hosts if h.node == node)):
                # Hard affinity: a soft one spilled over to another node while this one's worker
                # was starting. Should the node die first, the first call fails and the session
                # resumes on another (MatcherProcessDiedError).
                actor: Any = self._host_class.options(
                    scheduling_strategy=NodeAffinitySchedulingStrategy(node, soft=False)
                ).remote()
                if self.transport == "socket":
                    key = os.urandom(32)
                    self._hosts.append(_Host(actor, node, actor.listen.remote(key), key))
                else:
                    self._hosts.append(_Host(actor, node, actor.ready.remote()))

    def _channel(self, host: _Host) -> _SocketChannel:
        """The connection to ``host``'s socket, made at its first use (once the host listens)."""
        with host.lock:
            if host.channel is not None:
                return host.channel
            name = f"Ray matcher host on node {host.node[:12]}"
            try:
                address = tuple(self._ray.get(host.ready))
            except self._ray.exceptions.RayError as exc:
                self._died(host)
                raise MatcherProcessDiedError(f"{name} is gone: {type(exc).__name__}") from exc
            try:
                sock = socket.create_connection(address, timeout=CONNECT_TIMEOUT_S)
                sock.settimeout(None)
                conn = Connection(sock.detach())
                answer_challenge(conn, host.authkey)
                deliver_challenge(conn, host.authkey)
                _no_delay(conn)
            except (OSError, EOFError, AuthenticationError) as exc:
                self._died(host)
                log.error(
                    "executor ray: cannot connect to the %s at %s:%s (%s): the service must reach "
                    'every Ray node\'s address on ephemeral TCP ports (or use transport "ray")',
                    name,
                    *address,
                    exc,
                )
                raise MatcherProcessDiedError(f"cannot connect to the {name} at {address}: {exc}") from exc
            host.channel = _SocketChannel(conn, f"{name} at {address[0]}:{address[1]}", self._ray, host.actor)
            return host.channel

    def _is_suspect(self, node: str) -> bool:
        """A host on ``node`` died less than :data:`SUSPECT_NODE_S` ago (called with the lock)."""
        return time.monotonic() - self._suspect.get(node, -math.inf) < SUSPECT_NODE_S

    def _died(self, host: _Host) -> None:
        """A call on ``host`` found its actor or node gone: place no one there again, and no one
        on its node for a while (:data:`SUSPECT_NODE_S`)."""
        with self._lock:
            host.dead = True
            self._suspect[host.node] = time.monotonic()
        if host.channel is not None:
            host.channel.close()

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
            trusted = [h for h in self._hosts if not self._is_suspect(h.node)]
            for h in trusted or self._hosts:
                per_node.setdefault(h.node, []).append(h)
            load = {n: sum(len(h.sessions) for h in hs) / len(hs) for n, hs in per_node.items()}
            node = min(per_node, key=lambda n: load[n])
            host = min(per_node[node], key=lambda h: len(h.sessions))
            host.sessions.add(key)
            self._placed[key] = host
        matcher = RayMatcher(self, host, key, state)
        try:
            matcher._call("open", state, params, settings, registration)
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
            if host.channel is not None:
                host.channel.close()
            with contextlib.suppress(self._ray.exceptions.RayError):
                self._ray.kill(host.actor, no_restart=True)


class RayMatcher(ForwardingMatcher):
    """A session's matcher in a Ray actor: the interface of
    :class:`randt.service.matcher_pool.RemoteMatcher`, over the host's socket or a Ray call."""

    def __init__(
        self, pool: RayMatcherPool, host: _Host, key: Key, state: dict[str, np.ndarray] | None
    ) -> None:
        self._pool, self._host, self._key = pool, host, key
        super().__init__(state)

    def _call(self, op: str, *args: Any) -> Any:
        """``op`` on the session's host, over its socket or as a Ray call (the pool's transport):
        the value; an exception raised there raised as itself; a dead host or node is a
        :class:`MatcherProcessDiedError`."""
        if self._pool.transport == "socket":
            try:
                return self._pool._channel(self._host).call(op, self._key, *args)
            except MatcherProcessDiedError:
                self._pool._died(self._host)
                raise
        ray = self._pool._ray
        try:
            return ray.get(self._host.actor.call.remote(op, self._key, *args))
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

    def close(self) -> None:
        """Forget the session in its host (its state should have been saved first)."""
        self._pool._release(self._key, self._host)
        if self._host.dead:
            return
        if self._pool.transport == "socket":
            with contextlib.suppress(MatcherProcessDiedError):
                self._call("drop")
        else:  # not waited for: the host's next request follows it
            self._host.actor.call.remote("drop", self._key)
