"""The incremental keyframe model (core/model.py) against exact counts and the batch rebuild."""

from __future__ import annotations

import numpy as np
import pytest

from randt.core.config import RegistrationSettings
from randt.core.errors import InvalidCloudError
from randt.core.io import read_cloud
from randt.core.kernels import within_xy_radius
from randt.core.model import KeyframeModel, VoxelMoments
from randt.core.odometry import IncrementalMatcher
from randt.core.registration import prepare_reference, register
from randt.core.transforms import transform_error
from randt.core.voxel import VoxelGaussianMap, voxel_downsample
from tests.data import require_data


@pytest.fixture(scope="module")
def kitti_scans() -> list[np.ndarray]:
    root = require_data("kitti00/velodyne/000008.bin") / "kitti00"
    return [read_cloud(root / f"velodyne/{k:06d}.bin").xyz for k in range(9)]


def _line(x0: int, x1: int) -> np.ndarray:
    """Points at the centres of the 1 m voxels x0..x1-1 (y, z in the first voxel)."""
    x = np.arange(x0, x1) + 0.5
    return np.stack([x, np.full_like(x, 0.5), np.full_like(x, 0.5)], axis=1)


NONE = RegistrationSettings(outlier_removal="none")


def _add(
    model: KeyframeModel, pts: np.ndarray, *, keep: int = 20, at: float = 0.0, radius: float = 1e3
) -> KeyframeModel:
    return model.add_keyframe(pts, NONE, center_xy=(at, 0.0), radius_m=radius, max_keyframes=keep)


def _same_moments(a: VoxelMoments, b: VoxelMoments) -> None:
    np.testing.assert_array_equal(a.keys, b.keys)
    np.testing.assert_array_equal(a.counts, b.counts)
    np.testing.assert_allclose(a.sums, b.sums, atol=1e-9)
    np.testing.assert_allclose(a.scatter, b.scatter, atol=1e-9)


def test_voxels_hold_the_window_centroid_and_the_oldest_keyframe_leaves() -> None:
    m = KeyframeModel.empty(1.0, 2.0)
    m = _add(m, _line(0, 10), keep=2)  # id 0: voxels 0..9 at x + 0.5
    m = _add(m, _line(5, 15) + [0.2, 0, 0], keep=2)  # id 1: voxels 5..14 at x + 0.7
    assert m.points_xyz.shape[0] == 15 and m.ids == (0, 1)
    np.testing.assert_array_equal(m.counts, [1] * 5 + [2] * 5 + [1] * 5)
    np.testing.assert_allclose(
        m.points_xyz[:, 0], np.r_[np.arange(5) + 0.5, np.arange(5, 10) + 0.6, np.arange(10, 15) + 0.7]
    )
    m = _add(m, _line(12, 20), keep=2)  # id 0 leaves: voxels 0..4 empty, 5..9 keep id 1's points
    assert m.ids == (1, 2) and m.points_xyz.shape[0] == 15 and m.n_points == 15
    np.testing.assert_array_equal(m.counts, [1] * 7 + [2] * 3 + [1] * 5)
    np.testing.assert_allclose(
        m.points_xyz[:, 0], np.r_[np.arange(5, 12) + 0.7, np.arange(12, 15) + 0.6, np.arange(15, 20) + 0.5]
    )
    _same_moments(m.moments, VoxelMoments.of_points(m.points_xyz, 2.0))


def test_far_voxels_leave_and_a_reborn_voxel_forgets_its_past() -> None:
    m = _add(KeyframeModel.empty(1.0, 2.0), _line(0, 10), keep=2)
    m = _add(m, _line(95, 100), keep=2, at=100.0, radius=50.0)  # voxels 0..9 are 90 m away
    np.testing.assert_allclose(m.points_xyz[:, 0], np.arange(95, 100) + 0.5)
    m = _add(m, _line(0, 3) + [0.2, 0, 0], keep=2)  # 0..2 reborn; id 0 leaves and subtracts nothing
    np.testing.assert_array_equal(m.counts, [1] * 8)
    np.testing.assert_allclose(m.points_xyz[:, 0], np.r_[np.arange(3) + 0.7, np.arange(95, 100) + 0.5])
    _same_moments(m.moments, VoxelMoments.of_points(m.points_xyz, 2.0))


def test_moments_add_and_remove_exactly_on_real_points(kitti_scans) -> None:
    a = voxel_downsample(kitti_scans[0], 0.2)
    b = voxel_downsample(kitti_scans[4], 0.2)
    ma, mb = VoxelMoments.of_points(a, 0.8), VoxelMoments.of_points(b, 0.8)
    _same_moments(ma.merged(mb, +1), VoxelMoments.of_points(np.vstack([a, b]), 0.8))
    _same_moments(ma.merged(mb, +1).merged(mb, -1), ma)
    levels = (6.4, 3.2, 1.6, 0.8)
    built = VoxelGaussianMap.build_pyramid(a, levels)
    from_moments = VoxelGaussianMap.pyramid_from_moments(ma.gaussian_moments(), 0.8, levels)
    for x, y in zip(built, from_moments, strict=True):
        np.testing.assert_array_equal(x.keys, y.keys)
        np.testing.assert_allclose(x.means, y.means, atol=1e-9)
        np.testing.assert_allclose(x.covariances, y.covariances, atol=1e-9)


def test_incremental_model_matches_like_the_batch_rebuild(kitti_scans) -> None:
    """The batch Get (every keyframe stacked, cropped, downsampled, Algorithm 1 on the whole,
    pyramid from every point) and the incremental model place the next sweep within 0.1 mm and
    1e-4 deg of each other, with the same number of points to 0.2 %."""
    matcher = IncrementalMatcher()
    for s in kitti_scans[:8]:
        matcher.register_scan(s)
    st = matcher.state
    assert len(st.keyframes) >= 3 and st.store is not None and st.model is not None
    T0 = st.keyframes[-1][0]
    fused = np.vstack([pts for _, pts in st.keyframes])
    fused = within_xy_radius(fused, float(T0[0, 3]), float(T0[1, 3]), matcher.settings.model_radius_m**2)
    fused = voxel_downsample(fused, matcher.model_voxel_m)
    levels = matcher.registration.voxel_sizes_m or ()
    batch = prepare_reference(fused, matcher.registration, levels, downsampled_at_m=matcher.model_voxel_m)
    assert 0.998 < st.model.points_xyz.shape[0] / batch.points_xyz.shape[0] < 1.002  # measured 0.99993
    init = matcher.poses[-1] @ matcher.state.delta
    feats = matcher._preparer(kitti_scans[8], None, {"deskew": 0.0, "features": 0.0})(st.delta)[1]
    a = register(feats.matching_xyz, None, init, settings=matcher.registration, reference=st.model)
    b = register(feats.matching_xyz, None, init, settings=matcher.registration, reference=batch)
    err_m, err_deg = transform_error(a.T_target_source, b.T_target_source)
    assert err_m < 1e-4 and err_deg < 1e-4, (err_m, err_deg)  # measured 0.002 mm, 5e-6 deg
    assert abs(a.inlier_ratio - b.inlier_ratio) < 0.005, (a.inlier_ratio, b.inlier_ratio)  # measured equal


def test_a_failed_keyframe_leaves_the_model_untouched(kitti_scans, monkeypatch) -> None:
    """The keyframe's model cannot be prepared: the sweep raises, the state equals its snapshot,
    and the store is the same object with the same arrays (nothing was changed in place)."""
    matcher = IncrementalMatcher()
    for s in kitti_scans[:4]:
        matcher.register_scan(s)
    before = matcher.state.snapshot()
    store = matcher.state.store
    assert store is not None
    arrays = [store.points_xyz.copy(), store.keys.copy(), store.counts.copy(), store.moments.scatter.copy()]

    def unbuildable(new_store: KeyframeModel) -> None:
        assert new_store is not store and new_store.ids[-1] == store.ids[-1] + 1
        raise InvalidCloudError("model: too sparse")

    monkeypatch.setattr(matcher, "_prepare", unbuildable)
    matcher.settings = matcher.settings.model_copy(update={"keyframe_distance_m": 0.01})
    with pytest.raises(InvalidCloudError):
        matcher.register_scan(kitti_scans[4])
    assert matcher.state == before and matcher.state.store is store
    for x, y in zip(arrays, [store.points_xyz, store.keys, store.counts, store.moments.scatter], strict=True):
        np.testing.assert_array_equal(x, y)


def test_a_loaded_state_replays_the_same_model(kitti_scans) -> None:
    """``load_state_dict`` replays the keyframes into the same model (points, tags, moments) and
    the next sweep gets the same pose."""
    a = IncrementalMatcher()
    for s in kitti_scans[:7]:
        a.register_scan(s)
    b = IncrementalMatcher()
    b.load_state_dict({k: v.copy() for k, v in a.state_dict().items()})
    sa, sb = a.state.store, b.state.store
    assert sa is not None and sb is not None
    oa, ob = np.argsort(sa.keys), np.argsort(sb.keys)
    np.testing.assert_array_equal(sa.keys[oa], sb.keys[ob])
    np.testing.assert_array_equal(sa.points_xyz[oa], sb.points_xyz[ob])
    assert len(sa.ids) == len(sb.ids)
    _same_moments(sa.moments, sb.moments)
    ra, rb = a.register_scan(kitti_scans[7]), b.register_scan(kitti_scans[7])
    np.testing.assert_allclose(rb.T_world_sensor, ra.T_world_sensor, atol=1e-9)


def test_the_compiled_update_is_the_numpy_one(kitti_scans) -> None:
    """The compiled voxel bookkeeping (merge, eviction, radius crop, cells to judge) gives the
    numpy form's model bit for bit over a window that fills, evicts and crops (radius 30 m on
    KITTI sweeps 2-4 m apart, a window of 4)."""
    settings = RegistrationSettings()
    from randt.core.transforms import transform_points

    matcher = IncrementalMatcher()
    for s in kitti_scans:
        matcher.register_scan(s)
    a = b = KeyframeModel.empty(0.25, 1.0)
    for T, s in zip(matcher.poses, kitti_scans, strict=True):
        world = voxel_downsample(transform_points(T, s), 0.25)
        kw = {"center_xy": (float(T[0, 3]), float(T[1, 3])), "radius_m": 30.0, "max_keyframes": 4}
        a = a.add_keyframe(world, settings, **kw)
        b = b.add_keyframe_numpy(world, settings, **kw)
        for name in ("keys", "counts", "born", "fine", "inlier", "sums", "points_xyz"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        _same_moments(a.moments, b.moments)
        assert a.n_removed_outliers == b.n_removed_outliers
    assert len(a.ids) == 4 and a.n_points < a.points_xyz.shape[0]  # evicted, and outliers judged


def test_merged_moments_are_those_of_the_points_together() -> None:
    """A voxel's moments from two parts of its points (two map tiles) combined equal its moments
    from all of them; unique keys pass through, sorted."""
    from randt.core.kernels import group_moments
    from randt.core.voxel import merge_moments, voxel_groups

    rng = np.random.default_rng(3)
    pts = rng.uniform(0.0, 4.0, size=(3000, 3))
    parts = []
    for h in (pts[:1300], pts[1300:]):
        inverse, keys, _ = voxel_groups(h, 1.0)
        parts.append((keys, *group_moments(h, inverse, keys.size)))
    keys, counts, means, scatter = merge_moments(*(np.concatenate([p[i] for p in parts]) for i in range(4)))
    inverse, k_all, _ = voxel_groups(pts, 1.0)
    c_all, m_all, s_all = group_moments(pts, inverse, k_all.size)
    order = np.argsort(k_all)
    assert keys.size == 64 == k_all.size  # (every voxel of the 4 m cube in both parts)
    np.testing.assert_array_equal(keys, k_all[order])
    np.testing.assert_array_equal(counts, c_all[order])
    np.testing.assert_allclose(means, m_all[order], atol=1e-12)
    np.testing.assert_allclose(scatter, s_all[order], atol=1e-9)
    same = merge_moments(k_all, c_all, m_all, s_all)
    np.testing.assert_array_equal(same[0], k_all[order])
    np.testing.assert_array_equal(same[3], s_all[order])
