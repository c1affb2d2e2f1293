"""The incremental keyframe model of Algorithm 2: points and NDT moments added and removed per keyframe.

The paper's Get rebuilds the fused, density-equalized model and its NDT pyramid at every keyframe;
:class:`KeyframeModel` keeps the same model up to date instead, as KISS-ICP keeps its voxel hash
map: per-voxel sums and counts (centroids without a refill), Algorithm 1 on the voxels a keyframe
touches, a radius bound, finest-level NDT moments with the coarser levels by the parent rule, and
compiled bookkeeping (:func:`randt.core.kernels.model_merge` and friends;
:meth:`KeyframeModel.add_keyframe_numpy` is their numpy reference). Each step against the batch
form, and the equivalence measured: docs/mapping.md, "The keyframe model".

A :class:`KeyframeModel` is immutable: :meth:`KeyframeModel.add_keyframe` returns a new one and
shares nothing it changes, so a matcher state holding it is snapshotted by reference and a sweep
that raises leaves the previous model untouched (all or nothing).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from randt.core.config import RegistrationSettings
from randt.core.errors import InvalidCloudError
from randt.core.kernels import (
    group_int_keys,
    group_moments,
    group_weighted_moments,
    in_marked_cells,
    model_compact,
    model_evict,
    model_merge,
)
from randt.core.registration import PreparedReference, reference_inlier_mask
from randt.core.voxel import VoxelGaussianMap, pack_keys, unpack_keys, voxel_coords, voxel_groups

__all__ = ["KeyframeModel", "VoxelMoments"]


@dataclass(frozen=True, eq=False)
class VoxelMoments:
    """Per-voxel point moments about each voxel's centre, keys ascending.

    Attributes
    ----------
    voxel_size_m : edge of the voxels.
    keys : (F,) int64 packed keys (:func:`randt.core.voxel.pack_keys`), ascending, unique.
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

    def select(self, mask: np.ndarray) -> VoxelMoments:
        """The moments of the voxels where ``mask`` (F,) is true."""
        return VoxelMoments(
            self.voxel_size_m,
            self.keys[mask],
            self.counts[mask],
            np.compress(mask, self.sums, axis=0),
            np.compress(mask, self.scatter, axis=0),
        )

    @staticmethod
    def disjoint_union(a: VoxelMoments, b: VoxelMoments) -> VoxelMoments:
        """The moments of ``a``'s voxels and ``b``'s (no voxel in both), keys ascending."""
        keys = np.concatenate([a.keys, b.keys])
        order = np.argsort(keys, kind="stable")
        return VoxelMoments(
            a.voxel_size_m,
            keys[order],
            np.concatenate([a.counts, b.counts])[order],
            np.concatenate([a.sums, b.sums])[order],
            np.concatenate([a.scatter, b.scatter])[order],
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
    fine : (M,) int64 the packed key of each centroid's finest NDT voxel (as
        :func:`randt.core.voxel.voxel_groups` groups): the cell its moments are in.
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
    fine: np.ndarray
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
            np.zeros(0, dtype=np.int64),
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

        The voxel bookkeeping is compiled (:func:`randt.core.kernels.model_merge`, ``model_evict``,
        ``model_compact``): its cost is a pass over the model's voxels, no sort or search.
        :meth:`add_keyframe_numpy` is the same update in numpy (the tests compare them).
        """
        return self._add(points_world, settings, center_xy, radius_m, max_keyframes, compiled=True)

    def add_keyframe_numpy(
        self,
        points_world: np.ndarray,
        settings: RegistrationSettings,
        *,
        center_xy: tuple[float, float],
        radius_m: float,
        max_keyframes: int,
    ) -> KeyframeModel:
        """:meth:`add_keyframe` with the voxel bookkeeping in numpy (sorted-key merges and
        searches): the reference of the compiled kernels."""
        return self._add(points_world, settings, center_xy, radius_m, max_keyframes, compiled=False)

    def _add(
        self,
        points_world: np.ndarray,
        settings: RegistrationSettings,
        center_xy: tuple[float, float],
        radius_m: float,
        max_keyframes: int,
        *,
        compiled: bool,
    ) -> KeyframeModel:
        """The stages of :meth:`add_keyframe`: the keyframe's voxels, the window's voxels after it
        joined and the oldest left, Algorithm 1 on the finest voxels that changed, their moments."""
        finest = self.moments.voxel_size_m
        kid = self.next_id
        k, p = _keyframe_voxels(points_world, self.voxel_m, center_xy, radius_m)
        window, evicted = _evict(self.window, max_keyframes)
        after = _Voxels.compiled if compiled else _Voxels.numpy
        v = after(self, k, p, kid, evicted, center_xy, float(radius_m) ** 2, finest)
        judged, marks = self._cells_to_judge(v, compiled=compiled)
        verdict, groups = _algorithm1(v, judged, settings, finest)
        return KeyframeModel(
            voxel_m=self.voxel_m,
            keys=v.keys,
            sums=v.sums,
            counts=v.counts,
            born=v.born,
            points_xyz=v.centroid,
            inlier=self._verdicts(v, judged, verdict),
            moments=self._moments_after(v, judged, verdict, groups, marks),
            fine=v.fine,
            window=(*window, (kid, k, p)),
            next_id=kid + 1,
            n_removed_outliers=int(verdict.size - np.count_nonzero(verdict)),
        )

    def _cells_to_judge(self, v: _Voxels, *, compiled: bool) -> tuple[np.ndarray, np.ndarray]:
        """``(judged (m,) bool, marked cells)``: the centroids in the finest voxels (cells) where
        a keyframe's point joined or left a centroid; Algorithm 1 judges them all again, against
        Gaussians of every centroid there (whole cells, so their Gaussians are the window's)."""
        marks = v.fine[v.changed]
        if compiled:
            return in_marked_cells(v.fine, marks), marks
        return np.isin(v.fine, marks), marks

    def _verdicts(self, v: _Voxels, judged: np.ndarray, verdict: np.ndarray) -> np.ndarray:
        """(m,) bool Algorithm 1's verdicts: the new ones where judged, the old ones elsewhere."""
        inlier = np.zeros(v.keys.size, dtype=bool)
        stay = v.old_row >= 0
        inlier[v.old_row[stay]] = self.inlier[stay]
        inlier[judged] = verdict
        return inlier

    def _moments_after(
        self,
        v: _Voxels,
        judged: np.ndarray,
        verdict: np.ndarray,
        groups: tuple[np.ndarray, np.ndarray],
        marks: np.ndarray,
    ) -> VoxelMoments:
        """The inliers' finest-voxel moments: the marked cells' from their judged inliers, the
        other cells' as they were less the inliers that left them (a voxel emptied or cropped:
        the centroids left there keep their verdict)."""
        finest = self.moments.voxel_size_m
        inverse, cells = groups
        xyz = np.compress(judged, v.centroid, axis=0)
        centres = (unpack_keys(cells) + 0.5) * finest
        wsum, sums, scatter = group_weighted_moments(xyz, inverse, centres, verdict.astype(np.float64))
        counts = np.rint(wsum).astype(np.int64)
        has = counts > 0
        fresh = VoxelMoments(
            finest, cells[has], counts[has], np.compress(has, sums, axis=0), np.compress(has, scatter, axis=0)
        )
        stay = v.old_row >= 0
        moved = ~stay
        moved[stay] = v.changed[v.old_row[stay]]
        left = np.flatnonzero(self.inlier & moved & ~in_marked_cells(self.fine, marks))
        gone = VoxelMoments.of_weighted_points(
            np.take(self.points_xyz, left, axis=0), finest, [np.full(left.size, -1.0)]
        )[0]
        kept = self.moments.select(~in_marked_cells(self.moments.keys, marks)).merged(gone, +1)
        return VoxelMoments.disjoint_union(kept, fresh)

    def reference(
        self, settings: RegistrationSettings, voxel_sizes_m: tuple[float, ...]
    ) -> PreparedReference:
        """The model prepared for :func:`randt.core.registration.register` (``reference=``): its points
        and the NDT pyramid at ``voxel_sizes_m`` from the finest moments (from the points when
        the sizes are not the finest times powers of two).

        Raises :class:`~randt.core.errors.InvalidCloudError` when no voxel of a level holds
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


@dataclass(frozen=True, eq=False)
class _Voxels:
    """The model's voxels after a keyframe joined and the oldest left, those that stay, keys
    ascending: their sums, counts, birth, centroids, finest cells (``fine``), whether a
    keyframe's point joined or left them (``changed``), and each old voxel's row (-1: gone)."""

    keys: np.ndarray
    sums: np.ndarray
    counts: np.ndarray
    born: np.ndarray
    centroid: np.ndarray
    fine: np.ndarray
    changed: np.ndarray
    old_row: np.ndarray

    @classmethod
    def compiled(
        cls,
        model: KeyframeModel,
        k: np.ndarray,
        p: np.ndarray,
        kid: int,
        evicted: tuple[tuple[int, np.ndarray, np.ndarray], ...],
        center_xy: tuple[float, float],
        radius2: float,
        finest: float,
    ) -> _Voxels:
        keys, sums, counts, born, changed, at_old = model_merge(
            model.keys, model.sums, model.counts, model.born, k, p, kid
        )
        for eid, ek, ep in evicted:
            model_evict(keys, sums, counts, born, changed, ek, ep, eid)
        cx, cy = center_xy
        keys, sums, counts, born, centroid, fine, changed, row = model_compact(
            keys, sums, counts, born, changed, float(cx), float(cy), radius2, finest
        )
        return cls(keys, sums, counts, born, centroid, fine, changed, row[at_old])

    @classmethod
    def numpy(
        cls,
        model: KeyframeModel,
        k: np.ndarray,
        p: np.ndarray,
        kid: int,
        evicted: tuple[tuple[int, np.ndarray, np.ndarray], ...],
        center_xy: tuple[float, float],
        radius2: float,
        finest: float,
    ) -> _Voxels:
        keys = _union(model.keys, k)
        n = keys.size
        at_old, at_new = np.searchsorted(keys, model.keys), np.searchsorted(keys, k)
        sums, counts, born = np.zeros((n, 3)), np.zeros(n, dtype=np.int64), np.full(n, kid, dtype=np.int64)
        sums[at_old], counts[at_old], born[at_old] = model.sums, model.counts, model.born
        sums[at_new] += p
        counts[at_new] += 1
        changed = np.zeros(n, dtype=bool)
        changed[at_new] = True
        for eid, ek, ep in evicted:  # the oldest keyframe's points leave
            at = np.minimum(np.searchsorted(keys, ek), n - 1)
            ok = np.flatnonzero(keys[at] == ek)
            ok = ok[born[at[ok]] <= eid]
            sums[at[ok]] -= np.take(ep, ok, axis=0)
            counts[at[ok]] -= 1
            changed[at[ok]] = True
        centroid = sums / np.maximum(counts, 1)[:, None]
        keep = (counts > 0) & (_xy_dist2(centroid, *center_xy) <= radius2)
        row = np.full(n, -1, dtype=np.int64)
        row[keep] = np.arange(np.count_nonzero(keep))
        centroid = np.compress(keep, centroid, axis=0)
        fine = pack_keys(np.floor(centroid * (1.0 / finest)).astype(np.int64))
        return cls(
            keys[keep],
            np.compress(keep, sums, axis=0),
            counts[keep],
            born[keep],
            centroid,
            fine,
            changed[keep],
            row[at_old],
        )


def _keyframe_voxels(
    points_world: np.ndarray, voxel_m: float, center_xy: tuple[float, float], radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """``(keys ascending, points)``: the keyframe's model voxels within ``radius_m`` (x-y) of
    ``center_xy`` and its first point in each."""
    pts = np.asarray(points_world, dtype=np.float64)
    near = np.flatnonzero(_xy_dist2(pts, *center_xy) <= float(radius_m) ** 2)
    k, first = _sorted_unique(pack_keys(voxel_coords(np.take(pts, near, axis=0), voxel_m)))
    return k, np.take(pts, near[first], axis=0)


def _evict(
    window: tuple[tuple[int, np.ndarray, np.ndarray], ...], max_keyframes: int
) -> tuple[tuple[tuple[int, np.ndarray, np.ndarray], ...], tuple[tuple[int, np.ndarray, np.ndarray], ...]]:
    """``(window left, keyframes leaving)``: the oldest leave until one more fits."""
    n_out = max(len(window) - max_keyframes + 1, 0)
    return window[n_out:], window[:n_out]


def _algorithm1(
    v: _Voxels, judged: np.ndarray, settings: RegistrationSettings, finest: float
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """``(verdicts, (group of each judged centroid, group cells ascending))``: Algorithm 1 on the
    judged centroids, grouped by their finest cells (all outliers when no cell holds a Gaussian:
    isolated returns)."""
    xyz = np.compress(judged, v.centroid, axis=0)
    order, cells, starts = group_int_keys(v.fine[judged])
    sizes = np.diff(starts)
    by_key = np.argsort(cells)
    rank = np.empty_like(by_key)
    rank[by_key] = np.arange(by_key.size)
    inverse = np.empty(xyz.shape[0], dtype=np.int64)
    inverse[order] = np.repeat(rank, sizes)
    cells, sizes = cells[by_key], sizes[by_key]
    try:
        verdict = reference_inlier_mask(xyz, settings, finest, groups=(inverse, cells, sizes))
    except InvalidCloudError:
        verdict = np.zeros(xyz.shape[0], dtype=bool)
    return verdict, (inverse, cells)


def _sorted_unique(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(keys, return_index=True)`` by one sort: numpy 2's hashed ``np.unique`` is much
    slower on a model's keys."""
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
