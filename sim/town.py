"""A procedural town for the LiDAR simulator: ground, a street grid, buildings, poles, trees, parked cars.

:class:`Town` (generated deterministically from a seed) in the world frame, metres, z up, its
geometry as numpy arrays per primitive type (:class:`Boxes`, :class:`Cylinders`,
:class:`Spheres`), each primitive with a :class:`Material` and a reflectivity, as the ray caster
(:mod:`randt.sim.lidar`) consumes them. Frames and layout: docs/clients.md, "The simulator".
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
import numpy.typing as npt

__all__ = [
    "GROUND_MATERIALS",
    "Boxes",
    "Cylinders",
    "Material",
    "PrimitiveBounds",
    "Spheres",
    "Town",
]

log = logging.getLogger(__name__)


class Material(IntEnum):
    """Surface classes; a simulated point's ``label`` is the material of the surface it hit."""

    ROAD = 0
    SIDEWALK = 1
    MARKING = 2
    BUILDING = 3
    POLE = 4
    TRUNK = 5
    FOLIAGE = 6
    CAR = 7


#: Materials of the ground plane (a point with one of these labels lies on ``z = g · xy``).
GROUND_MATERIALS: tuple[Material, ...] = (Material.ROAD, Material.SIDEWALK, Material.MARKING)

#: Reflectivity of the ground materials, indexed by ``Material`` value (asphalt, concrete, paint).
_GROUND_REFLECTIVITY = np.array([0.12, 0.30, 0.75])

#: Half-width (m) of the dashed centre line and its dash / period lengths (m).
_MARKING_HALF_WIDTH_M = 0.075
_DASH_M, _DASH_PERIOD_M = 3.0, 9.0


def _as_array(value: object, shape: tuple[int, ...], dtype: type, name: str) -> np.ndarray:
    arr: np.ndarray = np.ascontiguousarray(value, dtype=dtype)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    return arr


@dataclass(frozen=True, eq=False)
class PrimitiveBounds:
    """Vertical bounding cylinders of K primitives, for culling.

    Attributes
    ----------
    centre_xy:
        (K,2) float64 world xy of the axis, metres.
    radius_m:
        (K,) float64 horizontal radius that contains the primitive, metres.
    z_min_m, z_max_m:
        (K,) float64 vertical extent, metres.
    """

    centre_xy: np.ndarray
    radius_m: np.ndarray
    z_min_m: np.ndarray
    z_max_m: np.ndarray


@dataclass(frozen=True, eq=False)
class Boxes:
    """K boxes rotated about the vertical axis.

    Attributes
    ----------
    centre_xyz:
        (K,3) float64 world centre, metres.
    half_extents_xyz:
        (K,3) float64 half sizes along the box's own x, y, z axes, metres.
    yaw_rad:
        (K,) float64 rotation of the box's x axis from world x about world z, radians.
    material:
        (K,) uint8 :class:`Material` values.
    reflectivity:
        (K,) float64 in [0, 1].
    """

    centre_xyz: np.ndarray
    half_extents_xyz: np.ndarray
    yaw_rad: np.ndarray
    material: np.ndarray
    reflectivity: np.ndarray

    def __post_init__(self) -> None:
        k = np.asarray(self.yaw_rad).reshape(-1).shape[0]
        object.__setattr__(self, "centre_xyz", _as_array(self.centre_xyz, (k, 3), np.float64, "centre_xyz"))
        object.__setattr__(
            self, "half_extents_xyz", _as_array(self.half_extents_xyz, (k, 3), np.float64, "half_extents")
        )
        object.__setattr__(self, "yaw_rad", _as_array(np.reshape(self.yaw_rad, -1), (k,), np.float64, "yaw"))
        object.__setattr__(self, "material", _as_array(self.material, (k,), np.uint8, "material"))
        object.__setattr__(self, "reflectivity", _as_array(self.reflectivity, (k,), np.float64, "refl"))
        if np.any(self.half_extents_xyz <= 0):
            raise ValueError("box half extents must be positive")

    def __len__(self) -> int:
        return self.yaw_rad.shape[0]

    def bounds(self) -> PrimitiveBounds:
        """Vertical bounding cylinders (the footprint's half diagonal is yaw-invariant)."""
        h = self.half_extents_xyz
        return PrimitiveBounds(
            self.centre_xyz[:, :2],
            np.hypot(h[:, 0], h[:, 1]),
            self.centre_xyz[:, 2] - h[:, 2],
            self.centre_xyz[:, 2] + h[:, 2],
        )

    def surface_distance(self, points_xyz: np.ndarray) -> np.ndarray:
        """Unsigned distance (m) from (N,3) points to each box's surface: (N,K) float64."""
        c, s = np.cos(self.yaw_rad), np.sin(self.yaw_rad)
        rel = points_xyz[:, None, :] - self.centre_xyz[None, :, :]
        q = np.stack(
            [c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1], rel[..., 2]], axis=-1
        )
        excess = np.abs(q) - self.half_extents_xyz[None, :, :]
        outside = np.linalg.norm(np.maximum(excess, 0.0), axis=-1)
        inside = np.minimum(excess.max(axis=-1), 0.0)
        return np.abs(outside + inside)


@dataclass(frozen=True, eq=False)
class Cylinders:
    """K vertical, capped cylinders.

    Attributes
    ----------
    centre_xy:
        (K,2) float64 world xy of the axis, metres.
    radius_m:
        (K,) float64.
    z_min_m, z_max_m:
        (K,) float64 bottom and top cap heights, metres (``z_min_m < z_max_m``).
    material:
        (K,) uint8 :class:`Material` values.
    reflectivity:
        (K,) float64 in [0, 1].
    """

    centre_xy: np.ndarray
    radius_m: np.ndarray
    z_min_m: np.ndarray
    z_max_m: np.ndarray
    material: np.ndarray
    reflectivity: np.ndarray

    def __post_init__(self) -> None:
        k = np.asarray(self.radius_m).reshape(-1).shape[0]
        object.__setattr__(self, "centre_xy", _as_array(self.centre_xy, (k, 2), np.float64, "centre_xy"))
        for name in ("radius_m", "z_min_m", "z_max_m", "reflectivity"):
            value = np.reshape(getattr(self, name), -1)
            object.__setattr__(self, name, _as_array(value, (k,), np.float64, name))
        object.__setattr__(self, "material", _as_array(self.material, (k,), np.uint8, "material"))
        if np.any(self.radius_m <= 0) or np.any(self.z_max_m <= self.z_min_m):
            raise ValueError("cylinders need positive radii and z_max_m > z_min_m")

    def __len__(self) -> int:
        return self.radius_m.shape[0]

    def bounds(self) -> PrimitiveBounds:
        """Vertical bounding cylinders (the cylinders themselves)."""
        return PrimitiveBounds(self.centre_xy, self.radius_m, self.z_min_m, self.z_max_m)

    def surface_distance(self, points_xyz: np.ndarray) -> np.ndarray:
        """Unsigned distance (m) from (N,3) points to each capped cylinder's surface: (N,K) float64."""
        dxy = points_xyz[:, None, :2] - self.centre_xy[None, :, :]
        d_r = np.hypot(dxy[..., 0], dxy[..., 1]) - self.radius_m[None, :]
        z = points_xyz[:, None, 2]
        d_z = np.maximum(self.z_min_m[None, :] - z, z - self.z_max_m[None, :])
        outside = np.hypot(np.maximum(d_r, 0.0), np.maximum(d_z, 0.0))
        inside = np.minimum(np.maximum(d_r, d_z), 0.0)
        return np.abs(outside + inside)


@dataclass(frozen=True, eq=False)
class Spheres:
    """K spheres.

    Attributes
    ----------
    centre_xyz:
        (K,3) float64 world centre, metres.
    radius_m:
        (K,) float64.
    material:
        (K,) uint8 :class:`Material` values.
    reflectivity:
        (K,) float64 in [0, 1].
    """

    centre_xyz: np.ndarray
    radius_m: np.ndarray
    material: np.ndarray
    reflectivity: np.ndarray

    def __post_init__(self) -> None:
        k = np.asarray(self.radius_m).reshape(-1).shape[0]
        object.__setattr__(self, "centre_xyz", _as_array(self.centre_xyz, (k, 3), np.float64, "centre_xyz"))
        object.__setattr__(self, "radius_m", _as_array(np.reshape(self.radius_m, -1), (k,), np.float64, "r"))
        object.__setattr__(self, "material", _as_array(self.material, (k,), np.uint8, "material"))
        object.__setattr__(self, "reflectivity", _as_array(self.reflectivity, (k,), np.float64, "refl"))
        if np.any(self.radius_m <= 0):
            raise ValueError("sphere radii must be positive")

    def __len__(self) -> int:
        return self.radius_m.shape[0]

    def bounds(self) -> PrimitiveBounds:
        """Vertical bounding cylinders of the spheres."""
        c, r = self.centre_xyz, self.radius_m
        return PrimitiveBounds(c[:, :2], r, c[:, 2] - r, c[:, 2] + r)

    def surface_distance(self, points_xyz: np.ndarray) -> np.ndarray:
        """Unsigned distance (m) from (N,3) points to each sphere's surface: (N,K) float64."""
        d = np.linalg.norm(points_xyz[:, None, :] - self.centre_xyz[None, :, :], axis=-1)
        return np.abs(d - self.radius_m[None, :])


class _Builder:
    """Collects primitives as per-type lists of column arrays while the town is generated."""

    def __init__(self, gradient: np.ndarray) -> None:
        self.gradient = gradient
        self.boxes: list[tuple[np.ndarray, ...]] = []
        self.cylinders: list[tuple[np.ndarray, ...]] = []
        self.spheres: list[tuple[np.ndarray, ...]] = []

    def ground_z(self, xy: np.ndarray) -> np.ndarray:
        return np.asarray(xy, dtype=np.float64) @ self.gradient

    def _base_z(self, xy: np.ndarray, radius: np.ndarray) -> np.ndarray:
        # lowest ground height under a footprint of this radius, so nothing floats on a slope
        return self.ground_z(xy) - np.linalg.norm(self.gradient) * radius - 0.05

    def add_boxes(
        self,
        xy: npt.ArrayLike,
        size_xy: npt.ArrayLike,
        height: npt.ArrayLike,
        yaw: npt.ArrayLike,
        mat: Material,
        refl: npt.ArrayLike,
    ) -> None:
        xy, size_xy = np.atleast_2d(xy), np.atleast_2d(size_xy)
        height, yaw = np.atleast_1d(height), np.atleast_1d(yaw)
        base = self._base_z(xy, 0.5 * np.hypot(size_xy[:, 0], size_xy[:, 1]))
        top = self.ground_z(xy) + height
        centre = np.column_stack([xy, 0.5 * (base + top)])
        half = np.column_stack([0.5 * size_xy, 0.5 * (top - base)])
        refl = np.broadcast_to(np.asarray(refl, dtype=np.float64), yaw.shape)
        self.boxes.append((centre, half, yaw, np.full(yaw.shape, mat, np.uint8), refl))

    def add_cylinders(
        self,
        xy: npt.ArrayLike,
        radius: npt.ArrayLike,
        height: npt.ArrayLike,
        mat: Material,
        refl: npt.ArrayLike,
    ) -> None:
        xy, radius, height = np.atleast_2d(xy), np.atleast_1d(radius), np.atleast_1d(height)
        base = self._base_z(xy, radius)
        refl = np.broadcast_to(np.asarray(refl, dtype=np.float64), radius.shape)
        mats = np.full(radius.shape, mat, np.uint8)
        self.cylinders.append((xy, radius, base, self.ground_z(xy) + height, mats, refl))

    def add_trees(self, xy: np.ndarray, rng: np.random.Generator) -> None:
        """Trunk cylinders with sphere crowns; the crown's bottom clears 2 m (cars, the sensor)."""
        xy = np.atleast_2d(xy)
        n: int = xy.shape[0]
        if n == 0:
            return
        crown_r = rng.uniform(1.2, 2.5, n)
        trunk_h = 2.0 + 0.8 * crown_r + rng.uniform(0.0, 1.5, n)
        self.add_cylinders(xy, rng.uniform(0.15, 0.3, n), trunk_h, Material.TRUNK, rng.uniform(0.2, 0.3, n))
        centre = np.column_stack([xy, self.ground_z(xy) + trunk_h + 0.2 * crown_r])
        self.spheres.append(
            (centre, crown_r, np.full(n, Material.FOLIAGE, np.uint8), rng.uniform(0.3, 0.45, n))
        )

    def build(self) -> tuple[Boxes, Cylinders, Spheres]:
        def cat(parts: list[tuple[np.ndarray, ...]], n_fields: int, widths: tuple[int, ...]) -> list:
            if not parts:
                return [np.zeros((0, w)) if w else np.zeros(0) for w in widths]
            return [np.concatenate([np.asarray(p[i]) for p in parts]) for i in range(n_fields)]

        b = cat(self.boxes, 5, (3, 3, 0, 0, 0))
        c = cat(self.cylinders, 6, (2, 0, 0, 0, 0, 0))
        s = cat(self.spheres, 4, (3, 0, 0, 0))
        return Boxes(*b), Cylinders(*c), Spheres(*s)


def _positions_along(
    rng: np.random.Generator, lo: float, hi: float, first: tuple[float, float], step: tuple[float, float]
) -> np.ndarray:
    """Positions in [lo, hi] starting ``U(first)`` after ``lo`` with ``U(step)`` gaps (1-D, sorted)."""
    if hi <= lo:
        return np.zeros(0)
    n_max = int((hi - lo) / step[0]) + 2
    u = lo + rng.uniform(*first) + np.concatenate([[0.0], np.cumsum(rng.uniform(*step, n_max - 1))])
    return u[u <= hi]


@dataclass(frozen=True, eq=False)
class Town:
    """A generated town: a ground plane, a street grid and primitives by type.

    Build one with :meth:`generate`; the constructor takes explicit arrays (tests build tiny
    hand-made towns with it).

    Attributes
    ----------
    boxes, cylinders, spheres:
        The primitives (buildings and parked cars; poles and tree trunks; tree crowns).
    ground_gradient:
        (2,) float64 ``g`` of the ground plane ``z = g · (x, y)`` (dimensionless, rise per metre).
    street_coords_m:
        (S,) float64 coordinates of the street centrelines, the same along x and y (S may be 0).
    street_width_m, block_m, sidewalk_m:
        Street width kerb to kerb, block side, sidewalk width, metres.
    extent_m:
        Side of the square town centred on the origin, metres.
    seed:
        The generator seed, or ``None`` for a hand-made town.
    """

    boxes: Boxes
    cylinders: Cylinders
    spheres: Spheres
    ground_gradient: np.ndarray = field(default_factory=lambda: np.zeros(2))
    street_coords_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    street_width_m: float = 12.0
    block_m: float = 60.0
    sidewalk_m: float = 3.0
    extent_m: float = 0.0
    seed: int | None = None

    def __post_init__(self) -> None:
        g = _as_array(self.ground_gradient, (2,), np.float64, "ground_gradient")
        object.__setattr__(self, "ground_gradient", g)
        object.__setattr__(self, "street_coords_m", np.sort(np.asarray(self.street_coords_m, np.float64)))

    # ------------------------------------------------------------------ generation
    @classmethod
    def generate(
        cls,
        seed: int,
        *,
        size_m: float = 400.0,
        block_m: float = 60.0,
        street_width_m: float = 12.0,
        sidewalk_m: float = 3.0,
        slope_pct: float = 0.0,
        parked_car_fraction: float = 0.35,
        tree_row_fraction: float = 0.6,
        park_fraction: float = 0.1,
    ) -> Town:
        """Generate a town deterministically from ``seed``.

        Parameters
        ----------
        seed:
            Seed of every random choice; the same seed and arguments give the same town.
        size_m:
            Upper bound on the side of the square town (m). It holds as many ``block_m`` blocks
            per axis as fit with ``street_width_m`` streets between them (at least 3 per axis, so
            that there are at least 2 streets per axis and routes have loops to follow).
        block_m:
            Side of a block, kerb to kerb (m).
        street_width_m:
            Street width kerb to kerb (m); two 3.5 m lanes and two parking lanes at 12 m.
        sidewalk_m:
            Sidewalk width inside each block (m); poles stand 0.4 m from the kerb, trees at 60 %.
        slope_pct:
            Ground slope in percent (rise per 100 m) in a random direction; 0 gives the plane z = 0.
        parked_car_fraction:
            Fraction of ~6.5 m parking slots along the kerbs that hold a car.
        tree_row_fraction:
            Fraction of kerb segments (one block side) lined with trees.
        park_fraction:
            Fraction of lots without a building (a small park with a few trees).

        Returns
        -------
        Town
            Buildings (boxes 10-40 m footprint, 6-25 m high, 30 % yawed up to 8 deg), poles (radius
            0.1-0.2 m, 5-8 m high, every 20-30 m), trees (trunk cylinder and sphere crown), parked
            cars (boxes about 4.5 x 1.8 x 1.5 m).
        """
        rng = np.random.default_rng(seed)
        pitch = block_m + street_width_m
        n_blocks = int((size_m + street_width_m) // pitch)
        if n_blocks < 3:
            raise ValueError(f"size_m={size_m} holds {n_blocks} blocks per axis; need at least 3")
        extent = n_blocks * pitch - street_width_m
        block_lo = -0.5 * extent + pitch * np.arange(n_blocks)
        streets = block_lo[:-1] + block_m + 0.5 * street_width_m
        slope_dir = rng.uniform(0.0, 2.0 * np.pi)
        gradient = slope_pct / 100.0 * np.array([np.cos(slope_dir), np.sin(slope_dir)])
        b = _Builder(gradient)

        for bx in block_lo:
            for by in block_lo:
                _fill_block(b, rng, bx + sidewalk_m, by + sidewalk_m, block_m - 2 * sidewalk_m, park_fraction)

        half_w = 0.5 * street_width_m
        for axis in (0, 1):  # 0: streets along y (constant x), 1: streets along x (constant y)
            for c in streets:
                for lo in block_lo:
                    for side in (-1.0, 1.0):
                        _line_kerb(
                            b,
                            rng,
                            axis,
                            c + side * half_w,
                            side,
                            lo,
                            lo + block_m,
                            sidewalk_m,
                            parked_car_fraction,
                            tree_row_fraction,
                        )

        boxes, cylinders, spheres = b.build()
        town = cls(
            boxes, cylinders, spheres, gradient, streets, street_width_m, block_m, sidewalk_m, extent, seed
        )
        log.debug(
            "town seed=%d extent=%.0f m: %d boxes, %d cylinders, %d spheres",
            seed,
            extent,
            len(boxes),
            len(cylinders),
            len(spheres),
        )
        return town

    # ------------------------------------------------------------------ queries
    @property
    def pitch_m(self) -> float:
        """Distance between neighbouring street centrelines (m)."""
        return self.block_m + self.street_width_m

    def ground_z(self, xy: np.ndarray) -> np.ndarray:
        """Ground height (m) at (..., 2) world xy: (...) float64."""
        return np.asarray(xy, dtype=np.float64) @ self.ground_gradient

    def ground_normal(self) -> np.ndarray:
        """(3,) unit normal of the ground plane, pointing up."""
        n = np.array([-self.ground_gradient[0], -self.ground_gradient[1], 1.0])
        return n / np.linalg.norm(n)

    def intersections(self) -> np.ndarray:
        """(S*S, 2) world xy of the street crossings, x-major."""
        gx, gy = np.meshgrid(self.street_coords_m, self.street_coords_m, indexing="ij")
        return np.column_stack([gx.ravel(), gy.ravel()])

    def street_centerlines(self) -> np.ndarray:
        """(2S, 2, 2) world xy segments ``[start, end]`` of every street centreline, edge to edge.

        The first S run along y (constant x), the last S along x (constant y).
        """
        h = 0.5 * self.extent_m
        c = self.street_coords_m
        along_y = np.stack(
            [np.column_stack([c, np.full_like(c, -h)]), np.column_stack([c, np.full_like(c, h)])], 1
        )
        along_x = np.stack(
            [np.column_stack([np.full_like(c, -h), c]), np.column_stack([np.full_like(c, h), c])], 1
        )
        return np.concatenate([along_y, along_x])

    def _street_offset(self, u: np.ndarray) -> np.ndarray:
        """Signed offset of coordinates ``u`` from the nearest street centreline (inf if none)."""
        c = self.street_coords_m
        if c.size == 0:
            return np.full(np.shape(u), np.inf)
        i = np.clip(np.searchsorted(c, u), 1, max(c.size - 1, 1))
        lo, hi = c[np.maximum(i - 1, 0)], c[np.minimum(i, c.size - 1)]
        return np.where(np.abs(u - lo) <= np.abs(u - hi), u - lo, u - hi)

    def ground_material(self, xy: np.ndarray) -> np.ndarray:
        """:class:`Material` of the ground at (N,2) world xy: (N,) uint8.

        Road inside the street bands (within the town), a dashed centre line outside
        intersections, sidewalk (concrete) everywhere else.
        """
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        inside = np.all(np.abs(xy) <= 0.5 * self.extent_m, axis=1)
        off_x, off_y = self._street_offset(xy[:, 0]), self._street_offset(xy[:, 1])
        half = 0.5 * self.street_width_m
        in_x, in_y = inside & (np.abs(off_x) < half), inside & (np.abs(off_y) < half)
        dash_y = np.mod(xy[:, 1], _DASH_PERIOD_M) < _DASH_M
        dash_x = np.mod(xy[:, 0], _DASH_PERIOD_M) < _DASH_M
        marking = (in_x & ~in_y & (np.abs(off_x) < _MARKING_HALF_WIDTH_M) & dash_y) | (
            in_y & ~in_x & (np.abs(off_y) < _MARKING_HALF_WIDTH_M) & dash_x
        )
        out = np.full(xy.shape[0], Material.SIDEWALK, np.uint8)
        out[in_x | in_y] = Material.ROAD
        out[marking] = Material.MARKING
        return out

    @staticmethod
    def ground_reflectivity(material: np.ndarray) -> np.ndarray:
        """Reflectivity in [0, 1] of ground materials (N,) uint8: (N,) float64."""
        return _GROUND_REFLECTIVITY[np.asarray(material, dtype=np.intp)]

    def primitives(self) -> tuple[Boxes, Cylinders, Spheres]:
        """The primitive sets, in the order the ray caster and :meth:`surface_distance` visit them."""
        return self.boxes, self.cylinders, self.spheres

    def surface_distance(
        self, points_xyz: np.ndarray, *, search_radius_m: float = 1.0, chunk: int = 4096
    ) -> np.ndarray:
        """Unsigned distance from world points to the nearest surface of the town.

        Points are processed in chunks; each chunk only looks at primitives whose bounding
        cylinder comes within ``search_radius_m`` of the chunk's bounding box (the ground plane is
        always included), so memory stays at ``chunk`` x (nearby primitives).

        Parameters
        ----------
        points_xyz:
            (N,3) world points, metres. Spatially coherent order (e.g. a scan's firing order)
            makes the per-chunk culling effective.
        search_radius_m:
            Distances below this are exact; a value at or above it only says the true distance is
            at least ``search_radius_m``.
        chunk:
            Points per chunk.

        Returns
        -------
        np.ndarray
            (N,) float64 distances, metres.
        """
        pts = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
        n = self.ground_normal()
        out = np.abs(pts @ n)  # the plane z = g·xy passes through the origin
        prims = [(p, p.bounds()) for p in self.primitives() if len(p)]
        for start in range(0, pts.shape[0], chunk):
            p = pts[start : start + chunk]
            lo, hi = p.min(axis=0) - search_radius_m, p.max(axis=0) + search_radius_m
            best = out[start : start + chunk]
            for prim, bd in prims:
                near = np.all(bd.centre_xy + bd.radius_m[:, None] >= lo[:2], axis=1)
                near &= np.all(bd.centre_xy - bd.radius_m[:, None] <= hi[:2], axis=1)
                near &= (bd.z_max_m >= lo[2]) & (bd.z_min_m <= hi[2])
                idx = np.flatnonzero(near)
                if idx.size:
                    d = _take(prim, idx).surface_distance(p).min(axis=1)
                    np.minimum(best, d, out=best)
        return out


def _take(prim: Boxes | Cylinders | Spheres, idx: np.ndarray) -> Boxes | Cylinders | Spheres:
    """The subset ``idx`` of a primitive set (same type)."""
    if isinstance(prim, Boxes):
        return Boxes(
            prim.centre_xyz[idx],
            prim.half_extents_xyz[idx],
            prim.yaw_rad[idx],
            prim.material[idx],
            prim.reflectivity[idx],
        )
    if isinstance(prim, Cylinders):
        return Cylinders(
            prim.centre_xy[idx],
            prim.radius_m[idx],
            prim.z_min_m[idx],
            prim.z_max_m[idx],
            prim.material[idx],
            prim.reflectivity[idx],
        )
    return Spheres(prim.centre_xyz[idx], prim.radius_m[idx], prim.material[idx], prim.reflectivity[idx])


def _split(rng: np.random.Generator, lo: float, length: float) -> np.ndarray:
    """Lot boundaries (n+1,) splitting [lo, lo+length] into 1-3 parts of random proportions."""
    n = int(rng.choice([1, 2, 3], p=[0.25, 0.5, 0.25]))
    w = rng.uniform(0.7, 1.3, n)
    return lo + length * np.concatenate([[0.0], np.cumsum(w) / w.sum()])


def _fill_block(
    b: _Builder, rng: np.random.Generator, x0: float, y0: float, side: float, park: float
) -> None:
    """Buildings (or small parks) on the lots of one block's inner square ``[x0, x0+side]²``."""
    xs, ys = _split(rng, x0, side), _split(rng, y0, side)
    for lx0, lx1 in itertools.pairwise(xs):
        for ly0, ly1 in itertools.pairwise(ys):
            setback = rng.uniform(1.0, 4.0, 4)  # -x, +x, -y, +y
            ax0, ax1, ay0, ay1 = lx0 + setback[0], lx1 - setback[1], ly0 + setback[2], ly1 - setback[3]
            aw, ah = ax1 - ax0, ay1 - ay0
            if rng.random() < park or aw < 10.0 or ah < 10.0:
                n_trees = max(1, int((lx1 - lx0) * (ly1 - ly0) / 150.0))
                u = rng.random((n_trees, 2)) - 0.5  # 3 m from the lot's edges where the lot allows
                span = np.maximum(np.array([lx1 - lx0, ly1 - ly0]) - 6.0, 0.0)
                xy = np.array([0.5 * (lx0 + lx1), 0.5 * (ly0 + ly1)]) + u * span
                b.add_trees(xy, rng)
                continue
            fw = rng.uniform(min(max(10.0, 0.55 * aw), 40.0), min(40.0, aw))  # 10-40 m, most of the lot
            fh = rng.uniform(min(max(10.0, 0.55 * ah), 40.0), min(40.0, ah))
            yaw = rng.uniform(-np.radians(8.0), np.radians(8.0)) if rng.random() < 0.3 else 0.0
            c, s = abs(np.cos(yaw)), abs(np.sin(yaw))
            k = min(1.0, aw / (c * fw + s * fh), ah / (s * fw + c * fh))  # the yawed box fits the lot
            if k * min(fw, fh) < 10.0:
                yaw, c, s, k = 0.0, 1.0, 0.0, 1.0
            fw, fh = k * fw, k * fh
            bw, bh = c * fw + s * fh, s * fw + c * fh  # axis-aligned bounding box of the footprint
            cx = ax0 + 0.5 * bw + rng.random() * max(aw - bw, 0.0)
            cy = ay0 + 0.5 * bh + rng.random() * max(ah - bh, 0.0)
            b.add_boxes(
                np.array([cx, cy]),
                np.array([fw, fh]),
                rng.uniform(6.0, 25.0),
                yaw,
                Material.BUILDING,
                rng.uniform(0.3, 0.7),
            )


def _line_kerb(
    b: _Builder,
    rng: np.random.Generator,
    axis: int,
    kerb: float,
    side: float,
    lo: float,
    hi: float,
    sidewalk_m: float,
    car_fraction: float,
    tree_fraction: float,
) -> None:
    """Poles, trees and parked cars along one kerb of one block side.

    ``axis`` 0 is a street along y (the kerb is the line x = ``kerb``), 1 along x; ``side`` is +1
    when the block (sidewalk) lies at larger coordinates than the street, -1 otherwise; the block
    side spans ``[lo, hi]`` along the street.
    """

    def xy(u: np.ndarray, lateral: npt.ArrayLike) -> np.ndarray:
        lateral = np.broadcast_to(lateral, u.shape)
        return np.column_stack([lateral, u] if axis == 0 else [u, lateral])

    poles = _positions_along(rng, lo + 2.0, hi - 2.0, (1.0, 8.0), (20.0, 30.0))
    b.add_cylinders(
        xy(poles, kerb + side * 0.4),
        rng.uniform(0.1, 0.2, poles.size),
        rng.uniform(5.0, 8.0, poles.size),
        Material.POLE,
        rng.uniform(0.45, 0.6, poles.size),
    )
    if rng.random() < tree_fraction:
        trees = _positions_along(rng, lo + 3.0, hi - 3.0, (2.0, 8.0), (12.0, 22.0))
        if poles.size:
            trees = trees[np.min(np.abs(trees[:, None] - poles[None, :]), axis=1) > 2.5]
        b.add_trees(xy(trees, kerb + side * 0.6 * sidewalk_m), rng)
    slots = np.arange(lo + 5.0 + 2.5, hi - 5.0 - 2.5, 6.5)
    cars = slots[rng.random(slots.size) < car_fraction]
    n = cars.size
    if n:
        cars = cars + rng.uniform(-0.5, 0.5, n)
        lateral = kerb - side * 1.2 + rng.uniform(-0.15, 0.15, n)  # parking lane, inside the street
        size = np.column_stack([rng.uniform(4.1, 4.9, n), rng.uniform(1.7, 1.9, n)])
        yaw = (0.5 * np.pi if axis == 0 else 0.0) + rng.normal(0.0, np.radians(1.5), n)
        b.add_boxes(
            xy(cars, lateral), size, rng.uniform(1.4, 1.6, n), yaw, Material.CAR, rng.uniform(0.15, 0.9, n)
        )
