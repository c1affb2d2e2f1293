"""Tests for randt.core.metrics.trajectory: trajectory errors against analytic values, against evo,
and the KITTI devkit errors on the real sequence-00 ground truth."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from randt.core.errors import InvalidCloudError
from randt.core.io import read_kitti_poses
from randt.core.metrics.trajectory import (
    KITTI_LENGTHS_M,
    KittiResult,
    ate,
    evaluate_trajectory,
    kitti_relative_errors,
    rpe,
)
from randt.core.transforms import make_transform
from tests.data import require_data


def smooth_trajectory(n: int, seed: int = 0) -> np.ndarray:
    """(n,4,4) poses along a 3-D curve with slowly varying orientations."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 4.0 * np.pi, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.column_stack([20.0 * np.cos(s), 15.0 * np.sin(s), 2.0 * s + rng.normal(0, 0.1, n)])
    rotvecs = np.column_stack([0.1 * np.sin(3 * s), 0.05 * np.cos(2 * s), s])
    poses[:, :3, :3] = Rotation.from_rotvec(rotvecs).as_matrix()
    return poses


def noisy_copy(poses: np.ndarray, seed: int, sigma_t: float = 0.05, sigma_r: float = 0.01) -> np.ndarray:
    """Each pose right-multiplied by an independent random rigid perturbation."""
    rng = np.random.default_rng(seed)
    n = poses.shape[0]
    noise = np.tile(np.eye(4), (n, 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(rng.normal(0.0, sigma_r, (n, 3))).as_matrix()
    noise[:, :3, 3] = rng.normal(0.0, sigma_t, (n, 3))
    return poses @ noise


# --------------------------------------------------------------------------------------------
# ATE, RPE
# --------------------------------------------------------------------------------------------


def test_ate_rigid_copy_is_zero_with_se3_and_the_offset_without() -> None:
    reference = smooth_trajectory(120)
    offset = make_transform(translation=[1.0, 2.0, -2.0])  # |t| = 3 m
    shifted = offset @ reference
    assert ate(reference, shifted, align="none").translation_m.rmse == pytest.approx(3.0, rel=1e-12)
    stats = ate(reference, shifted, align="none").translation_m
    assert stats.mean == pytest.approx(3.0) and stats.max == pytest.approx(3.0)
    moved = make_transform([0.2, -0.4, 1.1], [30.0, -5.0, 7.0]) @ reference
    aligned = ate(reference, moved, align="se3")
    assert aligned.translation_m.rmse == pytest.approx(0.0, abs=1e-9)
    assert aligned.translation_m.max == pytest.approx(0.0, abs=1e-9)
    assert aligned.scale == 1.0
    np.testing.assert_allclose(
        aligned.T_reference_estimate @ moved[:, :, 3].T, reference[:, :, 3].T, atol=1e-9
    )
    assert ate(reference, moved, align="none").translation_m.rmse > 10.0


def test_ate_sim3_recovers_scale() -> None:
    reference = smooth_trajectory(150, seed=3)
    similarity = make_transform([0.5, 0.1, -0.7], [3.0, 1.0, 0.0])
    estimate = similarity @ reference
    estimate[:, :3, 3] *= 0.4  # the estimate is 0.4 times too small
    result = ate(reference, estimate, align="sim3")
    assert result.scale == pytest.approx(1.0 / 0.4, rel=1e-12)
    assert result.translation_m.rmse == pytest.approx(0.0, abs=1e-9)
    assert ate(reference, estimate, align="se3").translation_m.rmse > 1.0


def test_rpe_constant_per_step_error() -> None:
    reference = smooth_trajectory(100, seed=2)
    C = make_transform(np.radians(0.5) * np.array([0.6, 0.0, 0.8]), [0.01, 0.02, -0.02])  # 0.5 deg, 0.03 m
    steps = np.linalg.inv(reference[:-1]) @ reference[1:]
    estimate = np.empty_like(reference)
    estimate[0] = make_transform([0.1, 0.2, 0.3], [5.0, 5.0, 5.0])  # RPE ignores the start pose
    for i, D in enumerate(steps):  # P_{i+1} = P_i D_i C, so every E_i = C
        estimate[i + 1] = estimate[i] @ D @ C
    result = rpe(reference, estimate, delta=1)
    assert result.translation_m.rmse == pytest.approx(0.03, rel=1e-9)
    assert result.translation_m.max == pytest.approx(0.03, rel=1e-9)
    assert result.rotation_deg.rmse == pytest.approx(0.5, rel=1e-9)
    assert result.translation_m.n == 99 and result.delta == 1
    assert rpe(reference, estimate, delta=3).translation_m.n == 33  # (0,3), (3,6), ..., (96,99)
    assert rpe(reference, estimate, delta=3, all_pairs=True).translation_m.n == 97
    assert rpe(reference, reference, delta=5).rotation_deg.max == pytest.approx(0.0, abs=1e-9)


def test_trajectory_metrics_reject_bad_input() -> None:
    reference = smooth_trajectory(10)
    with pytest.raises(InvalidCloudError, match="associate"):
        ate(reference, reference[:-1])
    with pytest.raises(InvalidCloudError, match=r"\(N,4,4\)"):
        rpe(reference[:, :3, :], reference)
    bad = reference.copy()
    bad[2, 3, 0] = 1.0
    with pytest.raises(InvalidCloudError, match="bottom row"):
        ate(reference, bad)
    with pytest.raises(ValueError, match="align"):
        ate(reference, reference, align="affine")  # type: ignore[arg-type]
    with pytest.raises(InvalidCloudError, match="at least 11 poses"):
        rpe(reference, reference, delta=10)
    with pytest.raises(ValueError, match="delta"):
        rpe(reference, reference, delta=0)


# --------------------------------------------------------------------------------------------
# Against evo
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("align", "correct_scale"), [("se3", False), ("sim3", True), ("none", None)])
def test_ate_matches_evo(align: str, correct_scale: bool | None) -> None:
    pytest.importorskip("evo")
    from evo.core.metrics import APE, PoseRelation
    from evo.core.trajectory import PosePath3D

    reference = smooth_trajectory(300, seed=4)
    estimate = make_transform([0.1, 0.2, -0.3], [4.0, -2.0, 1.0]) @ noisy_copy(reference, seed=5)
    estimate[:, :3, 3] *= 1.05
    ref_path = PosePath3D(poses_se3=list(reference))
    est_path = copy.deepcopy(PosePath3D(poses_se3=list(estimate)))
    if correct_scale is not None:
        est_path.align(ref_path, correct_scale=correct_scale)
    ape = APE(PoseRelation.translation_part)
    ape.process_data((ref_path, est_path))
    expected = ape.get_all_statistics()

    stats = ate(reference, estimate, align=align).translation_m  # type: ignore[arg-type]
    for key in ("rmse", "mean", "median", "max"):
        assert getattr(stats, key) == pytest.approx(expected[key], rel=1e-9), key


@pytest.mark.parametrize(("delta", "all_pairs"), [(1, False), (4, False), (4, True)])
def test_rpe_matches_evo(delta: int, all_pairs: bool) -> None:
    pytest.importorskip("evo")
    from evo.core.metrics import RPE, PoseRelation, Unit
    from evo.core.trajectory import PosePath3D

    reference = smooth_trajectory(300, seed=6)
    estimate = noisy_copy(reference, seed=7)
    ref_path = PosePath3D(poses_se3=list(reference))
    est_path = PosePath3D(poses_se3=list(estimate))
    ours = rpe(reference, estimate, delta=delta, all_pairs=all_pairs)
    for relation, stats in (
        (PoseRelation.translation_part, ours.translation_m),
        (PoseRelation.rotation_angle_deg, ours.rotation_deg),
    ):
        metric = RPE(relation, delta=delta, delta_unit=Unit.frames, all_pairs=all_pairs)
        metric.process_data((ref_path, est_path))
        expected = metric.get_all_statistics()
        assert stats.n == len(metric.error)
        for key in ("rmse", "mean", "median", "max"):
            assert getattr(stats, key) == pytest.approx(expected[key], rel=1e-9), (relation, key)


# --------------------------------------------------------------------------------------------
# KITTI devkit errors on the real sequence-00 ground truth
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def kitti00_gt() -> np.ndarray:
    root = require_data("kitti_gt_poses/00.txt")
    return read_kitti_poses(root / "kitti_gt_poses/00.txt")


def reference_segments(
    poses: np.ndarray, lengths: tuple[float, ...] = KITTI_LENGTHS_M, step: int = 10
) -> set[tuple[int, int, float]]:
    """The devkit's segment search written out plainly: first frame with dist > dist[first] + L."""
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1))])
    segments = set()
    for first in range(0, len(poses), step):
        for length in lengths:
            beyond = dist[first:] > dist[first] + length
            if beyond.any():
                segments.add((first, first + int(np.argmax(beyond)), float(length)))
    return segments


def result_segments(result: KittiResult) -> set[tuple[int, int, float]]:
    return {
        (int(f), int(last), float(length))
        for f, last, length in zip(
            result.segment_first, result.segment_last, result.segment_length_m, strict=True
        )
    }


def test_kitti_identity_copy_is_zero(kitti00_gt: np.ndarray) -> None:
    result = kitti_relative_errors(kitti00_gt, kitti00_gt.copy())
    assert result.translation_pct == pytest.approx(0.0, abs=1e-10)
    assert result.rotation_deg_per_100m == pytest.approx(0.0, abs=1e-6)  # acos floor ~1e-8 rad
    assert result_segments(result) == reference_segments(kitti00_gt)
    assert result.n_segments == 3283
    assert [entry.n_segments for entry in result.per_length] == [445, 431, 424, 416, 408, 399, 385, 375]


def test_kitti_scaled_relative_translations(kitti00_gt: np.ndarray) -> None:
    G = kitti00_gt
    steps = np.linalg.inv(G[:-1]) @ G[1:]
    steps[:, :3, 3] *= 1.01  # every relative translation 1 % too long, rotations exact
    estimate = np.empty_like(G)
    estimate[0] = G[0]
    for i, step in enumerate(steps):
        estimate[i + 1] = estimate[i] @ step
    result = kitti_relative_errors(G, estimate)

    # pose_error = inv((A, 1.01 t)) (A, t) = (I, -0.01 A^-1 t): the error is 1 % of the segment's
    # CHORD |A^-1 t| (start-to-end displacement), not of its length L, so t_err = 0.01 |chord| / L.
    f, last, L = result.segment_first, result.segment_last, result.segment_length_m
    chord = np.linalg.norm((np.linalg.inv(G[last]) @ G[f])[:, :3, 3], axis=1)
    np.testing.assert_allclose(result.segment_t_err, 0.01 * chord / L, rtol=1e-9)
    assert result.translation_pct == pytest.approx(100.0 * np.mean(0.01 * chord / L), rel=1e-9)
    assert result.translation_pct == pytest.approx(0.6166014, abs=1e-6)  # < 1 %: sequence 00 turns a lot
    assert result.rotation_deg_per_100m == pytest.approx(0.0, abs=1e-5)
    per_100 = result.per_length[0]
    sel = L == 100.0
    assert per_100.translation_pct == pytest.approx(np.mean(chord[sel] / L[sel]), rel=1e-9)
    # the overall mean pools every segment: it is the count-weighted mean of the per-length means
    weighted = sum(e.translation_pct * e.n_segments for e in result.per_length) / result.n_segments
    assert weighted == pytest.approx(result.translation_pct, rel=1e-12)


def test_kitti_straight_line_scale_error_is_exactly_one_percent() -> None:
    n = 2001
    reference = np.tile(np.eye(4), (n, 1, 1))
    reference[:, 2, 3] = np.arange(n) * 0.5  # 1000 m straight ahead, 0.5 m per frame
    estimate = reference.copy()
    estimate[:, 2, 3] *= 1.01
    result = kitti_relative_errors(reference, estimate)
    # here the chord equals the path, and every segment ends one frame (0.5 m) past first + L
    np.testing.assert_allclose(
        result.segment_t_err, 0.01 * (result.segment_length_m + 0.5) / result.segment_length_m, rtol=1e-9
    )
    assert result.rotation_deg_per_100m == 0.0
    assert result.translation_pct == pytest.approx(
        100.0 * np.mean(0.01 * (1.0 + 0.5 / result.segment_length_m)), rel=1e-12
    )


def test_kitti_yaw_drift(kitti00_gt: np.ndarray) -> None:
    G = kitti00_gt
    eps = 1e-4  # rad of extra yaw per frame about the world vertical (camera y) axis
    drift = np.tile(np.eye(4), (len(G), 1, 1))
    drift[:, :3, :3] = Rotation.from_rotvec(np.outer(np.arange(len(G)) * eps, [0.0, 1.0, 0.0])).as_matrix()
    result = kitti_relative_errors(G, drift @ G)
    # pose_error = inv(G_l) Ry(-(l - f) eps) G_l, a rotation by exactly (l - f) eps
    frames = result.segment_last - result.segment_first
    np.testing.assert_allclose(result.segment_r_err, frames * eps / result.segment_length_m, rtol=1e-9)
    expected = np.mean(frames * eps / result.segment_length_m) * 180.0 / math.pi * 100.0
    assert result.rotation_deg_per_100m == pytest.approx(expected, rel=1e-9)
    assert result.rotation_deg_per_100m == pytest.approx(0.70795292, abs=1e-7)
    # from the mean frame spacing (3724.19 m over 4540 steps) alone: eps / 0.8203 m, within 2 %
    spacing = np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1).mean()
    assert result.rotation_deg_per_100m == pytest.approx(math.degrees(eps) / spacing * 100.0, rel=0.02)


def test_kitti_too_short_raises_and_evaluate_notes_it(kitti00_gt: np.ndarray) -> None:
    short = kitti00_gt[:100]  # about 86 m
    with pytest.raises(InvalidCloudError, match=r"path is 8\d\.\d\d m long.*100 m"):
        kitti_relative_errors(short, short)
    with pytest.raises(ValueError, match="lengths"):
        kitti_relative_errors(kitti00_gt, kitti00_gt, lengths=())
    report = evaluate_trajectory(short, noisy_copy(short, seed=8))
    assert report["kitti"] is None
    assert "KITTI errors skipped" in report["notes"][0]
    json.dumps(report, allow_nan=False)


def test_evaluate_trajectory_bundles_the_metrics(kitti00_gt: np.ndarray) -> None:
    reference = kitti00_gt[:800]
    estimate = noisy_copy(reference, seed=9, sigma_t=0.02, sigma_r=0.001)
    report = json.loads(json.dumps(evaluate_trajectory(reference, estimate), allow_nan=False))
    assert report["n_poses"] == 800 and report["notes"] == []
    assert report["ate"]["align"] == "se3"
    assert report["ate"]["translation_m"]["rmse"] == pytest.approx(
        ate(reference, estimate).translation_m.rmse
    )
    assert report["rpe"]["rotation_deg"]["rmse"] == pytest.approx(rpe(reference, estimate).rotation_deg.rmse)
    kitti = kitti_relative_errors(reference, estimate)
    assert report["kitti"]["translation_pct"] == pytest.approx(kitti.translation_pct)
    assert report["path_length_m"] > 500.0
    by_length = {entry["length_m"]: entry for entry in report["kitti"]["per_length"]}
    assert by_length[800.0]["n_segments"] == 0 and by_length[800.0]["translation_pct"] is None
