"""Tests for randt.wire.codes: the error codes of docs/wire-format.md are exactly the ErrorCode members."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import msgpack

from randt.wire.codes import CODE_REGEX, DECODE_CODES, SERVICE_CODES, ErrorCode
from randt.wire.messages import SCHEMA_VERSION, ErrorMessage, decode_error, encode

REPO = Path(__file__).resolve().parents[2]
DOC = REPO / "docs" / "wire-format.md"


def doc_code_tables() -> list[list[str]]:
    """The codes of each table in the doc's "Error codes" section (first column), table by table."""
    text = DOC.read_text(encoding="utf-8")
    section = text[text.index("\n## Error codes\n") :]
    section = section[: section.index("\n## ", 1)]
    blocks = re.findall(r"(?:^\|.*\n)+", section, flags=re.MULTILINE)
    return [re.findall(r"^\| `([^`]+)` \|", block, flags=re.MULTILINE) for block in blocks]


def test_the_doc_lists_exactly_the_members() -> None:
    decode_table, service_table = doc_code_tables()
    assert set(decode_table) == {c.value for c in DECODE_CODES}
    assert set(service_table) == {c.value for c in SERVICE_CODES}
    assert sorted(decode_table + service_table) == sorted(c.value for c in ErrorCode)


def test_the_families_partition_the_codes() -> None:
    assert not set(DECODE_CODES) & set(SERVICE_CODES)
    assert set(DECODE_CODES) | set(SERVICE_CODES) == set(ErrorCode)
    assert all(meaning for meaning in [*DECODE_CODES.values(), *SERVICE_CODES.values()])


def test_members_are_their_strings() -> None:
    assert ErrorCode.DROPPED == "dropped" and str(ErrorCode.DROPPED) == "dropped"
    assert f"{ErrorCode.SESSIONS_FULL}" == "sessions_full"
    assert {"dropped": 1}.get(ErrorCode.DROPPED) == 1
    for code in ErrorCode:
        assert code.value == code.name.lower()
        assert re.fullmatch(CODE_REGEX, code), code


def test_a_member_goes_on_the_wire_as_its_plain_string() -> None:
    message = ErrorMessage(vehicle="car", session="s", seq=3, code=ErrorCode.DROPPED, reason="full")
    reference = {
        "v": SCHEMA_VERSION,
        "vehicle": "car",
        "session": "s",
        "seq": 3,
        "code": "dropped",
        "reason": "full",
    }
    assert encode(message) == msgpack.packb(reference, use_bin_type=True)
    got = decode_error(encode(message))
    assert type(got.code) is str and got.code == ErrorCode.DROPPED


def _code_literals(path: Path) -> list[tuple[int, str]]:
    """String constants equal to an error code, except inside f-string replacement fields (column
    titles such as ``{'dropped':>7}``, counters such as ``{stats['dropped']}``)."""
    values = {c.value for c in ErrorCode}
    tree = ast.parse(path.read_text(encoding="utf-8"))
    formatted = {
        id(inner) for n in ast.walk(tree) if isinstance(n, ast.FormattedValue) for inner in ast.walk(n)
    }
    return [
        (n.lineno, n.value)
        for n in ast.walk(tree)
        if isinstance(n, ast.Constant) and n.value in values and id(n) not in formatted
    ]


def test_no_code_is_spelled_as_a_literal_outside_wire_codes() -> None:
    found = [
        f"{path.relative_to(REPO)}:{line}: {value!r}"
        for folder in ("wire", "service", "clients")
        for path in sorted((REPO / folder).rglob("*.py"))
        if path != REPO / "wire" / "codes.py"
        for line, value in _code_literals(path)
    ]
    assert not found, "use randt.wire.codes.ErrorCode: " + ", ".join(found)
