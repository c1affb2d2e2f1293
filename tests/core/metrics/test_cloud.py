"""Tests for randt.core.metrics.cloud: hand-computed cloud metrics."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from randt.core.errors import InvalidCloudError
from randt.core.metrics.cloud import (
    chamfer_distance,
    correspondence_rmse,
    overlap_ratio,
    pdu,
    pdu_per_group,
    voxel_count_std,
)
from randt.core.transforms import make_transform


def grid(nx: int, ny: int, nz: int, spacing: float = 1.0) -> np.ndarray:
    """(nx*ny*nz, 3) regular grid of points starting at the origin."""
    axes = [np.arange(n) * spacing for n in (nx, ny, nz)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def points_with_counts(counts: list[int], voxel_size: float = 1.0, origin: float = 0.0) -> np.ndarray:
    """Points in distinct voxels along x, ``counts[k]`` of them inside voxel k (never on a border)."""
    chunks = []
    for k, c in enumerate(counts):
        centre = origin + (k + 0.5) * voxel_size
        jitter = np.linspace(-0.4, 0.4, c) * voxel_size if c > 1 else np.zeros(1)
        chunks.append(np.column_stack([np.full(c, centre), jitter + 0.5 * voxel_size, np.full(c, 0.5)]))
    return np.concatenate(chunks)


# --------------------------------------------------------------------------------------------
# Cloud metrics
# --------------------------------------------------------------------------------------------


def test_correspondence_rmse_offset_grids_and_transform() -> None:
    target = grid(6, 5, 4)
    source = target - [0.1, 0.0, 0.0]  # every source point 0.1 m from its partner
    result = correspondence_rmse(source, target)
    assert result.rmse_m == pytest.approx(0.1, abs=1e-12)
    assert (result.n_pairs, result.n_source, result.fitness) == (120, 120, 1.0)
    moved = correspondence_rmse(source, target, make_transform(translation=[0.1, 0.0, 0.0]))
    assert moved.rmse_m == pytest.approx(0.0, abs=1e-12)


def test_correspondence_rmse_max_distance_excludes_pairs_inclusively() -> None:
    target = np.zeros((1, 3))
    source = np.array([[3.0, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, 100.0]])
    all_pairs = correspondence_rmse(source, target)
    assert all_pairs.rmse_m == pytest.approx(math.sqrt((9 + 16 + 10000) / 3))
    assert all_pairs.n_pairs == 3
    near = correspondence_rmse(source, target, max_distance_m=4.0)  # 4.0 itself is kept
    assert near.rmse_m == pytest.approx(math.sqrt(12.5))
    assert (near.n_pairs, near.n_source) == (2, 3)
    assert near.fitness == pytest.approx(2 / 3)
    assert correspondence_rmse(source, target, max_distance_m=3.5).n_pairs == 1
    none = correspondence_rmse(source, target, max_distance_m=1.0)
    assert none.n_pairs == 0 and math.isnan(none.rmse_m)
    assert none.as_dict()["rmse_m"] is None


def test_correspondence_rmse_rejects_bad_input() -> None:
    target = grid(3, 3, 3)
    with pytest.raises(InvalidCloudError, match="empty"):
        correspondence_rmse(np.zeros((0, 3)), target)
    with pytest.raises(InvalidCloudError, match=r"\(N,3\)"):
        correspondence_rmse(np.zeros((4, 2)), target)
    with pytest.raises(InvalidCloudError, match="not finite"):
        correspondence_rmse(np.array([[np.nan, 0.0, 0.0]]), target)
    with pytest.raises(ValueError, match="max_distance_m"):
        correspondence_rmse(target, target, max_distance_m=0.0)
    with pytest.raises(ValueError, match="4x4"):
        correspondence_rmse(target, target, np.eye(3))


def test_chamfer_distance_offset_grids() -> None:
    a = grid(5, 4, 3, spacing=1.0)
    b = a + [0.0, 0.25, 0.0]  # offset < spacing / 2: every nearest neighbour is the partner
    assert chamfer_distance(a, b) == pytest.approx(0.25, abs=1e-12)
    assert chamfer_distance(a, b, squared=True) == pytest.approx(0.0625, abs=1e-12)
    assert chamfer_distance(a, a) == 0.0


def test_chamfer_distance_is_the_halved_sum_of_both_directions() -> None:
    a = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    b = np.array([[0.0, 0.0, 0.0]])
    # a->b: (0 + 2) / 2 = 1; b->a: 0; (1 + 0) / 2 = 0.5. Squared: ((0 + 4) / 2 + 0) / 2 = 1.
    assert chamfer_distance(a, b) == pytest.approx(0.5)
    assert chamfer_distance(b, a) == pytest.approx(0.5)
    assert chamfer_distance(a, b, squared=True) == pytest.approx(1.0)


def test_overlap_ratio_half_shifted_sets() -> None:
    a = grid(10, 4, 1)
    b = a + [5.0, 0.0, 0.0]  # columns x = 5..9 of a coincide with b
    assert overlap_ratio(a, b, radius_m=0.5) == pytest.approx(0.5)
    assert overlap_ratio(b, a, radius_m=0.5) == pytest.approx(0.5)
    lifted = a + [5.0, 0.0, 0.5]  # overlapping half now exactly 0.5 m away
    assert overlap_ratio(a, lifted, radius_m=0.5) == pytest.approx(0.5)  # inclusive radius
    assert overlap_ratio(a, lifted, radius_m=0.49) == 0.0
    assert overlap_ratio(a, a + [20.0, 0.0, 0.0], radius_m=1.0) == 0.0
    with pytest.raises(ValueError, match="radius_m"):
        overlap_ratio(a, b, radius_m=-1.0)


def test_voxel_count_std_and_pdu_by_hand() -> None:
    points = points_with_counts([1, 2, 3, 6], voxel_size=0.5, origin=-1.0)  # negative cells too
    # counts 1, 2, 3, 6: mean 3, deviations -2, -1, 0, 3 -> variance 14/4 = 3.5 (population)
    assert voxel_count_std(points, 0.5) == pytest.approx(math.sqrt(3.5))
    assert pdu(points, 0.5) == pytest.approx(1.0 - math.sqrt(3.5) / 3.0)


def test_pdu_uniform_is_one_and_skewed_goes_negative() -> None:
    uniform = points_with_counts([5, 5, 5, 5, 5])
    assert voxel_count_std(uniform, 1.0) == 0.0
    assert pdu(uniform, 1.0) == 1.0
    # counts 1, 1, 1, 1, 16: mean 4, deviations -3 (x4), 12 -> variance 180/5 = 36, sigma 6
    skewed = points_with_counts([1, 1, 1, 1, 16])
    assert voxel_count_std(skewed, 1.0) == pytest.approx(6.0)
    assert pdu(skewed, 1.0) == pytest.approx(1.0 - 6.0 / 4.0)
    # one voxel holding everything: a single count, sigma 0, PDU 1
    assert pdu(uniform, 100.0) == 1.0
    with pytest.raises(ValueError, match="voxel_size_m"):
        pdu(uniform, 0.0)


def test_pdu_per_group_matches_hand_values_and_per_subset_pdu() -> None:
    g0 = points_with_counts([1, 2, 3, 6])  # voxels x = 0..3
    g1 = points_with_counts([5, 5], origin=10.0)  # voxels x = 10, 11
    g2 = points_with_counts([1, 1, 1, 1, 16], origin=-20.0)
    shared = points_with_counts([2])  # lands in g0's first voxel but belongs to group 7
    points = np.concatenate([g0, g1, g2, shared])
    ids = np.concatenate([np.full(len(g0), 3), np.full(len(g1), 5), np.full(len(g2), -1), [7, 7]])
    result = pdu_per_group(points, 1.0, ids)
    np.testing.assert_array_equal(result.groups, [-1, 3, 5, 7])
    np.testing.assert_allclose(result.pdu, [1.0 - 6.0 / 4.0, 1.0 - math.sqrt(3.5) / 3.0, 1.0, 1.0])
    np.testing.assert_array_equal(result.n_voxels, [5, 4, 2, 1])
    np.testing.assert_array_equal(result.n_points, [20, 12, 10, 2])
    for g, value in zip(result.groups, result.pdu, strict=True):
        assert value == pytest.approx(pdu(points[ids == g], 1.0))
    assert json.loads(json.dumps(result.as_dict()))["groups"] == [-1, 3, 5, 7]
    with pytest.raises(InvalidCloudError, match="group_ids"):
        pdu_per_group(points, 1.0, ids[:-1])
