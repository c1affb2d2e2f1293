"""Where on a map a sweep was taken, without a prior: each map's places for relocalization.

A place is a keyframe the map's pose graph holds: its Scan Context descriptor (:mod:`randt.core.place`,
computed from the keyframe's points when it is offered, or taken again from the graph's log at a
restart) and its pose in the graph. A session whose first scan carries no prior (no GNSS: a
warehouse, a tunnel, a ROS 2 robot) asks :meth:`MapPlaces.guesses` with its sweep: the places
whose descriptors are nearest, each turned into a guess of the sweep's pose, which the matcher then
verifies on the map around it as it verifies a first sweep's GNSS prior
(``IncrementalMatcher.register_scan``'s ``relocalize``): docs/mapping.md, "Relocalization".
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import cast

import numpy as np

from randt.core.errors import InvalidCloudError
from randt.core.odometry import PosePrior
from randt.core.place import (
    PlaceCandidate,
    PlaceIndex,
    PlaceSettings,
    query_descriptors,
    scan_context,
    scan_context_distance,
)

__all__ = ["GUESSES", "GUESS_COVARIANCE", "MapPlaces", "PlaceKey"]

#: A place: a keyframe ``(vehicle, session, index)`` of the map's graph.
PlaceKey = tuple[str, str, int]

#: Places turned into guesses per sweep, nearest first (each one the matcher tries costs a first
#: sweep's match on the map).
GUESSES = 2
#: How far a guess may be from the sweep's pose: the place is the keyframe nearest in Scan Context,
#: up to half the keyframe spacing (10 m) along the road from the sweep, less the query's shifts
#: (``PlaceSettings.query_shifts_m``: the view 4 m ahead or behind that matched best); the yaw
#: comes from the descriptor's column shift (6 deg bins). What it is off by: docs/mapping.md,
#: "Relocalization". A match on the map farther from the guess than this allows (the first
#: sweep's chi-square test) is refused.
GUESS_COVARIANCE = np.diag([3.0**2, 3.0**2, 1.0**2] + [np.radians(3.0) ** 2] * 2 + [np.radians(6.0) ** 2])


class MapPlaces:
    """Each map's places (module docstring); thread-safe."""

    def __init__(self, settings: PlaceSettings | None = None) -> None:
        self.settings = settings or PlaceSettings()
        self._lock = threading.Lock()
        self._index: dict[str, PlaceIndex] = {}

    def add(self, map_name: str, key: PlaceKey, points: np.ndarray) -> None:
        """A keyframe of ``map_name``'s graph (its points in the sensor frame) becomes a place; one
        too sparse to describe, or known already, is left out."""
        try:
            descriptor = scan_context(points, self.settings)
        except InvalidCloudError:
            return
        with self._lock:
            index = self._index.get(map_name) or self._index.setdefault(map_name, PlaceIndex(self.settings))
            if key not in index:
                index.add(key, descriptor)

    def forget(self, map_name: str) -> None:
        """A deleted map's places."""
        with self._lock:
            self._index.pop(map_name, None)

    def __len__(self) -> int:
        with self._lock:
            return sum(len(index) for index in self._index.values())

    def guesses(
        self, map_name: str, xyz: np.ndarray, pose_of: Callable[[PlaceKey], np.ndarray | None]
    ) -> list[PosePrior]:
        """Up to :data:`GUESSES` guesses of the pose of a sweep (``xyz``, sensor frame) on
        ``map_name``, nearest place first: the place's pose (``pose_of``: ``None`` for one the
        graph no longer holds) turned by the descriptor's yaw and moved by the query's shift that
        matched best, with :data:`GUESS_COVARIANCE`. Empty when no place is near enough
        (``PlaceSettings.max_distance``) or the sweep is too sparse to describe."""
        with self._lock:
            index = self._index.get(map_name)
        if index is None or not len(index):
            return []
        try:
            queries = query_descriptors(xyz, self.settings)
        except InvalidCloudError:
            return []

        with self._lock:  # (the poses are read outside it: the graph's view has a lock of its own)
            found = index.query(queries, k=4 * GUESSES)
            stored = [index.descriptor(c.key) for c in found]
        out: list[PosePrior] = []
        for candidate, descriptor in zip(found, stored, strict=True):
            T = pose_of(cast(PlaceKey, candidate.key))
            if T is None:
                continue
            out.append(PosePrior(T @ self._offset(candidate, queries, descriptor), GUESS_COVARIANCE))
            if len(out) == GUESSES:
                break
        return out

    def _offset(self, candidate: PlaceCandidate, queries: np.ndarray, descriptor: np.ndarray) -> np.ndarray:
        """``T_place_sweep`` of a candidate: the descriptor's yaw, and the query's view that
        matched best (the sweep seen ``dx`` ahead matched: the place is ``dx`` ahead of it)."""
        distances = [float(scan_context_distance(q, descriptor[None])[0][0]) for q in queries]
        dx = (0.0, *self.settings.query_shifts_m)[int(np.argmin(distances))]
        a = np.radians(candidate.yaw_deg)
        T = np.eye(4)
        T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        T[:2, 3] = T[:2, :2] @ np.array([-dx, 0.0])
        return T
