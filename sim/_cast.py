"""The ray caster's inner loop, compiled (numba): each (chunk of rays, candidate primitive) pair.

:func:`randt.sim.lidar.cast_rays` culls primitives per chunk of coherent rays with numpy; what is left is
a few million (ray, primitive) pairs a sweep. Intersected with numpy, each pair would go through
dozens of temporary arrays; here each pair is a few dozen flops in registers and the nearest hit
per ray is kept as it goes. The arithmetic is that of :func:`randt.sim.lidar.intersect_boxes`,
:func:`~randt.sim.lidar.intersect_cylinders` and :func:`~randt.sim.lidar.intersect_spheres`, operation for
operation (``tests/sim/test_sim.py`` checks the two against each other), and among equally near
hits the last visited wins, as there.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = ["BOX", "CYLINDER", "SPHERE", "chunk_stats", "nearest_hits"]

#: ``kind`` of :func:`nearest_hits`, and the columns of its ``params``:
#: boxes: centre x, y, z, half extent x, y, z, cos yaw, sin yaw;
BOX = 0
#: cylinders: axis x, y, radius, z min, z max;
CYLINDER = 1
#: spheres: centre x, y, z, radius.
SPHERE = 2

_EPS_T = 1e-9  # as randt.sim.lidar's: hits closer than this along the ray are ignored


@nb.njit(cache=True, inline="always")
def _box(
    ox: float, oy: float, oz: float, dx: float, dy: float, dz: float, p: np.ndarray
) -> tuple[float, float]:
    c, s = p[6], p[7]
    rx, ry, rz = ox - p[0], oy - p[1], oz - p[2]
    o = (c * rx + s * ry, -s * rx + c * ry, rz)
    d = (c * dx + s * dy, -s * dx + c * dy, dz)
    t_near = -math.inf
    t_far = math.inf
    cos_near = 0.0
    for axis in range(3):
        h = p[3 + axis]
        inv = 1.0 / d[axis] if d[axis] != 0.0 else math.copysign(math.inf, d[axis])
        t1, t2 = (-h - o[axis]) * inv, (h - o[axis]) * inv
        if math.isnan(t1) or math.isnan(t2):  # numpy's minimum/maximum carry the NaN: a miss
            return math.inf, 0.0
        lo, hi = min(t1, t2), max(t1, t2)
        if axis == 0 or lo > t_near:
            cos_near = abs(d[axis])
        t_near = lo if axis == 0 else max(t_near, lo)
        t_far = hi if axis == 0 else min(t_far, hi)
    if t_near <= t_far and t_near > _EPS_T:
        return t_near, cos_near
    return math.inf, cos_near


@nb.njit(cache=True, inline="always")
def _cylinder(
    ox: float, oy: float, oz: float, dx: float, dy: float, dz: float, p: np.ndarray
) -> tuple[float, float]:
    px, py = ox - p[0], oy - p[1]
    r = p[2]
    a = dx * dx + dy * dy
    b = px * dx + py * dy
    r2 = r * r
    disc = b * b - a * (px * px + py * py - r2)
    t = math.inf
    cos = 0.0
    if disc >= 0.0 and a > 1e-12:
        t_side = (-b - math.sqrt(disc)) / a
        z_side = oz + t_side * dz
        if t_side > _EPS_T and z_side >= p[3] and z_side <= p[4]:
            t = t_side
            cos = abs((px + t_side * dx) * dx + (py + t_side * dy) * dy) / r
    if dz != 0.0:
        for z_cap, toward in ((p[4], dz < 0.0), (p[3], dz > 0.0)):  # the top seen from above, the bottom
            t_cap = (z_cap - oz) / dz
            qx, qy = px + t_cap * dx, py + t_cap * dy
            if toward and t_cap > _EPS_T and qx * qx + qy * qy <= r2 and t_cap < t:
                t = t_cap
                cos = abs(dz)
    return t, cos


@nb.njit(cache=True, inline="always")
def _sphere(
    ox: float, oy: float, oz: float, dx: float, dy: float, dz: float, p: np.ndarray
) -> tuple[float, float]:
    rx, ry, rz = ox - p[0], oy - p[1], oz - p[2]
    r = p[3]
    b = rx * dx + ry * dy + rz * dz
    disc = b * b - ((rx * rx + ry * ry + rz * rz) - r * r)
    if disc < 0.0:
        return math.inf, 0.0
    t = -b - math.sqrt(disc)
    if t > _EPS_T:
        return t, abs(b + t) / r
    return math.inf, 0.0


@nb.njit(cache=True, nogil=True)
def nearest_hits(
    kind: int,
    params: np.ndarray,
    origins: np.ndarray,
    dirs: np.ndarray,
    starts: np.ndarray,
    ends: np.ndarray,
    pair_chunk: np.ndarray,
    pair_prim: np.ndarray,
    max_range_m: float,
    best: np.ndarray,
    best_cos: np.ndarray,
    best_kind: np.ndarray,
    best_prim: np.ndarray,
) -> int:
    """Every ray of chunk ``pair_chunk[j]`` against primitive ``pair_prim[j]`` (a row of
    ``params``, of type ``kind``); where a hit within ``max_range_m`` is as near as ``best`` or
    nearer, it takes ``best``, ``best_cos``, ``best_kind`` and ``best_prim`` (in place). Returns
    the number of (ray, primitive) pairs tested."""
    n_pairs = 0
    for j in range(pair_chunk.size):
        c, k = pair_chunk[j], pair_prim[j]
        p = params[k]
        for i in range(starts[c], ends[c]):
            ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
            dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
            if kind == BOX:
                t, cos = _box(ox, oy, oz, dx, dy, dz, p)
            elif kind == CYLINDER:
                t, cos = _cylinder(ox, oy, oz, dx, dy, dz, p)
            else:
                t, cos = _sphere(ox, oy, oz, dx, dy, dz, p)
            if t <= max_range_m and t <= best[i]:
                best[i] = t
                best_cos[i] = cos
                best_kind[i] = kind
                best_prim[i] = k
        n_pairs += ends[c] - starts[c]
    return n_pairs


@nb.njit(cache=True, nogil=True)
def chunk_stats(
    origins: np.ndarray, dirs: np.ndarray, chunk_rays: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per block of ``chunk_rays`` consecutive rays (:class:`randt.sim.lidar._ChunkStats`' fields, in
    order): first and one-past-last ray, mean origin, the origins' largest distance from it, the
    unit mean horizontal direction, the largest angle of a ray's horizontal direction from it
    (pi for a block with a vertical ray or whose directions spread over more than a half turn),
    and the elevation range (rad)."""
    m = origins.shape[0]
    n = (m + chunk_rays - 1) // chunk_rays
    starts = np.arange(0, m, chunk_rays)
    ends = np.minimum(starts + chunk_rays, m)
    centre = np.zeros((n, 3))
    spread = np.zeros(n)
    azimuth_dir = np.zeros((n, 2))
    half = np.zeros(n)
    el_min = np.full(n, np.inf)
    el_max = np.full(n, -np.inf)
    for c in range(n):
        a, b = starts[c], ends[c]
        sx = sy = sz = 0.0
        ux = uy = 0.0
        vertical = False
        for i in range(a, b):
            sx += origins[i, 0]
            sy += origins[i, 1]
            sz += origins[i, 2]
            nxy = math.hypot(dirs[i, 0], dirs[i, 1])
            vertical |= nxy < 1e-6
            nxy = max(nxy, 1e-12)
            ux += dirs[i, 0] / nxy
            uy += dirs[i, 1] / nxy
            el = math.asin(min(max(dirs[i, 2], -1.0), 1.0))
            el_min[c] = min(el_min[c], el)
            el_max[c] = max(el_max[c], el)
        count = b - a
        cx, cy, cz = sx / count, sy / count, sz / count
        centre[c, 0], centre[c, 1], centre[c, 2] = cx, cy, cz
        mean_norm = math.sqrt(ux * ux + uy * uy)
        ax, ay = ux / max(mean_norm, 1e-12), uy / max(mean_norm, 1e-12)
        azimuth_dir[c, 0], azimuth_dir[c, 1] = ax, ay
        worst = 0.0
        for i in range(a, b):
            ex, ey, ez = origins[i, 0] - cx, origins[i, 1] - cy, origins[i, 2] - cz
            spread[c] = max(spread[c], math.sqrt(ex * ex + ey * ey + ez * ez))
            nxy = max(math.hypot(dirs[i, 0], dirs[i, 1]), 1e-12)
            cos_dev = min(max((dirs[i, 0] / nxy) * ax + (dirs[i, 1] / nxy) * ay, -1.0), 1.0)
            worst = max(worst, math.acos(cos_dev))
        half[c] = math.pi if vertical or mean_norm < 0.5 * count else worst
    return starts, ends, centre, spread, azimuth_dir, half, el_min, el_max
