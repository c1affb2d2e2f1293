"""The shared real scan pairs (:mod:`randt.core.shared_data`) with the tests' accuracy bounds.

Each loader returns ``(source_xyz, target_xyz, T_target_source_reference)`` in the convention
``p_target = T @ p_source``; missing data skip the test (fail under ``CI=true``, :mod:`tests.data`).
"""

from __future__ import annotations

from randt.core import shared_data
from tests.data import skip_if_missing

small_gicp = skip_if_missing(shared_data.small_gicp)
argoverse2 = skip_if_missing(shared_data.argoverse2)
bunny = skip_if_missing(shared_data.bunny)
car = skip_if_missing(shared_data.car)
kitti00_velodyne = skip_if_missing(shared_data.kitti00_velodyne)
threedmatch = skip_if_missing(shared_data.threedmatch)
kitti00_loops_velodyne = skip_if_missing(shared_data.kitti00_loops_velodyne)
kitti00_loop_pairs = skip_if_missing(shared_data.kitti00_loop_pairs)
kitti00_loops_poses = skip_if_missing(shared_data.kitti00_loops_poses)

#: name -> (loader, translation tolerance m, rotation tolerance deg, perturbation scale m).
#: Issue 2's bounds are the best peer's accuracy (small_gicp pair 2 cm / 0.3 deg, Argoverse 2 cm /
#: 0.1 deg, bunny 5 mm / 1 deg, car 10 cm / 0.3 deg); where RANDT does better the bound is tightened
#: to about twice what it reaches (measured 2026-11-23 from the identity and 9 perturbed starts
#: each, all landing on the same fixed point: small_gicp 0.60 cm / 0.254 deg, Argoverse 0.32 cm /
#: 0.041 deg, bunny 0.10 mm / 0.099 deg, car 1.84 cm / 0.220 deg).
PAIRS = {
    "small_gicp": (small_gicp, 0.012, 0.3, 1.0),
    "argoverse2": (argoverse2, 0.006, 0.08, 1.0),
    "bunny": (bunny, 0.0005, 0.2, 0.02),
    "car": (car, 0.04, 0.3, 1.0),
}
