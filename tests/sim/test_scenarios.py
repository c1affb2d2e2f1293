"""A small mapping fleet end to end, scored against the simulator's exact poses.

Three vehicles on overlapping routes of the town for a little more than one lap each, the third
without GNSS; the others' GNSS has 1 m noise, a 2 m wandering bias (4 m vertically), 1 % multipath
jumps and a 15 s outage. ``bench/fleet_map.py`` runs the issue's 2 km fleet and reports the same
figures. About a minute on 2 cores (92 s of CPU, quiet, 2026-11-29; the 1400 sweeps' simulation
about 32 s of it at 23 ms each): the sensor sees to 70 m instead of 120 (the town is small). At
5 Hz the odometry loses track, and with 600 instead of 1000 columns the session without GNSS met
the others too late to be placed within 1.1 laps.
"""

from __future__ import annotations

import pytest

from randt.sim.lidar import Lidar64
from randt.sim.scenarios import MappingRun, run_mapping_fleet


@pytest.fixture(scope="module")
def run() -> MappingRun:
    return run_mapping_fleet(n_vehicles=3, laps=1.15, lidar=Lidar64(n_azimuth=1000, max_range_m=70.0))


@pytest.mark.slow
def test_every_session_joins_the_shared_map_even_without_gnss(run: MappingRun) -> None:
    assert run.without_gnss == ["sim002"]
    assert sorted(run.placed) == sorted(run.sessions)
    assert set(run.graph) == set(run.truth)  # every keyframe of every session is in the graph


@pytest.mark.slow
def test_no_wrong_loop_enters_the_graph_and_loops_are_found(run: MappingRun) -> None:
    assert run.false_accepted == 0
    assert run.accepted >= 10
    # look-alike streets do fool single registrations: they stay votes, never graph edges
    assert all(ok for r, ok in zip(run.loops, run.loop_correct, strict=True) if r.accepted)


@pytest.mark.slow
def test_the_graph_map_is_far_more_consistent_than_odometry_placed_by_gnss(run: MappingRun) -> None:
    assert run.ate_graph_m < 0.6
    assert run.ate_odometry_m > 5 * run.ate_graph_m
