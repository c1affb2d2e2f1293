"""Shared pytest fixtures.

Tests that need the real data set go through :func:`require_data` (also importable from
``tests.data``) or the ``data_dir`` fixture built on it: absent data skip with a clear reason,
except in CI (``CI=true``) where they fail.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from core.shared_data import DATA_DIR_ENV_VAR, data_root
from tests.data import require_data

__all__ = ["DATA_DIR_ENV_VAR", "data_dir", "data_root", "require_data"]

# Admission by measured capacity (service/capacity.py) admits what this machine's measured CPU
# allows, so a test of anything else that opens several sessions at once would pass or fail by the
# machine's speed: tests run without it (as with a count limit) unless they ask for it, as
# tests/service/test_admission.py does; bench/service.py measures it on the real service. Services
# the tests start as child processes inherit it.
os.environ.setdefault("RANDT_CAPACITY_TARGET", "0")


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared real-data directory (``$RANDT_SHARED_DATA`` or ``<repo>/../shared/data``)."""
    return require_data()
