"""Localization on a fixed map (core/localizer.py), on real KITTI 00 revisits.

The map: the first-pass sweeps of ``kitti00_loops/`` (frames below 1000) placed by KITTI's ground
truth and folded into density-equalized tiles as the service folds them. Each second-pass sweep of
a revisit whose ICP reference is good (inlier fraction at least 0.6) is localized from priors 2 m
and 10 deg off; the reference is the first pass's ground truth x ``T_icp`` (itself good to about
7 cm and 0.45 deg: two references of one sweep differ by up to 10.9 cm).
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from randt.core.errors import InvalidCloudError, RegistrationFailedError
from randt.core.localizer import LocalizerSettings, MapLocalizer
from randt.core.shared_data import kitti00_loop_pairs, kitti00_loops_poses, kitti00_loops_velodyne
from randt.core.tiles import TileGrid
from randt.core.transforms import transform_error

FIRST_PASS_BELOW = 1000


def _offset(T: np.ndarray, shift_m: float, heading_deg: float, yaw_deg: float) -> np.ndarray:
    """``T`` moved ``shift_m`` towards ``heading_deg`` (sensor frame, horizontal) and turned ``yaw_deg``."""
    a, h = np.radians(yaw_deg), np.radians(heading_deg)
    P = np.eye(4)
    P[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    P[:3, 3] = (shift_m * np.cos(h), shift_m * np.sin(h), 0.0)
    return T @ P


@functools.cache
def _first_pass_map() -> TileGrid:
    poses = kitti00_loops_poses()
    grid = TileGrid(20, 0.2, 1)
    for frame in sorted(f for f in poses if f < FIRST_PASS_BELOW):
        T = poses[frame]
        grid.insert(kitti00_loops_velodyne(frame) @ T[:3, :3].T + T[:3, 3])
    return grid


def _localizer_at(T: np.ndarray, token: object = "kitti") -> MapLocalizer:
    grid = _first_pass_map()
    loc = MapLocalizer()
    r = loc.settings.window_radius_m
    window = loc.load(T[:2, 3], grid.points_in_bbox(T[:2, 3] - r, T[:2, 3] + r).xyz, token)
    assert window is not None
    return loc


def test_every_second_pass_sweep_lands_on_the_first_pass_map_from_2_m_and_10_deg_off() -> None:
    poses = kitti00_loops_poses()
    revisits = [p for p in kitti00_loop_pairs() if p.icp_inlier_fraction >= 0.6]
    assert len(revisits) == 10
    errors = []
    for loop in revisits:
        T_ref = poses[loop.i] @ loop.T_icp
        loc = _localizer_at(T_ref)
        sweep = kitti00_loops_velodyne(loop.j)
        for heading, yaw in [(0, 10), (90, -10), (180, 10), (270, -10), (45, -10), (225, 10)]:
            found = loc.localize(sweep, _offset(T_ref, 2.0, heading, yaw), predicted=False)
            dt, dr = transform_error(found.T_map_sensor, T_ref)
            errors.append((loop.i, loop.j, heading, yaw, round(100 * dt, 1), round(dr, 2), found.agrees))
            # and the next sweep's way: from a motion prediction near the pose found
            tracked = loc.localize(sweep, _offset(found.T_map_sensor, 0.3, heading, 1.0), predicted=True)
            dq, rq = transform_error(tracked.T_map_sensor, T_ref)
            errors.append((loop.i, loop.j, "predicted", 1, round(100 * dq, 1), round(rq, 2), tracked.agrees))
    bad = [e for e in errors if not (e[4] < 10.0 and e[5] < 0.5 and e[6])]
    assert not bad, bad
    # the covariance is the registration's, positive definite
    assert np.all(np.linalg.eigvalsh(found.covariance) > 0)


def test_a_prior_50_m_off_is_never_answered_as_agreeing() -> None:
    poses = kitti00_loops_poses()
    loop = next(p for p in kitti00_loop_pairs() if p.icp_inlier_fraction >= 0.7)
    T_ref = poses[loop.i] @ loop.T_icp
    loc = _localizer_at(T_ref)
    sweep = kitti00_loops_velodyne(loop.j)
    refused = 0
    for heading in (0, 90, 180, 270):
        try:
            found = loc.localize(sweep, _offset(T_ref, 50.0, heading, 0.0), predicted=False)
        except RegistrationFailedError:  # nothing of the map near the sweep: said so
            refused += 1
            continue
        dt, _ = transform_error(found.T_map_sensor, T_ref)
        assert not found.agrees or dt < 0.1, (heading, dt, found.score)


def test_a_window_is_loaded_again_after_reload_m_and_for_another_map() -> None:
    loc = MapLocalizer(LocalizerSettings(min_map_points=100, window_radius_m=30.0))
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-40, 40, (60_000, 3)) * (1, 1, 0.01)  # a flat floor
    assert loc.load(np.zeros(2), xyz, ("m", 1)) is not None
    T = np.eye(4)
    assert not loc.needs_window(T, ("m", 1))
    T[:2, 3] = (loc.settings.reload_m * 0.9, 0.0)
    assert not loc.needs_window(T, ("m", 1))
    T[:2, 3] = (loc.settings.reload_m * 1.1, 0.0)
    assert loc.needs_window(T, ("m", 1))
    assert loc.needs_window(np.eye(4), ("m", 2))  # the map changed
    assert loc.window is not None and loc.window.n_points < xyz.shape[0]  # only the points within reach


def test_where_the_map_is_missing_no_window_is_loaded_and_localizing_is_refused() -> None:
    loc = MapLocalizer()
    assert loc.load(np.zeros(2), np.zeros((10, 3)), "empty") is None
    with pytest.raises(InvalidCloudError, match="no map window"):
        loc.localize(np.zeros((100, 3)), np.eye(4), predicted=True)
