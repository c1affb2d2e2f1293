"""Voxel hashing, voxel-grid downsampling and the voxel Gaussian (NDT) map.

Voxel keys are the integer cell coordinates ``floor(p / voxel_size_m)`` packed into one int64
(21 bits per axis, offset so negative cells pack too). Every operation here is vectorized: cells
are grouped with ``np.unique`` and summed with ``np.bincount``; lookups are ``np.searchsorted`` on
the sorted key array. There is no Python loop over points or voxels.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from core.errors import InvalidCloudError

__all__ = [
    "NEIGHBOR_OFFSETS",
    "VoxelGaussianMap",
    "pack_keys",
    "voxel_coords",
    "voxel_downsample",
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


def voxel_downsample(points_xyz: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Replace the points of each occupied voxel by their centroid.

    Parameters
    ----------
    points_xyz : (N,3) float64
    voxel_size_m : edge length of the cubic voxels, metres.

    Returns
    -------
    (M,3) float64 centroids, M <= N, in ascending voxel-key order.
    """
    keys = pack_keys(voxel_coords(points_xyz, voxel_size_m))
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    sums = np.stack(
        [np.bincount(inverse, weights=points_xyz[:, k], minlength=counts.size) for k in range(3)],
        axis=1,
    )
    return sums / counts[:, None]


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
        keys_all = pack_keys(voxel_coords(points_xyz, voxel_size_m))
        uniq, inverse, counts = np.unique(keys_all, return_inverse=True, return_counts=True)
        keep = counts >= min_points_per_voxel
        if not np.any(keep):
            raise InvalidCloudError(
                f"no voxel of {voxel_size_m:g} m holds {min_points_per_voxel} points: "
                "the cloud is too sparse for this voxel size"
            )
        n = uniq.size
        x, y, z = points_xyz[:, 0], points_xyz[:, 1], points_xyz[:, 2]

        def bsum(w: np.ndarray) -> np.ndarray:
            return np.bincount(inverse, weights=w, minlength=n)

        c = counts.astype(np.float64)
        mean = np.stack([bsum(x), bsum(y), bsum(z)], axis=1) / c[:, None]
        # Second moments around the voxel means (two passes for numerical accuracy).
        d = points_xyz - mean[inverse]
        dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
        sxx, syy, szz = bsum(dx * dx), bsum(dy * dy), bsum(dz * dz)
        sxy, sxz, syz = bsum(dx * dy), bsum(dx * dz), bsum(dy * dz)
        cov = np.empty((n, 3, 3))
        cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2] = sxx, syy, szz
        cov[:, 0, 1] = cov[:, 1, 0] = sxy
        cov[:, 0, 2] = cov[:, 2, 0] = sxz
        cov[:, 1, 2] = cov[:, 2, 1] = syz
        cov /= np.maximum(c - 1.0, 1.0)[:, None, None]

        uniq, mean, cov, counts = uniq[keep], mean[keep], cov[keep], counts[keep]
        evals, evecs = np.linalg.eigh(cov)
        floor = np.maximum(evals[:, 2:3] * eigenvalue_ratio, 1e-12)
        evals = np.maximum(evals, floor)
        cov = (evecs * evals[:, None, :]) @ np.swapaxes(evecs, 1, 2)
        inv = (evecs / evals[:, None, :]) @ np.swapaxes(evecs, 1, 2)
        whitening = np.swapaxes(evecs / np.sqrt(evals)[:, None, :], 1, 2)
        return cls(
            voxel_size_m=float(voxel_size_m),
            keys=uniq,
            means=mean,
            covariances=cov,
            inv_covariances=inv,
            whitening=whitening,
            normals=evecs[:, :, 0],
            counts=counts.astype(np.int64),
        )

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
