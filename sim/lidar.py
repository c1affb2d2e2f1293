"""Vectorized ray casting against a :class:`~randt.sim.town.Town`, and an HDL-64E-like sensor.

Ray-primitive intersections (ground plane, yawed boxes, capped vertical cylinders, spheres), each
returning the distance to the first hit and the cosine of incidence; :func:`cast_rays`, which culls
primitives per chunk of coherent rays and intersects the rest in a compiled loop
(:mod:`randt.sim._cast`); and :class:`Lidar64`, a Velodyne HDL-64E as in KITTI (64 beams, range
noise, dropouts, intensity from reflectivity and incidence). How the culling works and the
sensor's geometry: docs/clients.md, "The simulator".
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from randt.sim._cast import BOX, CYLINDER, SPHERE, chunk_stats, nearest_hits
from randt.sim.town import Boxes, Cylinders, PrimitiveBounds, Spheres, Town

__all__ = [
    "NO_RETURN",
    "Lidar64",
    "RayHits",
    "Sweep",
    "cast_rays",
    "hdl64e_elevations_deg",
    "intersect_boxes",
    "intersect_cylinders",
    "intersect_ground",
    "intersect_spheres",
]

log = logging.getLogger(__name__)

#: ``RayHits.material`` of a ray without a return.
NO_RETURN = 255

_EPS_T = 1e-9  # hits closer than this along the ray are ignored (the origin on a surface)


# ---------------------------------------------------------------------------------- intersections
def intersect_ground(
    origins: np.ndarray, dirs: np.ndarray, gradient: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Rays against the ground plane ``z = g · (x, y)``, hit from above only.

    Parameters
    ----------
    origins, dirs:
        (..., 3) world ray origins (m) and unit directions.
    gradient:
        (2,) ``g``; ``None`` is the plane z = 0.

    Returns
    -------
    t, cos_incidence:
        (...) float64 distance (m, ``inf`` for a miss) and ``|cos|`` of the incidence angle.
    """
    g = np.zeros(2) if gradient is None else np.asarray(gradient, dtype=np.float64)
    norm = np.sqrt(1.0 + g @ g)
    height = origins[..., 2] - origins[..., 0] * g[0] - origins[..., 1] * g[1]  # above the plane, * norm
    rate = dirs[..., 2] - dirs[..., 0] * g[0] - dirs[..., 1] * g[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -height / rate
    hit = (rate < 0.0) & (height >= 0.0) & (t > _EPS_T)
    return np.where(hit, t, np.inf), np.abs(rate) / norm


def intersect_boxes(
    origins: np.ndarray,
    dirs: np.ndarray,
    centre_xyz: np.ndarray,
    half_extents_xyz: np.ndarray,
    yaw_rad: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Rays against boxes yawed about z (slab method in the box frame).

    Parameters
    ----------
    origins, dirs:
        (..., 3) world ray origins (m) and unit directions.
    centre_xyz, half_extents_xyz:
        (..., 3) box centres and half sizes (m), broadcastable against the rays.
    yaw_rad:
        (...) box yaw about world z (rad).

    Returns
    -------
    t, cos_incidence:
        (...) float64 distance to the entering face (m, ``inf`` for a miss or an origin inside the
        box) and ``|cos|`` between the ray and that face's normal.
    """
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    rel = origins - centre_xyz
    o = (c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1], rel[..., 2])
    d = (c * dirs[..., 0] + s * dirs[..., 1], -s * dirs[..., 0] + c * dirs[..., 1], dirs[..., 2])
    t_near: np.ndarray | None = None
    t_far: np.ndarray | None = None
    cos_near: np.ndarray | None = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(3):  # the three slabs
            h = half_extents_xyz[..., axis]
            inv = 1.0 / d[axis]
            t1, t2 = (-h - o[axis]) * inv, (h - o[axis]) * inv
            lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
            if t_near is None:
                t_near, t_far = lo, hi
                cos_near = np.broadcast_to(np.abs(d[axis]), lo.shape)
            else:
                assert t_far is not None and cos_near is not None  # set with t_near on the first slab
                enter = lo > t_near
                cos_near = np.where(enter, np.abs(d[axis]), cos_near)
                t_near, t_far = np.maximum(t_near, lo), np.minimum(t_far, hi)
    assert t_near is not None and t_far is not None and cos_near is not None  # three slabs were cut
    hit = (t_near <= t_far) & (t_near > _EPS_T)
    return np.where(hit, t_near, np.inf), cos_near


def intersect_cylinders(
    origins: np.ndarray,
    dirs: np.ndarray,
    centre_xy: np.ndarray,
    radius_m: np.ndarray,
    z_min_m: np.ndarray,
    z_max_m: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Rays against vertical cylinders with caps at ``z_min_m`` and ``z_max_m``.

    Parameters
    ----------
    origins, dirs:
        (..., 3) world ray origins (m) and unit directions.
    centre_xy:
        (..., 2) axis positions (m), broadcastable against the rays.
    radius_m, z_min_m, z_max_m:
        (...) radii and cap heights (m).

    Returns
    -------
    t, cos_incidence:
        (...) float64 nearest hit of the side or a cap (m, ``inf`` for a miss) and ``|cos|``
        between the ray and the normal there (horizontal on the side, vertical on a cap).
    """
    px, py = origins[..., 0] - centre_xy[..., 0], origins[..., 1] - centre_xy[..., 1]
    oz = origins[..., 2]
    dx, dy, dz = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    a = dx * dx + dy * dy
    b = px * dx + py * dy  # half of the usual b
    r2 = radius_m * radius_m
    disc = b * b - a * (px * px + py * py - r2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
        z_side = oz + t_side * dz
        side = (disc >= 0.0) & (a > 1e-12) & (t_side > _EPS_T) & (z_side >= z_min_m) & (z_side <= z_max_m)
        cos_side = np.abs((px + t_side * dx) * dx + (py + t_side * dy) * dy) / radius_m
        t = np.where(side, t_side, np.inf)
        cos = np.where(side, cos_side, 0.0)
        for z_cap, toward in ((z_max_m, dz < 0.0), (z_min_m, dz > 0.0)):  # top seen from above, bottom
            t_cap = (z_cap - oz) / dz
            qx, qy = px + t_cap * dx, py + t_cap * dy
            cap = toward & (t_cap > _EPS_T) & (qx * qx + qy * qy <= r2) & (t_cap < t)
            t = np.where(cap, t_cap, t)
            cos = np.where(cap, np.abs(dz), cos)
    return t, cos


def intersect_spheres(
    origins: np.ndarray, dirs: np.ndarray, centre_xyz: np.ndarray, radius_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rays against spheres.

    Parameters
    ----------
    origins, dirs:
        (..., 3) world ray origins (m) and unit directions.
    centre_xyz:
        (..., 3) sphere centres (m), broadcastable against the rays.
    radius_m:
        (...) radii (m).

    Returns
    -------
    t, cos_incidence:
        (...) float64 distance to the near surface (m, ``inf`` for a miss or an origin inside)
        and ``|cos|`` between the ray and the radial normal there.
    """
    rel = origins - centre_xyz
    b = np.sum(rel * dirs, axis=-1)
    disc = b * b - (np.sum(rel * rel, axis=-1) - radius_m * radius_m)
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(np.maximum(disc, 0.0))
    hit = (disc >= 0.0) & (t > _EPS_T)
    cos = np.abs(b + t) / radius_m  # (rel + t d) · d / r with |d| = 1
    return np.where(hit, t, np.inf), np.where(hit, cos, 0.0)


# ---------------------------------------------------------------------------------- casting
@dataclass(frozen=True, eq=False)
class RayHits:
    """Nearest return of M rays.

    Attributes
    ----------
    range_m:
        (M,) float64 distance along the ray (m); ``inf`` where there is no return (no surface within
        the maximum range, or the nearest one closer than the minimum range).
    material:
        (M,) uint8 :class:`~randt.sim.town.Material` of the surface hit; ``NO_RETURN`` for none.
    reflectivity:
        (M,) float64 in [0, 1] of the surface hit (0 for none).
    cos_incidence:
        (M,) float64 ``|cos|`` of the incidence angle (0 for none).
    """

    range_m: np.ndarray
    material: np.ndarray
    reflectivity: np.ndarray
    cos_incidence: np.ndarray


@dataclass(frozen=True, eq=False)
class _ChunkStats:
    starts: np.ndarray  # (C,) first ray of each chunk
    ends: np.ndarray  # (C,) one past the last ray
    origin: np.ndarray  # (C,3) mean origin
    spread: np.ndarray  # (C,) max distance of a chunk's origins from its mean origin
    azimuth_dir: np.ndarray  # (C,2) unit mean horizontal direction
    azimuth_half: np.ndarray  # (C,) largest angle of a ray's horizontal direction from it (rad)
    elevation_min: np.ndarray  # (C,) rad
    elevation_max: np.ndarray  # (C,) rad


def _chunk_stats(origins: np.ndarray, dirs: np.ndarray, chunk_rays: int) -> _ChunkStats:
    return _ChunkStats(*chunk_stats(origins, dirs, chunk_rays))


def _candidates(stats: _ChunkStats, bd: PrimitiveBounds, max_range_m: float) -> np.ndarray:
    """(C,K) bool: primitive k may be hit by a ray of chunk c (conservative)."""
    vx = bd.centre_xy[None, :, 0] - stats.origin[:, 0, None]
    vy = bd.centre_xy[None, :, 1] - stats.origin[:, 1, None]
    d = np.hypot(vx, vy)
    r = bd.radius_m[None, :] + stats.spread[:, None]
    near = d <= r
    safe_d = np.maximum(d, 1e-12)
    cos_beta = (vx * stats.azimuth_dir[:, 0, None] + vy * stats.azimuth_dir[:, 1, None]) / safe_d
    beta = np.arccos(np.clip(cos_beta, -1.0, 1.0))
    alpha = np.arcsin(np.clip(r / safe_d, 0.0, 1.0))
    in_wedge = (beta <= alpha + stats.azimuth_half[:, None] + 1e-9) & (d - r <= max_range_m)
    rho_min, rho_max = np.maximum(d - r, 0.0), d + r
    top = bd.z_max_m[None, :] - stats.origin[:, 2, None] + stats.spread[:, None]
    bottom = bd.z_min_m[None, :] - stats.origin[:, 2, None] - stats.spread[:, None]
    el_top = np.arctan2(top, np.where(top >= 0.0, rho_min, rho_max))
    el_bottom = np.arctan2(bottom, np.where(bottom >= 0.0, rho_max, rho_min))
    in_band = (el_top >= stats.elevation_min[:, None] - 1e-9) & (
        el_bottom <= stats.elevation_max[:, None] + 1e-9
    )
    return (near | in_wedge) & in_band


def cast_rays(
    town: Town,
    origins: np.ndarray,
    dirs: np.ndarray,
    *,
    max_range_m: float = 120.0,
    min_range_m: float = 0.0,
    chunk_rays: int = 256,
) -> RayHits:
    """Nearest surface of ``town`` along each ray.

    Parameters
    ----------
    town:
        The scene.
    origins, dirs:
        (M,3) world ray origins (m) and unit directions, in a coherent order (see the module
        docstring): culling is per block of ``chunk_rays`` consecutive rays, so an incoherent order
        is still correct, only slower.
    max_range_m, min_range_m:
        No return beyond ``max_range_m``; a nearest surface closer than ``min_range_m`` blocks the
        ray and gives no return.
    chunk_rays:
        Rays per culling chunk.

    Returns
    -------
    RayHits
        Per-ray range, material, reflectivity and incidence.
    """
    origins = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
    dirs = np.ascontiguousarray(dirs, dtype=np.float64).reshape(-1, 3)
    m = origins.shape[0]
    if m == 0:
        return RayHits(np.zeros(0), np.zeros(0, np.uint8), np.zeros(0), np.zeros(0))
    t_ground, cos_ground = intersect_ground(origins, dirs, town.ground_gradient)
    best, best_cos = t_ground.copy(), cos_ground.copy()
    best_kind = np.full(m, -1, np.int8)  # -1: the ground (or nothing)
    best_prim = np.zeros(m, np.int64)
    stats = _chunk_stats(origins, dirs, chunk_rays)
    counts = stats.ends - stats.starts
    sweep_centre = counts @ stats.origin / m
    # (an upper bound of the origins' largest distance from their mean: the chunks' spreads about
    # their own centres, and the centres' distances from the mean)
    sweep_spread = float(np.max(np.linalg.norm(stats.origin - sweep_centre, axis=1) + stats.spread))
    n_pairs = 0
    prims: tuple[Boxes | Cylinders | Spheres, ...] = town.primitives()
    for kind, prim in zip((BOX, CYLINDER, SPHERE), prims, strict=True):
        if len(prim) == 0:
            continue
        bd = prim.bounds()
        reach = np.hypot(*(bd.centre_xy - sweep_centre[:2]).T) - bd.radius_m - sweep_spread
        keep = np.flatnonzero(reach <= max_range_m)  # global cull before the per-chunk test
        if keep.size == 0:
            continue
        bd = PrimitiveBounds(bd.centre_xy[keep], bd.radius_m[keep], bd.z_min_m[keep], bd.z_max_m[keep])
        cc, kk = np.nonzero(_candidates(stats, bd, max_range_m))
        n_pairs += nearest_hits(
            kind, _kernel_params(prim), origins, dirs, stats.starts, stats.ends, cc, keep[kk],
            max_range_m, best, best_cos, best_kind, best_prim,
        )  # fmt: skip

    material = np.full(m, NO_RETURN, np.uint8)
    reflectivity = np.zeros(m)
    g_ray = np.flatnonzero((best_kind < 0) & np.isfinite(best))  # the ground is the nearest
    g_mat = town.ground_material(origins[g_ray, :2] + best[g_ray, None] * dirs[g_ray, :2])
    material[g_ray] = g_mat
    reflectivity[g_ray] = town.ground_reflectivity(g_mat)
    for kind, prim in zip((BOX, CYLINDER, SPHERE), prims, strict=True):
        ray = np.flatnonzero(best_kind == kind)
        material[ray] = prim.material[best_prim[ray]]
        reflectivity[ray] = prim.reflectivity[best_prim[ray]]
    returned = np.isfinite(best) & (best <= max_range_m) & (best >= min_range_m)
    material[~returned] = NO_RETURN
    reflectivity[~returned] = 0.0
    cos_incidence = np.where(returned, best_cos, 0.0)
    log.debug("cast %d rays: %d (ray, primitive) pairs, %d returns", m, n_pairs, int(returned.sum()))
    return RayHits(np.where(returned, best, np.inf), material, reflectivity, cos_incidence)


def _kernel_params(prim: Boxes | Cylinders | Spheres) -> np.ndarray:
    """``prim``'s parameters as :func:`randt.sim._cast.nearest_hits` reads them, one row a primitive."""
    if isinstance(prim, Boxes):
        yaw = prim.yaw_rad
        return np.column_stack((prim.centre_xyz, prim.half_extents_xyz, np.cos(yaw), np.sin(yaw)))
    if isinstance(prim, Cylinders):
        return np.column_stack((prim.centre_xy, prim.radius_m, prim.z_min_m, prim.z_max_m))
    return np.column_stack((prim.centre_xyz, prim.radius_m))


# ---------------------------------------------------------------------------------- the sensor
def hdl64e_elevations_deg() -> np.ndarray:
    """(64,) beam elevations (deg), ring 0 highest: +2.0..-8.33 (32 beams), -8.83..-24.8 (32)."""
    return np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.8, 32)])


@dataclass(frozen=True, eq=False)
class Sweep:
    """The returns of one revolution, in firing order (azimuth column, then ring).

    Attributes
    ----------
    points_xyz:
        (N,3) float64 points, metres, in the sensor frame at each point's firing time or, when the
        sweep was deskewed, in the reference sensor frame.
    intensity:
        (N,) float32 in [0, 1].
    column:
        (N,) int64 firing (azimuth column) index, 0..n_azimuth-1.
    ring:
        (N,) uint8 beam index, 0 = highest elevation.
    label:
        (N,) uint8 :class:`~randt.sim.town.Material` of the surface hit.
    range_m:
        (N,) float64 measured range (with noise), metres.
    """

    points_xyz: np.ndarray
    intensity: np.ndarray
    column: np.ndarray
    ring: np.ndarray
    label: np.ndarray
    range_m: np.ndarray


@dataclass(frozen=True, eq=False)
class Lidar64:
    """HDL-64E-like spinning LiDAR (docs/clients.md, "The simulator").

    Attributes
    ----------
    n_azimuth:
        Firings per revolution (2000: 0.18 deg, 128k rays). Tests use fewer for speed.
    max_range_m, min_range_m:
        Returns beyond / closer than these are dropped (m).
    range_noise_m:
        Standard deviation of the Gaussian range noise (m).
    dropout:
        Probability that a return is lost at random.
    intensity_noise:
        Standard deviation of the additive intensity noise.
    mount_height_m:
        Height of the sensor origin above the vehicle origin (on the ground), as KITTI's 1.73 m.
    chunk_rays:
        Culling chunk of :func:`cast_rays`; rays are ordered in tiles of 16 columns x 16 rings.
    """

    n_azimuth: int = 2000
    max_range_m: float = 120.0
    min_range_m: float = 1.0
    range_noise_m: float = 0.02
    dropout: float = 0.04
    intensity_noise: float = 0.02
    mount_height_m: float = 1.73
    chunk_rays: int = 256

    def __post_init__(self) -> None:
        if self.n_azimuth < 1 or not 0.0 <= self.dropout < 1.0 or self.range_noise_m < 0.0:
            raise ValueError("Lidar64 needs n_azimuth >= 1, 0 <= dropout < 1 and range_noise_m >= 0")
        if not 0.0 <= self.min_range_m < self.max_range_m:
            raise ValueError("Lidar64 needs 0 <= min_range_m < max_range_m")

    @property
    def n_beams(self) -> int:
        """Number of lasers (64)."""
        return 64

    @cached_property
    def elevations_rad(self) -> np.ndarray:
        """(64,) beam elevations (rad), ring 0 highest."""
        return np.radians(hdl64e_elevations_deg())

    @cached_property
    def azimuths_rad(self) -> np.ndarray:
        """(n_azimuth,) azimuth of each firing in the sensor frame (rad from +x towards +y).

        Starts at pi (pointing backwards) and decreases: the head turns clockwise seen from above.
        """
        return np.pi - 2.0 * np.pi * np.arange(self.n_azimuth) / self.n_azimuth

    @cached_property
    def ray_directions(self) -> np.ndarray:
        """(n_azimuth, 64, 3) unit ray directions in the sensor frame (x forward, y left, z up)."""
        az = self.azimuths_rad[:, None]
        el = self.elevations_rad[None, :]
        return np.stack(
            np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), axis=-1
        )

    @cached_property
    def _tile_order(self) -> np.ndarray:
        """Permutation of the flat (column, ring) rays into tiles of 16 columns x 16 rings."""
        col, ring = np.meshgrid(np.arange(self.n_azimuth), np.arange(64), indexing="ij")
        tile = (col // 16) * 4 + ring // 16
        return np.argsort(tile.ravel(), kind="stable")

    def firing_offsets_s(self, rate_hz: float) -> np.ndarray:
        """(n_azimuth,) time of each firing after the start of the sweep (s), in [0, 1/rate_hz)."""
        return np.arange(self.n_azimuth) / (self.n_azimuth * rate_hz)

    def sweep(
        self,
        town: Town,
        T_world_sensor_cols: np.ndarray,
        rng: np.random.Generator,
        *,
        T_world_reference: np.ndarray | None = None,
    ) -> Sweep:
        """Cast one revolution from per-firing sensor poses and return the points.

        Parameters
        ----------
        town:
            The scene.
        T_world_sensor_cols:
            (n_azimuth,4,4) world<-sensor pose at each firing (all equal for a static sensor).
        rng:
            Source of the range noise, dropouts and intensity noise.
        T_world_reference:
            (4,4) world<-sensor pose to express all points in (an exact deskew); ``None`` leaves
            each point in the sensor frame at its own firing time (the raw, motion-distorted sweep).

        Returns
        -------
        Sweep
            The returns in firing order.
        """
        T = np.asarray(T_world_sensor_cols, dtype=np.float64)
        if T.shape != (self.n_azimuth, 4, 4):
            raise ValueError(f"T_world_sensor_cols must be ({self.n_azimuth}, 4, 4), got {T.shape}")
        dirs_s = self.ray_directions  # (A,64,3)
        dirs_w = np.matmul(dirs_s, T[:, :3, :3].transpose(0, 2, 1))  # (A,64,3) world
        origins = np.broadcast_to(T[:, None, :3, 3], dirs_w.shape)
        order = self._tile_order
        hits = cast_rays(
            town,
            origins.reshape(-1, 3)[order],
            dirs_w.reshape(-1, 3)[order],
            max_range_m=self.max_range_m,
            min_range_m=self.min_range_m,
            chunk_rays=self.chunk_rays,
        )
        n = order.size
        inverse = np.empty(n, np.int64)
        inverse[order] = np.arange(n)
        rng_true = hits.range_m[inverse]
        noise = rng.standard_normal(n) * self.range_noise_m
        keep = rng.random(n) >= self.dropout
        i_noise = rng.standard_normal(n) * self.intensity_noise
        measured = rng_true + noise
        ok = np.isfinite(rng_true) & keep & (measured <= self.max_range_m) & (measured >= self.min_range_m)
        idx = np.flatnonzero(ok)  # firing order: column-major over (column, ring)
        column, ring = np.divmod(idx, 64)
        r = np.where(ok, measured, 0.0).reshape(self.n_azimuth, 64, 1)
        pts = dirs_s * r  # (A,64,3) in the firing-time sensor frames
        if T_world_reference is not None:
            R_ref_world = np.asarray(T_world_reference, dtype=np.float64)[:3, :3].T
            R = R_ref_world @ T[:, :3, :3]  # (A,3,3) reference<-firing, exact rigid inverse
            t = (T[:, :3, 3] - T_world_reference[:3, 3]) @ R_ref_world.T
            pts = np.matmul(pts, R.transpose(0, 2, 1)) + t[:, None, :]
        pts = pts.reshape(-1, 3)[idx]
        hit = inverse[idx]
        intensity = hits.reflectivity[hit] * (0.25 + 0.75 * hits.cos_incidence[hit]) + i_noise[idx]
        return Sweep(
            pts,
            np.clip(intensity, 0.0, 1.0).astype(np.float32),
            column,
            ring.astype(np.uint8),
            hits.material[hit],
            measured[idx],
        )
