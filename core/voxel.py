"""Voxel hashing, voxel-grid downsampling and the voxel Gaussian (NDT) map.

Voxel keys are the integer cell coordinates ``floor(p / voxel_size_m)`` packed into one int64
(21 bits per axis, offset so negative cells pack too). Points are grouped by voxel in one hashed
pass (:func:`randt.core.kernels.group_voxels`, instead of sorting the keys with ``np.unique``),
per-voxel sums and 3x3 eigen-decompositions are compiled loops too (:mod:`randt.core.kernels`); map
lookups are ``np.searchsorted`` on the sorted key array. There is no Python loop over points or
voxels.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from randt.core.errors import InvalidCloudError
from randt.core.kernels import (
    cell_shift,
    conditioned_gaussians,
    eigh3,
    group_centroids,
    group_moments,
    group_voxels,
    parent_moments,
)

__all__ = [
    "NEIGHBOR_OFFSETS",
    "VoxelGaussianMap",
    "merge_moments",
    "pack_keys",
    "stratified_subsample",
    "unpack_keys",
    "voxel_coords",
    "voxel_downsample",
    "voxel_groups",
]

_BITS = 21
_OFFSET = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def _neighbor_offsets(n: int) -> np.ndarray:
    if n == 1:
        return np.zeros((1, 3), dtype=np.int64)
    if n == 7:
        return np.array(
            [[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
            dtype=np.int64,
        )
    if n == 8:
        g = np.array([0, 1], dtype=np.int64)
        return np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    if n == 27:
        g = np.array([0, -1, 1], dtype=np.int64)
        return np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    raise ValueError(f"neighbour search must use 1, 7, 8 or 27 voxels, got {n}")


#: Cell offsets for the 1-, 7-, 8- and 27-voxel neighbourhoods, from the base cell
#: (:func:`neighborhood_base`; the point's own cell first for 1, 7 and 27).
NEIGHBOR_OFFSETS: dict[int, np.ndarray] = {n: _neighbor_offsets(n) for n in (1, 7, 8, 27)}


def trilinear_weights(points_xyz: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """(8, N) the weight of each of a point's 8 enclosing voxels (:data:`NEIGHBOR_OFFSETS` [8]
    order), 8 times its trilinear interpolation weight so that the 8 sum to 8.

    Unweighted, a point's 8 voxels switch at once when it crosses a cell's centre plane, and the
    NDT cost jumps there: a ripple one voxel long, which pinned poses on walls and ground lined
    up with the grid (docs/registration.md, "NDT"). Weighted, a voxel leaves the sum at weight 0:
    the cost is continuous (Magnusson 2009, trilinear NDT).
    """
    scaled = np.asarray(points_xyz, dtype=np.float64) / voxel_size_m - cell_shift(8)
    f = scaled - np.floor(scaled)  # (N,3) in [0,1): from the base cell's centre
    offsets = NEIGHBOR_OFFSETS[8]
    per_axis = np.where(offsets[:, None, :] == 1, f[None, :, :], 1.0 - f[None, :, :])  # (8,N,3)
    weights: np.ndarray = 8.0 * per_axis.prod(axis=2)
    return weights


def neighborhood_base(points_xyz: np.ndarray, voxel_size_m: float, n_neighbors: int) -> np.ndarray:
    """(N,3) int64 base cell of each point's neighbourhood (:data:`NEIGHBOR_OFFSETS` are added).

    For 1, 7 and 27 voxels the point's own cell. The 8-voxel neighbourhood is the 2x2x2 voxels
    whose centres enclose the point (the cell of ``p / v - 1/2`` and the next one along each
    axis): every point sees the Gaussians on both sides of the nearest cell boundary in each
    axis, where the 7-voxel one (own cell and its 6 faces) sees 5 on its own side of a boundary it
    lies near and one across. A flat ground on a boundary (the simulated town's z = 0) then pulls
    the matched height by the imbalance, which the 8 do not (docs/registration.md, "NDT").
    :func:`randt.core.kernels.cell_shift` is the same rule for the compiled kernels. The 8 are weighted
    trilinearly (:func:`trilinear_weights`).
    """
    shift = cell_shift(n_neighbors)
    if shift == 0.0:
        return voxel_coords(points_xyz, voxel_size_m)
    scaled = np.asarray(points_xyz, dtype=np.float64) / voxel_size_m
    coords: np.ndarray = np.floor(scaled - shift).astype(np.int64)
    return coords


def voxel_coords(points_xyz: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Integer cell coordinates (N,3) int64 of each point."""
    return np.floor(points_xyz / voxel_size_m).astype(np.int64)


def pack_keys(coords: np.ndarray) -> np.ndarray:
    """Pack (N,3) int64 cell coordinates into (N,) int64 keys (21 bits per axis)."""
    shifted = coords + _OFFSET
    if shifted.size and (shifted.min() < 0 or shifted.max() > _MASK):
        raise InvalidCloudError(
            f"points span more than {_MASK} voxels along an axis; use a larger voxel size"
        )
    keys: np.ndarray = (shifted[:, 0] << (2 * _BITS)) | (shifted[:, 1] << _BITS) | shifted[:, 2]
    return keys


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """Cell coordinates (N,3) int64 of packed keys (the inverse of :func:`pack_keys`)."""
    keys = np.asarray(keys, dtype=np.int64)
    shifted = np.stack([keys >> (2 * _BITS), (keys >> _BITS) & _MASK, keys & _MASK], axis=1)
    return shifted - _OFFSET


def voxel_groups(
    points_xyz: np.ndarray, voxel_size_m: float, *, sort: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Group points by voxel: ``(inverse, keys, counts)``.

    ``inverse[i]`` is point i's group; ``keys`` are the groups' packed keys and ``counts`` their
    sizes, in first-seen order, or in ascending key order with ``sort`` (what ``np.unique`` gives).
    """
    pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
    inverse, keys, counts, _, _, ok = group_voxels(pts, float(voxel_size_m))
    if not ok:
        raise InvalidCloudError(
            f"points span more than {_MASK} voxels of {voxel_size_m:g} m along an axis (or are "
            "non-finite); use a larger voxel size"
        )
    if sort:
        order = np.argsort(keys, kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        inverse, keys, counts = rank[inverse], keys[order], counts[order]
    return inverse, keys, counts


def voxel_downsample(points_xyz: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Replace the points of each occupied voxel by their centroid.

    Parameters
    ----------
    points_xyz : (N,3) float64
    voxel_size_m : edge length of the cubic voxels, metres.

    Returns
    -------
    (M,3) float64 centroids, M <= N, in the order the voxels are first met in ``points_xyz``.
    """
    pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
    inverse, keys, _ = voxel_groups(pts, voxel_size_m)
    return group_centroids(pts, inverse, keys.size)


def stratified_subsample(points_xyz: np.ndarray, max_points: int, cell_m: float) -> np.ndarray:
    """``max_points`` of ``points_xyz`` spread over space as the points are: a systematic sample
    along the points sorted by ``cell_m`` cell (each cell's points together, in a fixed
    pseudo-random order), so every cell gives its share, within one point, of what it holds.
    The sample keeps the cloud's spatial distribution with less variance than a random one
    (no region is left out by chance) and the statistics of the whole (a cap per cell instead
    over-weights sparse, far cells, whose inlier ratio is lower: on the simulated drive the
    matcher's inlier gate then refused good matches). Deterministic; all points when there are
    at most ``max_points``.

    Returns
    -------
    (M,3) the chosen rows of ``points_xyz``, in their input order (M = min(N, max_points)).
    """
    n = points_xyz.shape[0]
    if n <= max_points:
        return points_xyz
    inverse, _, _ = voxel_groups(points_xyz, cell_m)
    at = np.arange(n)
    scramble = _SCRAMBLE[at % _SCRAMBLE.size] + (at // _SCRAMBLE.size) * _SCRAMBLE.size
    order = np.lexsort((scramble, inverse))
    step = n / max_points
    chosen = np.sort(order[((np.arange(max_points) + 0.5) * step).astype(np.int64)])
    return np.take(points_xyz, chosen, axis=0)


#: A fixed permutation: the order in which :func:`stratified_subsample` takes a cell's points.
_SCRAMBLE = np.random.default_rng(20261126).permutation(1 << 16)


@dataclass(frozen=True)
class VoxelGaussianMap:
    """Per-voxel Gaussians of a reference cloud: the NDT representation (Magnusson 2009, ch. 6).

    Attributes
    ----------
    voxel_size_m : edge length of the voxels.
    keys : (M,) int64 packed voxel keys, sorted ascending.
    means : (M,3) float64 voxel means.
    covariances : (M,3,3) float64 conditioned covariances.
    inv_covariances : (M,3,3) float64 their inverses.
    whitening : (M,3,3) float64 ``W`` with ``W^T W = Sigma^-1``: ``|W x|^2`` is the squared
        Mahalanobis distance, and ``W`` turns the NDT Hessian into plain matrix products.
    normals : (M,3) float64 eigenvector of the smallest eigenvalue (surface normal estimate).
    counts : (M,) int64 points per voxel.
    """

    voxel_size_m: float
    keys: np.ndarray
    means: np.ndarray
    covariances: np.ndarray
    inv_covariances: np.ndarray
    whitening: np.ndarray
    normals: np.ndarray
    counts: np.ndarray

    @property
    def n_voxels(self) -> int:
        return int(self.keys.size)

    def contains(self, points_xyz: np.ndarray) -> np.ndarray:
        """(N,) bool: the point falls in a voxel of this map (one that holds a Gaussian)."""
        from randt.core.kernels import in_voxels

        pts = np.ascontiguousarray(points_xyz, dtype=np.float64).reshape(-1, 3)
        out = np.zeros(pts.shape[0], dtype=bool)
        if pts.shape[0] and self.keys.size:
            in_voxels(pts, self.voxel_size_m, *self.hash_table, out)
        return out

    @cached_property
    def hash_table(self) -> tuple[np.ndarray, np.ndarray]:
        """Open-addressing table over :attr:`keys` for the compiled kernels (built on first use)."""
        from randt.core.kernels import build_hash

        return build_hash(self.keys)

    @classmethod
    def build(
        cls,
        points_xyz: np.ndarray,
        voxel_size_m: float,
        *,
        min_points_per_voxel: int = 6,
        eigenvalue_ratio: float = 0.01,
    ) -> VoxelGaussianMap:
        """Fit one Gaussian per voxel holding at least ``min_points_per_voxel`` points.

        Covariances are conditioned as in Magnusson (2009) eq. 6.11: eigenvalues smaller than
        ``eigenvalue_ratio`` times the largest are raised to that value, so flat or linear voxels
        stay invertible without losing their orientation.
        """
        gmap, _ = cls.build_with_assignment(
            points_xyz,
            voxel_size_m,
            min_points_per_voxel=min_points_per_voxel,
            eigenvalue_ratio=eigenvalue_ratio,
        )
        return gmap

    @classmethod
    def build_with_assignment(
        cls,
        points_xyz: np.ndarray,
        voxel_size_m: float,
        *,
        min_points_per_voxel: int = 6,
        eigenvalue_ratio: float = 0.01,
        groups: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> tuple[VoxelGaussianMap, np.ndarray]:
        """:meth:`build`, plus each point's voxel index in the map (-1 where its voxel has too
        few points for a Gaussian). ``groups``: the points' grouping ``(inverse, keys ascending,
        counts)`` when the caller has it (:func:`voxel_groups` with ``sort``)."""
        pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
        inverse, keys, counts = voxel_groups(pts, voxel_size_m, sort=True) if groups is None else groups
        _, mean, scatter = group_moments(pts, inverse, keys.size)
        keep = counts >= min_points_per_voxel
        gmap = cls._from_moments(
            voxel_size_m, keys, counts, mean, scatter, min_points_per_voxel, eigenvalue_ratio
        )
        new_index = np.cumsum(keep) - 1
        assignment = np.where(keep[inverse], new_index[inverse], -1)
        return gmap, assignment

    @classmethod
    def build_pyramid(
        cls,
        points_xyz: np.ndarray,
        voxel_sizes_m: tuple[float, ...],
        *,
        min_points_per_voxel: int = 6,
        eigenvalue_ratio: float = 0.01,
    ) -> tuple[VoxelGaussianMap, ...]:
        """:meth:`build` at each of ``voxel_sizes_m``, in that order, with one pass over the points.

        When every size is the finest times a power of two (the NDT pyramid's (16r, ..., r)),
        voxels nest: a voxel of 2v is exactly the union of 8 voxels of v. The points are then
        grouped and their moments summed once, at the finest size, and each coarser level sums
        its children's counts, means and scatter matrices (the parallel-axis rule, about the
        parent's centre for accuracy): the same Gaussians as building each level from the
        points (tested to 1e-9), from a few tens of thousands of voxels instead of every point.
        Other size sets build each level from the points.
        """
        sizes = tuple(float(v) for v in voxel_sizes_m)
        finest = min(sizes)
        powers = [round(np.log2(v / finest)) for v in sizes]
        if not all(abs(v - finest * 2.0**k) <= 1e-9 * v for v, k in zip(sizes, powers, strict=True)):
            return tuple(
                cls.build(
                    points_xyz,
                    v,
                    min_points_per_voxel=min_points_per_voxel,
                    eigenvalue_ratio=eigenvalue_ratio,
                )
                for v in sizes
            )
        pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
        inverse, keys, _ = voxel_groups(pts, finest)
        counts, mean, scatter = group_moments(pts, inverse, keys.size)
        return cls.pyramid_from_moments(
            (keys, counts, mean, scatter),
            finest,
            sizes,
            min_points_per_voxel=min_points_per_voxel,
            eigenvalue_ratio=eigenvalue_ratio,
        )

    @classmethod
    def pyramid_from_moments(
        cls,
        moments: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
        finest_m: float,
        voxel_sizes_m: tuple[float, ...],
        *,
        min_points_per_voxel: int = 6,
        eigenvalue_ratio: float = 0.01,
    ) -> tuple[VoxelGaussianMap, ...]:
        """The maps at ``voxel_sizes_m`` (each ``finest_m`` times a power of two) from the finest
        voxels' ``(keys, counts, means, scatter matrices about the means)`` (any key order): the
        coarser levels by the parent rule (:func:`_parent_moments`), as :meth:`build_pyramid`."""
        sizes = tuple(float(v) for v in voxel_sizes_m)
        powers = [round(np.log2(v / finest_m)) for v in sizes]
        pairs = zip(sizes, powers, strict=True)
        nested = [k >= 0 and abs(v - finest_m * 2.0**k) <= 1e-9 * v for v, k in pairs]
        if not all(nested):
            raise ValueError(f"voxel sizes {sizes} are not {finest_m:g} m times powers of two")
        keys, counts, mean, scatter = moments
        finest = finest_m
        by_power = {0: (keys, counts, mean, scatter)}
        v = finest
        for k in range(1, max(powers) + 1):
            keys, counts, mean, scatter = _parent_moments(keys, counts, mean, scatter, v)
            v *= 2.0
            by_power[k] = (keys, counts, mean, scatter)
        levels = []
        for v, k in zip(sizes, powers, strict=True):
            keys, counts, mean, scatter = by_power[k]
            order = np.argsort(keys)
            levels.append(
                cls._from_moments(
                    v,
                    keys[order],
                    counts[order],
                    mean[order],
                    scatter[order],
                    min_points_per_voxel,
                    eigenvalue_ratio,
                )
            )
        return tuple(levels)

    @classmethod
    def _from_moments(
        cls,
        voxel_size_m: float,
        keys: np.ndarray,
        counts: np.ndarray,
        mean: np.ndarray,
        scatter: np.ndarray,
        min_points_per_voxel: int,
        eigenvalue_ratio: float,
    ) -> VoxelGaussianMap:
        """The map of the voxels (keys ascending) holding at least ``min_points_per_voxel``
        points, from their counts, means and scatter matrices (:meth:`build`'s conditioning)."""
        keep = counts >= min_points_per_voxel
        if not np.any(keep):
            raise InvalidCloudError(
                f"no voxel of {voxel_size_m:g} m holds {min_points_per_voxel} points: "
                "the cloud is too sparse for this voxel size"
            )
        keys, counts = keys[keep], counts[keep]
        mean = np.compress(keep, mean, axis=0)  # np.compress: a boolean index of (M,3) is much slower
        cov, inv, whitening, normals = conditioned_gaussians(
            np.ascontiguousarray(np.compress(keep, scatter, axis=0), dtype=np.float64),
            counts.astype(np.float64),
            float(eigenvalue_ratio),
        )
        return cls(
            voxel_size_m=float(voxel_size_m),
            keys=keys,
            means=mean,
            covariances=cov,
            inv_covariances=inv,
            whitening=whitening,
            normals=normals,
            counts=counts.astype(np.int64),
        )

    @staticmethod
    def _from_moments_numpy(
        scatter: np.ndarray, counts: np.ndarray, eigenvalue_ratio: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(cov, inv, whitening, normals)`` of voxels with these scatter matrices and counts,
        vectorized: the reference of :func:`randt.core.kernels.conditioned_gaussians` (the tests)."""
        cov = scatter / np.maximum(counts - 1.0, 1.0)[:, None, None]
        evals, evecs = eigh3(cov)
        floor = np.maximum(evals[:, 2:3] * eigenvalue_ratio, 1e-12)
        evals = np.maximum(evals, floor)
        cov = (evecs * evals[:, None, :]) @ np.swapaxes(evecs, 1, 2)
        inv = (evecs / evals[:, None, :]) @ np.swapaxes(evecs, 1, 2)
        whitening = np.swapaxes(evecs / np.sqrt(evals)[:, None, :], 1, 2)
        return cov, inv, whitening, np.ascontiguousarray(evecs[:, :, 0])

    def lookup(self, coords: np.ndarray) -> np.ndarray:
        """Voxel indices (N,) of packed cell coordinates, -1 where the cell holds no Gaussian."""
        q = pack_keys(coords)
        idx = np.searchsorted(self.keys, q)
        idx = np.minimum(idx, self.keys.size - 1)
        return np.where(self.keys[idx] == q, idx, -1)

    def neighbors(self, points_xyz: np.ndarray, n_neighbors: int = 7) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (point, voxel) for the 1-, 7-, 8- or 27-voxel neighbourhood of each point
        (:func:`neighborhood_base`).

        Returns
        -------
        point_index : (P,) int64 index into ``points_xyz``
        voxel_index : (P,) int64 index into this map's arrays
        """
        pidx, vidx, _ = self.neighbor_pairs(points_xyz, n_neighbors)
        return pidx, vidx

    def neighbor_pairs(
        self, points_xyz: np.ndarray, n_neighbors: int = 7
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`neighbors` and each pair's weight in the NDT cost: 1, or for the 8 enclosing
        voxels :func:`trilinear_weights`."""
        base = neighborhood_base(points_xyz, self.voxel_size_m, n_neighbors)
        offsets = NEIGHBOR_OFFSETS[n_neighbors]
        cells = (base[None, :, :] + offsets[:, None, :]).reshape(-1, 3)
        vidx = self.lookup(cells)
        pidx = np.tile(np.arange(points_xyz.shape[0], dtype=np.int64), offsets.shape[0])
        if n_neighbors == 8:
            weight = trilinear_weights(points_xyz, self.voxel_size_m).reshape(-1)
        else:
            weight = np.ones(vidx.shape[0])
        hit = vidx >= 0
        return pidx[hit], vidx[hit], weight[hit]

    def subset(self, mask: np.ndarray) -> VoxelGaussianMap:
        """A map holding only the voxels where ``mask`` is true."""
        return VoxelGaussianMap(
            voxel_size_m=self.voxel_size_m,
            keys=self.keys[mask],
            means=self.means[mask],
            covariances=self.covariances[mask],
            inv_covariances=self.inv_covariances[mask],
            whitening=self.whitening[mask],
            normals=self.normals[mask],
            counts=self.counts[mask],
        )


def merge_moments(
    keys: np.ndarray, counts: np.ndarray, mean: np.ndarray, scatter: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Voxel moments ``(keys, counts, means, scatter matrices about the means)`` with each key once:
    the rows of a key that occurs more than once (the same voxel from two parts of a cloud, e.g.
    two map tiles) combined as the moments of their points together, ``S = sum(S_r + n_r d_r d_r^T)``
    with ``d_r`` a row's mean about the combined mean; keys ascending. Rows with unique keys come
    back as they are (sorted)."""
    order = np.argsort(keys, kind="stable")
    k = keys[order]
    first = np.ones(k.shape[0], dtype=bool)
    first[1:] = k[1:] != k[:-1]
    n = counts[order]
    m = np.ascontiguousarray(mean[order], dtype=np.float64)
    S = np.ascontiguousarray(scatter[order], dtype=np.float64)
    if first.all():
        return k, n, m, S
    start = np.flatnonzero(first)
    group = np.cumsum(first) - 1
    w = n.astype(np.float64)
    n_g = np.add.reduceat(w, start)
    mean_g = np.add.reduceat(w[:, None] * m, start) / n_g[:, None]
    d = m - mean_g[group]
    S_g = np.add.reduceat(S + w[:, None, None] * (d[:, :, None] * d[:, None, :]), start)
    return k[start], np.add.reduceat(n, start), mean_g, S_g


def _parent_moments(
    keys: np.ndarray, counts: np.ndarray, mean: np.ndarray, scatter: np.ndarray, voxel_size_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Counts, means and scatter matrices of the voxels of twice ``voxel_size_m`` from those of
    their children (keys, counts, means, scatters at ``voxel_size_m``), in first-seen order.

    A child's centre lies a quarter parent voxel inside its parent, so grouping the centres at
    twice the size finds each child's parent without rounding doubt. Sums are taken about the
    parent's centre: ``S = sum(S_c + n_c d_c d_c^T) - n e e^T``, with ``d_c`` the child mean and
    ``e`` the parent mean relative to it.
    """
    parent_size = 2.0 * voxel_size_m
    centers = (unpack_keys(keys) + 0.5) * voxel_size_m
    inverse, parent_keys, _ = voxel_groups(centers, parent_size)
    parent_center = (unpack_keys(parent_keys) + 0.5) * parent_size
    n_p, mean_p, scatter_p = parent_moments(
        inverse,
        parent_center,
        counts,
        np.ascontiguousarray(mean, dtype=np.float64),
        np.ascontiguousarray(scatter, dtype=np.float64),
    )
    return parent_keys, n_p, mean_p, scatter_p


def _parent_moments_numpy(
    keys: np.ndarray, counts: np.ndarray, mean: np.ndarray, scatter: np.ndarray, voxel_size_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_parent_moments` by ``np.bincount``: the reference of
    :func:`randt.core.kernels.parent_moments` (the tests)."""
    parent_size = 2.0 * voxel_size_m
    centers = (unpack_keys(keys) + 0.5) * voxel_size_m
    inverse, parent_keys, _ = voxel_groups(centers, parent_size)
    m = parent_keys.size
    n = counts.astype(np.float64)
    parent_center = (unpack_keys(parent_keys) + 0.5) * parent_size
    d = mean - parent_center[inverse]
    n_p = np.bincount(inverse, weights=n, minlength=m)
    e: np.ndarray = np.stack(
        [np.bincount(inverse, weights=n * d[:, a], minlength=m) for a in range(3)], axis=1
    )
    e /= n_p[:, None]
    s = scatter + n[:, None, None] * (d[:, :, None] * d[:, None, :])
    flat = s.reshape(-1, 9)
    parent_scatter = np.stack(
        [np.bincount(inverse, weights=flat[:, c], minlength=m) for c in range(9)], axis=1
    ).reshape(m, 3, 3)
    parent_scatter -= n_p[:, None, None] * (e[:, :, None] * e[:, None, :])
    return parent_keys, n_p.astype(np.int64), parent_center + e, parent_scatter
