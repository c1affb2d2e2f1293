"""Only sweeps that agree with the map reach it (issue 32): a session's map points wait until a
check says its sweeps still agree with the map they fold into.

A match's fitness says a sweep agrees with the session's own keyframes, not with the map (a town
the map never saw along the same coordinates, a wrong prior, a drift the graph has not corrected).
The threshold and what it separates: docs/benchmarks.md, "The map agreement check".
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from randt.core.tiles import Agreement, TileGrid, above_ground
from randt.core.transforms import transform_points

__all__ = ["AGREEING_CHECKS", "AgreementGate", "Held"]

log = logging.getLogger(__name__)

#: A session lost by disagreement folds again after this many agreeing checks in a row (two
#: agreeing registrations, as placement and relocalization ask).
AGREEING_CHECKS = 2

#: One sweep's map points waiting: ``(map name, xyz float32 (N, 3), intensity or None)``.
Held = tuple[str, np.ndarray, np.ndarray | None]


@dataclass
class AgreementGate:
    """One session's checks against its map, and the map points it holds between them.

    Every ``every`` sweeps (its first, every sweep the pose graph takes as a keyframe, and the
    first match after a fallback, which passed only the matcher's loose correction gate) the
    matcher also returns the sweep's thinned points, and the share of them above the ground within
    ``reach_m`` of the map's points, where the map has content, is measured
    (:meth:`randt.core.tiles.TileGrid.agreement`). It reaches ``min_share``, or fewer than
    ``min_points`` fall where the map has content: the held points go to the map. It does not:
    they are dropped, and the session is lost (answered ``lost``, nothing folded or offered to the
    pose graph) until :data:`AGREEING_CHECKS` checks in a row agree again. Poses answered ``ok``
    since the last check are not taken back. ``min_share`` 0 turns the gate off: every sweep's
    points go straight through.
    """

    min_share: float
    every: int
    min_points: int
    reach_m: float = 0.5
    #: Map points of sweeps since the last agreeing check.
    held: list[Held] = field(default_factory=list)
    #: Sweeps matched since the last check (a session's first sweep is checked).
    since_check: int = -1
    #: Lost by disagreement, and the agreeing checks since (AGREEING_CHECKS to fold again).
    disagreeing: bool = False
    agreeing_checks: int = 0
    #: The last check's figures (None before one).
    last: Agreement | None = None
    n_checks: int = 0
    n_disagreed: int = 0
    #: Points dropped because a check disagreed (never folded).
    n_dropped_points: int = 0

    @property
    def enabled(self) -> bool:
        return self.min_share > 0

    def due(self) -> bool:
        """Whether the sweep about to be matched should be checked (its thinned points asked for)."""
        return self.enabled and (self.since_check < 0 or self.since_check + 1 >= self.every)

    def hold(self, entry: Held) -> list[Held]:
        """A matched sweep's map points: returned to fold now when the gate is off, else held."""
        if not self.enabled:
            return [entry]
        self.held.append(entry)
        return []

    def release(self) -> list[Held]:
        """What is held, to fold (the session closes or merges its map), unless it disagreed."""
        out, self.held = ([] if self.disagreeing else self.held), []
        return out

    def check(self, grid: TileGrid, T_map_sensor: np.ndarray, points_sensor: np.ndarray) -> list[Held]:
        """Check a sweep (its thinned points in the sensor frame, ``T_map_sensor`` the pose they
        fold under) against ``grid``; returns the held points that may now be folded (none when it
        disagreed, or while the session has not yet agreed :data:`AGREEING_CHECKS` times)."""
        self.since_check = 0
        self.n_checks += 1
        found = grid.agreement(above_ground(transform_points(T_map_sensor, points_sensor)), self.reach_m)
        self.last = found
        if found.checked >= self.min_points and found.share < self.min_share:
            self.n_disagreed += 1
            self.n_dropped_points += sum(len(x) for _, x, _ in self.held)
            self.held = []
            self.disagreeing, self.agreeing_checks = True, 0
            return []
        return self._agreed()

    def localized(self) -> list[Held]:
        """A sweep localized on the map: its match was with the map (its inlier ratio reached the
        localizer's bar), a check that agreed, at no cost; returns the held points that may now
        be folded, as :meth:`check`."""
        self.since_check = 0
        return self._agreed()

    def _agreed(self) -> list[Held]:
        if self.disagreeing:
            self.agreeing_checks += 1
            if self.agreeing_checks < AGREEING_CHECKS:
                self.n_dropped_points += sum(len(x) for _, x, _ in self.held)
                self.held = []
                return []
            self.disagreeing, self.agreeing_checks = False, 0
        out, self.held = self.held, []
        return out

    def matched(self) -> None:
        """A sweep matched without a check."""
        self.since_check += 1

    def lost_reason(self, map_name: str) -> str:
        """Why a disagreeing session is answered ``lost`` (its last check's figures)."""
        last = self.last
        figures = "" if last is None else f"{last.share:.0%} of {last.checked:,} checked points"
        if self.agreeing_checks:
            return (
                f"lost: its sweeps agree with map {map_name!r} again ({figures}), "
                f"{self.agreeing_checks} of {AGREEING_CHECKS} checks; nothing is folded meanwhile"
            )
        return (
            f"lost: its sweeps do not agree with map {map_name!r} where the map has content "
            f"({figures} within {self.reach_m:g} m of its surfaces, {self.min_share:.0%} needed); "
            f"nothing is folded until {AGREEING_CHECKS} checks agree"
        )
