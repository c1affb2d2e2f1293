"""The shared real data set for tests: skip when it is absent, or fail under ``CI=true``.

Where the data are and how to load them is :mod:`randt.core.shared_data`'s (the benchmarks read them
without pytest); this module only turns a missing file into a skip or, in CI, a failure.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn, ParamSpec, TypeVar

import pytest

from randt.core.errors import NotFoundError
from randt.core.shared_data import require

__all__ = ["require_data", "skip_if_missing"]

P = ParamSpec("P")
R = TypeVar("R")


def _skip_or_fail(message: str) -> NoReturn:
    if os.environ.get("CI") == "true":
        pytest.fail(message, pytrace=False)
    pytest.skip(message)


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
    try:
        return require(*relative_paths)
    except NotFoundError as exc:
        _skip_or_fail(str(exc))


def skip_if_missing(loader: Callable[P, R]) -> Callable[P, R]:
    """``loader`` (a :mod:`randt.core.shared_data` loader), skipping (failing in CI) on missing data."""

    @functools.wraps(loader)
    def wrapped(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return loader(*args, **kwargs)
        except NotFoundError as exc:
            _skip_or_fail(str(exc))

    return wrapped
