"""Settings of the core algorithms as small pydantic models (one per stage, composed).

Core functions take explicit keyword arguments; these models are how the CLI, the service and
the benchmarks carry a validated set of them. ``randt config`` prints the defaults.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["FAST_SVD_STEP", "Method", "RegistrationSettings"]

Method = Literal["randt", "ndt", "icp-point", "icp-plane"]


#: Overrides for the faster, less accurate SVD step
#: (``RegistrationSettings.for_method("randt", **FAST_SVD_STEP)``, ``randt register --fast-svd``):
#: the step on the NDT solver's own points (the reference after the IQR filter, the moving
#: cloud's Algorithm 1 survivors at 0.5 of the finest voxel), 16-neighbour normals, looser fences,
#: stopping below 0.1 mm / 1e-5 rad (docs/registration.md, "Algorithm 3": the step as it was, and
#: what the default gains over it).
FAST_SVD_STEP: dict[str, float | bool | None] = {
    "svd_normal_neighbors": 16,
    "svd_residual_fence_k": 2.5,
    "svd_fence_k": 6.0,
    "svd_on_filtered_points": True,
    "svd_source_voxel_fraction": None,
    "svd_translation_eps_m": 1e-4,
    "svd_rotation_eps_rad": 1e-5,
}


class RegistrationSettings(BaseModel):
    """How :func:`randt.core.registration.register` aligns two clouds.

    Voxel sizes left ``None`` are derived from the target's spatial scale (see
    :func:`randt.core.registration.auto_voxel_sizes`), so the same defaults serve a 15 cm bunny and a
    120 m LiDAR sweep.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    method: Method = "randt"
    voxel_sizes_m: tuple[float, ...] | None = Field(
        default=None,
        description="NDT voxel sizes, coarse to fine; None derives them from the cloud",
    )
    source_voxel_fraction: float = Field(
        default=0.5, gt=0, le=2, description="source downsampling voxel / finest NDT voxel"
    )
    target_voxel_fraction: float = Field(
        default=0.25, gt=0, le=1, description="target pre-downsampling voxel / finest NDT voxel"
    )
    min_points_per_voxel: int = Field(default=6, ge=3)
    eigenvalue_ratio: float = Field(default=0.01, gt=0, lt=1, description="Magnusson eq. 6.11")
    outlier_ratio: float = Field(default=0.55, gt=0, lt=1, description="NDT mixture outlier ratio")
    n_neighbors: Literal[1, 7, 8, 27] = 7
    max_iterations: int = Field(default=30, ge=1, description="Newton iterations per level")
    translation_eps_m: float = Field(default=1e-4, gt=0)
    rotation_eps_rad: float = Field(default=1e-5, gt=0)
    outlier_removal: Literal["iqr", "sor", "none"] = Field(
        default="iqr", description="reference outlier removal: the paper's IQR rule, SOR, or none"
    )
    iqr_k: float = Field(default=1.5, gt=0, description="Tukey fence multiplier")
    iqr_min_points_for_voxel_quartiles: int = Field(default=10, ge=4)
    select_moving_points: bool = Field(
        default=True, description="drop low-probability moving points before matching (Alg. 1)"
    )
    svd_refinement: bool = Field(default=True, description="the paper's Algorithm 3 step")
    svd_correspondences: Literal["nearest", "voxel"] = Field(
        default="nearest",
        description="Algorithm 3's partners: the nearest reference point's local plane (KD-tree), "
        "or the most probable finest-level voxel's plane (faster, less accurate: docs/registration.md)",
    )
    svd_normal_neighbors: int = Field(
        default=10, ge=3, description="reference points per local plane of the SVD step's partners"
    )
    svd_iterations: int = Field(default=30, ge=1)
    svd_translation_eps_m: float = Field(default=3e-4, gt=0, description="SVD step stops below this")
    svd_rotation_eps_rad: float = Field(default=3e-5, gt=0)
    svd_fence_k: float = Field(
        default=3.0, gt=0, description="Tukey multiplier on SVD correspondence distances"
    )
    svd_residual_fence_k: float | None = Field(
        default=2.0,
        gt=0,
        description="Tukey multiplier on the SVD step's point-to-plane residuals at each search "
        "(None: no residual fence, only the distance fence)",
    )
    svd_max_rmse_rise: float = Field(
        default=0.02,
        ge=0,
        description="the SVD step is kept unless it raises the trimmed point-to-plane RMSE by more "
        "than this fraction (0: it must lower it)",
    )
    svd_on_filtered_points: bool = Field(
        default=False,
        description="the SVD step on the IQR-filtered reference and Algorithm 1's moving "
        "selection, as the NDT solver (FAST_SVD_STEP); False: on both clouds downsampled before "
        "those filters, its own distance and residual fences trimming the pairs",
    )
    svd_source_voxel_fraction: float | None = Field(
        default=0.4,
        gt=0,
        le=2,
        description="the SVD step's moving points downsampled at this x the finest NDT voxel "
        "(None: at source_voxel_fraction, as the NDT solver's)",
    )
    max_match_points: int | None = Field(
        default=None,
        ge=100,
        description="Newton's iterations on at most about this many of the moving points, a spatially "
        "stratified subsample (randt.core.voxel.stratified_subsample: the same count from every cell of "
        "match_cell_voxels finest voxels); None: every moving point",
    )
    match_cell_voxels: float = Field(
        default=2.0, gt=0, description="the subsample's cells, in finest NDT voxels (max_match_points)"
    )
    degeneracy_threshold: float = Field(
        default=1e-3, gt=0, lt=1, description="min/max eigenvalue ratio of the plane information"
    )
    min_points: int = Field(default=10, ge=3, description="fewer finite points is an invalid cloud")

    @model_validator(mode="after")
    def _check_levels(self) -> RegistrationSettings:
        if self.voxel_sizes_m is not None:
            if not self.voxel_sizes_m or any(v <= 0 for v in self.voxel_sizes_m):
                raise ValueError("voxel_sizes_m must be non-empty and positive")
            if list(self.voxel_sizes_m) != sorted(self.voxel_sizes_m, reverse=True):
                raise ValueError("voxel_sizes_m must go from coarse to fine (descending)")
        return self

    @classmethod
    def for_method(cls, method: Method, **overrides: object) -> RegistrationSettings:
        """Defaults for a method: classic NDT switches off outlier removal and the SVD step."""
        base: dict[str, Any] = {"method": method}
        if method != "randt":
            base.update(outlier_removal="none", select_moving_points=False, svd_refinement=False)
        base.update(overrides)
        return cls(**base)
