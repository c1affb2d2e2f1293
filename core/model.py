"""The incremental keyframe model of Algorithm 2: points and NDT moments added and removed per keyframe.

The paper's Get fuses the window's keyframes into one density-equalized cloud and fits the NDT
pyramid to it. Done in batch that is a full rebuild at every keyframe (every second or third
sweep): the window's ~20 keyframes stacked, cropped, downsampled, Algorithm 1 over the whole
fused cloud and the pyramid fitted from every point, about 120 ms for a KITTI window. Here the
same model is kept up to date instead, as KISS-ICP keeps its voxel hash map:

* **Density equalization** (Algorithm 2): one point per model voxel (``voxel_m``), the centroid
  of the window keyframes' points in it, as the batch form's downsampling of the fused
  keyframes gives. Each voxel keeps the sum and count of its keyframes' points: a keyframe adds
  its points, the evicted oldest subtracts its own (kept by reference in ``window``), so the
  centroids are the window's without a refill.
* **Algorithm 1** (IQR on Mahalanobis distances) judges every centroid in the finest NDT voxels
  a keyframe touches (nearly all of the model near the sensor), against Gaussians fitted to
  every window centroid there, outliers included, with per-voxel quartiles over those
  centroids, as the batch form does over the whole model; centroids elsewhere keep their
  verdict. Outliers keep their voxel and their share of the judging Gaussians but are not
  matched against.
* **Radius bound**: voxels whose centroid lies farther than ``radius_m`` (in x-y) from the
  newest keyframe leave the model for good (KISS-ICP drops its far voxels the same way); the
  batch form crops the window's points at each rebuild, so a voxel 80 m behind could come back
  if the vehicle turned around within the window's 20 keyframes.
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
from core.errors import InvalidCloudError
from core.kernels import group_moments, group_weighted_moments
from core.registration import PreparedReference, reference_inlier_mask
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

    @classmethod
    def of_weighted_points(
        cls, points_xyz: np.ndarray, voxel_size_m: float, weights: list[np.ndarray]
    ) -> list[VoxelMoments]:
        """Moments of ``points_xyz`` (N,3) for each of ``weights`` ((N,) each: +1 a point that
        joins, -1 one that leaves, 0 none), from one grouping; a voxel's entry may have count 0
        (one point left, another came) and still carry sums: :meth:`merged` adds them all.
        Sums are about the voxel centre, so they cancel to round-off when points leave."""
        if points_xyz.shape[0] == 0:
            return [cls.empty(voxel_size_m) for _ in weights]
        pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
        inverse, keys, _ = voxel_groups(pts, voxel_size_m, sort=True)
        centres = (unpack_keys(keys) + 0.5) * voxel_size_m
        out = []
        for w in weights:
            wsum, sums, scatter = group_weighted_moments(
                pts, inverse, centres, np.ascontiguousarray(w, dtype=np.float64)
            )
            out.append(cls(float(voxel_size_m), keys, np.rint(wsum).astype(np.int64), sums, scatter))
        return out

    def merged(self, other: VoxelMoments, sign: int) -> VoxelMoments:
        """These moments plus (``sign`` = 1) or minus (-1) ``other``'s; emptied voxels are dropped.

        Subtracting moments of points that were never added is the caller's error (asserted).
        """
        if other.keys.size == 0:
            return self
        keys = _union(self.keys, other.keys)
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
        return VoxelMoments(
            self.voxel_size_m,
            keys[keep],
            counts[keep],
            np.compress(keep, sums, axis=0),
            np.compress(keep, scatter, axis=0),
        )

    def subset(self, keys: np.ndarray) -> VoxelMoments:
        """The moments of the voxels among ``keys`` (ascending) that hold points here."""
        at = np.minimum(np.searchsorted(self.keys, keys), max(self.keys.size - 1, 0))
        hit = at[self.keys[at] == keys] if self.keys.size else at[:0]
        return VoxelMoments(
            self.voxel_size_m, self.keys[hit], self.counts[hit], self.sums[hit], self.scatter[hit]
        )

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
    keys : (M,) int64 the occupied model voxels' keys, ascending.
    sums : (M,3) float64 sum of the window keyframes' points in each voxel (world frame).
    counts : (M,) int64 how many of the window's keyframes put a point in it.
    born : (M,) int64 the keyframe that (re)created the voxel (an evicted keyframe older than
        that contributed to an earlier, cropped life of the voxel and subtracts nothing).
    points_xyz : (M,3) float64 the voxels' centroids: the model's points, outliers included.
    inlier : (M,) bool Algorithm 1's verdict on each centroid: only inliers are matched.
    moments : the inliers' moments at the finest NDT voxel (the matching model's).
    window : ``(id, keys, points)`` of each keyframe in the window, oldest first (keys unique).
    next_id : the id the next keyframe gets.
    n_removed_outliers : centroids Algorithm 1 judged outliers at the last keyframe.
    """

    voxel_m: float
    keys: np.ndarray
    sums: np.ndarray
    counts: np.ndarray
    born: np.ndarray
    points_xyz: np.ndarray
    inlier: np.ndarray
    moments: VoxelMoments
    window: tuple[tuple[int, np.ndarray, np.ndarray], ...] = ()
    next_id: int = 0
    n_removed_outliers: int = 0

    @classmethod
    def empty(cls, voxel_m: float, finest_ndt_m: float) -> KeyframeModel:
        return cls(
            float(voxel_m),
            np.zeros(0, dtype=np.int64),
            np.zeros((0, 3)),
            np.zeros(0, dtype=np.int64),
            np.zeros(0, dtype=np.int64),
            np.zeros((0, 3)),
            np.zeros(0, dtype=bool),
            VoxelMoments.empty(finest_ndt_m),
        )

    @property
    def ids(self) -> tuple[int, ...]:
        """The keyframes in the window, oldest first."""
        return tuple(kid for kid, _, _ in self.window)

    @property
    def n_points(self) -> int:
        """Points matched against (Algorithm 1's inliers)."""
        return int(np.count_nonzero(self.inlier))

    @property
    def inlier_xyz(self) -> np.ndarray:
        """(n_points, 3) the points matched against."""
        return np.compress(self.inlier, self.points_xyz, axis=0)

    def add_keyframe(
        self,
        points_world: np.ndarray,
        settings: RegistrationSettings,
        *,
        center_xy: tuple[float, float],
        radius_m: float,
        max_keyframes: int,
    ) -> KeyframeModel:
        """The model with one more keyframe (returns a new model; this one is not changed).

        Parameters
        ----------
        points_world : (N,3) the keyframe's points in the world frame, density-equalized at
            ``voxel_m`` (one per model voxel; extra ones in a voxel are ignored).
        settings : the reference's outlier removal (``outlier_removal``, Algorithm 1's fences).
        center_xy : the new keyframe's position; points beyond ``radius_m`` of it (x-y) leave.
        max_keyframes : window length; the oldest keyframe leaves when it is full.

        Raises :class:`~core.errors.InvalidCloudError` when Algorithm 1 finds no voxel with a
        Gaussian (a window too sparse to model).
        """
        finest = self.moments.voxel_size_m
        cx, cy = center_xy
        r2 = float(radius_m) ** 2
        pts = np.asarray(points_world, dtype=np.float64)
        near = np.flatnonzero(_xy_dist2(pts, cx, cy) <= r2)
        k, first = _sorted_unique(pack_keys(voxel_coords(np.take(pts, near, axis=0), self.voxel_m)))
        p = np.take(pts, near[first], axis=0)
        kid = self.next_id
        # Every voxel before and after, the keyframe's points summed in.
        keys = _union(self.keys, k)
        n = keys.size
        at_old, at_new = np.searchsorted(keys, self.keys), np.searchsorted(keys, k)
        sums, counts, born = np.zeros((n, 3)), np.zeros(n, dtype=np.int64), np.full(n, kid, dtype=np.int64)
        sums[at_old], counts[at_old], born[at_old] = self.sums, self.counts, self.born
        sums[at_new] += p
        counts[at_new] += 1
        changed = np.zeros(n, dtype=bool)
        changed[at_new] = True
        window = self.window
        while len(window) >= max_keyframes:  # the oldest keyframe's points leave
            eid, ek, ep = window[0]
            window = window[1:]
            at = np.minimum(np.searchsorted(keys, ek), n - 1)
            ok = np.flatnonzero(keys[at] == ek)
            ok = ok[born[at[ok]] <= eid]
            sums[at[ok]] -= np.take(ep, ok, axis=0)
            counts[at[ok]] -= 1
            changed[at[ok]] = True
        centroid = sums / np.maximum(counts, 1)[:, None]
        keep = (counts > 0) & (_xy_dist2(centroid, cx, cy) <= r2)
        changed &= keep
        old_gone = ~keep[at_old] | changed[at_old]  # old centroids that moved or left
        # Algorithm 1 on every centroid in the finest voxels the change touched: whole voxels,
        # so their own Gaussians are the window's there.
        fine = pack_keys(voxel_coords(centroid, finest))
        touched = _sorted_unique(np.compress(changed, fine))[0]
        at = np.minimum(np.searchsorted(touched, fine), max(touched.size - 1, 0))
        judged = keep & (touched[at] == fine) if touched.size else np.zeros(n, dtype=bool)
        judged_xyz = np.compress(judged, centroid, axis=0)
        try:
            verdict = reference_inlier_mask(judged_xyz, settings, finest)
        except InvalidCloudError:  # no voxel holds a Gaussian: all isolated returns, outliers
            verdict = np.zeros(judged_xyz.shape[0], dtype=bool)
        inlier = np.zeros(n, dtype=bool)
        inlier[at_old] = self.inlier
        inlier[judged] = verdict
        # The matched (inlier) moments: old inliers that moved, left or were judged again out,
        # the judged inliers in.
        out_mask = (old_gone | judged[at_old]) & self.inlier
        out_in = np.compress(out_mask, self.points_xyz, axis=0)
        new_in = np.compress(judged & inlier, centroid, axis=0)
        delta_in = VoxelMoments.of_weighted_points(
            np.concatenate([out_in, new_in]),
            finest,
            [np.concatenate([np.full(out_in.shape[0], -1.0), np.ones(new_in.shape[0])])],
        )[0]
        return KeyframeModel(
            voxel_m=self.voxel_m,
            keys=keys[keep],
            sums=np.compress(keep, sums, axis=0),
            counts=counts[keep],
            born=born[keep],
            points_xyz=np.compress(keep, centroid, axis=0),
            inlier=inlier[keep],
            moments=self.moments.merged(delta_in, +1),
            window=(*window, (kid, k, p)),
            next_id=kid + 1,
            n_removed_outliers=int(verdict.size - np.count_nonzero(verdict)),
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
        if self.moments.keys.size == 0:
            raise InvalidCloudError("keyframe model: Algorithm 1 left no point (the window is too sparse)")
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
                self.inlier_xyz, voxel_sizes_m, min_points_per_voxel=n_min, eigenvalue_ratio=ratio
            )
        n_all = int(self.points_xyz.shape[0])
        return PreparedReference(self.inlier_xyz, maps, n_all, n_all - self.n_points)


def _sorted_unique(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(keys, return_index=True)`` by one sort: numpy 2's hashed ``np.unique`` took
    17 ms for 130k int64 keys on the simulated drive, most of a keyframe's update."""
    order = np.argsort(keys, kind="stable")
    s = keys[order]
    first = np.ones(s.size, dtype=bool)
    first[1:] = s[1:] != s[:-1]
    return s[first], order[first]


def _union(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The sorted union of two ascending unique key arrays (the merge of two sorted runs: a
    stable sort of their concatenation is a linear merge)."""
    merged = np.sort(np.concatenate([a, b]), kind="stable")
    keep = np.ones(merged.size, dtype=bool)
    keep[1:] = merged[1:] != merged[:-1]
    return merged[keep]


def _xy_dist2(points_xyz: np.ndarray, cx: float, cy: float) -> np.ndarray:
    """Squared x-y distance of each point from ``(cx, cy)``."""
    dx = points_xyz[:, 0] - cx
    dy = points_xyz[:, 1] - cy
    d2: np.ndarray = dx * dx + dy * dy
    return d2
