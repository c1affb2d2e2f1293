"""randt.core.io.atomic.append_durably: the fsync'd append of the pose and graph logs."""

from __future__ import annotations

import os

import pytest

import randt.core.io.atomic as atomic
from randt.core.errors import FormatError
from randt.core.io.atomic import append_durably


def test_appends_in_order_and_creates_the_file_and_its_directories(
    tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "a" / "b" / "log"
    synced: list[str] = []
    real = atomic.fsync_directory

    def spy(directory) -> None:
        synced.append(str(directory))
        real(directory)

    monkeypatch.setattr(atomic, "fsync_directory", spy)
    append_durably(path, b"one", new_dirs=2)
    append_durably(path, b"two", new_dirs=2)
    assert path.read_bytes() == b"onetwo"
    assert synced == [str(tmp_path / "a" / "b"), str(tmp_path / "a")]  # only when it was created


def test_a_failed_sync_cuts_the_file_back_and_says_so(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "log"
    append_durably(path, b"kept")

    def full(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(FormatError, match=r"cannot append to .*No space left"):
        append_durably(path, b"lost")
    monkeypatch.undo()
    assert path.read_bytes() == b"kept"
