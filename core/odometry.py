"""The paper's Algorithm 2: incremental scan-to-keyframe-model matching with density equalization.

One :class:`IncrementalMatcher` per driving session, fed one sweep at a time
(:meth:`IncrementalMatcher.register_scan`)::

    sanitize   -> finite points in range (counted)
    predict    -> constant acceleration from the last two velocities (the prior for the first sweep)
    deskew     -> with per-point times: each point moved to the pose at the sweep's middle
    features   -> density-based split (randt.core.features): noise out, ground, objects
    get model  -> the fused keyframe model (the paper's Get)
    match      -> randt.core.registration.register(features, model, T_pred)
    guard      -> a failed or implausible match falls back to the prediction, flagged, never accepted
    relocalize -> a lost session: Scan Context (randt.core.place), then global registration
    set model  -> a new keyframe when the sensor moved or turned enough (the paper's Set)

Poses are ``T_world_sensor`` (4x4), the world being the first sweep's sensor frame unless a prior
pose places the session in a map frame; a deskewed sweep's pose is the sensor's at stamp +
period / 2. Each step and why: docs/mapping.md, "Algorithm 2, as implemented".
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace
from typing import Literal, NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from randt.core.config import RegistrationSettings
from randt.core.errors import InvalidCloudError, NotRelocalizedError, RandtError
from randt.core.features import Features, extract_features
from randt.core.global_registration import GlobalSettings, register_global
from randt.core.kernels import deskew_points
from randt.core.model import KeyframeModel
from randt.core.ndt import ndt_constants, ndt_cost
from randt.core.place import query_descriptors, scan_context, scan_context_distance
from randt.core.registration import (
    PreparedReference,
    ReferencePiece,
    RegistrationResult,
    auto_voxel_sizes,
    inlier_ratio,
    join_reference,
    prepare_reference,
    reference_piece,
    register,
    sanitize_points,
)
from randt.core.sweep_motion import pose_and_motion_on_map
from randt.core.transforms import (
    as_transform,
    invert,
    make_transform,
    orthonormalize,
    rotation_angle_deg,
    scale_motion,
    se3_log,
    so3_exp,
    so3_log,
    transform_points,
    yawed,
)
from randt.core.voxel import voxel_downsample

__all__ = [
    "MATCHER_REGISTRATION",
    "IncrementalMatcher",
    "MapPreparation",
    "MatcherSettings",
    "MatcherState",
    "PosePrior",
    "ScanResult",
    "extend_state_dict",
    "on_map_stride",
    "with_keyframe",
]

log = logging.getLogger(__name__)


#: With per-point times, sweeps are deskewed to their middle and poses refer to it. Deskewing to
#: the start lets an error in the velocity warp the sweep one-sidedly, which biases the next
#: velocity the same way; the symmetric mid-sweep warp stays bounded (KISS-ICP deskews the same
#: way; docs/mapping.md, step 4).
MID_SWEEP = 0.5

#: A gated match: (hypothesis index, result, the deskewed sweep, its features, the initial guess).
_Match = tuple[int, RegistrationResult, np.ndarray, Features, np.ndarray]


class _Gating(NamedTuple):
    """What a match of this sweep is gated against (:meth:`IncrementalMatcher._gate`'s arguments)."""

    T_pred: np.ndarray
    prior_pose: np.ndarray | None
    prior: PosePrior | None
    periods: float


#: Adaptive levels (``MatcherSettings.adaptive_levels``): a constant-velocity prediction on a
#: vehicle is off by centimetres, which the coarse NDT levels (up to 16 finest voxels) are there
#: to absorb from metres. A match from the prediction runs only the levels no coarser than
#: LEVEL_MARGIN times the largest correction of the last RECENT_CORRECTIONS matches (and at least
#: the two finest), once MIN_CORRECTIONS are known (the second sweep's, whose prediction knew no
#: velocity, is not one); a rotation counts as the displacement it gives a point
#: CORRECTION_REACH_M away (docs/mapping.md, step 6, "Adaptive levels").
LEVEL_MARGIN = 8.0
RECENT_CORRECTIONS = 5
MIN_CORRECTIONS = 3
#: A session's first match that moves the first pose by less than this (m) tries every yaw
#: hypothesis too (:meth:`IncrementalMatcher._try_hypotheses`): it may have stuck where it started.
FIRST_MATCH_STAYED_M = 0.25
CORRECTION_REACH_M = 30.0

#: ``ScanResult.message`` of a match found by relocalization (one global registration: the
#: service answers it only once a second match agrees with it, service/sessions.py).
RELOCALIZED = "relocalized"

#: After this many fallbacks in a row a session counts as lost: only its prediction is matched.
LOST_AFTER_FALLBACKS = 3

#: A lost session tries to relocalize (global registration against its model, no prediction) on
#: its LOST_AFTER_FALLBACKS-th fallback and then on every RELOCALIZE_EVERY-th: one costs several
#: sweeps' matching, so it is not tried on every sweep of a long blockage.
RELOCALIZE_EVERY = 5
#: Keyframes (the nearest by Scan Context) a relocalization tries, and the range of the points
#: its global registration uses.
RELOCALIZE_CANDIDATES = 2
RELOCALIZE_RANGE_M = 60.0

#: Keyframes that may wait for the model (``defer_model``) while a sweep is matched: one.
MAX_PENDING_KEYFRAMES = 1

#: A sweep whose stamp follows the last one's by one period within this fraction of a period is
#: the next sweep (no gap): only then is the velocity's change carried on
#: (:meth:`IncrementalMatcher._velocity`).
ONE_PERIOD_TOLERANCE = 0.25

#: A match's object points are judged on their own (``IncrementalMatcher._objects_refusal``) when
#: the sweep has at least MIN_OBJECT_POINTS, on every k-th of them up to OBJECT_CHECK_POINTS (a
#: ratio's standard error about 1 %, at a fraction of a match's cost).
MIN_OBJECT_POINTS = 100
OBJECT_CHECK_POINTS = 2000

#: A session's first sweep with a prior is matched to its map's points around the prior
#: (``register_scan``'s ``map_seed``) when there are at least this many.
MAP_SEED_MIN_POINTS = 2000
#: Sweep points matched against the map when localizing on it (a stratified subsample): the map
#: is fixed, so 1,500 (as Autoware's random_downsample_filter) drive Newton as well as all
#: (docs/mapping.md, "Localizing on the map").
ON_MAP_MATCH_POINTS = 1500
#: Of a sweep localized on the map, every k-th point is taken (features, match, the points it
#: returns for the map): the map already holds its surroundings. k is the smallest of
#: ON_MAP_STRIDES leaving at most ON_MAP_SWEEP_POINTS (:func:`on_map_stride`): primes, so a sweep
#: stored column by column keeps points of every ring of a 16- to 128-ring sensor; about 2,500 feed
#: the 1,500 matched (docs/mapping.md, "In the service", gives what it saves).
ON_MAP_SWEEP_POINTS = 2500
ON_MAP_STRIDES = (1, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37, 41, 43, 47, 53, 59, 61, 67, 71, 73, 79)
#: The message of a first sweep placed by its match to the map, not at its prior.
MATCHED_TO_MAP = "matched to the map from the prior"
#: A first sweep matched on its map is deskewed with the motion during it (forward and sideways
#: metres and yaw degrees a period) found with its pose in one Newton solve
#: (:func:`randt.core.sweep_motion.pose_and_motion_on_map`) on this many of its points, on the
#: map's two finest levels in turn (the coarser one's basin is wider), then matched again
#: (``IncrementalMatcher._first_deskewed_on_map``). The motion's steps in an iteration are at most
#: FIRST_MOTION_STEPS at the finest level (the coarser level's scaled by its voxel), converged
#: below FIRST_MOTION_EPS.
FIRST_MOTION_POINTS = 400
FIRST_MOTION_STEPS = (0.25, 0.25, 2.0)
FIRST_MOTION_EPS = (0.002, 0.002, 0.02)
FIRST_MOTION_ITERATIONS = 20
#: A first sweep whose match from its prior does not pass is matched again from the prior turned
#: by each of these (degrees), then with all its points (``IncrementalMatcher._first_candidates``).
FIRST_RETRY_YAW_DEG = (-5.0, 5.0, -10.0, 10.0)

#: Turns (degrees over the whole gap) scored when a gap's predicted match fails, and how many
#: of the best are matched (``IncrementalMatcher._hypotheses``).
GAP_TURN_DEG = tuple(float(d) for d in range(-100, 101, 5))
GAP_TURN_CANDIDATES = 3

#: A sweep with point times is deskewed again when its matched motion differs from the one it was
#: deskewed with by more than this (degrees over one sweep period, metres over one period), and
#: matched again on the two finest levels: the pose follows the deskew closely, and at a corner's
#: exit the motion found differs from the prediction by more than coarser thresholds would catch
#: (docs/mapping.md, step 4).
REDESKEW_DEG = 0.05
REDESKEW_M = 0.01
#: The same on the map: a localized pose is absolute, so the motion between two of them carries
#: both poses' centimetre of error, and below these the motion found is no better than the one
#: used (docs/mapping.md, "In the service").
REDESKEW_ON_MAP_DEG = 0.2
REDESKEW_ON_MAP_M = 0.04
#: The second sweep is matched again with the first keyframe deskewed anew until its velocity
#: changes by less than this (``IncrementalMatcher._second_sweep_again``), at most
#: ``SECOND_SWEEP_PASSES`` times. Finer than the redeskew's: it happens once a session, and a
#: warp left in the first keyframe turns every later pose.
SECOND_SWEEP_DEG = 0.002
SECOND_SWEEP_M = 0.001
SECOND_SWEEP_PASSES = 3


#: The registration settings a matcher uses unless given others (voxel sizes from the first sweep).
#: The density-based feature extraction already removes the sweep's noise, and features are too
#: sparse for Algorithm 1's own-voxel Gaussians: the moving-point selection is off here. Algorithm 3
#: (the SVD step) is off too: it measured worse in the matcher (docs/mapping.md, step 6). Pass
#: ``registration=RegistrationSettings(...)`` to turn it back on. Newton stops on the finest
#: level at a coarser step than pairwise registration's: from a good prediction the finer stop
#: only costs evaluations. Each point is scored against the 8 voxels whose centres enclose it,
#: weighted trilinearly (``n_neighbors=8``, :func:`randt.core.voxel.neighborhood_base`,
#: :func:`randt.core.voxel.trilinear_weights`), not its own and the 6 across its faces: the cost is
#: then continuous and symmetric about every cell boundary, and a flat ground on a voxel boundary
#: cannot drift (docs/registration.md, "NDT").
MATCHER_REGISTRATION = RegistrationSettings(
    select_moving_points=False,
    svd_refinement=False,
    translation_eps_m=5e-4,
    rotation_eps_rad=5e-5,
    n_neighbors=8,
)


class MatcherSettings(BaseModel):
    """Settings of the incremental matcher (Algorithm 2)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    voxel_sizes_m: tuple[float, ...] | None = Field(
        default=None,
        description="NDT levels against the keyframe model, coarse to fine; None: (16r, 8r, 4r, 2r, r) "
        "with r from the first sweep's scale (randt.core.registration.auto_voxel_sizes), 1 m for a KITTI "
        "sweep",
    )
    feature_voxel_m: float | None = Field(default=None, gt=0, description="object downsampling; None: r/2")
    ground_voxel_factor: float = Field(
        default=1.0,
        ge=1,
        description="ground is downsampled this many times coarser than objects (randt.core.features); 1 "
        "(as dense as objects) keeps pitch and height from drifting on long drives (docs/mapping.md, "
        "step 5; docs/benchmarks.md)",
    )
    keyframe_distance_m: float = Field(default=2.0, gt=0, description="new keyframe after this travel")
    keyframe_rotation_deg: float = Field(default=10.0, gt=0, description="or after this rotation")
    max_keyframes: int = Field(default=40, ge=1, description="keyframes fused into the model")
    model_radius_m: float = Field(default=80.0, gt=0, description="model points kept around the sensor")
    model_voxel_m: float | None = Field(
        default=None, gt=0, description="density equalization of the model; None: r/4"
    )
    max_range_m: float = Field(default=100.0, gt=0, description="points farther are ignored")
    min_range_m: float = Field(default=2.0, ge=0, description="points nearer are ignored (the vehicle)")
    min_inlier_ratio: float = Field(
        default=0.3, ge=0, le=1, description="a match with fewer inliers (chi2 gate) is a failed match"
    )
    on_map_min_inlier_ratio: float = Field(
        default=0.6,
        ge=0,
        le=1,
        description="the same for a sweep matched on the map (localizing): the right match on a fixed "
        "map keeps nearly all its points, a wrong one far fewer (docs/mapping.md)",
    )
    min_object_inlier_ratio: float = Field(
        default=0.1,
        ge=0,
        le=1,
        description="a match whose object points (not ground) keep fewer inliers is a failed match: "
        "on a flat street the ground matches at any offset along it",
    )
    on_map_min_object_inlier_ratio: float = Field(
        default=0.5,
        ge=0,
        le=1,
        description="the same for a sweep matched on the map: the right match keeps most of its "
        "object points, one turned off keeps the ground and few of them (docs/mapping.md)",
    )
    max_correction_m: float = Field(
        default=2.0,
        gt=0,
        description="a match moving the prediction farther than this (per sweep period since the last "
        "sweep, with stamps) is rejected",
    )
    max_tracking_correction_m: float = Field(
        default=0.5,
        gt=0,
        description="while tracking (the last sweep matched from a prediction with a measured "
        "velocity): a match moving the prediction farther than this plus what max_acceleration_mps2 "
        "allows over the time since the last sweep is rejected (tighter than max_correction_m)",
    )
    max_acceleration_mps2: float = Field(
        default=10.0,
        gt=0,
        description="the largest acceleration (braking, cornering; about 1 g for a car) the tracking "
        "correction limit allows for: half of it times the squared time since the last sweep",
    )
    retry_yaw_deg: tuple[float, ...] = Field(
        default=(5.0, 10.0), description="yaw hypotheses (both ways) tried when the predicted match fails"
    )
    adaptive_levels: bool = Field(
        default=True,
        description="from the prediction, skip the NDT levels coarser than LEVEL_MARGIN times the "
        "largest of the session's recent prediction corrections (every level after a gap, a "
        "fallback or a restart, and for the retried hypotheses)",
    )
    acceleration_gain: float = Field(
        default=1.0,
        ge=0,
        le=1,
        description="how much of the change in velocity between the last two matched sweeps the "
        "motion prediction (and the first deskew) carries on: 1 = constant acceleration (a corner's "
        "growing yaw rate, braking), 0 = constant velocity: fewer sweeps need a second deskew "
        "(docs/mapping.md, step 3)",
    )
    max_angular_acceleration_dps2: float = Field(
        default=100.0,
        gt=0,
        description="the largest change of turn rate the prediction carries on (degrees/s^2; with "
        "max_acceleration_mps2 for the speed): a car entering a corner at 3 m/s^2 lateral reaches "
        "about 50; a larger change (a jump no vehicle makes, a bad match) is carried on only this far",
    )
    redeskew: bool = Field(
        default=True,
        description="with point times: deskew per yaw hypothesis, and again with the matched velocity",
    )
    max_gap_s: float = Field(
        default=5.0,
        gt=0,
        description="with stamps: the motion prediction extrapolates the velocity over the time since "
        "the last sweep (scans dropped upstream), at most this long",
    )
    prior_gate_chi2: float = Field(
        default=16.27, gt=0, description="Mahalanobis^2 gate (chi2 3 dof 99.9 %) against a prior pose"
    )
    prior_drift_fraction: float = Field(
        default=0.02,
        ge=0,
        description="the prior gate's allowance for the session's drift from its priors: this "
        "fraction of the path driven since the last sweep that agreed with its prior (1 sigma)",
    )
    relocalize: bool = Field(
        default=True,
        description="a lost session (without a prior) tries global registration of its sweep against "
        "its model, with no prediction (RELOCALIZE_EVERY)",
    )


@dataclass(frozen=True)
class PosePrior:
    """An external pose (GNSS/INS): ``T_world_sensor`` and its 6x6 covariance (t then r)."""

    T_world_sensor: np.ndarray
    covariance: np.ndarray


@dataclass(frozen=True)
class ScanResult:
    """What the matcher concluded for one sweep.

    ``deskewed_xyz`` holds the sweep's points worth mapping (in range, not noise, deskewed, sensor
    frame) and ``map_index`` their row in the input, so per-point attributes such as intensity can
    follow them into the map.

    ``status`` is ``"first"`` (the first sweep, placed at the identity or its prior, or matched
    on the map: ``localized``), ``"ok"`` (a match was accepted) or ``"fallback"`` (the match failed
    or was rejected; ``T_world_sensor`` is the motion prediction or the prior and ``message`` says
    why).
    """

    index: int
    T_world_sensor: np.ndarray
    status: Literal["first", "ok", "fallback"]
    converged: bool
    fitness: float
    inlier_ratio: float
    is_keyframe: bool
    time_s: float
    covariance: np.ndarray
    deskewed_xyz: np.ndarray
    map_index: np.ndarray
    n_points: int
    n_nonfinite_dropped: int
    message: str = ""
    stage_times_s: dict[str, float] = field(default_factory=dict)
    #: matched on the map (``register_scan``'s ``on_map``), not on the session's keyframes
    localized: bool = False
    #: ``deskewed_xyz`` is deskewed by a known motion; False for a first sweep with point times,
    #: matched before any motion is known: its points carry the sweep's own motion (a metre at
    #: 10 m/s and 10 Hz), so a map or a pose graph keeps none of them (docs/mapping.md)
    deskewed: bool = True


def _same(a: object, b: object) -> bool:
    """Equality through arrays, tuples, lists and deques (``np.array_equal`` on arrays)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and np.array_equal(a, b)
    if isinstance(a, (tuple, list, deque)) and isinstance(b, (tuple, list, deque)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


@dataclass(eq=False)
class MatcherState:
    """Everything one sweep may change: the whole of what :meth:`IncrementalMatcher.register_scan`
    snapshots before a sweep and puts back if the sweep raises (all or nothing).

    Attributes
    ----------
    poses : ``T_world_sensor`` (4,4) of every sweep so far.
    delta : (4,4) the sensor's motion over one sweep period (the velocity), from the last two poses.
    delta_measured : ``delta`` was measured between two matched sweeps one period apart.
    prev_delta : the velocity before ``delta`` when both were so measured (for the acceleration,
        :meth:`IncrementalMatcher._velocity`); None after a fallback or a gap.
    keyframes : (pose, model points in the world frame) fused into the model, the newest last.
    model : the fused, density-equalized keyframe model prepared for matching (None before the first).
    store : the incremental keyframe model the matching model is prepared from
        (:class:`randt.core.model.KeyframeModel`, immutable: replaced, never changed in place).
    last_keyframe_pose : where the last keyframe (pending ones included) was taken.
    recent_inliers : inlier ratios of the last accepted matches (the weak-match test).
    recent_corrections : how far (metres at :data:`CORRECTION_REACH_M`) the last matches from the
        prediction moved it, emptied by a fallback, the match after fallbacks, a retried
        hypothesis or a gap (the adaptive levels; while it holds one, the tighter tracking gate).
    first_raw : the first sweep and its point times, kept until the second gives a velocity.
    last_stamp_s : the previous sweep's stamp (None without stamps).
    pending : keyframes ``register_scan(defer_model=True)`` left for :meth:`~IncrementalMatcher.update_model`.
    fallback_run : consecutive fallbacks (from :data:`LOST_AFTER_FALLBACKS` on, no retries).
    travel_m : the path length of the poses so far (metres).
    prior_offset : the last accepted pose's position minus its prior's (the session's drift from
        its priors, ``None`` before a sweep with a prior), and ``prior_offset_travel_m``: the
        path length then (the prior gate, :meth:`IncrementalMatcher._agrees`).
    localized : the map the last sweep was localized on, while the session localizes (below).

    Arrays in it are replaced, never changed in place, so a snapshot copies only the containers.
    Two states are equal when every field is (arrays element by element, the model and the store
    by identity).
    """

    poses: list[np.ndarray]
    delta: np.ndarray
    keyframes: deque[tuple[np.ndarray, np.ndarray]]
    delta_measured: bool = False
    prev_delta: np.ndarray | None = None
    model: PreparedReference | None = None
    store: KeyframeModel | None = None
    last_keyframe_pose: np.ndarray | None = None
    recent_inliers: deque[float] = field(default_factory=lambda: deque(maxlen=20))
    recent_corrections: deque[float] = field(default_factory=lambda: deque(maxlen=RECENT_CORRECTIONS))
    first_raw: tuple[np.ndarray, np.ndarray] | None = None
    last_stamp_s: float | None = None
    pending: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    fallback_run: int = 0
    travel_m: float = 0.0
    prior_offset: np.ndarray | None = None
    prior_offset_travel_m: float = 0.0
    #: The map the last sweep was localized on, while the session localizes: the first sweep that
    #: maps again is matched on it, and the keyframe model starts again from that sweep.
    localized: PreparedReference | None = None

    @classmethod
    def empty(cls, max_keyframes: int) -> MatcherState:
        """The state of a session before its first sweep."""
        return cls(poses=[], delta=np.eye(4), keyframes=deque(maxlen=max_keyframes))

    def snapshot(self) -> MatcherState:
        """A copy that later changes to this state do not reach."""
        return replace(
            self,
            poses=list(self.poses),
            delta=self.delta.copy(),
            keyframes=deque(self.keyframes, maxlen=self.keyframes.maxlen),
            recent_inliers=deque(self.recent_inliers, maxlen=self.recent_inliers.maxlen),
            recent_corrections=deque(self.recent_corrections, maxlen=self.recent_corrections.maxlen),
            pending=list(self.pending),
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, MatcherState):
            return NotImplemented
        return (
            self.model is other.model
            and self.localized is other.localized
            and all(
                _same(getattr(self, f.name), getattr(other, f.name))
                for f in fields(self)
                if f.name not in ("model", "localized")
            )
        )

    __hash__ = None  # type: ignore[assignment]  # mutable


@dataclass(frozen=True)
class _Sweep:
    """A sweep's finite points within range (sensor frame), their point times and input rows."""

    xyz: np.ndarray
    time_offset_s: np.ndarray | None
    source_index: np.ndarray
    n_nonfinite_dropped: int


@dataclass(frozen=True)
class _Outcome:
    """What matching concluded: the pose, how it was reached, and the sweep it was matched with."""

    T: np.ndarray
    status: Literal["first", "ok", "fallback"]
    message: str
    converged: bool
    fitness: float
    covariance: np.ndarray
    inlier_ratio: float
    xyz: np.ndarray
    feats: Features


def deskew(
    points_xyz: np.ndarray,
    time_offset_s: np.ndarray,
    delta: np.ndarray,
    period_s: float,
    *,
    reference_fraction: float = 0.0,
) -> np.ndarray:
    """Move each point to the pose at ``reference_fraction`` of the sweep, at constant velocity.

    ``delta`` is the sensor motion over one ``period_s`` (``T_start_end``). A point measured at
    ``tau`` seconds after the start was seen from ``exp(s * log(delta))`` relative to the start,
    ``s = tau / period_s``, the screw motion (:func:`randt.core.transforms.scale_motion`: turning at
    constant speed, the sensor moves along an arc); it is re-expressed in the frame at ``s =
    reference_fraction`` (0: the sweep's start, 0.5: its middle). The translation is not scaled
    linearly (``s * delta[:3, 3]``, the chord of the whole period): the chord's direction is half
    the period's turn off the heading, which shears a sweep in a corner (docs/mapping.md, step 4).
    """
    s = np.clip(np.asarray(time_offset_s, dtype=np.float64) / period_s, 0.0, 1.5) - reference_fraction
    rotvec, screw = se3_log(delta)
    pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
    return deskew_points(pts, np.ascontiguousarray(s), rotvec, screw)


def deskew_reference(
    points_xyz: np.ndarray,
    time_offset_s: np.ndarray,
    delta: np.ndarray,
    period_s: float,
    *,
    reference_fraction: float = 0.0,
) -> np.ndarray:
    """:func:`deskew` point by point, each with its own :func:`randt.core.transforms.scale_motion` of
    ``delta`` (the reference of :func:`randt.core.kernels.deskew_points`; slow)."""
    s = np.clip(time_offset_s / period_s, 0.0, 1.5) - reference_fraction
    moved = [scale_motion(delta, float(k)) for k in s]
    return np.array([T[:3, :3] @ p + T[:3, 3] for T, p in zip(moved, points_xyz, strict=True)])


def on_map_stride(n_points: int) -> int:
    """The stride a sweep of ``n_points`` rows is taken at when localized on the map: the smallest
    of :data:`ON_MAP_STRIDES` leaving at most :data:`ON_MAP_SWEEP_POINTS` rows (the largest one
    beyond)."""
    for k in ON_MAP_STRIDES:
        if n_points <= k * ON_MAP_SWEEP_POINTS:
            return k
    return ON_MAP_STRIDES[-1]


def _planar_motion(motion: np.ndarray) -> np.ndarray:
    """The motion over one period ``(forward m, sideways m, yaw deg)`` as a 4x4 (``T_start_end``)."""
    a = np.radians(motion[2])
    M = np.eye(4)
    M[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    M[:2, 3] = motion[:2]
    return M


@dataclass(frozen=True)
class MapPreparation:
    """How a session prepares the map it localizes on (:meth:`IncrementalMatcher.map_preparation`):
    its tiles' points as they are (the map's tiles equalize their density already), their moments
    at the finest of ``levels``, and the window's pyramid joined from them."""

    registration: RegistrationSettings
    levels: tuple[float, ...]

    def piece(self, map_xyz: np.ndarray) -> ReferencePiece:
        """One tile's points (world frame) made ready to be joined."""
        return reference_piece(np.asarray(map_xyz), self.registration, self.levels, downsample=False)

    def join(self, pieces: list[ReferencePiece]) -> PreparedReference:
        """The window of these pieces (InvalidCloudError: none, at other levels, too sparse)."""
        if not pieces or any(p.voxel_sizes_m != self.levels for p in pieces):
            raise InvalidCloudError("the map's pieces were not prepared at this session's levels")
        return join_reference(pieces, self.registration)


class IncrementalMatcher:
    """Algorithm 2 for one session (module docstring). Feed sweeps in order with :meth:`register_scan`."""

    def __init__(
        self,
        settings: MatcherSettings | None = None,
        registration: RegistrationSettings | None = None,
        *,
        period_s: float = 0.1,
    ) -> None:
        self.settings = settings or MatcherSettings()
        self._registration_given = registration
        self.registration = registration or RegistrationSettings(select_moving_points=False)
        self.period_s = period_s
        self.feature_voxel_m = 0.0
        self.model_voxel_m = 0.0
        self._state = MatcherState.empty(self.settings.max_keyframes)
        self._on_map_now = False  # (this sweep is matched on the map: _matching_on)
        self._first_why = ""  # why the first sweep's match to the map was not taken

    @property
    def state(self) -> MatcherState:
        """The session's state (read it; :meth:`register_scan` and :meth:`load_state_dict` change it)."""
        return self._state

    @property
    def poses(self) -> list[np.ndarray]:
        """``T_world_sensor`` (4,4) of every sweep so far."""
        return self._state.poses

    def _resolve_scales(self, first_xyz: np.ndarray) -> None:
        """Fix the voxel sizes from the first sweep (or the settings) for the whole session."""
        s = self.settings
        levels = s.voxel_sizes_m
        if levels is None and self._registration_given is not None:
            levels = self._registration_given.voxel_sizes_m
        if levels is None:
            # One level coarser than pairwise registration uses: the yaw rate's jump at a corner's
            # onset is more than (8r, ..., r) recovers from, and a 16r level is cheap
            # (docs/mapping.md, step 2).
            auto = auto_voxel_sizes(first_xyz)
            levels = (2.0 * auto[0], *auto)
        r = levels[-1]
        self._apply_scales(tuple(levels), s.feature_voxel_m or r / 2, s.model_voxel_m or r / 4)

    def _apply_scales(self, levels: tuple[float, ...], feature_voxel_m: float, model_voxel_m: float) -> None:
        base = self._registration_given or MATCHER_REGISTRATION
        self.registration = base.model_copy(update={"voxel_sizes_m": tuple(levels)})
        self.feature_voxel_m = feature_voxel_m
        self.model_voxel_m = model_voxel_m

    # -- the paper's Get and Set of the keyframe model ------------------------------------------
    def get_model(self) -> PreparedReference | None:
        """The fused, density-equalized keyframe model (prepared for matching), if any."""
        self.update_model()
        return self._state.model

    def set_keyframe(self, T_world_sensor: np.ndarray, points_sensor: np.ndarray) -> None:
        """Add a keyframe to the fused model (bounded in count and radius; :mod:`randt.core.model`).

        All or nothing: if the model cannot be built, the keyframes and the model stay as they were.
        """
        self._add_keyframes([(T_world_sensor, points_sensor)])

    def _add_keyframes(self, keyframes: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """Add keyframes (pose, sensor points) to the incremental model, then prepare it once for
        matching; the state changes only when all of it succeeded."""
        store = self._state.store
        added = []
        for T, points in keyframes:
            world = voxel_downsample(transform_points(T, points), self.model_voxel_m)
            store = self._store_add(store, T, world)
            added.append((T.copy(), world))
        assert store is not None  # at least one keyframe was added
        model = self._prepare(store)
        self._state.keyframes.extend(added)
        self._state.store, self._state.model = store, model
        self._state.last_keyframe_pose = keyframes[-1][0].copy()

    def _store_add(self, store: KeyframeModel | None, T: np.ndarray, world: np.ndarray) -> KeyframeModel:
        """``store`` with the keyframe at ``T`` (its density-equalized world points ``world``)
        added: Algorithm 1 judges its points, the newest keyframe wins its voxels, the oldest
        leaves a full window and points beyond ``model_radius_m`` leave (:mod:`randt.core.model`)."""
        levels = self.registration.voxel_sizes_m
        assert levels, "voxel sizes are fixed by the first sweep"
        finest = levels[-1]
        if store is None:
            store = KeyframeModel.empty(self.model_voxel_m, finest)
        return store.add_keyframe(
            world,
            self.registration,
            center_xy=(float(T[0, 3]), float(T[1, 3])),
            radius_m=self.settings.model_radius_m,
            max_keyframes=self.settings.max_keyframes,
        )

    def _prepare(self, store: KeyframeModel) -> PreparedReference:
        """The matching model (NDT pyramid) of ``store``."""
        return store.reference(self.registration, self.registration.voxel_sizes_m or ())

    @property
    def model_pending(self) -> bool:
        """Keyframes wait for :meth:`update_model` (left by ``register_scan(defer_model=True)``)."""
        return bool(self._state.pending)

    def update_model(self) -> float:
        """Fold the keyframes ``register_scan(defer_model=True)`` left pending into the model
        (one rebuild however many); returns the seconds spent, 0 when none was pending.

        :meth:`get_model` and :meth:`state_dict` call it first. :meth:`register_scan` calls it
        first only when more than :data:`MAX_PENDING_KEYFRAMES` are pending: a caller that is
        behind (more sweeps waiting) can skip it and match the next sweep against the model
        without its newest keyframe (2-4 m behind the sensor, in a window of 40), rebuilding once
        for two keyframes. Keyframes the model cannot be built from (too sparse) are skipped with
        a warning: the previous model stays, and the next sweep is a keyframe candidate again.
        """
        pending, self._state.pending = self._state.pending, []
        if not pending:
            return 0.0
        t0 = time.perf_counter()
        try:
            self._add_keyframes(pending)
        except RandtError as exc:
            log.warning("keyframes not modelled, the previous model stays: %s", exc)
            self._state.last_keyframe_pose = (
                self._state.keyframes[-1][0].copy() if self._state.keyframes else None
            )
        return time.perf_counter() - t0

    def _rebuild_model(self) -> None:
        """The model replayed from the keyframes, oldest first (the same as it was built
        incrementally: keyframes that left the window or the radius left no trace)."""
        store = None
        for T, world in self._state.keyframes:
            store = self._store_add(store, T, world)
        assert store is not None
        model = self._prepare(store)
        self._state.store, self._state.model = store, model

    @property
    def model_size(self) -> int:
        """Points in the fused model (bounded by ``max_keyframes`` and ``model_radius_m``)."""
        return 0 if self._state.model is None else int(self._state.model.points_xyz.shape[0])

    # -- one sweep --------------------------------------------------------------------------------
    def register_scan(
        self,
        points_xyz: np.ndarray,
        *,
        time_offset_s: np.ndarray | None = None,
        prior: PosePrior | None = None,
        stamp_s: float | None = None,
        defer_model: bool = False,
        map_seed: np.ndarray | None = None,
        on_map: PreparedReference | None = None,
        relocalize: bool = False,
    ) -> ScanResult:
        """Register one sweep (sensor frame) and return its :class:`ScanResult`.

        ``on_map``: the map around the vehicle (:meth:`prepare_map`): the sweep is matched against
        it instead of the session's keyframes (localizing on the map: no keyframe, no model
        update; ``ScanResult.localized``). The prediction, the gates and the hypotheses are the
        same. A session that maps again after localizing matches that sweep on the map it was
        localized on last and starts its keyframe model afresh from it (the keyframes from before
        lie behind it).

        ``map_seed``: for a session's first sweep with a ``prior``, the points (world frame) its
        map already has around the prior. The sweep is matched to them from the prior and placed
        where it matched, when the match keeps ``min_inlier_ratio`` inliers and agrees with the
        prior within its covariance (its message says so); else at the prior. A GNSS prior is
        metres off, and a session placed at it would fold its points that far from the map's.

        ``defer_model``: when this sweep becomes a keyframe, leave the model's rebuild (the
        costliest step, every second or third sweep) to :meth:`update_model`, so the caller can
        publish the pose first; a caller that is behind may skip that call (see there). The
        first keyframe is always modelled at once.

        ``stamp_s`` (the sweep's time, seconds) lets the motion prediction span a gap: when sweeps
        were dropped before reaching the matcher (an overloaded service sheds scans), the velocity
        is extrapolated over the time since the previous sweep instead of one period. Without
        stamps every sweep is taken to follow the previous one by ``period_s``.

        ``relocalize``: the session's first sweep, its ``prior`` a place guessed for it on the map
        ``on_map`` (place recognition: docs/mapping.md, "Relocalization"), not a fix: it is
        matched there as a first sweep is, and when no match passes it raises
        :class:`~randt.core.errors.NotRelocalizedError` instead of being placed at the guess.

        All or nothing: when it raises (an invalid sweep, a keyframe too sparse to model, a sweep
        not relocalized), the matcher is left exactly as it was, so the session's poses and stamps
        stay in step.
        """
        if relocalize and (prior is None or self._state.poses):
            raise ValueError("relocalize: a session's first sweep, with a prior (the place guessed)")
        if relocalize and on_map is None:
            raise NotRelocalizedError("relocalization: no map around the place guessed was prepared")
        if len(self._state.pending) > MAX_PENDING_KEYFRAMES:
            self.update_model()
        saved = self._state.snapshot()
        try:
            return self._register_scan(
                points_xyz,
                time_offset_s=time_offset_s,
                prior=prior,
                stamp_s=stamp_s,
                defer_model=defer_model,
                map_seed=map_seed,
                on_map=on_map,
                relocalize=relocalize,
            )
        except BaseException:
            self._state = saved
            raise

    def prepare_map(self, map_xyz: np.ndarray) -> PreparedReference:
        """The map's points around the vehicle (world frame) prepared as this session's model is
        (its levels: from the settings, else from its first sweep), for :meth:`register_scan`'s
        ``on_map``; a few thousand of a sweep's points are matched against it
        (:data:`ON_MAP_MATCH_POINTS`). The same as :meth:`join_map` of one piece.

        Raises
        ------
        InvalidCloudError
            The session's levels are not known yet (before its first sweep), or the points are too
            few or too sparse for them.
        """
        return self.join_map([self.prepare_map_piece(map_xyz)])

    def prepare_map_piece(self, map_xyz: np.ndarray) -> ReferencePiece:
        """One part of the map around the vehicle (a tile's points, world frame) for
        :meth:`join_map`: a window that moves keeps the pieces it still covers.

        Raises
        ------
        InvalidCloudError
            The session's levels are not known yet (before its first sweep).
        """
        return self.map_preparation().piece(map_xyz)

    def map_preparation(self) -> MapPreparation:
        """How :meth:`prepare_map_piece` and :meth:`join_map` prepare the map (the session's
        on-map settings and levels, fixed once its first sweep is matched), for a caller that
        prepares it on another thread: it touches no matcher.

        Raises
        ------
        InvalidCloudError
            The session's levels are not known yet (before its first sweep).
        """
        return MapPreparation(self._on_map_registration(), self.map_levels())

    def join_map(self, pieces: list[ReferencePiece]) -> PreparedReference:
        """The map around the vehicle from its pieces (:meth:`prepare_map_piece`, prepared at the
        session's current levels: :meth:`map_levels`), for :meth:`register_scan`'s ``on_map``.

        Raises
        ------
        InvalidCloudError
            No piece, pieces at other levels, or too few points or too sparse for the levels.
        """
        return self.map_preparation().join(pieces)

    def map_levels(self) -> tuple[float, ...]:
        """The NDT levels the map is prepared at (the session's: from the settings, else from its
        first sweep).

        Raises
        ------
        InvalidCloudError
            Not known yet (levels from the first sweep, before it).
        """
        if not self.registration.voxel_sizes_m and self.settings.voxel_sizes_m:
            self._resolve_scales(np.zeros((0, 3)))  # (levels the settings fix need no sweep)
        levels = tuple(float(v) for v in self.registration.voxel_sizes_m or ())
        if not levels:
            raise InvalidCloudError("the map cannot be prepared before the session's first sweep")
        return levels

    def _on_map_registration(self) -> RegistrationSettings:
        return self.registration.model_copy(
            update={"max_match_points": ON_MAP_MATCH_POINTS, "outlier_removal": "none"}
        )

    @contextmanager
    def _matching_on(self, on_map: PreparedReference | None) -> Iterator[None]:
        """Match this sweep against ``on_map`` (the session's model and settings put back after)."""
        if on_map is None:
            yield
            return
        model, registration = self._state.model, self.registration
        self._state.model, self.registration = on_map, self._on_map_registration()
        self._on_map_now = True
        try:
            yield
        finally:
            self._state.model, self.registration = model, registration
            self._on_map_now = False

    def _restart_model(self, T: np.ndarray, points: np.ndarray) -> None:
        """Mapping again after localizing: the keyframe model starts from this sweep (its pose
        found on the map), the keyframes from before lie behind the vehicle."""
        st = self._state
        st.keyframes.clear()
        st.store = st.model = None
        st.pending = []
        st.localized = None
        self.set_keyframe(T, points)

    def _register_scan(
        self,
        points_xyz: np.ndarray,
        *,
        time_offset_s: np.ndarray | None,
        prior: PosePrior | None,
        stamp_s: float | None = None,
        defer_model: bool = False,
        map_seed: np.ndarray | None = None,
        on_map: PreparedReference | None = None,
        relocalize: bool = False,
    ) -> ScanResult:
        """One sweep, the stages of the module docstring; :meth:`register_scan` restores the state
        if it raises."""
        t_start = time.perf_counter()
        times: dict[str, float] = {"deskew": 0.0, "features": 0.0}
        stride = 1 if on_map is None else on_map_stride(np.shape(points_xyz)[0] if np.ndim(points_xyz) else 0)
        sweep = self._sanitize(points_xyz, time_offset_s, stride)
        index = len(self._state.poses)
        if index == 0:
            self._resolve_scales(sweep.xyz)
        # (the first sweep that maps again is matched on the map it was localized on last)
        restart = on_map is None and self._state.localized is not None
        reference = self._state.localized if restart else on_map
        prior_T = None if prior is None else as_transform(prior.T_world_sensor, name="prior pose")
        # Periods since the previous sweep: 1 without stamps, more after sweeps dropped upstream.
        periods = self._periods_since_last(stamp_s)
        T_pred = self._predict(index, prior_T, periods)
        prepare = self._preparer(sweep.xyz, sweep.time_offset_s if index > 0 else None, times)
        xyz, feats = prepare(self._velocity(periods))
        fell_back = self._state.fallback_run  # sweeps since the last match, before this one
        velocity = None  # (a first sweep deskewed on the map: the motion measured within it)
        if index == 0:
            if sweep.time_offset_s is not None and on_map is None:  # (on the map: no first keyframe)
                self._state.first_raw = (xyz, sweep.time_offset_s)
            with self._matching_on(on_map):
                first = self._first_in_map(xyz, feats, prior_T, prior, map_seed, on_map)
                T_first, message, matched_on = first
                if relocalize and matched_on is None:
                    raise NotRelocalizedError(f"relocalization: {self._first_why}")
                if matched_on is not None and sweep.time_offset_s is not None:
                    timed = self._preparer(sweep.xyz, sweep.time_offset_s, times)  # (it deskews)
                    T_first, xyz, feats, velocity = self._first_deskewed_on_map(
                        sweep, T_first, xyz, feats, timed, matched_on
                    )
            outcome = _Outcome(T_first, "first", message, True, 0.0, np.full((6, 6), np.nan), 1.0, xyz, feats)
        else:
            t0 = time.perf_counter()
            has_times = sweep.time_offset_s is not None
            with self._matching_on(reference):
                outcome = self._match(index, xyz, feats, has_times, prepare, T_pred, prior_T, prior, periods)
                if (
                    index == 1
                    and self._state.first_raw is not None
                    and self._state.keyframes
                    and outcome.status == "ok"
                ):
                    gating = _Gating(T_pred, prior_T, prior, periods)
                    outcome = self._second_sweep_again(outcome, prepare, gating)
            times["match"] = time.perf_counter() - t0
        T = orthonormalize(outcome.T)
        matched = outcome.status == "ok"
        self._advance(T, index, periods, stamp_s, fell_back if matched else 0, matched)
        if index == 0 and velocity is not None:  # (the second sweep's prediction moves with it)
            self._state.delta = velocity
        self._keep_prior_offset(T, prior_T, outcome.status)
        keep_map = ~outcome.feats.noise_mask
        mapped_xyz = np.compress(keep_map, outcome.xyz, axis=0)  # not xyz[keep_map]: see _sanitize
        localized = on_map is not None and (matched or outcome.message == MATCHED_TO_MAP)
        if on_map is not None:  # no keyframe on the map
            is_kf = False
            if localized:
                self._state.localized = on_map
        elif restart:
            self._restart_model(T, mapped_xyz)
            is_kf = True
        else:
            is_kf = self._keyframe_if_due(T, outcome.status, mapped_xyz, defer_model, times)
        return ScanResult(
            index=index,
            T_world_sensor=T,
            status=outcome.status,
            converged=bool(outcome.converged),
            fitness=float(outcome.fitness),
            inlier_ratio=float(outcome.inlier_ratio),
            is_keyframe=is_kf,
            time_s=time.perf_counter() - t_start,
            covariance=outcome.covariance,
            deskewed_xyz=mapped_xyz,
            map_index=sweep.source_index[keep_map],
            n_points=int(outcome.xyz.shape[0]),
            n_nonfinite_dropped=sweep.n_nonfinite_dropped,
            message=outcome.message,
            stage_times_s=times,
            localized=localized,
            deskewed=index > 0 or sweep.time_offset_s is None or velocity is not None,
        )

    # -- the stages of one sweep ------------------------------------------------------------------
    def _sanitize(self, points_xyz: np.ndarray, time_offset_s: np.ndarray | None, stride: int = 1) -> _Sweep:
        """Finite points (counted) within ``min_range_m``..``max_range_m``, with their point times
        and their rows in the input; a sweep with too few is an :class:`InvalidCloudError`.
        ``stride``: only every this many rows are looked at (on the map: a share of the points is
        enough, the map holds the rest; the non-finite rows are counted among them)."""
        s = self.settings
        if np.ndim(points_xyz) != 2:  # (the shape's own error first)
            sanitize_points(points_xyz, name="scan", min_points=self.registration.min_points)
        n_rows = np.asarray(points_xyz).shape[0]
        if time_offset_s is not None:
            time_offset_s = np.asarray(time_offset_s, dtype=np.float64)
            if time_offset_s.shape != (n_rows,):
                raise InvalidCloudError(f"scan: {time_offset_s.shape[0]} time offsets for {n_rows} points")
        rows = np.arange(0, n_rows, stride) if stride > 1 else None
        if rows is not None:  # (taken before the float64 copy and the range test: a third of the work)
            points_xyz = np.asarray(points_xyz)[::stride]
            if time_offset_s is not None:
                time_offset_s = time_offset_s[::stride]
        xyz, n_bad = sanitize_points(points_xyz, name="scan", min_points=self.registration.min_points)
        if n_bad:
            source_index = np.flatnonzero(
                np.isfinite(np.asarray(points_xyz, dtype=np.float64)[:, :3]).all(axis=1)
            )
        else:
            source_index = np.arange(xyz.shape[0])
        if time_offset_s is not None:
            time_offset_s = time_offset_s[source_index]
        x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        rng2 = x * x + y * y + z * z
        keep = (rng2 >= s.min_range_m**2) & (rng2 <= s.max_range_m**2)
        # np.compress, not xyz[keep]: a boolean index of an (N,3) array takes numpy's generic,
        # much slower path.
        xyz = np.compress(keep, xyz, axis=0)
        source_index = source_index[keep]
        if rows is not None:
            source_index = rows[source_index]
        if time_offset_s is not None:
            time_offset_s = time_offset_s[keep]
        if xyz.shape[0] < self.registration.min_points:
            raise InvalidCloudError(f"scan: {xyz.shape[0]} points within {s.min_range_m}-{s.max_range_m} m")
        return _Sweep(xyz, time_offset_s, source_index, n_bad)

    def _first_in_map(
        self,
        xyz: np.ndarray,
        feats: Features,
        prior_T: np.ndarray | None,
        prior: PosePrior | None,
        map_seed: np.ndarray | None,
        on_map: PreparedReference | None = None,
    ) -> tuple[np.ndarray, str, PreparedReference | None]:
        """The first sweep's pose and message: matched to its map's points around its prior
        (``register_scan``'s ``map_seed``, or the map prepared: ``on_map``) when that match
        passes, else the prior (or the identity); and the map it was matched on (``None``: it
        was not). A match that does not pass is tried again (:meth:`_first_candidates`): a GNSS
        fix is metres and a degree off, and the sweep as it came is smeared by its motion."""
        if prior_T is None or prior is None:
            return np.eye(4), "", None
        if on_map is None and (map_seed is None or len(map_seed) < MAP_SEED_MIN_POINTS):
            return prior_T, "", None
        levels = self.registration.voxel_sizes_m or ()
        reference = on_map
        why = ""
        try:
            if reference is None:
                assert map_seed is not None
                seed = np.asarray(map_seed, dtype=np.float64)
                reference = prepare_reference(seed, self.registration, levels)
            for points, T0 in self._first_candidates(xyz, feats, prior_T):
                res = register(
                    points, None, T0, settings=self.registration, reference=reference,
                    coarsest_voxel_m=self._start_level(None),
                )  # fmt: skip
                why = self._first_refusal(res, prior, feats, reference)
                if not why:
                    return res.T_target_source, MATCHED_TO_MAP, reference
        except RandtError as exc:
            why = f"it failed ({exc})"
        log.info("first sweep: its match to the map is not taken (%s): placed at its prior", why)
        self._first_why = f"the sweep's match to the map is not taken ({why})"
        return prior_T, "", None

    def _first_candidates(
        self, xyz: np.ndarray, feats: Features, prior_T: np.ndarray
    ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """What a first sweep is matched with and from, in turn until one passes: its features
        from the prior, from the prior turned by each of :data:`FIRST_RETRY_YAW_DEG`, and on the
        map its points from the prior (the ground whole, where the features keep little of it;
        a mapping session's sweep is not taken at its stride, and costs too much): docs/mapping.md,
        "In the service"."""
        yield feats.matching_xyz, prior_T
        for yaw in FIRST_RETRY_YAW_DEG:
            yield feats.matching_xyz, yawed(prior_T, yaw)
        if self._on_map_now:
            yield xyz, prior_T

    def _first_refusal(
        self, res: RegistrationResult, prior: PosePrior, feats: Features, reference: PreparedReference
    ) -> str:
        """Why a first sweep's match is not taken ("": it is)."""
        if res.inlier_ratio < self._min_inlier_ratio():
            return f"{res.inlier_ratio:.2f} inliers"
        if not self._agrees(res.T_target_source, prior):
            d = float(np.linalg.norm(res.T_target_source[:3, 3] - prior.T_world_sensor[:3, 3]))
            return f"{d:.2f} m from the prior, beyond its covariance"
        # (as it came, its objects are smeared by its motion: at 10 m/s the right match keeps half)
        return self._objects_refusal(res.T_target_source, feats, reference, share=0.5) or ""

    def _first_deskewed_on_map(
        self,
        sweep: _Sweep,
        T: np.ndarray,
        xyz: np.ndarray,
        feats: Features,
        prepare: Callable[[np.ndarray], tuple[np.ndarray, Features]],
        on_map: PreparedReference,
    ) -> tuple[np.ndarray, np.ndarray, Features, np.ndarray | None]:
        """A first sweep matched on its map's points as it came (``T``), deskewed with the motion
        during it and matched again: ``(pose, sweep, features, velocity)``, or what it got with
        no velocity when the sweep matched deskewed does not agree with the map.

        No velocity is known before a second sweep, and at 10 m/s a sweep spans a metre of travel
        (in a corner, degrees of turn): matched as it came, its pose is tens of centimetres and
        half a degree off. On a fixed map the motion shows in the sweep itself: deskewed with the
        right one, its points fit the map best. Pose and motion are found together (a sweep matched
        as it came sits a third of its travel off: :func:`~randt.core.sweep_motion.pose_and_motion_on_map`
        on :data:`FIRST_MOTION_POINTS` of its points, on the map's second finest level and then
        its finest), and the whole sweep deskewed with that motion is matched once more
        (docs/mapping.md, "In the service")."""
        assert sweep.time_offset_s is not None
        levels = self.registration.voxel_sizes_m or ()
        below_coarsest = levels[min(1, len(levels) - 1)] if levels else None  # (T is near already)
        rows = np.unique(np.linspace(0, len(sweep.xyz) - 1, FIRST_MOTION_POINTS).astype(np.intp))
        sample, tau = sweep.xyz[rows], sweep.time_offset_s[rows]

        def deskewed_sample(motion: np.ndarray) -> np.ndarray:
            return deskew(sample, tau, _planar_motion(motion), self.period_s, reference_fraction=MID_SWEEP)

        motion, T_found = np.zeros(3), T
        for gmap in on_map.maps[-2:]:
            scale = gmap.voxel_size_m / on_map.maps[-1].voxel_size_m
            found = pose_and_motion_on_map(
                deskewed_sample,
                motion,
                np.asarray(FIRST_MOTION_STEPS) * scale,
                np.asarray(FIRST_MOTION_EPS),
                T_found,
                gmap,
                ndt_constants(gmap.voxel_size_m, self.registration.outlier_ratio),
                max_iterations=FIRST_MOTION_ITERATIONS,
            )
            motion, T_found = found.motion, found.T
        velocity = _planar_motion(motion)
        cloud, deskewed = prepare(velocity)
        try:
            res = register(
                deskewed.matching_xyz,
                None,
                T_found,
                settings=self._on_map_registration(),
                reference=on_map,
                coarsest_voxel_m=below_coarsest,
            )
        except RandtError:
            return T, xyz, feats, None
        if (
            res.inlier_ratio < self._min_inlier_ratio()
            or self._objects_refusal(res.T_target_source, deskewed, on_map) is not None
        ):
            return T, xyz, feats, None
        return res.T_target_source, cloud, deskewed, velocity

    def _predict(self, index: int, prior_T: np.ndarray | None, periods: float) -> np.ndarray:
        """``T_last`` moved by the predicted velocity (:meth:`_velocity`) over ``periods``; the
        first sweep at its prior (or the identity)."""
        if index == 0:
            return np.eye(4) if prior_T is None else prior_T
        return orthonormalize(self._state.poses[-1] @ scale_motion(self._velocity(periods), periods))

    def _velocity(self, periods: float) -> np.ndarray:
        """The motion over the next sweep period: the last velocity ``delta``, carried on by
        ``acceleration_gain`` times its change since the velocity before (``prev_delta``) when the
        next sweep follows the last by one period and both velocities came from matches; else
        ``delta`` (constant velocity: over a gap the yaw hypotheses take the turn,
        :meth:`_hypotheses`). A car's yaw rate grows through a corner's entry and its speed
        changes as it brakes: constant velocity is a sweep behind both, and its first deskew
        warps the sweep by the difference (:meth:`_redeskew` then deskews again)."""
        st, s = self._state, self.settings
        if st.prev_delta is None or s.acceleration_gain == 0.0 or abs(periods - 1.0) > ONE_PERIOD_TOLERANCE:
            return st.delta
        change = invert(st.prev_delta) @ st.delta
        dt2 = self.period_s**2
        turn, move = rotation_angle_deg(change[:3, :3]), float(np.linalg.norm(change[:3, 3]))
        limit = min(1.0, s.max_angular_acceleration_dps2 * dt2 / max(turn, 1e-12))
        limit = min(limit, s.max_acceleration_mps2 * dt2 / max(move, 1e-12))
        return orthonormalize(st.delta @ scale_motion(change, s.acceleration_gain * limit))

    def _preparer(
        self, xyz_raw: np.ndarray, tau: np.ndarray | None, times: dict[str, float]
    ) -> Callable[[np.ndarray], tuple[np.ndarray, Features]]:
        """``prepare(delta)``: the sweep deskewed with ``delta`` (when it has point times ``tau``)
        and its features, the time spent added to ``times``."""

        def prepare(delta: np.ndarray) -> tuple[np.ndarray, Features]:
            t0 = time.perf_counter()
            cloud = xyz_raw
            if tau is not None:
                cloud = deskew(xyz_raw, tau, delta, self.period_s, reference_fraction=MID_SWEEP)
            t1 = time.perf_counter()
            factor = self.settings.ground_voxel_factor
            feats = extract_features(cloud, voxel_size_m=self.feature_voxel_m, ground_voxel_factor=factor)
            times["deskew"] += t1 - t0
            times["features"] += time.perf_counter() - t1
            return cloud, feats

        return prepare

    def _match(
        self,
        index: int,
        xyz: np.ndarray,
        feats: Features,
        has_times: bool,
        prepare: Callable[[np.ndarray], tuple[np.ndarray, Features]],
        T_pred: np.ndarray,
        prior_T: np.ndarray | None,
        prior: PosePrior | None,
        periods: float,
    ) -> _Outcome:
        """Match against the model from the prediction (then its hypotheses), deskew again with the
        velocity found, and accept the best gated match or fall back to the prediction (or prior)."""
        best, outcome = self._try_hypotheses(xyz, feats, has_times, prepare, T_pred, prior_T, prior, periods)
        if best is None and prior_T is None and self._relocalization_due():
            best = self._relocalize(xyz, feats)
        if best is not None and best[0] >= 0 and has_times and self.settings.redeskew:
            best = self._redeskew(best, prepare, _Gating(T_pred, prior_T, prior, periods))
        if best is not None and best[0] >= 0:
            # Judged once deskewed with the velocity found: a yaw hypothesis's own deskew warps them.
            why = self._objects_refusal(best[1].T_target_source, best[3], self._state.model)
            if why is not None:
                best, outcome = None, replace(outcome, message=why)
        if best is not None:
            attempt, res, best_xyz, best_feats, _ = best
            self._state.recent_inliers.append(res.inlier_ratio)
            if index < 2:  # the first match's prediction knew no velocity: no measure of it
                pass
            elif attempt == 0 and periods <= 1.5 and not self._state.fallback_run:
                self._state.recent_corrections.append(_correction_m(invert(T_pred) @ res.T_target_source))
            else:  # a retried hypothesis, a gap or fallbacks before: the prediction was not good
                self._state.recent_corrections.clear()
            outcome = _Outcome(
                res.T_target_source, "ok", "", res.converged, res.fitness, res.covariance,
                res.inlier_ratio, best_xyz, best_feats,
            )  # fmt: skip
            if attempt < 0:
                outcome = replace(outcome, message=RELOCALIZED)
                log.warning(
                    "scan %d: relocalized %.1f m from the prediction after %d fallbacks",
                    index,
                    float(np.linalg.norm(res.T_target_source[:3, 3] - T_pred[:3, 3])),
                    self._state.fallback_run,
                )
            elif attempt:
                log.info("scan %d: matched from yaw hypothesis %d", index, attempt)
        else:
            self._state.recent_corrections.clear()
            if prior_T is not None:
                outcome = replace(outcome, T=self._in_live_frame(prior_T))
            log.warning(
                "scan %d: falling back to the %s: %s",
                index,
                "prior" if prior_T is not None else "motion prediction",
                outcome.message,
            )
        self._state.fallback_run = self._state.fallback_run + 1 if outcome.status == "fallback" else 0
        return outcome

    def _try_hypotheses(
        self,
        xyz: np.ndarray,
        feats: Features,
        has_times: bool,
        prepare: Callable[[np.ndarray], tuple[np.ndarray, Features]],
        T_pred: np.ndarray,
        prior_T: np.ndarray | None,
        prior: PosePrior | None,
        periods: float,
    ) -> tuple[_Match | None, _Outcome]:
        """Register from the prediction first; if its match fails a gate (or looks weak), from the
        alternatives of :meth:`_hypotheses` (a corner's onset changes the yaw rate faster than a
        constant-velocity prior can follow). Returns the gated match with the most inliers (None if
        none passed) and the fallback outcome: the prediction, with the prediction's own match
        figures and the first reason a match was refused."""
        message = ""
        converged, fitness, cov, inliers = False, 0.0, np.full((6, 6), np.nan), 0.0
        best: _Match | None = None
        # A session that has lost its track (LOST_AFTER_FALLBACKS in a row) tries the prediction
        # only: the retries (up to 8 registrations) cannot find it and would starve others.
        lost = self._state.fallback_run >= LOST_AFTER_FALLBACKS
        # The first match (the second sweep) has no velocity to predict from and no recent inlier
        # ratio to judge by, and may stop where it started with enough inliers to pass. So a first
        # match that stays where it started (a vehicle standing still, or one stuck there) tries
        # every hypothesis and keeps the best; one that moved found the motion, and is spared the
        # hypotheses' registrations (docs/mapping.md, step 6, "The first match").
        first_match = len(self._state.poses) < 2
        for attempt, init in enumerate(self._hypotheses(T_pred, periods, feats.matching_xyz)):
            if lost and attempt > 0:
                break
            coarsest = self._start_level(self._coarsest_level(periods) if attempt == 0 else None)
            cloud, cloud_feats = xyz, feats
            if has_times and attempt > 0 and self.settings.redeskew:
                # A yaw hypothesis implies another velocity: deskew the sweep with it.
                cloud, cloud_feats = prepare(self._per_period(invert(self._state.poses[-1]) @ init, periods))
            try:
                res = register(
                    cloud_feats.matching_xyz,
                    None,
                    init,
                    settings=self.registration,
                    reference=self._state.model,
                    coarsest_voxel_m=coarsest,
                )
            except RandtError as exc:
                message = message or f"registration failed: {exc}"
                continue
            why = self._gate(res, T_pred, prior_T, prior, periods)
            if why is None and (best is None or res.inlier_ratio > best[1].inlier_ratio):
                best = (attempt, res, cloud, cloud_feats, init)
            if attempt == 0 and best is None:
                converged, fitness, cov, inliers = (
                    res.converged,
                    res.fitness,
                    res.covariance,
                    res.inlier_ratio,
                )
            message = message or (why or "")
            stayed = first_match and _translation_m(T_pred, res.T_target_source) < FIRST_MATCH_STAYED_M
            if best is not None and best[0] == 0 and not self._weak(res.inlier_ratio) and not stayed:
                break  # the prediction's match passed and looks like the recent ones: no retries
        return best, _Outcome(T_pred, "fallback", message, converged, fitness, cov, inliers, xyz, feats)

    def _relocalization_due(self) -> bool:
        """Whether this sweep, whose prediction's match failed, tries :meth:`_relocalize`: on the
        sweep that makes the session lost and on every :data:`RELOCALIZE_EVERY`-th after."""
        run = self._state.fallback_run + 1  # counting this sweep's fallback
        return (
            self.settings.relocalize
            and self._state.localized is None  # (on the map: its keyframes are not there)
            and self._state.model is not None
            and run >= LOST_AFTER_FALLBACKS
            and (run - LOST_AFTER_FALLBACKS) % RELOCALIZE_EVERY == 0
        )

    def _relocalize(self, xyz: np.ndarray, feats: Features) -> _Match | None:
        """Find the sweep among the model's keyframes with no prediction.

        The window's keyframes are ranked by Scan Context distance to the sweep
        (:mod:`randt.core.place`; each keyframe seen from its own pose); the :data:`RELOCALIZE_CANDIDATES`
        nearest are tried in turn: global registration (:func:`randt.core.global_registration.
        register_global`) of the sweep against the keyframe's points, then the usual NDT match
        against the model from there. A keyframe, not the fused model, is the target: global
        registration wants two clouds of like extent and density. Accepted only when the global
        registration is confident and the match keeps ``min_inlier_ratio``; attempt -1 marks it.
        None when no candidate passes: the session stays lost."""
        st = self._state
        keyframes = list(st.keyframes)
        try:
            query = query_descriptors(xyz)
            described = [scan_context(transform_points(invert(T), pts)) for T, pts in keyframes]
        except RandtError as exc:
            log.info("relocalization: no descriptor: %s", exc)
            return None
        distance = np.min([scan_context_distance(q, np.stack(described))[0] for q in query], axis=0)
        order = np.argsort(distance, kind="stable")[:RELOCALIZE_CANDIDATES]
        for i in order:
            T_kf, pts = keyframes[int(i)]
            try:
                found = register_global(
                    xyz, transform_points(invert(T_kf), pts), GlobalSettings(max_range_m=RELOCALIZE_RANGE_M)
                )
            except RandtError as exc:
                log.info("relocalization against keyframe %d failed: %s", int(i), exc)
                continue
            if not found.confident:
                log.info("relocalization against keyframe %d not confident: %s", int(i), found.reason)
                continue
            init = T_kf @ found.T_target_source
            try:
                res = register(feats.matching_xyz, None, init, settings=self.registration, reference=st.model)
            except RandtError as exc:
                log.info("relocalization's match failed: %s", exc)
                continue
            if res.inlier_ratio >= self.settings.min_inlier_ratio and (
                self._objects_refusal(res.T_target_source, feats, st.model) is None
            ):
                return (-1, res, xyz, feats, init)
            log.info("relocalization's match keeps %.2f inliers", res.inlier_ratio)
        return None

    def _advance(
        self,
        T: np.ndarray,
        index: int,
        periods: float,
        stamp_s: float | None,
        fell_back: int = 0,
        matched: bool = False,
    ) -> None:
        """Append the pose; the velocity (per period) from the last matched pose, the stamp kept.

        ``fell_back``: the sweeps that fell back just before this matched one. Their poses are
        predictions, so the velocity is measured from the last match before them, over the
        periods since (one per fallback): after 20 blocked sweeps while the vehicle stood still,
        the match 20 m behind the prediction is no velocity of 20 m per period. The velocity
        before is kept for the acceleration (:meth:`_velocity`) only when this sweep ``matched``
        one period after a matched one whose velocity was measured too.
        """
        st = self._state
        if index > 0:
            back = min(fell_back, len(st.poses) - 1)
            delta = orthonormalize(self._per_period(invert(st.poses[-1 - back]) @ T, periods + back))
            measured = matched and not fell_back and abs(periods - 1.0) <= ONE_PERIOD_TOLERANCE
            st.prev_delta = st.delta if measured and st.delta_measured else None
            st.delta, st.delta_measured = delta, measured
        if st.poses:
            st.travel_m += float(np.linalg.norm(T[:3, 3] - st.poses[-1][:3, 3]))
        st.poses.append(T)
        if stamp_s is not None:
            st.last_stamp_s = float(stamp_s)

    def _second_sweep_again(
        self, outcome: _Outcome, prepare: Callable[[np.ndarray], tuple[np.ndarray, Features]], gating: _Gating
    ) -> _Outcome:
        """The second sweep matched again once the first keyframe is deskewed, until the velocity
        settles.

        Until the second sweep is matched no velocity is known: the model is the first sweep as it
        came, warped by the motion during it, and the second sweep's pose is measured against that
        warp. With the velocity the match found, the first keyframe is deskewed and the second
        sweep, deskewed with the same velocity, matched again from its pose; kept only if it passes
        the same gate. That first velocity is itself measured against the warp, and a first
        keyframe left warped gives the session a heading error it keeps. So it goes round again
        with the velocity of the new match, until that changes by less than
        :data:`SECOND_SWEEP_DEG` and :data:`SECOND_SWEEP_M` (at most :data:`SECOND_SWEEP_PASSES`
        times; docs/mapping.md, step 4).
        """
        for _ in range(SECOND_SWEEP_PASSES):
            velocity = self._per_period(invert(self._state.poses[-1]) @ outcome.T, gating.periods)
            self._deskew_first_keyframe(velocity)
            cloud, feats = prepare(velocity)
            again = self._match_again(feats, outcome.T, gating)
            if again is None:
                break
            outcome = replace(
                outcome, T=again.T_target_source, converged=again.converged, fitness=again.fitness,
                covariance=again.covariance, inlier_ratio=again.inlier_ratio, xyz=cloud, feats=feats,
            )  # fmt: skip
            found = self._per_period(invert(self._state.poses[-1]) @ again.T_target_source, gating.periods)
            if not _motion_changed(velocity, found, SECOND_SWEEP_DEG, SECOND_SWEEP_M):
                break
        self._state.first_raw = None
        return outcome

    def _deskew_first_keyframe(self, velocity: np.ndarray) -> None:
        """Replace the first keyframe by its raw sweep deskewed with ``velocity``."""
        st = self._state
        assert st.first_raw is not None
        raw, tau = st.first_raw
        first = deskew(raw, tau, velocity, self.period_s, reference_fraction=MID_SWEEP)
        st.keyframes.popleft()
        st.keyframes.appendleft(
            (st.poses[0], voxel_downsample(transform_points(st.poses[0], first), self.model_voxel_m))
        )
        if st.model is not None:
            self._rebuild_model()

    def _keyframe_if_due(
        self,
        T: np.ndarray,
        status: Literal["first", "ok", "fallback"],
        mapped_xyz: np.ndarray,
        defer_model: bool,
        times: dict[str, float],
    ) -> bool:
        """The paper's Set: a matched sweep far enough (or turned enough) from the last keyframe
        becomes one, modelled now or left pending (``defer_model``); returns whether it did."""
        is_kf = self._state.model is None or self._needs_keyframe(T)
        if is_kf and status != "fallback":
            if defer_model and self._state.model is not None:
                self._state.pending.append((T.copy(), mapped_xyz))
                self._state.last_keyframe_pose = T.copy()  # keyframe spacing counts pending ones
            else:
                t0 = time.perf_counter()
                self.set_keyframe(T, mapped_xyz)
                times["model"] = time.perf_counter() - t0
        return bool(is_kf and status != "fallback")

    # -- persistence ----------------------------------------------------------------------------
    def state_dict(self) -> dict[str, np.ndarray]:
        """Everything needed to resume this session after a restart, as plain numpy arrays.

        Keys: ``poses`` (N,4,4), ``delta`` (4,4), ``prev_delta`` (4,4, NaN when none) and
        ``delta_measured`` (the acceleration's memory), ``keyframe_poses`` (K,4,4), ``keyframe_points``
        (M,3) with ``keyframe_sizes`` (K,), ``scales`` (feature voxel, model voxel), ``levels``,
        ``last_keyframe_pose``, ``last_stamp_s`` (NaN when sweeps came without stamps) and
        ``recent_corrections`` (the adaptive levels' memory), ``travel_m``, ``prior_offset`` (NaN
        before a sweep with a prior) and ``prior_offset_travel_m`` (the prior gate's memory).
        Suitable for ``np.savez``; the settings are the caller's to keep. A pending keyframe
        (``defer_model``) is folded in first.
        """
        self.update_model()
        st = self._state
        kf = list(st.keyframes)
        return {
            "poses": np.array(st.poses).reshape(-1, 4, 4),
            "delta": st.delta.copy(),
            "prev_delta": np.full((4, 4), np.nan) if st.prev_delta is None else st.prev_delta.copy(),
            "delta_measured": np.array(st.delta_measured),
            "keyframe_poses": np.array([p for p, _ in kf]).reshape(-1, 4, 4),
            "keyframe_points": np.vstack([x for _, x in kf]) if kf else np.zeros((0, 3)),
            "keyframe_sizes": np.array([x.shape[0] for _, x in kf], dtype=np.int64),
            "scales": np.array([self.feature_voxel_m, self.model_voxel_m]),
            "levels": np.array(self.registration.voxel_sizes_m or (), dtype=np.float64),
            "last_keyframe_pose": (
                np.full((4, 4), np.nan) if st.last_keyframe_pose is None else st.last_keyframe_pose
            ),
            "last_stamp_s": np.array(np.nan if st.last_stamp_s is None else st.last_stamp_s),
            "recent_corrections": np.array(st.recent_corrections, dtype=np.float64),
            "travel_m": np.array(st.travel_m),
            "prior_offset": np.full(3, np.nan) if st.prior_offset is None else st.prior_offset.copy(),
            "prior_offset_travel_m": np.array(st.prior_offset_travel_m),
        }

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        """Resume from :meth:`state_dict` output (same settings); the model is rebuilt from keyframes."""
        st = self._state
        st.poses = [np.asarray(p, dtype=np.float64) for p in state["poses"]]
        st.delta = np.asarray(state["delta"], dtype=np.float64)
        # Older states have no acceleration: constant velocity until two sweeps have matched.
        prev = np.asarray(state.get("prev_delta", np.full((4, 4), np.nan)), dtype=np.float64)
        st.prev_delta = None if np.isnan(prev).any() else prev
        st.delta_measured = bool(np.asarray(state.get("delta_measured", False)))
        feature_voxel_m, model_voxel_m = (float(v) for v in state["scales"])
        self._apply_scales(tuple(float(v) for v in state["levels"]), feature_voxel_m, model_voxel_m)
        sizes = np.asarray(state["keyframe_sizes"], dtype=np.int64)
        chunks = np.split(np.asarray(state["keyframe_points"], dtype=np.float64), np.cumsum(sizes)[:-1])
        st.keyframes.clear()
        for pose, pts in zip(state["keyframe_poses"], chunks if sizes.size else [], strict=True):
            st.keyframes.append((np.asarray(pose, dtype=np.float64), pts))
        last = np.asarray(state["last_keyframe_pose"], dtype=np.float64)
        st.last_keyframe_pose = None if np.isnan(last).any() else last
        # States saved before stamps were kept have none: the next sweep then counts as one period.
        stamp = float(np.asarray(state.get("last_stamp_s", np.nan)))
        st.last_stamp_s = None if np.isnan(stamp) else stamp
        # Older states have none: the next sweeps then run every level until enough are known.
        st.recent_corrections.clear()
        st.recent_corrections.extend(float(c) for c in state.get("recent_corrections", ()))
        # Older states have no prior gate memory: the path from the poses, no offset known.
        if "travel_m" in state:
            st.travel_m = float(np.asarray(state["travel_m"]))
        else:
            xyz = np.array([p[:3, 3] for p in st.poses]).reshape(-1, 3)
            st.travel_m = float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum())
        offset = np.asarray(state.get("prior_offset", np.full(3, np.nan)), dtype=np.float64)
        st.prior_offset = None if np.isnan(offset).any() else offset
        st.prior_offset_travel_m = float(np.asarray(state.get("prior_offset_travel_m", st.travel_m)))
        st.first_raw = None
        st.model = st.store = None
        if st.keyframes:
            self._rebuild_model()

    def _coarsest_level(self, periods: float) -> float | None:
        """The coarsest NDT level a match from the prediction needs (adaptive levels,
        :data:`LEVEL_MARGIN`); None (every level) without enough recent matches or after a gap."""
        recent = self._state.recent_corrections
        fine = self._fine_levels()
        if fine is None or not self.settings.adaptive_levels or periods > 1.5:
            return None
        if len(recent) < MIN_CORRECTIONS:
            return None
        return max(LEVEL_MARGIN * max(recent), fine)

    def _fine_levels(self) -> float | None:
        """The second finest level (the finest when there is only one): a match again from a matched
        pose runs the two finest, a match from the prediction at least those."""
        levels = self.registration.voxel_sizes_m
        return None if not levels else levels[-2] if len(levels) > 1 else levels[-1]

    def _start_level(self, coarsest: float | None) -> float | None:
        """The coarsest level a match starts at (``coarsest``; None: every level); on the map no
        coarser than the second coarsest: its priors are a GNSS fix or a localized prediction,
        metres off at most, and over a window of the map the coarsest level (16 m) pulled matches
        from the truth metres away (docs/mapping.md, "In the service")."""
        levels = self.registration.voxel_sizes_m or ()
        if not self._on_map_now or len(levels) < 3:
            return coarsest
        return levels[1] if coarsest is None else min(coarsest, levels[1])

    def _min_inlier_ratio(self) -> float:
        """The inlier ratio a match needs: on the map (localizing) the stricter one."""
        s = self.settings
        return s.on_map_min_inlier_ratio if self._on_map_now else s.min_inlier_ratio

    def _weak(self, inlier_ratio: float) -> bool:
        """A match whose inlier ratio is below 70 % of the session's recent median is suspect: at a
        corner's onset a wrong match can pass the absolute gate."""
        if len(self._state.recent_inliers) < 3:
            return False
        return inlier_ratio < 0.7 * float(np.median(self._state.recent_inliers))

    def _redeskew(
        self, best: _Match, prepare: Callable[[np.ndarray], tuple[np.ndarray, Features]], gating: _Gating
    ) -> _Match:
        """Deskew once more with the velocity the match found, when it differs from the one used.

        Deskewing needs the sweep's motion, which only the match gives: at a corner's onset the
        yaw rate jumps and the previous sweep's velocity warps the points the wrong way. When the
        matched motion differs from the one used by more than :data:`REDESKEW_DEG` or
        :data:`REDESKEW_M`, the sweep is deskewed with it and matched again from the first result
        (one pass; kept only if it passes the same gate).
        """
        attempt, res, _, _, init = best
        used = self._per_period(invert(self._state.poses[-1]) @ init, gating.periods)
        found = self._per_period(invert(self._state.poses[-1]) @ res.T_target_source, gating.periods)
        deg, m = (REDESKEW_ON_MAP_DEG, REDESKEW_ON_MAP_M) if self._on_map_now else (REDESKEW_DEG, REDESKEW_M)
        if not _motion_changed(used, found, deg, m):
            return best
        cloud, feats = prepare(found)
        again = self._match_again(feats, res.T_target_source, gating)
        return best if again is None else (attempt, again, cloud, feats, res.T_target_source)

    def _match_again(self, feats: Features, T_init: np.ndarray, gating: _Gating) -> RegistrationResult | None:
        """The sweep (deskewed anew) matched again from a matched pose ``T_init`` on the two finest
        levels; None when it fails or does not pass the same gate."""
        try:
            again = register(
                feats.matching_xyz,
                None,
                T_init,
                settings=self.registration,
                reference=self._state.model,
                coarsest_voxel_m=self._fine_levels(),
            )
        except RandtError:
            return None
        return None if self._gate(again, *gating) is not None else again

    def _periods_since_last(self, stamp_s: float | None) -> float:
        """Sweep periods since the previous sweep's stamp (1 when either stamp is unknown).

        A non-increasing stamp counts as one period; a gap longer than ``max_gap_s`` as that long.
        """
        if stamp_s is None or self._state.last_stamp_s is None or not np.isfinite(stamp_s):
            return 1.0
        dt = float(stamp_s) - self._state.last_stamp_s
        if dt <= 0.0:
            return 1.0
        return min(dt, self.settings.max_gap_s) / self.period_s

    @staticmethod
    def _per_period(motion: np.ndarray, periods: float) -> np.ndarray:
        """The motion over ``periods`` sweep periods as the motion over one (a velocity)."""
        return motion if periods == 1.0 else scale_motion(motion, 1.0 / periods)

    def _hypotheses(
        self, T_pred: np.ndarray, periods: float = 1.0, matching_xyz: np.ndarray | None = None
    ) -> Iterator[np.ndarray]:
        """The prediction, then alternatives tried in order when its match fails a gate (lazily:
        nothing is computed for them when the prediction's match passes).

        After a gap (``periods`` > 1.5: sweeps dropped upstream) the turn rate may have changed
        within it, by tens of degrees over a corner (docs/mapping.md, step 7). So first the
        :data:`GAP_TURN_CANDIDATES` best turns over the gap, at the session's speed, by their NDT
        cost on the model's coarsest level (:meth:`_turns_over_gap`). Then the prediction yawed by
        each of ``retry_yaw_deg`` both ways (a corner's onset changes the yaw rate faster than a
        constant-velocity prior can follow).
        """
        yield T_pred
        if periods > 1.5 and self._state.poses and matching_xyz is not None and self._state.model is not None:
            yield from self._turns_over_gap(T_pred, periods, matching_xyz)
        for deg in self.settings.retry_yaw_deg:
            for sign in (1.0, -1.0):
                yield T_pred @ make_transform(rotvec=(0.0, 0.0, np.radians(sign * deg)))

    def _turns_over_gap(
        self, T_pred: np.ndarray, periods: float, matching_xyz: np.ndarray
    ) -> list[np.ndarray]:
        """Poses after turning by each of :data:`GAP_TURN_DEG` over the gap at the session's speed
        (the velocity's yaw rate replaced), best first by NDT cost on the coarsest model level;
        the :data:`GAP_TURN_CANDIDATES` best that are not the prediction itself."""
        assert self._state.model is not None
        gmap = self._state.model.maps[0]
        consts = ndt_constants(gmap.voxel_size_m, self.registration.outlier_ratio)
        pts = voxel_downsample(matching_xyz, 0.5 * gmap.voxel_size_m)
        rotvec = so3_log(self._state.delta[:3, :3])
        scored = []
        for turn in GAP_TURN_DEG:
            motion = self._state.delta.copy()
            motion[:3, :3] = so3_exp(np.array([rotvec[0], rotvec[1], np.radians(turn) / periods]))
            T = orthonormalize(self._state.poses[-1] @ scale_motion(motion, periods))
            if rotation_angle_deg((invert(T_pred) @ T)[:3, :3]) < 2.5:
                continue  # the prediction, tried already
            scored.append((ndt_cost(pts, T, gmap, consts, self.registration.n_neighbors), turn, T))
        scored.sort(key=lambda c: c[0])
        return [T for _, _, T in scored[:GAP_TURN_CANDIDATES]]

    def _gate(
        self,
        res: RegistrationResult,
        T_pred: np.ndarray,
        prior_T: np.ndarray | None,
        prior: PosePrior | None,
        periods: float = 1.0,
    ) -> str | None:
        """Why a registration result is not accepted, or None when it is.

        The correction limit grows with the time since the last sweep (``periods``) and with every
        sweep that fell back since the last match (``fallback_run``): the prediction's error grows
        with the time it extrapolates over, and a fallback's pose is a prediction. So a session
        whose sensor was blocked while the vehicle stood still finds its track again once the
        sweeps are good, where a fixed limit would refuse it forever.

        While the session tracks (its last sweep matched from the prediction, so the velocity the
        prediction extrapolates was measured between two matches: ``recent_corrections`` holds the
        last one's), the prediction is off by what the vehicle's acceleration moved it since,
        ``max_acceleration_mps2 * t**2 / 2`` (5 cm at 1 g over 0.1 s), plus the matches' own error
        (``max_tracking_correction_m``). A match farther than that is somewhere a vehicle cannot
        be, however many inliers it keeps (docs/mapping.md, step 7, "While the session tracks").
        """
        s = self.settings
        limit = s.max_correction_m * (max(1.0, periods) + self._state.fallback_run)
        if self._state.recent_corrections:
            t = max(1.0, periods) * self.period_s
            limit = min(limit, s.max_tracking_correction_m + 0.5 * s.max_acceleration_mps2 * t * t)
        correction = float(np.linalg.norm((invert(T_pred) @ res.T_target_source)[:3, 3]))
        least = self._min_inlier_ratio()
        if res.inlier_ratio < least:
            return f"inlier ratio {res.inlier_ratio:.2f} below {least}"
        if correction > limit:
            return f"match moved the prediction {correction:.2f} m (limit {limit:.2f} m)"
        if prior_T is not None and prior is not None and not self._agrees(res.T_target_source, prior):
            return "match disagrees with the prior pose beyond its covariance"
        return None

    def _objects_refusal(
        self, T: np.ndarray, feats: Features, reference: PreparedReference | None, share: float = 1.0
    ) -> str | None:
        """Why a match at ``T`` is refused on its objects alone, or None.

        On a flat street the ground matches at any offset along it, so a wrong match can keep
        enough inliers in all on the ground alone. The objects' own inlier ratio must reach
        ``min_object_inlier_ratio`` (on the map ``on_map_min_object_inlier_ratio``; times
        ``share``): matched sweeps keep far more than a wrong place (docs/mapping.md, step 7). A
        sweep with too few object points to judge is not refused for it.
        """
        objects = feats.object_matching_xyz
        if reference is None or len(objects) < MIN_OBJECT_POINTS:
            return None
        stride = -(-len(objects) // OBJECT_CHECK_POINTS)
        ratio = inlier_ratio(objects[::stride], T, reference, self.registration)
        s = self.settings
        least = share * (s.on_map_min_object_inlier_ratio if self._on_map_now else s.min_object_inlier_ratio)
        if ratio < least:
            return f"objects' inlier ratio {ratio:.2f} below {least}"
        return None

    def _needs_keyframe(self, T: np.ndarray) -> bool:
        last = self._state.last_keyframe_pose
        if last is None:
            return True
        rel = invert(last) @ T
        return bool(
            np.linalg.norm(rel[:3, 3]) >= self.settings.keyframe_distance_m
            or rotation_angle_deg(rel[:3, :3]) >= self.settings.keyframe_rotation_deg
        )

    def _agrees(self, T: np.ndarray, prior: PosePrior) -> bool:
        """Whether a match at ``T`` agrees with the sweep's prior.

        The session's poses live in the frame its first prior anchored, and drift from the later
        priors as it drives (a fraction of a percent of the path): the gate compares the match's
        offset from its prior with the last agreeing sweep's offset, not with zero, allowing
        ``prior_drift_fraction`` of the path driven since. A wrong match jumps; drift creeps.
        """
        st = self._state
        d = T[:3, 3] - prior.T_world_sensor[:3, 3]
        cov = np.asarray(prior.covariance, dtype=np.float64)[:3, :3]
        if st.prior_offset is not None:
            d = d - st.prior_offset
            cov = 2.0 * cov
        drift_m = self.settings.prior_drift_fraction * (st.travel_m - st.prior_offset_travel_m)
        cov = cov + np.eye(3) * drift_m**2
        return float(d @ np.linalg.solve(cov, d)) <= self.settings.prior_gate_chi2

    def _in_live_frame(self, prior_T: np.ndarray) -> np.ndarray:
        """A prior pose moved by the session's last known drift from its priors (a fallback's pose)."""
        offset = self._state.prior_offset
        if offset is None:
            return prior_T
        T = prior_T.copy()
        T[:3, 3] += offset
        return T

    def _keep_prior_offset(self, T: np.ndarray, prior_T: np.ndarray | None, status: str) -> None:
        """After a sweep with a prior that matched (or came first): its drift from the prior."""
        if prior_T is not None and status != "fallback":
            self._state.prior_offset = T[:3, 3] - prior_T[:3, 3]
            self._state.prior_offset_travel_m = self._state.travel_m


def _motion_changed(used: np.ndarray, found: np.ndarray, deg: float, m: float) -> bool:
    """Whether the per-period motion ``found`` differs from ``used`` by ``deg`` degrees or ``m``
    metres or more (a deskew with it would move the points)."""
    change = invert(used) @ found
    return bool(rotation_angle_deg(change[:3, :3]) >= deg or np.linalg.norm(change[:3, 3]) >= m)


def _translation_m(A: np.ndarray, B: np.ndarray) -> float:
    """Distance between two poses' positions (m)."""
    return float(np.linalg.norm(A[:3, 3] - B[:3, 3]))


def _correction_m(T_pred_match: np.ndarray) -> float:
    """How far a match moved its prediction: the translation plus the rotation's displacement of
    a point :data:`CORRECTION_REACH_M` away."""
    return float(
        np.linalg.norm(T_pred_match[:3, 3])
        + np.radians(rotation_angle_deg(T_pred_match[:3, :3])) * CORRECTION_REACH_M
    )


def extend_state_dict(
    state: dict[str, np.ndarray],
    poses: np.ndarray,
    stamps_s: np.ndarray,
    *,
    settings: MatcherSettings | None = None,
    period_s: float = 0.1,
) -> dict[str, np.ndarray]:
    """A saved :meth:`IncrementalMatcher.state_dict` brought forward to a longer trajectory.

    A service logs every pose it publishes but snapshots the matcher less often; after a crash
    the snapshot ends some sweeps before the last published pose. This returns the snapshot with
    ``poses`` replaced by the whole trajectory, ``delta`` (the velocity) recomputed from its last
    two poses exactly as :meth:`IncrementalMatcher.register_scan` advances it (per sweep period,
    from the stamps, a gap capped at ``max_gap_s``), and ``last_stamp_s`` set to the last stamp.
    The keyframes stay the snapshot's: the next sweep is predicted from the last published pose
    and matched against the model of the snapshot's keyframes (its last one at most one snapshot
    interval behind, well inside ``model_radius_m``), like a sweep after a gap; it then becomes a
    keyframe, the spacing from the last one being due.

    Parameters
    ----------
    state:
        What :meth:`IncrementalMatcher.state_dict` returned (not changed).
    poses:
        (N, 4, 4) the whole trajectory; its first poses are the snapshot's.
    stamps_s:
        (N,) their stamps, seconds.
    settings, period_s:
        The matcher's (``max_gap_s``; the sweep period).

    Returns
    -------
    dict
        ``state`` itself when it already holds N poses, else an extended copy.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    stamps_s = np.asarray(stamps_s, dtype=np.float64)
    n_saved = np.asarray(state["poses"]).reshape(-1, 4, 4).shape[0]
    if poses.shape[0] <= n_saved:
        return state
    out = dict(state)
    out["poses"] = poses.copy()
    out["last_stamp_s"] = np.array(stamps_s[-1])
    out["recent_corrections"] = np.zeros(0)  # the logged sweeps' are unknown: every level for a while
    if poses.shape[0] >= 2:
        max_gap_s = (settings or MatcherSettings()).max_gap_s
        dt = float(stamps_s[-1] - stamps_s[-2])
        periods = min(dt, max_gap_s) / period_s if np.isfinite(dt) and dt > 0.0 else 1.0
        motion = invert(poses[-2]) @ poses[-1]
        out["delta"] = orthonormalize(motion if periods == 1.0 else scale_motion(motion, 1.0 / periods))
    # the logged poses' velocities are not known to be matches: constant velocity for two sweeps
    out["prev_delta"], out["delta_measured"] = np.full((4, 4), np.nan), np.array(False)
    return out


def with_keyframe(
    state: dict[str, np.ndarray], T_world_sensor: np.ndarray, points_sensor: np.ndarray
) -> dict[str, np.ndarray]:
    """A saved :meth:`IncrementalMatcher.state_dict` with one more keyframe, the newest: the
    sweep ``points_sensor`` (sensor frame) at ``T_world_sensor``, density-equalized at the
    model's voxel as the matcher's own keyframes are.

    A resumed session's snapshot may end tens of metres before its last published pose
    (:func:`extend_state_dict`), too far for the next sweep to match its model; a sweep it sent
    since, at its logged pose, brings the model up to where the vehicle is.
    """
    T = np.asarray(T_world_sensor, dtype=np.float64).reshape(4, 4)
    points = np.asarray(points_sensor, dtype=np.float64)
    world = voxel_downsample(transform_points(T, points), float(state["scales"][1]))
    out = dict(state)
    out["keyframe_poses"] = np.concatenate([np.asarray(state["keyframe_poses"]).reshape(-1, 4, 4), T[None]])
    out["keyframe_points"] = np.vstack([np.asarray(state["keyframe_points"]).reshape(-1, 3), world])
    out["keyframe_sizes"] = np.append(np.asarray(state["keyframe_sizes"], dtype=np.int64), world.shape[0])
    out["last_keyframe_pose"] = T.copy()
    return out
