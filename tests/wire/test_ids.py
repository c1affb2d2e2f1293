"""Tests for randt.wire.ids: the one id rule accepts and rejects exactly what the four old copies did."""

from __future__ import annotations

import re
from typing import Annotated

import pytest
from pydantic import Field, TypeAdapter, ValidationError

from randt.wire.ids import (
    ID_MAX_LENGTH,
    ID_PATTERN,
    ID_REGEX,
    UNKNOWN_ID,
    UNSAFE_ID_SAMPLES,
    is_valid_id,
    validate_id,
)
from randt.wire.messages import WireLimits

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


# -- session-map names (issue 13, defect 3: "col.a"+"b" and "col"+"a.b" shared map "col.a.b") ------


def _ids_over(alphabet: str, max_len: int) -> list[str]:
    import itertools

    out = []
    for n in range(1, max_len + 1):
        out += ["".join(p) for p in itertools.product(alphabet, repeat=n)]
    return [s for s in out if is_valid_id(s)]


def test_session_map_names_are_injective_over_every_short_id_of_the_risky_characters() -> None:
    from randt.wire.ids import session_map_name, session_of_map_name

    ids = _ids_over("a_.-", 4)  # every valid id of up to 4 chars from the characters that escape
    assert len(ids) == 85
    names: dict[str, tuple[str, str]] = {}
    for v in ids:
        for s in ids:
            name = session_map_name(v, s)
            assert is_valid_id(name) and "." in name
            assert name not in names, f"{(v, s)} and {names[name]} share map {name}"
            names[name] = (v, s)
            assert session_of_map_name(name) == (v, s)
    assert len(names) == 85 * 85


def test_the_collision_of_the_issue_is_gone_and_plain_ids_keep_their_names() -> None:
    from randt.wire.ids import legacy_session_map_name, session_map_name

    assert legacy_session_map_name("col.a", "b") == legacy_session_map_name("col", "a.b") == "col.a.b"
    assert session_map_name("col.a", "b") == "col_-a.b"
    assert session_map_name("col", "a.b") == "col.a.b"
    assert session_map_name("car-07", "d1") == "car-07.d1"  # README's example, unchanged
    assert session_map_name("car_7", "d1") == "car__7.d1"


def test_long_ids_get_a_hashed_name_that_no_unhashed_name_can_equal() -> None:
    from randt.wire.ids import session_map_name, session_of_map_name

    long_pairs = [
        ("x" * 64, "y" * 64),
        ("x" * 64, "y" * 63),
        ("a" + "_" * 63, "s"),
        ("a" + "." * 63, "s"),
        ("ab." * 21 + "a", "s"),
        ("v" * 40, "s" * 30),
    ]
    names = {session_map_name(v, s) for v, s in long_pairs}
    assert len(names) == len(long_pairs)
    for name in names:
        assert is_valid_id(name) and len(name) <= ID_MAX_LENGTH
        head, _, digest = name.partition(".")
        assert len(digest) == 24 and int(digest, 16) >= 0
        assert head.endswith("_") and (len(head) - len(head.rstrip("_"))) % 2 == 1  # the unpaired marker
        assert session_of_map_name(name) is None
    # ...while every unhashed name's part before its first dot is a whole escape (even "_" runs)
    for v in _ids_over("a_.-", 3):
        head = session_map_name(v, "s").partition(".")[0]
        runs = re.findall(r"_+(?=[^_-]|$)", head)
        assert all(len(r) % 2 == 0 for r in runs), (v, head)


def test_session_map_name_refuses_invalid_ids() -> None:
    from randt.wire.ids import session_map_name

    for bad in ("", "a/b", "..", "*"):
        with pytest.raises(ValueError, match="invalid"):
            session_map_name(bad, "s")
        with pytest.raises(ValueError, match="invalid"):
            session_map_name("v", bad)
