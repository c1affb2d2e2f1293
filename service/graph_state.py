"""What the service knows of each map's pose graph (written by the receiver thread, read by HTTP)
and how a session's per-sweep poses are moved with its keyframes' corrections."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

__all__ = ["GraphLoop", "GraphState", "Keyframe", "correct_trajectory", "corrected_mask", "wants_keyframe"]

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
