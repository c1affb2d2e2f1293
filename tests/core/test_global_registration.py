"""Global (prior-free) registration on the real pairs, from the identity with no initial guess.

Bounds are each pair's local-registration accuracy:
tests/pairs.py's for the shared pairs; for the others what :func:`randt.core.registration.register`
reaches when started near the reference (measured 2026-11-24):

- 3DMatch: from the ground truth itself the local registration ends 12 cm / 1.8 deg away (the
  fragments overlap partially and the NDT cost slides along it); global: 12 cm / 1.8 deg.
- KITTI 00 frames 0 -> 10: started from 7.0, 7.6 or 8.6 m forward, the local registration lands
  on the same pose (7.498 m forward) within 0.1 mm; global: the same pose.
- The 21 KITTI 00 revisits against the ICP-refined pose of the data set (good to a few cm):
  global 0.9-6.6 cm / 0.05-0.41 deg (bench/global_registration.py prints each).
"""

from __future__ import annotations

import numpy as np
import pytest

from randt.core import kernels
from randt.core.errors import DegenerateProblemError, InvalidCloudError
from randt.core.fleet_map import FleetMapSettings
from randt.core.global_registration import FPFH_BINS, GlobalSettings, register_global, spfh_reference
from randt.core.registration import register
from randt.core.transforms import make_transform, transform_error
from tests import pairs

#: name -> (loader, translation bound m, rotation bound deg)
CASES = {
    "3dmatch": (pairs.threedmatch, 0.15, 2.5),
    "bun315": (lambda: pairs.bunny("bun315"), 0.0005, 0.2),
    "bun045": (pairs.bunny, 0.0005, 0.2),
    "small_gicp": (pairs.small_gicp, 0.012, 0.3),
    "argoverse2": (pairs.argoverse2, 0.006, 0.08),
    "car": (pairs.car, 0.04, 0.3),
}


def test_spfh_kernel_matches_the_numpy_reference() -> None:
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(2)
    points = rng.uniform(-1, 1, (400, 3))
    normals = rng.normal(size=(400, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    _, found = cKDTree(points).query(points, k=12, distance_upper_bound=0.3)
    idx = np.asarray(found, dtype=np.int64)
    got = kernels.spfh_histograms(points, normals, idx, FPFH_BINS)
    assert np.allclose(got, spfh_reference(points, normals, idx, FPFH_BINS))
    has = (idx[:, 1:] < 400).any(axis=1)
    # each angle's histogram sums to 100 % for a point with neighbours, 0 without
    sums = got.reshape(400, 3, FPFH_BINS).sum(axis=2)
    assert np.allclose(sums[has], 100.0) and np.allclose(sums[~has], 0.0)


@pytest.mark.parametrize("name", sorted(CASES))
def test_the_real_pairs_are_placed_from_the_identity_within_the_local_accuracy(name: str) -> None:
    loader, bound_m, bound_deg = CASES[name]
    source, target, T_ref = loader()
    result = register_global(source, target)
    dt, dr = transform_error(result.T_target_source, T_ref)
    assert result.confident, result.reason
    assert dt <= bound_m and dr <= bound_deg, f"{name}: {dt:.4f} m / {dr:.3f} deg"
    assert result.n_inliers >= 50


def test_where_local_registration_from_the_identity_fails_global_registration_does_not() -> None:
    """Our multi-level NDT from the identity already solves 3DMatch (12 cm / 1.9 deg), bun315 and
    most revisits; it fails on revisit 512 -> 3493 (9.9 m off) and on a sweep seen facing the
    other way (a vehicle driving the street in the opposite direction)."""
    loop = next(p for p in pairs.kitti00_loop_pairs() if (p.i, p.j) == (512, 3493))
    source, target = pairs.kitti00_loops_velodyne(loop.j), pairs.kitti00_loops_velodyne(loop.i)
    turned = make_transform(euler_deg=(0.0, 0.0, 180.0))
    # p_i = T_icp p_j = (T_icp turned^-1) (turned p_j)
    for src, T_ref in ((source, loop.T_icp), (source @ turned[:3, :3].T, loop.T_icp @ np.linalg.inv(turned))):
        local_dt, _ = transform_error(register(src, target).T_target_source, T_ref)
        assert local_dt > 1.0
        result = register_global(src, target)
        dt, dr = transform_error(result.T_target_source, T_ref)
        assert result.confident and dt < 0.07 and dr < 0.5, (dt, dr)


def test_kitti_frames_0_and_10_are_placed_7_5_m_apart_as_local_registration_from_near_finds() -> None:
    source, target = pairs.kitti00_velodyne(10), pairs.kitti00_velodyne(0)
    reference = register(source, target, make_transform(translation=(7.6, 0.0, 0.0))).T_target_source
    result = register_global(source, target)
    dt, dr = transform_error(result.T_target_source, reference)
    assert result.confident, result.reason
    assert dt < 0.01 and dr < 0.05
    assert 7.4 < result.T_target_source[0, 3] < 7.6


def test_every_kitti_revisit_is_placed_within_7_cm_of_the_icp_reference() -> None:
    """Measured against the ICP-refined reference (itself approximate: ICP from the ground truth,
    median residual 0.19-0.25 m): mean 3.0 cm / 0.23 deg, worst 5.7 cm and 0.53 deg (496-3495; the
    refinement without its SVD step gives 0.55 deg there, before the residual fence 0.41)."""
    errors = []
    for loop in pairs.kitti00_loop_pairs():
        result = register_global(pairs.kitti00_loops_velodyne(loop.j), pairs.kitti00_loops_velodyne(loop.i))
        dt, dr = transform_error(result.T_target_source, loop.T_icp)
        errors.append((loop.i, loop.j, dt, dr, result.confident, result.anisotropy))
    bad = [e for e in errors if not (e[4] and e[2] < 0.07 and e[3] < 0.6)]
    assert not bad, bad
    assert len(errors) == 21
    # Each refinement holds every direction about as well (anisotropy measured 1.34-2.59): the
    # fleet map's corridor bar (loop_max_anisotropy 6) keeps every true revisit.
    assert max(a for *_, a in errors) < 3.0 <= FleetMapSettings().loop_max_anisotropy / 2


def test_sweeps_of_different_places_are_never_confident() -> None:
    """Eight pairs of revisit-set sweeps from different streets: the consistent set stays below
    the threshold (measured 0-7 against 49-1011 for the true pairs)."""
    for i, j in ((120, 404), (1576, 3534), (172, 4235), (528, 1615), (4237, 3421), (202, 558), (1634, 492),
                 (3426, 129)):  # fmt: skip
        result = register_global(pairs.kitti00_loops_velodyne(j), pairs.kitti00_loops_velodyne(i))
        assert not result.confident, (i, j, result.n_inliers)
        assert result.n_inliers < GlobalSettings().min_inliers
        assert "consistent correspondences" in result.reason


def test_a_rotated_and_shifted_copy_is_recovered_exactly_and_nans_are_dropped() -> None:
    source, _, _ = pairs.bunny("bun000")
    T = make_transform(euler_deg=(20.0, -35.0, 150.0), translation=(0.3, -0.2, 0.1))
    target = source @ T[:3, :3].T + T[:3, 3]
    noisy = np.vstack([source, np.full((5, 3), np.nan)])
    result = register_global(noisy, target)
    dt, dr = transform_error(result.T_target_source, T)
    assert result.confident and dt < 1e-4 and dr < 0.05


def test_a_degenerate_refinement_is_a_reason_not_an_exception(monkeypatch: pytest.MonkeyPatch) -> None:
    """The NDT refinement of a corridor may not constrain every axis (DegenerateProblemError,
    seen on simulated street sweeps): the result is not confident and says why; it used to
    propagate and refuse the fleet map's keyframe that asked for the verification."""
    import randt.core.global_registration as gr

    def degenerate(*args: object, **kwargs: object) -> None:
        raise DegenerateProblemError("the geometry does not constrain 1 degree(s) of freedom (mostly tx)")

    source, _, _ = pairs.bunny("bun000")
    T = make_transform(euler_deg=(0.0, 0.0, 30.0), translation=(0.1, 0.0, 0.0))
    monkeypatch.setattr(gr, "register", degenerate)
    result = register_global(source, source @ T[:3, :3].T + T[:3, 3])
    assert not result.confident
    assert result.reason.startswith("NDT refinement failed: the geometry does not constrain")
    assert result.n_inliers >= GlobalSettings().min_inliers  # the coarse stage found it


def test_bad_input_is_named() -> None:
    with pytest.raises(InvalidCloudError, match="source"):
        register_global(np.zeros((0, 3)), np.random.default_rng(0).normal(size=(100, 3)))
    with pytest.raises(InvalidCloudError, match="voxels"):
        cloud = np.random.default_rng(0).normal(size=(100, 3))
        register_global(cloud, cloud, GlobalSettings(voxel_m=100.0))
