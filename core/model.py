"""The incremental keyframe model of Algorithm 2: points and NDT moments added and removed per keyframe.

The paper's Get fuses the window's keyframes into one density-equalized cloud and fits the NDT
pyramid to it. Done in batch that is a full rebuild at every keyframe (every second or third
sweep): the window's ~20 keyframes stacked, cropped, downsampled, Algorithm 1 over the whole
fused cloud and the pyramid fitted from every point, about 120 ms for a KITTI window. Here the
same model is kept up to date instead, as KISS-ICP keeps its voxel hash map:

* **Density equalization** (Algorithm 2): one point per model voxel (``voxel_m``), the newest
  keyframe's point winning its voxel. Evicting the oldest keyframe then removes exactly the
  voxels no newer keyframe covers, with nothing to refill.
* **Algorithm 1** (IQR on Mahalanobis distances) judges each keyframe's points once, as they
  join, with the keyframe's own Gaussians at the finest NDT voxel; outliers never enter.
* **Radius bound**: points farther than ``radius_m`` (in x-y) from the newest keyframe leave the
  model for good (KISS-ICP drops its far voxels the same way).
* **NDT moments**: per finest NDT voxel the count, the sum and the scatter of the points about
  the voxel's centre (small numbers, so adding and subtracting them stays exact to round-off),
  in key-sorted arrays merged with ``searchsorted``; the coarser levels follow by the parent rule
  of :meth:`core.voxel.VoxelGaussianMap.pyramid_from_moments`.

A :class:`KeyframeModel` is immutable: :meth:`KeyframeModel.add_keyframe` returns a new one and
shares nothing it changes, so a matcher state holding it is snapshotted by reference and a sweep
that raises leaves the previous model untouched (all or nothing).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.config import RegistrationSettings
from core.kernels import group_moments
from core.registration import PreparedReference
from core.voxel import VoxelGaussianMap, pack_keys, unpack_keys, voxel_coords, voxel_groups

__all__ = ["KeyframeModel", "VoxelMoments"]


@dataclass(frozen=True, eq=False)
class VoxelMoments:
    """Per-voxel point moments about each voxel's centre, keys ascending.

    Attributes
    ----------
    voxel_size_m : edge of the voxels.
    keys : (F,) int64 packed keys (:func:`core.voxel.pack_keys`), ascending, unique.
    counts : (F,) int64 points per voxel (all > 0).
    sums : (F,3) float64 sum of ``p - c`` (``c`` the voxel's centre).
    scatter : (F,3,3) float64 sum of ``(p - c)(p - c)^T``.
    """

    voxel_size_m: float
    keys: np.ndarray
    counts: np.ndarray
    sums: np.ndarray
    scatter: np.ndarray

    @classmethod
    def empty(cls, voxel_size_m: float) -> VoxelMoments:
        return cls(
            float(voxel_size_m),
            np.zeros(0, dtype=np.int64),
            np.zeros(0, dtype=np.int64),
            np.zeros((0, 3)),
            np.zeros((0, 3, 3)),
        )

    @classmethod
    def of_points(cls, points_xyz: np.ndarray, voxel_size_m: float) -> VoxelMoments:
        """The moments of ``points_xyz`` (N,3) grouped at ``voxel_size_m``."""
        if points_xyz.shape[0] == 0:
            return cls.empty(voxel_size_m)
        pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
        inverse, keys, _ = voxel_groups(pts, voxel_size_m)
        counts, mean, scatter = group_moments(pts, inverse, keys.size)
        d = mean - (unpack_keys(keys) + 0.5) * voxel_size_m
        n = counts.astype(np.float64)
        sums = n[:, None] * d
        about_centre = scatter + n[:, None, None] * (d[:, :, None] * d[:, None, :])
        order = np.argsort(keys)
        return cls(float(voxel_size_m), keys[order], counts[order], sums[order], about_centre[order])

    def merged(self, other: VoxelMoments, sign: int) -> VoxelMoments:
        """These moments plus (``sign`` = 1) or minus (-1) ``other``'s; emptied voxels are dropped.

        Subtracting moments of points that were never added is the caller's error (asserted).
        """
        if other.keys.size == 0:
            return self
        keys = np.union1d(self.keys, other.keys)
        a, b = np.searchsorted(keys, self.keys), np.searchsorted(keys, other.keys)
        counts = np.zeros(keys.size, dtype=np.int64)
        sums = np.zeros((keys.size, 3))
        scatter = np.zeros((keys.size, 3, 3))
        counts[a], sums[a], scatter[a] = self.counts, self.sums, self.scatter
        counts[b] += sign * other.counts
        sums[b] += sign * other.sums
        scatter[b] += sign * other.scatter
        assert counts.min(initial=0) >= 0, "removed points that were never added"
        keep = counts > 0
        return VoxelMoments(self.voxel_size_m, keys[keep], counts[keep], sums[keep], scatter[keep])

    def gaussian_moments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(keys, counts, means, scatter about the means)``: what the NDT fit takes."""
        n = self.counts.astype(np.float64)
        d = self.sums / n[:, None]
        mean = (unpack_keys(self.keys) + 0.5) * self.voxel_size_m + d
        scatter = self.scatter - n[:, None, None] * (d[:, :, None] * d[:, None, :])
        return self.keys, self.counts, mean, scatter


@dataclass(frozen=True, eq=False)
class KeyframeModel:
    """The density-equalized keyframe model (module docstring), immutable.

    Attributes
    ----------
    voxel_m : the model voxel: one point per voxel of this size.
    points_xyz : (M,3) float64 the model's points, world frame.
    keys : (M,) int64 their model-voxel keys (unique).
    tags : (M,) int64 the keyframe each point came from (ids count from 0 per session).
    moments : the points' moments at the finest NDT voxel.
    ids : the keyframes in the window, oldest first.
    next_id : the id the next keyframe gets.
    n_removed_outliers : points Algorithm 1 removed from the last keyframe added.
    """

    voxel_m: float
    points_xyz: np.ndarray
    keys: np.ndarray
    tags: np.ndarray
    moments: VoxelMoments
    ids: tuple[int, ...] = ()
    next_id: int = 0
    n_removed_outliers: int = 0

    @classmethod
    def empty(cls, voxel_m: float, finest_ndt_m: float) -> KeyframeModel:
        return cls(
            float(voxel_m),
            np.zeros((0, 3)),
            np.zeros(0, dtype=np.int64),
            np.zeros(0, dtype=np.int64),
            VoxelMoments.empty(finest_ndt_m),
        )

    @property
    def n_points(self) -> int:
        return int(self.points_xyz.shape[0])

    def add_keyframe(
        self,
        points_world: np.ndarray,
        inliers: np.ndarray,
        *,
        center_xy: tuple[float, float],
        radius_m: float,
        max_keyframes: int,
    ) -> KeyframeModel:
        """The model with one more keyframe (returns a new model; this one is not changed).

        Parameters
        ----------
        points_world : (N,3) the keyframe's points in the world frame, density-equalized at
            ``voxel_m`` (at most one per model voxel; extra ones in a voxel are ignored).
        inliers : (N,) bool Algorithm 1's verdict on them: only inliers join.
        center_xy : the new keyframe's position; points beyond ``radius_m`` of it (x-y) leave.
        max_keyframes : window length; the oldest keyframe leaves when it is full.
        """
        new = np.ascontiguousarray(points_world[inliers], dtype=np.float64)
        cx, cy = center_xy
        r2 = float(radius_m) ** 2
        new = new[_xy_dist2(new, cx, cy) <= r2]
        new_keys = pack_keys(voxel_coords(new, self.voxel_m))
        new_keys, first = np.unique(new_keys, return_index=True)
        new = new[first]
        ids = self.ids
        leave = np.zeros(self.keys.size, dtype=bool)
        if len(ids) >= max_keyframes:
            evicted = ids[: len(ids) - max_keyframes + 1]
            leave |= np.isin(self.tags, np.asarray(evicted, dtype=np.int64))
            ids = ids[len(evicted) :]
        if new_keys.size and self.keys.size:
            at = np.minimum(np.searchsorted(new_keys, self.keys), new_keys.size - 1)
            leave |= new_keys[at] == self.keys  # the newest keyframe wins its voxels
        leave |= _xy_dist2(self.points_xyz, cx, cy) > r2
        stay = ~leave
        finest = self.moments.voxel_size_m
        moments = self.moments.merged(VoxelMoments.of_points(self.points_xyz[leave], finest), -1)
        moments = moments.merged(VoxelMoments.of_points(new, finest), +1)
        return KeyframeModel(
            voxel_m=self.voxel_m,
            points_xyz=np.concatenate([self.points_xyz[stay], new]),
            keys=np.concatenate([self.keys[stay], new_keys]),
            tags=np.concatenate([self.tags[stay], np.full(new_keys.size, self.next_id, dtype=np.int64)]),
            moments=moments,
            ids=(*ids, self.next_id),
            next_id=self.next_id + 1,
            n_removed_outliers=int(inliers.size - np.count_nonzero(inliers)),
        )

    def reference(
        self, settings: RegistrationSettings, voxel_sizes_m: tuple[float, ...]
    ) -> PreparedReference:
        """The model prepared for :func:`core.registration.register` (``reference=``): its points
        and the NDT pyramid at ``voxel_sizes_m`` from the finest moments (from the points when
        the sizes are not the finest times powers of two).

        Raises :class:`~core.errors.InvalidCloudError` when no voxel of a level holds
        ``min_points_per_voxel`` points.
        """
        finest = self.moments.voxel_size_m
        n_min, ratio = settings.min_points_per_voxel, settings.eigenvalue_ratio
        try:
            maps = VoxelGaussianMap.pyramid_from_moments(
                self.moments.gaussian_moments(),
                finest,
                voxel_sizes_m,
                min_points_per_voxel=n_min,
                eigenvalue_ratio=ratio,
            )
        except ValueError:
            maps = VoxelGaussianMap.build_pyramid(
                self.points_xyz, voxel_sizes_m, min_points_per_voxel=n_min, eigenvalue_ratio=ratio
            )
        n = self.n_points
        return PreparedReference(self.points_xyz, maps, n + self.n_removed_outliers, self.n_removed_outliers)


def _xy_dist2(points_xyz: np.ndarray, cx: float, cy: float) -> np.ndarray:
    """Squared x-y distance of each point from ``(cx, cy)``."""
    dx = points_xyz[:, 0] - cx
    dy = points_xyz[:, 1] - cy
    d2: np.ndarray = dx * dx + dy * dy
    return d2
