"""A pose graph per map: keyframe poses fused from odometry, GNSS/INS and loop closures.

Nodes are keyframe poses ``T_world_sensor`` (any hashable key, e.g. ``(session, index)``); factors
are odometry between two keyframes of a session, GNSS positions (Huber kernel), whole-pose priors
(GNSS/INS, or a session's loose anchor on its first keyframe) and verified loops (Cauchy kernel
sized in metres). Solved incrementally by gtsam's iSAM2 (Kaess et al., IJRR 2012). gtsam orders a
Pose3's tangent (rotation, translation); every covariance here is ours, (t then r) like
:class:`randt.core.odometry.PosePrior`, and is reordered on the way in. The factors' noise and
kernels, and why: docs/mapping.md, "One map from many sessions", step 4.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field

from randt.core.errors import InvalidRequestError

__all__ = ["Edge", "PoseGraph", "PoseGraphSettings"]

EdgeKind = Literal["odometry", "loop"]


class PoseGraphSettings(BaseModel):
    """How :class:`PoseGraph` weighs and solves its factors."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    loop_kernel_m: float = Field(
        default=10.0,
        gt=0,
        description="Cauchy kernel width of loop factors in metres of disagreement: a loop whose "
        "correction is this large weighs half; drift corrections of a few metres keep most weight",
    )
    loop_iterations: int = Field(
        default=3, ge=0, description="extra iSAM2 updates after a batch that added a loop"
    )
    gnss_kernel_width: float = Field(
        default=1.345, gt=0, description="Huber kernel width of GNSS factors, in their sigmas"
    )
    anchor_sigma_m: float = Field(
        default=1000.0, gt=0, description="the weak anchor of a session with no absolute reference"
    )
    anchor_yaw_sigma_rad: float = Field(default=3.0, gt=0)
    anchor_tilt_sigma_rad: float = Field(
        default=0.1, gt=0, description="roll and pitch of a session's first keyframe: it starts level"
    )
    relinearize_threshold: float = Field(default=0.01, gt=0, description="iSAM2: relinearize above")


@dataclass(frozen=True)
class Edge:
    """A between factor, for the viewer and the API: ``kind`` and the two node keys."""

    kind: EdgeKind
    a: Hashable
    b: Hashable


def _covariance(cov: np.ndarray, size: int, what: str) -> np.ndarray:
    c = np.asarray(cov, dtype=np.float64)
    if c.shape != (size, size) or not np.all(np.isfinite(c)):
        raise InvalidRequestError(f"{what}: covariance must be a finite {size}x{size} matrix, got {c.shape}")
    c = 0.5 * (c + c.T)
    if np.linalg.eigvalsh(c).min() <= 0:
        raise InvalidRequestError(f"{what}: covariance is not positive definite")
    return c


def _gtsam_order(cov_tr: np.ndarray) -> np.ndarray:
    """(t, r) 6x6 covariance -> gtsam's (r, t) order."""
    p = np.r_[3:6, 0:3]
    return np.asarray(cov_tr[np.ix_(p, p)], dtype=np.float64)


def _check_pose(T: np.ndarray, what: str) -> np.ndarray:
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise InvalidRequestError(f"{what}: a finite 4x4 transform is needed, got shape {M.shape}")
    if not np.allclose(M[:3, :3] @ M[:3, :3].T, np.eye(3), atol=1e-6):
        raise InvalidRequestError(f"{what}: the rotation block is not orthonormal")
    return M


class PoseGraph:
    """Keyframe poses and their factors, solved incrementally (module docstring).

    Add nodes and factors in any order that names a node before it is used; :meth:`optimize` solves
    what is pending; :meth:`pose` / :meth:`poses` read the current estimate.
    """

    def __init__(self, settings: PoseGraphSettings | None = None) -> None:
        import gtsam  # the solver; imported here so that `import core` stays light

        self._gtsam: Any = gtsam
        self.settings = settings or PoseGraphSettings()
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.settings.relinearize_threshold)
        params.setFactorization("QR")  # the weak anchors span 1e12 in information: Cholesky fails
        self._isam = gtsam.ISAM2(params)
        self._pending = gtsam.NonlinearFactorGraph()
        self._pending_values = gtsam.Values()
        self._ids: dict[Hashable, int] = {}
        self._estimate: dict[int, np.ndarray] = {}
        self.edges: list[Edge] = []
        self.n_gnss = 0
        self._loops_pending = False

    # ------------------------------------------------------------------ nodes
    def __contains__(self, key: Hashable) -> bool:
        return key in self._ids

    def __len__(self) -> int:
        return len(self._ids)

    def add_node(self, key: Hashable, T_world_sensor: np.ndarray) -> None:
        """A keyframe node with its initial estimate (e.g. the odometry pose)."""
        if key in self._ids:
            raise InvalidRequestError(f"pose graph: node {key!r} exists already")
        T = _check_pose(T_world_sensor, f"node {key!r}")
        i = len(self._ids)
        self._ids[key] = i
        self._pending_values.insert(i, self._gtsam.Pose3(T))
        self._estimate[i] = T.copy()

    def _id(self, key: Hashable) -> int:
        try:
            return self._ids[key]
        except KeyError:
            raise InvalidRequestError(f"pose graph: no node {key!r}") from None

    # ---------------------------------------------------------------- factors
    def add_odometry(self, a: Hashable, b: Hashable, T_a_b: np.ndarray, covariance: np.ndarray) -> None:
        """Relative pose ``T_a_b`` (``p_a = T_a_b p_b``) from the matcher, (t, r) covariance."""
        self._between("odometry", a, b, T_a_b, covariance, robust=False)

    def add_loop(self, a: Hashable, b: Hashable, T_a_b: np.ndarray, covariance: np.ndarray) -> None:
        """A verified loop or inter-session constraint, robustified with a Cauchy kernel."""
        self._between("loop", a, b, T_a_b, covariance, robust=True)

    def _between(
        self, kind: EdgeKind, a: Hashable, b: Hashable, T_a_b: np.ndarray, cov: np.ndarray, *, robust: bool
    ) -> None:
        g = self._gtsam
        T = _check_pose(T_a_b, f"{kind} {a!r} -> {b!r}")
        noise = g.noiseModel.Gaussian.Covariance(_gtsam_order(_covariance(cov, 6, f"{kind} {a!r} -> {b!r}")))
        if robust:
            # The kernel acts on the whitened residual: its width in sigmas is the width in metres
            # over the loop's largest translation sigma. A width of a few sigmas would treat every
            # drift correction larger than the registration noise (2 cm) as an outlier.
            sigma_m = float(np.sqrt(np.max(np.diag(cov)[:3])))
            kernel = g.noiseModel.mEstimator.Cauchy.Create(self.settings.loop_kernel_m / sigma_m)
            noise = g.noiseModel.Robust.Create(kernel, noise)
            self._loops_pending = True
        self._pending.add(g.BetweenFactorPose3(self._id(a), self._id(b), g.Pose3(T), noise))
        self.edges.append(Edge(kind, a, b))

    def add_gnss(self, key: Hashable, position_xyz: npt.ArrayLike, covariance: np.ndarray) -> None:
        """A GNSS position of the node's sensor origin, in the world frame, Huber kernel."""
        g = self._gtsam
        p = np.asarray(position_xyz, dtype=np.float64).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise InvalidRequestError(f"gnss on {key!r}: a finite xyz position is needed, got {p.shape}")
        noise = g.noiseModel.Gaussian.Covariance(_covariance(covariance, 3, f"gnss on {key!r}"))
        kernel = g.noiseModel.mEstimator.Huber.Create(self.settings.gnss_kernel_width)
        self._pending.add(g.GPSFactor(self._id(key), g.Point3(*p), g.noiseModel.Robust.Create(kernel, noise)))
        self.n_gnss += 1

    def add_prior(
        self, key: Hashable, T_world_sensor: np.ndarray, covariance: np.ndarray, *, robust: bool = False
    ) -> None:
        """A whole-pose prior (GNSS/INS with attitude), (t, r) covariance; ``robust``: with the
        GNSS factors' Huber kernel (a fix can be wrong; a session's anchor is not)."""
        g = self._gtsam
        T = _check_pose(T_world_sensor, f"prior on {key!r}")
        noise = g.noiseModel.Gaussian.Covariance(
            _gtsam_order(_covariance(covariance, 6, f"prior on {key!r}"))
        )
        if robust:
            kernel = g.noiseModel.mEstimator.Huber.Create(self.settings.gnss_kernel_width)
            noise = g.noiseModel.Robust.Create(kernel, noise)
        self._pending.add(g.PriorFactorPose3(self._id(key), g.Pose3(T), noise))
        self.n_gnss += robust  # (a robust prior is a fix)

    def anchor(self, key: Hashable) -> None:
        """A session's anchor on its first keyframe (module docstring): where it is, give or take
        :attr:`PoseGraphSettings.anchor_sigma_m` and the yaw sigma (a gauge, not information),
        level within the tilt sigma."""
        s = self.settings
        tilt, yaw = s.anchor_tilt_sigma_rad**2, s.anchor_yaw_sigma_rad**2
        cov = np.diag([s.anchor_sigma_m**2] * 3 + [tilt, tilt, yaw])
        self.add_prior(key, self._estimate[self._id(key)], cov)

    # ----------------------------------------------------------------- solve
    def optimize(self, extra_iterations: int = 0) -> None:
        """Add the pending nodes and factors to iSAM2 and update the estimate (plus
        ``extra_iterations`` more iSAM2 updates; a batch with a loop gets
        :attr:`PoseGraphSettings.loop_iterations` at least, since a loop can move metres)."""
        self._isam.update(self._pending, self._pending_values)
        if self._loops_pending:
            extra_iterations = max(extra_iterations, self.settings.loop_iterations)
            self._loops_pending = False
        for _ in range(extra_iterations):
            self._isam.update()
        self._pending = self._gtsam.NonlinearFactorGraph()
        self._pending_values = self._gtsam.Values()
        values = self._isam.calculateEstimate()
        for i in list(self._estimate):
            if values.exists(i):
                self._estimate[i] = values.atPose3(i).matrix()

    def pose(self, key: Hashable) -> np.ndarray:
        """The current estimate of node ``key`` (its initial value until optimized)."""
        return self._estimate[self._id(key)].copy()

    def poses(self) -> dict[Hashable, np.ndarray]:
        """Every node's current estimate, by key, in insertion order."""
        return {k: self._estimate[i].copy() for k, i in self._ids.items()}
