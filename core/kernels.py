"""Compiled kernels for the hot loops the numpy formulation cannot make cheap (numba).

Why a compiled kernel here (the standards allow one when justified): the NDT score, gradient and
Hessian are sums over (point, neighbour voxel) pairs. In numpy every pair becomes a row of several
(P,3), (P,3,3) and (P,6) temporaries: about 15 ms per evaluation for a KITTI sweep's 7k points and
7 neighbours, 20-40 evaluations per registration, which made RANDT 3-5x slower than small_gicp.
Fused into one pass over the points with no temporaries, the same sums take 1-3 ms. Voxel
downsampling stays numpy: ``np.unique`` already hashes, and a compiled hash pass measured no faster.

The NDT kernels have numpy twins that stay the reference: ``core.ndt`` keeps the vectorized
formulation (``ndt_derivatives_numpy`` and friends) and ``tests/core/test_kernels.py`` checks the
kernels against it to round-off on real scans. The kernels release the GIL (``nogil``), so the
service's per-session worker threads run them on several cores at once. Kernels are compiled on
first use and cached on disk (numba ``cache=True``), so a process pays the compile time (a few
seconds) once per machine.

Voxel keys are packed exactly as :func:`core.voxel.pack_keys` packs them (21 bits per axis); a map's
keys go into an open-addressing hash table (:func:`build_hash`, built once per map), so a lookup
is one or two probes instead of the binary search ``np.searchsorted`` does.
"""

# ruff: noqa: RUF046  (int(math.floor(x)) keeps the cell index an explicit int64 inside numba)
from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = ["best_voxel", "build_hash", "ndt_accumulate", "ndt_scores"]

_BITS = 21
_OFFSET = 1 << (_BITS - 1)
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
    """Open-addressing table (keys, indices) over ``keys``, at most half full; empty slots hold -1."""
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
            return table_idx[h]
        if tk == -1:
            return -1
        h = (h + 1) & mask


@nb.njit(cache=True, inline="always")
def _moved_and_cell(
    points: np.ndarray, i: int, R: np.ndarray, t: np.ndarray, inv_v: float
) -> tuple[float, float, float, int, int, int]:
    """Point ``i`` moved by ``(R, t)`` and the integer cell it falls in."""
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    q0 = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
    q1 = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
    q2 = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
    return q0, q1, q2, int(math.floor(q0 * inv_v)), int(math.floor(q1 * inv_v)), int(math.floor(q2 * inv_v))


@nb.njit(cache=True, inline="always")
def _mahalanobis2(inv_cov: np.ndarray, v: int, x0: float, x1: float, x2: float) -> float:
    """Squared Mahalanobis distance ``x^T Sigma_v^-1 x``."""
    return (
        x0 * (inv_cov[v, 0, 0] * x0 + inv_cov[v, 0, 1] * x1 + inv_cov[v, 0, 2] * x2)
        + x1 * (inv_cov[v, 1, 0] * x0 + inv_cov[v, 1, 1] * x1 + inv_cov[v, 1, 2] * x2)
        + x2 * (inv_cov[v, 2, 0] * x0 + inv_cov[v, 2, 1] * x1 + inv_cov[v, 2, 2] * x2)
    )


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
) -> tuple[float, int]:
    """NDT cost (and, with ``derivatives``, gradient and Hessians) of ``R p + t`` in one pass.

    The formulas are those of :mod:`core.ndt` (Magnusson eq. 6.12-6.13 with the left
    perturbation about ``pivot``): per pair, ``x = q - mu``, ``a = Sigma^-1 x``, ``m = x.a``
    (pairs with ``m >= m_max`` pruned), ``e = exp(-d2 m / 2)``, cost ``d1 e``, weight
    ``w = -d1 d2 e``, ``J = [I, -[q - pivot]x]``; gradient ``w J^T a``; Hessian
    ``w (J^T Sigma^-1 J - d2 (J^T a)(J^T a)^T + S)``.
    ``out_grad`` (6,), ``out_hess`` and ``out_gn`` (6,6) are overwritten. Returns (cost, pairs).
    """
    inv_v = 1.0 / voxel_size
    cost = 0.0
    n_pairs = 0
    g = np.zeros(6)
    H = np.zeros((6, 6))
    G = np.zeros((6, 6))
    ja = np.zeros(6)
    Jr = np.zeros((3, 3))
    MJ = np.zeros((3, 3))
    n_off = offsets.shape[0]
    for i in range(points.shape[0]):
        q0, q1, q2, cx, cy, cz = _moved_and_cell(points, i, R, t, inv_v)
        for k in range(n_off):
            v = _find(table_key, table_idx, _pack(cx + offsets[k, 0], cy + offsets[k, 1], cz + offsets[k, 2]))
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
            cost += d1 * e
            n_pairs += 1
            if not derivatives:
                continue
            w = -d1 * d2 * e
            # J^T a = (a, q x a)
            ja[0], ja[1], ja[2] = a0, a1, a2
            # Rotation about the pivot: the lever arm is q - pivot.
            r0, r1, r2 = q0 - pivot[0], q1 - pivot[1], q2 - pivot[2]
            ja[3] = r1 * a2 - r2 * a1
            ja[4] = r2 * a0 - r0 * a2
            ja[5] = r0 * a1 - r1 * a0
            for r in range(6):
                g[r] += w * ja[r]
            # Rotation columns of J: e_k x q, i.e. Jr = -[q]x.
            Jr[0, 0], Jr[0, 1], Jr[0, 2] = 0.0, r2, -r1
            Jr[1, 0], Jr[1, 1], Jr[1, 2] = -r2, 0.0, r0
            Jr[2, 0], Jr[2, 1], Jr[2, 2] = r1, -r0, 0.0
            for r in range(3):
                for c in range(3):
                    MJ[r, c] = (
                        inv_cov[v, r, 0] * Jr[0, c]
                        + inv_cov[v, r, 1] * Jr[1, c]
                        + inv_cov[v, r, 2] * Jr[2, c]
                    )
            wd2 = w * d2
            aq = a0 * r0 + a1 * r1 + a2 * r2
            aa = (a0, a1, a2)
            qq = (r0, r1, r2)
            for r in range(3):
                for c in range(r, 3):
                    # translation-translation: Sigma^-1
                    s = w * inv_cov[v, r, c]
                    G[r, c] += s
                    H[r, c] += s - wd2 * ja[r] * ja[c]
                    # rotation-rotation: Jr^T Sigma^-1 Jr + S(a, q)
                    jsj = Jr[0, r] * MJ[0, c] + Jr[1, r] * MJ[1, c] + Jr[2, r] * MJ[2, c]
                    s_rr = 0.5 * (aa[r] * qq[c] + aa[c] * qq[r])
                    if r == c:
                        s_rr -= aq
                    G[3 + r, 3 + c] += w * jsj
                    H[3 + r, 3 + c] += w * (jsj + s_rr) - wd2 * ja[3 + r] * ja[3 + c]
                for c in range(3):
                    # translation-rotation: Sigma^-1 Jr
                    s = w * MJ[r, c]
                    G[r, 3 + c] += s
                    H[r, 3 + c] += s - wd2 * ja[r] * ja[3 + c]
    if derivatives:
        # Only the upper triangle was accumulated (the 3x3 diagonal blocks from their diagonal
        # up, the translation-rotation block whole): mirror it.
        for r in range(6):
            out_grad[r] = g[r]
            for c in range(r, 6):
                out_hess[r, c] = H[r, c]
                out_hess[c, r] = H[r, c]
                out_gn[r, c] = G[r, c]
                out_gn[c, r] = G[r, c]
    return cost, n_pairs


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
) -> None:
    """Per-point Autoware scores (see ``core.ndt.ndt_point_scores``), written into the outputs."""
    inv_v = 1.0 / voxel_size
    for i in range(points.shape[0]):
        q0, q1, q2, cx, cy, cz = _moved_and_cell(points, i, R, t, inv_v)
        s_sum, s_max, b_m = 0.0, 0.0, np.inf
        for k in range(offsets.shape[0]):
            v = _find(table_key, table_idx, _pack(cx + offsets[k, 0], cy + offsets[k, 1], cz + offsets[k, 2]))
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
    distance (``out_voxel``, -1 when none is near) and that distance (``out_m``, inf when none)."""
    inv_v = 1.0 / voxel_size
    for i in range(points.shape[0]):
        q0, q1, q2, cx, cy, cz = _moved_and_cell(points, i, R, t, inv_v)
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
