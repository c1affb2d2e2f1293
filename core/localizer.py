"""Localization on a fixed map: a sweep matched against the map's points around the vehicle.

Where a street is mapped, a sweep needs no keyframe model of its own: :class:`MapLocalizer`
matches a few thousand of its points (a stratified subsample) against an NDT model built once
from the map's points within :attr:`LocalizerSettings.window_radius_m` of the vehicle, and built
again once the vehicle has moved :attr:`LocalizerSettings.reload_m` from the window's centre
(Autoware's ``ndt_scan_matcher`` and its dynamic map loading do the same, 1,500 points against the
tiles within 150 m, reloaded every 20 m). Nothing is learned from the sweep: no model update, no
drift. The answer carries the registration's covariance and its inlier ratio, the score that says
how well the sweep agrees with the map (docs/mapping.md, "Localizing on the map").

Stages of :meth:`MapLocalizer.localize`::

    window  -> the prepared map around the prior (the caller loads it: :meth:`MapLocalizer.load`)
    match   -> NDT from the prior (coarse levels skipped when the prior is a motion prediction)
    retry   -> a weak match from a far prior (a GNSS fix): again from the prior turned by each of
               ``retry_yaw_deg``, the best kept
    judge   -> agrees (inlier ratio at least ``min_inlier_ratio``) or not; never the prior passed
               off as a pose
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from randt.core.config import RegistrationSettings
from randt.core.errors import DegenerateProblemError, InvalidCloudError, RegistrationFailedError
from randt.core.registration import PreparedReference, RegistrationResult, prepare_reference, register
from randt.core.transforms import as_transform, yawed

__all__ = ["Localized", "LocalizerSettings", "MapLocalizer", "MapWindow"]


class LocalizerSettings(BaseModel):
    """How a sweep is localized on the map (module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    voxel_sizes_m: tuple[float, ...] = Field(
        default=(4.0, 2.0, 1.0), description="NDT levels, coarse to fine (the service's from map_voxel_m)"
    )
    window_radius_m: float = Field(default=80.0, gt=0, description="map points loaded around the vehicle")
    reload_m: float = Field(default=20.0, gt=0, description="travel from the window's centre before a reload")
    max_match_points: int = Field(default=3000, ge=100, description="sweep points matched (stratified)")
    min_map_points: int = Field(
        default=20000, ge=1, description="fewer map points in the window: the map is missing here"
    )
    min_inlier_ratio: float = Field(
        default=0.6, gt=0, lt=1, description="a sweep agrees with the map from this share of inliers"
    )
    retry_yaw_deg: tuple[float, ...] = Field(
        default=(-10.0, 10.0, -20.0, 20.0), description="yaw offsets tried when a far prior matched weakly"
    )
    fine_levels_from: int = Field(
        default=1, ge=0, description="with a predicted prior, the coarsest level index matched"
    )

    svd_refinement: bool = Field(default=True, description="the paper's SVD step after NDT")

    def registration(self) -> RegistrationSettings:
        return RegistrationSettings(
            voxel_sizes_m=self.voxel_sizes_m,
            max_match_points=self.max_match_points,
            svd_refinement=self.svd_refinement,
        )


@dataclass(frozen=True)
class MapWindow:
    """The map's points around one place, prepared for NDT: where (``center_xy``), from what
    (``token``: the map's identity and content when it was loaded) and how many points."""

    center_xy: np.ndarray
    token: object
    reference: PreparedReference
    n_points: int


@dataclass(frozen=True)
class Localized:
    """One sweep localized on the map.

    ``agrees``: the inlier ratio reached ``min_inlier_ratio`` (else the pose is the best the map
    gave and must not be answered as good); ``result``: the registration itself (pose, covariance,
    inlier ratio, fitness); ``retried``: the yaw offsets tried after a weak first match."""

    T_map_sensor: np.ndarray
    agrees: bool
    result: RegistrationResult
    retried: int = 0

    @property
    def covariance(self) -> np.ndarray:
        return self.result.covariance

    @property
    def score(self) -> float:
        """The share of the matched points that agree with the map (its inlier ratio)."""
        return self.result.inlier_ratio


class MapLocalizer:
    """Localizes sweeps on the map's points around the vehicle (module docstring)."""

    def __init__(self, settings: LocalizerSettings | None = None) -> None:
        self.settings = settings or LocalizerSettings()
        self._registration = self.settings.registration()
        self.window: MapWindow | None = None

    def needs_window(self, T_prior: np.ndarray, token: object) -> bool:
        """No window yet, another map or content (``token``), or the prior has moved
        ``reload_m`` from the window's centre."""
        w = self.window
        if w is None or w.token != token:
            return True
        return bool(np.linalg.norm(np.asarray(T_prior)[:2, 3] - w.center_xy) > self.settings.reload_m)

    def load(self, center_xy: np.ndarray, map_xyz: np.ndarray, token: object) -> MapWindow | None:
        """Prepare the map's points around ``center_xy`` (those within ``window_radius_m``);
        ``None`` (and no window) when fewer than ``min_map_points``: the map is missing here."""
        center = np.asarray(center_xy, dtype=np.float64)[:2]
        xyz = np.asarray(map_xyz, dtype=np.float64).reshape(-1, 3)
        near = xyz[np.sum((xyz[:, :2] - center) ** 2, axis=1) <= self.settings.window_radius_m**2]
        if near.shape[0] < self.settings.min_map_points:
            self.window = None
            return None
        reference = prepare_reference(near, self._registration, self.settings.voxel_sizes_m)
        self.window = MapWindow(center.copy(), token, reference, int(near.shape[0]))
        return self.window

    def localize(self, sweep_xyz: np.ndarray, T_prior: np.ndarray, *, predicted: bool) -> Localized:
        """The sweep (sensor frame) on the loaded window from ``T_prior`` (map frame).
        ``predicted``: the prior is the motion prediction of a localized session (within a
        fraction of a coarse voxel: the coarse levels are skipped); else a far prior (a GNSS fix,
        a relocalization), matched from the coarsest level, with the yaw retries.

        Raises
        ------
        InvalidCloudError
            No window is loaded, or the sweep is empty or malformed.
        RegistrationFailedError
            The solver found no overlap at all.
        """
        if self.window is None:
            raise InvalidCloudError("no map window is loaded around the vehicle")
        T0 = as_transform(T_prior, name="T_prior")
        levels = self.settings.voxel_sizes_m
        coarsest = levels[min(self.settings.fine_levels_from, len(levels) - 1)] if predicted else None
        if predicted:
            best: RegistrationResult | None = self._match(sweep_xyz, T0, coarsest)
        else:
            best = self._far_match(sweep_xyz, T0, None)
        retried = 0
        if not predicted and (best is None or best.inlier_ratio < self.settings.min_inlier_ratio):
            for yaw in self.settings.retry_yaw_deg:
                retried += 1
                other = self._far_match(sweep_xyz, yawed(T0, yaw), None)
                if other is not None and (best is None or other.inlier_ratio > best.inlier_ratio):
                    best = other
                if best is not None and best.inlier_ratio >= self.settings.min_inlier_ratio:
                    break
        if best is None:
            raise RegistrationFailedError(
                f"the sweep does not overlap the map around the prior (tried {1 + retried} headings)"
            )
        agrees = best.inlier_ratio >= self.settings.min_inlier_ratio
        return Localized(best.T_target_source, agrees, best, retried)

    def _far_match(
        self, sweep_xyz: np.ndarray, T0: np.ndarray, coarsest: float | None
    ) -> RegistrationResult | None:
        """A match from a far prior, or None where the sweep found nothing of the map to match
        (too few of its points near the map's voxels, or no overlap)."""
        try:
            return self._match(sweep_xyz, T0, coarsest)
        except (InvalidCloudError, RegistrationFailedError, DegenerateProblemError):
            return None

    def _match(self, sweep_xyz: np.ndarray, T0: np.ndarray, coarsest: float | None) -> RegistrationResult:
        assert self.window is not None
        return register(
            sweep_xyz,
            None,
            T0,
            settings=self._registration,
            reference=self.window.reference,
            coarsest_voxel_m=coarsest,
        )
