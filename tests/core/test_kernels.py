"""The compiled kernels (core/kernels.py) against their vectorized numpy references, on real scans."""

from __future__ import annotations

import numpy as np
import pytest

from core import kernels
from core.io import read_cloud
from core.ndt import (
    ndt_constants,
    ndt_cost,
    ndt_cost_numpy,
    ndt_derivatives,
    ndt_derivatives_numpy,
    ndt_point_scores,
    ndt_point_scores_numpy,
)
from core.transforms import make_transform
from core.voxel import NEIGHBOR_OFFSETS, VoxelGaussianMap, pack_keys, voxel_coords, voxel_downsample
from tests.data import require_data


@pytest.fixture(scope="module")
def kitti_problem():
    d = require_data("kitti00/velodyne/000000.bin") / "kitti00/velodyne"
    target = read_cloud(d / "000000.bin").xyz.astype(np.float64)
    source = voxel_downsample(read_cloud(d / "000001.bin").xyz.astype(np.float64), 0.5)
    gmap = VoxelGaussianMap.build(voxel_downsample(target, 0.25), 1.0)
    T = make_transform(euler_deg=(0.3, -0.2, 1.5), translation=(0.8, 0.1, -0.05))
    return source, gmap, ndt_constants(1.0), T


@pytest.mark.parametrize("n_neighbors", [1, 7, 27])
def test_derivatives_kernel_matches_numpy(kitti_problem, n_neighbors: int) -> None:
    source, gmap, consts, T = kitti_problem
    fast = ndt_derivatives(source, T, gmap, consts, n_neighbors)
    ref = ndt_derivatives_numpy(source, T, gmap, consts, n_neighbors)
    assert fast.n_pairs == ref.n_pairs > 1000
    assert fast.cost == pytest.approx(ref.cost, rel=1e-12)
    np.testing.assert_allclose(fast.gradient, ref.gradient, rtol=1e-9, atol=1e-9 * np.abs(ref.gradient).max())
    for a, b in ((fast.hessian, ref.hessian), (fast.gauss_newton_hessian, ref.gauss_newton_hessian)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * np.abs(b).max())
        np.testing.assert_array_equal(a, a.T)
    assert ndt_cost(source, T, gmap, consts, n_neighbors) == pytest.approx(
        ndt_cost_numpy(source, T, gmap, consts, n_neighbors), rel=1e-12
    )


def test_point_scores_kernel_matches_numpy(kitti_problem) -> None:
    source, gmap, consts, T = kitti_problem
    fast = ndt_point_scores(source, T, gmap, consts)
    ref = ndt_point_scores_numpy(source, T, gmap, consts)
    for a, b in zip(fast, ref, strict=True):
        np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
        ok = np.isfinite(b)
        np.testing.assert_allclose(a[ok], b[ok], rtol=1e-10, atol=1e-12)
    assert np.isfinite(ref[2]).sum() > 1000  # most points have a voxel near


def test_hash_table_finds_every_key_and_no_other(kitti_problem) -> None:
    _, gmap, _, _ = kitti_problem
    table_key, table_idx = gmap.hash_table
    assert table_key.size >= 2 * gmap.n_voxels  # at most half full
    # Every stored key maps back to its index; cells next to occupied ones mostly miss.
    cells = voxel_coords(gmap.means, gmap.voxel_size_m)
    probe = np.concatenate([cells, cells + [0, 0, 5], cells + [7, -3, 0]])
    keys = pack_keys(probe)
    at = np.minimum(np.searchsorted(gmap.keys, keys), gmap.n_voxels - 1)
    expected = np.where(gmap.keys[at] == keys, at, -1)
    vox, m = np.empty(len(probe), dtype=np.int64), np.empty(len(probe))
    # best_voxel with the single-cell neighbourhood is a plain lookup (the point is the voxel mean).
    pts = (probe + 0.5) * gmap.voxel_size_m
    kernels.best_voxel(
        pts, np.eye(3), np.zeros(3), table_key, table_idx, gmap.means, gmap.inv_covariances,
        gmap.voxel_size_m, NEIGHBOR_OFFSETS[1], vox, m,
    )  # fmt: skip
    np.testing.assert_array_equal(vox, expected)
    assert (expected[: len(cells)] >= 0).all()
