"""Registration accuracy on the shared real pairs, from the identity and from perturbed starts."""

from __future__ import annotations

import numpy as np
import pytest

from randt.core.config import RegistrationSettings
from randt.core.errors import DegenerateProblemError, InvalidCloudError, RegistrationFailedError
from randt.core.registration import register, sanitize_points
from randt.core.scenes import synthetic_room as _box_room
from randt.core.transforms import make_transform, transform_error, transform_points
from tests.pairs import PAIRS

_cache: dict[str, tuple] = {}


def _pair(name: str):
    if name not in _cache:
        _cache[name] = PAIRS[name][0]()
    return _cache[name]


def _perturbations(scale_m: float, n: int, seed: int) -> list[np.ndarray]:
    """``n`` perturbations with translation norm ``scale_m`` and rotation 5 degrees, random axes."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        t = rng.normal(size=3)
        t *= scale_m / np.linalg.norm(t)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        out.append(make_transform(rotvec=axis * np.radians(5.0), translation=t))
    return out


@pytest.mark.parametrize("name", list(PAIRS))
def test_real_pair_from_identity(name: str) -> None:
    source, target, T_ref = _pair(name)
    _, tol_m, tol_deg, _ = PAIRS[name]
    result = register(source, target)
    err_m, err_deg = transform_error(result.T_target_source, T_ref)
    assert result.converged
    assert err_m < tol_m, f"{name}: translation error {err_m:.4f} m"
    assert err_deg < tol_deg, f"{name}: rotation error {err_deg:.3f} deg"
    assert 0.5 < result.inlier_ratio <= 1.0


@pytest.mark.parametrize("name", list(PAIRS))
def test_real_pair_from_perturbed_starts(name: str) -> None:
    """Starts 1 m and 5 degrees off the reference (bunny: 2 cm, 15 % of its size, and 5 degrees)."""
    source, target, T_ref = _pair(name)
    _, tol_m, tol_deg, scale = PAIRS[name]
    for P in _perturbations(scale, 3, seed=7):
        init = P @ T_ref
        result = register(source, target, init)
        err_m, err_deg = transform_error(result.T_target_source, T_ref)
        assert err_m < tol_m, f"{name}: translation error {err_m:.4f} m from a perturbed start"
        assert err_deg < tol_deg, f"{name}: rotation error {err_deg:.3f} deg from a perturbed start"


def test_synthetic_known_transform_every_method() -> None:
    rng = np.random.default_rng(1)
    target = _box_room(rng)
    T_true = make_transform(euler_deg=(1.0, -2.0, 4.0), translation=(0.4, -0.3, 0.1))
    source = transform_points(np.linalg.inv(T_true), _box_room(rng))
    for method in ("randt", "ndt", "icp-point", "icp-plane"):
        result = register(
            source, target, settings=RegistrationSettings.for_method(method, voxel_sizes_m=(2.0, 1.0, 0.5))
        )
        err_m, err_deg = transform_error(result.T_target_source, T_true)
        assert err_m < 0.03 and err_deg < 0.2, f"{method}: {err_m:.4f} m {err_deg:.3f} deg"
        assert result.covariance.shape == (6, 6)
        assert np.all(np.linalg.eigvalsh(result.covariance) > 0)


def test_single_plane_is_reported_degenerate() -> None:
    rng = np.random.default_rng(2)
    plane = np.c_[rng.uniform(-20, 20, (20000, 2)), 0.01 * rng.normal(size=20000)]
    with pytest.raises(DegenerateProblemError) as info:
        register(plane + [0.3, 0.2, 0.05], plane, settings=RegistrationSettings(voxel_sizes_m=(2.0, 1.0)))
    assert {"tx", "ty", "rz"} <= set(info.value.weak_directions)
    assert info.value.result is not None


def test_nonfinite_points_dropped_and_counted() -> None:
    rng = np.random.default_rng(3)
    target = _box_room(rng)
    source = target.copy()
    source[:50] = np.nan
    source[50:60, 1] = np.inf
    result = register(source, target, settings=RegistrationSettings(voxel_sizes_m=(2.0, 1.0, 0.5)))
    assert result.n_nonfinite_dropped == 60
    err_m, err_deg = transform_error(result.T_target_source, np.eye(4))
    assert err_m < 0.01 and err_deg < 0.05


@pytest.mark.parametrize(
    "bad, what",
    [
        (np.zeros((0, 3)), "0 finite points"),
        (np.zeros((5, 3)), "5 finite points"),
        (np.zeros((10, 2)), "expected an (N,3)"),
        (np.full((100, 3), np.nan), "after dropping 100 non-finite"),
        (np.array(["a", "b", "c"]).reshape(1, 3), "must be numeric"),
    ],
)
def test_invalid_clouds_raise_specific_errors(bad: np.ndarray, what: str) -> None:
    good = _box_room(np.random.default_rng(4))
    with pytest.raises(InvalidCloudError, match=None) as info:
        register(bad, good)
    assert what in str(info.value)
    assert "source" in str(info.value)


def test_sanitize_keeps_xyz_of_xyzi() -> None:
    pts = np.arange(40, dtype=np.float32).reshape(10, 4)
    xyz, n_bad = sanitize_points(pts, name="x", min_points=3)
    assert xyz.shape == (10, 3) and n_bad == 0 and xyz[1, 0] == 4.0


def test_no_overlap_is_a_failure_not_the_initial_guess() -> None:
    rng = np.random.default_rng(5)
    target = _box_room(rng)
    far = target + [500.0, 0.0, 0.0]
    with pytest.raises(RegistrationFailedError, match="do not overlap"):
        register(far, target, settings=RegistrationSettings(voxel_sizes_m=(2.0, 1.0)))


def test_sparse_object_clouds_get_levels_their_voxels_can_fill() -> None:
    """1024 points sampled on a ModelNet40 mesh (the paper's object protocol): the scale's finest
    voxel (3-4 cm in a unit sphere) holds 1.3-1.4 points by the mean, and every registration used
    to raise InvalidCloudError ("no voxel holds 6 points"). The levels now grow until the voxels
    hold 8 by the mean, and each object is placed (a 10.6 deg, 12 cm offset, the same points)
    within 2.5 deg and 3 cm, or its result says it failed: degenerate, or an inlier ratio below
    0.5 (a chair, 1024 points on thin legs and a seat: 0.04 where the placed ones have 0.96-0.99)."""
    from randt.core.io import read_cloud
    from randt.core.registration import auto_voxel_sizes
    from tests.data import require_data

    meshes = sorted((require_data("objects/modelnet40") / "objects" / "modelnet40").glob("*.off"))
    assert len(meshes) >= 10
    T_true = make_transform(euler_deg=(3.0, -5.0, 10.0), translation=(0.1, -0.05, 0.05))
    placed = grown = 0
    for mesh in meshes:
        xyz = read_cloud(mesh, n_mesh_samples=1024, seed=1).xyz.astype(np.float64)
        xyz -= xyz.mean(axis=0)
        xyz /= np.linalg.norm(xyz, axis=1).max()
        grown += auto_voxel_sizes(xyz)[-1] >= 0.1  # the scale alone gives 3-5 cm
        try:
            result = register(transform_points(np.linalg.inv(T_true), xyz), xyz)
        except DegenerateProblemError:
            continue
        err_m, err_deg = transform_error(result.T_target_source, T_true)
        if result.inlier_ratio < 0.5:  # a failure the result owns up to (measured: 0.04)
            assert err_m > 0.03 or err_deg > 2.5, f"{mesh.name}: placed, inlier ratio {result.inlier_ratio}"
            continue
        assert err_m < 0.03 and err_deg < 2.5, f"{mesh.name}: {err_m:.4f} m {err_deg:.3f} deg"
        placed += 1
    assert placed >= len(meshes) - 1
    assert grown >= len(meshes) - 1


def test_a_sparse_clouds_points_without_a_gaussian_are_kept_not_outliers() -> None:
    """Algorithm 1 calls a point in a voxel too sparse for a Gaussian an outlier. In a real scan
    that is isolated clutter; in 1024 points on a ModelNet40 object it is the thin parts (9-24 %
    of the reference dropped, wings and legs first), and it cost the paper's object protocol
    (rotation up to 45 deg, translation up to 0.5) most of its successes: RMSE 0.064, 11 of 24
    placed within 1 deg / 0.01. A sparse cloud (:func:`is_sparse_cloud`) now keeps them, in the
    reference and in the moving selection; measured 0.0587, 19 of 24 (bench/paper.py's trials)."""
    from randt.core.io import read_cloud
    from randt.core.registration import auto_voxel_sizes, is_sparse_cloud, prepare_reference
    from randt.core.shared_data import car
    from tests.data import require_data

    meshes = sorted((require_data("objects/modelnet40") / "objects" / "modelnet40").glob("*.off"))[:12]
    rng = np.random.default_rng(20261125)
    rmse, placed, sparse = [], 0, 0
    for mesh in meshes:
        xyz = read_cloud(mesh, n_mesh_samples=1024, seed=int(rng.integers(1 << 31))).xyz.astype(np.float64)
        xyz -= xyz.mean(axis=0)
        xyz /= np.linalg.norm(xyz, axis=1).max()
        sparse += is_sparse_cloud(xyz)
        for _ in range(2):
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            T_true = make_transform(
                rotvec=axis * np.radians(rng.uniform(0.0, 45.0)), translation=rng.uniform(-0.5, 0.5, size=3)
            )
            source = transform_points(np.linalg.inv(T_true), xyz)
            try:
                T = register(source, xyz).T_target_source
            except DegenerateProblemError as exc:
                T = exc.result.T_target_source
            except RegistrationFailedError:  # counted as the identity, as bench/paper.py does
                T = np.eye(4)
            d = transform_points(T, source) - xyz
            rmse.append(float(np.sqrt(np.mean(np.sum(d * d, axis=1)))))
            err_m, err_deg = transform_error(T, T_true)
            placed += err_m <= 0.01 and err_deg <= 1.0
    assert sparse >= 11  # (one chair holds 2.3 points per voxel of its scale: not sparse)
    assert np.mean(rmse) <= 0.062, f"object RMSE {np.mean(rmse):.4f} (the paper's 0.062)"
    assert placed >= 18, f"{placed} of 24 placed"
    # A real scan, even the sparse car pair (3 points per voxel of its scale), still drops them.
    _, target, _ = car()
    target = target.astype(np.float64)
    assert not is_sparse_cloud(target)
    settings = RegistrationSettings()
    levels = auto_voxel_sizes(target)
    ref = prepare_reference(target, settings, levels)
    kept = prepare_reference(target, settings.model_copy(update={"outlier_removal": "none"}), levels)
    # measured: 55 % of the car's downsampled reference (isolated far points and clutter)
    assert ref.n_removed_outliers > 0.3 * ref.n_input_points and kept.n_removed_outliers == 0


def test_a_wrong_basin_at_the_coarsest_level_is_retried_from_the_next(monkeypatch) -> None:
    """Figure 9's scene (bench/paper.py): the paper's Velodyne scan 4 under the protocol (1.7 m /
    6.8 deg), its source equalized at 0.3 or 0.5 m. From the coarsest level (5.6 m, the target's
    scale) RANDT fell into a wrong basin, 2.3 and 4.0 m off with an inlier ratio of 0.04-0.05;
    run once more from the next level (RETRY_BELOW_INLIER_RATIO) it is placed within 1 cm, and
    the result with more inliers is kept."""
    import randt.core.registration as registration
    from randt.core.io import read_cloud
    from randt.core.trials import make_trial
    from randt.core.voxel import pack_keys, voxel_coords
    from tests.data import require_data

    root = require_data("randt_velodyne/velodyne")
    scans = sorted((root / "randt_velodyne" / "velodyne").glob("*.bin"))
    scan = read_cloud(scans[4]).xyz.astype(np.float64)
    trial = make_trial(scan, np.random.default_rng(20261125 + 200 + 4))
    for voxel in (0.3, 0.5):
        _, first = np.unique(pack_keys(voxel_coords(trial.source_xyz, voxel)), return_index=True)
        source = trial.source_xyz[np.sort(first)]
        result = register(source, trial.target_xyz)
        err_m, err_deg = transform_error(result.T_target_source, trial.T_true)
        assert err_m < 0.01 and err_deg < 0.1, f"{voxel} m: {err_m:.3f} m {err_deg:.3f} deg"
        assert result.inlier_ratio >= 0.1
        with monkeypatch.context() as m:  # without the retry: the wrong basin, and it says so
            m.setattr(registration, "RETRY_BELOW_INLIER_RATIO", 0.0)
            alone = register(source, trial.target_xyz)
        assert transform_error(alone.T_target_source, trial.T_true)[0] > 1.0
        assert alone.inlier_ratio < 0.06


def test_the_svd_residual_fence_and_the_dense_step_help_on_the_papers_protocol() -> None:
    """The SVD step trims its correspondences by their point-to-plane residuals as well as their
    distances (``svd_residual_fence_k``; before 2026-11-26 None), and since 2026-11-26 runs on its
    own denser moving selection with tighter fences (``FAST_SVD_STEP`` keeps the fenced step on
    the NDT solver's points). On the paper's protocol (noise, 10 % outliers, 50 % overlap) each
    lowers the placement error (bench/paper.py). Measured here on five trials of one KITTI 00
    sweep: before 4.8 mm mean (one trial 10 mm), fast 2.1 mm, default 1.5 mm."""
    from randt.core.config import FAST_SVD_STEP
    from randt.core.shared_data import kitti00_velodyne
    from randt.core.trials import make_trial
    from tests.data import require_data

    require_data("kitti00/velodyne/000000.bin")
    scan = kitti00_velodyne(0).astype(np.float64)
    variants = {
        "before": RegistrationSettings.for_method(
            "randt", **{**FAST_SVD_STEP, "svd_residual_fence_k": None, "svd_max_rmse_rise": 0.0}
        ),
        "fast": RegistrationSettings.for_method("randt", **FAST_SVD_STEP),
        "default": RegistrationSettings.for_method("randt"),
    }
    errors: dict[str, list[float]] = {name: [] for name in variants}
    for seed in range(5):
        trial = make_trial(scan, np.random.default_rng(20261125 + seed))
        for name, settings in variants.items():
            T = register(trial.source_xyz, trial.target_xyz, settings=settings).T_target_source
            errors[name].append(transform_error(T, trial.T_true)[0])
    assert max(errors["default"]) < 0.01, errors
    assert np.mean(errors["fast"]) < 0.6 * np.mean(errors["before"]), errors
    assert np.mean(errors["default"]) < np.mean(errors["fast"]), errors


def test_the_svd_step_on_unfiltered_points_removes_the_rotation_bias_of_real_pairs() -> None:
    """The SVD step pairs the clouds as downsampled, before the reference's IQR filter and
    Algorithm 1 (its own fences trim the pairs), since 2026-11-26. On real scans those filters
    drop thin structure (a third of a KITTI reference), and the same step on the filtered points
    leaves a rotation bias the point-to-plane ICPs do not have: measured here car 0.31 deg and
    small_gicp 0.32 deg from the reference (``FAST_SVD_STEP``: 0.25 / 0.25 deg; Open3D's
    point-to-plane 0.13 / 0.15 deg, small_gicp GICP 0.04 / 0.15 deg), on unfiltered points 0.08 /
    0.17 deg."""
    from tests.pairs import car, small_gicp

    for loader, bound_deg in ((car, 0.12), (small_gicp, 0.22)):
        source, target, T_ref = loader()
        errors = {}
        for filtered in (False, True):
            settings = RegistrationSettings(svd_on_filtered_points=filtered)
            result = register(source, target, settings=settings)
            assert result.svd_accepted, (loader.__name__, filtered)
            errors[filtered] = transform_error(result.T_target_source, T_ref)
        assert errors[False][1] < bound_deg and errors[False][1] < errors[True][1] - 0.05, errors
        assert errors[False][0] < 0.025, errors


def test_the_unfiltered_reference_is_kept_only_for_the_svd_step_that_uses_it() -> None:
    """A prepared reference keeps its downsampled points before the IQR filter only when an SVD
    step on unfiltered points will ask for them: the incremental matcher's references (no SVD
    step) hold one copy of their points, as before."""
    from randt.core.odometry import MATCHER_REGISTRATION
    from randt.core.registration import auto_voxel_sizes, prepare_reference
    from randt.core.shared_data import kitti00_velodyne
    from tests.data import require_data

    require_data("kitti00/velodyne/000000.bin")
    scan = kitti00_velodyne(0).astype(np.float64)
    levels = auto_voxel_sizes(scan)
    ref = prepare_reference(scan, RegistrationSettings(), levels)
    assert ref.unfiltered_xyz is not None and ref.n_removed_outliers > 0.2 * ref.n_input_points
    assert ref.unfiltered.points_xyz.shape[0] == ref.n_input_points == ref.unfiltered_xyz.shape[0]
    assert ref.unfiltered.maps is ref.maps and ref.unfiltered is ref.unfiltered  # built once
    for settings in (MATCHER_REGISTRATION, RegistrationSettings(svd_on_filtered_points=True)):
        other = prepare_reference(scan, settings, levels)
        assert other.unfiltered_xyz is None and other.unfiltered is other


def test_the_svd_step_is_kept_unless_its_rmse_clearly_rises() -> None:
    """On the car pair the fenced SVD step on the NDT solver's points (``FAST_SVD_STEP``) reaches
    1.6-2.6 cm from the reference at every residual fence from 2 to 3, while its trimmed RMSE
    moves 0.01-0.1 cm either way; a strict "must lower it" test kept it at 2 and 2.5 and rejected
    it at 2.25, 2.75 and 3 (NDT's pose, 4.6 cm). With the 2 % tolerance (``svd_max_rmse_rise``)
    every one is kept."""
    from randt.core.config import FAST_SVD_STEP
    from tests.pairs import car

    source, target, T_ref = car()
    rejected = 0
    for k in (2.0, 2.25, 2.5, 2.75, 3.0):
        step = {**FAST_SVD_STEP, "svd_residual_fence_k": k}
        kept = register(source, target, settings=RegistrationSettings(**step))
        assert kept.svd_accepted, k
        assert transform_error(kept.T_target_source, T_ref)[0] < 0.027, k
        strict = register(source, target, settings=RegistrationSettings(**step, svd_max_rmse_rise=0))
        rejected += not strict.svd_accepted
    assert rejected == 3


def test_a_moving_cloud_equalized_coarser_than_the_finest_voxel_still_registers() -> None:
    """A sweep equalized at 0.5 m (one point per voxel; the paper's density equalization taken
    far) against the 0.6 m finest NDT level: Algorithm 1's moving-point selection kept 0.1 % of it
    (its voxels hold too few points for Gaussians) and registration ended degenerate. The
    selection is now skipped when it would keep less than a quarter (real scans keep 43-89 %),
    and five protocol trials are placed within its success bounds (5 cm, 0.5 deg; measured
    0.4-3.2 cm, 0.02-0.11 deg)."""
    from randt.core.shared_data import kitti00_velodyne
    from randt.core.trials import make_trial
    from randt.core.voxel import pack_keys, voxel_coords
    from tests.data import require_data

    require_data("kitti00/velodyne/000000.bin")
    scan = kitti00_velodyne(0).astype(np.float64)
    for seed in range(5):
        trial = make_trial(scan, np.random.default_rng(20261325 + seed))
        _, first = np.unique(pack_keys(voxel_coords(trial.source_xyz, 0.5)), return_index=True)
        result = register(trial.source_xyz[np.sort(first)], trial.target_xyz)
        err_m, err_deg = transform_error(result.T_target_source, trial.T_true)
        assert err_m < 0.05 and err_deg < 0.5, f"seed {seed}: {err_m:.4f} m {err_deg:.3f} deg"


def test_the_centroid_start_places_objects_the_identity_cannot() -> None:
    """``centroid_start`` is the translation between the two centroids (non-finite rows ignored).
    ModelNet40 objects (1024 points in the unit sphere) posed 0.5 per axis and 28 deg apart: from
    the identity RANDT ends 77 cm / 78 deg off (the chair) or finds no overlap (the airplane); from
    the centroids within 2 cm and 0.5 deg (measured 0.18 cm / 0.08 deg and 1.3 cm / 0.43 deg: on
    the airplane's 193 moving points the SVD step's trimmed RMSE rises 4 % and NDT's pose is kept;
    ``FAST_SVD_STEP`` places it within 0.58 cm)."""
    from randt.core.io import read_cloud
    from randt.core.registration import centroid_start
    from randt.core.shared_data import data_root
    from tests.data import require_data

    a = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [np.nan, 1.0, 1.0]])
    b = np.array([[1.0, 1.0, 1.0], [1.0, 3.0, 1.0], [1.0, 2.0, 1.0]])
    np.testing.assert_allclose(centroid_start(a, b), make_transform(translation=(0.0, 2.0, 1.0)))

    require_data("objects/modelnet40")
    T = make_transform(euler_deg=(10.0, 20.0, -15.0), translation=(0.5, -0.5, 0.5))
    for name in ("chair_0002.off", "airplane_0003.off"):
        xyz = read_cloud(data_root() / "objects/modelnet40" / name, n_mesh_samples=1024, seed=7).xyz
        xyz = xyz.astype(np.float64) - xyz.mean(axis=0)
        xyz /= np.linalg.norm(xyz, axis=1).max()
        source = transform_points(np.linalg.inv(T), xyz)
        try:
            from_identity = transform_error(register(source, xyz).T_target_source, T)[0]
        except RegistrationFailedError:
            from_identity = np.inf
        assert from_identity > 0.1, name
        dt, dr = transform_error(register(source, xyz, centroid_start(source, xyz)).T_target_source, T)
        assert dt < 0.02 and dr < 0.5, (name, dt, dr)


def test_stratified_subsample_keeps_each_cells_share_in_input_order() -> None:
    """randt.core.voxel.stratified_subsample: exactly the asked count, every cell's share within one
    point of its proportion, rows in input order, the same rows every call."""
    from randt.core.voxel import stratified_subsample, voxel_groups

    rng = np.random.default_rng(5)
    dense = rng.normal(0.0, 0.5, (6000, 3))  # a few cells near the origin hold most points
    sparse = rng.uniform(-40.0, 40.0, (3000, 3))  # thousands of cells with one or two
    xyz = np.vstack([dense, sparse])
    out = stratified_subsample(xyz, 3000, 2.0)
    assert out.shape == (3000, 3)
    np.testing.assert_array_equal(out, stratified_subsample(xyz, 3000, 2.0))
    rows = np.flatnonzero((xyz[:, None, :] == out[None, :1000, :]).all(axis=2).any(axis=1))
    assert np.all(np.diff(rows) > 0)  # (a prefix's rows, in input order)
    inverse, _, counts = voxel_groups(xyz, 2.0)
    cell_of = {tuple(p): c for p, c in zip(map(tuple, xyz), inverse, strict=True)}
    got = np.bincount([cell_of[tuple(p)] for p in out], minlength=counts.size)
    share = counts * 3000 / xyz.shape[0]
    assert np.all(np.abs(got - share) <= 1.0 + 1e-9), np.max(np.abs(got - share))
    # the dense cells gave up most of theirs: the sample is the cloud's distribution, thinned
    assert abs(np.mean(np.linalg.norm(out, axis=1) < 3.0) - 6000 / 9000) < 0.02
    np.testing.assert_array_equal(stratified_subsample(xyz[:100], 3000, 2.0), xyz[:100])


@pytest.mark.parametrize("name", ["small_gicp", "argoverse2"])
def test_real_pair_with_a_subsample_driving_newton(name: str) -> None:
    """``max_match_points``: 2000 stratified moving points drive the Newton iterations and the
    pose stays within the pair's bound (docs/mapping.md, the matcher's subsample)."""
    source, target, T_ref = _pair(name)
    _, tol_m, tol_deg, _ = PAIRS[name]
    full = register(source, target)
    sub = register(source, target, settings=RegistrationSettings(max_match_points=2000))
    assert sub.n_source_used == 2000 < full.n_source_used
    err_m, err_deg = transform_error(sub.T_target_source, T_ref)
    assert err_m < tol_m and err_deg < tol_deg, f"{name}: {err_m:.4f} m {err_deg:.3f} deg"


@pytest.mark.parametrize("name", ["small_gicp", "argoverse2"])
def test_plane_information_kernel_matches_numpy(name: str) -> None:
    """The degeneracy test's point-to-plane information, compiled and vectorized, on real pairs
    at their reference pose, on 0.5 m and 1.5 m voxels (a size whose reciprocal is not exact)."""
    from randt.core.registration import _plane_information, _plane_information_numpy
    from randt.core.voxel import VoxelGaussianMap, voxel_downsample

    source, target, T = _pair(name)
    moving = voxel_downsample(source, 0.25)
    for size in (0.5, 1.5):
        gmap = VoxelGaussianMap.build(voxel_downsample(target, 0.1), size)
        got = _plane_information(moving, T, gmap)
        ref = _plane_information_numpy(moving, T, gmap)
        assert np.abs(ref).max() > 0.01
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12)
        evals = np.linalg.eigvalsh(got)
        assert evals.min() > 1e-3 * evals.max()  # a real scene constrains every direction
