"""Place recognition: a Scan Context descriptor per keyframe and an index to query it.

The descriptor (Kim & Kim, IROS 2018) of a sweep in its sensor frame is a polar grid of ``rings``
x ``sectors`` bins out to ``max_range_m``; each bin holds the highest point in it, measured from
``ground_offset_m`` below the sensor (0: empty). A place seen again from another heading gives the
same grid with its columns rolled, so two descriptors are compared at every column shift:

    distance(q, c) = min over shifts k of  1 - mean_j cos(q[:, j], roll(c, k)[:, j])

over the columns non-empty in both, and the best shift is the yaw between the two sensors. The
index keeps each descriptor's ring key (the fraction of occupied bins per ring, which no rotation
changes) in a KD-tree: a query takes the ``ring_candidates`` nearest ring keys, then the exact
distance of those. A candidate is proposed when its distance is below ``max_distance``; the
geometric verification (core.global_registration) decides.
"""

from __future__ import annotations

from collections.abc import Collection, Hashable
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree

from core.errors import InvalidCloudError, InvalidRequestError

__all__ = ["PlaceCandidate", "PlaceIndex", "PlaceSettings", "scan_context", "scan_context_distance"]


class PlaceSettings(BaseModel):
    """Scan Context's grid and the index's search."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    rings: int = Field(default=20, ge=2)
    sectors: int = Field(default=60, ge=4)
    max_range_m: float = Field(default=80.0, gt=0)
    ground_offset_m: float = Field(
        default=2.0, ge=0, description="heights are measured from this far below the sensor"
    )
    ring_candidates: int = Field(default=10, ge=1, description="ring-key neighbours compared exactly")
    max_distance: float = Field(
        default=0.3, gt=0, le=2, description="candidates farther (Scan Context distance) are not proposed"
    )


@dataclass(frozen=True)
class PlaceCandidate:
    """A proposed revisit: the stored ``key``, its Scan Context distance, and the yaw (deg) that
    rotates the query's sensor frame onto the candidate's (``R_candidate_query = Rz(yaw)``)."""

    key: Hashable
    distance: float
    yaw_deg: float


def scan_context(points_sensor: np.ndarray, settings: PlaceSettings | None = None) -> np.ndarray:
    """The (rings, sectors) Scan Context of a sweep given in its sensor frame (module docstring)."""
    s = settings or PlaceSettings()
    p = np.asarray(points_sensor, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] < 3:
        raise InvalidCloudError(f"scan context: points must be (N, 3), got {p.shape}")
    p = p[np.all(np.isfinite(p[:, :3]), axis=1)]
    r = np.hypot(p[:, 0], p[:, 1])
    keep = (r < s.max_range_m) & (r > 0)
    if not keep.any():
        raise InvalidCloudError(f"scan context: no finite point within {s.max_range_m} m of the sensor")
    p, r = p[keep], r[keep]
    ring = np.minimum((r * (s.rings / s.max_range_m)).astype(np.int64), s.rings - 1)
    sector = ((np.arctan2(p[:, 1], p[:, 0]) + np.pi) * (s.sectors / (2 * np.pi))).astype(np.int64)
    sector = np.minimum(sector, s.sectors - 1)
    height = np.maximum(p[:, 2] + s.ground_offset_m, 0.0)
    desc = np.zeros(s.rings * s.sectors)
    np.maximum.at(desc, ring * s.sectors + sector, height)
    return desc.reshape(s.rings, s.sectors)


def _ring_key(desc: np.ndarray) -> np.ndarray:
    return np.asarray((desc > 0).mean(axis=1), dtype=np.float64)


def scan_context_distance(query: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances (K,) and best column shifts (K,) of ``query`` (R,S) against ``candidates`` (K,R,S).

    All shifts at once: the candidates' columns are gathered rolled into (K, S shifts, R, S).
    """
    n_sectors = query.shape[1]
    shift_idx = (np.arange(n_sectors)[None, :] - np.arange(n_sectors)[:, None]) % n_sectors  # (k, j)
    rolled = candidates[:, :, shift_idx]  # (K, R, shifts, S): column j of roll(c, k) is c[:, j - k]
    dots = np.einsum("rj,krsj->ksj", query, rolled)
    q_norm = np.linalg.norm(query, axis=0)  # (S,)
    c_norm = np.linalg.norm(rolled, axis=1)  # (K, shifts, S)
    both = (q_norm[None, None, :] > 0) & (c_norm > 0)
    cos = np.where(both, dots / np.where(both, q_norm[None, None, :] * c_norm, 1.0), 0.0)
    n = both.sum(axis=2)
    dist = np.where(n > 0, 1.0 - cos.sum(axis=2) / np.maximum(n, 1), 2.0)  # (K, shifts)
    best = np.argmin(dist, axis=1)
    return dist[np.arange(dist.shape[0]), best], best


class PlaceIndex:
    """Descriptors by key; :meth:`query` proposes revisits (module docstring)."""

    def __init__(self, settings: PlaceSettings | None = None) -> None:
        self.settings = settings or PlaceSettings()
        self._keys: list[Hashable] = []
        self._descriptors: list[np.ndarray] = []
        self._tree: cKDTree | None = None
        self._ring_keys = np.empty((0, self.settings.rings))

    def __len__(self) -> int:
        return len(self._keys)

    def keys(self) -> list[Hashable]:
        return list(self._keys)

    def add(self, key: Hashable, descriptor: np.ndarray) -> None:
        """Store ``descriptor`` (from :func:`scan_context` with this index's settings) as ``key``."""
        d = np.asarray(descriptor, dtype=np.float64)
        shape = (self.settings.rings, self.settings.sectors)
        if d.shape != shape or not np.all(np.isfinite(d)):
            raise InvalidRequestError(
                f"place index: descriptor of {key!r} must be finite {shape}, got {d.shape}"
            )
        self._keys.append(key)
        self._descriptors.append(d)
        self._tree = None

    def query(
        self, descriptor: np.ndarray, *, exclude: Collection[Hashable] = (), max_distance: float | None = None
    ) -> list[PlaceCandidate]:
        """Candidates for ``descriptor``, nearest first, at most ``ring_candidates``, none in
        ``exclude`` and none farther than ``max_distance`` (default: the settings')."""
        if not self._keys:
            return []
        limit = self.settings.max_distance if max_distance is None else max_distance
        if self._tree is None:
            self._ring_keys = np.array([_ring_key(d) for d in self._descriptors])
            self._tree = cKDTree(self._ring_keys)
        want = min(len(self._keys), self.settings.ring_candidates + len(exclude))
        _, idx = self._tree.query(_ring_key(descriptor), k=want)
        picks = [int(i) for i in np.atleast_1d(idx) if self._keys[int(i)] not in exclude]
        picks = picks[: self.settings.ring_candidates]
        if not picks:
            return []
        dist, shift = scan_context_distance(
            np.asarray(descriptor, dtype=np.float64), np.array([self._descriptors[i] for i in picks])
        )
        step = 360.0 / self.settings.sectors
        out = [
            PlaceCandidate(self._keys[i], float(d), float((-k * step + 180.0) % 360.0 - 180.0))
            for i, d, k in zip(picks, dist, shift, strict=True)
            if d <= limit
        ]
        return sorted(out, key=lambda c: c.distance)
