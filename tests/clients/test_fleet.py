"""The fleet summary's error definitions on trajectories with known errors, and its table."""

from __future__ import annotations

import numpy as np

from randt.clients.fleet import TABLE_HEADER, FleetSettings, evaluate, summary_table


def _line(n: int = 11, step_m: float = 1.0) -> dict[int, np.ndarray]:
    poses = {}
    for k in range(n):
        T = np.eye(4)
        T[0, 3] = k * step_m
        poses[k] = T
    return poses


def test_constant_offset_is_ate_without_drift() -> None:
    truth = _line()
    est = {k: T.copy() for k, T in truth.items()}
    for T in est.values():
        T[1, 3] += 0.10
    e = evaluate(truth, est)
    assert e is not None
    assert np.isclose(e.ate_m, 0.10) and np.isclose(e.path_length_m, 10.0)
    assert np.isclose(e.rpe_cm, 0.0, atol=1e-9) and np.isclose(e.drift_pct, 0.0, atol=1e-9)
    assert e.kitti_pct is None, "KITTI segments need more than 100 m"


def test_scale_error_is_drift() -> None:
    truth = _line()
    est = {k: T.copy() for k, T in truth.items()}
    for T in est.values():
        T[0, 3] *= 1.01  # 1 cm too far per metre
    e = evaluate(truth, est)
    assert e is not None
    assert np.isclose(e.drift_pct, 1.0) and np.isclose(e.rpe_cm, 1.0)
    assert np.isclose(e.ate_m, np.sqrt(np.mean((0.01 * np.arange(11)) ** 2)))


def test_only_common_scans_count_and_too_few_give_none() -> None:
    truth = _line()
    est = {k: truth[k] for k in (0, 1, 5, 9)}
    e = evaluate(truth, est)
    assert e is not None and e.n_poses == 4 and np.isclose(e.path_length_m, 9.0)
    assert evaluate(truth, {0: truth[0], 1: truth[1]}) is None


def test_table_adds_service_drops_to_dropped() -> None:
    summary = {
        "vehicle": "sim000",
        "gnss": "none",
        "scans": 20,
        "stats": {
            "acknowledged": 17,
            "rejected": 3,
            "dropped": 1,
            "lost": 0,
            "rejected_codes": {"dropped": 2},
        },
        "errors": {
            "n_fallback": 1,
            "path_length_m": 11.4,
            "ate_m": 0.0123,
            "aligned": True,
            "rpe_cm": 0.5,
            "rpe_deg": 0.01,
            "drift_pct": 0.2,
        },
    }
    header, row = summary_table([summary])
    assert header == TABLE_HEADER
    assert row.split() == [
        *("sim000", "none", "20", "17", "1", "1", "3", "0", "11.4", "0.012*", "0.50", "0.010", "0.20")
    ]
    assert FleetSettings(duration_s=2.0).n_scans == 20
