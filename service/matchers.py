"""Where the sessions' matchers run: worker processes, so the numeric work uses every core.

Measured (``bench/workers.py``, KITTI 00 sessions on this 2-core machine): two sessions on two
threads ran 1.18x the sequential rate, on two processes 1.64x; four sessions 1.35x against 1.66x.
Our kernels and numpy release the GIL, but the matcher's Python glue between them does not, so
threads serialize a third of the work. The service therefore runs the matchers in a pool of
worker processes (``matcher_processes`` in the settings: one per core by default, 0 keeps them in
the session threads).

Each session thread still owns its queue and its order; it hands one sweep at a time to its
:class:`RemoteMatcher`, which forwards it to the process the session was assigned to (the one
with fewest sessions) and waits for the result. A process serves its sessions one request at a
time. Requests and results are pickled through a pipe (a 120k-point sweep and its result are a
few MB: about 5 ms against 100-300 ms of matching).

An exception raised in a worker process reaches the session thread as the same class with the
same attributes (a :class:`~randt.core.errors.DegenerateProblemError` keeps its ``weak_directions``, a
``ValueError`` stays a ``ValueError``), the worker's traceback attached as a note; one that cannot
be pickled arrives as a :class:`MatcherProcessError` naming it. If a worker process dies, the calls
on it raise :class:`MatcherProcessDiedError`; the session manager then drops the affected sessions
without saving them (their last snapshot plus their pose log is the truth) and the next scan
resumes each from the store on a fresh process.

A snapshot's matcher state leaves the trajectory out (:meth:`SessionMatcher.snapshot_state`,
:func:`without_trajectory`): the store already holds every pose (its pose log), so what crosses
the pipe and is written does not grow with the session's length; :func:`with_trajectory` puts it
back when the session resumes.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import pickle
import threading
import time
import traceback
from collections.abc import Iterator
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection
from typing import Any, Protocol

import numpy as np

from randt.core.config import RegistrationSettings
from randt.core.errors import FormatError, RandtError
from randt.core.odometry import IncrementalMatcher, MatcherSettings, PosePrior, ScanResult
from randt.core.tiles import SentVoxels, TileGrid
from randt.core.transforms import invert, transform_points
from randt.core.voxel import pack_keys, voxel_coords
from randt.service.processes import (
    ignore_group_signals,
    single_threaded_blas,
    start_ignoring_group_signals,
)
from randt.wire.messages import ScanHeader, ScanMessage, WireLimits, decode_scan
from randt.wire.ros2 import Ros2Scan, sweep_arrays

__all__ = [
    "CpuLedger",
    "LocalMatcher",
    "MapFrame",
    "MatcherExecutor",
    "MatcherPool",
    "MatcherProcessDiedError",
    "MatcherProcessError",
    "Registered",
    "RemoteMatcher",
    "SessionMatcher",
    "ignore_group_signals",
    "prior_of",
    "single_threaded_blas",
    "start_ignoring_group_signals",
    "warm_up",
    "with_trajectory",
    "without_trajectory",
]

log = logging.getLogger(__name__)

Key = tuple[str, str]


class SessionMatcher(Protocol):
    """What a session worker asks of its matcher, wherever it runs: in the session thread
    (:class:`LocalMatcher`), in a worker process (:class:`RemoteMatcher`) or in a Ray actor
    (:class:`randt.service.ray_executor.RayMatcher`)."""

    @property
    def poses(self) -> list[np.ndarray]: ...

    def register(
        self,
        points_xyz: np.ndarray,
        *,
        time_offset_s: np.ndarray | None = None,
        prior: PosePrior | None = None,
        stamp_s: float | None = None,
        behind: bool = False,
        keyframe_voxel_m: float | None = None,
        frame: MapFrame | None = None,
    ) -> Registered: ...

    def register_payload(
        self,
        payload: bytes | Ros2Scan,
        *,
        limits: WireLimits | None = None,
        behind: bool = False,
        keyframe_voxel_m: float | None = None,
        frame: MapFrame | None = None,
    ) -> Registered: ...

    def update_model(self) -> float: ...

    def state_dict(self) -> dict[str, np.ndarray]: ...

    def snapshot_state(self) -> dict[str, np.ndarray]:
        """:meth:`state_dict` without the trajectory (:func:`without_trajectory`), for a snapshot."""
        ...

    def close(self) -> None: ...


#: A snapshot's matcher state keeps the number of poses it was taken at under this key, in place
#: of the poses themselves (:func:`without_trajectory`).
TRAJECTORY_LENGTH_KEY = "n_poses"


def without_trajectory(state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """An :meth:`IncrementalMatcher.state_dict <randt.core.odometry.IncrementalMatcher.state_dict>` for a
    snapshot: its ``poses`` (N, 4, 4), which grow with the session, replaced by N
    (:data:`TRAJECTORY_LENGTH_KEY`). The store holds the trajectory (every pose is logged before
    it is published); :func:`with_trajectory` undoes this."""
    out = {key: value for key, value in state.items() if key != "poses"}
    n = np.asarray(state["poses"]).reshape(-1, 4, 4).shape[0]
    out[TRAJECTORY_LENGTH_KEY] = np.array(n, dtype=np.int64)
    return out


def with_trajectory(state: dict[str, np.ndarray], poses: np.ndarray) -> dict[str, np.ndarray]:
    """The state :meth:`IncrementalMatcher.load_state_dict
    <randt.core.odometry.IncrementalMatcher.load_state_dict>` takes, from a snapshot's
    (:func:`without_trajectory`) and the stored trajectory ``poses`` (N, 4, 4): its first
    ``n_poses`` poses go back in. A state that kept its poses (snapshots written before) is
    returned as it is.

    Raises
    ------
    FormatError
        The trajectory is shorter than the snapshot's.
    """
    if "poses" in state or TRAJECTORY_LENGTH_KEY not in state:
        return state
    n = int(state[TRAJECTORY_LENGTH_KEY])
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if not 0 <= n <= poses.shape[0]:
        raise FormatError(f"the matcher state was taken at {n} poses, the trajectory has {poses.shape[0]}")
    out = {key: value for key, value in state.items() if key != TRAJECTORY_LENGTH_KEY}
    out["poses"] = poses[:n].copy()
    return out


class MatcherExecutor(Protocol):
    """Where the sessions' matchers run (``executor`` in the settings): local worker processes
    (:class:`MatcherPool`) or Ray actors (:class:`randt.service.ray_executor.RayMatcherPool`). Order,
    back-pressure and drops stay the session layer's, the same for both."""

    @property
    def ready(self) -> bool: ...

    def wait_ready(self, timeout: float | None = None) -> bool: ...

    def open(
        self,
        key: Key,
        state: dict[str, np.ndarray] | None = None,
        grid: TileGrid | None = None,
        settings: MatcherSettings | None = None,
        registration: RegistrationSettings | None = None,
    ) -> SessionMatcher: ...

    def close(self) -> None: ...


class MatcherProcessError(RandtError, RuntimeError):
    """A matcher worker process failed: an error raised there could not be sent back as itself."""


class MatcherProcessDiedError(MatcherProcessError):
    """The worker process holding a session's matcher is gone (the session must be resumed)."""


def _portable(exc: Exception) -> Exception:
    """``exc`` with the worker's traceback as a note, if it survives pickling; else a
    :class:`MatcherProcessError` naming it (the caller's ``recv`` must never fail to unpickle)."""
    exc.add_note(f"raised in matcher process pid {os.getpid()}:\n{''.join(traceback.format_exception(exc))}")
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:
        return MatcherProcessError(f"in matcher process pid {os.getpid()}: {type(exc).__name__}: {exc}")
    return exc


@dataclass(frozen=True, eq=False)
class MapFrame:
    """Where a sweep's map points go, as the session thread knows it when it sends the sweep.

    Attributes
    ----------
    token:
        The map's content and identity (its name and :attr:`randt.core.tiles.TileGrid.content_token`):
        a matcher that knows the map sends only the voxels it has not sent under the same token
        (:class:`randt.core.tiles.SentVoxels`) and starts over when it changes.
    correction:
        The pose graph's newest correction of the session (4x4), which moves the map points
        before they are folded (``None``: none yet). The matcher applies it with the pose, so
        the points arrive in the frame they are folded in.
    seed_xyz:
        With a session's first sweep that carries a prior: the map's points around the prior
        (world frame, float32), which the matcher places the sweep against
        (:meth:`randt.core.odometry.IncrementalMatcher.register_scan`'s ``map_seed``); ``None`` else.
    prior:
        The scan's prior in the map frame when the session thread placed it there (a WGS84
        ``geo_prior``, through the map's geodetic origin: core/geo.py); it replaces the payload's
        own (which then has none). ``None``: the payload's ``prior``, if any.
    """

    token: tuple[str, int, int]
    correction: np.ndarray | None = None
    seed_xyz: np.ndarray | None = None
    prior: PosePrior | None = None


@dataclass(frozen=True)
class Registered:
    """A registered sweep and the points of it that the session's map may keep.

    Attributes
    ----------
    result:
        The matcher's :class:`~randt.core.odometry.ScanResult`. From a matcher process that knows the
        session's map, its ``deskewed_xyz`` and ``map_index`` are empty: ``map_xyz`` and
        ``map_index`` below replace them (nothing is sent twice).
    map_xyz:
        (M, 3) float32 points in the map frame, ready for :meth:`randt.core.tiles.TileGrid.insert`
        (which stores float32): the deskewed sweep moved by the pose, cut to the points the map
        can keep (:meth:`~randt.core.tiles.TileGrid.candidate_mask`) when the map is known; none for
        a ``fallback`` result (its points are not folded into the map).
    map_index:
        (M,) rows of the sweep as sent, for each point of ``map_xyz`` (its intensity).
    keyframe_xyz, keyframe_index:
        When asked for (``keyframe_voxel_m``): the sweep's mappable points, deskewed, in the
        sensor frame, the first of each voxel (real points, float32), for the pose graph and the
        re-folding of the map (service/graph.py), and their rows in the sweep as sent (their
        intensity); else ``None``, and always ``None`` for a fallback.
    map_intensity, keyframe_intensity:
        From :meth:`register_payload` (the sweep decoded where it was matched): the intensity
        (float32) of each point of ``map_xyz`` and ``keyframe_xyz``; ``None`` when the sweep has
        none, or when the caller holds the sweep (``register``) and reads them by index.
    correction:
        The correction ``map_xyz`` was moved by (the :class:`MapFrame`'s), ``None`` for none.
    cpu_s:
        CPU seconds the matcher's thread spent on this sweep where it ran: decoding, matching, and
        the keyframe model's rebuild after the session's previous sweep (service/capacity.py).
    """

    result: ScanResult
    map_xyz: np.ndarray
    map_index: np.ndarray
    keyframe_xyz: np.ndarray | None = None
    keyframe_index: np.ndarray | None = None
    map_intensity: np.ndarray | None = None
    keyframe_intensity: np.ndarray | None = None
    correction: np.ndarray | None = None
    cpu_s: float = 0.0

    def map_points_under(self, correction: np.ndarray | None) -> np.ndarray:
        """``map_xyz`` moved from the correction they were sent with to ``correction`` (the
        pose graph corrected the session while the sweep was matched); ``map_xyz`` itself when
        the two are equal (``None``: no correction)."""
        sent = self.correction
        if correction is sent or (
            correction is not None and sent is not None and np.array_equal(correction, sent)
        ):
            return self.map_xyz
        C = np.eye(4) if correction is None else correction
        D = C if sent is None else C @ invert(sent)
        return transform_points(D, self.map_xyz).astype(np.float32)


def decoded_sweep(
    payload: bytes | Ros2Scan, limits: WireLimits | None, frame: MapFrame | None = None
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, PosePrior | None, float]:
    """A scan payload decoded for the matcher (:func:`randt.wire.messages.decode_scan`: v2 bodies
    decompressed here; a ROS 2 PointCloud2 by :func:`randt.wire.ros2.sweep_arrays`): ``(xyz float32
    view, time offsets float32 or None, intensity float32 or None, prior, stamp s)``; the prior is
    ``frame``'s when it has one (:attr:`MapFrame.prior`). Raises
    :class:`~randt.core.errors.BadMessageError` as the decoder does."""
    if isinstance(payload, Ros2Scan):
        xyz, offsets, intensity, stamp_s = sweep_arrays(payload)
        return xyz, offsets, intensity, None if frame is None else frame.prior, stamp_s
    scan = decode_scan(payload, limits)
    offsets = None if scan.time_offsets is None else np.frombuffer(scan.time_offsets, dtype="<f4")
    prior = frame.prior if frame is not None and frame.prior is not None else prior_of(scan)
    return scan.points_f32()[:, :3], offsets, scan.intensity(), prior, scan.stamp_ns * 1e-9


def prior_of(scan: ScanMessage | ScanHeader) -> PosePrior | None:
    """The scan's prior pose (GNSS/INS) with its covariance, if it carries one."""
    pose = scan.prior_pose()
    if pose is None:
        return None
    cov = scan.prior_covariance()
    assert cov is not None  # a scan's prior carries both
    return PosePrior(pose, cov)


def _with_intensity(registered: Registered, intensity: np.ndarray | None) -> Registered:
    """``registered`` with the intensities of its map and keyframe points (none without)."""
    if intensity is None:
        return registered
    kf = registered.keyframe_index
    return replace(
        registered,
        map_intensity=intensity[registered.map_index],
        keyframe_intensity=None if kf is None else intensity[kf],
    )


def _registered(
    result: ScanResult,
    grid: TileGrid | None,
    keyframe_voxel_m: float | None = None,
    frame: MapFrame | None = None,
    sent: SentVoxels | None = None,
) -> Registered:
    """:class:`Registered` of a result: its points in the map frame (float32, moved by the
    frame's correction), cut to those the map could keep when its sizes are known (``grid``):
    to the voxels not sent before under the frame's token (``sent``, with a ``frame``), else to
    the candidates (:meth:`TileGrid.candidate_mask`); and the keyframe's points when
    ``keyframe_voxel_m`` is given. A fallback keeps no points."""
    if result.status == "fallback":
        return Registered(result, np.empty((0, 3), np.float32), np.empty(0, np.intp))
    keyframe = keyframe_index = None
    if keyframe_voxel_m is not None and len(result.deskewed_xyz):
        keys = pack_keys(voxel_coords(result.deskewed_xyz, keyframe_voxel_m))
        _, first = np.unique(keys, return_index=True)
        keyframe = result.deskewed_xyz[first].astype(np.float32)
        keyframe_index = result.map_index[first]
    C = None if frame is None else frame.correction
    T = result.T_world_sensor if C is None else C @ result.T_world_sensor
    world = transform_points(T, result.deskewed_xyz)
    if grid is None:
        return Registered(
            result, world.astype(np.float32), result.map_index, keyframe, keyframe_index, correction=C
        )
    keep = grid.candidate_mask(world) if frame is None or sent is None else sent.admitted(world, frame.token)
    slim = replace(result, deskewed_xyz=np.empty((0, 3)), map_index=np.empty(0, np.intp))
    return Registered(
        slim, world[keep].astype(np.float32), result.map_index[keep], keyframe, keyframe_index, correction=C
    )


def warm_up() -> None:
    """Load (or compile) the numba kernels before the first sweep arrives: an incremental matcher
    fed three sweeps of a small synthetic room (registration, Algorithm 1, feature extraction and
    the map's candidate mask) and one pairwise registration with the default settings (moving-point
    selection and the SVD step, which a matcher configured so would use), so a vehicle's first scan
    does not pay for it. With a cold numba cache this compiles for about 10 s; from the cache it
    takes about 1 s."""
    from randt.core.registration import register
    from randt.core.scenes import synthetic_room

    room = synthetic_room(np.random.default_rng(0), 5000)
    register(room + [0.2, 0.1, 0.0], room)
    matcher = IncrementalMatcher()
    grid = TileGrid()
    for i in range(3):
        result = matcher.register_scan(room - [0.1 * i, 0.0, 0.0])
        grid.candidate_mask(transform_points(result.T_world_sensor, result.deskewed_xyz))


#: The first message a worker process sends, once warmed up (:meth:`MatcherPool.wait_ready`).
_READY = (True, "ready")


class _Sessions:
    """The matchers of one worker (a matcher process, a Ray matcher host): one per session key,
    with an empty grid of each session's map (its sizes and cap) to cut the answers to."""

    def __init__(self) -> None:
        self.matchers: dict[Key, IncrementalMatcher] = {}
        self.grids: dict[Key, TileGrid | None] = {}
        self.sent: dict[Key, SentVoxels] = {}
        self.ledger = CpuLedger()
        self.rebuilds = _Rebuilds(self.ledger)

    def open(
        self,
        key: Key,
        state: dict[str, np.ndarray] | None,
        grid_params: tuple[int, float, int] | None,
        settings: MatcherSettings | None,
        registration: RegistrationSettings | None,
    ) -> None:
        matcher = IncrementalMatcher(settings, registration)
        if state:
            matcher.load_state_dict(state)
        self.matchers[key] = matcher
        self.grids[key] = None if grid_params is None else TileGrid(*grid_params)
        if grid_params is not None:
            self.sent[key] = SentVoxels(*grid_params)

    def register(
        self,
        key: Key,
        xyz: np.ndarray,
        offsets: np.ndarray | None,
        prior: PosePrior | None,
        stamp_s: float | None,
        keyframe_voxel_m: float | None,
        frame: MapFrame | None = None,
        rebuild: bool = False,
    ) -> Registered:
        """One sweep. A keyframe's model rebuild is deferred: with ``rebuild`` it starts on a thread
        at once (:class:`_Rebuilds`), beside the rest of this request and the reply, else it is
        left for the caller (``self.matchers[key].model_pending``). With the session's map known,
        only the points it could keep go back, already in the frame they are folded in (float32,
        as the map stores them): with a ``frame``, those of voxels not sent before
        (:class:`SentVoxels`, about a tenth of a sweep once the map around the vehicle is built),
        else the candidates (about a quarter); the service process's insert handles those and
        transforms nothing."""
        matcher = self.matchers[key]
        result = matcher.register_scan(
            xyz,
            time_offset_s=offsets,
            prior=prior,
            stamp_s=stamp_s,
            defer_model=True,
            map_seed=None if frame is None else frame.seed_xyz,
        )
        if rebuild and matcher.model_pending:  # (it and _registered only read the sweep's points)
            self.rebuilds.start(key, matcher)
        return _registered(result, self.grids.get(key), keyframe_voxel_m, frame, self.sent.get(key))

    def register_payload(
        self,
        key: Key,
        payload: bytes | Ros2Scan,
        limits: WireLimits | None,
        keyframe_voxel_m: float | None,
        frame: MapFrame | None = None,
        rebuild: bool = False,
    ) -> Registered:
        """:meth:`register` of a scan payload, decoded here (:func:`decoded_sweep`): the service
        process routes the bytes and reads only the header, the numeric work is the worker's."""
        xyz, offsets, intensity, prior, stamp_s = decoded_sweep(payload, limits, frame)
        registered = self.register(key, xyz, offsets, prior, stamp_s, keyframe_voxel_m, frame, rebuild)
        return _with_intensity(registered, intensity)

    def state(self, key: Key) -> dict[str, np.ndarray]:
        return self.matchers[key].state_dict()

    def snapshot(self, key: Key) -> dict[str, np.ndarray]:
        """The session's state for a snapshot: what crosses the pipe does not grow with its length."""
        return without_trajectory(self.matchers[key].state_dict())

    def drop(self, key: Key) -> bool:
        self.grids.pop(key, None)
        self.sent.pop(key, None)
        return self.matchers.pop(key, None) is not None

    def _catch_up(self, key: Key, behind: bool) -> None:
        """A session that is not behind matches against its whole model: a keyframe whose rebuild
        was left while it was behind is folded in before its next sweep. Only a session that is
        behind lets the model lag (else one vehicle's trajectory depended on when its requests met
        others': the same 600 sweeps gave 11.3, 11.7 and 15.6 cm max error in the service against
        8.4 cm offline)."""
        matcher = self.matchers.get(key)
        if matcher is not None and not behind:
            matcher.update_model()

    def handle(self, op: str, key: Key, args: tuple[Any, ...]) -> Any:
        """One request of the protocol (``open``, ``register``, ``register_payload``, ``state``,
        ``snapshot``, ``drop``): its value, a :class:`Registered` billed with the CPU it cost
        (:class:`CpuLedger`). The session's model rebuild started by its previous sweep is waited
        for first; a ``register`` whose session is not behind starts its keyframe's rebuild
        (:meth:`register`)."""
        self.rebuilds.wait(key)
        t0 = time.thread_time()
        value = self._value(op, key, args)
        return self.ledger.bill(op, key, value, time.thread_time() - t0)

    def _value(self, op: str, key: Key, args: tuple[Any, ...]) -> Any:
        if op == "open":
            return self.open(key, *args)
        if op == "register":
            xyz, offsets, prior, stamp_s, behind, keyframe_voxel_m, frame = args
            self._catch_up(key, behind)
            return self.register(key, xyz, offsets, prior, stamp_s, keyframe_voxel_m, frame, not behind)
        if op == "register_payload":
            payload, limits, behind, keyframe_voxel_m, frame = args
            self._catch_up(key, behind)
            return self.register_payload(key, payload, limits, keyframe_voxel_m, frame, not behind)
        if op == "state":
            return self.state(key)
        if op == "snapshot":
            return self.snapshot(key)
        if op == "drop":
            return self.drop(key)
        raise ValueError(f"unknown request {op!r}")


class _Rebuilds:
    """Keyframe model rebuilds (:meth:`IncrementalMatcher.update_model`) on threads of their own,
    at most one per session: started as soon as a sweep is matched, so the rebuild (15 ms a sweep
    on average, up to 40 ms for one keyframe) runs on another core beside the rest of the request
    (the map points, about 10 ms), the reply and whatever the worker does next, instead of after
    them. The session's next request waits for it (:meth:`wait`), so every sweep still matches
    against the model of all keyframes before it, as offline: the poses do not depend on timing.
    The kernels release the GIL. The rebuild's CPU time is billed to the session's next sweep."""

    def __init__(self, ledger: CpuLedger) -> None:
        self._ledger = ledger
        self._lock = threading.Lock()  # (a Ray host serves several connections on threads)
        self._running: dict[Key, threading.Thread] = {}

    def start(self, key: Key, matcher: IncrementalMatcher) -> None:
        thread = threading.Thread(target=self._rebuild, args=(key, matcher), name="randt-rebuild")
        thread.daemon = True  # (a worker that quits waits for them: wait_all)
        with self._lock:
            self._running[key] = thread
        thread.start()

    def _rebuild(self, key: Key, matcher: IncrementalMatcher) -> None:
        try:
            with self._ledger.carry(key):
                matcher.update_model()
        except Exception:  # a bug, not bad input: the next request would meet it too
            log.exception("keyframe model update failed")

    def wait(self, key: Key) -> None:
        """Until ``key``'s rebuild, if one runs, is done."""
        with self._lock:
            thread = self._running.pop(key, None)
        if thread is not None:
            thread.join()

    def wait_all(self) -> None:
        with self._lock:
            threads, self._running = list(self._running.values()), {}
        for thread in threads:
            thread.join()


def _serve(conn: Connection) -> None:
    """A worker process: warm up, say so (:data:`_READY`), then :func:`serve_requests` until the
    service quits or is gone.

    SIGINT and SIGTERM are ignored: Ctrl-C in a terminal reaches the whole process group, and so
    does systemd's stop (``KillMode=control-group``, or ``kill -- -PGID``); the service (the parent)
    stops its workers itself after draining and saving the sessions (``quit``, or the pipe closing,
    which a service killed with SIGKILL closes too). Before, SIGTERM to the group ended the
    matchers first: "matcher process died: Broken pipe; not saved" for every session.
    """
    ignore_group_signals()
    single_threaded_blas()
    try:
        warm_up()
    except Exception:  # a failed warm-up only costs the first sweep its compile time
        log.exception("matcher process warm-up failed")
    try:
        conn.send(_READY)
    except (BrokenPipeError, OSError):  # the service is gone already
        return
    serve_requests(conn, _Sessions())


def serve_requests(conn: Connection, sessions: _Sessions) -> None:
    """The loop of a matcher process (or of a Ray matcher host's connection): one request at a
    time, ``(op, key, args)`` in, ``(ok, value)`` out, until ``quit`` or the connection closes.
    Keyframe model rebuilds run on threads beside it (:class:`_Rebuilds`)."""
    while True:
        try:
            op, key, args = conn.recv()
        except (EOFError, OSError):  # the service is gone (even a kill -9 closes the pipe)
            return
        if op == "quit":
            sessions.rebuilds.wait_all()
            conn.send((True, None))
            return
        try:
            value = sessions.handle(op, key, args)
        except Exception as exc:  # raised again in the session thread, as itself (module docstring)
            conn.send((False, _portable(exc)))
        else:
            conn.send((True, value))


class CpuLedger:
    """Each session's CPU time where its matcher runs, billed to its sweeps
    (:attr:`Registered.cpu_s`): a request's own thread CPU time, plus what the session's model
    rebuilds cost since its last sweep (:meth:`carry`). Thread CPU time: the matchers' kernels and
    BLAS run single-threaded on the calling thread, and it does not count the time a busy machine
    gives to other processes."""

    def __init__(self) -> None:
        self._carried: dict[Key, float] = {}

    @contextlib.contextmanager
    def carry(self, key: Key) -> Iterator[None]:
        """Around work for ``key`` that is billed to its next sweep (a model rebuild)."""
        t0 = time.thread_time()
        try:
            yield
        finally:
            self._carried[key] = self._carried.get(key, 0.0) + time.thread_time() - t0

    def bill(self, op: str, key: Key, value: Any, spent_s: float) -> Any:
        """Request ``op``'s value: a :class:`Registered` with the request's CPU (``spent_s``) and
        what was carried in ``cpu_s``; any other value as it is (``drop`` forgets the carry)."""
        if op == "drop":
            self._carried.pop(key, None)
        if not isinstance(value, Registered):
            return value
        return replace(value, cpu_s=spent_s + self._carried.pop(key, 0.0))


class _Channel:
    """A connection to a worker that speaks :func:`serve_requests`' protocol (a matcher process's
    pipe, a Ray matcher host's socket): the worker's ready message first, then one call at a time
    (a lock). A closed connection marks it dead: its calls raise :class:`MatcherProcessDiedError`."""

    def __init__(self, conn: Connection, name: str) -> None:
        self._conn = conn
        self.name = name
        self._lock = threading.Lock()
        self.sessions: set[Key] = set()
        self.dead = False
        self.ready = False  # set once the worker has sent its ready message (warm-up done)

    def _take_ready(self, timeout: float | None) -> bool:
        """Consume the ready message if it has come within ``timeout`` (call with the lock held)."""
        if self.ready:
            return True
        if timeout is not None and not self._conn.poll(timeout):
            return False
        message = self._conn.recv()
        if message != _READY:
            raise MatcherProcessError(f"{self.name} sent {message!r} before being ready")
        self.ready = True
        return True

    def wait_ready(self, timeout: float | None) -> bool:
        """Whether the worker finished its warm-up within ``timeout`` s (None: wait for it)."""
        with self._lock:
            if self.dead:
                return False
            try:
                return self._take_ready(timeout)
            except (EOFError, OSError):
                self.dead = True
                return False

    def poll_ready(self) -> bool:
        """Whether the warm-up is done, without waiting (False while a first call waits for it)."""
        if self.ready:
            return True
        if not self._lock.acquire(blocking=False):
            return False
        try:
            return not self.dead and self._take_ready(0.0)
        except (EOFError, OSError):
            self.dead = True
            return False
        finally:
            self._lock.release()

    def _wait_answer(self) -> None:
        """Return once the answer can be read (or the connection is closed). A pipe to a child
        process closes when the child dies, so this does nothing; a socket across machines
        overrides it to notice a dead peer that cannot close its end."""

    def call(self, op: str, key: Key | None, *args: object) -> Any:
        with self._lock:
            if self.dead:
                raise MatcherProcessDiedError(f"{self.name} is gone")
            try:
                self._take_ready(None)
                self._conn.send((op, key, args))
                self._wait_answer()
                ok, value = self._conn.recv()
            except (EOFError, OSError) as exc:
                self.dead = True
                raise MatcherProcessDiedError(f"{self.name} died: {exc or type(exc).__name__}") from exc
        if ok:
            return value
        raise value

    def close(self) -> None:
        """Close the connection (the worker's loop ends, or waits for another)."""
        self.dead = True
        self._conn.close()


class _WorkerProcess(_Channel):
    """One child process and the pipe to it."""

    def __init__(self, ctx: multiprocessing.context.SpawnContext, index: int) -> None:
        conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child,), name=f"randt-matcher-{index}", daemon=True)
        start_ignoring_group_signals(self._proc)
        child.close()
        super().__init__(conn, f"matcher process {index} (pid {self._proc.pid})")
        self.index = index

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def _warm(self) -> bool:
        """Whether the process has finished its warm-up (without waiting for it; a call in progress
        counts as warm)."""
        if not self._lock.acquire(blocking=False):
            return True
        try:
            return self._take_ready(0)
        except (EOFError, OSError, MatcherProcessError):
            return False
        finally:
            self._lock.release()

    def close(self, timeout: float = 10.0) -> None:
        if not self.dead and (self.sessions or self._warm()):
            with contextlib.suppress(MatcherProcessDiedError):
                self.call("quit", None)
        elif self._proc.is_alive():  # still warming up, nothing to keep: not worth the wait
            self._proc.kill()
        self._proc.join(timeout)
        if self._proc.is_alive():  # (it ignores SIGTERM: _serve)
            self._proc.kill()
            self._proc.join(timeout)
        self._conn.close()
        self.dead = True


class MatcherPool:
    """``n`` worker processes (started with ``spawn``: the service has threads, so no ``fork``)."""

    def __init__(self, n: int) -> None:
        if n < 1:
            raise ValueError(f"a matcher pool needs at least one process, got {n}")
        self._ctx = multiprocessing.get_context("spawn")
        self._lock = threading.Lock()
        self._procs = [_WorkerProcess(self._ctx, i) for i in range(n)]
        self._next_index = n

    def __len__(self) -> int:
        return len(self._procs)

    def pids(self) -> list[int | None]:
        return [p.pid for p in self._procs]

    def wait_ready(self, timeout: float | None = None) -> bool:
        """Whether every process finished its warm-up (compiled or loaded the kernels) within
        ``timeout`` s in all (None: wait as long as it takes). Sessions may open before: their
        first call waits for the warm-up instead."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._lock:
            procs = list(self._procs)
        for p in procs:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not p.wait_ready(left):
                return False
        return True

    @property
    def ready(self) -> bool:
        """Every process has finished its warm-up (a non-blocking check)."""
        procs = list(self._procs)  # no lock: /status must not wait while open() replaces a process
        return all(p.poll_ready() for p in procs)

    def open(
        self,
        key: Key,
        state: dict[str, np.ndarray] | None = None,
        grid: TileGrid | None = None,
        settings: MatcherSettings | None = None,
        registration: RegistrationSettings | None = None,
    ) -> RemoteMatcher:
        """A matcher for session ``key`` (restored from ``state``) on the least busy process.

        With ``grid`` (the session's map), results carry only the points ``grid.insert`` could
        keep (:meth:`~randt.core.tiles.TileGrid.candidate_mask`, computed in the worker process).
        ``settings`` and ``registration`` are the :class:`~randt.core.odometry.IncrementalMatcher`'s
        (None: its defaults).
        """
        with self._lock:
            for i, p in enumerate(self._procs):
                if p.dead:  # replace a dead process before placing anyone on it
                    log.warning("matcher process %d died: starting a replacement", p.index)
                    p.close(timeout=1.0)
                    self._procs[i] = _WorkerProcess(self._ctx, self._next_index)
                    self._next_index += 1
            proc = min(self._procs, key=lambda p: len(p.sessions))
            proc.sessions.add(key)
        params = None if grid is None else (grid.tile_size_m, grid.voxel_size_m, grid.max_points_per_voxel)
        try:
            return RemoteMatcher(self, proc, key, state, params, settings, registration)
        except BaseException:
            proc.sessions.discard(key)
            raise

    def _release(self, proc: _WorkerProcess, key: Key) -> None:
        proc.sessions.discard(key)

    def close(self) -> None:
        with self._lock:
            procs, self._procs = self._procs, []
        for p in procs:
            p.close()


class ForwardingMatcher:
    """What a matcher running elsewhere (a worker process, a Ray actor) shares: the trajectory kept
    here as well (appended from each result, so reading it needs no round trip),
    :meth:`register_scan` on top of the subclass's ``register``, and no model update to ask for
    (the far side rebuilds the model on a thread as soon as the sweep is matched)."""

    poses: list[np.ndarray]

    def register(
        self,
        points_xyz: np.ndarray,
        *,
        time_offset_s: np.ndarray | None = None,
        prior: PosePrior | None = None,
        stamp_s: float | None = None,
        behind: bool = False,
        keyframe_voxel_m: float | None = None,
        frame: MapFrame | None = None,
    ) -> Registered:
        raise NotImplementedError

    def register_payload(
        self,
        payload: bytes | Ros2Scan,
        *,
        limits: WireLimits | None = None,
        behind: bool = False,
        keyframe_voxel_m: float | None = None,
        frame: MapFrame | None = None,
    ) -> Registered:
        raise NotImplementedError

    def register_scan(
        self,
        points_xyz: np.ndarray,
        *,
        time_offset_s: np.ndarray | None = None,
        prior: PosePrior | None = None,
        stamp_s: float | None = None,
        defer_model: bool = True,
        behind: bool = False,
    ) -> ScanResult:
        """:meth:`register`'s result (``defer_model`` is accepted for
        :meth:`IncrementalMatcher.register_scan`'s signature: the far side always defers). With
        the session's map given to the executor's ``open``, its ``deskewed_xyz`` is empty: the
        map's points are in :meth:`register`'s answer."""
        del defer_model
        return self.register(
            points_xyz, time_offset_s=time_offset_s, prior=prior, stamp_s=stamp_s, behind=behind
        ).result

    def update_model(self) -> float:
        """Nothing to do here: the far side rebuilds the model itself (``_Rebuilds``)."""
        return 0.0


class RemoteMatcher(ForwardingMatcher):
    """The part of :class:`~randt.core.odometry.IncrementalMatcher` a session worker uses, run remotely.

    ``poses`` is kept here as well (appended from each result), so reading a trajectory needs no
    round trip; ``state_dict`` asks the process.
    """

    def __init__(
        self,
        pool: MatcherPool,
        proc: _WorkerProcess,
        key: Key,
        state: dict[str, np.ndarray] | None,
        grid_params: tuple[int, float, int] | None = None,
        settings: MatcherSettings | None = None,
        registration: RegistrationSettings | None = None,
    ) -> None:
        self._pool, self._proc, self._key = pool, proc, key
        proc.call("open", key, state, grid_params, settings, registration)
        self.poses: list[np.ndarray] = [] if not state else list(np.asarray(state["poses"]).reshape(-1, 4, 4))

    @property
    def process_index(self) -> int:
        return self._proc.index

    def register(
        self,
        points_xyz: np.ndarray,
        *,
        time_offset_s: np.ndarray | None = None,
        prior: PosePrior | None = None,
        stamp_s: float | None = None,
        behind: bool = False,
        keyframe_voxel_m: float | None = None,
        frame: MapFrame | None = None,
    ) -> Registered:
        """:meth:`IncrementalMatcher.register_scan` in the session's process, with the points the
        session's map may keep (:class:`Registered`; with ``keyframe_voxel_m``, the keyframe's
        points too). Points and time offsets are sent as given
        (float32 straight from the wire: half the bytes of float64; the matcher widens them).

        Unless ``behind`` (several of the session's scans are waiting), the process starts a
        keyframe's model rebuild on a thread as soon as the sweep is matched, beside the reply,
        and the session's next request waits for it (``_Rebuilds``). Only when ``behind`` does
        the next sweep match without the newest keyframe (the model rebuilt once for two,
        :meth:`IncrementalMatcher.update_model`)."""
        registered: Registered = self._proc.call(
            "register", self._key, points_xyz, time_offset_s, prior, stamp_s, behind, keyframe_voxel_m, frame
        )
        self.poses.append(registered.result.T_world_sensor)
        return registered

    def register_payload(
        self,
        payload: bytes | Ros2Scan,
        *,
        limits: WireLimits | None = None,
        behind: bool = False,
        keyframe_voxel_m: float | None = None,
        frame: MapFrame | None = None,
    ) -> Registered:
        """:meth:`register` of a scan payload, sent as the bytes that came (a reduced sweep's
        120 kB instead of its 0.6 MB of arrays) and decoded in the session's process
        (:func:`decoded_sweep`), which also returns the map points' intensities. A payload whose
        bodies do not decode raises the decoder's :class:`~randt.core.errors.BadMessageError`."""
        registered: Registered = self._proc.call(
            "register_payload", self._key, payload, limits, behind, keyframe_voxel_m, frame
        )
        self.poses.append(registered.result.T_world_sensor)
        return registered

    def state_dict(self) -> dict[str, np.ndarray]:
        return self._proc.call("state", self._key)

    def snapshot_state(self) -> dict[str, np.ndarray]:
        """:meth:`state_dict` without the trajectory (:func:`without_trajectory`), built in the process."""
        return self._proc.call("snapshot", self._key)

    def close(self) -> None:
        """Forget the session in its process (its state should have been saved first)."""
        try:
            self._proc.call("drop", self._key)
        except MatcherProcessDiedError:
            pass
        finally:
            self._pool._release(self._proc, self._key)


class LocalMatcher(IncrementalMatcher):
    """An in-process matcher with :class:`RemoteMatcher`'s ``close`` (``matcher_processes=0``)."""

    #: CPU seconds of model rebuilds not billed to a sweep yet (:attr:`Registered.cpu_s`)
    _carried_cpu_s: float = 0.0

    def update_model(self) -> float:
        """:meth:`IncrementalMatcher.update_model`, its CPU time billed to the next sweep."""
        t0 = time.thread_time()
        try:
            return super().update_model()
        finally:
            self._carried_cpu_s += time.thread_time() - t0

    def register_scan(
        self,
        points_xyz: np.ndarray,
        *,
        time_offset_s: np.ndarray | None = None,
        prior: PosePrior | None = None,
        stamp_s: float | None = None,
        defer_model: bool = False,
        behind: bool = False,
        map_seed: np.ndarray | None = None,
    ) -> ScanResult:
        """:meth:`IncrementalMatcher.register_scan`; ``behind`` is the caller's to act on (it
        skips :meth:`update_model` then), accepted for :class:`RemoteMatcher`'s signature."""
        del behind
        return super().register_scan(
            points_xyz,
            time_offset_s=time_offset_s,
            prior=prior,
            stamp_s=stamp_s,
            defer_model=defer_model,
            map_seed=map_seed,
        )

    def register(
        self,
        points_xyz: np.ndarray,
        *,
        time_offset_s: np.ndarray | None = None,
        prior: PosePrior | None = None,
        stamp_s: float | None = None,
        behind: bool = False,
        keyframe_voxel_m: float | None = None,
        frame: MapFrame | None = None,
    ) -> Registered:
        """:meth:`register_scan` (the model rebuild deferred: the caller runs :meth:`update_model`
        after publishing) and every point of the sweep in the map frame (:class:`Registered`;
        with ``keyframe_voxel_m``, the keyframe's points too)."""
        t0 = time.thread_time()
        result = self.register_scan(
            points_xyz,
            time_offset_s=time_offset_s,
            prior=prior,
            stamp_s=stamp_s,
            defer_model=True,
            behind=behind,
            map_seed=None if frame is None else frame.seed_xyz,
        )
        registered = _registered(result, None, keyframe_voxel_m, frame)
        cpu_s, self._carried_cpu_s = time.thread_time() - t0 + self._carried_cpu_s, 0.0
        return replace(registered, cpu_s=cpu_s)

    def register_payload(
        self,
        payload: bytes | Ros2Scan,
        *,
        limits: WireLimits | None = None,
        behind: bool = False,
        keyframe_voxel_m: float | None = None,
        frame: MapFrame | None = None,
    ) -> Registered:
        """:meth:`register` of a scan payload, decoded here (:func:`decoded_sweep`)."""
        t0 = time.thread_time()
        xyz, offsets, intensity, prior, stamp_s = decoded_sweep(payload, limits, frame)
        self._carried_cpu_s += time.thread_time() - t0  # (the decoding, billed by register)
        registered = self.register(
            xyz,
            time_offset_s=offsets,
            prior=prior,
            stamp_s=stamp_s,
            behind=behind,
            keyframe_voxel_m=keyframe_voxel_m,
            frame=frame,
        )
        return _with_intensity(registered, intensity)

    def snapshot_state(self) -> dict[str, np.ndarray]:
        """:meth:`state_dict` without the trajectory (:func:`without_trajectory`)."""
        return without_trajectory(self.state_dict())

    def close(self) -> None:
        """Nothing to release."""
