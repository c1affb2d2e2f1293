"""LiDAR simulator: a procedural town, an HDL-64E-like sensor and vehicles driving its streets.

It stands in for real vehicles where exact ground truth is needed: long runs, many vehicles, load
tests. ::

    from randt.sim import Route, Town, simulate

    town = Town.generate(seed=1)
    route = Route.loop(town, seed=2, length_m=600.0)
    for scan in simulate(town, route, n_scans=100, seed=3):
        ...  # scan.points_xyz (N,3) float32 sensor frame, scan.T_world_sensor exact

Modules: :mod:`~randt.sim.town` (scene), :mod:`~randt.sim.lidar` (ray casting, sensor),
:mod:`~randt.sim.drive` (routes, motion, scan and fleet streams).
"""

from randt.sim.drive import FleetVehicle, Motion, Route, SimScan, plan_fleet, simulate, simulate_fleet
from randt.sim.lidar import Lidar64, RayHits, cast_rays
from randt.sim.town import GROUND_MATERIALS, Boxes, Cylinders, Material, Spheres, Town

__all__ = [
    "GROUND_MATERIALS",
    "Boxes",
    "Cylinders",
    "FleetVehicle",
    "Lidar64",
    "Material",
    "Motion",
    "RayHits",
    "Route",
    "SimScan",
    "Spheres",
    "Town",
    "cast_rays",
    "plan_fleet",
    "simulate",
    "simulate_fleet",
]
