"""Tests for wire.ids: the one id rule accepts and rejects exactly what the four old copies did."""

from __future__ import annotations

import re
from typing import Annotated

import pytest
from pydantic import Field, TypeAdapter, ValidationError

from wire.ids import (
    ID_MAX_LENGTH,
    ID_PATTERN,
    ID_REGEX,
    UNKNOWN_ID,
    UNSAFE_ID_SAMPLES,
    is_valid_id,
    validate_id,
)
from wire.messages import WireLimits

#: The regular expression spelled, before the wire package, in core/wire.py (WireLimits.id_pattern),
#: service/store.py (NAME_PATTERN, plus a check against "." and ".."), service/settings.py (instance,
#: default_map) and, through NAME_PATTERN, service/api/deps.py (path parameters, max_length=64).
OLD_REGEX = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"

ACCEPTED = [
    "a",
    "0",
    "car-07",
    "Car_1.rev-2",
    "2024-05-01.a",
    "20260501-142233",
    "randt-1",
    "default",
    "car-07.20260501-142233",
    "a..b",
    "a.",
    "a-",
    "x" * 64,
]

REJECTED = [
    "",
    ".",
    "..",
    "../etc",
    "a/b",
    "car/7",
    "/abs",
    "a\\b",
    ".hidden",
    "-dash",
    "_under",
    "has space",
    "a b",
    "nul\x00",
    "newline\n",
    "a\nb",
    "caf\u00e9",
    "x" * 65,
    "*",
    "**",
    "$*",
    "a?b",
    "a#b",
    "a*",
    UNKNOWN_ID,
]


def _old_store_rule(name: str) -> bool:
    """service/store.py's validate_name before the move, as a predicate."""
    return name not in (".", "..") and re.compile(OLD_REGEX).fullmatch(name) is not None


def test_the_rule_is_the_old_regex() -> None:
    assert ID_REGEX == OLD_REGEX
    assert ID_PATTERN.pattern == OLD_REGEX
    assert ID_MAX_LENGTH == 64
    assert WireLimits().id_pattern == ID_REGEX


@pytest.mark.parametrize("name", ACCEPTED)
def test_accepted_ids(name: str) -> None:
    assert is_valid_id(name)
    assert validate_id(name, "map") == name
    assert WireLimits().id_ok(name)
    assert _old_store_rule(name) and re.fullmatch(OLD_REGEX, name)


@pytest.mark.parametrize("name", REJECTED)
def test_rejected_ids(name: str) -> None:
    assert not is_valid_id(name)
    with pytest.raises(ValueError, match=f"invalid vehicle name {re.escape(repr(name))}"):
        validate_id(name, "vehicle")
    assert not WireLimits().id_ok(name)
    assert not _old_store_rule(name) and not re.fullmatch(OLD_REGEX, name)


@pytest.mark.parametrize("name", ACCEPTED + REJECTED)
def test_pydantic_pattern_agrees(name: str) -> None:
    """Settings and HTTP path parameters check ids with pydantic's (Rust) regex engine, whose ``$``
    does not match before a final newline the way Python's does: it must agree all the same."""
    adapter = TypeAdapter(Annotated[str, Field(pattern=ID_REGEX, max_length=ID_MAX_LENGTH)])
    try:
        adapter.validate_python(name)
        accepted = True
    except ValidationError:
        accepted = False
    assert accepted == is_valid_id(name)


def test_non_strings_are_not_ids() -> None:
    for value in (None, 7, b"car", ["car"]):
        assert not is_valid_id(value)
    with pytest.raises(ValueError, match="map name must be a string, got bytes"):
        validate_id(b"car", "map")


def test_unsafe_samples_are_rejected_by_the_rule() -> None:
    assert all(not is_valid_id(sample) for sample in UNSAFE_ID_SAMPLES)
    assert set(UNSAFE_ID_SAMPLES) <= set(REJECTED)
