"""Trajectory error metrics.

They take two (N,4,4) float64 stacks of world<-sensor poses, row ``i`` of the reference ``Q``
corresponding to row ``i`` of the estimate ``P`` (associate timestamps first):

- :func:`ate`: absolute trajectory error of positions after an optional Umeyama alignment
  (as evo's ``APE`` with ``PoseRelation.translation_part``).
- :func:`rpe`: relative pose error over a fixed frame gap (evo's ``RPE`` definition).
- :func:`kitti_relative_errors`: the KITTI odometry devkit's segment errors
  (``evaluate_odometry.cpp``: 100..800 m segments, every 10th frame as a start).
- :func:`evaluate_trajectory`: the three bundled into one JSON-ready dict.

Every result is a frozen dataclass with an ``as_dict()`` giving plain floats, ints and lists.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation

from randt.core.errors import InvalidCloudError
from randt.core.metrics.values import json_float
from randt.core.transforms import invert, transform_points, umeyama

__all__ = [
    "KITTI_LENGTHS_M",
    "AteResult",
    "ErrorStats",
    "KittiLengthError",
    "KittiResult",
    "RpeResult",
    "ate",
    "evaluate_trajectory",
    "kitti_relative_errors",
    "rpe",
]

logger = logging.getLogger(__name__)

#: Segment lengths of the KITTI odometry benchmark, metres.
KITTI_LENGTHS_M: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)

AlignMode = Literal["se3", "sim3", "none"]


# --------------------------------------------------------------------------------------------
# Validation helpers
# --------------------------------------------------------------------------------------------


def _poses(poses: np.ndarray, name: str) -> np.ndarray:
    """Return ``poses`` as a finite (N,4,4) float64 stack with bottom rows [0 0 0 1] or raise."""
    arr = np.asarray(poses)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4) or arr.shape[0] == 0:
        raise InvalidCloudError(f"{name}: poses must be (N,4,4) with N > 0, got shape {arr.shape}")
    arr = arr.astype(np.float64, copy=False)
    if not np.all(np.isfinite(arr)):
        raise InvalidCloudError(f"{name}: poses contain non-finite values")
    bad = ~np.all(np.abs(arr[:, 3, :] - [0.0, 0.0, 0.0, 1.0]) <= 1e-9, axis=1)
    if bad.any():
        raise InvalidCloudError(
            f"{name}: pose {int(np.argmax(bad))} has bottom row {arr[int(np.argmax(bad)), 3].tolist()}, "
            "expected [0, 0, 0, 1]"
        )
    return arr


def _pose_pair(reference: np.ndarray, estimate: np.ndarray, min_poses: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate two pose stacks of equal length >= ``min_poses``."""
    Q = _poses(reference, "reference")
    P = _poses(estimate, "estimate")
    if Q.shape[0] != P.shape[0]:
        raise InvalidCloudError(
            f"reference has {Q.shape[0]} poses but estimate has {P.shape[0]}; "
            "associate them by timestamp first"
        )
    if Q.shape[0] < min_poses:
        raise InvalidCloudError(f"need at least {min_poses} poses, got {Q.shape[0]}")
    return Q, P


# --------------------------------------------------------------------------------------------
# Trajectory metrics
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ErrorStats:
    """Summary of a vector of non-negative errors ``e`` (units of the errors).

    ``rmse = sqrt(mean(e^2))``; ``mean``, ``median``, ``max``; ``n = len(e)``.
    """

    rmse: float
    mean: float
    median: float
    max: float
    n: int

    @classmethod
    def from_errors(cls, errors: np.ndarray) -> ErrorStats:
        """Summarize (M,) errors, M >= 1."""
        e = np.asarray(errors, dtype=np.float64)
        return cls(
            rmse=float(np.sqrt(np.mean(e * e))),
            mean=float(e.mean()),
            median=float(np.median(e)),
            max=float(e.max()),
            n=int(e.size),
        )

    def as_dict(self) -> dict[str, float | int]:
        """JSON-ready dict."""
        return {"rmse": self.rmse, "mean": self.mean, "median": self.median, "max": self.max, "n": self.n}


@dataclass(frozen=True)
class AteResult:
    """Result of :func:`ate`.

    Attributes
    ----------
    translation_m : statistics of the per-pose position errors, metres.
    align : the alignment used (``"se3"``, ``"sim3"`` or ``"none"``).
    T_reference_estimate : (4,4) the alignment ``[[c R, t], [0, 1]]`` applied to the estimate.
    scale : ``c`` (1 unless ``align == "sim3"``).
    """

    translation_m: ErrorStats
    align: str
    T_reference_estimate: np.ndarray
    scale: float

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return {
            "align": self.align,
            "translation_m": self.translation_m.as_dict(),
            "scale": self.scale,
            "T_reference_estimate": self.T_reference_estimate.tolist(),
        }


def ate(reference: np.ndarray, estimate: np.ndarray, *, align: AlignMode = "se3") -> AteResult:
    """Absolute trajectory error of positions after aligning the estimate to the reference.

    With reference positions ``q_i`` and estimate positions ``p_i`` (translation columns):

    .. math::  e_i = | q_i - (c R p_i + t) |

    where ``(c, R, t)`` minimises ``sum_i e_i^2``: ``"se3"`` a rigid fit (``c = 1``, Kabsch,
    :func:`randt.core.transforms.umeyama`), ``"sim3"`` a similarity (the same with scale, for monocular
    or scale-drifting estimates), ``"none"`` the identity. This is evo's ``APE`` with
    ``PoseRelation.translation_part`` after ``align(correct_scale=...)``.

    Parameters
    ----------
    reference, estimate : (N,4,4) float64 world<-sensor poses, row-aligned (N >= 3 to align).
    align : ``"se3"`` (default), ``"sim3"`` or ``"none"``.

    Returns
    -------
    AteResult
        ``translation_m`` holds RMSE / mean / median / max of ``e_i`` in metres.
    """
    if align not in ("se3", "sim3", "none"):
        raise ValueError(f"align must be 'se3', 'sim3' or 'none', got {align!r}")
    Q, P = _pose_pair(reference, estimate, 1 if align == "none" else 3)
    q = Q[:, :3, 3]
    p = P[:, :3, 3]
    if align == "se3":
        T, scale = umeyama(p, q)
    elif align == "sim3":
        T, scale = umeyama(p, q, with_scale=True)
    else:
        T, scale = np.eye(4), 1.0
    errors = np.linalg.norm(q - transform_points(T, p), axis=1)
    stats = ErrorStats.from_errors(errors)
    logger.debug("ATE (%s, scale %.6f): rmse %.4f m over %d poses", align, scale, stats.rmse, stats.n)
    return AteResult(translation_m=stats, align=align, T_reference_estimate=T, scale=scale)


@dataclass(frozen=True)
class RpeResult:
    """Result of :func:`rpe`.

    Attributes
    ----------
    delta : frame gap of the pairs.
    translation_m : statistics of ``|t(E_i)|``, metres.
    rotation_deg : statistics of ``angle(R(E_i))``, degrees.
    """

    delta: int
    translation_m: ErrorStats
    rotation_deg: ErrorStats

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return {
            "delta": self.delta,
            "translation_m": self.translation_m.as_dict(),
            "rotation_deg": self.rotation_deg.as_dict(),
        }


def rpe(reference: np.ndarray, estimate: np.ndarray, *, delta: int = 1, all_pairs: bool = False) -> RpeResult:
    """Relative pose error over a gap of ``delta`` frames (evo's RPE definition).

    For each pair ``(i, j = i + delta)``, with reference ``Q`` and estimate ``P``:

    .. math::

        E_i = \\big(Q_i^{-1} Q_j\\big)^{-1} \\big(P_i^{-1} P_j\\big), \\quad
        e^t_i = |t(E_i)| \\;[\\mathrm{m}], \\quad
        e^r_i = \\angle R(E_i) \\;[\\mathrm{deg}]

    and the RMSE (plus mean, median, max) of each. As evo with ``all_pairs=False``, the pairs are
    consecutive and non-overlapping, ``i = 0, delta, 2 delta, ...`` while ``j < N``;
    ``all_pairs=True`` uses every ``i`` with ``i + delta < N``. No alignment is needed (the error
    is invariant to a rigid transform of either trajectory).

    Parameters
    ----------
    reference, estimate : (N,4,4) float64 world<-sensor poses, row-aligned, N > delta.
    delta : frame gap, >= 1.
    all_pairs : overlapping pairs instead of consecutive ones.

    Returns
    -------
    RpeResult
        ``translation_m.rmse`` (m) and ``rotation_deg.rmse`` (deg) are the usual headline values.
    """
    if int(delta) != delta or delta < 1:
        raise ValueError(f"delta must be an integer >= 1, got {delta}")
    delta = int(delta)
    Q, P = _pose_pair(reference, estimate, delta + 1)
    n = Q.shape[0]
    i = np.arange(n - delta) if all_pairs else np.arange(0, n - delta, delta)
    j = i + delta
    rel_q = invert(Q[i]) @ Q[j]
    rel_p = invert(P[i]) @ P[j]
    E = invert(rel_q) @ rel_p
    t_err = np.linalg.norm(E[:, :3, 3], axis=1)
    r_err = np.degrees(Rotation.from_matrix(E[:, :3, :3]).magnitude())
    result = RpeResult(
        delta=delta,
        translation_m=ErrorStats.from_errors(t_err),
        rotation_deg=ErrorStats.from_errors(r_err),
    )
    logger.debug(
        "RPE (delta %d, %d pairs): %.4f m, %.4f deg RMSE",
        delta,
        i.size,
        result.translation_m.rmse,
        result.rotation_deg.rmse,
    )
    return result


@dataclass(frozen=True)
class KittiLengthError:
    """KITTI errors of the segments of one nominal length (NaN values when ``n_segments == 0``)."""

    length_m: float
    translation_pct: float
    rotation_deg_per_100m: float
    n_segments: int

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict (NaN becomes ``None``)."""
        return {
            "length_m": self.length_m,
            "translation_pct": json_float(self.translation_pct),
            "rotation_deg_per_100m": json_float(self.rotation_deg_per_100m),
            "n_segments": self.n_segments,
        }


@dataclass(frozen=True)
class KittiResult:
    """Result of :func:`kitti_relative_errors`.

    Attributes
    ----------
    translation_pct : mean over all segments of ``t_err``, in percent.
    rotation_deg_per_100m : mean over all segments of ``r_err``, in degrees per 100 m.
    per_length : one :class:`KittiLengthError` per requested length, in the given order.
    segment_first, segment_last : (S,) int64 first and last frame of each segment.
    segment_length_m : (S,) float64 nominal length of each segment.
    segment_t_err : (S,) float64 translation error per metre (m/m, the devkit's unit).
    segment_r_err : (S,) float64 rotation error per metre (rad/m, the devkit's unit).
    """

    translation_pct: float
    rotation_deg_per_100m: float
    per_length: tuple[KittiLengthError, ...]
    segment_first: np.ndarray
    segment_last: np.ndarray
    segment_length_m: np.ndarray
    segment_t_err: np.ndarray
    segment_r_err: np.ndarray

    @property
    def n_segments(self) -> int:
        """Number of segments averaged."""
        return int(self.segment_first.size)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the per-segment arrays are left out)."""
        return {
            "translation_pct": self.translation_pct,
            "rotation_deg_per_100m": self.rotation_deg_per_100m,
            "n_segments": self.n_segments,
            "per_length": [entry.as_dict() for entry in self.per_length],
        }


def _path_distances(poses: np.ndarray) -> np.ndarray:
    """(N,) cumulative travelled distance along the positions, ``dist[0] = 0``, metres."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def _kitti_rotation_error(pose_error: np.ndarray) -> np.ndarray:
    """(S,) devkit rotation angle, rad: ``acos(clip((trace(R) - 1) / 2, -1, 1))``."""
    trace = np.trace(pose_error[:, :3, :3], axis1=1, axis2=2)
    angle: np.ndarray = np.arccos(np.clip(0.5 * (trace - 1.0), -1.0, 1.0))
    return angle


def kitti_relative_errors(
    reference: np.ndarray,
    estimate: np.ndarray,
    *,
    lengths: Sequence[float] = KITTI_LENGTHS_M,
    step: int = 10,
) -> KittiResult:
    """Translation (%) and rotation (deg/100 m) drift of the KITTI odometry devkit.

    Follows ``calcSequenceErrors`` of the devkit's ``evaluate_odometry.cpp``:

    1. ``dist[k]`` = cumulative path length of the REFERENCE positions up to frame ``k``.
    2. For every ``first`` in ``0, step, 2 step, ...`` and every length ``L``, ``last`` is the
       first frame with ``dist[last] > dist[first] + L``; no such frame, no segment.
    3. With ``G`` = reference and ``E`` = estimate (general 4x4 inverses, as the devkit's
       ``Matrix::inv``)::

           delta_gt   = inv(G[first]) @ G[last]
           delta_est  = inv(E[first]) @ E[last]
           pose_error = inv(delta_est) @ delta_gt
           t_err = |t(pose_error)| / L                                    (m/m)
           r_err = acos(clip((trace(R(pose_error)) - 1) / 2, -1, 1)) / L   (rad/m)

    4. The sequence errors are the plain means of ``t_err`` and ``r_err`` over all segments
       (every length pooled), reported as ``100 * mean(t_err)`` percent and
       ``mean(r_err) * 180/pi * 100`` degrees per 100 m; ``per_length`` gives the same means
       over the segments of each length.

    The devkit computes in float32; this computes in float64, so values agree to float32
    precision and a segment end could differ only where ``dist`` ties ``dist[first] + L``
    within float32 rounding.

    Parameters
    ----------
    reference, estimate : (N,4,4) float64 world<-sensor poses, row-aligned (KITTI frames are
        10 Hz, so ``step = 10`` starts a segment every second).
    lengths : segment lengths, metres (> 0); default 100, 200, ..., 800.
    step : frame stride between segment starts, >= 1.

    Returns
    -------
    KittiResult

    Raises
    ------
    InvalidCloudError
        Bad pose stacks, or a reference path not longer than the shortest segment length
        (no segment at all).
    ValueError
        Empty or non-positive ``lengths``, or ``step < 1``.
    """
    lengths_arr = np.asarray(lengths, dtype=np.float64).reshape(-1)
    if lengths_arr.size == 0 or not np.all(np.isfinite(lengths_arr)) or np.any(lengths_arr <= 0.0):
        raise ValueError(f"lengths must be a non-empty sequence of positive metres, got {list(lengths)}")
    if int(step) != step or step < 1:
        raise ValueError(f"step must be an integer >= 1, got {step}")
    G, E = _pose_pair(reference, estimate, 2)
    n = G.shape[0]
    dist = _path_distances(G)
    shortest = float(lengths_arr.min())
    if not dist[-1] > shortest:
        raise InvalidCloudError(
            f"reference path is {dist[-1]:.2f} m long; KITTI errors need a path longer than the "
            f"shortest segment length ({shortest:g} m)"
        )

    firsts = np.arange(0, n, int(step))
    seg_first, seg_last, seg_len = [], [], []
    for length in lengths_arr:  # a handful of lengths; frames are vectorized
        last = np.searchsorted(dist, dist[firsts] + length, side="right")
        ok = last < n
        seg_first.append(firsts[ok])
        seg_last.append(last[ok])
        seg_len.append(np.full(int(ok.sum()), length))
    first_idx = np.concatenate(seg_first).astype(np.int64)
    last_idx = np.concatenate(seg_last).astype(np.int64)
    seg_length = np.concatenate(seg_len)

    delta_gt = np.linalg.inv(G[first_idx]) @ G[last_idx]
    delta_est = np.linalg.inv(E[first_idx]) @ E[last_idx]
    pose_error = np.linalg.inv(delta_est) @ delta_gt
    t_err = np.linalg.norm(pose_error[:, :3, 3], axis=1) / seg_length
    r_err = _kitti_rotation_error(pose_error) / seg_length

    to_deg_per_100m = 180.0 / math.pi * 100.0  # rad/m -> deg/100 m
    per_length = []
    for length in lengths_arr:
        sel = seg_length == length
        count = int(sel.sum())
        t_pct = float(100.0 * t_err[sel].mean()) if count else math.nan
        r_deg = float(r_err[sel].mean() * to_deg_per_100m) if count else math.nan
        per_length.append(
            KittiLengthError(
                length_m=float(length), translation_pct=t_pct, rotation_deg_per_100m=r_deg, n_segments=count
            )
        )
    result = KittiResult(
        translation_pct=float(100.0 * t_err.mean()),
        rotation_deg_per_100m=float(r_err.mean() * to_deg_per_100m),
        per_length=tuple(per_length),
        segment_first=first_idx,
        segment_last=last_idx,
        segment_length_m=seg_length,
        segment_t_err=t_err,
        segment_r_err=r_err,
    )
    logger.debug(
        "KITTI errors over %d segments: %.4f %%, %.4f deg/100 m",
        result.n_segments,
        result.translation_pct,
        result.rotation_deg_per_100m,
    )
    return result


def evaluate_trajectory(reference: np.ndarray, estimate: np.ndarray) -> dict[str, Any]:
    """ATE (SE(3)-aligned), RPE (delta 1 frame) and, if the path allows, the KITTI errors.

    Parameters
    ----------
    reference, estimate : (N,4,4) float64 world<-sensor poses, row-aligned, N >= 3.

    Returns
    -------
    dict
        JSON-ready (plain floats, ints, lists, ``None``)::

            {"n_poses": int, "path_length_m": float,
             "ate": AteResult.as_dict(), "rpe": RpeResult.as_dict(),
             "kitti": KittiResult.as_dict() or None, "notes": [str, ...]}

        ``kitti`` is ``None`` (with a note) when the reference path is not longer than 100 m.
    """
    Q, P = _pose_pair(reference, estimate, 3)
    path_length = float(_path_distances(Q)[-1])
    notes: list[str] = []
    kitti: dict[str, Any] | None = None
    if path_length > KITTI_LENGTHS_M[0]:
        kitti = kitti_relative_errors(Q, P).as_dict()
    else:
        notes.append(
            f"KITTI errors skipped: the reference path is {path_length:.2f} m, not longer than the "
            f"shortest segment ({KITTI_LENGTHS_M[0]:g} m)"
        )
    return {
        "n_poses": int(Q.shape[0]),
        "path_length_m": path_length,
        "ate": ate(Q, P, align="se3").as_dict(),
        "rpe": rpe(Q, P, delta=1).as_dict(),
        "kitti": kitti,
        "notes": notes,
    }
