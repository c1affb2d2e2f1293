"""The compiled kernels (core/kernels.py) against their numpy references on real scans; the pivoted
Newton parametrization and registration far from the frame origin."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from randt.core import kernels
from randt.core.io import read_cloud
from randt.core.ndt import (
    apply_update_about,
    ndt_constants,
    ndt_cost,
    ndt_cost_numpy,
    ndt_derivatives,
    ndt_derivatives_numpy,
    ndt_point_derivatives,
    ndt_point_derivatives_numpy,
    ndt_point_scores,
    ndt_point_scores_numpy,
)
from randt.core.registration import register
from randt.core.transforms import invert, make_transform, transform_error, transform_points
from randt.core.voxel import (
    NEIGHBOR_OFFSETS,
    VoxelGaussianMap,
    pack_keys,
    unpack_keys,
    voxel_coords,
    voxel_downsample,
    voxel_groups,
)
from tests.data import require_data


@pytest.fixture(scope="module")
def kitti_problem():
    d = require_data("kitti00/velodyne/000000.bin") / "kitti00/velodyne"
    target = read_cloud(d / "000000.bin").xyz.astype(np.float64)
    source = voxel_downsample(read_cloud(d / "000001.bin").xyz.astype(np.float64), 0.5)
    gmap = VoxelGaussianMap.build(voxel_downsample(target, 0.25), 1.0)
    T = make_transform(euler_deg=(0.3, -0.2, 1.5), translation=(0.8, 0.1, -0.05))
    return source, gmap, ndt_constants(1.0), T


@pytest.mark.parametrize("n_neighbors", [1, 7, 8, 27])
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


@pytest.mark.parametrize("n_neighbors", [7, 8])
def test_point_scores_kernel_matches_numpy(kitti_problem, n_neighbors: int) -> None:
    source, gmap, consts, T = kitti_problem
    fast = ndt_point_scores(source, T, gmap, consts, n_neighbors)
    ref = ndt_point_scores_numpy(source, T, gmap, consts, n_neighbors)
    for a, b in zip(fast, ref, strict=True):
        np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
        ok = np.isfinite(b)
        np.testing.assert_allclose(a[ok], b[ok], rtol=1e-10, atol=1e-12)
    assert np.isfinite(ref[2]).sum() > 1000  # most points have a voxel near


@pytest.mark.parametrize("n_neighbors", [7, 8])
def test_point_derivatives_kernel_matches_numpy(kitti_problem, n_neighbors: int) -> None:
    """Per point, the gradient and Hessian w.r.t. the moved point match the numpy reference, and
    chained by the pose's Jacobian they give :func:`ndt_derivatives`' gradient (its Hessian less
    the rotation's second-order term)."""
    source, gmap, consts, T = kitti_problem
    fast = ndt_point_derivatives(source, T, gmap, consts, n_neighbors)
    ref = ndt_point_derivatives_numpy(source, T, gmap, consts, n_neighbors)
    assert fast.cost == pytest.approx(ref.cost, rel=1e-10)
    np.testing.assert_allclose(fast.gradient, ref.gradient, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fast.hessian, ref.hessian, rtol=1e-9, atol=1e-12)
    assert (np.abs(ref.gradient).sum(axis=1) > 0).sum() > 1000  # most points have a pair
    q = transform_points(T, source)
    J = np.zeros((len(q), 3, 6))
    J[:, :, :3] = np.eye(3)
    J[:, :, 3:] = -np.array([[np.zeros(len(q)), -q[:, 2], q[:, 1]], [q[:, 2], np.zeros(len(q)), -q[:, 0]],
                             [-q[:, 1], q[:, 0], np.zeros(len(q))]]).transpose(2, 0, 1)  # fmt: skip
    pose = ndt_derivatives(source, T, gmap, consts, n_neighbors)
    np.testing.assert_allclose(np.einsum("nij,ni->j", J, fast.gradient), pose.gradient, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(
        np.einsum("nki,nkl,nlj->ij", J, fast.hessian, J)[:3], pose.hessian[:3], rtol=1e-8, atol=1e-8
    )


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


def test_in_voxels_is_the_sorted_lookup(kitti_problem) -> None:
    """A point is in the map's voxels exactly where the sorted keys hold its cell (voxel centres,
    cells beside them, points far outside the keys' range)."""
    _, gmap, _, _ = kitti_problem
    cells = voxel_coords(gmap.means, gmap.voxel_size_m)
    probe = np.concatenate([cells, cells + [0, 0, 1], cells + [3, -2, 0]])
    pts = np.concatenate([(probe + 0.5) * gmap.voxel_size_m, [[1e9, 0.0, 0.0], [-1e9, 5.0, 2.0]]])
    keys = pack_keys(probe)
    at = np.minimum(np.searchsorted(gmap.keys, keys), gmap.n_voxels - 1)
    expected = np.concatenate([gmap.keys[at] == keys, [False, False]])
    got = np.empty(len(pts), dtype=bool)
    kernels.in_voxels(pts, gmap.voxel_size_m, *gmap.hash_table, got)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(gmap.contains(pts), expected)
    assert expected[: len(cells)].all() and not expected[len(cells) :].all()


def test_pivoted_derivatives_match_numpy_and_finite_differences(kitti_problem) -> None:
    """Derivatives w.r.t. a rotation about a pivot (the Newton solver's parametrization)."""
    source, gmap, consts, T = kitti_problem
    pivot = transform_points(T, source).mean(axis=0)
    fast = ndt_derivatives(source, T, gmap, consts, 7, pivot)
    ref = ndt_derivatives_numpy(source, T, gmap, consts, 7, pivot)
    np.testing.assert_allclose(fast.gradient, ref.gradient, rtol=1e-9, atol=1e-9 * np.abs(ref.gradient).max())
    np.testing.assert_allclose(fast.hessian, ref.hessian, rtol=1e-9, atol=1e-9 * np.abs(ref.hessian).max())
    # Central differences along the pivoted perturbation. The cost jumps where a point crosses a
    # voxel boundary, so use steps small enough that (almost) no point does.
    h = 1e-7
    fd = np.array(
        [
            (
                ndt_cost(source, apply_update_about(h * e, T, pivot), gmap, consts)
                - ndt_cost(source, apply_update_about(-h * e, T, pivot), gmap, consts)
            )
            / (2 * h)
            for e in np.eye(6)
        ]
    )
    np.testing.assert_allclose(fast.gradient, fd, rtol=1e-4, atol=1e-5 * np.abs(fd).max())


def test_registration_far_from_the_origin_recovers_yaw() -> None:
    """Hundreds of metres from the target frame's origin (a long drive, a georeferenced map) a yaw
    error must still be recovered: rotations are taken about the moving points, not the origin.

    Regression: two simulated sweeps 1.2 m apart, the pair moved 300 m from the origin, started 4
    degrees off in yaw. With rotations about the origin the Newton solver stalled 1.2-1.9 m and
    4.2-4.4 degrees off (inlier ratio 0.4); at the origin the same pair converged to 1 mm.
    """
    from randt.sim.drive import Route, simulate
    from randt.sim.town import Town

    town = Town.generate(1)
    route = Route.loop(town, 3, length_m=1000.0)
    a, b = simulate(town, route, n_scans=2, speed_mps=12.0, seed=1)
    W = make_transform(euler_deg=(0.0, 0.0, 20.0), translation=(220.0, -210.0, 0.0))
    Tb = W @ invert(a.T_world_sensor) @ b.T_world_sensor  # sweep b in a frame where a sits at W
    target = transform_points(W, a.points_xyz.astype(np.float64))
    for yaw in (-4.0, 4.0):
        init = Tb @ make_transform(euler_deg=(0.0, 0.0, yaw))
        result = register(b.points_xyz.astype(np.float64), target, init)
        err_m, err_deg = transform_error(result.T_target_source, Tb)
        assert err_m < 0.01 and err_deg < 0.02, f"yaw {yaw}: {err_m:.3f} m {err_deg:.3f} deg off"
        assert result.inlier_ratio > 0.7


@pytest.fixture(scope="module")
def kitti_clouds():
    d = require_data("kitti00/velodyne/000000.bin") / "kitti00/velodyne"
    return (
        read_cloud(d / "000000.bin").xyz.astype(np.float64),
        read_cloud(d / "000001.bin").xyz.astype(np.float64),
    )


@pytest.mark.parametrize("voxel", [0.05, 0.225, 1.0, 8.0])
def test_group_voxels_matches_np_unique(kitti_clouds, voxel: float) -> None:
    """The hashed grouping finds exactly np.unique's groups (the table grows several times at
    5 cm: 100k groups from a 1024-slot start)."""
    points = kitti_clouds[0]
    inverse, keys, counts, *_, ok = kernels.group_voxels(points, voxel)
    assert ok
    ref_keys = pack_keys(voxel_coords(points, voxel))
    uniq, ref_counts = np.unique(ref_keys, return_counts=True)
    np.testing.assert_array_equal(np.sort(keys), uniq)
    np.testing.assert_array_equal(keys[inverse], ref_keys)
    np.testing.assert_array_equal(counts[np.argsort(keys)], ref_counts)
    # First-seen order: group g first appears before group g + 1.
    first = np.full(keys.size, points.shape[0])
    np.minimum.at(first, inverse, np.arange(points.shape[0]))
    assert np.all(np.diff(first) > 0)


def test_group_voxels_flags_non_finite_and_out_of_range_points() -> None:
    for bad in (np.nan, np.inf, 1e9):
        pts = np.zeros((5, 3))
        pts[3, 1] = bad
        assert not kernels.group_voxels(pts, 0.1)[-1]


def test_voxel_gaussians_match_a_per_voxel_numpy_fit(kitti_clouds) -> None:
    """Means and conditioned covariances of the compiled build against np.mean/np.cov per voxel."""
    points = voxel_downsample(kitti_clouds[0], 0.25)
    gmap, assignment = VoxelGaussianMap.build_with_assignment(points, 2.0, min_points_per_voxel=6)
    assert np.all(np.diff(gmap.keys) > 0)
    keys = pack_keys(voxel_coords(points, 2.0))
    for v in np.linspace(0, gmap.n_voxels - 1, 25).astype(int):
        members = points[keys == gmap.keys[v]]
        np.testing.assert_array_equal(np.flatnonzero(assignment == v), np.flatnonzero(keys == gmap.keys[v]))
        np.testing.assert_allclose(gmap.means[v], members.mean(axis=0), rtol=1e-12, atol=1e-9)
        evals, evecs = np.linalg.eigh(np.cov(members.T))
        evals = np.maximum(evals, max(evals[2] * 0.01, 1e-12))
        np.testing.assert_allclose(gmap.covariances[v], (evecs * evals) @ evecs.T, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(gmap.inv_covariances[v] @ gmap.covariances[v], np.eye(3), atol=1e-8)
    dropped = np.isin(keys, gmap.keys, invert=True)
    assert np.all(assignment[dropped] == -1) and dropped.any()


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (3517.3, -2210.9, 41.7)])
def test_pyramid_from_moments_matches_building_each_level(kitti_clouds, offset) -> None:
    """Coarse NDT levels summed from the finest level's moments equal levels fitted from the
    points (same voxels, counts; means and covariances to rounding), near and far from the origin."""
    points = voxel_downsample(kitti_clouds[0], 0.25) + np.asarray(offset)
    sizes = (16.0, 8.0, 4.0, 2.0, 1.0)
    pyramid = VoxelGaussianMap.build_pyramid(points, sizes)
    for level, v in zip(pyramid, sizes, strict=True):
        direct = VoxelGaussianMap.build(points, v)
        assert level.voxel_size_m == v
        np.testing.assert_array_equal(level.keys, direct.keys)
        np.testing.assert_array_equal(level.counts, direct.counts)
        np.testing.assert_allclose(level.means, direct.means, rtol=0, atol=1e-9)
        np.testing.assert_allclose(level.covariances, direct.covariances, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(level.inv_covariances, direct.inv_covariances, rtol=1e-7, atol=1e-7)
    # Sizes that do not nest are built level by level (same result as build).
    odd = VoxelGaussianMap.build_pyramid(points, (3.0, 1.0))
    np.testing.assert_array_equal(odd[0].keys, VoxelGaussianMap.build(points, 3.0).keys)


def test_eigh3_matches_lapack() -> None:
    rng = np.random.default_rng(3)
    X = rng.normal(size=(4000, 3, 3)) * 10.0 ** rng.uniform(-4, 4, size=(4000, 1, 1))
    M = X @ np.swapaxes(X, 1, 2)
    M[:500, 2] = M[:500, :, 2] = 0.0  # rank-deficient (flat) matrices too
    evals, evecs = kernels.eigh3(M)
    ref_vals = np.linalg.eigvalsh(M)
    scale = np.abs(ref_vals).max(axis=1, keepdims=True)
    np.testing.assert_allclose(evals, ref_vals, atol=1e-12 * scale.max(), rtol=1e-12)
    assert np.all(np.diff(evals, axis=1) >= 0)
    eye = np.broadcast_to(np.eye(3), M.shape)
    np.testing.assert_allclose(evecs @ np.swapaxes(evecs, 1, 2), eye, atol=1e-12)
    rebuilt = (evecs * evals[:, None, :]) @ np.swapaxes(evecs, 1, 2)
    np.testing.assert_allclose(rebuilt, M, atol=1e-11 * scale.max())


def test_conditioned_gaussians_match_the_numpy_fit(kitti_clouds) -> None:
    """The fused fit (conditioning, covariance, inverse, whitening, normal) is the vectorized
    one to round-off, on a real sweep's 1 m voxels and on flat (rank-deficient) scatters."""
    from randt.core.kernels import group_moments

    pts = np.ascontiguousarray(kitti_clouds[0], dtype=np.float64)
    inverse, keys, _ = voxel_groups(pts, 1.0)
    counts, _, scatter = group_moments(pts, inverse, keys.size)
    scatter = np.concatenate([scatter, np.zeros((50, 3, 3))])
    scatter[-50:, :2, :2] = np.eye(2)  # flat voxels: the floor decides the third eigenvalue
    counts = np.concatenate([counts, np.full(50, 7)]).astype(np.float64)
    assert scatter.shape[0] > 2000
    got = kernels.conditioned_gaussians(scatter, counts, 0.01)
    ref = VoxelGaussianMap._from_moments_numpy(scatter, counts, 0.01)
    for name, a, b in zip(("cov", "inv", "whitening", "normals"), got, ref, strict=True):
        scale = np.abs(b).max(axis=tuple(range(1, b.ndim)), keepdims=True)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * scale.max(), err_msg=name)
    cov, inv, white, _ = got
    eye = np.broadcast_to(np.eye(3), cov.shape)
    np.testing.assert_allclose(cov @ inv, eye, atol=1e-6)
    np.testing.assert_allclose(
        np.swapaxes(white, 1, 2) @ white, inv, rtol=1e-9, atol=1e-9 * np.abs(inv).max()
    )
    evals = np.linalg.eigvalsh(cov[-50:])
    np.testing.assert_allclose(evals[:, 0], 0.01 * evals[:, 2], rtol=1e-9)


def test_parent_moments_match_bincount(kitti_clouds) -> None:
    """Moments one level up from the children's, compiled and by ``np.bincount``, on a real sweep."""
    from randt.core.kernels import group_moments
    from randt.core.voxel import _parent_moments, _parent_moments_numpy

    pts = np.ascontiguousarray(kitti_clouds[0], dtype=np.float64)
    inverse, keys, _ = voxel_groups(pts, 0.5)
    counts, means, scatter = group_moments(pts, inverse, keys.size)
    got = _parent_moments(keys, counts, means, scatter, 0.5)
    ref = _parent_moments_numpy(keys, counts, means, scatter, 0.5)
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])
    np.testing.assert_allclose(got[2], ref[2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(got[3], ref[3], rtol=0, atol=1e-9 * np.abs(ref[3]).max())
    # and they are the moments of the points grouped at the parent size directly
    inv1, keys1, _ = voxel_groups(pts, 1.0)
    c1, m1, s1 = group_moments(pts, inv1, keys1.size)
    order, order1 = np.argsort(got[0]), np.argsort(keys1)
    np.testing.assert_array_equal(got[1][order], c1[order1])
    np.testing.assert_allclose(got[2][order], m1[order1], atol=1e-9)
    np.testing.assert_allclose(got[3][order], s1[order1], atol=1e-7 * np.abs(s1).max())


def test_in_marked_cells_matches_isin() -> None:
    rng = np.random.default_rng(5)
    cells = pack_keys(rng.integers(-50, 50, size=(20000, 3)))
    marked = np.concatenate([rng.choice(cells, 3000), pack_keys(rng.integers(60, 90, size=(500, 3)))])
    got = kernels.in_marked_cells(cells, marked)
    np.testing.assert_array_equal(got, np.isin(cells, marked))
    assert 0 < got.sum() < got.size
    assert not kernels.in_marked_cells(cells, marked[:0]).any()


def test_point_grid_nearest_matches_kdtree(kitti_clouds) -> None:
    from scipy.spatial import cKDTree

    from randt.core.grid import PointGrid

    ref = voxel_downsample(kitti_clouds[0], 0.2)
    queries = voxel_downsample(kitti_clouds[1], 0.4)
    T = make_transform(euler_deg=(0.5, -0.3, 2.0), translation=(0.6, -0.2, 0.05))
    grid = PointGrid.build(ref, 0.8)
    idx, dist = grid.nearest(queries, T, 0.8)
    ref_dist, ref_idx = cKDTree(ref).query(transform_points(T, queries), distance_upper_bound=0.8)
    found = np.isfinite(ref_dist)
    assert found.sum() > 5000 and (~found).sum() > 100
    np.testing.assert_array_equal(idx >= 0, found)
    np.testing.assert_allclose(dist[found], ref_dist[found], rtol=1e-12, atol=1e-12)
    assert np.mean(idx[found] == ref_idx[found]) > 0.999  # ties aside, the same points
    with pytest.raises(ValueError, match="exceeds the cell size"):
        grid.nearest(queries, T, 1.0)


@pytest.mark.parametrize("cell", [1.6, 0.8, 0.55])
def test_point_grid_normals_match_hybrid_knn(kitti_clouds, cell: float) -> None:
    """Normals from up to k neighbours within the radius equal an exact k-NN/radius fit, whether
    the radius spans one cell or three (where the search stops at the first shell of cells that
    cannot hold a nearer point)."""
    from scipy.spatial import cKDTree

    from randt.core.grid import PointGrid

    ref = voxel_downsample(kitti_clouds[0], 0.2)
    which = np.arange(0, ref.shape[0], 7)
    grid = PointGrid.build(ref, cell)
    normals, valid = grid.normals(which, 16, 1.6, min_points=5)
    dist, idx = cKDTree(ref).query(ref[which], k=16, distance_upper_bound=1.6)
    n_within = np.isfinite(dist).sum(axis=1)
    np.testing.assert_array_equal(valid, n_within >= 5)
    assert valid.mean() > 0.8
    for w in np.flatnonzero(valid)[::10]:
        nb = ref[idx[w, : n_within[w]]]
        evals, evecs = np.linalg.eigh(np.cov(nb.T))
        if evals[1] - evals[0] < 1e-3 * evals[2]:
            continue  # no unique normal (a line or a blob)
        assert abs(evecs[:, 0] @ normals[w]) > 1 - 1e-9
    np.testing.assert_allclose(np.linalg.norm(normals[valid], axis=1), 1.0, atol=1e-12)
    assert np.all(normals[~valid] == 0)


def test_projected_pair_moments_match_umeyama(kitti_clouds) -> None:
    """The SVD step's fused Kabsch sums give umeyama's fit of the moved points onto their
    projections on the partners' planes, and the point-to-plane residuals' sum of squares."""
    from randt.core.registration import _projected_kabsch
    from randt.core.transforms import umeyama

    rng = np.random.default_rng(5)
    src = voxel_downsample(kitti_clouds[1], 0.3) + np.array([250.0, -40.0, 3.0])  # far from the origin
    dst = src + rng.normal(scale=0.05, size=src.shape)
    nrm = rng.normal(size=src.shape)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    T = make_transform(euler_deg=(0.4, -0.2, 1.1), translation=(0.3, 0.1, -0.02))
    q = transform_points(T, src)
    r = np.einsum("ij,ij->i", q - dst, nrm)
    D_ref, _ = umeyama(q, q - nrm * r[:, None])
    D, centroid, rmse = _projected_kabsch(T, (src, dst, nrm))
    np.testing.assert_allclose(D, D_ref, atol=1e-9)
    np.testing.assert_allclose(centroid, q.mean(axis=0), rtol=1e-12)
    assert rmse == pytest.approx(np.sqrt(np.mean(r**2)), rel=1e-10)
    assert rmse > 0.01 and transform_error(D, np.eye(4))[0] > 1e-3  # a real step, not the identity


@pytest.mark.parametrize("voxel", [0.5, 1.0, 3.0])
def test_algorithm1_kernel_matches_the_lexsort_formulation(kitti_clouds, voxel: float) -> None:
    from randt.core.outliers import iqr_inlier_mask, iqr_inlier_mask_numpy

    points = voxel_downsample(kitti_clouds[0], 0.2)
    fast = iqr_inlier_mask(points, voxel)
    ref = iqr_inlier_mask_numpy(points, voxel)
    np.testing.assert_array_equal(fast, ref)
    assert fast.sum() > 5000 and (~fast).sum() > 500  # both outcomes occur


@pytest.mark.parametrize("voxel", [0.25, 0.5, 1.0])
def test_isolated_point_kernel_matches_numpy(kitti_clouds, voxel: float) -> None:
    from randt.core.features import _isolated, _isolated_numpy

    for cloud in kitti_clouds:
        fast = _isolated(cloud, voxel)
        np.testing.assert_array_equal(fast, _isolated_numpy(cloud, voxel))
        assert fast.any()


def test_group_min_skips_flagged_entries() -> None:
    values = np.array([5.0, 1.0, 3.0, -2.0, 7.0])
    groups = np.array([0, 0, 1, 1, 2])
    skip = np.array([False, True, False, False, True])
    np.testing.assert_array_equal(kernels.group_min(values, groups, 3, skip), [5.0, -2.0, np.inf])


def test_neighbor_cache_gives_the_uncached_derivatives(kitti_problem) -> None:
    """A cache warmed at one pose serves the next poses exactly, also where points change cells."""
    from randt.core.ndt import NeighborCache

    source, gmap, consts, T = kitti_problem
    cache = NeighborCache.empty(source.shape[0], 7)
    ndt_derivatives(source, T, gmap, consts, 7, cache=cache)
    for step in (1e-4, 0.02, 0.3):  # small steps reuse the cells, a 0.3 m one moves many points
        T2 = make_transform(translation=(step, -step, 0.5 * step), euler_deg=(0, 0, 10 * step)) @ T
        cached = ndt_derivatives(source, T2, gmap, consts, 7, cache=cache)
        fresh = ndt_derivatives(source, T2, gmap, consts, 7)
        assert cached.cost == fresh.cost and cached.n_pairs == fresh.n_pairs
        np.testing.assert_array_equal(cached.gradient, fresh.gradient)
        np.testing.assert_array_equal(cached.hessian, fresh.hessian)
        assert ndt_cost(source, T2, gmap, consts, 7, cache) == fresh.cost


def test_within_xy_radius_matches_the_numpy_crop(kitti_clouds) -> None:
    """The compiled crop keeps exactly the rows (in order) a numpy XY-distance mask keeps, z ignored."""
    points = np.vstack(kitti_clouds) + np.array([250.0, -40.0, 3.0])
    for cx, cy, r in ((250.0, -40.0, 20.0), (260.5, -31.0, 7.5), (0.0, 0.0, 1.0)):
        d = points[:, :2] - (cx, cy)
        expected = points[(d**2).sum(axis=1) <= r * r]
        got = kernels.within_xy_radius(points, cx, cy, r * r)
        np.testing.assert_array_equal(got, expected)
    assert kernels.within_xy_radius(points, 0.0, 0.0, 1.0).shape == (0, 3)


def test_group_centroids_match_bincount(kitti_clouds) -> None:
    """Per-group means (all points, and the masked ones of the groups holding any) against
    weighted ``np.bincount`` sums over the same grouping."""
    points = kitti_clouds[0]
    inverse, keys, *_ = kernels.group_voxels(points, 0.5)
    n = keys.size
    expected = np.stack([np.bincount(inverse, weights=points[:, d], minlength=n) for d in range(3)], 1)
    expected /= np.bincount(inverse, minlength=n)[:, None]
    np.testing.assert_allclose(kernels.group_centroids(points, inverse, n), expected, rtol=1e-12, atol=1e-9)
    mask = points[:, 2] > -1.0  # above the road
    sub = np.stack([np.bincount(inverse[mask], weights=points[mask, d], minlength=n) for d in range(3)], 1)
    sub_counts = np.bincount(inverse[mask], minlength=n)
    expected_masked = sub[sub_counts > 0] / sub_counts[sub_counts > 0, None]
    got = kernels.masked_group_centroids(points, inverse, n, mask)
    assert 0 < got.shape[0] < n
    np.testing.assert_allclose(got, expected_masked, rtol=1e-12, atol=1e-9)


def test_group_weighted_moments_match_bincount(kitti_clouds) -> None:
    """Weighted count, sums and scatter about each voxel's centre against weighted np.bincount
    passes over the same grouping (the form randt.core.model used before the kernel)."""
    points = kitti_clouds[0]
    inverse, keys, *_ = kernels.group_voxels(points, 1.0)
    n = keys.size
    centres = (unpack_keys(keys) + 0.5) * 1.0
    w = np.random.default_rng(3).choice([-1.0, 0.0, 1.0], size=points.shape[0])
    wsum, sums, scatter = kernels.group_weighted_moments(points, inverse, centres, w)
    d = points - centres[inverse]
    np.testing.assert_allclose(wsum, np.bincount(inverse, weights=w, minlength=n), atol=1e-9)
    for a in range(3):
        np.testing.assert_allclose(
            sums[:, a], np.bincount(inverse, weights=w * d[:, a], minlength=n), rtol=1e-10, atol=1e-9
        )
        for b in range(3):
            expected = np.bincount(inverse, weights=w * d[:, a] * d[:, b], minlength=n)
            np.testing.assert_allclose(scatter[:, a, b], expected, rtol=1e-10, atol=1e-9)
    assert np.abs(wsum).max() > 2  # the weights do not all cancel: the test can fail


def test_group_min_matches_minimum_at() -> None:
    rng = np.random.default_rng(7)
    values = rng.normal(size=5000)
    groups = rng.integers(0, 300, 5000)
    skip = rng.random(5000) < 0.3
    expected = np.full(310, np.inf)  # the last ten groups are empty
    np.minimum.at(expected, groups[~skip], values[~skip])
    np.testing.assert_array_equal(kernels.group_min(values, groups, 310, skip), expected)


def _kernel_docstrings() -> dict[str, str]:
    """Every public compiled kernel of randt.core.kernels (a numba dispatcher) and its docstring."""
    from numba.core.registry import CPUDispatcher

    found = {
        name: obj.py_func.__doc__ or ""
        for name, obj in vars(kernels).items()
        if isinstance(obj, CPUDispatcher) and not name.startswith("_")
    }
    assert len(found) >= 20
    return found


@pytest.mark.parametrize("name", sorted(_kernel_docstrings()))
def test_every_kernel_names_an_existing_reference_and_test(name: str) -> None:
    """A kernel's docstring ends with ``Reference: module:function`` and ``Test: path::test_name``;
    the reference resolves to a function and the test is defined in that file."""
    import ast
    import importlib
    import re
    from pathlib import Path

    doc = _kernel_docstrings()[name]
    ref = re.search(r"^\s*Reference: ([\w.]+):([\w.]+)\s*$", doc, re.MULTILINE)
    test = re.search(r"^\s*Test: (tests/[\w/]+\.py)::(test_\w+)\s*$", doc, re.MULTILINE)
    assert ref and test, f"{name}: no Reference/Test line in its docstring"
    target: object = importlib.import_module(ref.group(1))
    for attr in ref.group(2).split("."):
        target = getattr(target, attr)
    assert callable(target), f"{name}: {ref.group(1)}:{ref.group(2)} is not callable"
    path = Path(__file__).resolve().parents[2] / test.group(1)
    defined = {n.name for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.FunctionDef)}
    assert test.group(2) in defined, f"{name}: {test.group(1)} defines no {test.group(2)}"


def _core_numbers_reference(adj: np.ndarray) -> np.ndarray:
    """Core numbers by definition: the k-core is what is left after repeatedly deleting every
    vertex of degree < k; a vertex's core number is the largest k whose core holds it."""
    n = adj.shape[0]
    core = np.zeros(n, dtype=np.int64)
    for k in range(1, n):
        alive = np.ones(n, dtype=bool)
        while True:
            degree = adj[:, alive].sum(axis=1)
            drop = alive & (degree < k)
            if not drop.any():
                break
            alive &= ~drop
        if not alive.any():
            break
        core[alive] = k
    return core


def test_consistency_graph_and_core_numbers_match_numpy() -> None:
    rng = np.random.default_rng(4)
    a = rng.uniform(-10, 10, (120, 3))
    R = Rotation.from_euler("zyx", [40, 5, -3], degrees=True).as_matrix()
    b = a @ R.T + [3.0, -2.0, 1.0]
    b[60:] = rng.uniform(-10, 10, (60, 3))  # half the correspondences are outliers
    adj = kernels.consistency_graph(a, b, 0.2)
    da = np.linalg.norm(a[:, None] - a[None], axis=2)
    db = np.linalg.norm(b[:, None] - b[None], axis=2)
    expected = np.abs(da - db) <= 0.2
    np.fill_diagonal(expected, False)
    assert np.array_equal(adj, expected)
    # the 60 inliers are a clique: their core number is at least 59, the outliers' is far lower
    core = kernels.core_numbers(adj)
    assert np.array_equal(core, _core_numbers_reference(adj))
    assert core[:60].min() >= 59 and core[60:].max() < 20


def test_the_8_voxel_neighbourhood_encloses_the_point() -> None:
    """The 8 voxels a point is scored against are those whose centres enclose it: a point just
    above a cell boundary (z = 0.02 of a 1 m voxel) sees the layers below and above the boundary
    alike, where the 7-voxel neighbourhood sees its own layer 5 times and the one below once."""
    from randt.core.voxel import NEIGHBOR_OFFSETS, neighborhood_base

    p = np.array([[0.3, 0.8, 0.02]])
    cells8 = neighborhood_base(p, 1.0, 8)[0] + NEIGHBOR_OFFSETS[8]
    centres = (cells8 + 0.5) * 1.0
    assert np.all(centres.min(axis=0) <= p[0]) and np.all(centres.max(axis=0) >= p[0])
    assert sorted(set(cells8[:, 2])) == [-1, 0] and (cells8[:, 2] == -1).sum() == 4
    cells7 = neighborhood_base(p, 1.0, 7)[0] + NEIGHBOR_OFFSETS[7]
    assert (cells7[:, 2] == 0).sum() == 5 and (cells7[:, 2] == -1).sum() == 1
    assert kernels.cell_shift(8) == 0.5 and kernels.cell_shift(7) == 0.0


def test_the_8_voxel_cost_is_continuous_where_the_voxels_change(kitti_problem) -> None:
    """Points on the planes where their 8 enclosing voxels change (the cells' centre planes), a
    nanometre either side: the trilinearly weighted cost moves by round-off, where unweighted the 8
    would switch at once and the 7-voxel neighbourhood jumps at its own switch, the cell faces."""
    _, gmap, consts, _ = kitti_problem
    v = gmap.voxel_size_m
    cells = np.floor(gmap.means[:400] / v)
    eps, jumps7, jumps8 = 1e-9, [], []
    for c, mu in zip(cells, gmap.means[:400], strict=True):
        for plane, n in (((c[0] + 0.5) * v, 8), (c[0] * v, 7)):  # the x plane where n's voxels change
            lo, hi = mu.copy(), mu.copy()
            lo[0], hi[0] = plane - eps, plane + eps
            f_lo = ndt_cost(lo[None, :], np.eye(4), gmap, consts, n)
            f_hi = ndt_cost(hi[None, :], np.eye(4), gmap, consts, n)
            (jumps8 if n == 8 else jumps7).append(abs(f_hi - f_lo))
    assert max(jumps8) < 1e-6
    assert np.median(jumps7) > 1e-3  # the 7's cost is not continuous at its cell faces


def test_trilinear_weights_sum_to_8_and_favour_the_nearest_centre() -> None:
    from randt.core.voxel import trilinear_weights

    rng = np.random.default_rng(4)
    p = rng.uniform(-50, 50, (1000, 3))
    w = trilinear_weights(p, 1.0)
    np.testing.assert_allclose(w.sum(axis=0), 8.0, rtol=1e-12)
    # a point at a voxel's centre: that voxel alone (the base cell, offset (0,0,0)), weight 8
    w_c = trilinear_weights(np.array([[3.5, -2.5, 0.5]]), 1.0)[:, 0]
    assert w_c[0] == pytest.approx(8.0) and np.abs(w_c[1:]).max() < 1e-12


def test_deskew_kernel_matches_the_screw_motion() -> None:
    """randt.core.kernels.deskew_points against each point's own SE(3) power of the period's motion
    (randt.core.transforms.scale_motion, itself tested against scipy's fractional matrix power), on a
    sweep-like cloud with a car's motion over one period, a spin of 0.5 rad, and no rotation."""
    from scipy.spatial.transform import Rotation

    from randt.core.odometry import deskew, deskew_reference

    rng = np.random.default_rng(3)
    xyz = rng.uniform(-80, 80, (2000, 3))
    tau = rng.uniform(0.0, 0.1, 2000)
    for rotvec, t in (
        ([0.0, 0.01, 0.08], [1.2, 0.05, 0.01]),
        ([0.3, -0.2, 0.3], [0, 0, 0]),
        ([0, 0, 0], [1, 2, 3]),
    ):
        delta = np.eye(4)
        delta[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
        delta[:3, 3] = t
        for fraction in (0.0, 0.5):
            got = deskew(xyz, tau, delta, 0.1, reference_fraction=fraction)
            want = deskew_reference(xyz, tau, delta, 0.1, reference_fraction=fraction)
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    # the motion itself is applied: a point seen at the sweep's end moves by the whole of it
    moved = deskew(np.array([[10.0, 0, 0]]), np.array([0.1]), delta, 0.1)
    np.testing.assert_allclose(moved[0], [11.0, 2.0, 3.0], atol=1e-12)


def test_deskew_follows_the_arc_not_the_chord() -> None:
    """Turning 3.3 deg a period at 10 m/s (33 deg/s, a simulated corner), the sensor half a
    period from the middle is on the arc: 7.2 mm inside the period's chord, and a point seen then
    is moved by that, not by half the chord (which put it 14 mm across before 2026-11-28)."""
    from randt.core.odometry import deskew

    turn = np.radians(3.3)
    radius = 1.0 / turn  # a 1 m arc
    delta = make_transform(
        rotvec=(0, 0, turn), translation=(radius * np.sin(turn), radius * (1 - np.cos(turn)), 0.0)
    )
    # A point at the sensor's own origin at the sweep's end, re-expressed at its middle: the
    # sensor's position then, half the arc on from the middle.
    end = deskew(np.zeros((1, 3)), np.array([0.1]), delta, 0.1, reference_fraction=0.5)[0]
    half = turn / 2
    np.testing.assert_allclose(end, [radius * np.sin(half), radius * (1 - np.cos(half)), 0.0], atol=1e-12)
    start = deskew(np.zeros((1, 3)), np.array([0.0]), delta, 0.1, reference_fraction=0.5)[0]
    np.testing.assert_allclose(start, [-radius * np.sin(half), radius * (1 - np.cos(half)), 0.0], atol=1e-12)
    assert start[1] == pytest.approx(radius * half**2 / 2, rel=1e-3)  # 7.2 mm of sagitta at 1 m
    assert 0.0071 < start[1] < 0.0073


def test_group_int_keys_matches_a_stable_sort() -> None:
    """randt.core.kernels.group_int_keys: groups in first-seen order, rows in input order within each."""
    from randt.core.kernels import group_int_keys

    rng = np.random.default_rng(8)
    keys = rng.integers(0, 40, 5000) * 1_000_003 + (1 << 40)
    order, uniq, starts = group_int_keys(keys)
    first_seen = keys[np.sort(np.unique(keys, return_index=True)[1])]
    np.testing.assert_array_equal(uniq, first_seen)
    for g, k in enumerate(uniq):
        rows = order[starts[g] : starts[g + 1]]
        np.testing.assert_array_equal(rows, np.flatnonzero(keys == k))
    assert starts[-1] == keys.size
    empty = group_int_keys(np.zeros(0, dtype=np.int64))
    assert empty[0].size == 0 and empty[1].size == 0 and list(empty[2]) == [0]
