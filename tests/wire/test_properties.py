"""Property-based tests of the decoders (hypothesis): whatever arrives, a valid message or a
``BadMessageError`` with a documented code; never another exception.

Bounded CI time: every property has ``max_examples`` and a deadline (``_SETTINGS``); the
``derandomize`` flag makes a CI run reproducible (the same examples every run).
"""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from randt.core.errors import BadMessageError
from randt.wire.codes import DECODE_CODES, ErrorCode
from randt.wire.messages import (
    WireLimits,
    decode_error,
    decode_pose,
    decode_scan,
    decode_tile_update,
    encode,
    peek_ids,
    peek_seq,
    scan_from_arrays,
    tile_update_from_arrays,
)

_SETTINGS = settings(
    max_examples=150,
    deadline=2000,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
DECODERS = [decode_scan, decode_pose, decode_error, decode_tile_update]
LIMITS = WireLimits(max_points=2000, max_payload_bytes=200_000)

# any msgpack-encodable object (str keys and int keys, nesting, bin, floats incl. NaN/Inf)
_scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20)
    | st.binary(max_size=64)
)
_objects = st.recursive(
    _scalars,
    lambda children: (
        st.lists(children, max_size=6)
        | st.dictionaries(st.text(max_size=10) | st.integers(-5, 5), children, max_size=6)
    ),
    max_leaves=30,
)
_FIELD_NAMES = [
    "v", "vehicle", "session", "seq", "stamp_ns", "fields", "points", "time_offsets", "prior",
    "pose", "fitness", "inlier_ratio", "converged", "status", "covariance", "latency_ms", "map",
    "code", "reason", "tile", "ix", "iy", "version", "bounds", "n_points",
]  # fmt: skip
# maps that look like messages: known keys with arbitrary values
_message_like = st.dictionaries(st.sampled_from(_FIELD_NAMES), _objects, max_size=14)


def _decodes_or_known_error(decoder, payload: bytes) -> None:
    try:
        decoder(payload, LIMITS)
    except BadMessageError as exc:
        assert exc.code in DECODE_CODES, exc.code
        assert str(exc), "a reason is given"


@pytest.mark.parametrize("decoder", DECODERS, ids=lambda d: d.__name__)
@_SETTINGS
@given(payload=st.binary(max_size=512))
def test_any_bytes_decode_or_raise_a_known_code(decoder, payload: bytes) -> None:
    _decodes_or_known_error(decoder, payload)


@pytest.mark.parametrize("decoder", DECODERS, ids=lambda d: d.__name__)
@_SETTINGS
@given(obj=_objects | _message_like)
def test_any_msgpack_object_decodes_or_raises_a_known_code(decoder, obj: object) -> None:
    _decodes_or_known_error(decoder, msgpack.packb(obj, use_bin_type=True))


@_SETTINGS
@given(payload=st.binary(max_size=512) | _message_like.map(lambda o: msgpack.packb(o, use_bin_type=True)))
def test_peeks_never_raise_and_return_only_safe_values(payload: bytes) -> None:
    vehicle, session = peek_ids(payload, LIMITS)
    assert vehicle is None or LIMITS.id_ok(vehicle)
    assert session is None or LIMITS.id_ok(session)
    seq = peek_seq(payload)
    assert seq is None or (type(seq) is int and 0 <= seq < 2**63)


_ids = st.from_regex(r"\A[A-Za-z0-9][A-Za-z0-9_.-]{0,20}\Z")


@_SETTINGS
@given(
    vehicle=_ids,
    session=_ids,
    seq=st.integers(0, 2**63 - 1),
    stamp_ns=st.integers(0, 2**63 - 1),
    n=st.integers(1, 50),
    with_intensity=st.booleans(),
    with_offsets=st.booleans(),
    yaw=st.floats(-math.pi, math.pi),
    seed=st.integers(0, 2**32 - 1),
)
def test_scan_round_trips(
    vehicle, session, seq, stamp_ns, n, with_intensity, with_offsets, yaw, seed
) -> None:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-100, 100, (n, 3)).astype(np.float32)
    intensity = rng.uniform(0, 1, n).astype(np.float32) if with_intensity else None
    offsets = rng.uniform(0, 0.1, n).astype(np.float32) if with_offsets else None
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:3, 3] = rng.uniform(-1000, 1000, 3)
    cov = np.diag(rng.uniform(0, 1, 6))
    msg = scan_from_arrays(vehicle, session, seq, stamp_ns, xyz, intensity, offsets, T, cov, limits=LIMITS)
    back = decode_scan(encode(msg), LIMITS)
    assert back == msg
    np.testing.assert_array_equal(back.xyz(), xyz.astype(np.float64))
    np.testing.assert_array_equal(back.prior_pose(), T)
    if with_intensity:
        np.testing.assert_array_equal(back.intensity(), intensity)


@_SETTINGS
@given(
    ix=st.integers(-(2**31), 2**31 - 1),
    iy=st.integers(-(2**31), 2**31 - 1),
    version=st.integers(1, 2**63 - 1),
    n=st.integers(0, 40),
    seed=st.integers(0, 2**32 - 1),
)
def test_tile_update_round_trips(ix, iy, version, n, seed) -> None:
    xyz = np.random.default_rng(seed).uniform(-50, 50, (n, 3))
    msg = tile_update_from_arrays("default", ix, iy, version, xyz)
    assert decode_tile_update(encode(msg)) == msg


# ---------------------------------------------------------------------------------------------
# mutations of one valid scan: one field replaced by a value of a wrong type or out of range
# ---------------------------------------------------------------------------------------------

_POINTS = np.random.default_rng(1).uniform(-10, 10, (32, 3)).astype("<f4")
_VALID = msgpack.unpackb(
    encode(
        scan_from_arrays(
            "car", "s1", 3, 10**18, _POINTS, prior_pose=np.eye(4), prior_covariance=np.eye(6) * 0.01
        )
    ),
    raw=False,
)

_ints = st.integers(-(2**63), 2**64 - 1)  # what msgpack can pack
_not_int = (
    st.text(max_size=5)
    | st.floats(allow_nan=True)
    | st.binary(max_size=5)
    | st.lists(_ints, max_size=3)
    | st.none()
)
_not_str = (
    _ints
    | st.floats(allow_nan=True)
    | st.binary(max_size=5)
    | st.lists(_ints, max_size=3)
    | st.none()
    | st.booleans()
)
_not_bytes = st.text(max_size=5) | _ints | st.floats(allow_nan=True) | st.lists(_ints, max_size=3)

# field -> (strategy of a bad value, the documented code)
MUTATIONS: dict[str, tuple[st.SearchStrategy[object], set[str]]] = {
    "vehicle": (_not_str, {ErrorCode.INVALID_FIELD}),
    "session": (_not_str, {ErrorCode.INVALID_FIELD}),
    "seq": (_not_int | st.booleans(), {ErrorCode.INVALID_FIELD}),
    "seq_range": (
        st.integers(min_value=-(2**63), max_value=-1) | st.integers(min_value=2**63, max_value=2**64 - 1),
        {ErrorCode.INVALID_FIELD},
    ),
    "stamp_ns": (_not_int | st.booleans(), {ErrorCode.INVALID_FIELD}),
    "stamp_range": (
        st.integers(min_value=-(2**63), max_value=-1) | st.integers(min_value=2**63, max_value=2**64 - 1),
        {ErrorCode.INVALID_FIELD},
    ),
    "fields": (
        _not_str | st.text(max_size=6).filter(lambda s: s not in ("xyz", "xyzi")),
        {ErrorCode.INVALID_FIELD},
    ),
    "points": (_not_bytes, {ErrorCode.INVALID_FIELD}),
    "points_len": (
        st.binary(min_size=1, max_size=200).filter(lambda b: len(b) % 12),
        {ErrorCode.INVALID_POINTS},
    ),
    "time_offsets": (_not_bytes, {ErrorCode.INVALID_FIELD}),
    "prior": (_not_str.filter(lambda v: v is not None) | st.text(max_size=5), {ErrorCode.INVALID_FIELD}),
    "prior_pose": (
        st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=16, max_size=16).filter(
            lambda v: not (np.allclose(np.reshape(v, (4, 4)), np.eye(4)) if np.all(np.isfinite(v)) else False)
        ),
        {ErrorCode.INVALID_PRIOR},
    ),
    "ids": (
        st.sampled_from(
            ["", "a/b", "*", "**", "$*", "a?b", "a#b", "a b", ".", "..", "a\nb", "é", "-x", "a" * 65]
        ),
        {ErrorCode.INVALID_ID},
    ),
    "v": (_ints.filter(lambda v: v != 1), {ErrorCode.UNSUPPORTED_VERSION}),
}


def _mutated(kind: str, value: object) -> dict:
    doc = dict(_VALID)
    if kind == "seq_range":
        doc["seq"] = value
    elif kind == "stamp_range":
        doc["stamp_ns"] = value
    elif kind == "points_len":
        doc["points"] = value
    elif kind == "prior_pose":
        doc["prior"] = {**doc["prior"], "pose": value}
    elif kind == "ids":
        doc["session"] = value
    else:
        doc[kind] = value
    return doc


@pytest.mark.parametrize("kind", list(MUTATIONS))
@settings(max_examples=40, deadline=2000, derandomize=True)
@given(data=st.data())
def test_one_bad_field_gets_the_documented_code(kind: str, data: st.DataObject) -> None:
    strategy, codes = MUTATIONS[kind]
    value = data.draw(strategy)
    if kind == "prior_pose" and np.all(np.isfinite(value)):
        T = np.reshape(value, (4, 4))
        R = T[:3, :3]
        rigid = (
            np.allclose(T[3], [0, 0, 0, 1], atol=1e-9)
            and np.abs(R @ R.T - np.eye(3)).max() <= 1e-4
            and np.linalg.det(R) > 0
        )
        if rigid:  # a random rigid transform is valid: not a mutation
            return
    payload = msgpack.packb(_mutated(kind, value), use_bin_type=True)
    with pytest.raises(BadMessageError) as info:
        decode_scan(payload, LIMITS)
    assert info.value.code in codes, (kind, value, info.value.code, str(info.value))


def test_the_unmutated_scan_decodes() -> None:
    """The control: the scan every mutation starts from is valid."""
    assert decode_scan(msgpack.packb(_VALID, use_bin_type=True), LIMITS).seq == 3
