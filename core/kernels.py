"""Compiled kernels (numba) for the hot loops the numpy formulation cannot make cheap.

The NDT score, gradient and Hessian are sums over (point, neighbour voxel) pairs; in numpy every
pair becomes rows of large temporaries, here one pass over the points with none. Grouping points
by voxel (downsampling, Gaussian fits, Algorithm 1) is a hashed pass instead of ``np.unique``'s
sort, and batches of 3x3 symmetric eigenproblems go through a Jacobi loop instead of LAPACK's
per-matrix calls. Why, and what it saves: docs/registration.md, "NDT".

Every public kernel's docstring ends with ``Reference: module:function`` (the numpy formulation, or
the numpy/scipy function, it is tested against) and ``Test: tests/...::test_name`` (the test that
compares them); ``tests/core/test_kernels.py`` checks that both exist. The kernels release the GIL
(``nogil``), so the service's worker threads run them on several cores at once, and are compiled on
first use and cached on disk (numba ``cache=True``).

Voxel keys are packed exactly as :func:`randt.core.voxel.pack_keys` packs them (21 bits per axis); a
map's keys go into an open-addressing hash table (:func:`build_hash`, built once per map), so a
lookup is a probe or two instead of the binary search ``np.searchsorted`` does.
"""

# ruff: noqa: RUF046  (int(math.floor(x)) keeps the cell index an explicit int64 inside numba)
from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = [
    "best_voxel",
    "build_grid",
    "build_hash",
    "cell_shift",
    "conditioned_gaussians",
    "deskew_points",
    "eigh3",
    "first_per_voxel_pair",
    "grid_knn_normals",
    "grid_nearest",
    "group_centroids",
    "group_int_keys",
    "group_min",
    "group_moments",
    "group_voxels",
    "group_weighted_moments",
    "grouped_fence_mask",
    "in_marked_cells",
    "in_voxels",
    "isolated_points",
    "mahalanobis_to_assigned",
    "masked_group_centroids",
    "model_compact",
    "model_evict",
    "model_merge",
    "ndt_accumulate",
    "ndt_scores",
    "parent_moments",
    "plane_information",
    "smallest_eigenvector",
    "tile_voxel_keys",
    "voxel_table_admit",
    "voxel_table_forget",
    "voxel_table_grow",
    "voxel_table_near",
    "within_xy_radius",
]

_BITS = 21
_OFFSET = 1 << (_BITS - 1)
#: ``cache_cell`` value no real cell has (cells are within 21 bits of the origin).
CACHE_EMPTY = -(1 << 62)
_MASK = (1 << _BITS) - 1


@nb.njit(cache=True, inline="always")
def _pack(cx: int, cy: int, cz: int) -> int:
    """Packed key of a cell, or -1 outside the 21-bit range (no map voxel can be there)."""
    sx, sy, sz = cx + _OFFSET, cy + _OFFSET, cz + _OFFSET
    if sx < 0 or sy < 0 or sz < 0 or sx > _MASK or sy > _MASK or sz > _MASK:
        return -1
    return (sx << (2 * _BITS)) | (sy << _BITS) | sz


@nb.njit(cache=True, inline="always")
def _slot(key: int, mask: int) -> int:
    """Home slot of a key in a power-of-two table (xor-shift-multiply mixing of all 63 bits)."""
    k = key ^ (key >> 31)
    k = k * 0x5851F42D4C957F2D
    k = k ^ (k >> 29)
    return k & mask


@nb.njit(cache=True, nogil=True)
def build_hash(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Open-addressing table (keys, indices) over ``keys``, at most half full; empty slots hold -1.

    Reference: numpy:searchsorted
    Test: tests/core/test_kernels.py::test_hash_table_finds_every_key_and_no_other
    """
    cap = 16
    while cap < 2 * keys.shape[0]:
        cap <<= 1
    table_key = np.full(cap, -1, dtype=np.int64)
    table_idx = np.full(cap, -1, dtype=np.int64)
    mask = cap - 1
    for i in range(keys.shape[0]):
        h = _slot(keys[i], mask)
        while table_key[h] != -1 and table_key[h] != keys[i]:
            h = (h + 1) & mask
        table_key[h] = keys[i]
        table_idx[h] = i
    return table_key, table_idx


@nb.njit(cache=True, inline="always")
def _find(table_key: np.ndarray, table_idx: np.ndarray, key: int) -> int:
    """Index stored for ``key`` in a :func:`build_hash` table, -1 when absent."""
    if key < 0:
        return -1
    mask = table_key.shape[0] - 1
    h = _slot(key, mask)
    while True:
        tk = table_key[h]
        if tk == key:
            idx: int = table_idx[h]
            return idx
        if tk == -1:
            return -1
        h = (h + 1) & mask


@nb.njit(cache=True, nogil=True)
def in_voxels(
    points: np.ndarray, voxel_size: float, table_key: np.ndarray, table_idx: np.ndarray, out: np.ndarray
) -> None:
    """``out[i]``: point ``i`` falls in a voxel of a :func:`build_hash` table (cells as
    :func:`randt.core.voxel.voxel_coords` computes them).

    Reference: numpy:searchsorted
    Test: tests/core/test_kernels.py::test_in_voxels_is_the_sorted_lookup
    """
    for i in range(points.shape[0]):
        cx = int(math.floor(points[i, 0] / voxel_size))
        cy = int(math.floor(points[i, 1] / voxel_size))
        cz = int(math.floor(points[i, 2] / voxel_size))
        out[i] = _find(table_key, table_idx, _pack(cx, cy, cz)) >= 0


@nb.njit(cache=True, inline="always")
def _moved(points: np.ndarray, i: int, R: np.ndarray, t: np.ndarray) -> tuple[float, float, float]:
    """Point ``i`` moved by ``(R, t)``."""
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    return (
        R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0],
        R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1],
        R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2],
    )


@nb.njit(cache=True, inline="always")
def _moved_and_cell(
    points: np.ndarray, i: int, R: np.ndarray, t: np.ndarray, inv_v: float, shift: float = 0.0
) -> tuple[float, float, float, int, int, int]:
    """Point ``i`` moved by ``(R, t)`` (:func:`_moved`) and the integer cell of ``q / v - shift``
    (its own cell at ``shift`` 0; a neighbourhood's base cell with :func:`cell_shift`)."""
    q0, q1, q2 = _moved(points, i, R, t)
    c0, c1, c2 = q0 * inv_v - shift, q1 * inv_v - shift, q2 * inv_v - shift
    return q0, q1, q2, int(math.floor(c0)), int(math.floor(c1)), int(math.floor(c2))


@nb.njit(cache=True, inline="always")
def _trilinear_weight(offsets: np.ndarray, k: int, fx: float, fy: float, fz: float) -> float:
    """8 times the trilinear weight of the enclosing voxel ``offsets[k]`` (in {0,1}^3) for a point
    at ``(fx, fy, fz)`` in [0, 1)^3 from the base cell's centre (:func:`randt.core.voxel.trilinear_weights`):
    the 8 weights sum to 8, as many as the unweighted terms."""
    w = 8.0 * (fx if offsets[k, 0] else 1.0 - fx) * (fy if offsets[k, 1] else 1.0 - fy)
    return w * (fz if offsets[k, 2] else 1.0 - fz)


@nb.njit(cache=True)
def cell_shift(n_neighbors: int) -> float:
    """How far (in voxels) a neighbourhood's base cell is below the point's own: 1/2 for the 8
    voxels whose centres enclose it, 0 for the 1-, 7- and 27-voxel ones (the own cell and the
    offsets around it). The rule and its reasons: :func:`randt.core.voxel.neighborhood_base`.

    Reference: randt.core.voxel:neighborhood_base
    Test: tests/core/test_kernels.py::test_derivatives_kernel_matches_numpy
    """
    return 0.5 if n_neighbors == 8 else 0.0


@nb.njit(cache=True, inline="always")
def _mahalanobis2(inv_cov: np.ndarray, v: int, x0: float, x1: float, x2: float) -> float:
    """Squared Mahalanobis distance ``x^T Sigma_v^-1 x``."""
    d2: float = (
        x0 * (inv_cov[v, 0, 0] * x0 + inv_cov[v, 0, 1] * x1 + inv_cov[v, 0, 2] * x2)
        + x1 * (inv_cov[v, 1, 0] * x0 + inv_cov[v, 1, 1] * x1 + inv_cov[v, 1, 2] * x2)
        + x2 * (inv_cov[v, 2, 0] * x0 + inv_cov[v, 2, 1] * x1 + inv_cov[v, 2, 2] * x2)
    )
    return d2


@nb.njit(cache=True, nogil=True)
def ndt_accumulate(
    points: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    table_key: np.ndarray,
    table_idx: np.ndarray,
    means: np.ndarray,
    inv_cov: np.ndarray,
    voxel_size: float,
    offsets: np.ndarray,
    d1: float,
    d2: float,
    m_max: float,
    derivatives: bool,
    pivot: np.ndarray,
    out_grad: np.ndarray,
    out_hess: np.ndarray,
    out_gn: np.ndarray,
    cache_cell: np.ndarray,
    cache_vox: np.ndarray,
) -> tuple[float, int]:
    """NDT cost (and, with ``derivatives``, gradient and Hessians) of ``R p + t`` in one pass.

    The formulas are those of :mod:`randt.core.ndt` (Magnusson eq. 6.12-6.13 with the left
    perturbation about ``pivot``): per pair, ``x = q - mu``, ``a = Sigma^-1 x``, ``m = x.a``
    (pairs with ``m >= m_max`` pruned), ``e = exp(-d2 m / 2)``, cost ``d1 e``, weight
    ``w = -d1 d2 e``, ``J = [I, -[q - pivot]x]``; gradient ``w J^T a``; Hessian
    ``w (J^T Sigma^-1 J - d2 (J^T a)(J^T a)^T + S)``.
    ``out_grad`` (6,), ``out_hess`` and ``out_gn`` (6,6) are overwritten. Returns (cost, pairs).
    With the 8 enclosing voxels (``offsets`` of 8 rows) each pair's ``e`` is weighted trilinearly
    (:func:`_trilinear_weight`; the weights held constant in the derivatives, as Magnusson's
    trilinear NDT does), so the cost is continuous where a point's 8 voxels change.

    The 48 sums live in scalar locals, not arrays: LLVM keeps them in registers, where sums into
    heap arrays (which might alias the inputs) cost a load and a store per pair and term. The
    per-pair code is written out term by term for that reason.

    ``cache_cell`` (N,3) and ``cache_vox`` (N, neighbours) memoize each point's cell and its
    neighbour voxels across calls on the same points and map (pass (0,3) and (0,0) arrays for
    none; fill ``cache_cell`` with ``CACHE_EMPTY`` to start): Newton steps move points by
    millimetres, so after the first evaluation almost no point changes cell, and the hash lookups
    are skipped.

    Reference: randt.core.ndt:ndt_derivatives_numpy
    Test: tests/core/test_kernels.py::test_derivatives_kernel_matches_numpy
    """
    inv_v = 1.0 / voxel_size
    cost = 0.0
    n_pairs = 0
    g0 = g1 = g2 = g3 = g4 = g5 = 0.0
    G00 = G01 = G02 = G03 = G04 = G05 = G11 = 0.0
    G12 = G13 = G14 = G15 = G22 = G23 = G24 = 0.0
    G25 = G33 = G34 = G35 = G44 = G45 = G55 = 0.0
    K00 = K01 = K02 = K03 = K04 = K05 = K11 = 0.0
    K12 = K13 = K14 = K15 = K22 = K23 = K24 = 0.0
    K25 = K33 = K34 = K35 = K44 = K45 = K55 = 0.0
    n_off = offsets.shape[0]
    shift = cell_shift(n_off)
    trilinear = n_off == 8
    use_cache = cache_cell.shape[0] == points.shape[0] and cache_vox.shape[1] == n_off
    vk = np.empty(n_off, dtype=np.int64)
    for i in range(points.shape[0]):
        q0, q1, q2, cx, cy, cz = _moved_and_cell(points, i, R, t, inv_v, shift)
        if use_cache and cache_cell[i, 0] == cx and cache_cell[i, 1] == cy and cache_cell[i, 2] == cz:
            for k in range(n_off):
                vk[k] = cache_vox[i, k]
        else:
            for k in range(n_off):
                vk[k] = _find(
                    table_key, table_idx, _pack(cx + offsets[k, 0], cy + offsets[k, 1], cz + offsets[k, 2])
                )
            if use_cache:
                cache_cell[i, 0], cache_cell[i, 1], cache_cell[i, 2] = cx, cy, cz
                for k in range(n_off):
                    cache_vox[i, k] = vk[k]
        fx = q0 * inv_v - shift - cx
        fy = q1 * inv_v - shift - cy
        fz = q2 * inv_v - shift - cz
        for k in range(n_off):
            v = vk[k]
            if v < 0:
                continue
            x0 = q0 - means[v, 0]
            x1 = q1 - means[v, 1]
            x2 = q2 - means[v, 2]
            a0 = inv_cov[v, 0, 0] * x0 + inv_cov[v, 0, 1] * x1 + inv_cov[v, 0, 2] * x2
            a1 = inv_cov[v, 1, 0] * x0 + inv_cov[v, 1, 1] * x1 + inv_cov[v, 1, 2] * x2
            a2 = inv_cov[v, 2, 0] * x0 + inv_cov[v, 2, 1] * x1 + inv_cov[v, 2, 2] * x2
            m = x0 * a0 + x1 * a1 + x2 * a2
            if m >= m_max:
                continue
            e = math.exp(-0.5 * d2 * m)
            if trilinear:
                e *= _trilinear_weight(offsets, k, fx, fy, fz)
            cost += d1 * e
            n_pairs += 1
            if not derivatives:
                continue
            w = -d1 * d2 * e
            wd2 = w * d2
            # J^T a = (a, (q - pivot) x a); rotation about the pivot.
            r0, r1, r2 = q0 - pivot[0], q1 - pivot[1], q2 - pivot[2]
            j0, j1, j2 = a0, a1, a2
            j3 = r1 * a2 - r2 * a1
            j4 = r2 * a0 - r0 * a2
            j5 = r0 * a1 - r1 * a0
            g0 += w * j0
            g1 += w * j1
            g2 += w * j2
            g3 += w * j3
            g4 += w * j4
            g5 += w * j5
            i00, i01, i02 = inv_cov[v, 0, 0], inv_cov[v, 0, 1], inv_cov[v, 0, 2]
            i11, i12, i22 = inv_cov[v, 1, 1], inv_cov[v, 1, 2], inv_cov[v, 2, 2]
            # M = Sigma^-1 Jr with Jr = -[q - pivot]x (columns e_k x (q - pivot)).
            m00 = i02 * r1 - i01 * r2
            m01 = i00 * r2 - i02 * r0
            m02 = i01 * r0 - i00 * r1
            m10 = i12 * r1 - i11 * r2
            m11 = i01 * r2 - i12 * r0
            m12 = i11 * r0 - i01 * r1
            m20 = i22 * r1 - i12 * r2
            m21 = i02 * r2 - i22 * r0
            m22 = i12 * r0 - i02 * r1
            G00 += w * i00
            G01 += w * i01
            G02 += w * i02
            G11 += w * i11
            G12 += w * i12
            G22 += w * i22
            G03 += w * m00
            G04 += w * m01
            G05 += w * m02
            G13 += w * m10
            G14 += w * m11
            G15 += w * m12
            G23 += w * m20
            G24 += w * m21
            G25 += w * m22
            G33 += w * (-r2 * m10 + r1 * m20)
            G34 += w * (-r2 * m11 + r1 * m21)
            G35 += w * (-r2 * m12 + r1 * m22)
            G44 += w * (r2 * m01 - r0 * m21)
            G45 += w * (r2 * m02 - r0 * m22)
            G55 += w * (r0 * m12 - r1 * m02)
            aq = a0 * r0 + a1 * r1 + a2 * r2
            K00 -= wd2 * j0 * j0
            K01 -= wd2 * j0 * j1
            K02 -= wd2 * j0 * j2
            K03 -= wd2 * j0 * j3
            K04 -= wd2 * j0 * j4
            K05 -= wd2 * j0 * j5
            K11 -= wd2 * j1 * j1
            K12 -= wd2 * j1 * j2
            K13 -= wd2 * j1 * j3
            K14 -= wd2 * j1 * j4
            K15 -= wd2 * j1 * j5
            K22 -= wd2 * j2 * j2
            K23 -= wd2 * j2 * j3
            K24 -= wd2 * j2 * j4
            K25 -= wd2 * j2 * j5
            K33 += w * (a0 * r0 - aq) - wd2 * j3 * j3
            K34 += w * (0.5 * (a0 * r1 + a1 * r0)) - wd2 * j3 * j4
            K35 += w * (0.5 * (a0 * r2 + a2 * r0)) - wd2 * j3 * j5
            K44 += w * (a1 * r1 - aq) - wd2 * j4 * j4
            K45 += w * (0.5 * (a1 * r2 + a2 * r1)) - wd2 * j4 * j5
            K55 += w * (a2 * r2 - aq) - wd2 * j5 * j5
    # Only upper triangles were accumulated (G: Gauss-Newton part, K: the rest of H): mirror.
    if derivatives:
        out_grad[0] = g0
        out_grad[1] = g1
        out_grad[2] = g2
        out_grad[3] = g3
        out_grad[4] = g4
        out_grad[5] = g5
        out_gn[0, 0] = out_gn[0, 0] = G00
        out_hess[0, 0] = out_hess[0, 0] = G00 + K00
        out_gn[0, 1] = out_gn[1, 0] = G01
        out_hess[0, 1] = out_hess[1, 0] = G01 + K01
        out_gn[0, 2] = out_gn[2, 0] = G02
        out_hess[0, 2] = out_hess[2, 0] = G02 + K02
        out_gn[0, 3] = out_gn[3, 0] = G03
        out_hess[0, 3] = out_hess[3, 0] = G03 + K03
        out_gn[0, 4] = out_gn[4, 0] = G04
        out_hess[0, 4] = out_hess[4, 0] = G04 + K04
        out_gn[0, 5] = out_gn[5, 0] = G05
        out_hess[0, 5] = out_hess[5, 0] = G05 + K05
        out_gn[1, 1] = out_gn[1, 1] = G11
        out_hess[1, 1] = out_hess[1, 1] = G11 + K11
        out_gn[1, 2] = out_gn[2, 1] = G12
        out_hess[1, 2] = out_hess[2, 1] = G12 + K12
        out_gn[1, 3] = out_gn[3, 1] = G13
        out_hess[1, 3] = out_hess[3, 1] = G13 + K13
        out_gn[1, 4] = out_gn[4, 1] = G14
        out_hess[1, 4] = out_hess[4, 1] = G14 + K14
        out_gn[1, 5] = out_gn[5, 1] = G15
        out_hess[1, 5] = out_hess[5, 1] = G15 + K15
        out_gn[2, 2] = out_gn[2, 2] = G22
        out_hess[2, 2] = out_hess[2, 2] = G22 + K22
        out_gn[2, 3] = out_gn[3, 2] = G23
        out_hess[2, 3] = out_hess[3, 2] = G23 + K23
        out_gn[2, 4] = out_gn[4, 2] = G24
        out_hess[2, 4] = out_hess[4, 2] = G24 + K24
        out_gn[2, 5] = out_gn[5, 2] = G25
        out_hess[2, 5] = out_hess[5, 2] = G25 + K25
        out_gn[3, 3] = out_gn[3, 3] = G33
        out_hess[3, 3] = out_hess[3, 3] = G33 + K33
        out_gn[3, 4] = out_gn[4, 3] = G34
        out_hess[3, 4] = out_hess[4, 3] = G34 + K34
        out_gn[3, 5] = out_gn[5, 3] = G35
        out_hess[3, 5] = out_hess[5, 3] = G35 + K35
        out_gn[4, 4] = out_gn[4, 4] = G44
        out_hess[4, 4] = out_hess[4, 4] = G44 + K44
        out_gn[4, 5] = out_gn[5, 4] = G45
        out_hess[4, 5] = out_hess[5, 4] = G45 + K45
        out_gn[5, 5] = out_gn[5, 5] = G55
        out_hess[5, 5] = out_hess[5, 5] = G55 + K55
    return cost, n_pairs


@nb.njit(cache=True, nogil=True)
def plane_information(
    points: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    table_key: np.ndarray,
    table_idx: np.ndarray,
    normals: np.ndarray,
    voxel_size: float,
) -> tuple[np.ndarray, int]:
    """``(6x6 information, points matched)``: the point-to-plane information of the points
    ``R p + t`` that lie in a map voxel, ``mean(J J^T)`` with ``J = [n, (q - c) x n / rho]``
    (``n`` the voxel's normal, ``c`` the matched points' centroid, ``rho`` their RMS distance from
    it), in two passes with no (N, 6) temporaries. The cell is ``floor(q / voxel_size)``, as
    :meth:`randt.core.voxel.VoxelGaussianMap.neighbors` finds it.

    Reference: randt.core.registration:_plane_information_numpy
    Test: tests/core/test_registration.py::test_plane_information_kernel_matches_numpy
    """
    n = points.shape[0]
    vox = np.empty(n, dtype=np.int64)
    cx = cy = cz = 0.0
    m = 0
    for i in range(n):
        q0, q1, q2 = _moved(points, i, R, t)
        v = _find(
            table_key,
            table_idx,
            _pack(
                int(math.floor(q0 / voxel_size)),
                int(math.floor(q1 / voxel_size)),
                int(math.floor(q2 / voxel_size)),
            ),
        )
        vox[i] = v
        if v >= 0:
            cx += q0
            cy += q1
            cz += q2
            m += 1
    info = np.zeros((6, 6))
    if m == 0:
        return info, 0
    cx, cy, cz = cx / m, cy / m, cz / m
    acc = np.zeros((6, 6))
    r2 = 0.0
    J = np.empty(6)
    for i in range(n):
        v = vox[i]
        if v < 0:
            continue
        q0, q1, q2 = _moved(points, i, R, t)
        r0, r1, r2_ = q0 - cx, q1 - cy, q2 - cz
        r2 += r0 * r0 + r1 * r1 + r2_ * r2_
        n0, n1, n2 = normals[v, 0], normals[v, 1], normals[v, 2]
        J[0], J[1], J[2] = n0, n1, n2
        J[3] = r1 * n2 - r2_ * n1
        J[4] = r2_ * n0 - r0 * n2
        J[5] = r0 * n1 - r1 * n0
        for a in range(6):
            for b in range(a, 6):
                acc[a, b] += J[a] * J[b]
    radius = max(math.sqrt(r2 / m), 1e-9)
    for a in range(6):
        for b in range(a, 6):
            scale = (1.0 / radius if a >= 3 else 1.0) * (1.0 / radius if b >= 3 else 1.0)
            info[a, b] = info[b, a] = acc[a, b] * scale / m
    return info, m


@nb.njit(cache=True, nogil=True)
def ndt_scores(
    points: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    table_key: np.ndarray,
    table_idx: np.ndarray,
    means: np.ndarray,
    inv_cov: np.ndarray,
    voxel_size: float,
    offsets: np.ndarray,
    d1: float,
    d2: float,
    m_max: float,
    score_sum: np.ndarray,
    score_max: np.ndarray,
    best_m: np.ndarray,
    cache_cell: np.ndarray,
    cache_vox: np.ndarray,
) -> None:
    """Per-point Autoware scores (see ``randt.core.ndt.ndt_point_scores``), written into the outputs
    (``cache_cell``/``cache_vox`` as in :func:`ndt_accumulate`).

    Reference: randt.core.ndt:ndt_point_scores_numpy
    Test: tests/core/test_kernels.py::test_point_scores_kernel_matches_numpy
    """
    inv_v = 1.0 / voxel_size
    n_off = offsets.shape[0]
    shift = cell_shift(n_off)
    use_cache = cache_cell.shape[0] == points.shape[0] and cache_vox.shape[1] == n_off
    vk = np.empty(n_off, dtype=np.int64)
    for i in range(points.shape[0]):
        q0, q1, q2, cx, cy, cz = _moved_and_cell(points, i, R, t, inv_v, shift)
        s_sum, s_max, b_m = 0.0, 0.0, np.inf
        if use_cache and cache_cell[i, 0] == cx and cache_cell[i, 1] == cy and cache_cell[i, 2] == cz:
            for k in range(n_off):
                vk[k] = cache_vox[i, k]
        else:
            for k in range(n_off):
                vk[k] = _find(
                    table_key, table_idx, _pack(cx + offsets[k, 0], cy + offsets[k, 1], cz + offsets[k, 2])
                )
        for k in range(n_off):
            v = vk[k]
            if v < 0:
                continue
            x0 = q0 - means[v, 0]
            x1 = q1 - means[v, 1]
            x2 = q2 - means[v, 2]
            m = _mahalanobis2(inv_cov, v, x0, x1, x2)
            if m >= m_max:
                continue
            s = -d1 * math.exp(-0.5 * d2 * m)
            s_sum += s
            s_max = max(s_max, s)
            b_m = min(b_m, m)
        score_sum[i] = s_sum
        score_max[i] = s_max
        best_m[i] = b_m


@nb.njit(cache=True, nogil=True)
def ndt_point_derivatives(
    points: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    table_key: np.ndarray,
    table_idx: np.ndarray,
    means: np.ndarray,
    inv_cov: np.ndarray,
    voxel_size: float,
    offsets: np.ndarray,
    d1: float,
    d2: float,
    m_max: float,
    out_grad: np.ndarray,
    out_hess: np.ndarray,
    cache_cell: np.ndarray,
    cache_vox: np.ndarray,
) -> float:
    """Per point, the NDT cost's gradient and Hessian w.r.t. the moved point ``q = R p + t``
    (the terms of :func:`ndt_accumulate` before any parameter's Jacobian): ``out_grad[i] = sum
    w a`` (3) and ``out_hess[i] = sum w (Sigma^-1 - d2 a a^T)`` (the upper triangle: xx, xy, xz,
    yy, yz, zz) over the point's pairs, weighted trilinearly with 8 ``offsets`` as there. A
    caller with its own parameters (a motion during the sweep, say) chains them by its point
    Jacobians. Returns the cost. ``cache_cell``/``cache_vox`` as in :func:`ndt_accumulate`.

    Reference: randt.core.ndt:ndt_point_derivatives_numpy
    Test: tests/core/test_kernels.py::test_point_derivatives_kernel_matches_numpy
    """
    inv_v = 1.0 / voxel_size
    n_off = offsets.shape[0]
    shift = cell_shift(n_off)
    trilinear = n_off == 8
    use_cache = cache_cell.shape[0] == points.shape[0] and cache_vox.shape[1] == n_off
    vk = np.empty(n_off, dtype=np.int64)
    cost = 0.0
    for i in range(points.shape[0]):
        q0, q1, q2, cx, cy, cz = _moved_and_cell(points, i, R, t, inv_v, shift)
        if use_cache and cache_cell[i, 0] == cx and cache_cell[i, 1] == cy and cache_cell[i, 2] == cz:
            for k in range(n_off):
                vk[k] = cache_vox[i, k]
        else:
            for k in range(n_off):
                vk[k] = _find(
                    table_key, table_idx, _pack(cx + offsets[k, 0], cy + offsets[k, 1], cz + offsets[k, 2])
                )
            if use_cache:
                cache_cell[i, 0], cache_cell[i, 1], cache_cell[i, 2] = cx, cy, cz
                for k in range(n_off):
                    cache_vox[i, k] = vk[k]
        fx = q0 * inv_v - shift - cx
        fy = q1 * inv_v - shift - cy
        fz = q2 * inv_v - shift - cz
        g0 = g1 = g2 = 0.0
        h00 = h01 = h02 = h11 = h12 = h22 = 0.0
        for k in range(n_off):
            v = vk[k]
            if v < 0:
                continue
            x0 = q0 - means[v, 0]
            x1 = q1 - means[v, 1]
            x2 = q2 - means[v, 2]
            a0 = inv_cov[v, 0, 0] * x0 + inv_cov[v, 0, 1] * x1 + inv_cov[v, 0, 2] * x2
            a1 = inv_cov[v, 1, 0] * x0 + inv_cov[v, 1, 1] * x1 + inv_cov[v, 1, 2] * x2
            a2 = inv_cov[v, 2, 0] * x0 + inv_cov[v, 2, 1] * x1 + inv_cov[v, 2, 2] * x2
            m = x0 * a0 + x1 * a1 + x2 * a2
            if m >= m_max:
                continue
            e = math.exp(-0.5 * d2 * m)
            if trilinear:
                e *= _trilinear_weight(offsets, k, fx, fy, fz)
            cost += d1 * e
            w = -d1 * d2 * e
            wd2 = w * d2
            g0 += w * a0
            g1 += w * a1
            g2 += w * a2
            h00 += w * inv_cov[v, 0, 0] - wd2 * a0 * a0
            h01 += w * inv_cov[v, 0, 1] - wd2 * a0 * a1
            h02 += w * inv_cov[v, 0, 2] - wd2 * a0 * a2
            h11 += w * inv_cov[v, 1, 1] - wd2 * a1 * a1
            h12 += w * inv_cov[v, 1, 2] - wd2 * a1 * a2
            h22 += w * inv_cov[v, 2, 2] - wd2 * a2 * a2
        out_grad[i, 0], out_grad[i, 1], out_grad[i, 2] = g0, g1, g2
        out_hess[i, 0], out_hess[i, 1], out_hess[i, 2] = h00, h01, h02
        out_hess[i, 3], out_hess[i, 4], out_hess[i, 5] = h11, h12, h22
    return cost


@nb.njit(cache=True, nogil=True)
def best_voxel(
    points: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    table_key: np.ndarray,
    table_idx: np.ndarray,
    means: np.ndarray,
    inv_cov: np.ndarray,
    voxel_size: float,
    offsets: np.ndarray,
    out_voxel: np.ndarray,
    out_m: np.ndarray,
) -> None:
    """For each point moved by ``(R, t)``: the neighbour voxel of least squared Mahalanobis
    distance (``out_voxel``, -1 when none is near) and that distance (``out_m``, inf when none).

    Reference: numpy:searchsorted
    Test: tests/core/test_kernels.py::test_hash_table_finds_every_key_and_no_other
    """
    inv_v = 1.0 / voxel_size
    shift = cell_shift(offsets.shape[0])
    for i in range(points.shape[0]):
        q0, q1, q2, cx, cy, cz = _moved_and_cell(points, i, R, t, inv_v, shift)
        best, best_m = -1, np.inf
        for k in range(offsets.shape[0]):
            v = _find(table_key, table_idx, _pack(cx + offsets[k, 0], cy + offsets[k, 1], cz + offsets[k, 2]))
            if v < 0:
                continue
            x0 = q0 - means[v, 0]
            x1 = q1 - means[v, 1]
            x2 = q2 - means[v, 2]
            m = _mahalanobis2(inv_cov, v, x0, x1, x2)
            if m < best_m:
                best, best_m = v, m
        out_voxel[i] = best
        out_m[i] = best_m


@nb.njit(cache=True, nogil=True)
def _grow(table_key: np.ndarray, table_idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same entries in a table twice as large (rehashed)."""
    cap = 2 * table_key.shape[0]
    new_key = np.full(cap, -1, dtype=np.int64)
    new_idx = np.full(cap, -1, dtype=np.int64)
    mask = cap - 1
    for s in range(table_key.shape[0]):
        key = table_key[s]
        if key == -1:
            continue
        h = _slot(key, mask)
        while new_key[h] != -1:
            h = (h + 1) & mask
        new_key[h] = key
        new_idx[h] = table_idx[s]
    return new_key, new_idx


@nb.njit(cache=True, nogil=True)
def _group_run(
    points: np.ndarray,
    start: int,
    inv_v: float,
    table_key: np.ndarray,
    table_idx: np.ndarray,
    inverse: np.ndarray,
    keys: np.ndarray,
    counts: np.ndarray,
    m: int,
) -> tuple[int, int]:
    """:func:`group_voxels`' loop from point ``start`` until the end or until the table is half
    full. Returns ``(next point, groups so far)``; next point -1 flags an invalid point."""
    mask = table_key.shape[0] - 1
    last_key, last_group = -2, -1
    for i in range(start, points.shape[0]):
        x, y, z = points[i, 0] * inv_v, points[i, 1] * inv_v, points[i, 2] * inv_v
        if not (abs(x) < 2.0**40 and abs(y) < 2.0**40 and abs(z) < 2.0**40):  # also catches NaN
            return -1, m
        key = _pack(int(math.floor(x)), int(math.floor(y)), int(math.floor(z)))
        if key < 0:
            return -1, m
        if key != last_key:
            if 2 * (m + 1) > mask:
                return i, m  # grow the table before inserting more
            h = _slot(key, mask)
            while table_key[h] != -1 and table_key[h] != key:
                h = (h + 1) & mask
            if table_key[h] == -1:
                table_key[h] = key
                table_idx[h] = m
                keys[m] = key
                m += 1
            last_key, last_group = key, table_idx[h]
        inverse[i] = last_group
        counts[last_group] += 1
    return points.shape[0], m


@nb.njit(cache=True, nogil=True)
def group_voxels(
    points: np.ndarray, voxel_size: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """Group points by voxel in one hashed pass (no sort), groups numbered in first-seen order.

    Returns ``(inverse, keys, counts, table_key, table_idx, ok)``: the group of each point, each
    group's packed key and size, the open-addressing table from key to group (as
    :func:`build_hash` makes it), and ``ok`` false when a point is non-finite or its cell lies
    outside the 21-bit key range (the outputs are then meaningless). The table starts small and
    doubles at half full, so it stays in cache; a point in the same voxel as the one before it (the
    common case in a scan's ring order) skips the probe. (Growing happens outside the hot loop:
    numba reference-counts arrays reassigned inside a loop.)

    Reference: numpy:unique
    Test: tests/core/test_kernels.py::test_group_voxels_matches_np_unique
    """
    n = points.shape[0]
    inv_v = 1.0 / voxel_size
    table_key = np.full(1024, -1, dtype=np.int64)
    table_idx = np.full(1024, -1, dtype=np.int64)
    inverse = np.empty(n, dtype=np.int64)
    keys = np.empty(n, dtype=np.int64)
    counts = np.zeros(n, dtype=np.int64)
    i, m = 0, 0
    while True:
        i, m = _group_run(points, i, inv_v, table_key, table_idx, inverse, keys, counts, m)
        if i < 0:
            return inverse, keys[:0].copy(), counts[:0].copy(), table_key, table_idx, False
        if i >= n:
            return inverse, keys[:m].copy(), counts[:m].copy(), table_key, table_idx, True
        table_key, table_idx = _grow(table_key, table_idx)


@nb.njit(cache=True, nogil=True)
def group_moments(
    points: np.ndarray, inverse: np.ndarray, n_groups: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per group: point count, mean and scatter matrix (sum of outer products of the deviations
    from the mean, two passes for accuracy). Returns ``(counts, means (m,3), scatter (m,3,3))``.

    Reference: numpy:cov
    Test: tests/core/test_kernels.py::test_voxel_gaussians_match_a_per_voxel_numpy_fit
    """
    counts = np.zeros(n_groups, dtype=np.int64)
    means = np.zeros((n_groups, 3))
    scatter = np.zeros((n_groups, 3, 3))
    for i in range(points.shape[0]):
        g = inverse[i]
        counts[g] += 1
        means[g, 0] += points[i, 0]
        means[g, 1] += points[i, 1]
        means[g, 2] += points[i, 2]
    for g in range(n_groups):
        c = max(counts[g], 1)
        means[g, 0] /= c
        means[g, 1] /= c
        means[g, 2] /= c
    for i in range(points.shape[0]):
        g = inverse[i]
        d0, d1, d2 = points[i, 0] - means[g, 0], points[i, 1] - means[g, 1], points[i, 2] - means[g, 2]
        scatter[g, 0, 0] += d0 * d0
        scatter[g, 0, 1] += d0 * d1
        scatter[g, 0, 2] += d0 * d2
        scatter[g, 1, 1] += d1 * d1
        scatter[g, 1, 2] += d1 * d2
        scatter[g, 2, 2] += d2 * d2
    for g in range(n_groups):
        scatter[g, 1, 0] = scatter[g, 0, 1]
        scatter[g, 2, 0] = scatter[g, 0, 2]
        scatter[g, 2, 1] = scatter[g, 1, 2]
    return counts, means, scatter


@nb.njit(cache=True, nogil=True)
def group_weighted_moments(
    points: np.ndarray, inverse: np.ndarray, centres: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per group, weighted moments about the group's centre, in one pass: ``(sum w (m,),
    sum w d (m,3), sum w d d^T (m,3,3))`` with ``d = p - centres[group]`` (a weight of -1 takes a
    point out, so the sums of points that came and left cancel to round-off).

    Reference: numpy:bincount
    Test: tests/core/test_kernels.py::test_group_weighted_moments_match_bincount
    """
    m = centres.shape[0]
    wsum = np.zeros(m)
    sums = np.zeros((m, 3))
    scatter = np.zeros((m, 3, 3))
    for i in range(points.shape[0]):
        g = inverse[i]
        w = weights[i]
        d0 = points[i, 0] - centres[g, 0]
        d1 = points[i, 1] - centres[g, 1]
        d2 = points[i, 2] - centres[g, 2]
        wsum[g] += w
        sums[g, 0] += w * d0
        sums[g, 1] += w * d1
        sums[g, 2] += w * d2
        scatter[g, 0, 0] += w * d0 * d0
        scatter[g, 0, 1] += w * d0 * d1
        scatter[g, 0, 2] += w * d0 * d2
        scatter[g, 1, 1] += w * d1 * d1
        scatter[g, 1, 2] += w * d1 * d2
        scatter[g, 2, 2] += w * d2 * d2
    for g in range(m):
        scatter[g, 1, 0] = scatter[g, 0, 1]
        scatter[g, 2, 0] = scatter[g, 0, 2]
        scatter[g, 2, 1] = scatter[g, 1, 2]
    return wsum, sums, scatter


@nb.njit(cache=True, nogil=True)
def parent_moments(
    inverse: np.ndarray, parent_center: np.ndarray, counts: np.ndarray, means: np.ndarray, scatter: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Counts, means and scatter matrices (about the means) of parent voxels from their
    children's (child ``c`` in parent ``inverse[c]``): ``S = sum(S_c + n_c d_c d_c^T) - n e e^T``
    with ``d_c`` the child's mean and ``e`` the parent's about the parent's centre.

    Reference: randt.core.voxel:_parent_moments_numpy
    Test: tests/core/test_kernels.py::test_parent_moments_match_bincount
    """
    m = parent_center.shape[0]
    n_p = np.zeros(m)
    e = np.zeros((m, 3))
    out = np.zeros((m, 3, 3))
    for c in range(inverse.shape[0]):
        g = inverse[c]
        n = float(counts[c])
        d0 = means[c, 0] - parent_center[g, 0]
        d1 = means[c, 1] - parent_center[g, 1]
        d2 = means[c, 2] - parent_center[g, 2]
        n_p[g] += n
        e[g, 0] += n * d0
        e[g, 1] += n * d1
        e[g, 2] += n * d2
        d = (d0, d1, d2)
        for r in range(3):
            for k in range(3):
                out[g, r, k] += scatter[c, r, k] + n * d[r] * d[k]
    mean = np.empty((m, 3))
    for g in range(m):
        for r in range(3):
            e[g, r] /= n_p[g]
        for r in range(3):
            for k in range(3):
                out[g, r, k] -= n_p[g] * e[g, r] * e[g, k]
            mean[g, r] = parent_center[g, r] + e[g, r]
    return n_p.astype(np.int64), mean, out


@nb.njit(cache=True, nogil=True)
def group_centroids(points: np.ndarray, inverse: np.ndarray, n_groups: int) -> np.ndarray:
    """Mean of each group's points, (m,3).

    Reference: numpy:bincount
    Test: tests/core/test_kernels.py::test_group_centroids_match_bincount
    """
    sums = np.zeros((n_groups, 3))
    counts = np.zeros(n_groups)
    for i in range(points.shape[0]):
        g = inverse[i]
        counts[g] += 1.0
        sums[g, 0] += points[i, 0]
        sums[g, 1] += points[i, 1]
        sums[g, 2] += points[i, 2]
    for g in range(n_groups):
        sums[g, 0] /= counts[g]
        sums[g, 1] /= counts[g]
        sums[g, 2] /= counts[g]
    return sums


def cell_block(reach: int) -> np.ndarray:
    """Offsets of the ``(2 reach + 1)^3`` cell block, own cell first, then by their least possible
    distance (faces, edges, corners, then the next shell), so the best candidates are met early and
    the rest are pruned by their box distance."""
    r = range(-reach, reach + 1)
    offsets = [(dx, dy, dz) for dx in r for dy in r for dz in r]

    def rank(o: tuple[int, int, int]) -> tuple[int, int]:
        return sum(max(abs(d) - 1, 0) ** 2 for d in o), sum(abs(d) for d in o)

    return np.array(sorted(offsets, key=rank), dtype=np.int64)


_BLOCK = cell_block(1)


@nb.njit(cache=True, inline="always")
def _face_d2(d: int, low: float, cell: float) -> float:
    """Squared gap along one axis from a point ``low`` above its cell's lower face to the cell at
    offset ``d``."""
    if d < 0:
        g = low + (-d - 1) * cell
        return g * g
    if d > 0:
        g = (cell - low) + (d - 1) * cell
        return g * g
    return 0.0


@nb.njit(cache=True, inline="always")
def _shell_gap(d: int) -> int:
    """Least number of whole cells between a point and the cell at offset ``d`` along one axis,
    squared (:func:`cell_block`'s first sort key, summed over the axes)."""
    g = abs(d) - 1
    return g * g if g > 0 else 0


@nb.njit(cache=True, nogil=True)
def build_grid(
    points: np.ndarray, cell_size: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """A hashed uniform grid over ``points`` for fixed-radius searches (cell = search radius).

    Returns ``(table_key, table_idx, starts, order, ok)``: cell ``c`` (found through the table)
    holds the points ``order[starts[c]:starts[c + 1]]``; ``ok`` as in :func:`group_voxels`.

    Reference: scipy.spatial:cKDTree
    Test: tests/core/test_kernels.py::test_point_grid_nearest_matches_kdtree
    """
    inverse, keys, counts, table_key, table_idx, ok = group_voxels(points, cell_size)
    m = keys.shape[0]
    starts = np.zeros(m + 1, dtype=np.int64)
    order = np.empty(points.shape[0], dtype=np.int64)
    if not ok:
        return table_key, table_idx, starts, order, False
    for c in range(m):
        starts[c + 1] = starts[c] + counts[c]
    fill = starts[:m].copy()
    for i in range(points.shape[0]):
        g = inverse[i]
        order[fill[g]] = i
        fill[g] += 1
    return table_key, table_idx, starts, order, True


@nb.njit(cache=True, nogil=True)
def grid_nearest(
    queries: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    ref: np.ndarray,
    table_key: np.ndarray,
    table_idx: np.ndarray,
    starts: np.ndarray,
    order: np.ndarray,
    cell_size: float,
    max_dist: float,
    out_idx: np.ndarray,
    out_d2: np.ndarray,
) -> None:
    """Nearest reference point of each query moved by ``(R, t)``, within ``max_dist``.

    Exact when ``max_dist <= cell_size`` (every point that close lies in the query's 3x3x3 cell
    block). Writes the index (-1 when none is that close) and the squared distance (inf then).

    Reference: scipy.spatial:cKDTree
    Test: tests/core/test_kernels.py::test_point_grid_nearest_matches_kdtree
    """
    inv_c = 1.0 / cell_size
    max_d2 = max_dist * max_dist
    for i in range(queries.shape[0]):
        q0, q1, q2, cx, cy, cz = _moved_and_cell(queries, i, R, t, inv_c)
        # Offsets of the query inside its cell, per axis: to the lower and the upper face.
        lx, ly, lz = q0 - cx * cell_size, q1 - cy * cell_size, q2 - cz * cell_size
        best, best_d2 = -1, max_d2
        for n_off in range(27):
            # The own cell first (n_off 0 maps to offset 0,0,0), then the others.
            dx, dy, dz = _BLOCK[n_off, 0], _BLOCK[n_off, 1], _BLOCK[n_off, 2]
            box = _face_d2(dx, lx, cell_size) + _face_d2(dy, ly, cell_size) + _face_d2(dz, lz, cell_size)
            if box > best_d2:
                continue  # nothing in that cell can beat the best so far
            c = _find(table_key, table_idx, _pack(cx + dx, cy + dy, cz + dz))
            if c < 0:
                continue
            for s in range(starts[c], starts[c + 1]):
                j = order[s]
                e0, e1, e2 = ref[j, 0] - q0, ref[j, 1] - q1, ref[j, 2] - q2
                d2 = e0 * e0 + e1 * e1 + e2 * e2
                if d2 <= best_d2:
                    best, best_d2 = j, d2
        out_idx[i] = best
        out_d2[i] = best_d2 if best >= 0 else np.inf


@nb.njit(cache=True, inline="always")
def _jacobi_rotate(A: np.ndarray, V: np.ndarray, p: int, q: int) -> None:
    """One Jacobi rotation zeroing ``A[p, q]`` of a symmetric 3x3 ``A`` (accumulated into ``V``)."""
    apq = A[p, q]
    if apq == 0.0:
        return
    theta = (A[q, q] - A[p, p]) / (2.0 * apq)
    tt = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
    if theta < 0.0:
        tt = -tt
    c = 1.0 / math.sqrt(tt * tt + 1.0)
    s = tt * c
    for k in range(3):
        akp, akq = A[k, p], A[k, q]
        A[k, p] = c * akp - s * akq
        A[k, q] = s * akp + c * akq
    for k in range(3):
        apk, aqk = A[p, k], A[q, k]
        A[p, k] = c * apk - s * aqk
        A[q, k] = s * apk + c * aqk
    for k in range(3):
        vkp, vkq = V[k, p], V[k, q]
        V[k, p] = c * vkp - s * vkq
        V[k, q] = s * vkp + c * vkq


@nb.njit(cache=True, nogil=True)
def smallest_eigenvector(A: np.ndarray, V: np.ndarray) -> int:
    """Cyclic Jacobi on a symmetric 3x3 ``A`` (overwritten with its eigenvalues on the diagonal,
    ``V`` with the eigenvectors as columns); returns the column of the smallest eigenvalue.

    Reference: numpy.linalg:eigh
    Test: tests/core/test_kernels.py::test_point_grid_normals_match_hybrid_knn
    """
    for r in range(3):
        for c in range(3):
            V[r, c] = 1.0 if r == c else 0.0
    scale = A[0, 0] * A[0, 0] + A[1, 1] * A[1, 1] + A[2, 2] * A[2, 2]
    for _ in range(20):
        off = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
        if off <= 1e-30 * scale or off == 0.0:
            break
        _jacobi_rotate(A, V, 0, 1)
        _jacobi_rotate(A, V, 0, 2)
        _jacobi_rotate(A, V, 1, 2)
    best = 0
    if A[1, 1] < A[best, best]:
        best = 1
    if A[2, 2] < A[best, best]:
        best = 2
    return best


@nb.njit(cache=True, nogil=True)
def grid_knn_normals(
    ref: np.ndarray,
    which: np.ndarray,
    table_key: np.ndarray,
    table_idx: np.ndarray,
    starts: np.ndarray,
    order: np.ndarray,
    cell_size: float,
    offsets: np.ndarray,
    radius: float,
    k: int,
    min_points: int,
    out_normals: np.ndarray,
    out_valid: np.ndarray,
) -> None:
    """Surface normals at ``ref[which]`` from their ``k`` nearest neighbours within ``radius``.

    The hybrid search of Open3D's ``KDTreeSearchParamHybrid(radius, max_nn=k)``: up to ``k``
    nearest reference points (the point itself included) no farther than ``radius``; the normal is
    the eigenvector of the smallest eigenvalue of their covariance. Fewer than ``min_points``
    neighbours give no normal (``out_valid`` false, normal zero). ``offsets`` is the
    :func:`cell_block` whose reach covers the radius (``reach * cell_size >= radius``).

    Reference: numpy.linalg:eigh
    Test: tests/core/test_kernels.py::test_point_grid_normals_match_hybrid_knn
    """
    inv_c = 1.0 / cell_size
    r2 = radius * radius
    c2 = cell_size * cell_size
    bd2 = np.empty(k)
    bi = np.empty(k, dtype=np.int64)
    A = np.empty((3, 3))
    V = np.empty((3, 3))
    identity = np.eye(3)
    zero = np.zeros(3)
    for w in range(which.shape[0]):
        p = which[w]
        q0, q1, q2, cx, cy, cz = _moved_and_cell(ref, p, identity, zero, inv_c)
        lx, ly, lz = q0 - cx * cell_size, q1 - cy * cell_size, q2 - cz * cell_size
        n_found = 0
        for n_off in range(offsets.shape[0]):
            dx, dy, dz = offsets[n_off, 0], offsets[n_off, 1], offsets[n_off, 2]
            # The offsets come by their least possible distance: once that is beyond the radius
            # or the k-th best so far, so is every later cell's.
            least = _shell_gap(dx) + _shell_gap(dy) + _shell_gap(dz)
            if least * c2 > (bd2[k - 1] if n_found == k else r2):
                break
            box = _face_d2(dx, lx, cell_size) + _face_d2(dy, ly, cell_size) + _face_d2(dz, lz, cell_size)
            if box > r2 or (n_found == k and box >= bd2[k - 1]):
                continue
            c = _find(table_key, table_idx, _pack(cx + dx, cy + dy, cz + dz))
            if c < 0:
                continue
            for s in range(starts[c], starts[c + 1]):
                j = order[s]
                e0, e1, e2 = ref[j, 0] - q0, ref[j, 1] - q1, ref[j, 2] - q2
                d2 = e0 * e0 + e1 * e1 + e2 * e2
                if d2 > r2 or (n_found == k and d2 >= bd2[k - 1]):
                    continue
                # Insertion into the sorted buffer of the k best so far.
                pos = n_found if n_found < k else k - 1
                while pos > 0 and bd2[pos - 1] > d2:
                    bd2[pos] = bd2[pos - 1]
                    bi[pos] = bi[pos - 1]
                    pos -= 1
                bd2[pos] = d2
                bi[pos] = j
                if n_found < k:
                    n_found += 1
        if n_found < min_points:
            out_valid[w] = False
            out_normals[w, 0] = out_normals[w, 1] = out_normals[w, 2] = 0.0
            continue
        m0 = m1 = m2 = 0.0
        for s in range(n_found):
            j = bi[s]
            m0 += ref[j, 0]
            m1 += ref[j, 1]
            m2 += ref[j, 2]
        m0 /= n_found
        m1 /= n_found
        m2 /= n_found
        for r in range(3):
            for c in range(3):
                A[r, c] = 0.0
        for s in range(n_found):
            j = bi[s]
            e0, e1, e2 = ref[j, 0] - m0, ref[j, 1] - m1, ref[j, 2] - m2
            A[0, 0] += e0 * e0
            A[0, 1] += e0 * e1
            A[0, 2] += e0 * e2
            A[1, 1] += e1 * e1
            A[1, 2] += e1 * e2
            A[2, 2] += e2 * e2
        A[1, 0], A[2, 0], A[2, 1] = A[0, 1], A[0, 2], A[1, 2]
        col = smallest_eigenvector(A, V)
        out_valid[w] = True
        out_normals[w, 0], out_normals[w, 1], out_normals[w, 2] = V[0, col], V[1, col], V[2, col]


@nb.njit(cache=True, nogil=True)
def eigh3(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigen-decomposition of symmetric 3x3 matrices (Jacobi), like ``np.linalg.eigh``: eigenvalues
    ascending (m,3) and eigenvectors as columns (m,3,3). Faster than LAPACK's per-matrix calls for
    thousands of 3x3 voxel covariances.

    Reference: numpy.linalg:eigh
    Test: tests/core/test_kernels.py::test_eigh3_matches_lapack
    """
    m = matrices.shape[0]
    evals = np.empty((m, 3))
    evecs = np.empty((m, 3, 3))
    A = np.empty((3, 3))
    V = np.empty((3, 3))
    for g in range(m):
        for r in range(3):
            for c in range(3):
                A[r, c] = matrices[g, r, c]
        smallest_eigenvector(A, V)
        d0, d1, d2 = A[0, 0], A[1, 1], A[2, 2]
        # Sort the three eigenpairs ascending.
        i0, i1, i2 = 0, 1, 2
        if d1 < d0:
            i0, i1 = i1, i0
        if d2 < A[i1, i1]:
            i1, i2 = i2, i1
        if A[i1, i1] < A[i0, i0]:
            i0, i1 = i1, i0
        order = (i0, i1, i2)
        for c in range(3):
            src_c = order[c]
            evals[g, c] = A[src_c, src_c]
            for r in range(3):
                evecs[g, r, c] = V[r, src_c]
    return evals, evecs


@nb.njit(cache=True, nogil=True)
def conditioned_gaussians(
    scatter: np.ndarray, counts: np.ndarray, eigenvalue_ratio: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per voxel, from its scatter matrix about the mean and its point count, the conditioned
    covariance (eigenvalues below ``eigenvalue_ratio`` times the largest raised to it, at least
    1e-12), its inverse, the whitening ``W`` (``W^T W`` the inverse) and the normal (eigenvector
    of the smallest eigenvalue): ``(cov, inv, whitening, normals)``, in one pass with no (m,3,3)
    temporaries (the numpy form's batched 3x3 products were most of a pyramid's fit).

    Reference: randt.core.voxel:VoxelGaussianMap._from_moments_numpy
    Test: tests/core/test_kernels.py::test_conditioned_gaussians_match_the_numpy_fit
    """
    m = scatter.shape[0]
    cov = np.empty((m, 3, 3))
    inv = np.empty((m, 3, 3))
    white = np.empty((m, 3, 3))
    normals = np.empty((m, 3))
    A = np.empty((3, 3))
    V = np.empty((3, 3))
    e = np.empty(3)
    vec = np.empty((3, 3))
    for g in range(m):
        denom = max(counts[g] - 1.0, 1.0)
        for r in range(3):
            for c in range(3):
                A[r, c] = scatter[g, r, c] / denom
        smallest_eigenvector(A, V)
        d0, d1, d2 = A[0, 0], A[1, 1], A[2, 2]
        i0, i1, i2 = 0, 1, 2  # the eigenpairs ascending, as eigh3 sorts them
        if d1 < d0:
            i0, i1 = i1, i0
        if d2 < A[i1, i1]:
            i1, i2 = i2, i1
        if A[i1, i1] < A[i0, i0]:
            i0, i1 = i1, i0
        order = (i0, i1, i2)
        for c in range(3):
            e[c] = A[order[c], order[c]]
            for r in range(3):
                vec[r, c] = V[r, order[c]]
        floor = max(e[2] * eigenvalue_ratio, 1e-12)
        for c in range(3):
            e[c] = max(e[c], floor)
        for r in range(3):
            for c in range(3):
                s_cov = 0.0
                s_inv = 0.0
                for k in range(3):
                    s_cov += vec[r, k] * e[k] * vec[c, k]
                    s_inv += vec[r, k] / e[k] * vec[c, k]
                cov[g, r, c] = s_cov
                inv[g, r, c] = s_inv
                white[g, r, c] = vec[c, r] / math.sqrt(e[r])
            normals[g, r] = vec[r, 0]
    return cov, inv, white, normals


@nb.njit(cache=True, nogil=True)
def mahalanobis_to_assigned(
    points: np.ndarray, assignment: np.ndarray, means: np.ndarray, inv_cov: np.ndarray
) -> np.ndarray:
    """Squared Mahalanobis distance of each point to its assigned voxel (inf where -1).

    Reference: randt.core.outliers:iqr_inlier_mask_numpy
    Test: tests/core/test_kernels.py::test_algorithm1_kernel_matches_the_lexsort_formulation
    """
    out = np.empty(points.shape[0])
    for i in range(points.shape[0]):
        v = assignment[i]
        if v < 0:
            out[i] = np.inf
            continue
        out[i] = _mahalanobis2(
            inv_cov, v, points[i, 0] - means[v, 0], points[i, 1] - means[v, 1], points[i, 2] - means[v, 2]
        )
    return out


@nb.njit(cache=True, nogil=True)
def grouped_fence_mask(
    values: np.ndarray,
    group: np.ndarray,
    n_groups: int,
    k: float,
    min_count: int,
    pooled_lo: float,
    pooled_hi: float,
) -> np.ndarray:
    """True where a value lies inside its group's Tukey fences ``[Q1 - k IQR, Q3 + k IQR]``.

    Quartiles are linear-interpolated order statistics (NumPy's default: the q-quantile of n sorted
    values sits at position ``q (n - 1)``). Groups of fewer than ``min_count`` values use the
    pooled fences; values of group -1 are outside. One counting sort by group, then a sort of each
    group's few values: no global ``lexsort``.

    Reference: randt.core.outliers:iqr_inlier_mask_numpy
    Test: tests/core/test_kernels.py::test_algorithm1_kernel_matches_the_lexsort_formulation
    """
    n = values.shape[0]
    counts = np.zeros(n_groups + 1, dtype=np.int64)
    for i in range(n):
        if group[i] >= 0:
            counts[group[i] + 1] += 1
    for g in range(n_groups):
        counts[g + 1] += counts[g]
    fill = counts[:n_groups].copy()
    order = np.empty(counts[n_groups], dtype=np.int64)
    for i in range(n):
        g = group[i]
        if g >= 0:
            order[fill[g]] = i
            fill[g] += 1
    inside = np.zeros(n, dtype=np.bool_)
    for g in range(n_groups):
        s, e = counts[g], counts[g + 1]
        m = e - s
        if m == 0:
            continue
        if m < min_count:
            lo, hi = pooled_lo, pooled_hi
        else:
            vals = np.empty(m)
            for t in range(m):
                vals[t] = values[order[s + t]]
            vals.sort()
            qs = np.empty(2)
            for qi in range(2):
                pos = (0.25 if qi == 0 else 0.75) * (m - 1)
                lo_i = int(math.floor(pos))
                hi_i = min(lo_i + 1, m - 1)
                frac = pos - lo_i
                qs[qi] = vals[lo_i] * (1.0 - frac) + vals[hi_i] * frac
            iqr = qs[1] - qs[0]
            lo, hi = qs[0] - k * iqr, qs[1] + k * iqr
        for t in range(s, e):
            v = values[order[t]]
            inside[order[t]] = v >= lo and v <= hi
    return inside


@nb.njit(cache=True, nogil=True)
def isolated_points(
    points: np.ndarray,
    voxel_size: float,
    inverse: np.ndarray,
    counts: np.ndarray,
    table_key: np.ndarray,
    table_idx: np.ndarray,
) -> np.ndarray:
    """True for points alone in their voxel whose 26 neighbour voxels are all empty (the voxel
    grouping of :func:`group_voxels` passed in).

    Reference: randt.core.features:_isolated_numpy
    Test: tests/core/test_kernels.py::test_isolated_point_kernel_matches_numpy
    """
    inv_v = 1.0 / voxel_size
    out = np.zeros(points.shape[0], dtype=np.bool_)
    for i in range(points.shape[0]):
        if counts[inverse[i]] != 1:
            continue
        cx = int(math.floor(points[i, 0] * inv_v))
        cy = int(math.floor(points[i, 1] * inv_v))
        cz = int(math.floor(points[i, 2] * inv_v))
        alone = True
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    if (dx or dy or dz) and _find(
                        table_key, table_idx, _pack(cx + dx, cy + dy, cz + dz)
                    ) >= 0:
                        alone = False
                        break
                if not alone:
                    break
            if not alone:
                break
        out[i] = alone
    return out


@nb.njit(cache=True, nogil=True)
def group_min(values: np.ndarray, inverse: np.ndarray, n_groups: int, skip: np.ndarray) -> np.ndarray:
    """Least value of each group over the entries not flagged in ``skip`` (inf for none).

    Reference: numpy:minimum
    Test: tests/core/test_kernels.py::test_group_min_matches_minimum_at
    """
    out = np.full(n_groups, np.inf)
    for i in range(values.shape[0]):
        if not skip[i] and values[i] < out[inverse[i]]:
            out[inverse[i]] = values[i]
    return out


@nb.njit(cache=True, nogil=True)
def masked_group_centroids(
    points: np.ndarray, inverse: np.ndarray, n_groups: int, mask: np.ndarray
) -> np.ndarray:
    """Mean of the masked points of each group, for the groups holding at least one masked point
    (in group order): voxel downsampling of a subset, reusing a grouping of the whole cloud.

    Reference: numpy:bincount
    Test: tests/core/test_kernels.py::test_group_centroids_match_bincount
    """
    sums = np.zeros((n_groups, 3))
    counts = np.zeros(n_groups)
    for i in range(points.shape[0]):
        if mask[i]:
            g = inverse[i]
            counts[g] += 1.0
            sums[g, 0] += points[i, 0]
            sums[g, 1] += points[i, 1]
            sums[g, 2] += points[i, 2]
    m = 0
    for g in range(n_groups):
        if counts[g] > 0:
            sums[m, 0] = sums[g, 0] / counts[g]
            sums[m, 1] = sums[g, 1] / counts[g]
            sums[m, 2] = sums[g, 2] / counts[g]
            m += 1
    return sums[:m].copy()


@nb.njit(cache=True, nogil=True)
def first_per_voxel_pair(
    tile_keys: np.ndarray, voxel_keys: np.ndarray, xyz32: np.ndarray, cap: int
) -> np.ndarray:
    """True for the first ``cap`` distinct points of each (tile key, voxel key) pair, in arrival
    order: what :meth:`randt.core.tiles.TileGrid.candidate_mask` keeps, in one hashed pass where its
    numpy twin sorts twice (``np.lexsort``). A point equal (float32 x, y, z) to one already kept in
    its voxel is not distinct and is skipped, as the map's insert drops it: the map's policy
    (:func:`voxel_table_admit`) against an empty map.

    Reference: randt.core.tiles:TileGrid.candidate_mask_numpy
    Test: tests/core/test_tiles.py::test_compiled_candidate_mask_equals_the_numpy_reference
    """
    n = tile_keys.shape[0]
    size = 16
    while size < 2 * (n + 1):
        size <<= 1
    table_t = np.full(size, -1, dtype=np.int64)
    table_v = np.empty(size, dtype=np.int64)
    table_c = np.zeros(size, dtype=np.int32)
    table_xyz = np.empty((size, cap if cap > 1 else 0, 3), dtype=np.float32)
    out = np.zeros(n, dtype=np.bool_)
    voxel_table_admit(table_t, table_v, table_c, table_xyz, 0, tile_keys, voxel_keys, xyz32, cap, 0, out)
    return out


@nb.njit(cache=True, nogil=True)
def tile_voxel_keys(
    xyz32: np.ndarray, tile_size: float, voxel_size: float, tile_offset: int
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Packed tile keys and packed tile-local voxel keys of float32 points,
    with the same float64 operations as the numpy formulation in :mod:`randt.core.tiles` (``floor(x /
    tile)``, ``x - ix * tile``, ``floor(local / voxel)``), so the keys are identical. ``ok`` is
    false when a voxel coordinate leaves the 21-bit key range.

    Reference: randt.core.tiles:TileGrid.candidate_mask_numpy
    Test: tests/core/test_tiles.py::test_compiled_candidate_mask_equals_the_numpy_reference
    """
    n = xyz32.shape[0]
    tkeys = np.empty(n, dtype=np.int64)
    vkeys = np.empty(n, dtype=np.int64)
    big = 2.0**40
    for i in range(n):
        x, y, z = np.float64(xyz32[i, 0]), np.float64(xyz32[i, 1]), np.float64(xyz32[i, 2])
        if not (abs(x / tile_size) < big and abs(y / tile_size) < big and abs(z / voxel_size) < big):
            return tkeys, vkeys, False  # also catches NaN
        tx = int(math.floor(x / tile_size))
        ty = int(math.floor(y / tile_size))
        lx = x - tx * tile_size
        ly = y - ty * tile_size
        cx, cy = int(math.floor(lx / voxel_size)), int(math.floor(ly / voxel_size))
        key = _pack(cx, cy, int(math.floor(z / voxel_size)))
        if key < 0:
            return tkeys, vkeys, False
        tkeys[i] = ((tx + tile_offset) << 31) | (ty + tile_offset)
        vkeys[i] = key
    return tkeys, vkeys, True


@nb.njit(cache=True, nogil=True)
def within_xy_radius(points: np.ndarray, cx: float, cy: float, radius2: float) -> np.ndarray:
    """The rows of ``points`` (N,3) within ``sqrt(radius2)`` of ``(cx, cy)`` in XY, in order.

    A counting pass, then one writing the survivors into an array of exactly their size (no
    oversized buffer to fill and copy: for a full window's fused keyframe points, fresh pages cost
    more than the loop), instead of numpy's boolean mask and fancy indexing.

    Reference: numpy:sum
    Test: tests/core/test_kernels.py::test_within_xy_radius_matches_the_numpy_crop
    """
    n = points.shape[0]
    m = 0
    for i in range(n):
        dx = points[i, 0] - cx
        dy = points[i, 1] - cy
        if dx * dx + dy * dy <= radius2:
            m += 1
    out = np.empty((m, 3))
    m = 0
    for i in range(n):
        dx = points[i, 0] - cx
        dy = points[i, 1] - cy
        if dx * dx + dy * dy <= radius2:
            out[m, 0] = points[i, 0]
            out[m, 1] = points[i, 1]
            out[m, 2] = points[i, 2]
            m += 1
    return out


@nb.njit(cache=True, nogil=True)
def consistency_graph(a: np.ndarray, b: np.ndarray, bound: float) -> np.ndarray:
    """Pairwise consistency of correspondences ``a[i] <-> b[i]`` (n,3 each): ``adj[i, j]`` when a
    rigid motion can keep both, ``| |a_i - a_j| - |b_i - b_j| | <= bound`` (no self loops).

    The numpy form builds two (n,n,3) difference arrays (430 MB at n = 3000); this one writes the
    (n,n) booleans directly.

    Reference: numpy:linalg.norm
    Test: tests/core/test_kernels.py::test_consistency_graph_and_core_numbers_match_numpy
    """
    n = a.shape[0]
    adj = np.zeros((n, n), dtype=np.bool_)
    for i in range(n):
        for j in range(i + 1, n):
            da = math.sqrt((a[i, 0] - a[j, 0]) ** 2 + (a[i, 1] - a[j, 1]) ** 2 + (a[i, 2] - a[j, 2]) ** 2)
            db = math.sqrt((b[i, 0] - b[j, 0]) ** 2 + (b[i, 1] - b[j, 1]) ** 2 + (b[i, 2] - b[j, 2]) ** 2)
            if abs(da - db) <= bound:
                adj[i, j] = True
                adj[j, i] = True
    return adj


@nb.njit(cache=True, nogil=True)
def core_numbers(adj: np.ndarray) -> np.ndarray:
    """Core number of every vertex of the graph ``adj`` ((n,n) bool, symmetric): the largest k
    such that the vertex belongs to a subgraph where every vertex has degree >= k. Peeling the
    vertex of least degree each time (Batagelj & Zaversnik 2003), O(n^2) on a dense matrix.

    Reference: numpy:sum
    Test: tests/core/test_kernels.py::test_consistency_graph_and_core_numbers_match_numpy
    """
    n = adj.shape[0]
    degree = np.zeros(n, dtype=np.int64)
    for i in range(n):
        for j in range(n):
            if adj[i, j]:
                degree[i] += 1
    removed = np.zeros(n, dtype=np.bool_)
    core = np.zeros(n, dtype=np.int64)
    k = 0
    for _ in range(n):
        v = -1
        for u in range(n):
            if not removed[u] and (v < 0 or degree[u] < degree[v]):
                v = u
        k = max(k, degree[v])
        core[v] = k
        removed[v] = True
        for u in range(n):
            if adj[v, u] and not removed[u]:
                degree[u] -= 1
    return core


@nb.njit(cache=True, nogil=True)
def spfh_histograms(points: np.ndarray, normals: np.ndarray, neighbors: np.ndarray, bins: int) -> np.ndarray:
    """Simplified point feature histograms (n, 3*bins) in percent of each point's pairs.

    ``neighbors`` (n,k) holds each point's neighbour rows (``n`` marks a missing one). For a pair,
    the source is the point whose normal is closer to the connecting line (PCL's rule); with the
    Darboux frame ``u = n_s, v = u x d, w = u x v`` (``d`` the unit line from source to target),
    ``alpha = v.n_t`` and ``phi = u.d`` are binned over [-1, 1] and
    ``theta = atan2(w.n_t, u.n_t)`` over [-pi, pi] (Rusu et al., ICRA 2009).

    Reference: randt.core.global_registration:spfh_reference
    Test: tests/core/test_global_registration.py::test_spfh_kernel_matches_the_numpy_reference
    """
    n, k = neighbors.shape
    out = np.zeros((n, 3 * bins))
    for i in range(n):
        count = 0
        for c in range(k):
            j = neighbors[i, c]
            if j >= n or j == i:
                continue
            dx = points[j, 0] - points[i, 0]
            dy = points[j, 1] - points[i, 1]
            dz = points[j, 2] - points[i, 2]
            length = math.sqrt(dx * dx + dy * dy + dz * dz)
            if length == 0.0:
                continue
            dx, dy, dz = dx / length, dy / length, dz / length
            a0, a1, a2 = normals[i, 0], normals[i, 1], normals[i, 2]
            b0, b1, b2 = normals[j, 0], normals[j, 1], normals[j, 2]
            if abs(a0 * dx + a1 * dy + a2 * dz) < abs(b0 * dx + b1 * dy + b2 * dz):
                a0, a1, a2, b0, b1, b2 = b0, b1, b2, a0, a1, a2
                dx, dy, dz = -dx, -dy, -dz
            v0, v1, v2 = a1 * dz - a2 * dy, a2 * dx - a0 * dz, a0 * dy - a1 * dx
            vn = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            if vn > 1e-12:
                v0, v1, v2 = v0 / vn, v1 / vn, v2 / vn
            w0, w1, w2 = a1 * v2 - a2 * v1, a2 * v0 - a0 * v2, a0 * v1 - a1 * v0
            alpha = v0 * b0 + v1 * b1 + v2 * b2
            phi = a0 * dx + a1 * dy + a2 * dz
            theta = math.atan2(w0 * b0 + w1 * b1 + w2 * b2, a0 * b0 + a1 * b1 + a2 * b2)
            h0 = min(max(int((alpha + 1.0) * 0.5 * bins), 0), bins - 1)
            h1 = min(max(int((phi + 1.0) * 0.5 * bins), 0), bins - 1)
            h2 = min(max(int((theta + math.pi) / (2.0 * math.pi) * bins), 0), bins - 1)
            out[i, h0] += 1.0
            out[i, bins + h1] += 1.0
            out[i, 2 * bins + h2] += 1.0
            count += 1
        if count > 0:
            for b in range(3 * bins):
                out[i, b] *= 100.0 / count
    return out


@nb.njit(cache=True, nogil=True)
def projected_pair_moments(
    src: np.ndarray,
    dst: np.ndarray,
    nrm: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    out_mu_q: np.ndarray,
    out_mu_y: np.ndarray,
    out_cross: np.ndarray,
) -> float:
    """One Kabsch solve's sums for the SVD step, in two passes and no temporaries.

    Each moving point ``src[i]`` moved by ``(R, t)`` is ``q_i``; its partner is ``y_i``, the
    projection of ``q_i`` onto the plane through ``dst[i]`` with unit normal ``nrm[i]``
    (``y_i = q_i - n_i r_i``, ``r_i = (q_i - dst_i) . n_i``). Writes the means of ``q`` and ``y``
    and the cross-covariance ``sum_i (y_i - mu_y)(q_i - mu_q)^T`` (the matrix whose SVD gives the
    rotation), and returns ``sum_i r_i^2``.

    Reference: randt.core.transforms:umeyama
    Test: tests/core/test_kernels.py::test_projected_pair_moments_match_umeyama
    """
    n = src.shape[0]
    sq0 = sq1 = sq2 = sy0 = sy1 = sy2 = ss = 0.0
    for i in range(n):
        q0, q1, q2 = _moved(src, i, R, t)
        r = (q0 - dst[i, 0]) * nrm[i, 0] + (q1 - dst[i, 1]) * nrm[i, 1] + (q2 - dst[i, 2]) * nrm[i, 2]
        sq0 += q0
        sq1 += q1
        sq2 += q2
        sy0 += q0 - nrm[i, 0] * r
        sy1 += q1 - nrm[i, 1] * r
        sy2 += q2 - nrm[i, 2] * r
        ss += r * r
    m0, m1, m2 = sq0 / n, sq1 / n, sq2 / n
    y0m, y1m, y2m = sy0 / n, sy1 / n, sy2 / n
    for a in range(3):
        for b in range(3):
            out_cross[a, b] = 0.0
    for i in range(n):
        q0, q1, q2 = _moved(src, i, R, t)
        r = (q0 - dst[i, 0]) * nrm[i, 0] + (q1 - dst[i, 1]) * nrm[i, 1] + (q2 - dst[i, 2]) * nrm[i, 2]
        a0, a1, a2 = q0 - m0, q1 - m1, q2 - m2
        b0, b1, b2 = q0 - nrm[i, 0] * r - y0m, q1 - nrm[i, 1] * r - y1m, q2 - nrm[i, 2] * r - y2m
        out_cross[0, 0] += b0 * a0
        out_cross[0, 1] += b0 * a1
        out_cross[0, 2] += b0 * a2
        out_cross[1, 0] += b1 * a0
        out_cross[1, 1] += b1 * a1
        out_cross[1, 2] += b1 * a2
        out_cross[2, 0] += b2 * a0
        out_cross[2, 1] += b2 * a1
        out_cross[2, 2] += b2 * a2
    out_mu_q[0], out_mu_q[1], out_mu_q[2] = m0, m1, m2
    out_mu_y[0], out_mu_y[1], out_mu_y[2] = y0m, y1m, y2m
    return ss


@nb.njit(cache=True, nogil=True)
def deskew_points(points: np.ndarray, s: np.ndarray, rotvec: np.ndarray, screw: np.ndarray) -> np.ndarray:
    """Each point ``p_i`` (N,3) moved by the rigid motion ``s_i`` times along the constant
    velocity ``exp([rotvec, screw])`` (an SE(3) twist: a car turning at constant speed moves
    along its arc): ``exp(s_i [rotvec, screw]) p_i = R(s_i w) p_i + V(s_i w) s_i u``, with
    Rodrigues' formula and the closed form of ``V`` per point in one pass (scipy's
    ``Rotation.from_rotvec(...).apply`` builds N rotation objects and quaternions).
    ``V(s w) s u = s u + s^2 c (w x u) + s^3 e (w x (w x u))`` with ``c = (1 - cos t) / t^2``,
    ``e = (t - sin t) / t^3``, ``t = |s w|``.

    Reference: randt.core.odometry:deskew_reference
    Test: tests/core/test_kernels.py::test_deskew_kernel_matches_the_screw_motion
    """
    n = points.shape[0]
    out = np.empty((n, 3))
    u0, u1, u2 = screw[0], screw[1], screw[2]
    # w x u and w x (w x u)
    wu0 = rotvec[1] * u2 - rotvec[2] * u1
    wu1 = rotvec[2] * u0 - rotvec[0] * u2
    wu2 = rotvec[0] * u1 - rotvec[1] * u0
    ww0 = rotvec[1] * wu2 - rotvec[2] * wu1
    ww1 = rotvec[2] * wu0 - rotvec[0] * wu2
    ww2 = rotvec[0] * wu1 - rotvec[1] * wu0
    for i in range(n):
        si = s[i]
        w0, w1, w2 = si * rotvec[0], si * rotvec[1], si * rotvec[2]
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        theta2 = w0 * w0 + w1 * w1 + w2 * w2
        # w x p and w . p
        c0, c1, c2 = w1 * z - w2 * y, w2 * x - w0 * z, w0 * y - w1 * x
        d = w0 * x + w1 * y + w2 * z
        if theta2 < 1e-8:  # the series to second order: exact to round-off below 1e-4 rad
            a, b = 1.0 - theta2 / 2.0, 1.0 - theta2 / 6.0
            c, e = 0.5 - theta2 / 24.0, 1.0 / 6.0 - theta2 / 120.0
        else:
            theta = math.sqrt(theta2)
            a = math.cos(theta)
            b = math.sin(theta) / theta
            c = (1.0 - a) / theta2
            e = (1.0 - b) / theta2
        s2c, s3e = si * si * c, si * si * si * e
        out[i, 0] = a * x + b * c0 + c * d * w0 + si * u0 + s2c * wu0 + s3e * ww0
        out[i, 1] = a * y + b * c1 + c * d * w1 + si * u1 + s2c * wu1 + s3e * ww1
        out[i, 2] = a * z + b * c2 + c * d * w2 + si * u2 + s2c * wu2 + s3e * ww2
    return out


# ------------------------------------------------------------- the map's persistent voxel table
@nb.njit(cache=True, inline="always")
def _pair_slot(tk: int, vk: int, mask: int) -> int:
    """Home slot of a (tile key, voxel key) pair (as :func:`first_per_voxel_pair` hashes it)."""
    return _slot(vk ^ (tk * 0x27D4EB2F165667C5), mask)


@nb.njit(cache=True, nogil=True)
def voxel_table_admit(
    table_t: np.ndarray,
    table_v: np.ndarray,
    table_c: np.ndarray,
    table_xyz: np.ndarray,
    used: int,
    tile_keys: np.ndarray,
    voxel_keys: np.ndarray,
    xyz32: np.ndarray,
    cap: int,
    start: int,
    accept: np.ndarray,
) -> tuple[int, int]:
    """The map's equalization policy, point by point in arrival order, against the voxels the
    map holds: a point is admitted (``accept[i] = True``) while its (tile, voxel) holds fewer
    than ``cap`` points and none equal to it (float32 x, y, z), and the voxel's count goes up.
    The table (``table_t`` tile keys, -1 empty; ``table_v`` voxel keys; ``table_c`` counts;
    ``table_xyz`` (size, cap, 3) the kept points when ``cap > 1``, else (size, 0, 3): with one
    point a voxel is full, no duplicate can be admitted) persists across inserts: the cost is
    the new points', not the map's (:meth:`randt.core.tiles.TileGrid.insert`).

    Runs from point ``start`` until the end, or until the table would pass half full; returns
    ``(next point, slots used)`` (grow it with :func:`voxel_table_grow` and call again).

    Reference: tests.core.test_tiles:reference_equalize
    Test: tests/core/test_tiles.py::test_insert_matches_a_per_point_reference
    """
    size = table_t.shape[0]
    mask = size - 1
    keep_points = table_xyz.shape[1] > 0
    for i in range(start, tile_keys.shape[0]):
        if 2 * (used + 1) > size:
            return i, used
        tk, vk = tile_keys[i], voxel_keys[i]
        h = _pair_slot(tk, vk, mask)
        while table_t[h] != -1 and (table_t[h] != tk or table_v[h] != vk):
            h = (h + 1) & mask
        if table_t[h] == -1:
            table_t[h], table_v[h], table_c[h] = tk, vk, 0
            used += 1
        c = table_c[h]
        if c >= cap:
            continue
        if keep_points:
            duplicate = False
            for j in range(c):
                if (
                    table_xyz[h, j, 0] == xyz32[i, 0]
                    and table_xyz[h, j, 1] == xyz32[i, 1]
                    and table_xyz[h, j, 2] == xyz32[i, 2]
                ):
                    duplicate = True
                    break
            if duplicate:
                continue
            table_xyz[h, c, 0], table_xyz[h, c, 1], table_xyz[h, c, 2] = xyz32[i, 0], xyz32[i, 1], xyz32[i, 2]
        table_c[h] = c + 1
        accept[i] = True
    return tile_keys.shape[0], used


@nb.njit(cache=True, nogil=True)
def voxel_table_grow(
    table_t: np.ndarray, table_v: np.ndarray, table_c: np.ndarray, table_xyz: np.ndarray, size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The entries of a :func:`voxel_table_admit` table rehashed into ``size`` slots (a power of
    two above twice the entries).

    Reference: tests.core.test_tiles:reference_equalize
    Test: tests/core/test_tiles.py::test_insert_matches_a_per_point_reference
    """
    new_t = np.full(size, -1, dtype=np.int64)
    new_v = np.empty(size, dtype=np.int64)
    new_c = np.zeros(size, dtype=table_c.dtype)
    new_xyz = np.empty((size, table_xyz.shape[1], 3), dtype=np.float32)
    mask = size - 1
    for s in range(table_t.shape[0]):
        tk = table_t[s]
        if tk == -1:
            continue
        h = _pair_slot(tk, table_v[s], mask)
        while new_t[h] != -1:
            h = (h + 1) & mask
        new_t[h], new_v[h], new_c[h] = tk, table_v[s], table_c[s]
        for j in range(table_xyz.shape[1]):
            for a in range(3):
                new_xyz[h, j, a] = table_xyz[s, j, a]
    return new_t, new_v, new_c, new_xyz


@nb.njit(cache=True, nogil=True)
def voxel_table_forget(
    table_t: np.ndarray,
    table_v: np.ndarray,
    table_c: np.ndarray,
    table_xyz: np.ndarray,
    tile_keys: np.ndarray,
    voxel_keys: np.ndarray,
) -> int:
    """Remove the (tile, voxel) pairs given (those a re-folded tile held) from a
    :func:`voxel_table_admit` table, by backward-shift deletion (linear probing needs no
    tombstones: each later entry of the probe run moves back into the gap when its home slot
    allows). Pairs not in the table are skipped. Returns how many entries were removed.

    Reference: tests.core.test_tiles:reference_equalize
    Test: tests/core/test_tiles.py::test_refold_replaces_the_tiles_equalized_as_new
    """
    mask = table_t.shape[0] - 1
    removed = 0
    for i in range(tile_keys.shape[0]):
        tk, vk = tile_keys[i], voxel_keys[i]
        h = _pair_slot(tk, vk, mask)
        while table_t[h] != -1 and (table_t[h] != tk or table_v[h] != vk):
            h = (h + 1) & mask
        if table_t[h] == -1:
            continue
        removed += 1
        gap = h
        j = h
        while True:
            j = (j + 1) & mask
            if table_t[j] == -1:
                break
            home = _pair_slot(table_t[j], table_v[j], mask)
            # the entry at j may fill the gap unless its home lies cyclically in (gap, j]
            if (j > gap and (home <= gap or home > j)) or (j < gap and home <= gap and home > j):
                table_t[gap], table_v[gap], table_c[gap] = table_t[j], table_v[j], table_c[j]
                for q in range(table_xyz.shape[1]):
                    for a in range(3):
                        table_xyz[gap, q, a] = table_xyz[j, q, a]
                gap = j
        table_t[gap] = -1
    return removed


@nb.njit(cache=True, nogil=True)
def voxel_table_near(
    table_t: np.ndarray,
    table_v: np.ndarray,
    xyz: np.ndarray,
    tile_size: float,
    voxel_size: float,
    tile_offset: int,
    reach_xy: int,
    reach_z: int,
) -> np.ndarray:
    """Whether a :func:`voxel_table_admit` table holds a voxel within ``reach_xy`` voxels (x and
    y) and ``reach_z`` (z) of each point (``xyz`` (N, 3) float64, map frame): the keys of the
    point moved by whole voxel steps, computed as :func:`tile_voxel_keys` computes a point's, so
    a step may cross into the next tile. Probes stop at the first hit. A point whose keys leave
    the 21-bit range is False.

    Reference: randt.core.tiles:TileGrid.near_numpy
    Test: tests/core/test_tiles.py::test_near_map_kernel_equals_the_numpy_reference
    """
    n = xyz.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    mask = table_t.shape[0] - 1
    big = 2.0**40
    for i in range(n):
        found = False
        for dx in range(-reach_xy, reach_xy + 1):
            x = xyz[i, 0] + dx * voxel_size
            if not abs(x / tile_size) < big:
                break
            tx = int(math.floor(x / tile_size))
            cx = int(math.floor((x - tx * tile_size) / voxel_size))
            for dy in range(-reach_xy, reach_xy + 1):
                y = xyz[i, 1] + dy * voxel_size
                if not abs(y / tile_size) < big:
                    break
                ty = int(math.floor(y / tile_size))
                cy = int(math.floor((y - ty * tile_size) / voxel_size))
                tk = ((tx + tile_offset) << 31) | (ty + tile_offset)
                for dz in range(-reach_z, reach_z + 1):
                    z = xyz[i, 2] + dz * voxel_size
                    if not abs(z / voxel_size) < big:
                        break
                    vk = _pack(cx, cy, int(math.floor(z / voxel_size)))
                    if vk < 0:
                        continue
                    h = _pair_slot(tk, vk, mask)
                    while table_t[h] != -1:
                        if table_t[h] == tk and table_v[h] == vk:
                            found = True
                            break
                        h = (h + 1) & mask
                    if found:
                        break
                if found:
                    break
            if found:
                break
        out[i] = found
    return out


@nb.njit(cache=True, nogil=True)
def model_merge(
    old_keys: np.ndarray,
    old_sums: np.ndarray,
    old_counts: np.ndarray,
    old_born: np.ndarray,
    new_keys: np.ndarray,
    new_points: np.ndarray,
    kid: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A keyframe's points summed into the keyframe model's voxels: one merge of the two
    ascending key runs (the model's, the keyframe's, each unique). Returns ``(keys, sums,
    counts, born, changed, at_old)``: every voxel before and after, keys ascending, the
    keyframe's point added where it has one (``changed``), a new voxel ``born`` at ``kid``, and
    each old voxel's row. Fresh arrays: the model's are not changed.

    Reference: randt.core.model:KeyframeModel.add_keyframe_numpy
    Test: tests/core/test_model.py::test_the_compiled_update_is_the_numpy_one
    """
    n_old, n_new = old_keys.shape[0], new_keys.shape[0]
    cap = n_old + n_new
    keys = np.empty(cap, dtype=np.int64)
    sums = np.empty((cap, 3))
    counts = np.empty(cap, dtype=np.int64)
    born = np.empty(cap, dtype=np.int64)
    changed = np.zeros(cap, dtype=np.bool_)
    at_old = np.empty(n_old, dtype=np.int64)
    i = j = n = 0
    while i < n_old or j < n_new:
        take_old = j >= n_new or (i < n_old and old_keys[i] <= new_keys[j])
        take_new = i >= n_old or (j < n_new and new_keys[j] <= old_keys[i])
        if take_old:
            keys[n] = old_keys[i]
            sums[n, 0], sums[n, 1], sums[n, 2] = old_sums[i, 0], old_sums[i, 1], old_sums[i, 2]
            counts[n], born[n] = old_counts[i], old_born[i]
            at_old[i] = n
            i += 1
        else:
            keys[n] = new_keys[j]
            sums[n, 0] = sums[n, 1] = sums[n, 2] = 0.0
            counts[n], born[n] = 0, kid
        if take_new:
            sums[n, 0] += new_points[j, 0]
            sums[n, 1] += new_points[j, 1]
            sums[n, 2] += new_points[j, 2]
            counts[n] += 1
            changed[n] = True
            j += 1
        n += 1
    return keys[:n], sums[:n], counts[:n], born[:n], changed[:n], at_old


@nb.njit(cache=True, nogil=True)
def model_evict(
    keys: np.ndarray,
    sums: np.ndarray,
    counts: np.ndarray,
    born: np.ndarray,
    changed: np.ndarray,
    evicted_keys: np.ndarray,
    evicted_points: np.ndarray,
    evicted_id: int,
) -> None:
    """The evicted keyframe's points subtracted, in place, from the voxels (keys ascending) it
    still contributes to: those not reborn after it (``born <= evicted_id``); its keys are
    ascending too, so one merge walk finds them.

    Reference: randt.core.model:KeyframeModel.add_keyframe_numpy
    Test: tests/core/test_model.py::test_the_compiled_update_is_the_numpy_one
    """
    i, n = 0, keys.shape[0]
    for j in range(evicted_keys.shape[0]):
        k = evicted_keys[j]
        while i < n and keys[i] < k:
            i += 1
        if i < n and keys[i] == k and born[i] <= evicted_id:
            sums[i, 0] -= evicted_points[j, 0]
            sums[i, 1] -= evicted_points[j, 1]
            sums[i, 2] -= evicted_points[j, 2]
            counts[i] -= 1
            changed[i] = True


@nb.njit(cache=True, nogil=True)
def model_compact(
    keys: np.ndarray,
    sums: np.ndarray,
    counts: np.ndarray,
    born: np.ndarray,
    changed: np.ndarray,
    cx: float,
    cy: float,
    radius2: float,
    finest_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The voxels that stay (a point left in them, their centroid within ``sqrt(radius2)`` of
    ``(cx, cy)`` in x-y), in order: ``(keys, sums, counts, born, centroids, fine, changed, row)``
    with ``fine`` the packed key of each centroid's voxel of ``finest_m`` (grouped as
    :func:`group_voxels` groups) and ``row`` each input voxel's row in the output (-1: gone).

    Reference: randt.core.model:KeyframeModel.add_keyframe_numpy
    Test: tests/core/test_model.py::test_the_compiled_update_is_the_numpy_one
    """
    n = keys.shape[0]
    row = np.full(n, -1, dtype=np.int64)
    centroid = np.empty((n, 3))
    m = 0
    for i in range(n):
        if counts[i] <= 0:
            continue
        x, y, z = sums[i, 0] / counts[i], sums[i, 1] / counts[i], sums[i, 2] / counts[i]
        if (x - cx) * (x - cx) + (y - cy) * (y - cy) > radius2:
            continue
        centroid[m, 0], centroid[m, 1], centroid[m, 2] = x, y, z
        row[i] = m
        m += 1
    out_keys = np.empty(m, dtype=np.int64)
    out_sums = np.empty((m, 3))
    out_counts = np.empty(m, dtype=np.int64)
    out_born = np.empty(m, dtype=np.int64)
    out_changed = np.empty(m, dtype=np.bool_)
    fine = np.empty(m, dtype=np.int64)
    inv_v = 1.0 / finest_m
    for i in range(n):
        r = row[i]
        if r < 0:
            continue
        out_keys[r], out_counts[r], out_born[r], out_changed[r] = keys[i], counts[i], born[i], changed[i]
        out_sums[r, 0], out_sums[r, 1], out_sums[r, 2] = sums[i, 0], sums[i, 1], sums[i, 2]
        fine[r] = _pack(
            int(math.floor(centroid[r, 0] * inv_v)),
            int(math.floor(centroid[r, 1] * inv_v)),
            int(math.floor(centroid[r, 2] * inv_v)),
        )
    return out_keys, out_sums, out_counts, out_born, centroid[:m].copy(), fine, out_changed, row


@nb.njit(cache=True, nogil=True)
def in_marked_cells(cells: np.ndarray, marked: np.ndarray) -> np.ndarray:
    """True where ``cells[i]`` is one of ``marked`` (packed keys, repeats allowed): a hashed set.

    Reference: numpy:isin
    Test: tests/core/test_kernels.py::test_in_marked_cells_matches_isin
    """
    size = 16
    while size < 2 * marked.shape[0]:
        size <<= 1
    mask = size - 1
    table = np.full(size, -1, dtype=np.int64)
    for j in range(marked.shape[0]):
        k = marked[j]
        h = _slot(k, mask)
        while table[h] != -1 and table[h] != k:
            h = (h + 1) & mask
        table[h] = k
    out = np.zeros(cells.shape[0], dtype=np.bool_)
    for i in range(cells.shape[0]):
        k = cells[i]
        h = _slot(k, mask)
        while table[h] != -1:
            if table[h] == k:
                out[i] = True
                break
            h = (h + 1) & mask
    return out


@nb.njit(cache=True, nogil=True)
def group_int_keys(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows grouped by key, in one hashed pass and a counting sort: ``(order, unique keys,
    starts)`` with group ``g``'s rows ``order[starts[g]:starts[g + 1]]`` in their input order and
    groups in first-seen order. Keys must be >= 0 (the tile keys of :mod:`randt.core.tiles`): no
    sort, where a stable ``np.argsort`` of a sweep's tile keys would be one.

    Reference: numpy:unique
    Test: tests/core/test_kernels.py::test_group_int_keys_matches_a_stable_sort
    """
    n = keys.shape[0]
    size = 16
    while size < 2 * n:
        size <<= 1
    mask = size - 1
    table_k = np.full(size, -1, dtype=np.int64)
    table_g = np.empty(size, dtype=np.int64)
    group = np.empty(n, dtype=np.int64)
    uniq = np.empty(n, dtype=np.int64)
    counts = np.zeros(n + 1, dtype=np.int64)
    m = 0
    for i in range(n):
        k = keys[i]
        h = _slot(k, mask)
        while table_k[h] != -1 and table_k[h] != k:
            h = (h + 1) & mask
        if table_k[h] == -1:
            table_k[h], table_g[h] = k, m
            uniq[m] = k
            m += 1
        g = table_g[h]
        group[i] = g
        counts[g + 1] += 1
    starts = np.cumsum(counts[: m + 1])
    fill = starts[:m].copy()
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        g = group[i]
        order[fill[g]] = i
        fill[g] += 1
    return order, uniq[:m].copy(), starts
