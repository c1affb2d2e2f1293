"""The simulated GNSS receiver: its error statistics are what its settings say."""

from __future__ import annotations

import numpy as np
import pytest

from randt.sim.gnss import GnssReceiver


def _errors(rx: GnssReceiver, seconds: float, rate_hz: float = 1.0) -> np.ndarray:
    fixes = [rx.fix(t, np.zeros(3)) for t in np.arange(0.0, seconds, 1.0 / rate_hz)]
    return np.array([f.error_xyz for f in fixes if f is not None])


def test_noise_and_bias_have_the_configured_spread_and_the_bias_wanders_slowly() -> None:
    rx = GnssReceiver(seed=1, noise_sigma_m=1.0, bias_sigma_m=2.0, bias_tau_s=60.0, jump_probability=0.0)
    e = _errors(rx, 20000.0)
    # horizontal: sqrt(1 + 4) = 2.24 m per axis; vertical twice that
    assert np.std(e[:, 0]) == pytest.approx(np.sqrt(5.0), rel=0.15)
    assert np.std(e[:, 2]) == pytest.approx(2 * np.sqrt(5.0), rel=0.15)
    # successive fixes 1 s apart share the bias: their differences are the noise only (sqrt 2 m)
    assert np.std(np.diff(e[:, 0])) == pytest.approx(np.sqrt(2.0 + 4.0 * 2 * (1 - np.exp(-1 / 60))), rel=0.1)
    fix = GnssReceiver(seed=1).fix(0.0, np.zeros(3))
    assert fix is not None and np.allclose(np.diag(fix.covariance), [5.0, 5.0, 20.0])


def test_outages_give_no_fix_and_jumps_are_marked() -> None:
    rx = GnssReceiver(seed=2, jump_probability=0.05, jump_m=15.0, outages=((10.0, 20.0),))
    fixes = [rx.fix(t, np.array([100.0, 0.0, 0.0])) for t in np.arange(0.0, 2000.0, 1.0)]
    assert all(f is None for f in fixes[10:20]) and all(f is not None for f in fixes[:10])
    jumped = [f for f in fixes if f is not None and f.jumped]
    assert 60 < len(jumped) < 140  # 5 % of 1990
    assert np.median([np.linalg.norm(f.error_xyz[:2]) for f in jumped]) > 10.0
    for f in fixes[:10]:
        assert f is not None and np.allclose(f.position_xyz - [100.0, 0.0, 0.0], f.error_xyz)


def test_time_must_not_go_back_and_settings_are_checked() -> None:
    rx = GnssReceiver(seed=0)
    rx.fix(5.0, np.zeros(3))
    with pytest.raises(ValueError, match="time went back"):
        rx.fix(4.0, np.zeros(3))
    with pytest.raises(ValueError, match="probability"):
        GnssReceiver(seed=0, jump_probability=2.0)
