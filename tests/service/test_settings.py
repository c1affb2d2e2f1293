"""The service's settings reach every session's matcher: ``RANDT_MATCHER__<FIELD>`` and
``RANDT_REGISTRATION__<FIELD>`` (pydantic-settings' nested delimiter) change what the matchers use,
in the session threads and in the matcher processes."""

from __future__ import annotations

import time

import numpy as np
import pytest

from randt.core.config import RegistrationSettings
from randt.core.odometry import MATCHER_REGISTRATION, IncrementalMatcher, MatcherSettings
from randt.service.metrics import ServiceMetrics
from randt.service.sessions import SessionManager
from randt.service.settings import ServiceSettings
from randt.service.store import Store
from randt.wire.messages import ErrorMessage, PoseMessage, encode, scan_from_arrays
from tests.service.test_matchers import _sweeps


def test_the_defaults_are_the_matchers_own() -> None:
    settings = ServiceSettings()
    assert settings.matcher == MatcherSettings()
    assert settings.registration == MATCHER_REGISTRATION
    assert not settings.registration.select_moving_points and not settings.registration.svd_refinement
    # and a matcher given them explicitly (as the service now does) matches as one given none
    sweeps = [s.astype(np.float64) for s in _sweeps(4)]
    default, configured = IncrementalMatcher(), IncrementalMatcher(settings.matcher, settings.registration)
    for xyz in sweeps:
        a, b = default.register_scan(xyz), configured.register_scan(xyz)
        np.testing.assert_array_equal(b.T_world_sensor, a.T_world_sensor)


def test_nested_environment_variables(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RANDT_MATCHER__MAX_RANGE_M", "80")
    monkeypatch.setenv("RANDT_MATCHER__RETRY_YAW_DEG", "[3, 6, 9]")
    monkeypatch.setenv("RANDT_REGISTRATION__MAX_ITERATIONS", "12")
    monkeypatch.setenv("RANDT_MAX_SESSIONS", "3")  # the flat ones are unchanged
    settings = ServiceSettings()
    assert settings.matcher == MatcherSettings(max_range_m=80.0, retry_yaw_deg=(3.0, 6.0, 9.0))
    # one registration field given: the others keep the matcher's defaults, not pairwise registration's
    assert settings.registration == MATCHER_REGISTRATION.model_copy(update={"max_iterations": 12})
    assert RegistrationSettings().svd_refinement and not settings.registration.svd_refinement
    assert settings.max_sessions == 3
    monkeypatch.setenv("RANDT_MATCHER__MAX_RANGE_M", "-1")
    with pytest.raises(ValueError, match="max_range_m"):
        ServiceSettings()  # the matcher's own validators hold
    monkeypatch.setenv("RANDT_MATCHER__MAX_RANGE_M", "80")
    monkeypatch.setenv("RANDT_MATCHER__NO_SUCH_FIELD", "1")
    with pytest.raises(ValueError, match="no_such_field"):
        ServiceSettings()


@pytest.mark.parametrize("processes", [0, 1], ids=["session-thread", "matcher-process"])
def test_an_environment_variable_changes_what_a_sessions_matcher_uses(
    monkeypatch: pytest.MonkeyPatch, tmp_path, processes: int
) -> None:
    """Keyframes every 0.1 m (sweeps 0.3 m apart: each one a keyframe, against one keyframe by
    default) and NDT levels (4, 2, 1) m (against (11.2, ..., 0.7) m derived from the first sweep),
    read back from the session's matcher state, which a matcher process sends over its pipe."""
    monkeypatch.setenv("RANDT_MATCHER__KEYFRAME_DISTANCE_M", "0.1")
    monkeypatch.setenv("RANDT_REGISTRATION__VOXEL_SIZES_M", "[4, 2, 1]")
    settings = ServiceSettings(data_dir=tmp_path, matcher_processes=processes, flush_interval_s=0.2)
    out: list[object] = []
    mgr = SessionManager(settings, Store(tmp_path), out.append, ServiceMetrics())
    try:
        for seq, sweep in enumerate(_sweeps(4)):
            mgr.submit("v", encode(scan_from_arrays("v", "s", seq, seq * 100_000_000, sweep)))
        deadline = time.monotonic() + 60
        while len([m for m in out if isinstance(m, PoseMessage | ErrorMessage)]) < 4:
            assert time.monotonic() < deadline, out
            time.sleep(0.05)
        assert all(isinstance(m, PoseMessage) for m in out if isinstance(m, PoseMessage | ErrorMessage))
        worker = mgr.worker("v", "s")
        # the session's worker rebuilds the keyframe model after the pose is out, under its lock:
        # read the state under it too (state_dict folds in whatever is still pending)
        with worker.lock:
            state = worker.matcher.state_dict()
        np.testing.assert_array_equal(state["levels"], [4.0, 2.0, 1.0])
        assert len(state["keyframe_sizes"]) == 4
    finally:
        mgr.stop()


def test_every_session_matches_at_ndt_levels_tied_to_the_map_voxel(monkeypatch: pytest.MonkeyPatch) -> None:
    """Finest level 5 map voxels unless levels are given or the tie is switched off (then the
    matcher derives them from a session's first sweep, as `randt map` does)."""
    for var in ("RANDT_MATCHER__VOXEL_SIZES_M", "RANDT_REGISTRATION__VOXEL_SIZES_M"):
        monkeypatch.delenv(var, raising=False)
    np.testing.assert_allclose(ServiceSettings().session_matcher().voxel_sizes_m, (16, 8, 4, 2, 1))
    np.testing.assert_allclose(
        ServiceSettings(map_voxel_m=0.1).session_matcher().voxel_sizes_m, (8, 4, 2, 1, 0.5)
    )
    assert ServiceSettings(ndt_levels_from_map=False).session_matcher().voxel_sizes_m is None
    monkeypatch.setenv("RANDT_MATCHER__VOXEL_SIZES_M", "[4, 2]")
    assert ServiceSettings().session_matcher().voxel_sizes_m == (4.0, 2.0)
