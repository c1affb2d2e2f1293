"""Voxel hashing, voxel-grid downsampling and the voxel Gaussian (NDT) map.

Voxel keys are the integer cell coordinates ``floor(p / voxel_size_m)`` packed into one int64
(21 bits per axis, offset so negative cells pack too). Points are grouped by voxel in one hashed
pass (:func:`core.kernels.group_voxels`, 4x faster than sorting the keys with ``np.unique``),
per-voxel sums and 3x3 eigen-decompositions are compiled loops too (:mod:`core.kernels`); map
lookups are ``np.searchsorted`` on the sorted key array. There is no Python loop over points or
voxels.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from core.errors import InvalidCloudError
from core.kernels import eigh3, group_centroids, group_moments, group_voxels

__all__ = [
    "NEIGHBOR_OFFSETS",
    "VoxelGaussianMap",
    "pack_keys",
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
    if n == 27:
        g = np.array([0, -1, 1], dtype=np.int64)
        return np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    raise ValueError(f"neighbour search must use 1, 7 or 27 voxels, got {n}")


#: Cell offsets for the 1-, 7- and 27-voxel neighbourhoods (the centre cell first).
NEIGHBOR_OFFSETS: dict[int, np.ndarray] = {n: _neighbor_offsets(n) for n in (1, 7, 27)}


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
    return (shifted[:, 0] << (2 * _BITS)) | (shifted[:, 1] << _BITS) | shifted[:, 2]


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

    @cached_property
    def hash_table(self) -> tuple[np.ndarray, np.ndarray]:
        """Open-addressing table over :attr:`keys` for the compiled kernels (built on first use)."""
        from core.kernels import build_hash

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
    ) -> tuple[VoxelGaussianMap, np.ndarray]:
        """:meth:`build`, plus each point's voxel index in the map (-1 where its voxel has too
        few points for a Gaussian)."""
        pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
        inverse, keys, counts = voxel_groups(pts, voxel_size_m, sort=True)
        keep = counts >= min_points_per_voxel
        if not np.any(keep):
            raise InvalidCloudError(
                f"no voxel of {voxel_size_m:g} m holds {min_points_per_voxel} points: "
                "the cloud is too sparse for this voxel size"
            )
        _, mean, scatter = group_moments(pts, inverse, keys.size)
        cov = scatter / np.maximum(counts - 1.0, 1.0)[:, None, None]
        new_index = np.cumsum(keep) - 1
        assignment = np.where(keep[inverse], new_index[inverse], -1)

        keys, mean, cov, counts = keys[keep], mean[keep], cov[keep], counts[keep]
        evals, evecs = eigh3(cov)
        floor = np.maximum(evals[:, 2:3] * eigenvalue_ratio, 1e-12)
        evals = np.maximum(evals, floor)
        cov = (evecs * evals[:, None, :]) @ np.swapaxes(evecs, 1, 2)
        inv = (evecs / evals[:, None, :]) @ np.swapaxes(evecs, 1, 2)
        whitening = np.swapaxes(evecs / np.sqrt(evals)[:, None, :], 1, 2)
        gmap = cls(
            voxel_size_m=float(voxel_size_m),
            keys=keys,
            means=mean,
            covariances=cov,
            inv_covariances=inv,
            whitening=whitening,
            normals=np.ascontiguousarray(evecs[:, :, 0]),
            counts=counts.astype(np.int64),
        )
        return gmap, assignment

    def lookup(self, coords: np.ndarray) -> np.ndarray:
        """Voxel indices (N,) of packed cell coordinates, -1 where the cell holds no Gaussian."""
        q = pack_keys(coords)
        idx = np.searchsorted(self.keys, q)
        idx = np.minimum(idx, self.keys.size - 1)
        return np.where(self.keys[idx] == q, idx, -1)

    def neighbors(self, points_xyz: np.ndarray, n_neighbors: int = 7) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (point, voxel) for the 1-, 7- or 27-voxel neighbourhood of each point.

        Returns
        -------
        point_index : (P,) int64 index into ``points_xyz``
        voxel_index : (P,) int64 index into this map's arrays
        """
        base = voxel_coords(points_xyz, self.voxel_size_m)
        offsets = NEIGHBOR_OFFSETS[n_neighbors]
        cells = (base[None, :, :] + offsets[:, None, :]).reshape(-1, 3)
        vidx = self.lookup(cells)
        pidx = np.tile(np.arange(points_xyz.shape[0], dtype=np.int64), offsets.shape[0])
        hit = vidx >= 0
        return pidx[hit], vidx[hit]

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
