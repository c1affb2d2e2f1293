"""A GNSS receiver for the simulated vehicles: metres of noise, a wandering bias, outages, jumps.

A fix at time t is the true antenna position (the sensor origin here) plus

    bias(t)   -> first-order Gauss-Markov per axis: correlation time ``bias_tau_s``, stationary
                 sigma ``bias_sigma_m`` (horizontal; vertical twice as large), as atmospheric and
                 orbit errors of a single-frequency receiver drift over minutes
    noise     -> white, ``noise_sigma_m`` horizontal and twice that vertical
    multipath -> with probability ``jump_probability`` per fix, an extra horizontal jump of
                 ``jump_m`` in a random direction (urban canyons)

and no fix at all inside an outage (tunnels, parking garages): ``outages`` as (start, end) times.
Each fix reports the covariance a receiver would: bias and noise variances together, not the
jumps (a receiver does not know it is being fooled). Everything is drawn from ``seed``, so a run
is reproducible and the errors are known exactly for the tests.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["GnssFix", "GnssReceiver"]


@dataclass(frozen=True)
class GnssFix:
    """One fix: ``position_xyz`` (world, m) with its reported 3x3 ``covariance``; ``error_xyz`` is
    the exact error (fix - truth), for scoring only."""

    t_s: float
    position_xyz: np.ndarray
    covariance: np.ndarray
    error_xyz: np.ndarray
    jumped: bool


@dataclass
class GnssReceiver:
    """A receiver model (module docstring); call :meth:`fix` with increasing times."""

    seed: int
    noise_sigma_m: float = 1.0
    bias_sigma_m: float = 2.0
    bias_tau_s: float = 60.0
    jump_probability: float = 0.01
    jump_m: float = 15.0
    outages: tuple[tuple[float, float], ...] = ()
    _rng: np.random.Generator = field(init=False, repr=False)
    _bias: np.ndarray = field(init=False, repr=False)
    _t: float | None = field(init=False, default=None, repr=False)

    def __post_init__(self) -> None:
        if min(self.noise_sigma_m, self.bias_sigma_m, self.bias_tau_s, self.jump_m) < 0 or not (
            0.0 <= self.jump_probability <= 1.0
        ):
            raise ValueError("GnssReceiver: sigmas, tau and jump size must be >= 0, probability in [0, 1]")
        self._rng = np.random.default_rng([self.seed, 4242])
        self._bias = self._rng.normal(0.0, 1.0, 3) * self._axis_scale(self.bias_sigma_m)

    @staticmethod
    def _axis_scale(sigma_m: float) -> np.ndarray:
        return np.array([sigma_m, sigma_m, 2.0 * sigma_m])

    def in_outage(self, t_s: float) -> bool:
        return any(a <= t_s < b for a, b in self.outages)

    def fix(self, t_s: float, true_position_xyz: np.ndarray) -> GnssFix | None:
        """The fix at ``t_s`` of a receiver at ``true_position_xyz``, or ``None`` in an outage."""
        if self._t is not None and t_s < self._t:
            raise ValueError(f"GnssReceiver.fix: time went back from {self._t} to {t_s}")
        dt = 0.0 if self._t is None else t_s - self._t
        self._t = t_s
        # Gauss-Markov: exact discretisation over dt (advances through outages too).
        phi = np.exp(-dt / self.bias_tau_s) if self.bias_tau_s > 0 else 0.0
        self._bias = phi * self._bias + np.sqrt(1.0 - phi**2) * self._rng.normal(
            0.0, 1.0, 3
        ) * self._axis_scale(self.bias_sigma_m)
        noise = self._rng.normal(0.0, 1.0, 3) * self._axis_scale(self.noise_sigma_m)
        jumped = bool(self._rng.random() < self.jump_probability)
        angle = self._rng.uniform(0.0, 2.0 * np.pi)
        if self.in_outage(t_s):
            return None
        error = self._bias + noise
        if jumped:
            error = error + self.jump_m * np.array([np.cos(angle), np.sin(angle), 0.0])
        variance = self._axis_scale(self.noise_sigma_m) ** 2 + self._axis_scale(self.bias_sigma_m) ** 2
        return GnssFix(
            t_s=float(t_s),
            position_xyz=np.asarray(true_position_xyz, dtype=np.float64) + error,
            covariance=np.diag(variance),
            error_xyz=error,
            jumped=jumped,
        )
