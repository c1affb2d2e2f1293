"""Tests for randt.wire.messages: round trips, one crafted payload per error code, fuzzing, peeking."""

from __future__ import annotations

import hashlib
import logging
import re
import time
from pathlib import Path
from typing import Any, get_args

import msgpack
import numpy as np
import pytest
from pydantic import ValidationError

from randt.core.errors import BadMessageError
from randt.core.transforms import make_transform
from randt.wire.codes import DECODE_CODES
from randt.wire.messages import (
    SCHEMA_VERSION,
    ErrorMessage,
    PoseMessage,
    ScanMessage,
    SchemaVersion,
    TileUpdateMessage,
    WireLimits,
    decode_error,
    decode_pose,
    decode_scan,
    decode_tile_update,
    encode,
    encode_scan_v2,
    matrix_to_pose,
    peek_ids,
    peek_seq,
    pose_to_matrix,
    scan_from_arrays,
    tile_update_from_arrays,
    tile_update_from_table,
)

DOC = Path(__file__).resolve().parents[2] / "docs" / "wire-format.md"
DROP = object()  # marks a key to remove from a crafted message


def pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def f32(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype="<f4").tobytes()


def scan_dict(n: int = 20, **overrides: Any) -> dict[str, Any]:
    """A valid scan as the raw msgpack map, with fields replaced (or dropped with ``DROP``)."""
    rng = np.random.default_rng(3)
    obj: dict[str, Any] = {
        "v": SCHEMA_VERSION,
        "vehicle": "car-07",
        "session": "2024-05-01.a",
        "seq": 12,
        "stamp_ns": 1_714_550_000_000_000_000,
        "fields": "xyz",
        "points": f32(rng.uniform(-30.0, 30.0, size=(n, 3))),
    }
    obj.update(overrides)
    return {k: v for k, v in obj.items() if v is not DROP}


def prior_dict(T: np.ndarray | None = None, C: np.ndarray | None = None) -> dict[str, Any]:
    T = make_transform([0.1, -0.2, 0.3], [10.0, 20.0, 1.5]) if T is None else T
    C = np.diag([0.04, 0.04, 0.09, 1e-4, 1e-4, 4e-4]) if C is None else C
    return {"pose": T.ravel().tolist(), "covariance": C.ravel().tolist()}


def rejected(payload: bytes, decoder=decode_scan, limits: WireLimits | None = None) -> BadMessageError:
    with pytest.raises(BadMessageError) as info:
        decoder(payload, limits)
    return info.value


def base_of(array: np.ndarray) -> object:
    while isinstance(array, np.ndarray) and array.base is not None:
        array = array.base
    return array


# --------------------------------------------------------------------------------------------
# round trips
# --------------------------------------------------------------------------------------------


def test_scan_round_trip_with_every_optional_field() -> None:
    rng = np.random.default_rng(0)
    n = 1000
    xyz = rng.uniform(-80.0, 80.0, size=(n, 3)).astype(np.float32)
    intensity = rng.uniform(0.0, 255.0, size=n).astype(np.float32)
    offsets = np.sort(rng.uniform(0.0, 0.1, size=n)).astype(np.float32)
    T = make_transform([0.01, 0.02, 1.2], [105.0, -42.0, 3.0])
    C = np.diag([0.5, 0.5, 1.0, 1e-3, 1e-3, 5e-3])
    C[0, 1] = C[1, 0] = 0.1
    sent = scan_from_arrays("car-07", "s1", 5, 1_700_000_000_123_456_789, xyz, intensity, offsets, T, C)
    got = decode_scan(encode(sent), WireLimits())

    assert isinstance(got, ScanMessage) and got == sent
    assert (got.vehicle, got.session, got.seq, got.stamp_ns, got.fields) == (
        "car-07",
        "s1",
        5,
        1_700_000_000_123_456_789,
        "xyzi",
    )
    assert got.n_points == n
    assert got.xyz().dtype == np.float64 and got.xyz().shape == (n, 3)
    np.testing.assert_array_equal(got.xyz(), xyz.astype(np.float64))
    assert got.intensity().dtype == np.float32
    np.testing.assert_array_equal(got.intensity(), intensity)
    np.testing.assert_array_equal(got.time_offset_s(), offsets.astype(np.float64))
    np.testing.assert_array_equal(got.prior_pose(), T)
    np.testing.assert_array_equal(got.prior_covariance(), C)
    cloud = got.to_cloud()
    np.testing.assert_array_equal(cloud.xyz, xyz.astype(np.float64))
    np.testing.assert_array_equal(cloud.time_offset_s, offsets.astype(np.float64))


def test_encode_writes_the_documented_v1_maps() -> None:
    """The exact bytes: each message is the msgpack map of docs/wire-format.md, keys in the order of
    its tables and ``v`` = 1 first, so a v1 sender or receiver written from the doc keeps working."""
    xyz = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    T = make_transform([0.0, 0.0, 0.5], [105.2, -42.7, 1.9])
    C = np.diag([0.04, 0.04, 0.09, 1e-4, 1e-4, 4e-4])
    scan = scan_from_arrays("car-07", "2024-05-01.a", 1842, 17, xyz, np.ones(2), np.zeros(2), T, C)
    assert encode(scan) == pack(
        {
            "v": 1,
            "vehicle": "car-07",
            "session": "2024-05-01.a",
            "seq": 1842,
            "stamp_ns": 17,
            "fields": "xyzi",
            "points": f32(np.c_[xyz, np.ones(2)]),
            "time_offsets": f32(np.zeros(2)),
            "prior": {"pose": T.ravel().tolist(), "covariance": C.ravel().tolist()},
        }
    )
    bare = scan_from_arrays("car-07", "s", 0, 0, xyz)
    assert encode(bare) == pack(
        {
            "v": 1,
            "vehicle": "car-07",
            "session": "s",
            "seq": 0,
            "stamp_ns": 0,
            "fields": "xyz",
            "points": f32(xyz),
            "time_offsets": None,
            "prior": None,
        }
    )
    pose_fields = {
        "vehicle": "car-07",
        "session": "s",
        "seq": 3,
        "stamp_ns": 17,
        "pose": T.ravel().tolist(),
        "fitness": 2.41,
        "inlier_ratio": 0.93,
        "converged": True,
        "status": "ok",
        "covariance": None,
        "latency_ms": 38.5,
        "map": "default",
    }
    assert encode(PoseMessage(**pose_fields)) == pack({"v": 1, **pose_fields})
    error = ErrorMessage(vehicle="car-07", session="?", code="malformed", reason="why")
    assert encode(error) == pack(
        {"v": 1, "vehicle": "car-07", "session": "?", "seq": None, "code": "malformed", "reason": "why"}
    )
    tile = tile_update_from_arrays("default", 5, -3, 12, xyz, np.array([7.0, 8.0]))
    assert encode(tile) == pack(
        {
            "v": 1,
            "map": "default",
            "tile": "5_-3",
            "ix": 5,
            "iy": -3,
            "version": 12,
            "bounds": {"min": (1.0, 2.0, 3.0), "max": (4.0, 5.0, 6.0)},
            "n_points": 2,
            "points": f32(np.c_[xyz, [7.0, 8.0]]),
            "digest": hashlib.sha256(f32(np.c_[xyz, [7.0, 8.0]])).hexdigest()[:16],
        }
    )


def test_schema_version_is_the_only_accepted_v() -> None:
    assert SCHEMA_VERSION == 1
    assert get_args(SchemaVersion) == (SCHEMA_VERSION,)
    for model in (ScanMessage, PoseMessage, ErrorMessage, TileUpdateMessage):
        assert model.model_fields["v"].default == SCHEMA_VERSION
    with pytest.raises(ValidationError):
        ErrorMessage(v=SCHEMA_VERSION + 1, vehicle="car", session="s", code="malformed", reason="r")


def test_scan_points_are_views_of_the_unpacked_bytes() -> None:
    xyz = np.arange(30, dtype=np.float32).reshape(10, 3)
    got = decode_scan(encode(scan_from_arrays("car", "s", 0, 0, xyz, intensity=np.ones(10))))
    table = got.points_f32()
    assert table.shape == (10, 4) and table.dtype == np.dtype("<f4")
    assert base_of(table) is got.points and base_of(got.intensity()) is got.points
    assert not table.flags.writeable


def test_scan_without_optional_fields() -> None:
    xyz = np.array([[1.0, 2.0, 3.0], [-4.5, 5.25, 0.0]])
    got = decode_scan(encode(scan_from_arrays("car", "s", 0, 0, xyz)))
    assert got.fields == "xyz" and len(got.points) == 24
    np.testing.assert_array_equal(got.xyz(), xyz)
    assert got.intensity() is None and got.time_offset_s() is None
    assert got.prior_pose() is None and got.prior_covariance() is None


def test_pose_round_trip() -> None:
    T = make_transform([0.3, -0.1, 2.0], [1234.5, -987.25, 12.0])
    cov = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6])
    sent = PoseMessage(
        vehicle="car-07",
        session="s1",
        seq=99,
        stamp_ns=123,
        pose=matrix_to_pose(T),
        fitness=2.75,
        inlier_ratio=0.93,
        converged=True,
        status="ok",
        covariance=cov.ravel().tolist(),
        latency_ms=41.5,
        map="default",
    )
    got = decode_pose(encode(sent))
    assert got == sent and got.v == SCHEMA_VERSION
    np.testing.assert_array_equal(got.matrix(), T)
    np.testing.assert_array_equal(pose_to_matrix(got), T)
    np.testing.assert_array_equal(got.covariance_matrix(), cov)
    assert (got.fitness, got.inlier_ratio, got.converged, got.status, got.latency_ms, got.map) == (
        2.75,
        0.93,
        True,
        "ok",
        41.5,
        "default",
    )


def test_pose_accepts_a_matrix_and_no_covariance() -> None:
    T = make_transform(translation=[1.0, 2.0, 3.0])
    sent = PoseMessage(
        vehicle="v",
        session="s",
        seq=0,
        stamp_ns=0,
        pose=T,
        fitness=0.0,
        inlier_ratio=0.0,
        converged=False,
        status="fallback",
        latency_ms=3.0,
        map="m",
    )
    got = decode_pose(encode(sent))
    assert got.covariance is None and got.covariance_matrix() is None
    np.testing.assert_array_equal(got.matrix(), T)


def test_error_round_trip_with_unknown_ids() -> None:
    sent = ErrorMessage(vehicle="?", session="?", seq=None, code="malformed", reason="payload: truncated")
    assert decode_error(encode(sent)) == sent
    known = ErrorMessage(vehicle="car", session="s", seq=7, code="out_of_order", reason="seq 7 after 9")
    assert decode_error(encode(known)) == known


def test_tile_update_round_trip() -> None:
    rng = np.random.default_rng(1)
    xyz = rng.uniform([40.0, -20.0, -2.0], [60.0, 0.0, 8.0], size=(500, 3)).astype(np.float32)
    intensity = rng.uniform(0.0, 1.0, size=500).astype(np.float32)
    sent = tile_update_from_arrays("default", 2, -1, 7, xyz, intensity)
    got = decode_tile_update(encode(sent))
    assert got == sent
    assert (got.map, got.tile, got.ix, got.iy, got.version, got.n_points) == (
        "default",
        "2_-1",
        2,
        -1,
        7,
        500,
    )
    np.testing.assert_array_equal(got.xyz(), xyz.astype(np.float64))
    np.testing.assert_array_equal(got.intensity(), intensity)
    np.testing.assert_array_equal(got.bounds.min, xyz.min(axis=0))
    np.testing.assert_array_equal(got.bounds.max, xyz.max(axis=0))


def test_tile_update_built_as_the_service_does() -> None:
    xyzi = np.array([[1.0, 2.0, 3.0, 0.5], [4.0, 5.0, 6.0, 0.25]], dtype="<f4")
    msg = TileUpdateMessage(
        map="default",
        tile="0_0",
        ix=0,
        iy=0,
        version=1,
        bounds={"min": [1.0, 2.0, 3.0], "max": [4.0, 5.0, 6.0]},
        n_points=2,
        points=xyzi.tobytes(),
    )
    np.testing.assert_array_equal(decode_tile_update(encode(msg)).points_f32(), xyzi)


def test_a_tile_update_from_a_checked_table_is_the_checked_one() -> None:
    """The service builds its saved tiles' updates without validating them again: the message,
    its bytes and its digest are those of the validated form, and it decodes."""
    rng = np.random.default_rng(3)
    xyzi = rng.uniform(-30.0, 30.0, size=(700, 4)).astype("<f4")
    checked = tile_update_from_arrays("default", -2, 5, 9, xyzi[:, :3], xyzi[:, 3])
    bounds = (xyzi[:, :3].min(axis=0).tolist(), xyzi[:, :3].max(axis=0).tolist())
    fast = tile_update_from_table("default", -2, 5, 9, xyzi, bounds)
    assert fast == checked
    assert encode(fast) == encode(checked)
    assert decode_tile_update(encode(fast)) == checked
    assert tile_update_from_table("default", -2, 5, 9, xyzi, bounds, digest=checked.digest) == checked


def test_unknown_keys_are_ignored_within_v1() -> None:
    payload = pack(scan_dict(ring_ids=b"\x00" * 20, vendor={"model": "HDL-64E"}))
    assert decode_scan(payload).n_points == 20


def test_nil_optional_fields_decode_as_absent() -> None:
    got = decode_scan(pack(scan_dict(time_offsets=None, prior=None)))
    assert got.time_offsets is None and got.prior is None


def test_decoding_a_120k_point_scan_is_cheap() -> None:
    rng = np.random.default_rng(2)
    n = 120_000
    payload = encode(
        scan_from_arrays(
            "car",
            "s",
            1,
            2,
            rng.uniform(-100.0, 100.0, size=(n, 3)),
            rng.uniform(0.0, 1.0, size=n),
            np.linspace(0.0, 0.1, n),
        )
    )
    decode_scan(payload)  # warm-up
    best = min(_timed(decode_scan, payload) for _ in range(5))
    assert best < 0.05, f"decoding 120k points took {best * 1e3:.1f} ms"
    assert min(_timed(peek_ids, payload) for _ in range(5)) < 0.01


def _timed(fn, payload: bytes) -> float:
    t0 = time.perf_counter()
    fn(payload)
    return time.perf_counter() - t0


# --------------------------------------------------------------------------------------------
# one test per error code
# --------------------------------------------------------------------------------------------


def test_payload_too_large_is_checked_before_unpacking() -> None:
    err = rejected(b"\xc1" * 2048, limits=WireLimits(max_payload_bytes=1024))  # \xc1 is never valid
    assert err.code == "payload_too_large"
    assert "2048 bytes" in str(err) and "1024" in str(err)


@pytest.mark.parametrize(
    ("payload", "words"),
    [
        (b"", "not valid msgpack"),
        (b"\xc1", "not valid msgpack"),
        (pack(scan_dict())[:-5], "not valid msgpack"),
        (pack(scan_dict()) + b"\x00", "trailing bytes"),
        (pack([1, 2, 3]), "top level must be a map, got an array of 3 items"),
        (pack("scan"), "top level must be a map"),
        (b"\x81\x91\x01\x01", "not valid msgpack"),  # a map keyed by an array
    ],
)
def test_malformed(payload: bytes, words: str) -> None:
    err = rejected(payload)
    assert err.code == "malformed"
    assert words in str(err)


def test_unsupported_version() -> None:
    err = rejected(pack(scan_dict(v=3)))
    assert err.code == "unsupported_version"
    assert str(err) == "v: schema version 3 is not supported (this decoder reads 1 and 2)"
    # v2 exists for scans only
    pose = msgpack.unpackb(encode(ErrorMessage(vehicle="car", session="s", code="malformed", reason="r")))
    err = rejected(pack({**pose, "v": 2}), decode_error)
    assert (err.code, str(err)) == (
        "unsupported_version",
        "v: schema version 2 is not supported (this decoder reads 1)",
    )


@pytest.mark.parametrize("field", ["v", "vehicle", "session", "seq", "stamp_ns", "fields", "points"])
def test_missing_field(field: str) -> None:
    err = rejected(pack(scan_dict(**{field: DROP})))
    assert err.code == "missing_field"
    assert str(err).startswith(f"{field}: ")


def test_missing_field_inside_the_prior() -> None:
    prior = prior_dict()
    del prior["covariance"]
    err = rejected(pack(scan_dict(prior=prior)))
    assert (err.code, str(err)) == ("missing_field", "prior.covariance: required field is missing")


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        ({"v": "1"}, "v: the schema version must be an integer, got '1'"),
        ({"v": True}, "v: the schema version must be an integer"),
        ({"seq": "12"}, "seq: input should be a valid integer, got '12'"),
        ({"seq": -1}, "seq: input should be greater than or equal to 0, got -1"),
        ({"seq": 1.0}, "seq: input should be a valid integer"),
        ({"stamp_ns": 2**64 - 1}, "stamp_ns: input should be less than or equal to"),
        ({"fields": "xy"}, "fields: input should be 'xyz' or 'xyzi', got 'xy'"),
        ({"points": [1.0, 2.0, 3.0]}, "points: input should be a valid bytes, got an array of 3 items"),
        ({"points": "abc" * 4}, "use_bin_type=True"),
        ({"time_offsets": 0.1}, "time_offsets: input should be a valid bytes, got 0.1"),
        ({"prior": [0.0] * 16}, "prior: input should be a valid dictionary"),
        (
            {"prior": {"pose": [0.0] * 15, "covariance": [0.0] * 36}},
            "prior.pose: expected at least 16 values, got 15",
        ),
        ({"vehicle": 7}, "vehicle: input should be a valid string, got 7"),
    ],
)
def test_invalid_field(overrides: dict[str, Any], words: str) -> None:
    err = rejected(pack(scan_dict(**overrides)))
    assert err.code == "invalid_field"
    assert words in str(err)


def test_invalid_field_counts_further_problems() -> None:
    err = rejected(pack(scan_dict(seq="a", stamp_ns="b")))
    assert err.code == "invalid_field"
    assert str(err).startswith("seq: ") and str(err).endswith("(and 1 more problems)")


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("vehicle", "car/1"),
        ("vehicle", "*"),
        ("vehicle", "car 1"),
        ("vehicle", "car1\n"),  # `$` alone would accept a trailing newline
        ("vehicle", ""),
        ("session", "$*"),
        ("session", "a?b"),
        ("session", "-lead"),
        ("session", "x" * 65),
    ],
)
def test_invalid_id(field: str, value: str) -> None:
    err = rejected(pack(scan_dict(**{field: value})))
    assert err.code == "invalid_id"
    assert str(err).startswith(f"{field}: ") and "is not a valid id" in str(err)


def test_invalid_id_quotes_a_long_id_truncated() -> None:
    err = rejected(pack(scan_dict(vehicle="bad/" + "x" * 5000)))
    assert err.code == "invalid_id"
    assert "(5004 chars)" in str(err) and len(str(err)) < 200


def test_invalid_map_name_in_a_tile_update() -> None:
    ok = encode(tile_update_from_arrays("default", 0, 0, 1, np.ones((1, 3))))
    obj = msgpack.unpackb(ok)
    obj["map"] = "a/b"
    err = rejected(pack(obj), decode_tile_update)
    assert (err.code, str(err).split(":")[0]) == ("invalid_id", "map")


def test_invalid_points_stride() -> None:
    err = rejected(pack(scan_dict(points=b"\x00" * 100)))
    assert err.code == "invalid_points"
    assert str(err) == "points: 100 bytes is not a multiple of 12 (fields xyz)"
    err = rejected(pack(scan_dict(fields="xyzi", points=b"\x00" * 24)))
    assert str(err) == "points: 24 bytes is not a multiple of 16 (fields xyzi)"


def test_invalid_points_time_offsets_length() -> None:
    err = rejected(pack(scan_dict(n=20, time_offsets=f32(np.zeros(19)))))
    assert err.code == "invalid_points"
    assert str(err) == "time_offsets: 76 bytes, expected 80 (one float32 per point, 20 points)"


@pytest.mark.parametrize(("bad", "count"), [(-0.01, 1), (1.5, 1), (np.nan, 1), (np.inf, 1)])
def test_invalid_points_time_offsets_range(bad: float, count: int) -> None:
    offsets = np.linspace(0.0, 0.1, 20)
    offsets[7] = bad
    err = rejected(pack(scan_dict(n=20, time_offsets=f32(offsets))))
    assert err.code == "invalid_points"
    assert f"time_offsets: {count} offsets outside [0, 1.0] s, first at index 7" in str(err)


def test_invalid_points_time_offsets_respect_the_limit() -> None:
    payload = pack(scan_dict(n=20, time_offsets=f32(np.full(20, 0.4))))
    assert decode_scan(payload).time_offset_s()[0] == pytest.approx(0.4)
    err = rejected(payload, limits=WireLimits(max_time_offset_s=0.2))
    assert err.code == "invalid_points" and "[0, 0.2] s" in str(err)


def test_invalid_points_in_a_tile_update() -> None:
    obj = msgpack.unpackb(encode(tile_update_from_arrays("m", 0, 0, 1, np.ones((3, 3)))))
    obj["n_points"] = 4
    err = rejected(pack(obj), decode_tile_update)
    assert err.code == "invalid_points" and str(err).startswith("points: 48 bytes, expected 64")


def test_empty_scan() -> None:
    err = rejected(pack(scan_dict(points=b"")))
    assert err.code == "empty_scan"
    assert "no points" in str(err)
    with pytest.raises(BadMessageError) as info:
        scan_from_arrays("car", "s", 0, 0, np.zeros((0, 3)))
    assert info.value.code == "empty_scan"


def test_too_many_points() -> None:
    payload = pack(scan_dict(n=101))
    assert decode_scan(payload).n_points == 101
    err = rejected(payload, limits=WireLimits(max_points=100))
    assert err.code == "too_many_points"
    assert str(err) == "points: 101 points exceed the limit of 100"


def test_nonfinite_points() -> None:
    xyz = np.ones((50, 3))
    xyz[17, 1] = np.nan
    xyz[30, 0] = np.inf
    xyz[31, 2] = -np.inf
    err = rejected(pack(scan_dict(points=f32(xyz))))
    assert err.code == "nonfinite_points"
    assert str(err) == "points: 3 points have a non-finite coordinate (NaN or Inf), first at index 17"


def test_nonfinite_intensity() -> None:
    xyzi = np.ones((10, 4))
    xyzi[4, 3] = np.nan
    err = rejected(pack(scan_dict(fields="xyzi", points=f32(xyzi))))
    assert err.code == "nonfinite_points"
    assert "1 points have a non-finite intensity" in str(err) and "index 4" in str(err)


def test_nonfinite_points_from_the_sender_helper() -> None:
    xyz = np.zeros((5, 3))
    xyz[2, 2] = np.nan
    with pytest.raises(BadMessageError) as info:
        scan_from_arrays("car", "s", 0, 0, xyz)
    assert info.value.code == "nonfinite_points" and "index 2" in str(info.value)


@pytest.mark.parametrize(
    ("prior", "words"),
    [
        (prior_dict(T=np.full((4, 4), np.nan)), "prior: pose has 16 non-finite entries"),
        (prior_dict(T=np.diag([1.0, 1.0, -1.0, 1.0])), "prior: pose rotation block is not a rotation"),
        (prior_dict(T=np.diag([2.0, 1.0, 1.0, 1.0])), "prior: pose rotation block is not a rotation"),
        (prior_dict(T=np.vstack([np.eye(4)[:3], [0.0, 0.0, 1.0, 1.0]])), "prior: pose last row must be"),
        (prior_dict(C=np.full((6, 6), np.inf)), "prior: covariance has 36 non-finite entries"),
        (prior_dict(C=np.triu(np.ones((6, 6)))), "prior: covariance is not symmetric"),
        (
            prior_dict(C=np.diag([1.0, 1.0, 1.0, 1.0, 1.0, -0.5])),
            "prior: covariance is not positive semi-definite",
        ),
    ],
)
def test_invalid_prior(prior: dict[str, Any], words: str) -> None:
    err = rejected(pack(scan_dict(prior=prior)))
    assert err.code == "invalid_prior"
    assert str(err).startswith(words)


def test_valid_prior_tolerates_float32_rounding() -> None:
    T = make_transform([0.4, 0.5, -1.0], [1e3, 2e3, 10.0]).astype(np.float32).astype(np.float64)
    C = np.full((6, 6), 0.01) + np.eye(6) * 0.1  # PSD, not diagonal
    got = decode_scan(pack(scan_dict(prior=prior_dict(T, C))))
    np.testing.assert_array_equal(got.prior_pose(), T)


def test_every_code_is_documented_and_exercised() -> None:
    doc = DOC.read_text(encoding="utf-8")
    for code in DECODE_CODES:
        assert re.search(rf"^\| `{code}` \|", doc, flags=re.MULTILINE), f"{code} missing from the doc table"
    tests = [name for name in globals() if name.startswith("test_")]
    for code in DECODE_CODES:
        assert any(name.startswith(f"test_{code}") for name in tests), f"no test for {code}"


def test_each_decoder_rejects_other_messages() -> None:
    scan = pack(scan_dict())
    for decoder in (decode_pose, decode_error, decode_tile_update):
        assert rejected(scan, decoder).code == "missing_field"


def test_non_buffer_payload_is_a_type_error() -> None:
    with pytest.raises(TypeError):
        decode_scan("not bytes")  # type: ignore[arg-type]


def test_bytearray_and_memoryview_payloads_decode() -> None:
    payload = pack(scan_dict())
    assert decode_scan(bytearray(payload)).n_points == 20
    assert decode_scan(memoryview(payload)).n_points == 20


# --------------------------------------------------------------------------------------------
# messages built by senders
# --------------------------------------------------------------------------------------------


def test_scan_from_arrays_checks_shapes_and_prior_pairs() -> None:
    xyz = np.zeros((4, 3))
    for kwargs in ({"xyz": np.zeros((4, 2))}, {"intensity": np.zeros(3)}, {"time_offset_s": np.zeros(5)}):
        with pytest.raises(BadMessageError) as info:
            scan_from_arrays("car", "s", 0, 0, **{"xyz": xyz, **kwargs})
        assert info.value.code == "invalid_points"
    with pytest.raises(BadMessageError) as info:
        scan_from_arrays("car", "s", 0, 0, xyz, prior_pose=np.eye(4))
    assert info.value.code == "invalid_prior"
    with pytest.raises(BadMessageError) as info:
        scan_from_arrays("car/x", "s", 0, 0, xyz)
    assert info.value.code == "invalid_id"


def test_constructors_validate() -> None:
    with pytest.raises(ValidationError):
        ErrorMessage(vehicle="a/b", session="?", code="malformed", reason="x")
    with pytest.raises(ValidationError):
        ErrorMessage(vehicle="?", session="?", code="Not A Code", reason="x")
    with pytest.raises(ValidationError):
        TileUpdateMessage(
            map="m",
            tile="1_2",
            ix=2,
            iy=1,
            version=1,
            bounds={"min": [0, 0, 0], "max": [1, 1, 1]},
            n_points=0,
            points=b"",
        )
    bad_pose = np.eye(4)
    bad_pose[0, 0] = 3.0
    with pytest.raises(ValidationError, match="pose: rotation block is not a rotation"):
        PoseMessage(
            vehicle="v",
            session="s",
            seq=0,
            stamp_ns=0,
            pose=bad_pose,
            fitness=1.0,
            inlier_ratio=1.0,
            converged=True,
            status="ok",
            latency_ms=1.0,
            map="m",
        )


def test_wire_limits_reject_unsafe_id_patterns() -> None:
    assert WireLimits(id_pattern=r"^[a-z]{1,8}$").id_ok("abc")
    for pattern in (r"^.*$", r"^[a-z/]+$", r"(unclosed"):
        with pytest.raises(ValidationError):
            WireLimits(id_pattern=pattern)


def test_encode_rejects_other_objects() -> None:
    with pytest.raises(TypeError):
        encode({"v": SCHEMA_VERSION})  # type: ignore[arg-type]


def test_pose_matrix_helpers() -> None:
    T = make_transform([0.1, 0.2, 0.3], [4.0, 5.0, 6.0])
    assert matrix_to_pose(T)[3] == 4.0  # row-major: T[0, 3]
    np.testing.assert_array_equal(pose_to_matrix(matrix_to_pose(T)), T)
    with pytest.raises(ValueError):
        pose_to_matrix([1.0] * 15)
    with pytest.raises(ValueError):
        matrix_to_pose(np.eye(3))


# --------------------------------------------------------------------------------------------
# peeking
# --------------------------------------------------------------------------------------------


def test_peek_ids_on_broken_payloads() -> None:
    good = pack(scan_dict(seq=41))
    assert peek_ids(good) == ("car-07", "2024-05-01.a") and peek_seq(good) == 41
    # points broken (stride): the ids are still there
    assert peek_ids(pack(scan_dict(points=b"\x00" * 7))) == ("car-07", "2024-05-01.a")
    # truncated inside the points: everything before them reads
    assert peek_ids(good[: len(good) // 2]) == ("car-07", "2024-05-01.a")
    assert peek_seq(good[: len(good) // 2]) == 41
    # truncated inside the session string: the vehicle only
    cut = good.index(b"2024-05-01.a") + 3
    assert peek_ids(good[:cut]) == ("car-07", None)
    # unsafe or mistyped ids are not returned
    assert peek_ids(pack(scan_dict(vehicle="a/b", session=5))) == (None, None)
    assert peek_ids(pack(scan_dict(vehicle="*", session="s"))) == (None, "s")
    assert peek_seq(pack(scan_dict(seq=-3))) is None and peek_seq(pack(scan_dict(seq=True))) is None
    # unsupported version, keys in any order, values that are maps: still peeked
    reordered = {"points": b"\x00" * 12, "extra": {"a": [1, 2]}, "session": "s", "v": 9, "vehicle": "car"}
    assert peek_ids(pack(reordered)) == ("car", "s")
    # not a map, not msgpack, empty, not bytes: nothing
    for payload in (pack([1, 2]), b"\xc1\xc1", b"", pack({1: "a"}), None, "car", 12):
        assert peek_ids(payload) == (None, None)  # type: ignore[arg-type]
        assert peek_seq(payload) is None  # type: ignore[arg-type]
    # an id pattern from the limits applies
    assert peek_ids(good, WireLimits(id_pattern=r"^[a-z]+$")) == (None, None)


# --------------------------------------------------------------------------------------------
# fuzzing: nothing but BadMessageError, whatever the bytes
# --------------------------------------------------------------------------------------------

DECODERS = (decode_scan, decode_pose, decode_error, decode_tile_update)


def _valid_payloads() -> list[bytes]:
    rng = np.random.default_rng(9)
    scan = scan_from_arrays(
        "car",
        "s",
        3,
        4,
        rng.normal(size=(8, 3)),
        rng.uniform(size=8),
        np.linspace(0.0, 0.1, 8),
        make_transform([0.1, 0.0, 0.0], [1.0, 2.0, 3.0]),
        np.eye(6),
    )
    pose = PoseMessage(
        vehicle="car",
        session="s",
        seq=3,
        stamp_ns=4,
        pose=np.eye(4),
        fitness=1.0,
        inlier_ratio=0.5,
        converged=True,
        status="ok",
        covariance=np.eye(6),
        latency_ms=2.0,
        map="m",
    )
    error = ErrorMessage(vehicle="car", session="s", seq=3, code="malformed", reason="why")
    tile = tile_update_from_arrays("m", 1, 2, 3, rng.normal(size=(4, 3)), rng.uniform(size=4))
    return [encode(m) for m in (scan, pose, error, tile)]


def _only_bad_message_errors(payload: bytes) -> None:
    for decoder in DECODERS:
        try:
            decoder(payload)
        except BadMessageError as exc:
            assert exc.code in DECODE_CODES, exc.code
    vehicle, session = peek_ids(payload)
    assert vehicle is None or isinstance(vehicle, str)
    assert session is None or isinstance(session, str)
    peek_seq(payload)


def assert_no_decoder_bug(caplog: pytest.LogCaptureFixture) -> None:
    """The decoders' safety net (unexpected exceptions reported as malformed) must never fire."""
    bugs = [r for r in caplog.records if r.name == "randt.wire.messages" and r.levelno >= logging.ERROR]
    assert not bugs, bugs[0].getMessage()


def test_fuzz_random_bytes(caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(12345)
    for _ in range(2000):
        size = int(rng.integers(0, 200))
        payload = rng.integers(0, 256, size=size, dtype=np.uint8).tobytes()
        if size and rng.random() < 0.5:  # half of them start like a map, to get past the first byte
            payload = bytes([0x80 | int(rng.integers(0, 16))]) + payload[1:]
        _only_bad_message_errors(payload)
    assert_no_decoder_bug(caplog)


def test_fuzz_truncations_and_bit_flips_of_valid_payloads(caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(54321)
    for payload in _valid_payloads():
        for cut in range(len(payload)):
            _only_bad_message_errors(payload[:cut])
        for _ in range(300):
            mutated = bytearray(payload)
            for index in rng.integers(0, len(mutated), size=int(rng.integers(1, 4))):
                mutated[index] ^= 1 << int(rng.integers(0, 8))
            _only_bad_message_errors(bytes(mutated))
    assert_no_decoder_bug(caplog)


_FIELD_NAMES = sorted(
    {"v", "vehicle", "session", "seq", "stamp_ns", "fields", "points", "time_offsets", "prior"}
    | {"pose", "covariance", "fitness", "inlier_ratio", "converged", "status", "latency_ms", "map"}
    | {"code", "reason", "tile", "ix", "iy", "version", "bounds", "n_points", "min", "max"}
)
_SPECIAL_FLOATS = (np.nan, np.inf, -np.inf, -0.0, 1e308, -1.0, 0.5)
_SPECIAL_INTS = (0, -1, 1, 2, 2**31, 2**63 - 1, 2**63, 2**64 - 1, -(2**63))
_SPECIAL_STRS = ("", "?", "*", "a/b", "car", "xyz", "xyzi", "ok", "0_0", "x" * 80, "é", "$*", "a\n")


def _random_value(rng: np.random.Generator, depth: int = 0) -> Any:
    """An arbitrary msgpack-able value, biased towards the shapes and edge cases the schema cares about."""
    kind = int(rng.integers(0, 11 if depth < 2 else 8))
    if kind == 0:
        return None
    if kind == 1:
        return bool(rng.integers(0, 2))
    if kind == 2:
        return _SPECIAL_INTS[int(rng.integers(0, len(_SPECIAL_INTS)))]
    if kind == 3:
        return _SPECIAL_FLOATS[int(rng.integers(0, len(_SPECIAL_FLOATS)))]
    if kind == 4:
        return _SPECIAL_STRS[int(rng.integers(0, len(_SPECIAL_STRS)))]
    if kind in (5, 6):  # point-like buffers: random floats, NaN/Inf, lengths around the strides
        n = int(rng.choice([0, 1, 3, 4, 12, 16, 24, 48, 64]))
        values = rng.choice(np.array([0.0, 1.0, -2.5, np.nan, np.inf, 0.05], dtype="<f4"), size=n)
        data = values.tobytes()
        return data if kind == 5 else data[: int(rng.integers(0, len(data) + 1))]
    if kind == 7:
        return int(rng.integers(-5, 50))
    if kind in (8, 9):  # arrays of the lengths poses, covariances and bounds have
        n = int(rng.choice([0, 2, 3, 15, 16, 36, 37]))
        return [
            _random_value(rng, depth + 1) if rng.random() < 0.1 else float(rng.normal()) for _ in range(n)
        ]
    keys = rng.choice(_FIELD_NAMES, size=int(rng.integers(0, 4)))
    return {str(key): _random_value(rng, depth + 1) for key in keys}


def test_fuzz_structured_messages(caplog: pytest.LogCaptureFixture) -> None:
    """Valid messages with fields replaced by arbitrary values reach every validator."""
    rng = np.random.default_rng(2024)
    valid = [msgpack.unpackb(payload) for payload in _valid_payloads()]
    for _ in range(2000):
        obj = dict(valid[int(rng.integers(0, len(valid)))])
        names = sorted(obj) if rng.random() < 0.8 else _FIELD_NAMES  # mostly the message's own fields
        for key in rng.choice(names, size=int(rng.integers(1, 3))):
            obj[str(key)] = _random_value(rng)
        for nested, keys in (("prior", ("pose", "covariance")), ("bounds", ("min", "max"))):
            if isinstance(obj.get(nested), dict) and rng.random() < 0.5:  # reach the nested models too
                obj[nested] = {**obj[nested], keys[int(rng.integers(0, 2))]: _random_value(rng)}
        _only_bad_message_errors(pack(obj))
    assert_no_decoder_bug(caplog)


# --------------------------------------------------------------------------------------------
# compact scans (v2): round trips, quantization bounds, hostile bodies
# --------------------------------------------------------------------------------------------


def _walk(n: int, seed: int = 5) -> np.ndarray:
    """(n, 3) points a few cm apart (a sweep's native order), with far points and big jumps."""
    rng = np.random.default_rng(seed)
    xyz = np.cumsum(rng.normal(0.0, 0.04, size=(n, 3)), axis=0) + [5.0, -3.0, 1.0]
    xyz[::97] = rng.uniform(-300.0, 300.0, size=(len(xyz[::97]), 3))  # far points: int16 overflows
    xyz[5] = [299.99, -299.99, 299.99]
    xyz[6] = [-299.99, 299.99, -299.99]  # a jump of 600 m (60 000 steps) on every axis
    return xyz


def v2_payload(n: int = 500, *, intensity: bool = True, offsets: bool = True, **kw: Any) -> bytes:
    rng = np.random.default_rng(9)
    scan = scan_from_arrays(
        "car-07",
        "s1",
        4,
        1_700_000_000_000_000_000,
        _walk(n),
        rng.uniform(0.0, 1.0, n) if intensity else None,
        np.sort(rng.uniform(0.0, 0.1, n)) if offsets else None,
    )
    return encode_scan_v2(scan, **kw)


def v2_dict(**overrides: Any) -> dict[str, Any]:
    obj = msgpack.unpackb(v2_payload())
    obj.update(overrides)
    return {k: v for k, v in obj.items() if v is not DROP}


def test_v2_round_trip_bounds_and_order() -> None:
    n = 3000
    rng = np.random.default_rng(1)
    xyz = _walk(n)
    intensity = rng.uniform(0.0, 0.99, n)
    offsets = np.sort(rng.uniform(0.0, 0.1, n))
    T = make_transform([0.01, 0.02, 1.2], [105.0, -42.0, 3.0])
    C = np.diag([0.5, 0.5, 1.0, 1e-3, 1e-3, 5e-3])
    sent = scan_from_arrays("car-07", "s1", 5, 17, xyz, intensity, offsets, T, C)
    payload = encode_scan_v2(sent, voxel_m=0.2, xyz_quantum_m=0.01, time_quantum_s=1e-5)
    got = decode_scan(payload)

    assert isinstance(got, ScanMessage) and sent.encoding is None
    assert (got.vehicle, got.session, got.seq, got.stamp_ns, got.fields, got.n_points) == (
        "car-07",
        "s1",
        5,
        17,
        "xyzi",
        n,
    )
    enc = got.encoding
    assert enc is not None and (enc.voxel_m, enc.xyz_quantum_m, enc.time_quantum_s, enc.codec) == (
        0.2,
        0.01,
        1e-5,
        "zstd",
    )
    # every point in its place: within half a step (+ float32 rounding of a 300 m value, 1.5e-5 m)
    err = np.abs(got.xyz() - xyz)
    assert err.max() <= 0.005 + 3e-5, err.max()
    assert err.max() > 0.004  # the bound is reached, so the test can tell a coarser step
    assert np.abs(got.time_offset_s() - offsets).max() <= 0.5e-5 + 1e-7
    assert np.abs(got.intensity() - intensity).max() <= 0.5 * enc.intensity_quantum + 1e-6
    np.testing.assert_array_equal(got.prior_pose(), T)
    np.testing.assert_array_equal(got.prior_covariance(), C)
    # the decoded message is a plain scan: re-encoding it as v1 gives the same arrays
    again = decode_scan(encode(got))
    np.testing.assert_array_equal(again.xyz(), got.xyz()) and again.encoding is None


def test_v2_without_optional_bodies_and_with_codec_none() -> None:
    xyz = _walk(200)
    for codec in ("zstd", "none"):
        payload = encode_scan_v2(scan_from_arrays("car", "s", 0, 0, xyz), codec=codec)
        got = decode_scan(payload)
        assert got.fields == "xyz" and got.intensity() is None and got.time_offset_s() is None
        assert np.abs(got.xyz() - xyz).max() <= 0.005 + 3e-5
    raw = msgpack.unpackb(encode_scan_v2(scan_from_arrays("car", "s", 0, 0, xyz), codec="none"))
    assert len(raw["xyz"]) == 12 * 200 and raw["encoding"]["layout"] == "delta-zigzag-planar"


def test_v2_layout_is_the_documented_one() -> None:
    """Byte for byte: differences, zigzag, byte planes column after column (docs/wire-format.md)."""
    top = 2**31 - 128  # the largest float32 below 2^31
    xyz = np.array([[1.0, 0.0, -2.0], [3.0, -100.0, -2.0], [-1.0, top, -(2.0**31)]])
    raw = msgpack.unpackb(
        encode_scan_v2(scan_from_arrays("c", "s", 0, 0, xyz), xyz_quantum_m=1.0, codec="none")
    )
    q = xyz.T.astype(np.int64)
    d = np.diff(q, axis=1, prepend=0)
    d = (d + 2**31) % 2**32 - 2**31  # int32 wrap-around
    z = np.where(d >= 0, 2 * d, -2 * d - 1).astype(np.uint32)
    planes = [((z[c] >> (8 * b)) & 0xFF).astype(np.uint8).tobytes() for c in range(3) for b in range(4)]
    assert raw["xyz"] == b"".join(planes)
    assert z[1].tolist() == [0, 199, 2 * (top + 100)]
    assert d[2].tolist() == [-2, 0, -(2**31) + 2]  # -2^31 - (-2) = -2^31 + 2: no wrap; zigzag 2^32 - 5
    assert z[2].tolist() == [3, 0, 2**32 - 5]


def test_v2_integer_intensities_are_exact() -> None:
    intensity = np.arange(200) % 256
    got = decode_scan(encode_scan_v2(scan_from_arrays("c", "s", 0, 0, _walk(200), intensity)))
    assert got.encoding is not None and (got.encoding.intensity_offset, got.encoding.intensity_quantum) == (
        0.0,
        1.0,
    )
    np.testing.assert_array_equal(got.intensity(), intensity)


def test_v2_coordinates_beyond_the_int32_range_are_refused() -> None:
    xyz = np.array([[0.0, 0.0, 0.0], [3.0e7, 0.0, 0.0]])  # 3e9 steps of 1 cm
    with pytest.raises(BadMessageError) as info:
        encode_scan_v2(scan_from_arrays("c", "s", 0, 0, xyz))
    assert info.value.code == "invalid_points" and "cannot be sent in steps of 0.01 m" in str(info.value)
    got = decode_scan(encode_scan_v2(scan_from_arrays("c", "s", 0, 0, xyz), xyz_quantum_m=1.0))
    assert got.xyz()[1, 0] == 3.0e7


def test_v2_wrapping_differences_decode_exactly() -> None:
    """The extreme int32 values next to each other: differences wrap modulo 2^32 both ways."""
    top, bottom = 2.0**31 - 128, -(2.0**31)  # float32-exact, 2^32 - 128 apart
    xyz = np.array([[top, bottom, 0.0], [bottom, top, 0.0], [top, top, bottom]] * 3)
    got = decode_scan(encode_scan_v2(scan_from_arrays("c", "s", 0, 0, xyz), xyz_quantum_m=1.0))
    np.testing.assert_array_equal(got.xyz(), xyz)


def test_invalid_compression_bomb_stops_at_the_declared_size() -> None:
    from randt.wire.packing import zstd

    bomb = zstd.compress(b"\x00" * (64 * 1024 * 1024), level=3)  # 64 MiB in about 2 KiB
    assert len(bomb) < 10_000
    t0 = time.perf_counter()
    err = rejected(pack(v2_dict(n_points=500, xyz=bomb)))
    assert time.perf_counter() - t0 < 0.5  # it stopped after 6000 bytes
    assert err.code == "invalid_compression"
    assert str(err) == (
        "xyz: the zstd frame decompresses to more than the 6000 bytes its point count implies "
        "(stopped there: a decompression bomb?)"
    )


def test_invalid_compression_other_failures() -> None:
    from randt.wire.packing import zstd

    good = v2_dict()
    cases = [
        (good["xyz"][: len(good["xyz"]) // 2], "xyz: the zstd frame ends after"),
        (b"not zstd at all", "xyz: not a valid zstd frame"),
        (good["xyz"] + b"\x00\x01", "xyz: 2 bytes after the zstd frame"),
        (good["xyz"] + good["xyz"], "bytes after the zstd frame"),
        (zstd.compress(b"\x00" * 100), "xyz: the zstd frame ends after 100 bytes, expected 6000"),
    ]
    for body, words in cases:
        err = rejected(pack({**good, "xyz": body}))
        assert err.code == "invalid_compression", (words, str(err))
        assert words in str(err), str(err)
    err = rejected(pack({**good, "intensity": zstd.compress(b"\x00" * 501)}))
    assert err.code == "invalid_compression" and str(err).startswith("intensity: ")
    err = rejected(pack({**good, "time_offsets": b""}))
    assert err.code == "invalid_compression" and str(err).startswith("time_offsets: ")


def test_v2_point_count_is_checked_before_decompressing() -> None:
    err = rejected(pack(v2_dict(n_points=0)))
    assert (err.code, str(err)) == ("empty_scan", "n_points: the scan holds no points")
    err = rejected(pack(v2_dict()), limits=WireLimits(max_points=499))
    assert (err.code, str(err)) == ("too_many_points", "n_points: 500 points exceed the limit of 499")
    err = rejected(pack(v2_dict(n_points=DROP)))
    assert (err.code, str(err)) == ("missing_field", "n_points: required field is missing")


def test_v2_codec_none_body_of_the_wrong_size() -> None:
    obj = msgpack.unpackb(v2_payload(codec="none"))
    err = rejected(pack({**obj, "xyz": obj["xyz"][:-1]}))
    assert (err.code, str(err)) == ("invalid_points", "xyz: 5999 bytes, expected 6000 (codec none)")


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [
        ("codec", "lz4", "encoding.codec: input should be 'zstd' or 'none', got 'lz4'"),
        ("layout", "rows", "encoding.layout: input should be 'delta-zigzag-planar'"),
        ("xyz_quantum_m", 0.0, "encoding.xyz_quantum_m: input should be greater than 0"),
        ("xyz_quantum_m", 5.0, "encoding.xyz_quantum_m: input should be less than or equal to 1"),
        ("time_quantum_s", float("nan"), "encoding.time_quantum_s: input should be a finite number"),
        ("intensity_quantum", -1.0, "encoding.intensity_quantum: input should be greater than 0"),
        ("voxel_m", "0.2", "encoding.voxel_m: input should be a valid number"),
        ("codec", DROP, "encoding.codec: required field is missing"),
    ],
)
def test_v2_encoding_fields_are_checked(field: str, value: Any, words: str) -> None:
    encoding = {**v2_dict()["encoding"], field: value}
    encoding = {k: v for k, v in encoding.items() if v is not DROP}
    err = rejected(pack(v2_dict(encoding=encoding)))
    assert err.code in ("invalid_field", "missing_field") and words in str(err), str(err)


def test_v2_decoded_values_are_range_checked() -> None:
    """Quantized time offsets decode to [0, max_time_offset_s] or the scan is refused."""
    obj = v2_dict()
    n = obj["n_points"]
    from randt.wire.packing import compress, pack_int_columns

    qt = np.full((1, n), 20_000, np.int32)  # 0.2 s
    qt[0, 7] = -3
    obj["time_offsets"] = compress(pack_int_columns(qt), "zstd")
    err = rejected(pack(obj))
    assert err.code == "invalid_points"
    assert str(err).startswith("time_offsets: 1 offsets outside [0, 1.0] s, first at index 7")
    qt[0, 7] = 20_000
    obj["time_offsets"] = compress(pack_int_columns(qt), "zstd")
    assert decode_scan(pack(obj)).time_offset_s()[7] == pytest.approx(0.2)
    err = rejected(pack(obj), limits=WireLimits(max_time_offset_s=0.1))
    assert err.code == "invalid_points" and "[0, 0.1] s" in str(err)
    # the declared ranges keep every decoded intensity finite in float32 (at most 2.56e32)
    enc = {**obj["encoding"], "intensity_quantum": 1e30, "intensity_offset": 1e30}
    got = decode_scan(pack({**obj, "encoding": enc}))
    assert np.isfinite(got.intensity()).all() and got.intensity().max() > 1e31
    err = rejected(pack({**obj, "encoding": {**enc, "intensity_offset": 1e31}}))
    assert err.code == "invalid_field" and str(err).startswith("encoding.intensity_offset: ")


def test_v2_ids_and_peeks() -> None:
    err = rejected(pack(v2_dict(vehicle="car/1")))
    assert err.code == "invalid_id"
    payload = pack(v2_dict(xyz=b"junk"))
    assert peek_ids(payload) == ("car-07", "s1") and peek_seq(payload) == 4


def test_v2_fuzz_truncations_and_bit_flips(caplog: pytest.LogCaptureFixture) -> None:
    payload = v2_payload(300)
    rng = np.random.default_rng(11)
    codes = set()
    with caplog.at_level(logging.ERROR, logger="randt.wire.messages"):
        for cut in range(0, len(payload), max(1, len(payload) // 150)):
            with pytest.raises(BadMessageError) as info:
                decode_scan(payload[:cut])
            codes.add(info.value.code)
        for _ in range(400):
            b = bytearray(payload)
            for pos in rng.integers(0, len(b), size=3):
                b[pos] ^= 1 << int(rng.integers(0, 8))
            try:
                decode_scan(bytes(b))
            except BadMessageError as exc:
                codes.add(exc.code)
                assert exc.code in DECODE_CODES
    assert not [r for r in caplog.records if "decoding a" in r.getMessage()], "a decoder bug was hit"
    assert "invalid_compression" in codes and "malformed" in codes


def test_correction_round_trip_and_its_checks() -> None:
    from randt.wire.keys import correction_key, key_for
    from randt.wire.messages import correction_from_arrays, decode_correction

    poses = np.stack(
        [make_transform(np.array([0.0, 0.0, 0.1 * k]), np.array([k, 2.0, 0.0])) for k in range(3)]
    )
    live = poses.copy()
    live[:, 0, 3] += 0.5
    message = correction_from_arrays("car-1", "d1", "default", 7, np.array([0, 10, 20]), poses, live)
    back = decode_correction(encode(message))
    assert back == message and key_for(back) == correction_key("car-1") == "randt/fleet/car-1/correction"
    np.testing.assert_array_equal(back.seqs(), [0, 10, 20])
    np.testing.assert_array_equal(back.poses(), poses)
    np.testing.assert_array_equal(back.live_poses(), live)
    good = message.model_dump()
    # a size that does not match n_keyframes, and a pose that is not rigid, are named
    short = pack({**good, "seq": good["seq"][:8]})
    error = rejected(short, decode_correction)
    assert error.code == "invalid_field" and "seq: 8 bytes, expected 24" in str(error)
    bent = poses.copy()
    bent[1, :3, :3] *= 1.5
    skewed = pack({**good, "pose": bent.astype("<f8").tobytes()})
    error = rejected(skewed, decode_correction)
    assert error.code == "invalid_field" and "pose[1]: rotation block is not a rotation" in str(error)
    nan = live.copy()
    nan[2, 0, 3] = np.nan
    error = rejected(pack({**good, "live": nan.astype("<f8").tobytes()}), decode_correction)
    assert "live[2]: has 1 non-finite entries" in str(error)
    assert rejected(pack({**good, "map": "a/b"}), decode_correction).code == "invalid_id"


def test_a_geo_prior_travels_in_v1_and_v2_and_in_the_header() -> None:
    """A WGS84 prior (issue 34): the same values back from a v1 and a v2 payload and from the
    header alone; a scan without one is the same bytes as before (no ``geo_prior`` key); with a
    map-frame prior too, or a quaternion that is not a rotation, it is refused ``invalid_prior``."""
    from randt.wire.messages import decode_scan_header, encode_scan_v2, geo_prior

    R = make_transform([0.0, 0.0, 0.3], [0.0, 0.0, 0.0])[:3, :3]
    cov = np.diag([0.25, 0.25, 1.0, 1e-4, 1e-4, 1e-3])
    g = geo_prior(35.6762, 139.6503, 40.25, R, cov)
    xyz = np.random.default_rng(1).normal(size=(50, 3))
    scan = scan_from_arrays("car", "s", 3, 17, xyz, geo_prior=g)
    for payload in (encode(scan), encode_scan_v2(scan)):
        back = decode_scan(payload).geo_prior
        assert back is not None and back == g
        assert np.allclose(back.rotation_enu(), R) and np.array_equal(back.covariance_matrix(), cov)
        header = decode_scan_header(payload)
        assert header.geo_prior == g and header.prior is None and header.prior_pose() is None
    plain = scan_from_arrays("car", "s", 3, 17, xyz)
    assert b"geo_prior" not in encode(plain) and b"geo_prior" not in encode_scan_v2(plain)
    with pytest.raises(BadMessageError, match="not both") as info:
        scan_from_arrays(
            "car", "s", 3, 17, xyz, prior_pose=np.eye(4), prior_covariance=np.eye(6), geo_prior=g
        )
    assert info.value.code == "invalid_prior"
    bad = msgpack.unpackb(encode(scan), raw=False)
    bad["geo_prior"]["orientation"] = [0.0, 0.0, 0.0, 2.0]
    with pytest.raises(BadMessageError, match="quaternion of length 2") as info:
        decode_scan(msgpack.packb(bad, use_bin_type=True))
    assert info.value.code == "invalid_prior"
    with pytest.raises(BadMessageError, match="not a rotation") as info:
        geo_prior(35.0, 139.0, 0.0, 2 * np.eye(3), cov)
    with pytest.raises(BadMessageError, match="latitude") as info:
        geo_prior(95.0, 139.0, 0.0, R, cov)
    assert info.value.code == "invalid_prior"


def test_localize_only_travels_in_v1_and_v2_and_in_the_header() -> None:
    """``localize_only`` (issue 57): true back from a v1 and a v2 payload and from the header
    alone; absent when false (a scan without it is the same bytes as before); not a bool:
    ``invalid_field``."""
    from randt.wire.messages import decode_scan_header, encode_scan_v2

    xyz = np.random.default_rng(2).normal(size=(50, 3))
    only = scan_from_arrays("car", "s", 0, 17, xyz, localize_only=True)
    for payload in (encode(only), encode_scan_v2(only)):
        assert decode_scan(payload).localize_only and decode_scan_header(payload).localize_only
    plain = scan_from_arrays("car", "s", 0, 17, xyz)
    for payload in (encode(plain), encode_scan_v2(plain)):
        assert b"localize_only" not in payload
        assert not decode_scan(payload).localize_only and not decode_scan_header(payload).localize_only
    for payload in (encode(only), encode_scan_v2(only)):
        bad = msgpack.unpackb(payload, raw=False)
        bad["localize_only"] = "yes"
        with pytest.raises(BadMessageError, match="localize_only") as info:
            decode_scan_header(msgpack.packb(bad, use_bin_type=True))
        assert info.value.code == "invalid_field"
