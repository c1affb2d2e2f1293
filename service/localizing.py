"""A session's choice, sweep by sweep, between localizing on its map and mapping.

:class:`SessionLocalizer` is the session thread's side (docs/mapping.md, "Localizing on the map"):
a session in the shared map's frame, with ``localize`` on, localizes where the map around the
vehicle has at least ``localize_min_map_points`` points. It cuts the window (the map's tiles
within ``localize_radius_m``) and sends it with the sweep once, then again after
``localize_reload_m`` of travel or when the map's content changed (its token); the matcher holds
it meanwhile (service/matcher_io.py, ``MapWindows``). A window cut again sends only the points of
the tiles that are new to it or grew since (:data:`RESEND_GROWTH`): the matcher keeps the others
prepared. A sweep the map does not hold (its answer comes back not localized: the match refused
it, the map ends there, or changed) is tried again; :data:`MISSES_BEFORE_MAPPING` in a row make
the session map for :data:`MAP_AFTER_MISS` sweeps before it tries again; its points extend the map
meanwhile.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

from randt.core.errors import InvalidCloudError, NotFoundError
from randt.core.odometry import IncrementalMatcher, MapPreparation, PosePrior, ScanResult
from randt.core.registration import ReferencePiece
from randt.core.tiles import Tile, TileGrid
from randt.service.matcher_io import MapWindow
from randt.service.session_record import SessionFrame
from randt.service.settings import ServiceSettings

__all__ = [
    "MAP_AFTER_MISS",
    "MAP_SHARE_RADIUS_M",
    "MIN_MAP_SHARE",
    "MISSES_BEFORE_MAPPING",
    "RESEND_GROWTH",
    "MapPieces",
    "SessionLocalizer",
    "expects_to_localize",
]

#: Sweeps a session maps after MISSES_BEFORE_MAPPING in a row that the map did not hold, before it
#: localizes again.
MAP_AFTER_MISS = 20
#: Sweeps in a row asked to be localized and not, before the session maps: one refused match on
#: mapped streets is no reason to map (its odometry would drift and fold points beside the map's).
MISSES_BEFORE_MAPPING = 3
#: A window is cut only where at least this share of the points of the tiles within
#: MAP_SHARE_RADIUS_M of the vehicle (what most of a sweep's matched points fall on) were there
#: before the session's own came near them: a session that mapped up to the map's edge would
#: otherwise localize on its own trail and the little the map saw from afar, and slide with it.
MIN_MAP_SHARE = 0.75
MAP_SHARE_RADIUS_M = 30.0
#: A tile the matcher holds is sent again with a new window when it has grown by more than this
#: share since: inserts only add (a removal changes the map's token, and every tile is sent), and
#: what a localized session folds is the little the map lacked around it, which changes no match
#: (docs/mapping.md, "In the service").
RESEND_GROWTH = 0.05


#: Tiles' pieces the service keeps prepared for its sessions' windows (:class:`MapPieces`), the
#: least recently used leaving beyond (a piece is its tile's voxel moments: about 100 KB).
MAX_PIECES = 2048


class MapPieces:
    """The map's tiles prepared once for every session's windows (:class:`MapPreparation`: their
    moments at the finest NDT voxel), in the service process: vehicles in one town cut windows
    of many of the same tiles, which each session's matcher prepared again (docs/mapping.md).
    A tile is prepared again once it has grown by more than :data:`RESEND_GROWTH` since (the same
    rule a window resends by); a window gets the piece and the version it was prepared at."""

    def __init__(self, preparation: MapPreparation) -> None:
        self.preparation = preparation
        self._lock = threading.Lock()
        self._pieces: OrderedDict[tuple[tuple[str, int, int], str], tuple[int, int, ReferencePiece]] = (
            OrderedDict()
        )

    @classmethod
    def for_settings(cls, settings: ServiceSettings) -> MapPieces | None:
        """The service's, when it localizes and its NDT levels are fixed (else each matcher
        prepares the tiles it is sent, at the levels of its session's first sweep)."""
        if not settings.localize:
            return None
        matcher = IncrementalMatcher(settings.session_matcher(), settings.registration)
        try:
            return cls(matcher.map_preparation())
        except InvalidCloudError:
            return None

    def get(self, token: tuple[str, int, int], tile: Tile) -> tuple[int, int, ReferencePiece]:
        """``(version, points, piece)`` of ``tile`` of the map ``token`` names, prepared now or
        before (while the tile grew by at most :data:`RESEND_GROWTH` since)."""
        key = (token, tile.id)
        with self._lock:
            kept = self._pieces.get(key)
            if kept is not None and tile.n_points <= kept[1] * (1.0 + RESEND_GROWTH):
                self._pieces.move_to_end(key)
                return kept
        made = (tile.version, tile.n_points, self.preparation.piece(tile.points))
        with self._lock:
            self._pieces[key] = made
            self._pieces.move_to_end(key)
            while len(self._pieces) > MAX_PIECES:
                self._pieces.popitem(last=False)
        return made

    def __len__(self) -> int:
        return len(self._pieces)


def expects_to_localize(
    settings: ServiceSettings, grid: TileGrid, prior_pose: object, *, only: bool = False
) -> bool:
    """Whether a session opening with this prior pose (16 floats, row-major ``T_map_sensor``;
    ``None``: none) will localize: ``localize`` on (or the session localizes ``only``) and the
    map's tiles around the prior holding what :class:`SessionLocalizer` asks of a window
    (admission counts it at that cost)."""
    if not (settings.localize or only) or prior_pose is None:
        return False
    T = np.asarray(prior_pose, dtype=np.float64).reshape(-1)
    if T.shape != (16,) or not np.isfinite(T).all():
        return False
    tiles = grid.tiles_near(T[[3, 7]], settings.localize_radius_m)
    return sum(t.n_points for t in tiles) >= settings.localize_min_map_points


class SessionLocalizer:
    """One session's localizing or mapping (module docstring)."""

    def __init__(
        self, settings: ServiceSettings, pieces: MapPieces | None = None, *, only: bool = False
    ) -> None:
        #: a session that only localizes (``localize_only``): it never maps, whatever ``localize``
        self.only = only
        self.enabled = settings.localize or only
        self.pieces = pieces  # (the service's tiles prepared for every session; None: send points)
        self.radius_m = settings.localize_radius_m
        self.reload_m = settings.localize_reload_m
        self.first_radius_m = min(settings.localize_first_radius_m, self.radius_m)
        self.min_points = settings.localize_min_map_points
        #: the window the matcher holds (token, centre; its tiles' versions and sizes as sent;
        #: its radius), as this side sent it
        self._held: (
            tuple[tuple[str, int, int], tuple[float, float], dict[str, tuple[int, int]], float] | None
        ) = None
        self._cut_before = False  # a window was cut for this session before (its first is smaller)
        self._asked = False  # the last sweep asked to be localized
        self._mapping_for = 0  # sweeps to map before localizing again
        self._misses = 0  # sweeps in a row asked to be localized that were not
        #: the last sweep was localized on the map (the next is likely to be)
        self.localizing = False
        #: per map, the points each tile ``(ix, iy)`` held before this session's first points near
        #: it: what it may localize on (not its own trail)
        self._before: dict[str, dict[tuple[int, int], int]] = {}

    def window(
        self,
        grid: TileGrid,
        token: tuple[str, int, int],
        prior: PosePrior | None,
        poses: list[np.ndarray],
        frame: SessionFrame,
    ) -> MapWindow | None:
        """The window to localize this sweep on, or ``None``: map it. The vehicle is about at its
        ``prior``, else at its last pose (neither: not known yet, it maps); only a session in the
        shared map's frame localizes (the map of ``grid``, its fold target)."""
        self._asked = False
        if not self.enabled or frame != "map" or (prior is None and not poses):
            return None
        if self._mapping_for > 0:
            self._mapping_for -= 1
            return None
        near = prior.T_world_sensor if prior is not None else poses[-1]
        xy = np.asarray(near, dtype=np.float64)[:2, 3]
        held = self._held
        # (a first window, smaller, is cut again sooner: as much map ahead of the vehicle)
        if (
            held is not None
            and held[0] == token
            and np.hypot(*(xy - held[1])) <= self.reload_m - (self.radius_m - held[3])
        ):
            self._asked = True
            return MapWindow(token, held[1], radius_m=held[3])
        return self._cut(grid, token, xy)

    def not_on_map(
        self, map_name: str, grid: TileGrid, prior: PosePrior | None, poses: list[np.ndarray]
    ) -> str:
        """Why a session that only localizes got no window for this sweep (:meth:`window`
        returned ``None``): its place is not known, or the map holds too little around it."""
        if prior is None and not poses:
            return (
                "this session only localizes (localize_only) and the vehicle's place is not known: "
                "send its scans with a prior pose (GNSS/INS); without one it is relocalized on the "
                "map only where the service runs its pose graph (the graph's keyframes are the places)"
            )
        near = prior.T_world_sensor if prior is not None else poses[-1]
        x, y = (float(v) for v in np.asarray(near, dtype=np.float64)[:2, 3])
        radius = self.radius_m if self._cut_before else self.first_radius_m
        held = sum(t.n_points for t in grid.tiles_near(np.array([x, y]), radius))
        return (
            f"this session only localizes (localize_only) and map {map_name!r} holds {held:,} points "
            f"within {radius:g} m of ({x:.1f}, {y:.1f}) m, fewer than the {self.min_points:,} it "
            "localizes on: no pose here"
        )

    def _cut(self, grid: TileGrid, token: tuple[str, int, int], xy: np.ndarray) -> MapWindow | None:
        """A new window: the tiles within ``localize_radius_m`` (the session's first:
        ``localize_first_radius_m``, which costs its start less), when they hold at least
        ``localize_min_map_points`` that were not this session's (:meth:`folding`). The matcher
        keeps the tiles of the window before: only the points of the new ones, and of those that
        grew by more than :data:`RESEND_GROWTH` since they were sent, go with it."""
        radius = self.radius_m if self._cut_before else self.first_radius_m
        tiles = grid.tiles_near(xy, radius)
        before = self._before.get(token[0], {})
        if sum(self._others(t, before) for t in tiles) < self.min_points or not self._mostly_others(
            grid, xy, before
        ):
            self._held = None
            return None
        sent = self._held[2] if self._held is not None and self._held[0] == token else {}
        held: dict[str, tuple[int, int]] = {}
        points: dict[str, np.ndarray] = {}
        pieces: dict[str, ReferencePiece] = {}
        for t in tiles:
            was = sent.get(t.id)
            if was is not None and t.n_points <= was[1] * (1.0 + RESEND_GROWTH):
                held[t.id] = was
            elif self.pieces is not None:
                version, n_points, pieces[t.id] = self.pieces.get(token, t)
                held[t.id] = (version, n_points)
            else:
                held[t.id], points[t.id] = (t.version, t.n_points), t.points
        center = (float(xy[0]), float(xy[1]))
        self._held, self._asked, self._cut_before = (token, center, held, radius), True, True
        listed = tuple((tid, v) for tid, (v, _) in held.items())
        return MapWindow(token, center, listed, points, radius, pieces=pieces)

    @staticmethod
    def _others(tile: Tile, before: dict[tuple[int, int], int]) -> int:
        """The points of ``tile`` that were there before the session's came near it."""
        return min(tile.n_points, before.get((tile.ix, tile.iy), tile.n_points))

    def _mostly_others(self, grid: TileGrid, xy: np.ndarray, before: dict[tuple[int, int], int]) -> bool:
        """Whether the tiles within :data:`MAP_SHARE_RADIUS_M` of the vehicle hold at least
        :data:`MIN_MAP_SHARE` of points that were there before the session's came near them."""
        near = grid.tiles_near(xy, MAP_SHARE_RADIUS_M)
        total = sum(t.n_points for t in near)
        return total == 0 or sum(self._others(t, before) for t in near) >= MIN_MAP_SHARE * total

    def folding(self, map_name: str, grid: TileGrid, xyz: np.ndarray) -> None:
        """A sweep's points about to be folded into ``map_name`` (``grid``): each tile around them,
        one beyond their box, that none of the session's points came near before keeps what it
        holds now as what it held before the session. A session mapping a new street does not
        localize on the trail it leaves (its window would end where its trail does), whichever
        way its points reach the tiles (its folds, the pose graph's re-folds)."""
        if not self.enabled or not len(xyz):
            return
        size = float(grid.tile_size_m)
        xy = xyz[:, :2]
        lo = np.floor(xy.min(axis=0) / size).astype(np.int64) - 1
        hi = np.floor(xy.max(axis=0) / size).astype(np.int64) + 1
        before = self._before.setdefault(map_name, {})
        for ix in range(int(lo[0]), int(hi[0]) + 1):
            for iy in range(int(lo[1]), int(hi[1]) + 1):
                if (ix, iy) not in before:
                    try:
                        before[ix, iy] = grid.tile(ix, iy).n_points
                    except NotFoundError:
                        before[ix, iy] = 0

    def answered(self, result: ScanResult) -> None:
        """A sweep's answer. One asked to be localized that was not (a sweep the match refused,
        the map does not hold it there, or the matcher lost the window): the next sweep tries the
        same window, the one after a window sent whole, and after :data:`MISSES_BEFORE_MAPPING`
        in a row the session maps for :data:`MAP_AFTER_MISS` sweeps (the poses localized are
        counted as they go out: SessionInfo)."""
        self.localizing = result.localized
        if result.localized:
            self._misses = 0
            return
        if not self._asked:
            return
        self._misses += 1
        if self._misses >= MISSES_BEFORE_MAPPING:
            self._held, self._misses = None, 0
            self._mapping_for = 0 if self.only else MAP_AFTER_MISS
        elif self._misses >= 2:
            self._held = None
