"""The paper's robustness protocol on its own scans (``randt_velodyne/``), see :mod:`randt.core.trials`."""

from __future__ import annotations

import numpy as np

from randt.core.io import read_cloud
from randt.core.registration import register
from randt.core.transforms import transform_error
from randt.core.trials import make_trial
from tests.data import require_data

N_TRIALS = 20


def test_randt_recovers_known_transforms_in_95_percent_of_trials() -> None:
    """Up to 2 m / 10 deg, noise 1-5 cm, 10 % outliers, 50 % overlap: 5 cm and 0.5 deg in >= 95 %."""
    root = require_data("randt_velodyne/velodyne")
    files = sorted((root / "randt_velodyne/velodyne").glob("*.bin"))
    assert len(files) == 10
    rng = np.random.default_rng(2026)
    errors = []
    for i in range(N_TRIALS):
        trial = make_trial(read_cloud(files[i % len(files)]).xyz, rng)
        result = register(trial.source_xyz, trial.target_xyz)
        errors.append(transform_error(result.T_target_source, trial.T_true))
    err = np.array(errors)
    success = (err[:, 0] < 0.05) & (err[:, 1] < 0.5)
    assert success.mean() >= 0.95, f"success {success.mean():.0%}, errors (m, deg):\n{err}"
    # The typical trial is far better than the threshold.
    assert np.median(err[:, 0]) < 0.02 and np.median(err[:, 1]) < 0.1


def test_protocol_trial_has_the_promised_shape() -> None:
    root = require_data("randt_velodyne/velodyne/000038.bin")
    scan = read_cloud(root / "randt_velodyne/velodyne/000038.bin").xyz
    trial = make_trial(scan, np.random.default_rng(0))
    n_moving = trial.source_xyz.shape[0] / 1.1
    assert 0.01 <= trial.noise_sigma_m <= 0.05
    assert abs(trial.target_xyz.shape[0] / scan.shape[0] - 0.75) < 0.2  # 270 of 360 degrees
    assert abs(n_moving / scan.shape[0] - 0.75) < 0.2
    t = np.linalg.norm(trial.T_true[:3, 3])
    angle = np.degrees(np.arccos((np.trace(trial.T_true[:3, :3]) - 1) / 2))
    assert t <= 2.0 and angle <= 10.0
