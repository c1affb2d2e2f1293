"""Tests for randt.wire.keys: every helper gives the exact key expressions of docs/wire-format.md."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from randt.wire.codes import ErrorCode
from randt.wire.keys import (
    ALL_CORRECTIONS,
    ALL_ERRORS,
    ALL_POSES,
    ALL_SCANS,
    ALL_TILES,
    correction_key,
    error_key,
    key_for,
    map_tiles_key,
    pose_key,
    scan_key,
    service_token_key,
    tile_key,
    tile_of_key,
    vehicle_of_scan_key,
)
from randt.wire.messages import (
    ErrorMessage,
    PoseMessage,
    correction_from_arrays,
    scan_from_arrays,
    tile_update_from_arrays,
)

DOC = Path(__file__).resolve().parents[2] / "docs" / "wire-format.md"

#: Each helper with the placeholders of the doc as arguments: it must spell the doc's template.
TEMPLATES = {
    "scan_key": scan_key("<vehicle>"),
    "pose_key": pose_key("<vehicle>"),
    "error_key": error_key("<vehicle>"),
    "correction_key": correction_key("<vehicle>"),
    "tile_key": tile_key("<map>", "<ix>_<iy>"),
    "map_tiles_key": map_tiles_key("<map>"),  # (a get with the tiles-near parameters)
    "service_token_key": service_token_key("<instance>"),
}


def doc_key_table() -> list[tuple[str, str]]:
    """``(key expression, declared by)`` of each row of the doc's key-expression table."""
    text = DOC.read_text(encoding="utf-8")
    section = text[text.index("\n## Key expressions\n") :]
    section = section[: section.index("\n## ", 1)]
    return [
        (m[1], m[2]) for m in re.finditer(r"^\| `([^`]+)` \|[^|]*\|[^|]*\|([^|]*)\|$", section, re.MULTILINE)
    ]


def test_every_documented_key_has_its_helper_and_back() -> None:
    documented = {key for key, _ in doc_key_table()}
    assert documented == set(TEMPLATES.values())
    assert TEMPLATES == {
        "scan_key": "randt/fleet/<vehicle>/scan",
        "pose_key": "randt/fleet/<vehicle>/pose",
        "error_key": "randt/fleet/<vehicle>/error",
        "correction_key": "randt/fleet/<vehicle>/correction",
        "tile_key": "randt/map/<map>/tile/<ix>_<iy>",
        "map_tiles_key": "randt/map/<map>/tile/*",
        "service_token_key": "randt/service/<instance>",
    }


def test_the_documented_wildcards() -> None:
    declared_by = " ".join(who for _, who in doc_key_table())
    wildcards = set(re.findall(r"`([^`]*\*[^`]*)`", declared_by))
    assert wildcards == {ALL_SCANS, ALL_TILES}
    assert ALL_SCANS == "randt/fleet/*/scan" and ALL_TILES == "randt/map/*/tile/*"
    assert ALL_POSES == "randt/fleet/*/pose" and ALL_ERRORS == "randt/fleet/*/error"
    assert ALL_CORRECTIONS == "randt/fleet/*/correction"
    assert map_tiles_key("default") == "randt/map/default/tile/*"


def test_helpers_with_the_doc_examples() -> None:
    assert scan_key("car-07") == "randt/fleet/car-07/scan"
    assert pose_key("car-07") == "randt/fleet/car-07/pose"
    assert error_key("bad") == "randt/fleet/bad/error"
    assert correction_key("car-07") == "randt/fleet/car-07/correction"
    assert tile_key("default", "5_-3") == "randt/map/default/tile/5_-3"
    assert service_token_key("randt-1") == "randt/service/randt-1"


def test_key_for_each_message() -> None:
    scan = scan_from_arrays("car-07", "s1", 0, 0, np.zeros((1, 3)))
    pose = PoseMessage(
        vehicle="car-07",
        session="s1",
        seq=0,
        stamp_ns=0,
        pose=np.eye(4),
        fitness=1.0,
        inlier_ratio=1.0,
        converged=True,
        status="first",
        latency_ms=1.0,
        map="default",
    )
    error = ErrorMessage(vehicle="car-07", session="?", code=ErrorCode.MALFORMED, reason="r")
    tile = tile_update_from_arrays("default", 5, -3, 1, np.zeros((2, 3)))
    assert key_for(scan) == "randt/fleet/car-07/scan"
    assert key_for(pose) == "randt/fleet/car-07/pose"
    assert key_for(error) == "randt/fleet/car-07/error"
    assert key_for(tile) == "randt/map/default/tile/5_-3"
    correction = correction_from_arrays(
        "car-07", "s1", "default", 1, np.zeros(1), np.eye(4)[None], np.eye(4)[None]
    )
    assert key_for(correction) == "randt/fleet/car-07/correction"
    with pytest.raises(TypeError, match="no key expression for dict"):
        key_for({"v": 1})  # type: ignore[arg-type]


def test_reading_received_keys_back() -> None:
    assert vehicle_of_scan_key(scan_key("car-07")) == "car-07"
    for key in (
        "randt/fleet/car-07/pose",
        "randt/fleet/scan",
        "other/fleet/car/scan",
        "randt/fleet/a/b/scan",
    ):
        with pytest.raises(ValueError, match="not a scan key"):
            vehicle_of_scan_key(key)
    assert tile_of_key(tile_key("default", "5_-3")) == ("default", "5_-3")
    assert tile_of_key(ALL_TILES) == ("*", "*")
    for key in (
        "randt/map/**",
        "randt/map/default/tile",
        "randt/map/default/tiles/0_0",
        "randt/map/a/tile/0/0",
    ):
        assert tile_of_key(key) is None


def test_a_tiles_near_selector_reads_back_and_bad_parameters_are_named() -> None:
    """The tiles-near query (docs/wire-format.md): what a selector says reads back the same; a
    parameter missing, not a number, not finite, a radius out of range or a bad ``have`` entry is
    ``invalid_field`` naming it."""
    from randt.core.errors import BadMessageError
    from randt.wire.keys import TilesNear, parse_tiles_near, tiles_near_selector

    selector = tiles_near_selector("default", 12.5, -3.0, 150.0, {"3_-4": 7, "0_0": 1})
    key, _, params = selector.partition("?")
    assert key == "randt/map/default/tile/*"
    assert parse_tiles_near(params) == TilesNear(12.5, -3.0, 150.0, {"3_-4": 7, "0_0": 1})
    assert parse_tiles_near("x=1;y=2;radius=0") == TilesNear(1.0, 2.0, 0.0)
    for bad, name in (
        ("x=1;y=2", "radius"),
        ("x=a;y=2;radius=3", "x"),
        ("x=1;y=nan;radius=3", "y"),
        ("x=1;y=2;radius=1001", "radius"),
        ("x=1;y=2;radius=-1", "radius"),
        ("x=1;y=2;radius=3;have=3_4", "have"),
        ("x=1;y=2;radius=3;have=a_4@2", "have"),
    ):
        with pytest.raises(BadMessageError, match=f"^{name}:") as info:
            parse_tiles_near(bad)
        assert info.value.code == "invalid_field"
