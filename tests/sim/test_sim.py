"""LiDAR simulator: analytic intersections, scans against the geometry, exact ground truth, fleets."""

from __future__ import annotations

import numpy as np
import pytest

from randt.sim import (
    GROUND_MATERIALS,
    Boxes,
    Cylinders,
    Lidar64,
    Material,
    Motion,
    Route,
    Spheres,
    Town,
    cast_rays,
    plan_fleet,
    simulate,
    simulate_fleet,
)
from randt.sim.lidar import (
    NO_RETURN,
    hdl64e_elevations_deg,
    intersect_boxes,
    intersect_cylinders,
    intersect_ground,
    intersect_spheres,
)

SMALL = Lidar64(n_azimuth=360)  # 1 deg columns: 23k rays, for the tests that need many scans
EXACT = Lidar64(n_azimuth=360, range_noise_m=0.0)


def _ray(origin, direction) -> tuple[np.ndarray, np.ndarray]:
    d = np.asarray(direction, dtype=np.float64)
    return np.asarray(origin, dtype=np.float64)[None], (d / np.linalg.norm(d))[None]


def _to_world(scan) -> np.ndarray:
    T = scan.T_world_sensor
    return scan.points_xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3]


@pytest.fixture(scope="module")
def town() -> Town:
    return Town.generate(7)


@pytest.fixture(scope="module")
def route(town: Town) -> Route:
    return Route.loop(town, 3, length_m=600.0)


# ---------------------------------------------------------------------------- intersections
def test_box_face_at_known_distance() -> None:
    o, d = _ray([0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    t, cos = intersect_boxes(o, d, np.array([[10.0, 0.0, 1.0]]), np.array([[2.0, 1.0, 1.0]]), np.array([0.0]))
    assert t[0] == pytest.approx(8.0, abs=1e-12) and cos[0] == pytest.approx(1.0)
    # a unit box yawed 45 deg at (10, 0): the ray y = 0.5 enters through its face y' = +1, the line
    # y - x = sqrt(2) - 10, at x = 10.5 - sqrt(2) (the face x' = -1 bounds the slab it is already in)
    o, d = _ray([0.0, 0.5, 0.0], [1.0, 0.0, 0.0])
    t, cos = intersect_boxes(o, d, np.array([[10.0, 0.0, 0.0]]), np.ones((1, 3)), np.array([np.pi / 4]))
    assert t[0] == pytest.approx(10.5 - np.sqrt(2.0), abs=1e-12)
    assert cos[0] == pytest.approx(np.sqrt(0.5), abs=1e-12)
    # the top face seen from above at 45 deg
    o, d = _ray([0.0, 0.0, 5.0], [1.0, 0.0, -1.0])
    t, cos = intersect_boxes(o, d, np.array([[4.0, 0.0, 0.5]]), np.array([[1.0, 1.0, 0.5]]), np.array([0.0]))
    assert t[0] == pytest.approx(4.0 * np.sqrt(2.0), abs=1e-12) and cos[0] == pytest.approx(np.sqrt(0.5))
    # misses: pointing away, passing above, starting inside
    box = (np.array([[10.0, 0.0, 1.0]]), np.array([[2.0, 1.0, 1.0]]), np.array([0.0]))
    assert np.isinf(intersect_boxes(*_ray([0, 0, 1], [-1, 0, 0]), *box)[0][0])
    assert np.isinf(intersect_boxes(*_ray([0, 0, 2.5], [1, 0, 0]), *box)[0][0])
    assert np.isinf(intersect_boxes(*_ray([10, 0, 1], [1, 0, 0]), *box)[0][0])


def test_cylinder_side_and_cap() -> None:
    cyl = (np.array([[5.0, 0.0]]), np.array([0.5]), np.array([0.0]), np.array([3.0]))
    t, cos = intersect_cylinders(*_ray([0.0, 0.0, 1.0], [1.0, 0.0, 0.0]), *cyl)
    assert t[0] == pytest.approx(4.5, abs=1e-12) and cos[0] == pytest.approx(1.0)
    # off-axis by 0.3 m: the chord's half length is sqrt(0.5^2 - 0.3^2) = 0.4, the normal's cos 0.8
    t, cos = intersect_cylinders(*_ray([0.0, 0.3, 1.0], [1.0, 0.0, 0.0]), *cyl)
    assert t[0] == pytest.approx(4.6, abs=1e-12) and cos[0] == pytest.approx(0.8, abs=1e-12)
    # diagonal ray to a cylinder at (5, 5): 5 sqrt(2) - r
    t, _ = intersect_cylinders(
        *_ray([0.0, 0.0, 1.0], [1.0, 1.0, 0.0]),
        np.array([[5.0, 5.0]]),
        np.array([0.5]),
        np.zeros(1),
        np.ones(1) * 3,
    )
    assert t[0] == pytest.approx(5.0 * np.sqrt(2.0) - 0.5, abs=1e-12)
    assert np.isinf(intersect_cylinders(*_ray([0.0, 0.0, 4.0], [1.0, 0.0, 0.0]), *cyl)[0][0])  # above the top
    t, cos = intersect_cylinders(*_ray([5.0, 0.2, 10.0], [0.0, 0.0, -1.0]), *cyl)  # down onto the top cap
    assert t[0] == pytest.approx(7.0, abs=1e-12) and cos[0] == pytest.approx(1.0)


def test_sphere_distances() -> None:
    sph = (np.array([[10.0, 0.0, 2.0]]), np.array([2.0]))
    t, cos = intersect_spheres(*_ray([0.0, 0.0, 2.0], [1.0, 0.0, 0.0]), *sph)
    assert t[0] == pytest.approx(8.0, abs=1e-12) and cos[0] == pytest.approx(1.0)
    t, cos = intersect_spheres(*_ray([0.0, 1.0, 2.0], [1.0, 0.0, 0.0]), *sph)
    assert t[0] == pytest.approx(10.0 - np.sqrt(3.0), abs=1e-12)
    assert cos[0] == pytest.approx(np.sqrt(3.0) / 2.0, abs=1e-12)
    assert np.isinf(intersect_spheres(*_ray([0.0, 2.5, 2.0], [1.0, 0.0, 0.0]), *sph)[0][0])


def test_ground_at_an_angle_and_on_a_slope() -> None:
    el = np.radians(-24.8)
    t, cos = intersect_ground(*_ray([0.0, 0.0, 1.73], [np.cos(el), 0.0, np.sin(el)]))
    assert t[0] == pytest.approx(1.73 / np.sin(np.radians(24.8)), abs=1e-12)
    assert t[0] * np.cos(el) == pytest.approx(1.73 / np.tan(np.radians(24.8)), abs=1e-12)
    assert cos[0] == pytest.approx(np.sin(np.radians(24.8)), abs=1e-12)
    # ground z = 0.1 x: a level ray at z = 2 meets the rising ground at x = 20; rays upward never
    t, _ = intersect_ground(*_ray([0.0, 0.0, 2.0], [1.0, 0.0, 0.0]), np.array([0.1, 0.0]))
    assert t[0] == pytest.approx(20.0, abs=1e-12)
    assert np.isinf(intersect_ground(*_ray([0.0, 0.0, 2.0], [0.0, 0.0, 1.0]))[0][0])


def test_cast_rays_takes_the_nearest_surface() -> None:
    town = Town(
        Boxes([[20.0, 0.0, 5.0]], [[1.0, 10.0, 5.0]], [0.0], [Material.BUILDING], [0.5]),
        Cylinders([[10.0, 0.0]], [0.2], [0.0], [6.0], [Material.POLE], [0.5]),
        Spheres([[0.0, 15.0, 3.0]], [2.0], [Material.FOLIAGE], [0.4]),
    )
    o = np.tile([0.0, 0.0, 1.73], (5, 1))
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.0, 1.0, 0.1], [-1.0, 0.0, -0.2], [-1.0, 0.0, 0.0]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hits = cast_rays(town, o, d, max_range_m=120.0, min_range_m=1.0)
    sphere_t = intersect_spheres(o[2], d[2], np.array([0.0, 15.0, 3.0]), np.array(2.0))[0]
    expected = [9.8, 19.0 / d[1, 0], sphere_t, 1.73 / 0.2 * np.linalg.norm([1.0, 0.2]), np.inf]
    np.testing.assert_allclose(hits.range_m, expected, rtol=0, atol=1e-9)
    assert hits.material.tolist() == [
        Material.POLE,
        Material.BUILDING,
        Material.FOLIAGE,
        Material.SIDEWALK,
        NO_RETURN,
    ]
    near = cast_rays(town, o[:1], d[:1], max_range_m=120.0, min_range_m=10.0)  # the pole blocks, too close
    assert np.isinf(near.range_m[0]) and near.material[0] == NO_RETURN
    assert np.isinf(cast_rays(town, o[:1], d[:1], max_range_m=9.0).range_m[0])


def test_culling_loses_no_hit(town: Town, route: Route) -> None:
    """Chunked culling and batching give exactly the brute-force nearest hit over all primitives."""
    lidar = Lidar64(n_azimuth=120)
    T = Motion(route, speed_mps=10.0).sensor_poses_at(np.arange(120) / 1200.0)
    dirs = np.matmul(lidar.ray_directions, T[:, :3, :3].transpose(0, 2, 1)).reshape(-1, 3)
    origins = np.repeat(T[:, :3, 3], 64, axis=0)
    # chunks of 8 columns x 64 rings (~24 deg azimuth, 27 deg elevation)
    fast = cast_rays(town, origins, dirs, max_range_m=120.0, chunk_rays=512)
    t_ground, cos_ground = intersect_ground(origins, dirs)
    o, d = origins[:, None], dirs[:, None]
    b, c, s = town.boxes, town.cylinders, town.spheres
    per_kind = [  # (M,K) distances and incidences of every ray against every primitive, materials
        (*intersect_boxes(o, d, b.centre_xyz[None], b.half_extents_xyz[None], b.yaw_rad[None]), b.material),
        (
            *intersect_cylinders(o, d, c.centre_xy[None], c.radius_m[None], c.z_min_m[None], c.z_max_m[None]),
            c.material,
        ),
        (*intersect_spheres(o, d, s.centre_xyz[None], s.radius_m[None]), s.material),
    ]
    t_all = np.column_stack([t_ground] + [t for t, _, _ in per_kind])
    cos_all = np.column_stack([cos_ground] + [np.broadcast_to(cos, t.shape) for t, cos, _ in per_kind])
    nearest = np.argmin(t_all, axis=1)
    rows = np.arange(len(t_all))
    best = t_all[rows, nearest]
    best[best > 120.0] = np.inf
    np.testing.assert_array_equal(np.isfinite(fast.range_m), np.isfinite(best))
    np.testing.assert_allclose(fast.range_m, best, rtol=0, atol=1e-9)
    assert np.isfinite(best).mean() > 0.9
    # the surface hit: its incidence, and a primitive's material (the ground's from the town)
    hit = np.isfinite(best)
    np.testing.assert_allclose(fast.cos_incidence[hit], cos_all[rows, nearest][hit], rtol=0, atol=1e-12)
    materials = np.concatenate([m for _, _, m in per_kind])
    on_prim = hit & (nearest > 0)
    np.testing.assert_array_equal(fast.material[on_prim], materials[nearest[on_prim] - 1])
    ground = hit & (nearest == 0)
    xy = origins[ground, :2] + best[ground, None] * dirs[ground, :2]
    np.testing.assert_array_equal(fast.material[ground], town.ground_material(xy))
    assert on_prim.sum() > 1000 and ground.sum() > 1000


# ---------------------------------------------------------------------------- the town
def test_town_is_deterministic_and_in_spec(town: Town) -> None:
    again = Town.generate(7)
    np.testing.assert_array_equal(again.boxes.centre_xyz, town.boxes.centre_xyz)
    np.testing.assert_array_equal(again.spheres.radius_m, town.spheres.radius_m)
    assert not np.array_equal(Town.generate(8).boxes.centre_xyz[:5], town.boxes.centre_xyz[:5])
    assert town.extent_m <= 400.0 and town.street_coords_m.size >= 2
    np.testing.assert_allclose(np.diff(town.street_coords_m), 72.0)
    b = town.boxes
    buildings = b.material == Material.BUILDING
    size = 2.0 * b.half_extents_xyz[buildings]
    assert buildings.sum() >= 40
    assert np.all((size[:, :2] >= 10.0 - 1e-9) & (size[:, :2] <= 40.0 + 1e-9))
    assert np.any(b.yaw_rad[buildings] != 0.0) and np.abs(b.yaw_rad[buildings]).max() <= np.radians(8.0)
    tops = b.centre_xyz[buildings, 2] + b.half_extents_xyz[buildings, 2]
    assert np.all((tops >= 6.0) & (tops <= 25.0))
    cars = 2.0 * b.half_extents_xyz[b.material == Material.CAR]
    assert (
        cars.shape[0] >= 50
        and np.all(np.abs(cars[:, 0] - 4.5) < 0.5)
        and np.all(np.abs(cars[:, 1] - 1.8) < 0.2)
    )
    c = town.cylinders
    poles = c.material == Material.POLE
    assert poles.sum() >= 50 and np.all((c.radius_m[poles] >= 0.1) & (c.radius_m[poles] <= 0.2))
    assert np.all((c.z_max_m[poles] >= 5.0) & (c.z_max_m[poles] <= 8.0))
    assert len(town.spheres) == (c.material == Material.TRUNK).sum() > 20
    # buildings stand back from the streets: footprint corners beyond kerb + sidewalk + 1 m setback
    y, h, ctr = b.yaw_rad[buildings], b.half_extents_xyz[buildings], b.centre_xyz[buildings]
    corners = np.stack([np.array([sx, sy]) for sx in (-1, 1) for sy in (-1, 1)])[None] * h[:, None, :2]
    R = np.stack([np.cos(y), -np.sin(y), np.sin(y), np.cos(y)], -1).reshape(-1, 1, 2, 2)
    xy = (R @ corners[..., None])[..., 0] + ctr[:, None, :2]
    off = np.abs(xy[..., None] - town.street_coords_m).min(axis=-1)
    assert off.min() >= 6.0 + 3.0 + 1.0 - 1e-6


def test_many_seeds_and_layouts_generate() -> None:
    for seed in range(25):
        town = Town.generate(seed)
        assert len(town.boxes) > 100 and len(town.cylinders) > 100
        Route.loop(town, seed, length_m=500.0)
    for kwargs in (
        {"size_m": 250.0},
        {"block_m": 40.0},
        {"block_m": 90.0},
        {"size_m": 800.0, "slope_pct": 2.0},
    ):
        town = Town.generate(1, **kwargs)
        assert town.extent_m <= kwargs.get("size_m", 400.0) and town.street_coords_m.size >= 2
        Route.random_walk(town, 1, length_m=600.0)
    with pytest.raises(ValueError):
        Town.generate(0, size_m=150.0)  # fewer than 3 blocks per axis


@pytest.mark.parametrize("kind", ["loop", "random_walk"])
def test_routes_stay_in_the_lane_clear_of_everything(town: Town, kind: str) -> None:
    route = getattr(Route, kind)(town, 11, length_m=800.0)
    assert route.length_m >= (800.0 if kind == "random_walk" else 0.5 * 800.0)
    s = np.arange(0.0, route.length_m, 0.5)
    xy, heading = route.xy_heading_at(s)
    # continuous position and heading (no jumps between pieces)
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    assert step.max() <= 0.5 + 1e-9 and np.abs(np.diff(np.unwrap(heading))).max() < 0.5 / 9.0 + 1e-9
    # a 1.8 m wide vehicle body (at z = 0.5, 1.0, 1.5 m) keeps 0.9 m + 0.1 m from every primitive
    body = np.concatenate([np.column_stack([xy, np.full(len(s), z)]) for z in (0.5, 1.0, 1.5)])
    clearance = min(prim.surface_distance(body).min() for prim in town.primitives())
    assert clearance > 1.0
    b = town.boxes  # and not inside any box
    rel = body[:, None, :] - b.centre_xyz[None]
    c, sn = np.cos(b.yaw_rad), np.sin(b.yaw_rad)
    q = np.stack([c * rel[..., 0] + sn * rel[..., 1], -sn * rel[..., 0] + c * rel[..., 1], rel[..., 2]], -1)
    assert not np.any(np.all(np.abs(q) <= b.half_extents_xyz[None], axis=-1))
    if kind == "loop":
        np.testing.assert_allclose(route.pose_at(route.length_m), route.pose_at(0.0), atol=1e-9)
    else:
        with pytest.raises(ValueError):
            route.pose_at(route.length_m + 1.0)


# ---------------------------------------------------------------------------- scans
def test_full_scan_point_count_range_and_ground_ring(town: Town, route: Route) -> None:
    lidar = Lidar64()
    scan = next(simulate(town, route, n_scans=1, seed=5, lidar=lidar, deskewed=False, start_s_m=30.0))
    n = len(scan)
    assert 80_000 <= n <= 140_000
    assert scan.points_xyz.dtype == np.float32 and scan.intensity.dtype == np.float32
    assert scan.time_offset_s.dtype == np.float64
    assert scan.time_offset_s.min() >= 0.0 and scan.time_offset_s.max() < 0.1
    assert np.all(np.diff(scan.time_offset_s) >= 0.0)  # firing order
    r = np.linalg.norm(scan.points_xyz.astype(np.float64), axis=1)
    assert r.max() <= lidar.max_range_m + 1e-4 and r.min() >= lidar.min_range_m - 1e-4
    assert scan.intensity.min() >= 0.0 and scan.intensity.max() <= 1.0
    # lowest beam (ring 63, -24.8 deg) on the ground: a circle of radius 1.73 / tan(24.8 deg)
    low = (scan.ring == 63) & np.isin(scan.label, GROUND_MATERIALS)
    assert low.sum() > 0.5 * lidar.n_azimuth
    rho = np.hypot(scan.points_xyz[low, 0], scan.points_xyz[low, 1])
    expected = 1.73 / np.tan(np.radians(24.8))
    sigma_rho = lidar.range_noise_m * np.cos(np.radians(24.8))
    assert np.abs(rho - expected).max() < 5.0 * sigma_rho
    assert abs(rho.mean() - expected) < 5.0 * sigma_rho / np.sqrt(low.sum())
    np.testing.assert_allclose(scan.points_xyz[low, 2], -1.73, atol=5.0 * lidar.range_noise_m)
    np.testing.assert_allclose(hdl64e_elevations_deg()[[0, 31, 32, 63]], [2.0, -8.33, -8.83, -24.8])


def test_a_corner_is_driven_as_a_car_drives_it(town: Town, route: Route) -> None:
    lidar = Lidar64(n_azimuth=32)
    entry = np.flatnonzero(route.curvature_rate_per_m2 > 0.0)[0]
    start = route.start_s_m[entry] - 40.0  # from the straight before a corner through it
    scans = list(simulate(town, route, n_scans=60, seed=1, lidar=lidar, speed_mps=10.0, start_s_m=start))
    s = np.array([sc.route_s_m for sc in scans])
    step = np.diff(s)
    np.testing.assert_allclose(step[:5], 1.0, atol=1e-6)  # 10 m/s on the straight
    assert 0.515 < step.min() < 0.53  # 5.2 m/s at the apex: 3 m/s^2 on the 9 m arc
    p = np.array([sc.T_world_sensor[:3, 3] for sc in scans])
    chord = np.linalg.norm(np.diff(p, axis=0), axis=1)
    np.testing.assert_allclose(chord, step, atol=2e-3)  # chords of the same arc lengths
    # the pose is the route's pose raised by the mount, x along the route heading
    for sc in scans[::7]:
        T_v = route.pose_at(sc.route_s_m)
        np.testing.assert_allclose(sc.T_world_sensor[:3, :3], T_v[:3, :3], atol=1e-12)
        np.testing.assert_allclose(sc.T_world_sensor[:3, 3], T_v[:3, 3] + [0.0, 0.0, 1.73], atol=1e-12)
    assert [sc.stamp_ns for sc in scans[:3]] == [0, 100_000_000, 200_000_000]
    # finely in time: lateral acceleration within 3 m/s^2, braking and accelerating within the
    # limits, and a yaw rate that changes by a few deg/s per sweep (it jumped by 64 deg/s before)
    motion = Motion(route, speed_mps=10.0, start_s_m=start)
    t = np.arange(0.0, 6.0, 0.01)
    s_fine = motion.s_at(t)
    v = np.diff(s_fine) / 0.01
    assert np.max(np.abs(route.curvature_at(s_fine[1:])) * v**2) < 3.0 + 0.02
    accel = np.diff(v) / 0.01
    assert accel.min() > -2.5 - 0.3 and accel.max() < 1.5 + 0.3  # finite differences of a 5 cm table
    yaw_rate = np.degrees(np.diff(np.unwrap(route.xy_heading_at(s_fine)[1]))) / 0.01
    assert np.degrees(np.abs(route.curvature_at(s_fine)).max()) * v.min() > 30.0  # really turned
    assert np.abs(yaw_rate[10:] - yaw_rate[:-10]).max() < 6.0  # per 0.1 s


def test_plain_arcs_and_constant_speed_remain_available(town: Town) -> None:
    corners = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 80.0], [0.0, 80.0]])
    plain = Route.from_corners(corners, closed=True, transition_m=0.0)
    assert np.all(plain.curvature_rate_per_m2 == 0.0)
    np.testing.assert_allclose(plain.length_m, 2 * (100 + 80) - 4 * 9.0 * (2.0 - np.pi / 2), atol=1e-9)
    motion = Motion(plain, speed_mps=10.0, max_lateral_mps2=np.inf)
    np.testing.assert_allclose(np.diff(motion.s_at(np.arange(0.0, 40.0, 0.1))), 1.0, atol=1e-6)
    np.testing.assert_allclose(motion.lap_time_s, plain.length_m / 10.0, rtol=1e-9)
    smooth = Route.from_corners(corners, closed=True)  # clothoids: continuous curvature, closed loop
    s = np.arange(0.0, smooth.length_m, 0.01)
    assert np.abs(np.diff(smooth.curvature_at(s))).max() < 0.01 * (1 / 9.0) / 8.0 + 1e-12
    xy, heading = smooth.xy_heading_at(s)
    chord_heading = np.arctan2(*np.diff(xy, axis=0).T[::-1])
    mid = 0.5 * (np.unwrap(heading)[1:] + np.unwrap(heading)[:-1])
    assert np.abs(np.angle(np.exp(1j * (chord_heading - mid)))).max() < 1e-6  # heading is the tangent
    np.testing.assert_allclose(smooth.pose_at(smooth.length_m), smooth.pose_at(0.0), atol=1e-9)


@pytest.mark.parametrize("deskewed", [True, False])
def test_points_lie_on_the_town_surfaces(town: Town, route: Route, deskewed: bool) -> None:
    """Noise-free points, mapped by the ground truth, lie on the surfaces (exact up to float32)."""
    scan = next(simulate(town, route, n_scans=1, seed=2, lidar=EXACT, deskewed=deskewed, start_s_m=50.0))
    if deskewed:
        world = _to_world(scan)
    else:  # each point in its firing-time frame: the exact per-point poses undo the motion
        T = Motion(route, speed_mps=10.0, start_s_m=50.0).sensor_poses_at(scan.time_offset_s)
        world = np.einsum("nij,nj->ni", T[:, :3, :3], scan.points_xyz.astype(np.float64)) + T[:, :3, 3]
        skewed = _to_world(scan)  # read in one frame, the raw sweep is off by up to speed/rate
        assert np.quantile(town.surface_distance(skewed), 0.99) > 0.3
    d = town.surface_distance(world)
    assert d.max() < 1e-3
    ground = np.isin(scan.label, GROUND_MATERIALS)
    assert np.abs(world[ground, 2]).max() < 1e-3 and ground.mean() > 0.3
    assert np.all(world[~ground, 2] > -1e-3)


def test_noisy_points_within_five_sigma(town: Town, route: Route) -> None:
    scan = next(simulate(town, route, n_scans=1, seed=4, lidar=SMALL, start_s_m=200.0))
    world = _to_world(scan)
    ground = np.isin(scan.label, GROUND_MATERIALS)
    assert np.abs(world[ground, 2]).max() < 5 * SMALL.range_noise_m
    d = town.surface_distance(world)
    assert d.max() < 5 * SMALL.range_noise_m
    assert np.std(d) > 0.3 * SMALL.range_noise_m  # the noise is really there
    assert 0.03 < 1.0 - len(scan) / (SMALL.n_azimuth * 64) < 0.3  # dropouts (4 %) and sky


def test_sloped_town_poses_follow_the_ground() -> None:
    town = Town.generate(3, slope_pct=3.0)
    assert np.linalg.norm(town.ground_gradient) == pytest.approx(0.03)
    route = Route.loop(town, 1, length_m=500.0)
    scan = next(simulate(town, route, n_scans=1, seed=0, lidar=EXACT, start_s_m=10.0))
    n = town.ground_normal()
    T = scan.T_world_sensor
    np.testing.assert_allclose(T[:3, 2], n, atol=1e-12)
    assert (T[:3, 3] - 1.73 * n) @ n == pytest.approx(0.0, abs=1e-9)  # vehicle origin on the plane
    world = _to_world(scan)
    ground = np.isin(scan.label, GROUND_MATERIALS)
    assert np.abs(world[ground] @ n).max() < 1e-3
    assert town.surface_distance(world).max() < 1e-3


def test_same_seed_same_scans(town: Town, route: Route) -> None:
    def run(seed: int) -> list:
        return list(simulate(town, route, n_scans=2, seed=seed, lidar=SMALL, speed_variation=0.2))

    a, b, c = run(9), run(9), run(10)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.points_xyz, y.points_xyz)
        np.testing.assert_array_equal(x.intensity, y.intensity)
        np.testing.assert_array_equal(x.time_offset_s, y.time_offset_s)
        np.testing.assert_array_equal(x.T_world_sensor, y.T_world_sensor)
    assert not np.array_equal(a[0].points_xyz[:100], c[0].points_xyz[:100])
    assert a[1].route_s_m != pytest.approx(1.0)  # the speed varies


def test_worker_processes_give_the_same_scans_in_order(town: Town, route: Route) -> None:
    """``workers``: the sweeps ray cast ahead in other processes are those computed in this one,
    in order, bit for bit; a consumer that stops early stops the processes."""
    kw = {"n_scans": 11, "seed": 4, "lidar": SMALL, "speed_variation": 0.2, "deskewed": False}
    here = list(simulate(town, route, **kw))
    there = list(simulate(town, route, workers=2, **kw))
    assert [s.index for s in there] == list(range(11))
    for x, y in zip(here, there, strict=True):
        np.testing.assert_array_equal(x.points_xyz, y.points_xyz)
        np.testing.assert_array_equal(x.time_offset_s, y.time_offset_s)
        np.testing.assert_array_equal(x.T_world_sensor, y.T_world_sensor)
        assert (x.stamp_ns, x.route_s_m) == (y.stamp_ns, y.route_s_m)
    stream = simulate(town, route, workers=1, **kw)
    assert next(stream).index == 0
    stream.close()  # type: ignore[attr-defined]  # (a generator)
    with pytest.raises(ValueError, match="workers"):
        simulate(town, route, workers=-1, **kw)
    # a drive's end alone (first_index): the same sweeps as the whole drive's, in both modes
    for workers in (0, 2):
        tail = list(simulate(town, route, workers=workers, first_index=8, **kw))
        assert [s.index for s in tail] == [8, 9, 10]
        for x, y in zip(here[8:], tail, strict=True):
            np.testing.assert_array_equal(x.points_xyz, y.points_xyz)
            assert (x.stamp_ns, x.route_s_m) == (y.stamp_ns, y.route_s_m)
    with pytest.raises(ValueError, match="first_index"):
        simulate(town, route, first_index=12, **kw)


def test_fleet_vehicles_take_different_routes(town: Town) -> None:
    fleet = plan_fleet(town, 3, seed=1, route_length_m=600.0)
    assert len({v.vehicle_id for v in fleet}) == 3
    lines = [v.route.polyline(5.0) for v in fleet]
    for i in range(3):
        for j in range(i + 1, 3):
            a, b = lines[i], lines[j]
            same = a.shape == b.shape and np.allclose(a, b)
            assert not same
    scans = list(simulate_fleet(town, 3, n_scans=2, seed=1, lidar=Lidar64(n_azimuth=32)))
    assert [vid for vid, _ in scans] == [v.vehicle_id for v in fleet] * 2
    stamps = [sc.stamp_ns for _, sc in scans]
    assert stamps == sorted(stamps) and len(set(stamps)) == 6
    starts = np.array([sc.T_world_sensor[:3, 3] for _, sc in scans[:3]])
    assert np.linalg.norm(starts[:, None] - starts[None], axis=-1)[np.triu_indices(3, 1)].min() > 5.0
    walks = plan_fleet(town, 2, seed=1, route_length_m=500.0, closed=False)
    assert not walks[0].route.closed and walks[0].route.length_m >= 500.0
    assert not np.allclose(walks[0].route.polyline(5.0)[:20], walks[1].route.polyline(5.0)[:20])


def test_bad_arguments_fail_at_the_call(town: Town) -> None:
    walk = Route.random_walk(town, 2, length_m=300.0)
    with pytest.raises(ValueError, match="open route"):
        simulate(town, walk, n_scans=int(1.5 * walk.length_m), lidar=SMALL)  # at most 1 m per scan: too far
    with pytest.raises(ValueError):
        simulate_fleet(town, 2, n_scans=1000, closed=False, route_length_m=300.0, lidar=SMALL)
    with pytest.raises(ValueError):
        Lidar64(dropout=1.0)
