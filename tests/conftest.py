"""Shared pytest fixtures.

Tests that need the real data set go through :func:`require_data` (also importable from
``tests.data``) or the ``data_dir`` fixture built on it: absent data skip with a clear reason,
except in CI (``CI=true``) where they fail.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from core.shared_data import DATA_DIR_ENV_VAR, data_root
from tests.data import require_data

__all__ = ["DATA_DIR_ENV_VAR", "data_dir", "data_root", "require_data"]


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared real-data directory (``$RANDT_SHARED_DATA`` or ``<repo>/../shared/data``)."""
    return require_data()
