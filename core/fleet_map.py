"""One map from many sessions: keyframes, place recognition, verified loops and the pose graph.

:class:`FleetMapper` takes each session's keyframes as its odometry produces them (a pose in the
session's own frame, the sweep's points, an optional GNSS fix) and keeps every session of a fleet
in one world frame: placement (by GNSS, or by two agreeing strong registrations), loop candidates
(:mod:`randt.core.place`) verified by global registration (:mod:`randt.core.global_registration`),
and the pose graph (:mod:`randt.core.pose_graph`). The per-sweep odometry is not touched: a
correction reaches a client as new keyframe poses, never as a rewritten answer. Each step and why:
docs/mapping.md, "One map from many sessions".
"""

from __future__ import annotations

import logging
from collections.abc import Hashable
from dataclasses import dataclass, field, replace
from typing import cast

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from randt.core.errors import InvalidRequestError
from randt.core.global_registration import GlobalResult, GlobalSettings, register_global
from randt.core.keyframe_cache import KeyframeCache
from randt.core.place import PlaceIndex, PlaceSettings, query_descriptors
from randt.core.pose_graph import PoseGraph, PoseGraphSettings
from randt.core.registration import sanitize_points
from randt.core.transforms import invert, rotation_angle_deg, umeyama
from randt.core.voxel import voxel_downsample

__all__ = ["FleetMapSettings", "FleetMapper", "LoopRecord", "level", "placement_vote"]

log = logging.getLogger(__name__)

Key = tuple[str, int]


class FleetMapSettings(BaseModel):
    """How :class:`FleetMapper` builds one graph from many sessions."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    keyframe_voxel_m: float = Field(default=0.25, gt=0, description="points kept per keyframe")
    odometry_sigma_fraction: float = Field(
        default=0.01, gt=0, description="odometry translation sigma per metre between keyframes"
    )
    odometry_sigma_deg_per_m: float = Field(default=0.02, gt=0)
    odometry_min_sigma_m: float = Field(default=0.02, gt=0)
    gnss_alignment_m: float = Field(
        default=40.0, gt=0, description="travel with fixes before a GNSS session is placed"
    )
    gnss_min_fixes: int = Field(default=4, ge=3)
    recent_exclusion_m: float = Field(
        default=60.0, gt=0, description="a session's own keyframes nearer in travel are no loop"
    )
    proximity_m: float = Field(
        default=12.0,
        gt=0,
        description="graph-estimate loop candidates: the nearest keyframe within this (registrations "
        "of sweeps farther apart are less accurate)",
    )
    loop_spacing_m: float = Field(
        default=15.0,
        ge=0,
        description="after an accepted loop between two sessions, candidates between them within "
        "this travel are skipped",
    )
    loop_sigma_m: float = Field(default=0.1, gt=0)
    loop_sigma_deg: float = Field(default=0.5, gt=0)
    loop_gate_m: float = Field(
        default=15.0, gt=0, description="a loop between placed keyframes disagreeing more is refused"
    )
    loop_max_anisotropy: float = Field(
        default=6.0,
        gt=1,
        description="a loop or placement vote whose refinement holds one direction this many times "
        "less well than the best (GlobalResult.anisotropy) is refused: NDT slid along a corridor "
        "(0.8 m off at 46 inliers, seen at 13; good loops 1.5-3.5)",
    )
    placement_max_distance: float = Field(
        default=0.6,
        gt=0,
        le=2,
        description="Scan Context distance up to which a session without a place proposes its best "
        "candidate for verification (looser than place.max_distance: verification decides, and "
        "without a graph estimate there is no other candidate)",
    )
    placement_agreement_m: float = Field(
        default=2.0, gt=0, description="two placements of a session without GNSS must agree within"
    )
    placement_agreement_deg: float = Field(default=3.0, gt=0)
    # A placement has no estimate to gate it, and a street can look like another one for 70 m:
    # a vote must be a strong registration, refined and past both of these, where the true
    # registrations measured are and the confident wrong ones are not (docs/mapping.md, "A session
    # without priors joins the shared map"):
    placement_min_inliers: int = Field(
        default=30, ge=3, description="a placement vote needs this many consistent correspondences"
    )
    placement_min_overlap: float = Field(
        default=0.6, ge=0, le=1, description="and this share of its points on the keyframe it matched"
    )
    global_registration: GlobalSettings = Field(default_factory=lambda: GlobalSettings(max_range_m=60.0))
    place: PlaceSettings = Field(default_factory=PlaceSettings)
    pose_graph: PoseGraphSettings = Field(default_factory=PoseGraphSettings)


@dataclass(frozen=True)
class LoopRecord:
    """One loop verification: keyframes ``a`` (source) and ``b`` (target), ``T_b_a`` found;
    ``confident``: the registration passed verification (and the graph's gate); ``accepted``: it
    entered the graph (a placement vote enters only once a second one agrees)."""

    a: Key
    b: Key
    source: str  # "place" | "proximity" | "placement"
    confident: bool
    accepted: bool
    reason: str
    n_inliers: int
    T_b_a: np.ndarray


@dataclass
class _Keyframe:
    """A keyframe's pose, travel and fix. Its points are in :attr:`FleetMapper.points` (a
    :class:`~randt.core.keyframe_cache.KeyframeCache`: on disk, the recent ones in RAM)."""

    T_odom: np.ndarray
    #: Scan Context of the sweep, then of it seen from ahead and behind (randt.core.place): [0] goes
    #: into the place index, the stack is queried once, when the keyframe comes (then None)
    descriptors: np.ndarray | None
    travel_m: float
    gnss: tuple[np.ndarray, np.ndarray] | None
    #: a fix with attitude (GNSS/INS, a vehicle's prior pose): the whole pose and its (t, r)
    #: covariance, a pose prior in the graph instead of the position alone
    attitude: tuple[np.ndarray, np.ndarray] | None = None


@dataclass
class _Session:
    name: str
    keyframes: list[_Keyframe] = field(default_factory=list)
    T_world_session: np.ndarray | None = None
    #: confident registrations against placed keyframes: (T_world_session they imply, loop index)
    placement_votes: list[tuple[np.ndarray, int]] = field(default_factory=list)
    #: (other session, own travel) of the last accepted loop with each session
    last_loop_travel: dict[str, float] = field(default_factory=dict)

    @property
    def placed(self) -> bool:
        return self.T_world_session is not None


def placement_vote(result: GlobalResult, settings: FleetMapSettings) -> tuple[bool, str]:
    """Whether a confident registration of a session without a place may vote for one, and why
    not: only with NDT's refinement kept (when the settings refine), ``placement_min_inliers``
    consistent correspondences and ``placement_min_overlap`` (:class:`FleetMapSettings`; the
    registrations they were measured on: docs/mapping.md)."""
    if settings.global_registration.refine and not result.refined:
        return False, "not a placement vote: NDT's refinement was not kept"
    if result.n_inliers < settings.placement_min_inliers:
        return False, (
            f"not a placement vote: {result.n_inliers} consistent correspondences, "
            f"fewer than {settings.placement_min_inliers}"
        )
    if result.overlap < settings.placement_min_overlap:
        overlap = f"{result.overlap:.2f} below {settings.placement_min_overlap:g}"
        return False, f"not a placement vote: overlap {overlap}"
    return True, "placement vote: waits for a second one that agrees"


class FleetMapper:
    """Sessions' keyframes into one optimized graph (module docstring)."""

    def __init__(self, settings: FleetMapSettings | None = None, points: KeyframeCache | None = None) -> None:
        """``points``: where the keyframes' points are kept (default: in memory)."""
        self.settings = settings or FleetMapSettings()
        self.graph = PoseGraph(self.settings.pose_graph)
        self.index = PlaceIndex(self.settings.place)
        self.sessions: dict[str, _Session] = {}
        self.loops: list[LoopRecord] = []
        self.points = points if points is not None else KeyframeCache()

    def keyframe_points(self, key: Key) -> np.ndarray:
        """A keyframe's points (sensor frame, at ``keyframe_voxel_m``)."""
        return self.points.get(key)[0]

    # ------------------------------------------------------------------ input
    def add_keyframe(
        self,
        session: str,
        T_session_sensor: np.ndarray,
        points_sensor: np.ndarray,
        gnss: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Key:
        """The next keyframe of ``session``: its odometry pose, points, and an optional GNSS fix
        of the sensor origin: ``(position_xyz, 3x3 covariance)``, or with attitude (GNSS/INS, a
        vehicle's prior pose) ``(T_world_sensor 4x4, 6x6 (t, r) covariance)``, which enters the
        graph as a whole-pose prior: a session whose only fix is its first keeps the heading it
        gave, instead of turning about that fix to meet the loops (docs/mapping.md, "One map from
        many sessions"). Returns its key."""
        T = np.asarray(T_session_sensor, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InvalidRequestError(f"keyframe of {session!r}: a finite 4x4 pose is needed")
        # Everything is checked before anything is kept: a refused keyframe leaves no trace.
        xyz, _ = sanitize_points(points_sensor, name=f"keyframe of {session!r}", min_points=10)
        gnss, attitude = _fix(session, gnss)
        s = self.sessions.setdefault(session, _Session(session))
        travel = 0.0
        if s.keyframes:
            prev = s.keyframes[-1]
            travel = prev.travel_m + float(np.linalg.norm(T[:3, 3] - prev.T_odom[:3, 3]))
        pts = voxel_downsample(xyz, self.settings.keyframe_voxel_m)
        kf = _Keyframe(T, query_descriptors(pts, self.settings.place), travel, gnss, attitude)
        key = (session, len(s.keyframes))
        self.points.put(key, pts)
        s.keyframes.append(kf)
        if s.placed:
            self._insert(s, key[1])
            self._search_loops(s, key[1])
            self.graph.optimize()
        else:
            self._try_to_place(s)
        if kf.descriptors is not None:  # (the query stack was for this call only)
            kf.descriptors = None if s.placed else kf.descriptors[:1]
        return key

    # -------------------------------------------------------------- placement
    def place(self, session: str, T_world_session: np.ndarray) -> None:
        """Place ``session`` where its frame is known (a session in its own map: the identity),
        before or after its first keyframes; its keyframes then enter the graph as they come."""
        T = np.asarray(T_world_session, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InvalidRequestError(f"placement of {session!r}: a finite 4x4 pose is needed")
        s = self.sessions.setdefault(session, _Session(session))
        if s.placed:
            raise InvalidRequestError(f"session {session!r} is placed already")
        self._place(s, T, "given")

    def _try_to_place(self, s: _Session) -> None:
        fixes = [(kf.T_odom[:3, 3], kf.gnss[0]) for kf in s.keyframes if kf.gnss is not None]
        if len(fixes) >= self.settings.gnss_min_fixes:
            odo = np.array([f[0] for f in fixes])
            span = float(np.linalg.norm(odo.max(axis=0) - odo.min(axis=0)))
            if span >= self.settings.gnss_alignment_m:
                T, _ = umeyama(odo, np.array([f[1] for f in fixes]))
                self._place(s, level(T), "gnss")
                return
        if not any(o.placed for o in self.sessions.values()):
            return
        k = len(s.keyframes) - 1
        record = self._verify_against_placed(s, k)
        if record is None or not record.confident:
            return
        T_world_b = self.graph.pose(record.b)
        vote = T_world_b @ record.T_b_a @ invert(s.keyframes[k].T_odom)
        for earlier, where in s.placement_votes:
            dt = float(np.linalg.norm(earlier[:3, 3] - vote[:3, 3]))
            dr = rotation_angle_deg(earlier[:3, :3].T @ vote[:3, :3])
            if dt <= self.settings.placement_agreement_m and dr <= self.settings.placement_agreement_deg:
                self._place(s, vote, "registration")
                for index in (where, len(self.loops) - 1):
                    self.loops[index] = replace(self.loops[index], accepted=True, reason="")
                    self._add_loop(self.loops[index])
                self.graph.optimize()
                return
        s.placement_votes.append((vote, len(self.loops) - 1))

    def _place(self, s: _Session, T_world_session: np.ndarray, how: str) -> None:
        s.T_world_session = T_world_session
        log.info("session %s placed by %s", s.name, how)
        for k in range(len(s.keyframes)):
            self._insert(s, k)
        for kf in s.keyframes:  # (in the place index now)
            kf.descriptors = None
        if how == "registration":
            return
        self.graph.optimize()

    def _insert(self, s: _Session, k: int) -> None:
        assert s.T_world_session is not None
        kf = s.keyframes[k]
        key = (s.name, k)
        self.graph.add_node(key, s.T_world_session @ kf.T_odom)
        if k == 0:  # a gauge for a session without GNSS, its roll and pitch for every session
            self.graph.anchor(key)
        else:
            prev = s.keyframes[k - 1]
            rel = invert(prev.T_odom) @ kf.T_odom
            dist = max(float(np.linalg.norm(rel[:3, 3])), 1.0)
            st = max(self.settings.odometry_sigma_fraction * dist, self.settings.odometry_min_sigma_m)
            sr = np.radians(self.settings.odometry_sigma_deg_per_m * dist)
            self.graph.add_odometry((s.name, k - 1), key, rel, np.diag([st**2] * 3 + [sr**2] * 3))
        if kf.attitude is not None:
            self.graph.add_prior(key, kf.attitude[0], kf.attitude[1], robust=True)
        elif kf.gnss is not None:
            self.graph.add_gnss(key, kf.gnss[0], kf.gnss[1])
        assert kf.descriptors is not None  # (dropped once it is in the index)
        self.index.add(key, kf.descriptors[0])

    # ------------------------------------------------------------------ loops
    def _excluded(self, s: _Session, k: int) -> set[Hashable]:
        """Own keyframes within ``recent_exclusion_m`` of travel, and sessions looped recently."""
        travel = s.keyframes[k].travel_m
        out: set[Hashable] = {
            (s.name, j)
            for j, kf in enumerate(s.keyframes)
            if abs(kf.travel_m - travel) < self.settings.recent_exclusion_m
        }
        for other, t in s.last_loop_travel.items():
            if travel - t < self.settings.loop_spacing_m and other in self.sessions:
                out |= {(other, j) for j in range(len(self.sessions[other].keyframes))}
        return out

    def _search_loops(self, s: _Session, k: int) -> None:
        excluded = self._excluded(s, k)
        key = (s.name, k)
        candidate: tuple[Key, str] | None = None
        descriptors = s.keyframes[k].descriptors
        assert descriptors is not None  # (the newest keyframe's, still whole)
        found = self.index.query(descriptors, exclude=excluded)
        if found:
            candidate = (cast(Key, found[0].key), "place")
        else:
            here = self.graph.pose(key)[:3, 3]
            best, best_d = None, self.settings.proximity_m
            for other_key, T in self.graph.poses().items():
                if other_key in excluded or other_key == key:
                    continue
                d = float(np.linalg.norm(T[:3, 3] - here))
                if d < best_d:
                    best, best_d = other_key, d
            if best is not None:
                candidate = (cast(Key, best), "proximity")
        if candidate is None:
            return
        record = self._verify(key, candidate[0], candidate[1], gate=True)
        if record.confident:
            self.loops[-1] = record = replace(record, accepted=True)
            self._add_loop(record)

    def _verify_against_placed(self, s: _Session, k: int) -> LoopRecord | None:
        placed = set(self.graph.poses())
        excluded = {key for key in self.index.keys() if key not in placed}  # noqa: SIM118
        descriptors = s.keyframes[k].descriptors
        assert descriptors is not None  # (the newest keyframe's, still whole)
        found = self.index.query(
            descriptors, exclude=excluded, max_distance=self.settings.placement_max_distance
        )
        if not found:
            return None
        return self._verify((s.name, k), cast(Key, found[0].key), "placement", gate=False)

    def _verify(self, a: Key, b: Key, source: str, *, gate: bool) -> LoopRecord:
        result = register_global(
            self.keyframe_points(a), self.keyframe_points(b), self.settings.global_registration
        )
        reason = result.reason
        confident = result.confident
        if confident and result.anisotropy > self.settings.loop_max_anisotropy:
            confident = False
            reason = (
                f"the refinement holds one direction {result.anisotropy:.1f} times less well than the "
                f"best (above {self.settings.loop_max_anisotropy:g}): it may slide along a corridor"
            )
        if confident and gate:
            expected = invert(self.graph.pose(b)) @ self.graph.pose(a)
            off = float(np.linalg.norm(expected[:3, 3] - result.T_target_source[:3, 3]))
            if off > self.settings.loop_gate_m:
                confident, reason = False, f"disagrees with the graph by {off:.1f} m"
        if confident and not gate:
            confident, reason = placement_vote(result, self.settings)
        record = LoopRecord(a, b, source, confident, False, reason, result.n_inliers, result.T_target_source)
        self.loops.append(record)
        return record

    def _add_loop(self, record: LoopRecord) -> None:
        s = self.settings
        cov = np.diag([s.loop_sigma_m**2] * 3 + [np.radians(s.loop_sigma_deg) ** 2] * 3)
        self.graph.add_loop(record.b, record.a, record.T_b_a, cov)
        sa, sb = self.sessions[record.a[0]], self.sessions[record.b[0]]
        if sa is sb:  # a loop within a session: the newer keyframe's travel
            ta = max(sa.keyframes[record.a[1]].travel_m, sa.keyframes[record.b[1]].travel_m)
            sa.last_loop_travel[sa.name] = ta
            return
        sa.last_loop_travel[sb.name] = sa.keyframes[record.a[1]].travel_m
        sb.last_loop_travel[sa.name] = sb.keyframes[record.b[1]].travel_m

    # ----------------------------------------------------------------- output
    def poses(self) -> dict[Key, np.ndarray]:
        """Every placed keyframe's optimized ``T_world_sensor``."""
        return {cast(Key, k): v for k, v in self.graph.poses().items()}

    def placed_sessions(self) -> list[str]:
        return [name for name, s in self.sessions.items() if s.placed]


def _fix(
    session: str, gnss: tuple[np.ndarray, np.ndarray] | None
) -> tuple[tuple[np.ndarray, np.ndarray] | None, tuple[np.ndarray, np.ndarray] | None]:
    """A keyframe's fix checked: ``(position, 3x3)``, and ``(pose, 6x6)`` when it has attitude."""
    if gnss is None:
        return None, None
    value = np.asarray(gnss[0], dtype=np.float64)
    cov = np.asarray(gnss[1], dtype=np.float64)
    with_attitude = value.shape == (4, 4)
    size = 6 if with_attitude else 3
    if (not with_attitude and value.reshape(-1).shape != (3,)) or cov.shape != (size, size):
        raise InvalidRequestError(
            f"GNSS fix of {session!r}: a position (3,) and a 3x3 covariance, or a pose (4, 4) and a "
            f"6x6 covariance are needed, got {value.shape} and {cov.shape}"
        )
    if not np.all(np.isfinite(value)) or not np.all(np.isfinite(cov)):
        raise InvalidRequestError(f"GNSS fix of {session!r}: the fix and its covariance must be finite")
    if np.linalg.eigvalsh(0.5 * (cov + cov.T)).min() <= 0:
        raise InvalidRequestError(f"GNSS fix of {session!r}: the covariance must be positive definite")
    if not with_attitude:
        return (value.reshape(-1), cov), None
    return (value[:3, 3].copy(), cov[:3, :3].copy()), (value, cov)


def level(T: np.ndarray) -> np.ndarray:
    """A GNSS fit's rotation reduced to its yaw: positions along a nearly straight, level drive
    leave roll and pitch unobservable, and the odometry frame is already gravity-aligned."""
    yaw = float(np.arctan2(T[1, 0], T[0, 0]))
    out = np.eye(4)
    out[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    out[:3, 3] = T[:3, 3]
    return out
