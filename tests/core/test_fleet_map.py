"""FleetMapper's input checks and placement on real sweeps, without the simulator (fast).

The end-to-end fleet, with GNSS, loops and a session without GNSS, is tests/sim/test_scenarios.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from randt.core.errors import InvalidCloudError, InvalidRequestError
from randt.core.fleet_map import FleetMapper, FleetMapSettings, placement_vote
from tests import pairs


def test_a_bad_keyframe_is_refused_whole_and_names_what_was_wrong() -> None:
    mapper = FleetMapper()
    points = pairs.kitti00_loops_velodyne(120)
    with pytest.raises(InvalidRequestError, match="finite 4x4 pose"):
        mapper.add_keyframe("a", np.full((4, 4), np.nan), points)
    with pytest.raises(InvalidCloudError, match="keyframe of 'a'"):
        mapper.add_keyframe("a", np.eye(4), np.full((20, 3), np.nan))
    with pytest.raises(InvalidRequestError, match="position \\(3,\\) and a 3x3 covariance"):
        mapper.add_keyframe("a", np.eye(4), points, gnss=(np.zeros(2), np.eye(3)))
    with pytest.raises(InvalidRequestError, match="positive definite"):
        mapper.add_keyframe("a", np.eye(4), points, gnss=(np.zeros(3), -np.eye(3)))
    assert mapper.sessions == {}  # nothing was kept


def test_a_gnss_session_is_placed_once_its_fixes_span_the_alignment_distance() -> None:
    """Four keyframes 15 m apart along x with fixes in a world rotated 90 deg and shifted: the
    session is placed by the fit, its keyframes at the fixes."""
    mapper = FleetMapper()
    points = pairs.kitti00_loops_velodyne(120)
    world = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    for k in range(4):
        T = np.eye(4)
        T[0, 3] = 15.0 * k
        fix = world @ T[:3, 3] + [100.0, 50.0, 0.0]
        mapper.add_keyframe("a", T, points, gnss=(fix, np.eye(3) * 0.01))
        assert mapper.placed_sessions() == ([] if k < 3 else ["a"])  # 45 m >= 40 m at the 4th
    poses = mapper.poses()
    assert len(poses) == 4
    assert np.allclose(poses[("a", 3)][:3, 3], [100.0, 95.0, 0.0], atol=0.05)
    assert np.allclose(poses[("a", 3)][:3, :3], world, atol=1e-3)


def test_a_session_placed_where_its_frame_is_known_enters_the_graph_at_once() -> None:
    """``place`` (the service's sessions, whose poses are in their map's frame): keyframes go
    into the graph as they come, at their odometry poses moved by the placement; a second
    placement, or one that is not a finite pose, is refused."""
    mapper = FleetMapper()
    points = pairs.kitti00_loops_velodyne(120)
    where = np.eye(4)
    where[:3, 3] = [5.0, -3.0, 0.0]
    mapper.place("a", where)
    assert mapper.placed_sessions() == ["a"]
    for k in range(3):
        T = np.eye(4)
        T[0, 3] = 10.0 * k
        mapper.add_keyframe("a", T, points)
        assert len(mapper.poses()) == k + 1
    assert np.allclose(mapper.poses()[("a", 2)][:3, 3], [25.0, -3.0, 0.0], atol=1e-6)
    with pytest.raises(InvalidRequestError, match="placed already"):
        mapper.place("a", np.eye(4))
    with pytest.raises(InvalidRequestError, match="finite 4x4 pose"):
        mapper.place("b", np.full((4, 4), np.inf))
    assert "b" not in mapper.sessions


def test_a_fix_with_attitude_holds_the_sessions_heading() -> None:
    """A vehicle's prior pose (GNSS/INS) with its 6x6 covariance is a whole-pose prior: a session
    whose only fix is its first keyframe's keeps the heading it gave (2 deg here: its keyframe 20 m
    on lies 0.70 m to the side), where a position alone leaves the heading to the odometry and the
    loops (issue 57: sessions turned about their first fix by up to 0.67 deg to meet the loops)."""
    points = pairs.kitti00_loops_velodyne(120)
    yaw = np.radians(2.0)
    fix = np.eye(4)
    fix[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    cov = np.diag([1e-4] * 3 + [np.radians(0.1) ** 2] * 3)
    side = {}
    for how, gnss in (("pose", (fix, cov)), ("position", (fix[:3, 3], cov[:3, :3]))):
        mapper = FleetMapper()
        mapper.place("a", np.eye(4))
        for k in range(3):
            T = np.eye(4)
            T[0, 3] = 10.0 * k
            mapper.add_keyframe("a", T, points, gnss=gnss if k == 0 else None)
        side[how] = float(mapper.poses()[("a", 2)][1, 3])
    assert side["pose"] == pytest.approx(20.0 * np.sin(yaw), abs=0.02)
    assert abs(side["position"]) < 0.01
    with pytest.raises(InvalidRequestError, match="6x6 covariance"):
        FleetMapper().add_keyframe("b", np.eye(4), points, gnss=(fix, np.eye(3)))


def test_every_kitti_revisit_at_keyframe_resolution_is_a_placement_vote() -> None:
    """The placement's own bar (randt.core.fleet_map.placement_vote: refined, 30 consistent
    correspondences, overlap 0.6) refuses no true registration of the 21 KITTI 00 revisits at the
    graph's keyframe resolution (measured: all refined, 35-305 correspondences, overlap
    0.64-0.97), each within 7 cm of the ICP reference."""
    from randt.core.global_registration import register_global
    from randt.core.transforms import transform_error
    from randt.core.voxel import voxel_downsample

    s = FleetMapSettings()
    votes = []
    for loop in pairs.kitti00_loop_pairs():
        a = voxel_downsample(pairs.kitti00_loops_velodyne(loop.j), s.keyframe_voxel_m)
        b = voxel_downsample(pairs.kitti00_loops_velodyne(loop.i), s.keyframe_voxel_m)
        result = register_global(a, b, s.global_registration)
        dt, _ = transform_error(result.T_target_source, loop.T_icp)
        votes.append((loop.i, loop.j, placement_vote(result, s), round(dt, 3)))
    assert len(votes) == 21
    refused = [v for v in votes if not (v[2][0] and v[3] < 0.07)]
    assert not refused, refused


def test_a_placement_vote_names_the_bar_it_missed() -> None:
    """A weak registration of a street that looks like another (as bench/service.py's town gave:
    32 and 41 consistent correspondences, refinement not kept) is no vote, and says why; without
    refinement in the settings only the counts decide."""
    from dataclasses import replace

    from randt.core.global_registration import register_global

    s = FleetMapSettings()
    points = pairs.kitti00_loops_velodyne(120)
    strong = register_global(points[::3], points[1::3], s.global_registration)
    assert strong.confident and strong.refined
    assert placement_vote(strong, s) == (True, "placement vote: waits for a second one that agrees")
    assert placement_vote(replace(strong, refined=False), s) == (
        False,
        "not a placement vote: NDT's refinement was not kept",
    )
    few = placement_vote(replace(strong, n_inliers=29), s)
    assert few == (False, "not a placement vote: 29 consistent correspondences, fewer than 30")
    low = placement_vote(replace(strong, overlap=0.55), s)
    assert low == (False, "not a placement vote: overlap 0.55 below 0.6")
    unrefined = FleetMapSettings(global_registration={"refine": False, "max_range_m": 60.0})
    assert placement_vote(replace(strong, refined=False), unrefined)[0]
