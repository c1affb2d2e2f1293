"""What a session and its matcher exchange, wherever the matcher runs: the sweep as a payload
(:func:`decoded_sweep`, :func:`scan_payload`), where its map points go (:class:`MapFrame`), the
answer (:class:`Registered`), the matcher's state in a snapshot (:func:`without_trajectory`,
:func:`with_trajectory`) and the errors of a matcher that runs in another process.

Everything here crosses a pipe or a socket pickled (service/matcher_host.py on the far side), so
both sides import these classes from this module.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from randt.core.errors import FormatError, InvalidCloudError, RandtError
from randt.core.odometry import IncrementalMatcher, PosePrior, ScanResult
from randt.core.registration import PreparedReference, ReferencePiece
from randt.core.tiles import SentVoxels, TileGrid
from randt.core.transforms import invert, transform_points
from randt.core.voxel import pack_keys, voxel_coords
from randt.wire.messages import ScanHeader, ScanMessage, WireLimits, decode_scan, encode, scan_from_arrays
from randt.wire.ros2 import Ros2Scan, sweep_arrays

log = logging.getLogger(__name__)

__all__ = [
    "TRAJECTORY_LENGTH_KEY",
    "Key",
    "MapFrame",
    "MapWindow",
    "MapWindows",
    "MatcherProcessDiedError",
    "MatcherProcessError",
    "Registered",
    "decoded_sweep",
    "prior_of",
    "scan_payload",
    "with_trajectory",
    "without_trajectory",
]

#: A session's key: (vehicle, session).
Key = tuple[str, str]


class MatcherProcessError(RandtError, RuntimeError):
    """A matcher worker process failed: an error raised there could not be sent back as itself."""


class MatcherProcessDiedError(MatcherProcessError):
    """The worker process holding a session's matcher is gone (the session must be resumed)."""


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
    window:
        The map around the vehicle, to localize the sweep on (:class:`MapWindow`); ``None``: the
        sweep is mapped (matched on the session's keyframes).
    for_map:
        Whether the sweep's points may go into the map (``False``: a session that only localizes,
        a sweep relocalized; the answer carries none, :class:`Registered`).
    relocalize:
        ``prior`` is a place guessed for a session's first sweep (service/places.py), not a fix:
        the matcher verifies it on ``window`` and raises
        :class:`~randt.core.errors.NotRelocalizedError` when the sweep does not match the map there
        (``IncrementalMatcher.register_scan``'s ``relocalize``).
    """

    token: tuple[str, int, int]
    correction: np.ndarray | None = None
    seed_xyz: np.ndarray | None = None
    prior: PosePrior | None = None
    window: MapWindow | None = None
    for_map: bool = True
    relocalize: bool = False


@dataclass(frozen=True, eq=False)
class MapWindow:
    """The map around the vehicle for a sweep to be localized on (docs/mapping.md, "Localizing on
    the map"): the map's identity and content when it was cut (``token``, as :attr:`MapFrame.token`),
    its centre, and the tiles it is made of, ``(id, version)`` each, when the matcher is to join it
    anew (``None``: the one it holds, cut with the same token and centre). ``points``: the points
    (world frame, float32) of those tiles the matcher does not hold at that version (the others it
    kept from the windows before), or, prepared by the service once for every session
    (``pieces``, :class:`randt.service.localizing.MapPieces`), their pieces."""

    token: tuple[str, int, int]
    center_xy: tuple[float, float]
    tiles: tuple[tuple[str, int], ...] | None = None
    points: dict[str, np.ndarray] = field(default_factory=dict)
    #: the map's tiles within this of the centre make it (the service's ``localize_radius_m``)
    radius_m: float = 0.0
    pieces: dict[str, ReferencePiece] = field(default_factory=dict)


_Key = tuple[tuple[str, int, int], tuple[float, float]]
_Pieces = dict[str, tuple[tuple[str, int, int], int, ReferencePiece]]


@dataclass(frozen=True)
class _Held:
    """A window a matcher holds: its key (token, centre), radius, pieces and prepared map."""

    key: _Key
    radius_m: float
    pieces: _Pieces
    reference: PreparedReference


class _Join:
    """A window joined on a thread of its own (:meth:`MapWindows.on_map`): what it holds once
    done (``None``: it could not be joined), and the thread CPU time it took."""

    def __init__(self, work: Callable[[], _Held]) -> None:
        self._work = work
        self._value: _Held | None = None
        self.cpu_s = 0.0
        self._thread = threading.Thread(target=self._run, name="randt-window", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        t0 = time.thread_time()
        try:
            self._value = self._work()
        except InvalidCloudError:
            pass  # (too sparse, or a tile not held: the sweep that waits for it maps)
        except Exception:  # a bug, not bad input: the sweep that waits for it maps
            log.exception("map window join failed")
        finally:
            self.cpu_s = time.thread_time() - t0

    def result(self) -> _Held | None:
        self._thread.join()
        return self._value


class MapWindows:
    """The window a matcher holds for one session, joined from its tiles' pieces; each tile is
    prepared once while it stays in the windows sent (:meth:`IncrementalMatcher.prepare_map_piece`).

    A window cut again around a vehicle that moved (the same map content, its token, and some of
    its tiles held already) is joined on a thread beside the requests of the matcher's other
    sessions: the sweep it came with is localized on the window held, the next one waits for the
    join and is localized on the new window. So a window's new tiles (tens of milliseconds) do not
    hold up the other sessions' sweeps queued behind it, and the poses do not depend on timing
    (docs/mapping.md, "In the service"). A session's first window, one of other map content, and
    one sent whole (after misses) are joined before the sweep they came with."""

    def __init__(self) -> None:
        self._held: _Held | None = None
        self._pending: tuple[_Key, _Join] | None = None
        #: the window this request's sweep is localized on
        self._used: _Held | None = None
        self._cpu_s = 0.0

    def on_map(self, matcher: IncrementalMatcher, window: MapWindow | None) -> PreparedReference | None:
        """The prepared map to match this sweep on (``register_scan``'s ``on_map``), or ``None``:
        no window asked for, one too sparse to prepare, or one this matcher does not hold (the
        sweep is mapped then, and its answer says so: ``ScanResult.localized``)."""
        self._used = None
        if window is None:
            return None
        key = (window.token, window.center_xy)
        self._adopt_pending()
        if window.tiles is not None:
            if self._joins_behind(window):
                work = self._work(matcher, window, self._held.pieces if self._held else {})
                self._pending = (key, _Join(work))
            else:
                try:
                    self._held = self._work(matcher, window, self._held.pieces if self._held else {})()
                except InvalidCloudError:
                    self._held = None
        held = self._held
        behind = self._pending is not None and self._pending[0] == key
        if held is None or (held.key != key and not behind):
            return None
        self._used = held
        return held.reference

    def take_cpu_s(self) -> float:
        """The thread CPU time of the joins adopted since last asked (billed to the session)."""
        cpu, self._cpu_s = self._cpu_s, 0.0
        return cpu

    def lacking(self, window: MapWindow | None, world_xyz: np.ndarray) -> np.ndarray | None:
        """Of a localized sweep's points (map frame), those the map lacks: within the radius of
        the window it was localized on (where the map's tiles are all in it) and in no voxel of
        its finest NDT level. ``None`` without a window used: nothing is known of the map here.
        What lies in the map's voxels is the map's surfaces seen again (folded, it would grow the
        map with the distance driven: docs/mapping.md, "In the service")."""
        used = self._used
        if window is None or used is None:
            return None
        xy = np.asarray(world_xyz, dtype=np.float64)[:, :2] - np.asarray(used.key[1])
        inside = np.einsum("ij,ij->i", xy, xy) <= used.radius_m**2
        return inside & ~used.reference.maps[-1].contains(world_xyz)

    def _joins_behind(self, window: MapWindow) -> bool:
        """A window cut again on the same map content, some of its tiles held: joined behind."""
        held = self._held
        return (
            held is not None
            and held.key[0] == window.token
            and any(tid not in window.points and tid not in window.pieces for tid, _ in window.tiles or ())
        )

    def _adopt_pending(self) -> None:
        """The window joined behind becomes the one held (waited for: the next sweep uses it)."""
        if self._pending is None:
            return
        join = self._pending[1]
        self._pending = None
        self._held = join.result()
        self._cpu_s += join.cpu_s

    @staticmethod
    def _work(matcher: IncrementalMatcher, window: MapWindow, before: _Pieces) -> Callable[[], _Held]:
        """The join of the window's tiles: the new ones prepared and the others taken from the
        window before (``before``; a tile sent without its points that is not held at that
        version: InvalidCloudError). The matcher's map settings are read here, on the request's
        thread: the join itself touches no matcher (it may run beside the session's sweep)."""
        prep = matcher.map_preparation()
        key = (window.token, window.center_xy)

        def join() -> _Held:
            pieces: _Pieces = {}
            for tid, version in window.tiles or ():
                xyz, given = window.points.get(tid), window.pieces.get(tid)
                held = before.get(tid)
                if given is not None:
                    if given.voxel_sizes_m != prep.levels:
                        raise InvalidCloudError(f"map tile {tid} was prepared at other levels")
                    pieces[tid] = (window.token, version, given)
                elif xyz is not None:
                    pieces[tid] = (window.token, version, prep.piece(xyz))
                elif (
                    held is not None
                    and held[:2] == (window.token, version)
                    and held[2].voxel_sizes_m == prep.levels
                ):
                    pieces[tid] = held
                else:
                    raise InvalidCloudError(f"map tile {tid} (version {version}) is not held")
            reference = prep.join([p for _, _, p in pieces.values()])
            return _Held(key, window.radius_m, pieces, reference)

        return join


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
        The intensity (float32) of each point of ``map_xyz`` and ``keyframe_xyz``, read from the
        payload where it was decoded; ``None`` when the sweep has none.
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

    @classmethod
    def of(
        cls,
        result: ScanResult,
        grid: TileGrid | None,
        keyframe_voxel_m: float | None = None,
        frame: MapFrame | None = None,
        sent: SentVoxels | None = None,
        windows: MapWindows | None = None,
    ) -> Registered:
        """The answer for ``result``: its points in the map frame (float32, moved by the frame's
        correction), cut to those the map could keep when its sizes are known (``grid``): to the
        voxels not sent before under the frame's token (``sent``, with a ``frame``), else to the
        candidates (:meth:`TileGrid.candidate_mask`); and the keyframe's points when
        ``keyframe_voxel_m`` is given. A fallback keeps no points, nor a sweep not deskewed
        (``ScanResult.deskewed``: a first sweep with point times) for the map; the agreement
        check still reads its keyframe points. A sweep localized on the window ``windows`` holds
        keeps for the map only what the map lacks (:meth:`MapWindows.lacking`); a sweep of a
        frame not ``for_map``, nothing."""
        if result.status == "fallback":
            return cls(result, np.empty((0, 3), np.float32), np.empty(0, np.intp))
        if frame is not None and not frame.for_map:  # (nor its sweep back from a matcher process)
            slim = replace(result, deskewed_xyz=np.empty((0, 3)), map_index=np.empty(0, np.intp))
            return cls(slim, np.empty((0, 3), np.float32), np.empty(0, np.intp))
        keyframe = keyframe_index = None
        if keyframe_voxel_m is not None and len(result.deskewed_xyz):
            keys = pack_keys(voxel_coords(result.deskewed_xyz, keyframe_voxel_m))
            _, first = np.unique(keys, return_index=True)
            keyframe = result.deskewed_xyz[first].astype(np.float32)
            keyframe_index = result.map_index[first]
        if not result.deskewed:
            kept = (
                result
                if grid is None
                else replace(result, deskewed_xyz=np.empty((0, 3)), map_index=np.empty(0, np.intp))
            )
            return cls(kept, np.empty((0, 3), np.float32), np.empty(0, np.intp), keyframe, keyframe_index)
        # (a localized pose is the map's already: the session's graph correction is not for it)
        C = None if frame is None or result.localized else frame.correction
        T = result.T_world_sensor if C is None else C @ result.T_world_sensor
        world = transform_points(T, result.deskewed_xyz)
        lacking = None
        if result.localized and windows is not None and frame is not None:
            lacking = windows.lacking(frame.window, world)
        if grid is None:
            if lacking is not None:
                world, index = world[lacking], result.map_index[lacking]
            else:
                index = result.map_index
            return cls(result, world.astype(np.float32), index, keyframe, keyframe_index, correction=C)
        if lacking is not None:  # (only what the map lacks is offered, and recorded as sent)
            world, index = world[lacking], result.map_index[lacking]
        else:
            index = result.map_index
        keep = (
            grid.candidate_mask(world) if frame is None or sent is None else sent.admitted(world, frame.token)
        )
        slim = replace(result, deskewed_xyz=np.empty((0, 3)), map_index=np.empty(0, np.intp))
        return cls(
            slim,
            world[keep].astype(np.float32),
            index[keep],
            keyframe,
            keyframe_index,
            correction=C,
        )

    def with_intensity(self, intensity: np.ndarray | None) -> Registered:
        """This answer with the intensities of its map and keyframe points (itself without)."""
        if intensity is None:
            return self
        kf = self.keyframe_index
        return replace(
            self,
            map_intensity=intensity[self.map_index],
            keyframe_intensity=None if kf is None else intensity[kf],
        )

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


def scan_payload(
    points_xyz: np.ndarray,
    *,
    stamp_ns: int,
    seq: int = 0,
    time_offset_s: np.ndarray | None = None,
    prior: PosePrior | None = None,
    intensity: np.ndarray | None = None,
    vehicle: str = "v",
    session: str = "s",
) -> bytes:
    """A sweep's arrays as the payload a vehicle sends, for a caller that holds arrays (tests,
    benchmarks) and a matcher's ``register_payload``: a v1 scan
    (:func:`randt.wire.messages.scan_from_arrays`), points and time offsets float32 as the wire
    carries them, the prior's pose and covariance as they are.

    The matcher reads the stamp back as ``stamp_ns * 1e-9`` s (:func:`decoded_sweep`): a caller
    comparing with an in-process matcher gives it that. Raises
    :class:`~randt.core.errors.BadMessageError` for a sweep the service would refuse.
    """
    message = scan_from_arrays(
        vehicle,
        session,
        seq,
        stamp_ns,
        points_xyz,
        intensity,
        time_offset_s,
        None if prior is None else prior.T_world_sensor,
        None if prior is None else prior.covariance,
    )
    return encode(message)


def prior_of(scan: ScanMessage | ScanHeader) -> PosePrior | None:
    """The scan's prior pose (GNSS/INS) with its covariance, if it carries one."""
    pose = scan.prior_pose()
    if pose is None:
        return None
    cov = scan.prior_covariance()
    assert cov is not None  # a scan's prior carries both
    return PosePrior(pose, cov)


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
