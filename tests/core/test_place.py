"""Place recognition on the 26 real KITTI 00 revisit sweeps (kitti00_loops), and its invariances.

Measured 2026-11-24 with the defaults (20 x 60 bins, 80 m): the yaw between the revisit pairs'
sensors is found within 3.1 deg for 20 of the 21 pairs (404 -> 3426: 10.7 deg); a query's best
candidate, excluding its own pass (frames within 50), is a listed revisit partner for 15 of the 23
sweeps that have one at the default threshold 0.3 (13 at 0.25, 17 at 0.4), with 3 proposals of
another place (which verification rejects: tests/core/test_global_registration.py).
"""

from __future__ import annotations

import numpy as np
import pytest

from core.errors import InvalidCloudError, InvalidRequestError
from core.place import PlaceIndex, PlaceSettings, scan_context, scan_context_distance
from tests import pairs

FRAMES = (120, 129, 172, 198, 199, 202, 404, 492, 493, 496, 508, 512, 528, 539, 558, 1576, 1615, 1634,
          3421, 3426, 3493, 3495, 3534, 4235, 4236, 4237)  # fmt: skip


@pytest.fixture(scope="module")
def descriptors() -> dict[int, np.ndarray]:
    return {f: scan_context(pairs.kitti00_loops_velodyne(f)) for f in FRAMES}


def test_the_yaw_between_revisits_is_found_within_one_sector(descriptors: dict[int, np.ndarray]) -> None:
    errors = []
    index = PlaceIndex(PlaceSettings(max_distance=2.0))
    for loop in pairs.kitti00_loop_pairs():
        index = PlaceIndex(PlaceSettings(max_distance=2.0, ring_candidates=1))
        index.add(loop.i, descriptors[loop.i])
        (found,) = index.query(descriptors[loop.j])
        yaw_icp = np.degrees(np.arctan2(loop.T_icp[1, 0], loop.T_icp[0, 0]))  # R_i_j: j's frame onto i's
        errors.append(abs((found.yaw_deg - yaw_icp + 180.0) % 360.0 - 180.0))
    errors_sorted = sorted(errors)
    assert errors_sorted[-2] <= 3.5 and errors_sorted[-1] <= 12.0, errors


def test_a_revisit_partner_is_the_best_candidate_for_most_sweeps(descriptors: dict[int, np.ndarray]) -> None:
    partners: dict[int, set[int]] = {}
    for loop in pairs.kitti00_loop_pairs():
        partners.setdefault(loop.i, set()).add(loop.j)
        partners.setdefault(loop.j, set()).add(loop.i)
    index = PlaceIndex()
    for f in FRAMES:
        index.add(f, descriptors[f])
    hits = other = 0
    for q in FRAMES:
        found = index.query(descriptors[q], exclude={f for f in FRAMES if abs(f - q) < 50})
        if found and found[0].key in partners.get(q, set()):
            hits += 1
        elif found:
            other += 1
        assert all(c.distance <= index.settings.max_distance for c in found)
    assert len(partners) == 23
    assert hits >= 14 and other <= 4, (hits, other)


def test_a_turned_copy_matches_itself_at_its_yaw_and_a_shifted_one_does_not() -> None:
    sweep = pairs.kitti00_loops_velodyne(120)
    c, s = np.cos(np.radians(42.0)), np.sin(np.radians(42.0))
    turned = sweep @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T  # the sensor turned by -42 deg
    index = PlaceIndex()
    index.add("original", scan_context(sweep))
    (found,) = index.query(scan_context(turned))
    assert found.distance < 0.1
    assert abs(found.yaw_deg - (-42.0)) <= 6.0  # R_original_turned = Rz(-42)
    far = scan_context(sweep + [30.0, 0.0, 0.0])
    d, _ = scan_context_distance(far, scan_context(sweep)[None])
    assert d[0] > 0.3


def test_bad_input_is_named() -> None:
    with pytest.raises(InvalidCloudError, match="no finite point"):
        scan_context(np.full((10, 3), np.nan))
    with pytest.raises(InvalidCloudError, match=r"\(N, 3\)"):
        scan_context(np.zeros(5))
    index = PlaceIndex()
    with pytest.raises(InvalidRequestError, match="must be finite"):
        index.add("x", np.zeros((3, 3)))
    assert index.query(np.zeros((20, 60))) == []
