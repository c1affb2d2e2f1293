"""Place recognition: a Scan Context descriptor per keyframe and an index that proposes revisits.

:func:`scan_context` (Kim & Kim, IROS 2018: a polar grid of each bin's highest point around the
sensor), :func:`query_descriptors` (the sweep also as seen ahead and behind), :class:`PlaceIndex`
(ring keys in a KD-tree, then the exact distance over every column shift) and
:func:`scan_context_distance`. A candidate is only a proposal, which
:mod:`randt.core.global_registration` verifies (:mod:`randt.core.fleet_map`). How it works and how
well: docs/mapping.md, "One map from many sessions", step 2.

Yaw convention: a candidate's ``yaw_deg`` rotates the query's sensor frame onto the candidate's,
``R_candidate_query = Rz(yaw)``, as in ``p_candidate = T p_query`` (``p_i = T p_j`` for the
KITTI revisit pairs of :mod:`randt.core.shared_data`, with ``i`` the stored sweep and ``j`` the query).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Collection, Hashable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field, FiniteFloat
from scipy.spatial import cKDTree

from randt.core.errors import ConflictError, FormatError, InvalidCloudError, InvalidRequestError

__all__ = [
    "PlaceCandidate",
    "PlaceIndex",
    "PlaceSettings",
    "query_descriptors",
    "ring_key",
    "scan_context",
    "scan_context_distance",
]

#: Every stored descriptor beyond the KD-tree's rows is searched by brute force; the tree is
#: rebuilt once more than this many (or a quarter of the tree's rows) are waiting.
_MIN_TAIL = 256


class PlaceSettings(BaseModel):
    """Scan Context's grid and the index's search (module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    rings: int = Field(default=20, ge=2, le=1000, description="radial bins out to max_range_m")
    sectors: int = Field(default=60, ge=4, le=3600, description="angular bins (60: 6 deg each)")
    max_range_m: float = Field(default=80.0, gt=0, description="points farther (horizontally) are ignored")
    ground_offset_m: float = Field(
        default=2.0,
        ge=0,
        description="a bin holds its highest point's z + this (about the LiDAR's height above the "
        "ground, so the ground is near 0); points lower still count as 0",
    )
    query_shifts_m: tuple[FiniteFloat, ...] = Field(
        default=(-4.0, 4.0),
        description="a query is also described from its sweep as seen this far ahead of and behind "
        "the sensor (along its x axis), and the best of these distances counts: a revisit is "
        "offset along the road by up to half the keyframe spacing, which the polar grid does not "
        "forgive (on the KITTI 00 revisits recall@1 goes from 16 to 21 of 23); () for plain Scan "
        "Context",
    )
    ring_candidates: int = Field(
        default=10, ge=1, description="nearest ring keys per query descriptor compared exactly"
    )
    max_distance: float = Field(
        default=0.25,
        gt=0,
        le=2,
        description="candidates farther (Scan Context distance, 0 same place, 1 unrelated) are not "
        "proposed. 0.25 sits in a gap of the KITTI 00 revisits' true best distances (none between "
        "0.224 and 0.281): 19 of 23 revisits proposed, precision 0.95 (one look-alike street at "
        "0.200, which verification rejects); the unrevisited sweeps' best is 0.385 or more "
        "(tests/core/test_place.py)",
    )


@dataclass(frozen=True)
class PlaceCandidate:
    """A proposed revisit of a stored keyframe.

    Attributes
    ----------
    key:
        The keyframe's key, as given to :meth:`PlaceIndex.add`.
    distance:
        Scan Context distance, 0 (same grid) to 1 (no column alike); 2 when no column pair is
        non-empty in both.
    yaw_deg:
        The yaw rotating the query's sensor frame onto the candidate's (``R_candidate_query =
        Rz(yaw)``), in (-180, 180], to about a degree; a straight street can match its own mirror
        180 deg off. An initial guess for verification, no more.
    """

    key: Hashable
    distance: float
    yaw_deg: float


def scan_context(points_xyz: npt.ArrayLike, settings: PlaceSettings | None = None) -> np.ndarray:
    """The Scan Context of a sweep given in its sensor frame.

    Parameters
    ----------
    points_xyz:
        (N, 3) or (N, >=4) points in the sensor frame (extra columns are ignored); rows with a
        non-finite coordinate are dropped.
    settings:
        The grid (``rings``, ``sectors``, ``max_range_m``, ``ground_offset_m``).

    Returns
    -------
    np.ndarray
        (rings, sectors) float64: bin ``[r, s]`` is the highest ``z + ground_offset_m`` (at least
        0) of the points at horizontal range ``[r, r + 1) * max_range_m / rings`` and azimuth
        ``[s, s + 1) * 360 / sectors`` degrees from -180 (the sensor's -x axis), counterclockwise.

    Raises
    ------
    InvalidCloudError
        Not an (N, 3) numeric array, empty, no finite point, or no point within ``max_range_m``.
    """
    s = settings or PlaceSettings()
    return _scan_context(_sanitize(points_xyz), s)


def query_descriptors(points_xyz: npt.ArrayLike, settings: PlaceSettings | None = None) -> np.ndarray:
    """The descriptors :meth:`PlaceIndex.query` compares a sweep by.

    Returns
    -------
    np.ndarray
        (1 + len(query_shifts_m), rings, sectors): first :func:`scan_context` of the sweep (the
        one to :meth:`PlaceIndex.add`), then that of the sweep as seen from each point
        ``(dx, 0, 0)`` of ``query_shifts_m`` in its sensor frame (the cloud moved by ``-dx``).

    Raises
    ------
    InvalidCloudError
        As :func:`scan_context`.
    """
    s = settings or PlaceSettings()
    xyz = _sanitize(points_xyz)
    out = [_scan_context(xyz, s)]
    out += [_scan_context(xyz, s, view_x_m=dx, allow_empty=True) for dx in s.query_shifts_m]
    return np.stack(out)


def ring_key(descriptor: np.ndarray) -> np.ndarray:
    """The ring key of a (rings, sectors) descriptor, or of each of a (..., rings, sectors) stack:
    the mean bin height per ring (m), which a yaw (a column roll) does not change.

    The mean ranks better than the occupied fraction: on the KITTI 00 revisit set the first true
    match is among the 3 nearest ring keys for 21 of 23 queries with the mean, 15 with the fraction.
    """
    return np.asarray(np.asarray(descriptor, dtype=np.float64).mean(axis=-1))


def scan_context_distance(query: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scan Context distances of ``query`` to each candidate, minimized over the column shifts.

    Parameters
    ----------
    query:
        (R, S) descriptor.
    candidates:
        (K, R, S) descriptors.

    Returns
    -------
    distance : np.ndarray
        (K,) ``min over k of 1 - mean_j cos(query[:, j], roll(candidate, k)[:, j])``, the mean
        over the columns ``j`` non-empty in both; 2.0 when no shift has such a column.
    yaw_deg : np.ndarray
        (K,) the yaw rotating the query's sensor frame onto the candidate's: ``-k * 360 / S`` at
        the best shift ``k``, refined between the neighbouring shifts by a parabola through the
        three distances, in (-180, 180].

    Raises
    ------
    InvalidRequestError
        Shapes that do not fit together.

    Notes
    -----
    All shifts at once: with unit columns, ``G[c, j, l] = <q_j, c_l>`` (one batched GEMM) holds
    every column pair's cosine, and shift ``k`` sums its wrapped diagonal ``l = j - k``. Cost per
    candidate: ``R * S**2`` multiply-adds (72k for 20 x 60).
    """
    q = np.asarray(query, dtype=np.float64)
    c = np.asarray(candidates, dtype=np.float64)
    if q.ndim != 2 or c.ndim != 3 or c.shape[1:] != q.shape:
        raise InvalidRequestError(
            f"scan context distance: a (R, S) query and (K, R, S) candidates are needed, got "
            f"{q.shape} and {c.shape}"
        )
    n_sectors = q.shape[1]
    qn, q_mask = _unit_columns(q)  # (R, S), (S,)
    cn, c_mask = _unit_columns(c)  # (K, R, S), (K, S)
    gram = np.matmul(qn.T, cn)  # (K, S, S): one batched GEMM
    j = np.arange(n_sectors)
    diag = (j[None, :] - j[:, None]) % n_sectors  # (shift k, j) -> l = j - k
    cos_sum = gram[:, j[None, :], diag].sum(axis=2)  # (K, shifts)
    n_both = (c_mask[:, diag] & q_mask[None, None, :]).sum(axis=2)  # (K, shifts)
    dist = np.where(n_both > 0, 1.0 - cos_sum / np.maximum(n_both, 1), 2.0)
    rows = np.arange(dist.shape[0])
    best = np.argmin(dist, axis=1)
    d0 = dist[rows, best]
    dm, dp = dist[rows, (best - 1) % n_sectors], dist[rows, (best + 1) % n_sectors]
    curvature = dm - 2.0 * d0 + dp
    frac = np.where(curvature > 1e-12, 0.5 * (dm - dp) / np.where(curvature > 1e-12, curvature, 1.0), 0.0)
    shift = best + np.clip(frac, -0.5, 0.5)
    yaw = -shift * (360.0 / n_sectors)
    return d0, _wrap_deg(yaw)


class PlaceIndex:
    """Descriptors by key; :meth:`query` proposes the stored places nearest a query.

    The ring keys live in a KD-tree (``scipy.spatial.cKDTree``) over the first rows and in a
    brute-force tail for rows added since; the tree is rebuilt, at a query, once the tail exceeds
    256 rows or a quarter of the tree. A rebuild costs O(N log N), so an add costs O(log N)
    amortized and a query O(log N + tail) for the ring keys, plus the exact distance of
    ``ring_candidates`` descriptors per query descriptor.
    """

    def __init__(self, settings: PlaceSettings | None = None) -> None:
        self.settings = settings or PlaceSettings()
        shape = (self.settings.rings, self.settings.sectors)
        self._keys: list[Hashable] = []
        self._rows: dict[Hashable, int] = {}
        self._descriptors = np.empty((0, *shape), dtype=np.float32)
        self._ring_keys = np.empty((0, shape[0]))
        self._tree: cKDTree | None = None
        self._n_tree = 0

    def __len__(self) -> int:
        return len(self._keys)

    def __contains__(self, key: object) -> bool:
        try:
            return key in self._rows
        except TypeError:
            return False

    def keys(self) -> list[Hashable]:
        """The stored keys, in the order added."""
        return list(self._keys)

    def descriptor(self, key: Hashable) -> np.ndarray:
        """The descriptor stored as ``key`` (a copy); :class:`KeyError` when none is."""
        return np.array(self._descriptors[self._rows[key]])

    def add(self, key: Hashable, descriptor: npt.ArrayLike) -> None:
        """Store ``descriptor`` (:func:`scan_context` with this index's settings) as ``key``.

        Raises
        ------
        InvalidRequestError
            ``key`` is not hashable, or the descriptor is not a finite, non-negative
            (rings, sectors) array.
        ConflictError
            ``key`` is already stored.
        """
        try:
            stored = key in self._rows
        except TypeError:
            raise InvalidRequestError(
                f"place index: a key must be hashable, got {type(key).__name__}"
            ) from None
        if stored:
            raise ConflictError(f"place index: key {key!r} is already stored")
        d = self._check(descriptor, f"descriptor of {key!r}", stack=False)
        n = len(self._keys)
        if n == self._descriptors.shape[0]:  # grow by doubling: O(1) amortized per add
            cap = max(64, 2 * n)
            self._descriptors = np.resize(self._descriptors, (cap, *d.shape))
            self._ring_keys = np.resize(self._ring_keys, (cap, d.shape[0]))
        self._descriptors[n] = d
        self._ring_keys[n] = ring_key(self._descriptors[n])  # of the stored float32 values
        self._rows[key] = n
        self._keys.append(key)

    def query(
        self,
        descriptor: npt.ArrayLike,
        *,
        k: int = 1,
        exclude: Collection[Hashable] | Callable[[Hashable], bool] | None = None,
        max_distance: float | None = None,
    ) -> list[PlaceCandidate]:
        """The stored places nearest ``descriptor``.

        Parameters
        ----------
        descriptor:
            (rings, sectors) from :func:`scan_context`, or (n, rings, sectors) from
            :func:`query_descriptors` (the best distance of the n counts).
        k:
            At most this many candidates (of the ``ring_candidates`` per query descriptor that
            are compared exactly).
        exclude:
            Keys never proposed (the query's own pass, say): a collection, or a predicate that
            is true for a key to exclude.
        max_distance:
            Candidates farther are not proposed (default: the settings').

        Returns
        -------
        list[PlaceCandidate]
            Nearest first; empty when nothing stored is within ``max_distance``.

        Raises
        ------
        InvalidRequestError
            A descriptor not finite, non-negative and (rings, sectors) or (n, rings, sectors), or
            ``k < 1``.
        """
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
            raise InvalidRequestError(f"place index: k must be an integer >= 1, got {k!r}")
        queries = self._check(descriptor, "query descriptor", stack=True)
        limit = self.settings.max_distance if max_distance is None else float(max_distance)
        if not self._keys:
            return []
        excluded = _exclusion(exclude)
        self._refresh_tree()
        rows = np.unique(np.concatenate([self._nearest(rk, excluded) for rk in ring_key(queries)]))
        if rows.size == 0:
            return []
        cands = self._descriptors[rows]
        per_query = [scan_context_distance(q, cands) for q in queries]
        dist = np.stack([d for d, _ in per_query])  # (n, K)
        yaw = np.stack([y for _, y in per_query])
        best = np.argmin(dist, axis=0)
        cols = np.arange(rows.size)
        out = [
            PlaceCandidate(self._keys[int(r)], float(d), float(y))
            for r, d, y in zip(rows, dist[best, cols], yaw[best, cols], strict=True)
            if d <= limit
        ]
        out.sort(key=lambda c: c.distance)
        return out[:k]

    def state_dict(self) -> dict[str, np.ndarray]:
        """Everything stored, as plain arrays (``np.savez`` them; no pickling needed).

        Returns
        -------
        dict[str, np.ndarray]
            ``keys`` (N,) str: each key as JSON (tuples as lists); ``descriptors`` (N, rings,
            sectors) float32; ``grid`` (4,): rings, sectors, max_range_m, ground_offset_m.

        Raises
        ------
        InvalidRequestError
            A key that is not an int, str, float, bool, None or a tuple of them.
        """
        keys = []
        for key in self._keys:
            try:
                keys.append(json.dumps(key, default=_json_scalar))
            except (TypeError, ValueError):
                raise InvalidRequestError(
                    f"place index: key {key!r} cannot be saved: keys must be int, str, float, bool, "
                    "None or tuples of them"
                ) from None
        n = len(self._keys)
        return {
            "keys": np.array(keys, dtype=np.str_).reshape(n),
            "descriptors": self._descriptors[:n].copy(),
            "grid": self._grid(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Replace the contents with a :meth:`state_dict` (the same grid settings are required).

        Raises
        ------
        FormatError
            An array missing or of the wrong shape, a key that is not JSON, a repeated key, or a
            state saved with another grid (rings, sectors, max_range_m, ground_offset_m).
        """
        missing = [name for name in ("keys", "descriptors", "grid") if name not in state]
        if missing:
            raise FormatError(f"place index state: missing {', '.join(missing)}")
        grid = np.asarray(state["grid"], dtype=np.float64)
        if grid.shape != (4,) or not np.array_equal(grid, self._grid()):
            raise FormatError(
                f"place index state: saved with grid (rings, sectors, max_range_m, ground_offset_m) "
                f"{grid.tolist()}, this index has {self._grid().tolist()}"
            )
        raw = np.asarray(state["keys"])
        desc = np.asarray(state["descriptors"], dtype=np.float32)
        shape = (self.settings.rings, self.settings.sectors)
        if raw.ndim != 1 or desc.shape != (raw.shape[0], *shape):
            raise FormatError(
                f"place index state: {raw.shape} keys and descriptors of shape {desc.shape} "
                f"(expected (N,) and (N, {shape[0]}, {shape[1]}))"
            )
        if not (np.all(np.isfinite(desc)) and np.all(desc >= 0)):
            raise FormatError("place index state: descriptors must be finite and >= 0")
        try:
            keys = [_tuples(json.loads(str(s))) for s in raw]
        except (json.JSONDecodeError, TypeError):
            raise FormatError("place index state: a key is not valid JSON") from None
        rows = {key: i for i, key in enumerate(keys)}
        if len(rows) != len(keys):
            raise FormatError("place index state: a key is repeated")
        self._keys, self._rows = keys, rows
        self._descriptors = desc.copy()
        self._ring_keys = ring_key(desc).reshape(len(keys), shape[0])
        self._tree, self._n_tree = None, 0

    # ---------------------------------------------------------------- internals
    def _grid(self) -> np.ndarray:
        s = self.settings
        return np.array([s.rings, s.sectors, s.max_range_m, s.ground_offset_m], dtype=np.float64)

    def _check(self, descriptor: npt.ArrayLike, what: str, *, stack: bool) -> np.ndarray:
        """A finite, non-negative (R, S) descriptor, or an (n, R, S) stack when ``stack``."""
        shape = (self.settings.rings, self.settings.sectors)
        try:
            d = np.asarray(descriptor, dtype=np.float64)
        except (TypeError, ValueError):
            raise InvalidRequestError(f"place index: {what} is not a numeric array") from None
        if stack and d.ndim == 2:
            d = d[None]
        if d.shape[-2:] != shape or d.ndim != (3 if stack else 2) or d.size == 0:
            want = f"{shape} or (n, {shape[0]}, {shape[1]})" if stack else f"{shape}"
            raise InvalidRequestError(
                f"place index: {what} has shape {d.shape}, expected {want} (rings, sectors of the "
                "index's settings)"
            )
        if not np.all(np.isfinite(d)) or np.any(d < 0):
            raise InvalidRequestError(f"place index: {what} must be finite and >= 0 everywhere")
        return d

    def _refresh_tree(self) -> None:
        n = len(self._keys)
        if n - self._n_tree > max(_MIN_TAIL, self._n_tree // 4):
            self._tree = cKDTree(self._ring_keys[:n])
            self._n_tree = n

    def _nearest(self, rk: np.ndarray, excluded: Callable[[Hashable], bool]) -> np.ndarray:
        """Rows of the ``ring_candidates`` nearest ring keys to ``rk`` that are not excluded.

        The tree is asked for a few more than wanted, four times more while exclusions eat them;
        the tail's rows are merged in up to the farthest distance the tree has answered.
        """
        n, want = len(self._keys), self.settings.ring_candidates
        tail = np.arange(self._n_tree, n)
        tail_d = np.linalg.norm(self._ring_keys[self._n_tree : n] - rk, axis=1)
        ask = min(self._n_tree, 2 * want)
        while True:
            if ask > 0 and self._tree is not None:
                d, i = self._tree.query(rk, k=ask)
                d, i = np.atleast_1d(d), np.atleast_1d(i)
            else:
                d, i = np.empty(0), np.empty(0, dtype=np.intp)
            exhausted = ask >= self._n_tree
            bound = np.inf if exhausted else float(d[-1])  # beyond it, unasked tree rows may be nearer
            all_d, all_i = np.concatenate([d, tail_d]), np.concatenate([i, tail])
            kept: list[int] = []
            for j in np.argsort(all_d, kind="stable"):
                if all_d[j] > bound:
                    break
                if not excluded(self._keys[int(all_i[j])]):
                    kept.append(int(all_i[j]))
                    if len(kept) == want:
                        return np.array(kept, dtype=np.intp)
            if exhausted:
                return np.array(kept, dtype=np.intp)
            ask = min(self._n_tree, 4 * ask)


def _sanitize(points_xyz: npt.ArrayLike) -> np.ndarray:
    """Finite (N, 3) float64 points, or :class:`InvalidCloudError` naming what is wrong."""
    try:
        arr = np.asarray(points_xyz)
    except (TypeError, ValueError):
        raise InvalidCloudError("scan context: points are not an array") from None
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise InvalidCloudError(f"scan context: points must be an (N, 3) array, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise InvalidCloudError(f"scan context: points must be real numbers, got dtype {arr.dtype}")
    if arr.shape[0] == 0:
        raise InvalidCloudError("scan context: the cloud is empty")
    xyz = np.ascontiguousarray(arr[:, :3], dtype=np.float64)
    if not np.isfinite(np.add.reduce(xyz, axis=None)):  # a finite sum proves every point finite
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
        if xyz.shape[0] == 0:
            raise InvalidCloudError(f"scan context: none of the {arr.shape[0]} points is finite (NaN or inf)")
    return xyz


def _scan_context(
    xyz: np.ndarray, s: PlaceSettings, *, view_x_m: float = 0.0, allow_empty: bool = False
) -> np.ndarray:
    """:func:`scan_context` of finite (N, 3) points as seen from ``(view_x_m, 0, 0)``: one
    scatter-max, no loop over points."""
    n_bins = s.rings * s.sectors
    x, y = (xyz[:, 0] - view_x_m if view_x_m else xyz[:, 0]), xyz[:, 1]
    r = np.hypot(x, y)
    ring = (r * (s.rings / s.max_range_m)).astype(np.int64)
    sector = ((np.arctan2(y, x) + np.pi) * (s.sectors / (2 * np.pi))).astype(np.int64)
    np.minimum(sector, s.sectors - 1, out=sector)  # arctan2 = pi lands on the last sector
    flat = ring * s.sectors + sector
    flat[ring >= s.rings] = n_bins  # out of range: a spare bin, dropped below
    if not allow_empty and not np.any(flat < n_bins):
        raise InvalidCloudError(
            f"scan context: none of the {xyz.shape[0]} points lies within max_range_m = "
            f"{s.max_range_m:g} m of the sensor (horizontally)"
        )
    desc = np.zeros(n_bins + 1)
    np.maximum.at(desc, flat, xyz[:, 2] + s.ground_offset_m)  # bins start at 0: lower points add 0
    return desc[:n_bins].reshape(s.rings, s.sectors)


def _unit_columns(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns (axis -2 summed) scaled to unit length, and which columns are non-empty."""
    norm = np.linalg.norm(d, axis=-2)
    mask = norm > 0
    return d / np.where(mask, norm, 1.0)[..., None, :], mask


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    """Angles in (-180, 180]."""
    return np.asarray(180.0 - (180.0 - a) % 360.0)


def _exclusion(
    exclude: Collection[Hashable] | Callable[[Hashable], bool] | None,
) -> Callable[[Hashable], bool]:
    if exclude is None:
        return lambda key: False
    if callable(exclude):
        return exclude
    if isinstance(exclude, Collection):
        return lambda key: key in exclude
    raise InvalidRequestError(
        f"place index: exclude must be a collection of keys or a predicate, got {type(exclude).__name__}"
    )


def _json_scalar(o: object) -> object:
    """numpy scalars as Python ones (``np.int64(3)`` -> ``3``) for ``json.dumps``."""
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(type(o).__name__)


def _tuples(o: object) -> Hashable:
    """JSON lists back to the tuples they were saved from."""
    if isinstance(o, list):
        return tuple(_tuples(v) for v in o)
    if isinstance(o, dict):
        raise TypeError("a key cannot be a mapping")
    return o
