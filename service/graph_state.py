"""What the service knows of each map's pose graph (written by the receiver thread, read by HTTP)
and how a session's per-sweep poses are moved with its keyframes' corrections."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from randt.core.odometry import PosePrior
from randt.service.metrics import ServiceMetrics
from randt.service.places import MapPlaces, PlaceKey
from randt.wire.messages import CorrectionMessage, correction_from_arrays

__all__ = [
    "GraphLoop",
    "GraphState",
    "GraphView",
    "Keyframe",
    "correct_trajectory",
    "corrected_mask",
    "wants_keyframe",
]

log = logging.getLogger(__name__)

SessionKey = tuple[str, str]


@dataclass
class Keyframe:
    seq: int
    index: int
    stamp_s: float
    live: np.ndarray
    optimized: np.ndarray | None = None


@dataclass(frozen=True)
class GraphLoop:
    """One loop verification between two keyframes ``(vehicle, session, seq)``."""

    a: tuple[str, str, int]
    b: tuple[str, str, int]
    source: str
    confident: bool
    accepted: bool
    reason: str
    n_inliers: int


@dataclass
class GraphState:
    """What the service knows of the graph: read by HTTP, written by the receiver thread."""

    map: str
    revision: int = 0
    keyframes: dict[SessionKey, dict[int, Keyframe]] = field(default_factory=dict)
    loops: list[GraphLoop] = field(default_factory=list)
    placed: set[SessionKey] = field(default_factory=set)
    n_refused: int = 0
    #: Sessions without priors placed into this map by the graph: ``T_map_session`` (the pose of
    #: their own frame, which their answers stay in, in this map's).
    joined: dict[SessionKey, np.ndarray] = field(default_factory=dict)

    def session_keyframes(self, key: SessionKey) -> list[Keyframe]:
        return sorted(self.keyframes.get(key, {}).values(), key=lambda k: k.index)


def correct_trajectory(
    poses: np.ndarray,
    indices: np.ndarray,
    live: np.ndarray,
    optimized: np.ndarray,
    outside: np.ndarray | None = None,
) -> np.ndarray:
    """Per-sweep poses moved with their keyframes' corrections.

    ``poses`` (N, 4, 4) are the live per-sweep poses; the keyframes are sweeps ``indices`` (K,)
    (increasing) with live poses ``live`` and optimized poses ``optimized`` (K, 4, 4). Each
    keyframe's correction ``C_k = optimized_k @ inv(live_k)`` is interpolated between the two
    keyframes around a sweep (translation linearly, rotation by slerp, over the sweep index) and
    applied on the left; sweeps before the first or after the last keyframe take its correction,
    or, with ``outside`` (4x4: the frame change alone, e.g. a join's ``T_map_session``), are
    only moved by it: live, uncorrected (:func:`corrected_mask` says which).
    """
    poses = np.asarray(poses, dtype=np.float64)
    if len(indices) == 0 or len(poses) == 0:
        return poses.copy()
    if outside is not None:
        out = correct_trajectory(poses, indices, live, optimized)
        beyond = ~corrected_mask(len(poses), indices)
        out[beyond] = outside @ poses[beyond]
        return out
    C = optimized @ np.linalg.inv(live)
    n = len(poses)
    at = np.clip(np.arange(n, dtype=np.float64), indices[0], indices[-1])
    if len(indices) == 1:
        out = C[0] @ poses
        return out
    t = np.interp(at, indices.astype(np.float64), np.arange(len(indices), dtype=np.float64))
    lo = np.minimum(np.floor(t).astype(int), len(indices) - 2)
    w = (t - lo)[:, None]
    trans = (1 - w) * C[lo, :3, 3] + w * C[lo + 1, :3, 3]
    rotations = Rotation.from_matrix(C[:, :3, :3])
    rot = Slerp(np.arange(len(indices), dtype=np.float64), rotations)(t).as_matrix()
    Ci = np.tile(np.eye(4), (n, 1, 1))
    Ci[:, :3, :3] = rot
    Ci[:, :3, 3] = trans
    return Ci @ poses


def corrected_mask(n: int, indices: np.ndarray) -> np.ndarray:
    """Which of ``n`` sweeps lie between two keyframes the graph holds (or are one): those a
    correction is interpolated for; the others are beyond what the graph knows of the session."""
    at = np.arange(n)
    if len(indices) == 0:
        return np.zeros(n, dtype=bool)
    return (at >= indices[0]) & (at <= indices[-1])


def wants_keyframe(poses: list[np.ndarray], last_keyframe: np.ndarray | None, keyframe_m: float) -> bool:
    """The keyframe rule: a session's next sweep is a keyframe when it is its first, or when it is
    expected to reach ``keyframe_m`` from the last keyframe (the last pose's distance plus the
    last step). Also bench/offline.py's, to ask for keyframes where the service would."""
    if last_keyframe is None or not poses:
        return True
    step = float(np.linalg.norm(poses[-1][:3, 3] - poses[-2][:3, 3])) if len(poses) > 1 else 0.0
    return float(np.linalg.norm(poses[-1][:3, 3] - last_keyframe[:3, 3])) + step >= keyframe_m


class GraphView:
    """What the service knows of every map's pose graph: each session's keyframes, live and
    optimized, its newest correction, the joins, the loops, the revisions (written by the
    receiver thread from the graph process's answers, read by the sessions and HTTP), under one
    lock."""

    def __init__(
        self,
        metrics: ServiceMetrics,
        outbox: Callable[[CorrectionMessage], None],
        on_refold: Callable[[str, list[str], np.ndarray, np.ndarray], None] | None,
        on_join: Callable[[str, str, str, np.ndarray], None] | None,
        keyframe_m: float,
        places: MapPlaces | None = None,
    ) -> None:
        self.metrics, self.outbox, self.on_refold, self.on_join = metrics, outbox, on_refold, on_join
        self.keyframe_m = keyframe_m
        #: Each map's keyframes as places to relocalize on (service/places.py): own lock.
        self.places = places or MapPlaces()
        self.lock = threading.Lock()  # guards what follows but ``last``
        self.states: dict[str, GraphState] = {}
        self.session_map: dict[SessionKey, str] = {}
        #: Per session, the correction of its newest optimized keyframe (``optimized @ inv(live)``):
        #: what its new sweeps' points are moved by before they are folded into the map.
        self.corrections: dict[SessionKey, tuple[int, np.ndarray]] = {}
        #: Sessions without priors the graph placed into a shared map: ``(map, T_map_session)``.
        self.joins: dict[SessionKey, tuple[str, np.ndarray]] = {}
        self.last: dict[SessionKey, np.ndarray] = {}  # last offered keyframe's live pose
        self.counted_loops: dict[str, int] = {}  # loop records counted in the metrics, per map
        #: Per map, the revision and loop count when the current process started: a restarted
        #: process counts both from zero, and what the service shows never goes back.
        self.bases: dict[str, tuple[int, int]] = {}
        #: Per map, the sessions placed before the current process started (it places only those
        #: that offer keyframes to it).
        self.placed_before: dict[str, set[SessionKey]] = {}

    def restore(self, records: list[tuple[float, tuple[Any, ...]]]) -> None:
        """The logged keyframes a restarted service takes again: each one's live pose and map."""
        with self.lock:
            for stamp_s, item in records:
                _, map_name, vehicle, session, seq, index, T_live = item[:7]
                key = (vehicle, session)
                self.session_map.setdefault(key, map_name)  # (a join moves it, as it did)
                st = self.states.get(map_name) or self.states.setdefault(map_name, GraphState(map_name))
                st.keyframes.setdefault(key, {})[index] = Keyframe(seq, index, stamp_s, T_live.copy())
                self.last[key] = T_live
        for _, item in records:  # (described outside the lock)
            _, map_name, vehicle, session, _seq, index, _T, points = item[:8]
            home = self.session_map.get((vehicle, session), map_name)
            self.places.add(home, (vehicle, session, index), points)

    def rebase(self, *, empty: bool) -> list[tuple[Any, ...]]:
        """The graph process died: the loops shown so far stay counted; when the next one starts
        ``empty`` (no log), revisions and loops go on from here, the sessions placed so far stay
        placed, and the sessions it had placed into another map than their own are to be placed
        there again (the returned ``place`` items)."""
        with self.lock:
            self.counted_loops = {name: len(st.loops) for name, st in self.states.items()}
            if not empty:
                return []
            self.bases = {name: (st.revision, len(st.loops)) for name, st in self.states.items()}
            self.placed_before = {name: set(st.placed) for name, st in self.states.items()}
            return [("place", map_name, key[0], key[1], T) for key, (map_name, T) in self.joins.items()]

    def offered(
        self, key: SessionKey, map_name: str, keyframe: Keyframe, points: np.ndarray | None = None
    ) -> str:
        """A session's keyframe offered to the graph of ``map_name`` (with its ``points``: a place
        of that map); the map it goes to (the one the session joined, if it did)."""
        self.last[key] = keyframe.live
        with self.lock:
            map_name = self.joins.get(key, (map_name, None))[0]  # it lives in the map it joined
            self.session_map[key] = map_name
            st = self.states.get(map_name) or self.states.setdefault(map_name, GraphState(map_name))
            st.keyframes.setdefault(key, {})[keyframe.index] = keyframe
        if points is not None:
            self.places.add(map_name, (*key, keyframe.index), points)
        return map_name

    def place_pose(self, map_name: str, key: PlaceKey) -> np.ndarray | None:
        """The pose in ``map_name`` of the keyframe ``(vehicle, session, index)`` as a place: its
        optimized pose, or its live one while the session lives in the map it was offered to
        (``None``: the graph holds no such keyframe there)."""
        vehicle, session, index = key
        with self.lock:
            st = self.states.get(map_name)
            kf = None if st is None else st.keyframes.get((vehicle, session), {}).get(index)
            if kf is None:
                return None
            if kf.optimized is not None:
                return kf.optimized
            lives_here = self.session_map.get((vehicle, session)) == map_name
            return kf.live if lives_here and (vehicle, session) not in self.joins else None

    def guesses(self, map_name: str, xyz: np.ndarray) -> list[PosePrior]:
        """Guesses of the pose of a sweep without a prior on ``map_name`` (:meth:`MapPlaces.guesses`)."""
        return self.places.guesses(map_name, xyz, lambda key: self.place_pose(map_name, key))

    def stamp_of(self, map_name: str, key: SessionKey, index: int) -> float:
        """The stamp of a session's keyframe ``index`` (0.0 if the graph holds none)."""
        with self.lock:
            for name in (map_name, self.session_map.get(key)):
                st = None if name is None else self.states.get(name)
                kf = None if st is None else st.keyframes.get(key, {}).get(index)
                if kf is not None:
                    return kf.stamp_s
        return 0.0

    def revision(self, map_name: str) -> int:
        """A map's revision as shown (its base included)."""
        with self.lock:
            st = self.states.get(map_name)
            return max(0 if st is None else st.revision, self.bases.get(map_name, (0, 0))[0])

    def forget(self, map_name: str, revision: int) -> None:
        """A deleted map's graph leaves the view; ``revision`` stays the base of a later one."""
        self.places.forget(map_name)  # (its own lock: never taken inside this one)
        with self.lock:
            self.states.pop(map_name, None)
            self.bases[map_name] = (revision, 0)
            self.counted_loops.pop(map_name, None)
            self.placed_before.pop(map_name, None)
            for key in [k for k, name in self.session_map.items() if name == map_name]:
                del self.session_map[key]
                self.corrections.pop(key, None)
                self.last.pop(key, None)
            for key in [k for k, (name, _) in self.joins.items() if name == map_name]:
                del self.joins[key]

    def wants_keyframe(self, vehicle: str, session: str, poses: list[np.ndarray]) -> bool:
        """Whether a session's next sweep should be a keyframe, from its poses so far: its first
        sweep, or the one expected to reach ``keyframe_m`` from the last keyframe (the last
        pose's distance plus the last step), so that the matcher returns its points
        (``keyframe_voxel_m``)."""
        return wants_keyframe(poses, self.last.get((vehicle, session)), self.keyframe_m)

    def known_place(self, map_name: str, T: np.ndarray, reach_m: float, turn_deg: float) -> bool:
        """The graph of ``map_name`` holds a keyframe within ``reach_m`` of pose ``T`` and within
        ``turn_deg`` of its heading (its optimized pose, else its live one)."""
        with self.lock:
            st = self.states.get(map_name)
            kfs = [] if st is None else [kf for per in st.keyframes.values() for kf in per.values()]
            poses = [kf.live if kf.optimized is None else kf.optimized for kf in kfs]
        if not poses:
            return False
        P = np.asarray(poses)
        near = np.linalg.norm(P[:, :3, 3] - T[:3, 3], axis=1) <= reach_m
        # heading: the angle between the sensors' x axes in the horizontal plane
        cos = np.einsum("ij,j->i", P[near][:, :2, 0], T[:2, 0]) / np.maximum(
            np.linalg.norm(P[near][:, :2, 0], axis=1) * np.linalg.norm(T[:2, 0]), 1e-12
        )
        return bool(np.any(cos >= np.cos(np.radians(turn_deg))))

    def passed(self, key: SessionKey, T: np.ndarray) -> None:
        """A session passed a place the graph holds without offering a keyframe: the spacing of
        its next one counts from here (:meth:`wants_keyframe`)."""
        self.last[key] = np.asarray(T, dtype=np.float64).copy()

    def forget_keyframe(self, map_name: str, key: SessionKey, seq: int) -> None:
        with self.lock:
            st = self.states.get(map_name)
            kfs = {} if st is None else st.keyframes.get(key, {})
            for index in [i for i, kf in kfs.items() if kf.seq == seq]:
                del kfs[index]

    def apply(self, message: tuple[Any, ...], *, publish: bool = True) -> None:
        """One message of the graph process into the service's view of the graphs; with
        ``publish`` false (a keyframe taken again from the log) no correction goes out and no
        counter moves: they did the first time."""
        m = self.metrics
        if message[0] == "refold":
            _, map_name, tile_ids, xyz, intensity, elapsed = message
            m.graph_refold_seconds.observe(elapsed)
            if self.on_refold is not None:
                self.on_refold(map_name, tile_ids, xyz, intensity)
            return
        if message[0] == "refused":
            _, map_name, vehicle, session, seq, reason, elapsed = message
            log.warning("pose graph refused keyframe %s/%s seq %d: %s", vehicle, session, seq, reason)
            m.graph_keyframes.labels("refused").inc()
            m.graph_update_seconds.observe(elapsed)
            self.forget_keyframe(map_name, (vehicle, session), seq)
            with self.lock:
                self.states[map_name].n_refused += 1
            return
        kind, map_name, revision, moved, held, start, loops, placed, elapsed = message
        base_revision, base_loops = self.bases.get(map_name, (0, 0))
        revision += base_revision
        start += base_loops
        if kind == "update" and publish:
            m.graph_keyframes.labels("added").inc()
        m.graph_update_seconds.observe(elapsed)
        by_session: dict[SessionKey, list[Keyframe]] = {}
        joins: list[tuple[SessionKey, np.ndarray]] = []
        with self.lock:
            st = self.states.get(map_name) or self.states.setdefault(map_name, GraphState(map_name))
            for name, T_map_session in placed.items():
                key = cast(SessionKey, tuple(name.split("/", 1)))
                home = self.session_map.get(key)
                if home is None or home == map_name or key in self.joins:
                    # (once joined, it stays: its own map's graph, answering keyframes offered to
                    # it before the service learned of the join, still lists it as placed there)
                    continue
                # A session without priors was placed into this map: it lives here from now on.
                self.joins[key] = (map_name, T_map_session)
                st.joined[key] = T_map_session
                self.session_map[key] = map_name
                self.corrections.pop(key, None)  # its own map's corrections no longer apply
                old = self.states[home]
                old.placed.discard(key)
                for moving in old.keyframes.pop(key, {}).values():
                    moving.optimized = None
                    st.keyframes.setdefault(key, {})[moving.index] = moving
                joins.append((key, T_map_session))  # (logged by on_join)
            # Moved keyframes are corrected (and said to their vehicle); held ones are in the graph
            # where they were answered. A keyframe the graph never held (dropped, refused, offered
            # before this map's graph existed) keeps no optimized pose: trajectories are corrected
            # only from keyframes the graph holds.
            reports = [(r, True) for r in moved] + [(r, False) for r in held]
            for (vehicle, session, _seq, index, P), was_moved in reports:
                if self.session_map.get((vehicle, session)) != map_name:
                    continue  # a session that joined another map, or still joining this one
                kf = st.keyframes.get((vehicle, session), {}).get(index)
                if kf is None:
                    continue
                kf.optimized = P
                if was_moved:
                    by_session.setdefault((vehicle, session), []).append(kf)
                newest = self.corrections.get((vehicle, session))
                if newest is None or newest[0] <= index:
                    self.corrections[(vehicle, session)] = (index, P @ np.linalg.inv(kf.live))
            del st.loops[start:]
            counted = self.counted_loops.get(map_name, 0)
            for loop in loops:
                record = GraphLoop(
                    a=tuple(loop["a"]),
                    b=tuple(loop["b"]),
                    source=loop["source"],
                    confident=loop["confident"],
                    accepted=loop["accepted"],
                    reason=loop["reason"],
                    n_inliers=loop["n_inliers"],
                )
                if len(st.loops) >= counted:
                    m.graph_loops.labels("accepted" if record.accepted else "refused").inc()
                st.loops.append(record)
            self.counted_loops[map_name] = max(counted, len(st.loops))
            st.placed = {
                key
                for key in (
                    *((name.split("/", 1)[0], name.split("/", 1)[1]) for name in placed),
                    *self.placed_before.get(map_name, ()),
                )
                if self.session_map.get(key) == map_name
            }
            st.revision = max(st.revision, revision)
        for (vehicle, session), T_map_session in joins:
            if self.on_join is not None:
                self.on_join(vehicle, session, map_name, T_map_session)
        for (vehicle, session), kfs in by_session.items() if publish else ():
            kfs.sort(key=lambda k: k.index)
            self.outbox(
                correction_from_arrays(
                    vehicle,
                    session,
                    map_name,
                    max(revision, 1),
                    np.array([k.seq for k in kfs]),
                    np.stack([k.optimized for k in kfs if k.optimized is not None]),
                    np.stack([k.live for k in kfs]),
                )
            )

    def fold_target(self, vehicle: str, session: str, map_name: str) -> tuple[np.ndarray | None, str]:
        """``(correction, map)`` for a new sweep's points of a session living in ``map_name``: the
        map they go into (the shared map a session without priors joined, else ``map_name``) and
        what they are moved by first (:meth:`correction`), read together."""
        key = (vehicle, session)
        with self.lock:
            found = self.corrections.get(key)
            joined = self.joins.get(key)
        return (None if found is None else found[1]), (map_name if joined is None else joined[0])

    def joined(self, vehicle: str, session: str) -> tuple[str, np.ndarray] | None:
        """``(map, T_map_session)`` once the graph placed a session without priors into a shared map."""
        with self.lock:
            return self.joins.get((vehicle, session))

    def correction(self, vehicle: str, session: str) -> np.ndarray | None:
        """The correction of the session's newest optimized keyframe (``optimized @ inv(live)``),
        or ``None`` while the graph has moved none of its keyframes: a new sweep's points are
        folded into the map moved by it, so the map follows the graph."""
        with self.lock:
            found = self.corrections.get((vehicle, session))
        return None if found is None else found[1]

    def corrected(self, vehicle: str, session: str, poses: np.ndarray) -> tuple[np.ndarray, str | None]:
        """``(poses, map)``: a session's live per-sweep poses moved with its keyframes
        (:func:`correct_trajectory`) and the map whose frame they are in; the live poses
        unchanged and ``None`` while the session is not placed in a graph."""
        out, map_name, _ = self.corrected_marked(vehicle, session, poses)
        return out, map_name

    def corrected_marked(
        self, vehicle: str, session: str, poses: np.ndarray
    ) -> tuple[np.ndarray, str | None, np.ndarray]:
        """``(poses, map, corrected)``: as :meth:`corrected`, except that the sweeps beyond the
        keyframes the graph holds of the session (before the first, after the newest: the graph
        dropped or has not yet taken them) are served live, only moved into the map's frame
        (a joined session's ``T_map_session``), and ``corrected`` (N,) bool says which were
        corrected from the graph's keyframes (issue 32: what cannot be corrected is marked so)."""
        key = (vehicle, session)
        with self.lock:
            map_name = self.session_map.get(key)
            st = None if map_name is None else self.states.get(map_name)
            placed = st is not None and key in st.placed
            kfs = [] if st is None else [k for k in st.session_keyframes(key) if k.optimized is not None]
            joined = self.joins.get(key)
        kfs = [k for k in kfs if k.index < len(poses)]
        if not placed or not kfs:
            return np.asarray(poses, dtype=np.float64).copy(), None, np.zeros(len(poses), dtype=bool)
        indices = np.array([k.index for k in kfs])
        live = np.stack([k.live for k in kfs])
        opt = np.stack([k.optimized for k in kfs if k.optimized is not None])
        frame = joined[1] if joined is not None and joined[0] == map_name else np.eye(4)
        out = correct_trajectory(poses, indices, live, opt, outside=frame)
        return out, map_name, corrected_mask(len(poses), indices)

    def maps(self) -> list[str]:
        """Maps with a graph (a keyframe was offered to it)."""
        with self.lock:
            return sorted(self.states)

    def snapshot(self, map_name: str) -> GraphState | None:
        """A consistent copy of one map's graph state (keyframes copied shallowly), or ``None``."""
        with self.lock:
            st = self.states.get(map_name)
            if st is None:
                return None
            return GraphState(
                st.map,
                st.revision,
                {k: dict(v) for k, v in st.keyframes.items()},
                list(st.loops),
                set(st.placed),
                st.n_refused,
                dict(st.joined),
            )
