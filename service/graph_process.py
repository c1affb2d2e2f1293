"""The pose graph's process: one :class:`~randt.core.fleet_map.FleetMapper` per map, fed keyframes
over a pipe, answering what moved, the loops it verified, the sessions it placed, and every
``graph_refold_s`` the tiles of the keyframes that moved, re-folded (``docs/mapping.md``, "In the
service")."""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import logging
import os
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from randt.core.errors import RandtError
from randt.core.fleet_map import FleetMapper, FleetMapSettings
from randt.core.keyframe_cache import KeyframeCache
from randt.core.tiles import TileGrid, tile_id
from randt.core.transforms import rotation_angle_deg
from randt.service.graph_priority import die_with_parent, lowest_priority
from randt.service.processes import ignore_group_signals, single_threaded_blas

__all__ = ["MOVE_TOL_DEG", "MOVE_TOL_M", "MapGeometry", "ProcessMap", "graph_main"]

log = logging.getLogger(__name__)

#: A keyframe is reported again once its optimized pose moved this much since last reported.
MOVE_TOL_M = 0.01
MOVE_TOL_DEG = 0.05
#: A keyframe's points are re-folded into the map's tiles once it moved this much from where they
#: were folded (half the default map voxel).
REFOLD_TOL_M = 0.1
REFOLD_TOL_DEG = 0.2
#: A re-fold waits for a pause in the keyframes; under a steady stream it is done anyway once the
#: last one is this many re-fold periods old (``graph_refold_s``).
REFOLD_STARVE_PERIODS = 3.0
#: Keyframes whose points the graph process keeps in memory per map (and per use: the matching's
#: points, the re-fold's cloud), the ones used last; every keyframe's are on disk under the graph
#: log's directory (``spill/``, rebuilt from the log at each start): in RAM they grew with the
#: drive (docs/architecture.md, "Threads or processes").
HOT_KEYFRAMES = 64


def _far(a: np.ndarray, b: np.ndarray, tol_m: float, tol_deg: float) -> bool:
    return bool(
        np.linalg.norm(a[:3, 3] - b[:3, 3]) > tol_m or rotation_angle_deg(a[:3, :3].T @ b[:3, :3]) > tol_deg
    )


def _moved(a: np.ndarray, b: np.ndarray) -> bool:
    return _far(a, b, MOVE_TOL_M, MOVE_TOL_DEG)


#: Tiles in a keyframe's bounding box up to which :meth:`ProcessMap._tiles` counts instead of sorting.
MAX_TILE_SPAN = 1 << 16


@dataclass(frozen=True)
class MapGeometry:
    """What the graph process needs of a map to re-fold its tiles (the service's settings)."""

    tile_size_m: int
    voxel_size_m: float
    max_points_per_voxel: int


class ProcessMap:
    """One map's graph inside the graph process: the mapper, what was last reported of it, and
    each keyframe's points (sensor frame, with intensity) for re-folding the map's tiles."""

    def __init__(
        self, name: str, settings: FleetMapSettings, geometry: MapGeometry, spill: Path | None = None
    ) -> None:
        """``spill``: where the keyframes' points are kept on disk, the :data:`HOT_KEYFRAMES` used
        last in memory (:class:`~randt.core.keyframe_cache.KeyframeCache`); ``None``: all in memory."""
        self.name = name
        where = None if spill is None else spill / hashlib.sha1(name.encode()).hexdigest()[:16]
        self.mapper = FleetMapper(
            settings, KeyframeCache(None if where is None else where / "points", HOT_KEYFRAMES)
        )
        self.geometry = geometry
        self.meta: dict[tuple[str, int], tuple[str, str, int, int]] = {}  # vehicle, session, seq, index
        self.reported: dict[tuple[str, int], np.ndarray] = {}
        #: Keyframes whose pose in this map was sent (moved or held): the service corrects a
        #: trajectory only from keyframes this graph holds, at the pose it holds them.
        self.announced: set[tuple[str, int]] = set()
        self.sent: list[bool] = []  # each loop record's ``accepted`` as last sent
        self.revision = 0
        #: Each keyframe's points (sensor frame, float32) and intensity, for the re-folds.
        self.cloud = KeyframeCache(None if where is None else where / "cloud", HOT_KEYFRAMES)
        self.folded: dict[tuple[str, int], np.ndarray] = {}  # the pose its points are in the tiles at
        self.tiles_of: dict[tuple[str, int], set[tuple[int, int]]] = {}
        self.poses: dict[tuple[str, int], np.ndarray] = {}  # the optimized poses after the last keyframe
        #: Keyframes moved since the last re-fold (it checks which moved far enough).
        self.refold_pending = False

    def close(self) -> None:
        """Remove the map's keyframe files (a deleted map)."""
        self.mapper.points.clear()
        self.cloud.clear()

    def _tiles(self, T: np.ndarray, xyz: np.ndarray) -> set[tuple[int, int]]:
        """The tiles a keyframe's points fall in at pose ``T``. A count over the few tiles of the
        points' bounding box, not ``np.unique(axis=0)``, which sorts: the re-fold asks this of
        every keyframe it touches."""
        xy = xyz.astype(np.float64) @ T[:2, :3].T + T[:2, 3]
        cells = np.floor(xy / self.geometry.tile_size_m).astype(np.int64)
        lo = cells.min(axis=0)
        span = cells.max(axis=0) - lo + 1
        if int(span[0]) * int(span[1]) > MAX_TILE_SPAN:  # far-flung points: sort them instead
            return {(int(a), int(b)) for a, b in np.unique(cells, axis=0)}
        flat = (cells[:, 0] - lo[0]) * span[1] + (cells[:, 1] - lo[1])
        hit = np.flatnonzero(np.bincount(flat, minlength=int(span[0] * span[1])))
        return {(int(lo[0] + h // span[1]), int(lo[1] + h % span[1])) for h in hit.tolist()}

    def _refold(
        self, poses: dict[tuple[str, int], np.ndarray]
    ) -> tuple[list[str], np.ndarray, np.ndarray] | None:
        """The tiles to re-fold once keyframes moved more than ``REFOLD_TOL_*`` from where their
        points were folded, with every keyframe's points that fall in them at its optimized pose."""
        # (a keyframe of a session that joined this map has not been folded into it yet)
        due = {
            k
            for k, P in poses.items()
            if k in self.cloud
            and (k not in self.folded or _far(P, self.folded[k], REFOLD_TOL_M, REFOLD_TOL_DEG))
        }
        if not due:
            return None
        now = {k: self._tiles(poses[k], self.cloud.get(k)[0]) for k in due}
        tiles: set[tuple[int, int]] = set()
        for k in due:
            tiles |= self.tiles_of.get(k, set()) | now[k]
        contributors = [
            k for k in self.cloud if k in poses and (now[k] if k in due else self.tiles_of[k]) & tiles
        ]
        # Equalized here, off the service's GIL: the service swaps the tiles in. Keyframe by
        # keyframe into an empty grid (what one refold of them all gives), each read once (from
        # disk, maybe): the memory it takes is the tiles', not every contributor's points at once.
        g = self.geometry
        grid = TileGrid(g.tile_size_m, g.voxel_size_m, g.max_points_per_voxel)
        ids = sorted(tile_id(ix, iy) for ix, iy in tiles)
        for k in contributors:
            xyz_k, intensity_k = self.cloud.get(k)
            grid.insert(xyz_k @ poses[k][:3, :3].T + poses[k][:3, 3], intensity_k, only_tiles=ids)
            self.folded[k] = poses[k]
            self.tiles_of[k] = now[k] if k in due else self._tiles(poses[k], xyz_k)
        kept = grid.tiles()
        if not kept:
            return None
        return (
            [t.id for t in kept],
            np.concatenate([t.points for t in kept]),
            np.concatenate([t.intensity for t in kept]),
        )

    def refold(self) -> tuple[list[str], np.ndarray, np.ndarray] | None:
        """The pending re-fold (:meth:`_refold` at the newest optimized poses), if any."""
        if not self.refold_pending:
            return None
        self.refold_pending = False
        return self._refold(self.poses)

    def add(self, message: tuple[Any, ...], *, joining: bool = False) -> tuple[Any, ...]:
        """One keyframe in; the ``update`` message out (raises on a refused keyframe). Re-folding
        the tiles is left to :meth:`refold`, which the process runs in a pause (``graph_main``).

        A session's first keyframe places it at the identity: its poses are in its map's frame
        already. With ``joining``, the keyframe is of a session without priors that lives in a map
        of its own: it enters unplaced, and FleetMapper places it once two registrations against
        this map agree, or by a fit of its GNSS fixes (a ROS 2 robot's NavSatFix, in this map's
        frame) (its points are then folded into this map's tiles by the next re-fold)."""
        _, _, vehicle, session, seq, index, T_live, points, intensity, gnss, _ = message
        mapper = self.mapper
        name = f"{vehicle}/{session}"
        if name not in mapper.sessions and not joining:
            mapper.place(name, np.eye(4))
        was_placed = set(mapper.placed_sessions())
        key = mapper.add_keyframe(name, T_live, points, gnss)
        self.meta[key] = (vehicle, session, seq, index)
        self.reported.setdefault(key, T_live)
        xyz = np.asarray(points, dtype=np.float32)
        self.cloud.put(key, xyz, np.zeros(len(xyz), np.float32) if intensity is None else intensity)
        if not joining:  # folded by the service, moved by the session's newest correction
            self.folded[key] = T_live
            self.tiles_of[key] = self._tiles(T_live, xyz)
        poses = self.poses = mapper.poses()
        if set(mapper.placed_sessions()) != was_placed:
            self.refold_pending = True
        moved, held = [], []
        for k, P in poses.items():
            if _moved(P, self.reported[k]):
                self.reported[k] = P
                moved.append((*self.meta[k], P))
            elif k not in self.announced:  # in the graph where it was answered: no correction
                held.append((*self.meta[k], P))
            self.announced.add(k)
        if moved:
            self.revision += 1
            self.refold_pending = True
        # Records from the first that changed (a placement vote is accepted once a second agrees).
        start = next(
            (i for i, (r, was) in enumerate(zip(mapper.loops, self.sent, strict=False)) if r.accepted != was),
            len(self.sent),
        )
        loops = [
            {
                "a": self.meta[r.a][:3],
                "b": self.meta[r.b][:3],
                "source": r.source,
                "confident": r.confident,
                "accepted": r.accepted,
                "reason": r.reason,
                "n_inliers": r.n_inliers,
            }
            for r in mapper.loops[start:]
        ]
        self.sent = [r.accepted for r in mapper.loops]
        placed = {n: mapper.sessions[n].T_world_session for n in mapper.placed_sessions()}
        kind = "join" if joining else "update"
        return (kind, self.name, self.revision, moved, held, start, loops, placed)


def release_memory() -> None:
    """Give the C heap's free memory back to the system (glibc's ``malloc_trim``; elsewhere
    nothing). A re-fold allocates and frees the points of every tile it touches; without this the
    freed heap stays resident and the graph process grows with the drive (docs/benchmarks.md,
    "The pose graph's memory")."""
    global _MALLOC_TRIM
    if _MALLOC_TRIM is None:
        try:
            libc = ctypes.CDLL("libc.so.6")
            _MALLOC_TRIM = libc.malloc_trim
            _MALLOC_TRIM.argtypes = [ctypes.c_size_t]
        except (OSError, AttributeError):
            _MALLOC_TRIM = False
    if _MALLOC_TRIM:
        _MALLOC_TRIM(0)


_MALLOC_TRIM: Any = None


def send_refolds(conn: Connection, maps: dict[str, ProcessMap]) -> None:
    """Re-fold every map with moved keyframes and send each map's tiles (``refold`` messages)."""
    for map_name, graph in maps.items():
        t0 = time.perf_counter()
        try:
            refold = graph.refold()
        except Exception:  # a bug: the tiles stay as they are, the graph goes on
            log.exception("graph process: re-folding map %s failed", map_name)
            continue
        if refold is not None:
            conn.send(("refold", map_name, *refold, time.perf_counter() - t0))
            del refold
            release_memory()


def graph_main(
    conn: Connection,
    settings: FleetMapSettings,
    geometry: MapGeometry,
    refold_s: float,
    parent: int,
    spill: Path | None = None,
) -> None:
    """The graph process: keyframes in, moved keyframes and loop verifications out (module docstring).

    First it asks to die with the service (``die_with_parent``), quits if the service (pid
    ``parent``) died before that, and says it is ``alive``: only then may the service's
    :class:`YieldGate` stop it (stopped before it asked, it would outlive a service killed with
    SIGKILL: docs/mapping.md, "In the service").

    Keyframes come first: the tiles of moved keyframes are re-folded at most every ``refold_s``
    seconds, when no keyframe waits (or once the last re-fold is ``REFOLD_STARVE_PERIODS`` periods
    old), and at once on a ``sync`` request. ``spill``: where the keyframes' points are kept on
    disk (:class:`ProcessMap`); ``None``: in memory."""
    ignore_group_signals()  # the service stops it (``quit`` or the pipe closing), not Ctrl-C
    die_with_parent()
    if os.getppid() != parent:  # the service died before the request: nobody would kill us
        return
    try:
        conn.send(("alive",))
    except (BrokenPipeError, OSError):
        return
    single_threaded_blas()
    lowest_priority()
    maps: dict[str, ProcessMap] = {}

    def new_map(name: str) -> ProcessMap:
        return ProcessMap(name, settings, geometry, spill)

    last_refold = time.monotonic()
    while True:
        try:
            if any(g.refold_pending for g in maps.values()):
                due_in = last_refold + refold_s - time.monotonic()
                starving = due_in <= -(REFOLD_STARVE_PERIODS - 1.0) * refold_s
                if starving or not conn.poll(max(due_in, 0.0)):
                    send_refolds(conn, maps)
                    last_refold = time.monotonic()
                    continue
            message = conn.recv()
        except (EOFError, OSError):  # the service is gone
            return
        if message[0] == "quit":
            return
        if message[0] == "sync":  # tests and benchmarks: the map as the graph has it now
            send_refolds(conn, maps)
            last_refold = time.monotonic()
            conn.send(("synced", message[1]))
            continue
        if message[0] == "forget":  # a deleted map (ServiceGraph.forget_map)
            gone = maps.pop(message[1], None)
            if gone is not None:
                gone.close()
            conn.send(("forgotten", message[1]))
            continue
        if message[0] == "place":  # a restarted process: a session the graph had placed
            _, map_name, vehicle, session, T_map_session = message
            graph = maps.get(map_name) or maps.setdefault(
                map_name, ProcessMap(map_name, settings, geometry, spill)
            )
            with contextlib.suppress(RandtError):  # (placed already: nothing to do)
                graph.mapper.place(f"{vehicle}/{session}", T_map_session)
            conn.send(("placed", map_name, vehicle, session))
            continue
        map_name, vehicle, session, seq, join = message[1], message[2], message[3], message[4], message[-1]
        t0 = time.perf_counter()
        try:
            graph = maps.get(map_name) or maps.setdefault(
                map_name, ProcessMap(map_name, settings, geometry, spill)
            )
            # a joining session's fixes are in the shared map's frame, not its own map's
            update = graph.add(message if join is None or join == map_name else (*message[:-2], None, join))
        except Exception as exc:  # bad input (or a bug): this keyframe is refused, the graph goes on
            if not isinstance(exc, RandtError):
                log.exception("graph process: keyframe %s/%s seq %d failed", vehicle, session, seq)
            reason = f"{type(exc).__name__}: {exc}"
            conn.send(("refused", map_name, vehicle, session, seq, reason, time.perf_counter() - t0))
            continue
        conn.send((*update, time.perf_counter() - t0))
        shared = None if join is None or join == map_name else maps.get(join)
        if shared is None and join is not None and join != map_name and message[-2] is not None:
            shared = maps[join] = new_map(join)  # GNSS fixes alone can place it: a graph for them
        if shared is None:  # (no session with priors, or with fixes, has made the shared map's graph yet)
            continue
        # A session without priors, in a map of its own: the same keyframe, unplaced, in the shared
        # map's graph, which places it once two registrations against its keyframes agree.
        t0 = time.perf_counter()
        try:
            update = shared.add(message, joining=True)
        except Exception:  # (it was taken by its own map's graph: a bug)
            log.exception(
                "graph process: keyframe %s/%s seq %d not offered to map %s", vehicle, session, seq, join
            )
            continue
        conn.send((*update, time.perf_counter() - t0))
