"""Routes through a town's street grid, vehicle motion, and the simulated scan stream.

:class:`Route` (lines, arcs and clothoids along the streets), :class:`Motion` (the speed a driver
keeps: slower in corners) and :func:`simulate`, the lazy stream of :class:`SimScan` sweeps with
their exact sensor poses (at each sweep's start) and per-point times, deskewed or as a real sensor
reports them. Frames, units, time and motion distortion: docs/clients.md, "The simulator".
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from randt.sim.lidar import Lidar64
from randt.sim.town import Town

__all__ = [
    "FleetVehicle",
    "Motion",
    "Route",
    "SimScan",
    "plan_fleet",
    "simulate",
    "simulate_fleet",
]

log = logging.getLogger(__name__)

_REPEAT_TOL_M = 1e-9

#: Spacing of the speed profile's table along the route (m), :class:`Motion`.
PROFILE_STEP_M = 0.05

#: Length of the clothoid into and out of every corner (m): a driver turns the wheel over about a
#: second at corner speed (5.2 m/s on a 9 m arc at 3 m/s^2 lateral).
TRANSITION_M = 8.0


def _right_normal(d: np.ndarray) -> np.ndarray:
    """(..., 2) unit vectors rotated -90 deg (to the right of travel)."""
    return np.stack([d[..., 1], -d[..., 0]], axis=-1)


@dataclass(frozen=True, eq=False)
class Route:
    """A planar route of P pieces (lines, circular arcs and clothoids), continuous in heading.

    Piece ``i`` starts at ``start_xy[i]`` with heading ``start_heading_rad[i]`` and curvature
    ``curvature_per_m[i]`` (0 for a line, +1/R turning left, -1/R right), which changes along it at
    ``curvature_rate_per_m2[i]`` (0 for lines and arcs; a clothoid's curvature is linear in arc
    length), and covers arc length ``[start_s_m[i], start_s_m[i] + piece_length_m[i]]``.

    Attributes
    ----------
    start_xy:
        (P,2) float64 world xy (m).
    start_heading_rad:
        (P,) float64 heading from world +x towards +y (rad).
    curvature_per_m:
        (P,) float64 signed curvature (1/m).
    piece_length_m:
        (P,) float64 piece lengths (m), positive.
    closed:
        A closed route is periodic: ``s`` wraps modulo :attr:`length_m`. An open one is defined on
        ``[0, length_m]`` only.
    ground_gradient:
        (2,) ``g`` of the town's ground ``z = g·xy``; poses sit on it.
    curvature_rate_per_m2:
        (P,) float64 change of curvature per metre along each piece (1/m^2); zeros when empty
        (the default).
    """

    start_xy: np.ndarray
    start_heading_rad: np.ndarray
    curvature_per_m: np.ndarray
    piece_length_m: np.ndarray
    closed: bool
    ground_gradient: np.ndarray
    curvature_rate_per_m2: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        p = np.asarray(self.piece_length_m).reshape(-1).shape[0]
        if p == 0 or np.any(np.asarray(self.piece_length_m) <= 0):
            raise ValueError("a route needs at least one piece, all of positive length")
        if np.asarray(self.curvature_rate_per_m2).size == 0:  # lines and arcs only
            object.__setattr__(self, "curvature_rate_per_m2", np.zeros(p))
        object.__setattr__(self, "start_xy", np.asarray(self.start_xy, np.float64).reshape(p, 2))
        for name in ("start_heading_rad", "curvature_per_m", "piece_length_m", "curvature_rate_per_m2"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), np.float64).reshape(p))
        object.__setattr__(self, "ground_gradient", np.asarray(self.ground_gradient, np.float64).reshape(2))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_corners(
        cls,
        corners_xy: np.ndarray,
        *,
        closed: bool,
        turn_radius_m: float = 9.0,
        ground_gradient: np.ndarray | None = None,
        transition_m: float = TRANSITION_M,
    ) -> Route:
        """A route along a polyline whose corners are rounded as a car turns: a clothoid of
        ``transition_m`` (curvature from 0 to 1/``turn_radius_m``), an arc of ``turn_radius_m``
        and a clothoid back to a straight line. A corner too gentle for the two clothoids is two
        clothoids of ``R |phi|`` each, meeting at the corner's sharpest curvature.

        Parameters
        ----------
        corners_xy:
            (n,2) world xy of the polyline's vertices (m); collinear vertices are dropped. A
            closed route returns from the last vertex to the first.
        closed:
            Whether the polyline is a loop.
        turn_radius_m:
            Radius of every corner arc (m). A corner's curve starts and ends at tangent points
            equally far from its corner (``R tan(phi/2)`` for a plain arc, ``phi`` the turn
            angle; further with clothoids); a leg too short for its two curves raises ValueError.
        ground_gradient:
            (2,) ground plane gradient (zero by default).
        transition_m:
            Length of each clothoid (m); 0: plain arcs (the curvature jumps at their ends).

        Returns
        -------
        Route
        """
        q = np.asarray(corners_xy, dtype=np.float64).reshape(-1, 2)
        q = q[np.r_[True, np.any(np.abs(np.diff(q, axis=0)) > _REPEAT_TOL_M, axis=1)]]  # no repeats
        if closed and q.shape[0] > 1 and np.allclose(q[0], q[-1]):
            q = q[:-1]
        q = _drop_collinear(q, closed)
        n = q.shape[0]
        if n < 2 or (closed and n < 3):
            raise ValueError("a route needs at least 2 distinct vertices (3 when closed)")
        legs = (np.roll(q, -1, axis=0) - q) if closed else np.diff(q, axis=0)  # leg i: vertex i -> i+1
        leg_len = np.linalg.norm(legs, axis=1)
        u = legs / leg_len[:, None]
        # turn at each vertex: from the leg arriving to the leg leaving (ends of an open route: none)
        u_in = np.roll(u, 1, axis=0) if closed else np.vstack([u[:1], u])
        u_out = u if closed else np.vstack([u, u[-1:]])
        phi = np.arctan2(u_in[:, 0] * u_out[:, 1] - u_in[:, 1] * u_out[:, 0], np.sum(u_in * u_out, axis=1))
        if np.any(np.abs(phi) > np.radians(179.0)):
            raise ValueError("a route cannot reverse (U-turn) at a vertex")
        corner = [_corner_curve(float(p), turn_radius_m, transition_m) for p in phi]
        tangent = np.array([c[0] for c in corner])
        tan_next = np.roll(tangent, -1) if closed else tangent[1:]
        if np.any(tangent[: leg_len.size] + tan_next > leg_len + 1e-9):
            raise ValueError(f"a leg is too short for corner curves of radius {turn_radius_m} m")

        xy, heading, kappa, rate, length = [], [], [], [], []
        for i in range(leg_len.size):  # a line along leg i, then the curve at its end vertex
            j = (i + 1) % n
            line_len = leg_len[i] - tangent[i] - tan_next[i]
            theta = float(np.arctan2(u[i, 1], u[i, 0]))
            if line_len > 1e-9:
                xy.append(q[i] + tangent[i] * u[i])
                heading.append(theta)
                kappa.append(0.0)
                rate.append(0.0)
                length.append(line_len)
            if abs(phi[j]) > 1e-12 and (closed or j < n - 1):
                at, th = q[j] - tangent[j] * u[i], theta
                for k0, c, ell in corner[j][1]:
                    xy.append(at)
                    heading.append(th)
                    kappa.append(k0)
                    rate.append(c)
                    length.append(ell)
                    at, th = _piece_end(at, th, k0, c, ell)
        g = np.zeros(2) if ground_gradient is None else ground_gradient
        return cls(
            np.array(xy), np.array(heading), np.array(kappa), np.array(length), closed, g, np.array(rate)
        )

    @classmethod
    def from_nodes(
        cls,
        town: Town,
        nodes_xy: np.ndarray,
        *,
        closed: bool,
        lane_offset_m: float = 1.75,
        turn_radius_m: float = 9.0,
        transition_m: float = TRANSITION_M,
    ) -> Route:
        """A route along street centreline vertices (e.g. intersections), in the right-hand lane.

        Parameters
        ----------
        town:
            The town (for its ground).
        nodes_xy:
            (n,2) world xy of the centreline path's vertices (m), in travel order.
        closed:
            Whether the path returns from the last node to the first.
        lane_offset_m:
            Offset of the driving line to the right of the centreline (m).
        turn_radius_m:
            Corner arc radius (m).
        transition_m:
            The clothoids into and out of each corner arc (:meth:`from_corners`; 0: plain arcs).

        Returns
        -------
        Route
        """
        q = _drop_collinear(np.asarray(nodes_xy, dtype=np.float64).reshape(-1, 2), closed)
        legs = (np.roll(q, -1, axis=0) - q) if closed else np.diff(q, axis=0)
        u = legs / np.linalg.norm(legs, axis=1, keepdims=True)
        u_in = np.roll(u, 1, axis=0) if closed else np.vstack([u[:1], u])
        u_out = u if closed else np.vstack([u, u[-1:]])
        r_in, r_out = _right_normal(u_in), _right_normal(u_out)
        # where the two offset lines meet: N + o (r_in + r_out) / (1 + r_in . r_out)
        corners = q + lane_offset_m * (r_in + r_out) / (1.0 + np.sum(r_in * r_out, axis=1))[:, None]
        return cls.from_corners(
            corners,
            closed=closed,
            turn_radius_m=turn_radius_m,
            ground_gradient=town.ground_gradient,
            transition_m=transition_m,
        )

    @classmethod
    def rectangle(
        cls,
        town: Town,
        i0: int,
        i1: int,
        j0: int,
        j1: int,
        *,
        clockwise: bool = False,
        start_corner: int = 0,
        lane_offset_m: float = 1.75,
        turn_radius_m: float = 9.0,
        transition_m: float = TRANSITION_M,
    ) -> Route:
        """A closed loop around the blocks between streets ``i0 < i1`` (x) and ``j0 < j1`` (y).

        ``start_corner`` (0-3) picks the corner the route's first leg leaves from, counted
        counter-clockwise from (x[i0], y[j0]).
        """
        c = town.street_coords_m
        if not (0 <= i0 < i1 < c.size and 0 <= j0 < j1 < c.size):
            raise ValueError(f"street indices must satisfy 0 <= i0 < i1 < {c.size}, likewise j")
        nodes = np.array([[c[i0], c[j0]], [c[i1], c[j0]], [c[i1], c[j1]], [c[i0], c[j1]]])
        nodes = np.roll(nodes, -int(start_corner) % 4, axis=0)
        if clockwise:
            nodes = np.vstack([nodes[:1], nodes[:0:-1]])
        return cls.from_nodes(
            town,
            nodes,
            closed=True,
            lane_offset_m=lane_offset_m,
            turn_radius_m=turn_radius_m,
            transition_m=transition_m,
        )

    @classmethod
    def loop(
        cls,
        town: Town,
        seed: int,
        *,
        length_m: float = 600.0,
        lane_offset_m: float = 1.75,
        turn_radius_m: float = 9.0,
        transition_m: float = TRANSITION_M,
    ) -> Route:
        """A random closed rectangular loop whose length is close to ``length_m``.

        Among the rectangles of the street grid, one whose centreline perimeter is within half a
        block pitch of the best match to ``length_m`` is drawn, with a random direction and
        starting corner. The route is periodic: a run longer than one lap goes round again (loop
        closures for the mapper). Corners as :meth:`rectangle` (``transition_m=0``: plain arcs).
        """
        rects = _rectangles(town)
        rng = np.random.default_rng(seed)
        err = np.abs(rects[:, 4] - length_m)
        pool = np.flatnonzero(err <= err.min() + 0.5 * town.pitch_m)
        i0, i1, j0, j1, _ = rects[rng.choice(pool)].astype(int)
        return cls.rectangle(
            town,
            i0,
            i1,
            j0,
            j1,
            clockwise=bool(rng.random() < 0.5),
            start_corner=int(rng.integers(4)),
            lane_offset_m=lane_offset_m,
            turn_radius_m=turn_radius_m,
            transition_m=transition_m,
        )

    @classmethod
    def random_walk(
        cls,
        town: Town,
        seed: int,
        *,
        length_m: float = 1000.0,
        lane_offset_m: float = 1.75,
        turn_radius_m: float = 9.0,
    ) -> Route:
        """An open route of at least ``length_m`` through the grid's intersections.

        From a random intersection and direction the walk goes straight (probability 1/2) or turns
        left or right (1/4 each) at every intersection, never leaving the grid nor turning back.
        """
        c = town.street_coords_m
        s = c.size
        if s < 2:
            raise ValueError("the town needs at least 2 streets per axis for routes")
        rng = np.random.default_rng(seed)
        steps = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])  # heading index 0..3, counter-clockwise
        node = rng.integers(0, s, 2)

        def ok(n: np.ndarray, h: int) -> bool:
            nxt = n + steps[h]
            return bool(np.all((nxt >= 0) & (nxt < s)))

        heading = int(rng.choice([h for h in range(4) if ok(node, h)]))
        path = [node.copy()]
        target = length_m + town.pitch_m
        while True:
            while (len(path) - 1) * town.pitch_m < target:
                options = [(heading + turn) % 4 for turn in (0, 1, 3) if ok(node, (heading + turn) % 4)]
                weights = np.array([0.5 if h == heading else 0.25 for h in options])
                heading = int(rng.choice(options, p=weights / weights.sum()))
                node = node + steps[heading]
                path.append(node.copy())
            route = cls.from_nodes(
                town,
                c[np.array(path)],
                closed=False,
                lane_offset_m=lane_offset_m,
                turn_radius_m=turn_radius_m,
            )
            if route.length_m >= length_m:  # corners cut a little off the centreline length
                return route
            target += town.pitch_m

    # ------------------------------------------------------------------ queries
    @property
    def start_s_m(self) -> np.ndarray:
        """(P,) arc length at the start of each piece (m)."""
        return np.concatenate([[0.0], np.cumsum(self.piece_length_m)[:-1]])

    @property
    def length_m(self) -> float:
        """Total arc length (m); one lap of a closed route."""
        return float(np.sum(self.piece_length_m))

    def xy_heading_at(self, s_m: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Position and heading at arc lengths ``s_m``.

        Parameters
        ----------
        s_m:
            (M,) or scalar arc length (m). Wrapped for a closed route; outside ``[0, length_m]``
            raises ValueError for an open one.

        Returns
        -------
        xy, heading:
            (M,2) world xy (m) and (M,) heading (rad): exact on lines and arcs, on clothoids to
            rounding (Gauss-Legendre quadrature of a smooth integrand, :func:`_piece_point`).
        """
        i, u = self._piece_at(self._checked_s(s_m))
        xy, th = _piece_point(
            self.start_xy[i],
            self.start_heading_rad[i],
            self.curvature_per_m[i],
            self.curvature_rate_per_m2[i],
            u,
        )
        return xy, th

    def curvature_at(self, s_m: np.ndarray | float) -> np.ndarray:
        """(M,) signed curvature (1/m) at arc lengths ``s_m`` (wrapped or checked as in
        :meth:`xy_heading_at`)."""
        i, u = self._piece_at(self._checked_s(s_m))
        return self.curvature_per_m[i] + self.curvature_rate_per_m2[i] * u

    def _checked_s(self, s_m: np.ndarray | float) -> np.ndarray:
        s = np.atleast_1d(np.asarray(s_m, dtype=np.float64))
        total = self.length_m
        if self.closed:
            return np.mod(s, total)
        if np.any(s < -1e-9) or np.any(s > total + 1e-9):
            raise ValueError(f"s outside the open route's [0, {total:.3f}] m")
        return s

    def _piece_at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The piece of each (wrapped) arc length and the arc length into it."""
        starts = self.start_s_m
        i = np.clip(np.searchsorted(starts, s, side="right") - 1, 0, starts.size - 1)
        return i, s - starts[i]

    def poses_at(self, s_m: np.ndarray | float) -> np.ndarray:
        """(M,4,4) world<-vehicle poses at arc lengths ``s_m`` (x forward, y left, z up, on the ground)."""
        xy, th = self.xy_heading_at(s_m)
        g = self.ground_gradient
        n = np.array([-g[0], -g[1], 1.0]) / np.sqrt(1.0 + g @ g)
        h = np.column_stack([np.cos(th), np.sin(th), np.zeros_like(th)])
        x = h - (h @ n)[:, None] * n
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        y = np.cross(np.broadcast_to(n, x.shape), x)
        T = np.zeros((th.size, 4, 4))
        T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = x, y, n
        T[:, :2, 3] = xy
        T[:, 2, 3] = xy @ g
        T[:, 3, 3] = 1.0
        return T

    def pose_at(self, s_m: float) -> np.ndarray:
        """(4,4) world<-vehicle pose at arc length ``s_m`` (see :meth:`poses_at`)."""
        return self.poses_at(s_m)[0]

    def polyline(self, step_m: float = 1.0) -> np.ndarray:
        """(M,2) world xy sampled every ``step_m`` along one lap (for plots and comparisons)."""
        return self.xy_heading_at(np.arange(0.0, self.length_m, step_m))[0]


_GL_X, _GL_W = np.polynomial.legendre.leggauss(16)


def _piece_point(
    xy0: np.ndarray, th0: np.ndarray, k0: np.ndarray, c: np.ndarray, u: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Position and heading ``u`` metres into pieces that start at ``xy0`` (M,2) with heading
    ``th0``, curvature ``k0`` and curvature rate ``c`` (all (M,)): closed forms on lines and arcs,
    16-point Gauss-Legendre quadrature of ``(cos, sin)`` of the quadratic heading on clothoids (a
    clothoid turns by less than 90 degrees here: the quadrature is exact to rounding)."""
    xy0, th0 = np.atleast_2d(xy0), np.atleast_1d(th0)
    k0, c, u = np.atleast_1d(k0), np.atleast_1d(c), np.atleast_1d(u)
    th = th0 + k0 * u + 0.5 * c * u * u
    straight = k0 == 0.0
    k_safe = np.where(straight, 1.0, k0)
    dx = np.where(straight, u * np.cos(th0), (np.sin(th) - np.sin(th0)) / k_safe)
    dy = np.where(straight, u * np.sin(th0), (np.cos(th0) - np.cos(th)) / k_safe)
    spiral = np.flatnonzero(c != 0.0)
    if spiral.size:
        us = u[spiral, None] * 0.5 * (_GL_X[None] + 1.0)  # (m, 16) nodes along each piece
        ths = th0[spiral, None] + k0[spiral, None] * us + 0.5 * c[spiral, None] * us * us
        half = 0.5 * u[spiral]
        dx[spiral] = half * (np.cos(ths) @ _GL_W)
        dy[spiral] = half * (np.sin(ths) @ _GL_W)
    return xy0 + np.column_stack([dx, dy]), th


def _piece_end(xy0: np.ndarray, th0: float, k0: float, c: float, length: float) -> tuple[np.ndarray, float]:
    """Where a piece (:func:`_piece_point`) ends: position and heading."""
    xy, th = _piece_point(
        np.asarray(xy0)[None], np.array([th0]), np.array([k0]), np.array([c]), np.array([length])
    )
    return xy[0], float(th[0])


def _corner_curve(
    phi: float, radius_m: float, transition_m: float
) -> tuple[float, list[tuple[float, float, float]]]:
    """A corner of turn ``phi`` (rad, + left): its tangent length (m, from the corner to where
    the curve leaves the straight, the same on both sides by symmetry) and its pieces
    ``(curvature, curvature rate, length)``: clothoid, arc, clothoid."""
    if abs(phi) <= 1e-12:
        return 0.0, []
    sign, turn = float(np.sign(phi)), abs(phi)
    ell = min(transition_m, radius_m * turn)  # a gentle corner: two clothoids, no arc
    if ell <= 1e-9:
        pieces = [(sign / radius_m, 0.0, radius_m * turn)]
    else:
        k_max = sign / radius_m
        arc = radius_m * turn - ell  # the clothoids turn ell / (2 R) each
        pieces = [(0.0, k_max / ell, ell)]
        if arc > 1e-9:
            pieces.append((k_max, 0.0, arc))
        pieces.append((k_max, -k_max / ell, ell))
    at, th = np.zeros(2), 0.0
    for k0, c, length in pieces:
        at, th = _piece_end(at, th, k0, c, length)
    chord = np.array([1.0 + np.cos(phi), np.sin(phi)])  # u_in + u_out with u_in = +x
    return float(at @ chord / (chord @ chord)), pieces


def _drop_collinear(q: np.ndarray, closed: bool) -> np.ndarray:
    """Vertices of a polyline without those where it goes straight on."""
    if q.shape[0] < 3:
        return q
    prev = np.roll(q, 1, axis=0)
    nxt = np.roll(q, -1, axis=0)
    a, b = q - prev, nxt - q
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    straight = (np.abs(cross) <= 1e-9 * np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)) & (
        np.sum(a * b, axis=1) > 0
    )
    if not closed:
        straight[[0, -1]] = False
    return q[~straight]


def _rectangles(town: Town) -> np.ndarray:
    """(R,5) every rectangle of the street grid: i0, i1, j0, j1 and its centreline perimeter (m)."""
    s = town.street_coords_m.size
    if s < 2:
        raise ValueError("the town needs at least 2 streets per axis for loops")
    pairs = np.array(list(itertools.combinations(range(s), 2)))
    a, b = np.meshgrid(np.arange(pairs.shape[0]), np.arange(pairs.shape[0]), indexing="ij")
    i, j = pairs[a.ravel()], pairs[b.ravel()]
    c = town.street_coords_m
    perimeter = 2.0 * ((c[i[:, 1]] - c[i[:, 0]]) + (c[j[:, 1]] - c[j[:, 0]]))
    return np.column_stack([i, j, perimeter])


@dataclass(frozen=True)
class Motion:
    """A vehicle driving a route as a driver would: arc length and poses as functions of time.

    The speed along the route is a profile ``v(s)``: ``speed_mps`` on the straights, at most
    ``sqrt(max_lateral_mps2 / |curvature|)`` in corners, reached by braking at ``max_decel_mps2``
    before them and accelerating at ``max_accel_mps2`` after (periodic over a closed route's lap).
    ``speed_variation`` adds a slow change of pace, ``1 + speed_variation * sin(2 pi t /
    speed_period_s + phase_rad)`` times the profile, integrated analytically. Time 0 is the start
    of the first sweep, at arc length ``start_s_m``. Arc length follows from the profile's travel
    time ``tau(s) = integral ds / v(s)``, tabulated every :data:`PROFILE_STEP_M` and inverted by
    interpolation: poses are exact to about 0.01 mm. ``max_lateral_mps2=inf`` drives the whole
    route at ``speed_mps``, corners included.
    """

    route: Route
    speed_mps: float = 10.0
    speed_variation: float = 0.0
    speed_period_s: float = 20.0
    phase_rad: float = 0.0
    start_s_m: float = 0.0
    mount_height_m: float = 1.73
    max_lateral_mps2: float = 3.0
    max_accel_mps2: float = 1.5
    max_decel_mps2: float = 2.5
    _profile: tuple[np.ndarray, np.ndarray] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.speed_mps < 0 or not 0.0 <= self.speed_variation < 1.0 or self.speed_period_s <= 0:
            raise ValueError("Motion needs speed_mps >= 0, 0 <= speed_variation < 1, speed_period_s > 0")
        if min(self.max_lateral_mps2, self.max_accel_mps2, self.max_decel_mps2) <= 0:
            raise ValueError("Motion needs positive lateral, acceleration and braking limits")
        object.__setattr__(self, "_profile", self._travel_times())

    def _travel_times(self) -> tuple[np.ndarray, np.ndarray]:
        """Arc lengths over one lap (closed) or the route (open), and the profile's travel time
        from ``s = 0`` to each."""
        total = self.route.length_m
        n = max(2, int(np.ceil(total / PROFILE_STEP_M)) + 1)
        s = np.linspace(0.0, total, n)
        if self.speed_mps == 0.0:
            return s, np.zeros(n)
        v = self.speed_profile(s)
        dt = np.diff(s) * 0.5 * (1.0 / v[1:] + 1.0 / v[:-1])
        return s, np.concatenate([[0.0], np.cumsum(dt)])

    def speed_profile(self, s_m: np.ndarray) -> np.ndarray:
        """(M,) speed (m/s) at arc lengths ``s_m`` in ``[0, length_m]`` before ``speed_variation``:
        the cruise speed, capped in corners, with braking and acceleration limits (the lowest of
        every bound reachable from a cap, in ``v^2``)."""
        s = np.asarray(s_m, dtype=np.float64)
        route = self.route
        if route.closed:  # the neighbouring laps' corners bound this lap's ends
            total = route.length_m
            s_all = np.concatenate([s - total, s, s + total])
        else:
            s_all = s
        kappa = np.abs(route.curvature_at(np.mod(s_all, route.length_m) if route.closed else s_all))
        with np.errstate(divide="ignore"):
            cap2 = np.minimum(self.speed_mps**2, self.max_lateral_mps2 / kappa)
        a, d = 2.0 * self.max_accel_mps2, 2.0 * self.max_decel_mps2
        reach_after = a * s_all + np.minimum.accumulate(cap2 - a * s_all)  # accelerating out of caps
        reach_before = -d * s_all + np.minimum.accumulate((cap2 + d * s_all)[::-1])[::-1]  # braking into
        v = np.sqrt(np.minimum(reach_after, reach_before))
        if route.closed:
            v = v[s.size : 2 * s.size]
        elif v.size and (v[0] == 0.0 or v[-1] == 0.0):
            raise ValueError("the speed profile stops")
        return v

    @property
    def lap_time_s(self) -> float:
        """Time to drive the whole route (one lap of a closed one) on the profile, without
        ``speed_variation`` (s); infinite at speed 0."""
        return float(self._profile[1][-1]) if self.speed_mps > 0 else float("inf")

    def s_at(self, t_s: np.ndarray | float) -> np.ndarray:
        """Arc length (m, unwrapped) at times ``t_s`` (s): (M,) float64."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        if self.speed_mps == 0.0:
            return np.full(t.shape, self.start_s_m)
        w = 2.0 * np.pi / self.speed_period_s
        wobble = self.speed_variation / w * (np.cos(self.phase_rad) - np.cos(w * t + self.phase_rad))
        return self._s_of_tau(self._tau_of_s(self.start_s_m) + t + wobble)

    def _tau_of_s(self, s_m: float) -> float:
        """The profile's travel time from ``s = 0`` to ``s_m`` (unwrapped on a closed route)."""
        s_grid, tau = self._profile
        total = s_grid[-1]
        if self.route.closed:
            laps = np.floor(s_m / total)
            return float(laps * tau[-1] + np.interp(s_m - laps * total, s_grid, tau))
        v0, v1 = self._end_speeds()
        if s_m < 0.0:
            return float(s_m / v0)
        if s_m > total:
            return float(tau[-1] + (s_m - total) / v1)
        return float(np.interp(s_m, s_grid, tau))

    def _end_speeds(self) -> tuple[float, float]:
        """The profile's speed over its first and last table step (an open route continues at
        them beyond its ends)."""
        s_grid, tau = self._profile
        return float(s_grid[1] / tau[1]), float((s_grid[-1] - s_grid[-2]) / (tau[-1] - tau[-2]))

    def _s_of_tau(self, x: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`_tau_of_s`; an open route continues at its end speeds beyond its ends."""
        s_grid, tau = self._profile
        total, lap = s_grid[-1], tau[-1]
        if self.route.closed:
            laps = np.floor(x / lap)
            return laps * total + np.interp(x - laps * lap, tau, s_grid)
        v0, v1 = self._end_speeds()
        out = np.interp(x, tau, s_grid)
        out = np.where(x < 0.0, x * v0, out)
        return np.where(x > lap, total + (x - lap) * v1, out)

    def vehicle_poses_at(self, t_s: np.ndarray | float) -> np.ndarray:
        """(M,4,4) world<-vehicle poses at times ``t_s`` (s)."""
        return self.route.poses_at(self.s_at(t_s))

    def sensor_poses_at(self, t_s: np.ndarray | float) -> np.ndarray:
        """(M,4,4) world<-sensor poses at times ``t_s`` (s): the vehicle pose raised by the mount."""
        T = self.vehicle_poses_at(t_s)
        T[:, :3, 3] += self.mount_height_m * T[:, :3, 2]
        return T


@dataclass(frozen=True, eq=False)
class SimScan:
    """One simulated sweep with its exact ground truth.

    Attributes
    ----------
    index:
        Scan number of this vehicle, from 0.
    stamp_ns:
        Time of the sweep's first firing (its reference time), nanoseconds.
    T_world_sensor:
        (4,4) float64 exact world<-sensor pose at ``stamp_ns`` (the sweep start).
    points_xyz:
        (N,3) float32 points (m) in the sensor frame: the reference (sweep-start) frame when
        ``deskewed``, else each point's firing-time frame (docs/clients.md, "The simulator").
    intensity:
        (N,) float32 in [0, 1].
    time_offset_s:
        (N,) float64 firing time of each point after ``stamp_ns`` (s), in ``[0, 1/rate_hz)``.
    ring:
        (N,) uint8 beam index, 0 = highest.
    label:
        (N,) uint8 :class:`~randt.sim.town.Material` of the surface each point lies on.
    deskewed:
        Which frame ``points_xyz`` are in (above).
    route_s_m:
        Arc length along the route at ``stamp_ns`` (m; unwrapped, may exceed one lap).
    """

    index: int
    stamp_ns: int
    T_world_sensor: np.ndarray
    points_xyz: np.ndarray
    intensity: np.ndarray
    time_offset_s: np.ndarray
    ring: np.ndarray
    label: np.ndarray
    deskewed: bool
    route_s_m: float

    def __len__(self) -> int:
        return self.points_xyz.shape[0]


def simulate(
    town: Town,
    route: Route,
    *,
    n_scans: int,
    rate_hz: float = 10.0,
    speed_mps: float = 10.0,
    seed: int = 0,
    lidar: Lidar64 | None = None,
    deskewed: bool = True,
    speed_variation: float = 0.0,
    start_s_m: float = 0.0,
    start_stamp_ns: int = 0,
    workers: int = 0,
    max_lateral_mps2: float = 3.0,
    first_index: int = 0,
) -> Iterator[SimScan]:
    """Drive ``route`` through ``town``: an iterator over ``n_scans`` sweeps, computed lazily.

    Arguments are checked at the call (not at the first ``next``).

    Parameters
    ----------
    town, route:
        The scene and the route (from :class:`Route`'s constructors on the same town).
    n_scans:
        Number of sweeps.
    rate_hz:
        Sweeps per second; scan ``k`` starts at ``start_stamp_ns + k * round(1e9 / rate_hz)``.
    speed_mps:
        Cruise speed on straights; slower in corners (:class:`Motion`): consecutive sweeps start
        ``speed_mps / rate_hz`` metres apart along a straight when ``speed_variation`` is 0.
    seed:
        Seed of the speed phase and of each sweep's noise (scan ``k`` uses ``[seed, k]``), so the
        same arguments give identical scans.
    lidar:
        The sensor (``Lidar64()`` by default).
    deskewed:
        Frame of the points (:class:`SimScan`).
    speed_variation:
        Relative amplitude of a slow (20 s) sinusoidal speed change, in [0, 1).
    start_s_m:
        Arc length of the first sweep's start (m).
    start_stamp_ns:
        Stamp of the first sweep (ns).
    workers:
        0: each sweep is computed when it is asked for. ``N > 0``: ``N`` worker processes compute
        the sweeps ahead of the consumer (at most :data:`AHEAD_PER_WORKER` each), so ray casting
        runs beside the consumer's work, or on several cores for a ``list(...)``. The scans are
        the same either way (sweep ``k`` depends only on ``k``).
    max_lateral_mps2:
        The driver's limit in corners (:class:`Motion`); ``inf``: the whole route at
        ``speed_mps``, corners included (with ``Route.loop(transition_m=0)``, the yaw rate jumps
        at a corner's onset as no car drives: a stress test for deskewing).
    first_index:
        The first sweep computed: sweeps ``first_index`` to ``n_scans - 1`` are yielded, the same
        as those of the whole drive (a test that needs only a drive's end does not simulate the
        rest).

    Returns
    -------
    Iterator[SimScan]
        One scan per sweep, in time order.
    """
    lidar = Lidar64() if lidar is None else lidar
    if n_scans < 0 or rate_hz <= 0:
        raise ValueError("n_scans must be >= 0 and rate_hz > 0")
    if workers < 0:
        raise ValueError(f"workers must be >= 0, got {workers}")
    if not 0 <= first_index <= n_scans:
        raise ValueError(f"first_index must be in 0..{n_scans}, got {first_index}")
    phase = float(np.random.default_rng([seed, 2**31]).uniform(0.0, 2.0 * np.pi))
    motion = Motion(
        route,
        speed_mps,
        speed_variation,
        phase_rad=phase,
        start_s_m=start_s_m,
        mount_height_m=lidar.mount_height_m,
        max_lateral_mps2=max_lateral_mps2,
    )
    period_ns = round(1e9 / rate_hz)
    if not route.closed:
        s_end = motion.s_at(n_scans * period_ns * 1e-9)[0]
        if s_end > route.length_m + 1e-9:
            raise ValueError(
                f"{n_scans} scans need {s_end:.1f} m but the open route has {route.length_m:.1f} m"
            )
    sweeper = _Sweeper(town, motion, lidar, period_ns, rate_hz, seed, deskewed, start_stamp_ns)
    if workers == 0:
        return (sweeper(k) for k in range(first_index, n_scans))
    return _ahead(sweeper, range(first_index, n_scans), workers)


#: Sweeps a worker process of :func:`simulate` may have computed ahead of the consumer.
AHEAD_PER_WORKER = 4


@dataclass(frozen=True)
class _Sweeper:
    """Sweep ``k`` of one drive (what :func:`simulate` yields); picklable, for worker processes."""

    town: Town
    motion: Motion
    lidar: Lidar64
    period_ns: int
    rate_hz: float
    seed: int
    deskewed: bool
    start_stamp_ns: int

    def __call__(self, k: int) -> SimScan:
        tic = time.perf_counter()
        firing = self.lidar.firing_offsets_s(self.rate_hz)
        t0 = k * self.period_ns * 1e-9
        T_cols = self.motion.sensor_poses_at(t0 + firing)
        T_ref = T_cols[0]  # firing 0 is at offset 0: the sweep start
        rng = np.random.default_rng([self.seed, k])
        sweep = self.lidar.sweep(self.town, T_cols, rng, T_world_reference=T_ref if self.deskewed else None)
        scan = SimScan(
            index=k,
            stamp_ns=self.start_stamp_ns + k * self.period_ns,
            T_world_sensor=T_ref.copy(),
            points_xyz=sweep.points_xyz.astype(np.float32),
            intensity=sweep.intensity,
            time_offset_s=firing[sweep.column],
            ring=sweep.ring,
            label=sweep.label,
            deskewed=self.deskewed,
            route_s_m=float(self.motion.s_at(t0)[0]),
        )
        log.debug("scan %d: %d points in %.3f s", k, len(scan), time.perf_counter() - tic)
        return scan


def _ahead(sweeper: _Sweeper, indices: range, workers: int) -> Iterator[SimScan]:
    """``sweeper(k)`` for every ``k`` of ``indices`` in order, computed by ``workers`` spawned
    processes (spawn: the caller may run threads, which fork would copy mid-flight) at most
    ``AHEAD_PER_WORKER * workers`` sweeps ahead; the processes stop when the iterator is closed."""
    import multiprocessing
    from collections import deque
    from concurrent.futures import Future, ProcessPoolExecutor

    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
    pending: deque[Future[SimScan]] = deque()
    try:
        for k in indices:
            pending.append(pool.submit(sweeper, k))
            if len(pending) >= AHEAD_PER_WORKER * workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


@dataclass(frozen=True)
class FleetVehicle:
    """One simulated vehicle of a fleet: its name, route, seed, start and clock offset."""

    vehicle_id: str
    route: Route
    seed: int
    start_s_m: float
    stamp_offset_ns: int


def plan_fleet(
    town: Town,
    n_vehicles: int,
    *,
    seed: int = 0,
    route_length_m: float = 600.0,
    closed: bool = True,
    rate_hz: float = 10.0,
    shared: bool = False,
) -> list[FleetVehicle]:
    """Routes, seeds and start positions for ``n_vehicles`` vehicles.

    Closed routes are distinct rectangles of the street grid while there are enough of them
    (drawn among those closest to ``route_length_m``, then any); open routes are random walks from
    independent seeds. Each vehicle starts at a random arc length and its sweeps are staggered by
    ``vehicle / n_vehicles`` of a sweep period, as unsynchronised sensors would be.

    ``shared`` (closed routes): every vehicle drives the first vehicle's rectangle, the same way
    round, from the same start (a depot): each drives the streets the ones before it mapped
    (places shared between sessions; loops within a session after a lap). When each leaves is
    the caller's (``randt.clients.fleet``: one after another).
    """
    if n_vehicles < 1:
        raise ValueError("n_vehicles must be >= 1")
    if shared and not closed:
        raise ValueError("shared routes are closed")
    rng = np.random.default_rng([seed, 7919])
    period_ns = round(1e9 / rate_hz)
    vehicle_seeds = rng.integers(0, 2**31 - 1, n_vehicles)
    if closed:
        rects = _rectangles(town)
        order = np.argsort(
            np.abs(rects[:, 4] - route_length_m) + rng.uniform(0, 0.5 * town.pitch_m, len(rects))
        )
        picks = order[np.arange(n_vehicles) % order.size]
    fleet: list[FleetVehicle] = []
    for v in range(n_vehicles):
        vs = int(vehicle_seeds[v])
        vr = np.random.default_rng(vs)
        if shared and fleet:
            first = fleet[0]
            fleet.append(
                FleetVehicle(f"sim{v:03d}", first.route, vs, first.start_s_m, (v * period_ns) // n_vehicles)
            )
            continue
        if closed:
            i0, i1, j0, j1, _ = rects[picks[v]].astype(int)
            route = Route.rectangle(
                town, i0, i1, j0, j1, clockwise=bool(vr.random() < 0.5), start_corner=int(vr.integers(4))
            )
            start = float(vr.uniform(0.0, route.length_m))
        else:
            route = Route.random_walk(town, vs, length_m=route_length_m)
            start = 0.0
        fleet.append(FleetVehicle(f"sim{v:03d}", route, vs, start, (v * period_ns) // n_vehicles))
    return fleet


def simulate_fleet(
    town: Town,
    n_vehicles: int,
    *,
    n_scans: int,
    seed: int = 0,
    route_length_m: float = 600.0,
    closed: bool = True,
    rate_hz: float = 10.0,
    speed_mps: float = 10.0,
    lidar: Lidar64 | None = None,
    deskewed: bool = True,
    start_stamp_ns: int = 0,
    workers: int = 0,
) -> Iterator[tuple[str, SimScan]]:
    """Simulate ``n_vehicles`` vehicles (:func:`plan_fleet`): an iterator over their scans in stamp order.

    Returns
    -------
    Iterator[tuple[str, SimScan]]
        ``n_vehicles * n_scans`` pairs ``(vehicle_id, scan)``; round ``k`` gives every vehicle's
        scan ``k`` in vehicle order, which is stamp order because vehicle ``v`` is staggered by
        ``v / n_vehicles`` periods. With ``closed=False`` each random walk must be long enough for
        ``n_scans`` (ValueError at the call otherwise). ``workers``: per vehicle, as in
        :func:`simulate`.
    """
    fleet = plan_fleet(
        town, n_vehicles, seed=seed, route_length_m=route_length_m, closed=closed, rate_hz=rate_hz
    )
    streams = [
        simulate(
            town,
            v.route,
            n_scans=n_scans,
            rate_hz=rate_hz,
            speed_mps=speed_mps,
            seed=v.seed,
            lidar=lidar,
            deskewed=deskewed,
            start_s_m=v.start_s_m,
            start_stamp_ns=start_stamp_ns + v.stamp_offset_ns,
            workers=workers,
        )
        for v in fleet
    ]
    return _interleave([v.vehicle_id for v in fleet], streams, n_scans)


def _interleave(
    names: list[str], streams: list[Iterator[SimScan]], n_scans: int
) -> Iterator[tuple[str, SimScan]]:
    """Round-robin over the vehicles' scan streams."""
    for _ in range(n_scans):
        for name, stream in zip(names, streams, strict=True):
            yield name, next(stream)
