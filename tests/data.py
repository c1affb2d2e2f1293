"""Locate the shared real data set for tests, skipping (or, in CI, failing) when it is absent.

The data live outside the repository (never copy them in): ``$RANDT_SHARED_DATA`` if set, else
``<repo root>/../shared/data``. See ``../shared/data/README.md`` for what each folder holds.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

__all__ = ["DATA_DIR_ENV_VAR", "data_root", "require_data"]

DATA_DIR_ENV_VAR = "RANDT_SHARED_DATA"
_REPO_ROOT = Path(__file__).resolve().parents[1]


def data_root() -> Path:
    """Return where the shared data should be: ``$RANDT_SHARED_DATA`` or ``<repo>/../shared/data``."""
    override = os.environ.get(DATA_DIR_ENV_VAR)
    if override:
        return Path(override).expanduser().resolve()
    return (_REPO_ROOT.parent / "shared" / "data").resolve()


def require_data(*relative_paths: str) -> Path:
    """Return the data directory if it and every ``relative_paths`` entry in it exist.

    Parameters
    ----------
    *relative_paths:
        Files or folders relative to the data directory, e.g. ``"kitti00/poses.txt"``.

    Returns
    -------
    Path
        The data directory.

    Notes
    -----
    When something is missing the calling test is skipped with a reason naming the missing path
    and ``$RANDT_SHARED_DATA``; when ``CI=true`` it fails instead, because CI always has the data.
    """
    root = data_root()
    missing = [p for p in ("", *relative_paths) if not (root / p).exists()]
    if missing:
        first = root / missing[0]
        message = (
            f"real test data missing: {first} does not exist (set {DATA_DIR_ENV_VAR} to the "
            f"shared data directory; without it the default is <repo root>/../shared/data)"
        )
        if os.environ.get("CI") == "true":
            pytest.fail(message, pytrace=False)
        pytest.skip(message)
    return root
