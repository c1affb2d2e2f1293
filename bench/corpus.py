"""The hostile-input corpus: writes ``tests/corpus/`` (case files and ``cases.json``) from recipes.

Run from the repository root::

    python -m bench.corpus [--out tests/corpus]

Three surfaces, one manifest (``cases.json``, a list of cases, each with ``name``, ``surface``,
``description`` and ``expect``):

* ``wire``: a payload published on ``randt/fleet/<key>/scan`` (``key``), after optional ``setup``
  scans of the same session that must each get a pose. ``payload`` is ``{"file": ...}`` (committed,
  at most :data:`MAX_FILE_BYTES`) or ``{"recipe": ...}`` for big ones, built at run time by
  :func:`build_payload` (a 16 MiB msgpack bomb is a dozen bytes of recipe, not a committed file).
  ``expect``: ``{"answer": "error", "codes": [...]}`` (an error message on the vehicle's error key
  with one of the documented codes, ``docs/wire-format.md``), ``{"answer": "pose"}`` (the protocol
  accepts it), or ``{"answer": "none", "codes": [...]}`` (no valid key to answer on: the rejection
  is only counted, ``randt_scans_rejected_total{reason}``).
* ``http``: a raw request line (``method``, ``target`` sent byte for byte, no client-side
  normalization of ``..`` or percent escapes) and ``expect``: ``{"status", "body"}`` where ``body``
  is the shape of the JSON error body (``docs/api.md``): ``validation`` (FastAPI's 422
  ``{"detail": [...]}``), ``not_found`` (``{"detail"}``, ``resource`` when the resource is ours),
  ``detail`` (``{"detail": "..."}``).
* ``file``: a malformed input to a CLI command (``argv``, with ``{case}`` for the case's file and
  ``{good}`` for a valid cloud written at run time) and ``expect``: ``{"exit": <randt exit code>}``
  (``cli/errors.py``, ``randt --help``).

Everything is deterministic (fixed seeds), so ``tests/test_corpus.py`` can check that the committed
corpus is what this script writes.
"""

from __future__ import annotations

import argparse
import json
import shutil
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "tests" / "corpus"

#: Wire payloads larger than this are not committed: the manifest holds their recipe.
MAX_FILE_BYTES = 16 * 1024

#: The vehicle every hostile wire case publishes as (unless the case is about the key).
HOSTILE = "hostile"
#: Stamp of a case session's first scan (ns); later scans add 0.1 s per seq.
T0_NS = 1_700_000_000_000_000_000
#: Points of a setup scan and of a case that must reach the matcher (a synthetic room).
ROOM_POINTS = 3000
#: Default ``max_payload_bytes`` of the service (service/settings.py): the size limit cases aim at.
MAX_PAYLOAD = 16 * 1024 * 1024
#: Default ``max_points``.
MAX_POINTS = 300_000

_IDENTITY = np.eye(4).ravel().tolist()
_COV = np.diag([0.01] * 3 + [0.001] * 3).ravel().tolist()


# --------------------------------------------------------------------------------------------
# payload recipes (shared by the generator and the runner)
# --------------------------------------------------------------------------------------------


def room_points(n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) float32: floor, walls and a pillar (``randt.core.scenes.synthetic_room``), first n points."""
    from randt.core.scenes import synthetic_room

    pts = synthetic_room(np.random.default_rng(seed), max(n // 3, 8)).astype("<f4")
    return np.ascontiguousarray(pts[np.random.default_rng(seed + 1).permutation(len(pts))[:n]])


def scan_doc(session: str, seq: int, /, *, n: int = 32, **override: Any) -> dict[str, Any]:
    """A valid scan as a dict in wire order.

    ``override`` replaces fields (or, given :data:`DELETE`, removes them).
    """
    doc: dict[str, Any] = {
        "v": 1,
        "vehicle": HOSTILE,
        "session": session,
        "seq": seq,
        "stamp_ns": T0_NS + (seq % 1_000_000) * 100_000_000,  # 0.1 s per seq (a seq of 2^62 stays in range)
        "fields": "xyz",
        "points": room_points(n).tobytes(),
        "time_offsets": None,
        "prior": None,
    }
    return _overridden(doc, override)


DELETE = "__delete__"

_ENCODING: dict[str, Any] = {
    "voxel_m": 0.2,
    "xyz_quantum_m": 0.01,
    "time_quantum_s": 1e-5,
    "intensity_offset": 0.0,
    "intensity_quantum": 1.0,
    "layout": "delta-zigzag-planar",
    "codec": "zstd",
}


def _overridden(doc: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """``doc`` with the ``override`` fields set, those given as :data:`DELETE` removed."""
    for key, value in override.items():
        if value is DELETE:
            doc.pop(key, None)
        else:
            doc[key] = value
    return doc


def zstd_frame(blocks: list[tuple[str, bytes, int]]) -> bytes:
    """A zstd frame (RFC 8878) built by hand from ``("raw", data, 0)`` and ``("rle", byte, count)``
    blocks, so committed cases do not depend on a zstd library's compressor output. No content
    size, no checksum, a 128 KiB window (blocks of at most 128 KiB)."""
    out = bytearray(b"\x28\xb5\x2f\xfd\x00\x38")  # magic, descriptor 0, window log 17
    for k, (kind, data, count) in enumerate(blocks):
        size = len(data) if kind == "raw" else count
        header = (size << 3) | ((0 if kind == "raw" else 1) << 1) | (k == len(blocks) - 1)
        out += header.to_bytes(3, "little") + data
    return bytes(out)


def zstd_stored(body: bytes) -> bytes:
    """``body`` as a valid zstd frame of raw (stored) blocks."""
    step = 128 * 1024
    chunks = [body[i : i + step] for i in range(0, len(body), step)] or [b""]
    return zstd_frame([("raw", c, 0) for c in chunks])


def zstd_bomb(total: int) -> bytes:
    """A zstd frame of RLE blocks that decompresses to ``total`` zero bytes (64 MiB in 2 KiB)."""
    step = 128 * 1024
    return zstd_frame([("rle", b"\x00", min(step, total - i)) for i in range(0, total, step)])


def v2_scan_doc(session: str, seq: int, /, *, n: int = 32, **override: Any) -> dict[str, Any]:
    """A valid compact (v2) scan as a dict in wire order (docs/wire-format.md, Scan v2); bodies
    in stored zstd frames. ``override`` as :func:`scan_doc`."""
    from randt.wire.packing import pack_int_columns

    q = np.rint(room_points(n).astype(np.float64).T / _ENCODING["xyz_quantum_m"]).astype(np.int32)
    doc: dict[str, Any] = {
        "v": 2,
        "vehicle": HOSTILE,
        "session": session,
        "seq": seq,
        "stamp_ns": T0_NS + (seq % 1_000_000) * 100_000_000,
        "n_points": n,
        "encoding": dict(_ENCODING),
        "xyz": zstd_stored(pack_int_columns(q)),
        "time_offsets": None,
        "intensity": None,
        "prior": None,
    }
    return _overridden(doc, override)


def pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _map_bomb(entries: int) -> bytes:
    """A msgpack map: ``v`` = 1, then ``entries`` distinct 4-character str keys with nil values."""
    alphabet = np.frombuffer(b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789", np.uint8)
    k = np.arange(entries, dtype=np.int64)
    body = np.empty((entries, 6), np.uint8)
    body[:, 0] = 0xA4  # fixstr of 4
    for j in range(4):
        body[:, 1 + j] = alphabet[(k // 62**j) % 62]
    body[:, 5] = 0xC0  # nil
    return b"\xdf" + struct.pack(">I", entries + 1) + b"\xa1v\x01" + body.tobytes()


def build_payload(recipe: dict[str, Any]) -> bytes:
    """The payload of a ``{"recipe": ...}`` wire case (deterministic)."""
    kind = recipe["kind"]
    if kind == "zeros":
        return b"\x00" * int(recipe["bytes"])
    if kind == "map_bomb":
        return _map_bomb(int(recipe["entries"]))
    if kind == "nil_array_points":
        n = int(recipe["items"])
        return _raw_map(recipe["session"], {"points": b"\xdd" + struct.pack(">I", n) + b"\xc0" * n})
    if kind == "too_many_points":
        doc = scan_doc(recipe["session"], recipe["seq"], n=8)
        doc["points"] = np.zeros((int(recipe["points"]), 3), "<f4").tobytes()
        return pack(doc)
    if kind == "room":
        seq = int(recipe["seq"])
        points = room_points(int(recipe.get("n", ROOM_POINTS))).copy()
        points[: int(recipe.get("extreme", 0))] = 3.0e38  # finite float32, far beyond any sensor
        override: dict[str, Any] = {"points": points.tobytes()}
        if "stamp_ns" in recipe:
            override["stamp_ns"] = int(recipe["stamp_ns"])
        if recipe.get("v2"):
            return pack(v2_scan_doc(recipe["session"], seq, n=int(recipe.get("n", ROOM_POINTS))))
        return pack(scan_doc(recipe["session"], seq, **override))
    raise ValueError(f"unknown recipe kind {kind!r}")


# --------------------------------------------------------------------------------------------
# wire cases
# --------------------------------------------------------------------------------------------

_WireCase = tuple[str, str, Callable[[str], bytes] | dict[str, Any], dict[str, Any]]


def _err(*codes: str) -> dict[str, Any]:
    return {"answer": "error", "codes": list(codes)}


def _f(session: str, /, **override: Any) -> bytes:
    return pack(scan_doc(session, 0, **override))


def _nested(depth: int) -> bytes:
    return b"\x91" * depth + b"\xc0"


def _raw_map(session: str, replace: dict[str, bytes]) -> bytes:
    """A scan map whose listed fields' values are raw msgpack bytes (headers that lie, nesting...)."""
    doc = scan_doc(session, 0)
    out = bytearray(b"\xde" + struct.pack(">H", len(doc)))
    for key, value in doc.items():
        out += pack(key) + (replace[key] if key in replace else pack(value))
    return bytes(out)


def _prior(pose: list[Any] | None = None, cov: list[Any] | None = None) -> dict[str, Any]:
    return {"pose": _IDENTITY if pose is None else pose, "covariance": _COV if cov is None else cov}


def _rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def wire_cases() -> list[dict[str, Any]]:
    """Every wire case (each with its own session id, so cases never share session state)."""
    nan_pts = room_points(32).copy()
    nan_pts[5, 1] = np.nan
    inf_pts = room_points(32).copy()
    inf_pts[0, 2] = np.inf
    xyzi = np.c_[room_points(32), np.ones(32, "<f4")].astype("<f4")
    xyzi[3, 3] = np.nan
    scale2 = np.eye(4) * 2.0
    scale2[3, 3] = 1.0
    reflect = np.diag([1.0, 1.0, -1.0, 1.0])
    shear = np.eye(4)
    shear[0, 1] = 0.3
    bad_last = np.eye(4)
    bad_last[3, 0] = 1.0
    nan_pose = np.eye(4)
    nan_pose[0, 3] = np.nan
    asym = np.diag([0.01] * 6)
    asym[0, 1] = 1.0
    neg = -np.eye(6)
    nan_cov = np.diag([0.01] * 6)
    nan_cov[2, 2] = np.inf
    good = scan_doc("x", 0)

    C: list[tuple[str, str, Any, dict[str, Any]]] = [
        # framing
        ("truncated-half", "a valid scan cut in half", lambda s: _f(s)[: len(_f(s)) // 2], _err("malformed")),
        ("truncated-one-byte", "only a map header (0x89)", lambda s: b"\x89", _err("malformed")),
        ("empty-payload", "zero bytes", lambda s: b"", _err("malformed")),
        (
            "not-msgpack",
            "0xc1 (never used by msgpack) and text",
            lambda s: b"\xc1\xc1 not msgpack",
            _err("malformed"),
        ),
        (
            "trailing-bytes",
            "a valid scan followed by garbage",
            lambda s: _f(s) + b"\x00\x01",
            _err("malformed"),
        ),
        ("top-level-array", "an array instead of a map", lambda s: pack([1, 2, 3]), _err("malformed")),
        ("top-level-int", "a bare integer", lambda s: pack(7), _err("malformed")),
        ("int-map-keys", "a map with integer keys", lambda s: pack({1: 2, 3: 4}), _err("malformed")),
        (
            "oversized",
            "one byte more than max_payload_bytes (16 MiB), checked before unpacking",
            {"kind": "zeros", "bytes": MAX_PAYLOAD + 1},
            _err("payload_too_large"),
        ),
        # lying headers and nesting
        (
            "declared-map-2e32",
            "a map32 header declaring 2^32-1 entries, then 3 bytes",
            lambda s: b"\xdf\xff\xff\xff\xff\xa1v\x01",
            _err("malformed"),
        ),
        (
            "declared-array-2e32",
            "points given as an array32 header declaring 2^32-1 items",
            lambda s: _raw_map(s, {"points": b"\xdd\xff\xff\xff\xff\xc0"}),
            _err("malformed"),
        ),
        (
            "declared-bin-4gib",
            "points given as a bin32 header declaring 4 GiB, with 12 bytes",
            lambda s: _raw_map(s, {"points": b"\xc6\xff\xff\xff\xff" + b"\x00" * 12}),
            _err("malformed"),
        ),
        (
            "declared-str-4gib",
            "vehicle given as a str32 header declaring 4 GiB",
            lambda s: _raw_map(s, {"vehicle": b"\xdb\xff\xff\xff\xff" + b"ab"}),
            _err("malformed"),
        ),
        (
            "deep-nesting-prior",
            "prior is 10 000 nested one-element arrays",
            lambda s: _raw_map(s, {"prior": _nested(10_000)}),
            _err("malformed", "invalid_field", "invalid_prior"),
        ),
        (
            "deep-nesting-top",
            "the payload is 10 000 nested arrays",
            lambda s: _nested(10_000),
            _err("malformed"),
        ),
        (
            "map-bomb-16mib",
            "eight 16 MiB maps of 2.8 million tiny entries each (v = 1, no scan fields): costly to unpack",
            {"kind": "map_bomb", "entries": (MAX_PAYLOAD - 64) // 6, "repeat": 8},
            _err("missing_field", "malformed", "payload_too_large"),
        ),
        (
            "array-bomb-points",
            "points given as an array of 8 million nils (8 MiB)",
            {"kind": "nil_array_points", "items": 8_000_000},
            _err("invalid_field", "malformed"),
        ),
        # versions
        ("v-missing", "no v", lambda s: _f(s, v=DELETE), _err("missing_field")),
        ("v-3", "schema version 3", lambda s: _f(s, v=3), _err("unsupported_version")),
        ("v-string", "v is the string '1'", lambda s: _f(s, v="1"), _err("invalid_field")),
        ("v-bool", "v is true", lambda s: _f(s, v=True), _err("invalid_field")),
    ]
    # every required field missing, every field of the wrong type
    for field in ("vehicle", "session", "seq", "stamp_ns", "fields", "points"):
        C.append(
            (
                f"missing-{field}",
                f"no {field}",
                (lambda fl: lambda s: _f(s, **{fl: DELETE}))(field),
                _err("missing_field"),
            )
        )
    wrong: list[tuple[str, Any, str]] = [
        ("vehicle", 42, "invalid_field"),
        ("vehicle", b"hostile", "invalid_field"),
        ("session", ["a"], "invalid_field"),
        ("session", None, "invalid_field"),
        ("seq", "twelve", "invalid_field"),
        ("seq", 1.0, "invalid_field"),
        ("seq", -1, "invalid_field"),
        ("seq", True, "invalid_field"),
        ("stamp_ns", "now", "invalid_field"),
        ("stamp_ns", -5, "invalid_field"),
        ("stamp_ns", 1.7e18, "invalid_field"),
        ("fields", "xyzrgb", "invalid_field"),
        ("fields", 3, "invalid_field"),
        ("points", "text not bin", "invalid_field"),
        ("points", 12, "invalid_field"),
        ("points", {"a": 1}, "invalid_field"),
        ("time_offsets", "text", "invalid_field"),
        ("time_offsets", [0.0] * 32, "invalid_field"),
        ("prior", "gnss", "invalid_field"),
        ("prior", [1, 2], "invalid_field"),
    ]
    for field, value, code in wrong:
        label = (
            type(value).__name__
            if not isinstance(value, int | float) or isinstance(value, bool)
            else repr(value)
        )
        name = f"wrong-{field}-{label}".replace("'", "").replace(".", "p").replace("-", "-")
        C.append(
            (
                name,
                f"{field} = {value!r}",
                (lambda fl, va: lambda s: _f(s, **{fl: va}))(field, value),
                _err(code),
            )
        )
    C += [
        ("seq-2e64", "seq = 2^64-1 (uint64)", lambda s: _f(s, seq=2**64 - 1), _err("invalid_field")),
        (
            "stamp-2e64",
            "stamp_ns = 2^64-1 (uint64)",
            lambda s: _f(s, stamp_ns=2**64 - 1),
            _err("invalid_field"),
        ),
        (
            "prior-pose-15",
            "prior pose of 15 floats",
            lambda s: _f(s, prior=_prior(_IDENTITY[:15])),
            _err("invalid_field"),
        ),
        (
            "prior-pose-strings",
            "prior pose of strings",
            lambda s: _f(s, prior=_prior(["1"] * 16)),
            _err("invalid_field"),
        ),
        (
            "prior-cov-35",
            "prior covariance of 35 floats",
            lambda s: _f(s, prior=_prior(cov=_COV[:35])),
            _err("invalid_field"),
        ),
        (
            "prior-missing-cov",
            "prior without covariance",
            lambda s: _f(s, prior={"pose": _IDENTITY}),
            _err("missing_field"),
        ),
        # non-finite and extreme values
        (
            "points-nan",
            "a NaN coordinate",
            lambda s: _f(s, points=nan_pts.tobytes()),
            _err("nonfinite_points"),
        ),
        (
            "points-inf",
            "an infinite coordinate",
            lambda s: _f(s, points=inf_pts.tobytes()),
            _err("nonfinite_points"),
        ),
        (
            "intensity-nan",
            "xyzi with a NaN intensity",
            lambda s: _f(s, fields="xyzi", points=xyzi.tobytes()),
            _err("nonfinite_points"),
        ),
        (
            "offsets-nan",
            "a NaN time offset",
            lambda s: _f(s, time_offsets=np.r_[np.zeros(31), np.nan].astype("<f4").tobytes()),
            _err("invalid_points"),
        ),
        (
            "offsets-negative",
            "a negative time offset",
            lambda s: _f(s, time_offsets=np.full(32, -0.01, "<f4").tobytes()),
            _err("invalid_points"),
        ),
        (
            "offsets-huge",
            "a time offset of 1e30 s",
            lambda s: _f(s, time_offsets=np.full(32, 1e30, "<f4").tobytes()),
            _err("invalid_points"),
        ),
        (
            "offsets-short",
            "31 time offsets for 32 points",
            lambda s: _f(s, time_offsets=np.zeros(31, "<f4").tobytes()),
            _err("invalid_points"),
        ),
        # byte lengths
        (
            "points-13-bytes",
            "13 bytes of xyz points (not a multiple of 12)",
            lambda s: _f(s, points=b"\x00" * 13),
            _err("invalid_points"),
        ),
        (
            "points-xyzi-60-bytes",
            "60 bytes of xyzi points (not a multiple of 16)",
            lambda s: _f(s, fields="xyzi", points=room_points(5).tobytes()),
            _err("invalid_points"),
        ),
        ("points-empty", "no points", lambda s: _f(s, points=b""), _err("empty_scan")),
        (
            "points-too-many",
            "max_points + 1 points (3.6 MB)",
            {"kind": "too_many_points", "points": MAX_POINTS + 1},
            _err("too_many_points"),
        ),
        # priors that are not rigid / covariances that are not PSD
        (
            "prior-scale",
            "prior pose scaled by 2",
            lambda s: _f(s, prior=_prior(scale2.ravel().tolist())),
            _err("invalid_prior"),
        ),
        (
            "prior-reflection",
            "prior pose with det -1",
            lambda s: _f(s, prior=_prior(reflect.ravel().tolist())),
            _err("invalid_prior"),
        ),
        (
            "prior-shear",
            "prior pose with a shear",
            lambda s: _f(s, prior=_prior(shear.ravel().tolist())),
            _err("invalid_prior"),
        ),
        (
            "prior-last-row",
            "prior pose whose last row is not [0 0 0 1]",
            lambda s: _f(s, prior=_prior(bad_last.ravel().tolist())),
            _err("invalid_prior"),
        ),
        (
            "prior-nan",
            "prior pose with a NaN",
            lambda s: _f(s, prior=_prior(nan_pose.ravel().tolist())),
            _err("invalid_prior"),
        ),
        (
            "prior-cov-asym",
            "asymmetric covariance",
            lambda s: _f(s, prior=_prior(cov=asym.ravel().tolist())),
            _err("invalid_prior"),
        ),
        (
            "prior-cov-negative",
            "negative definite covariance",
            lambda s: _f(s, prior=_prior(cov=neg.ravel().tolist())),
            _err("invalid_prior"),
        ),
        (
            "prior-cov-inf",
            "covariance with an Inf",
            lambda s: _f(s, prior=_prior(cov=nan_cov.ravel().tolist())),
            _err("invalid_prior"),
        ),
        # ids
        ("session-star", "session '*'", lambda s: _f(s, session="*"), _err("invalid_id")),
        ("session-doublestar", "session '**'", lambda s: _f(s, session="**"), _err("invalid_id")),
        ("session-dollar", "session '$*'", lambda s: _f(s, session="$*"), _err("invalid_id")),
        ("session-slash", "session 'a/b'", lambda s: _f(s, session="a/b"), _err("invalid_id")),
        ("session-dotdot", "session '..'", lambda s: _f(s, session=".."), _err("invalid_id")),
        (
            "session-traversal",
            "session '../../etc'",
            lambda s: _f(s, session="../../etc"),
            _err("invalid_id"),
        ),
        ("session-nul", "session 'a\\x00b'", lambda s: _f(s, session="a\x00b"), _err("invalid_id")),
        ("session-unicode", "session 'séance'", lambda s: _f(s, session="séance"), _err("invalid_id")),
        (
            "session-rtl",
            "session with a right-to-left override",
            lambda s: _f(s, session="a\u202eb"),
            _err("invalid_id"),
        ),
        (
            "session-65-chars",
            "session of 65 characters",
            lambda s: _f(s, session="a" * 65),
            _err("invalid_id"),
        ),
        ("session-hidden", "session '.hidden'", lambda s: _f(s, session=".hidden"), _err("invalid_id")),
        (
            "vehicle-star-in-message",
            "vehicle '*' in the message",
            lambda s: _f(s, vehicle="*"),
            _err("invalid_id"),
        ),
        (
            "vehicle-mismatch",
            "vehicle 'victim' published on hostile's key",
            lambda s: _f(s, vehicle="victim"),
            _err("invalid_field"),
        ),
    ]
    # compact (v2) scans: bodies that lie about their size, bombs, bad encodings
    from randt.wire.packing import pack_int_columns

    n2 = 32

    def _v2(s: str, **override: Any) -> bytes:
        return pack(v2_scan_doc(s, 0, n=n2, **override))

    def _v2_enc(**change: Any) -> dict[str, Any]:
        return {k: v for k, v in {**_ENCODING, **change}.items() if v is not DELETE}

    xyz_v2 = v2_scan_doc("x", 0, n=n2)["xyz"]
    C += [
        (
            "v-2-with-v1-fields",
            "v = 2 with the fields of a v1 scan (no n_points, encoding, xyz)",
            lambda s: _f(s, v=2),
            _err("missing_field"),
        ),
        (
            "v2-zstd-bomb",
            "v2 scan of 32 points whose xyz body is a 2 KiB zstd frame of 64 MiB (stopped at 384 bytes)",
            lambda s: _v2(s, xyz=zstd_bomb(64 * 1024 * 1024)),
            _err("invalid_compression"),
        ),
        (
            "v2-zstd-bomb-intensity",
            "v2 scan whose intensity body is a zstd frame of 16 MiB",
            lambda s: _v2(s, intensity=zstd_bomb(16 * 1024 * 1024)),
            _err("invalid_compression"),
        ),
        (
            "v2-frame-truncated",
            "v2 xyz body cut in the middle of its zstd frame",
            lambda s: _v2(s, xyz=xyz_v2[: len(xyz_v2) // 2]),
            _err("invalid_compression"),
        ),
        (
            "v2-not-zstd",
            "v2 xyz body that is not a zstd frame",
            lambda s: _v2(s, xyz=b"\x00" * 384),
            _err("invalid_compression"),
        ),
        (
            "v2-frame-trailing",
            "v2 xyz body: a valid frame followed by 7 bytes",
            lambda s: _v2(s, xyz=xyz_v2 + b"garbage"),
            _err("invalid_compression"),
        ),
        (
            "v2-count-too-high",
            "v2 n_points 33 for a body of 32 points",
            lambda s: _v2(s, n_points=33),
            _err("invalid_compression"),
        ),
        (
            "v2-count-too-low",
            "v2 n_points 31 for a body of 32 points",
            lambda s: _v2(s, n_points=31),
            _err("invalid_compression"),
        ),
        ("v2-count-zero", "v2 n_points 0", lambda s: _v2(s, n_points=0), _err("empty_scan")),
        (
            "v2-count-huge",
            "v2 n_points max_points + 1 with a 32-point body (refused before decompressing)",
            lambda s: _v2(s, n_points=MAX_POINTS + 1),
            _err("too_many_points"),
        ),
        ("v2-count-missing", "v2 without n_points", lambda s: _v2(s, n_points=DELETE), _err("missing_field")),
        (
            "v2-codec-lz4",
            "v2 codec 'lz4' (not part of the format)",
            lambda s: _v2(s, encoding=_v2_enc(codec="lz4")),
            _err("invalid_field"),
        ),
        (
            "v2-layout-unknown",
            "v2 layout 'rows'",
            lambda s: _v2(s, encoding=_v2_enc(layout="rows")),
            _err("invalid_field"),
        ),
        (
            "v2-quantum-zero",
            "v2 xyz_quantum_m 0",
            lambda s: _v2(s, encoding=_v2_enc(xyz_quantum_m=0.0)),
            _err("invalid_field"),
        ),
        (
            "v2-quantum-nan",
            "v2 time_quantum_s NaN",
            lambda s: _v2(s, encoding=_v2_enc(time_quantum_s=float("nan"))),
            _err("invalid_field"),
        ),
        (
            "v2-encoding-missing-codec",
            "v2 encoding without codec",
            lambda s: _v2(s, encoding=_v2_enc(codec=DELETE)),
            _err("missing_field"),
        ),
        (
            "v2-codec-none-short",
            "v2 codec none with an xyz body one byte short",
            lambda s: _v2(s, encoding=_v2_enc(codec="none"), xyz=b"\x00" * (12 * n2 - 1)),
            _err("invalid_points"),
        ),
        (
            "v2-offsets-negative",
            "v2 time offsets decoding to -10 us",
            lambda s: _v2(s, time_offsets=zstd_stored(b"\x01" + b"\x00" * (4 * n2 - 1))),
            _err("invalid_points"),
        ),
        (
            "v2-offsets-too-late",
            "v2 time offsets decoding to 2 s (beyond max_time_offset_s)",
            lambda s: _v2(s, time_offsets=zstd_stored(pack_int_columns(np.full((1, n2), 200_000)))),
            _err("invalid_points"),
        ),
        ("v2-xyz-text", "v2 xyz given as a str", lambda s: _v2(s, xyz="text"), _err("invalid_field")),
        (
            "v2-vehicle-slash",
            "v2 vehicle 'a/b'",
            lambda s: _v2(s, vehicle="a/b"),
            _err("invalid_id"),
        ),
    ]
    del good
    cases: list[dict[str, Any]] = []
    for name, description, payload, expect in C:
        cases.append(
            {
                "name": f"wire-{name}",
                "surface": "wire",
                "description": description,
                "key": HOSTILE,
                "setup": [],
                "payload": payload,
                "expect": expect,
            }
        )
    # keys that cannot be answered on
    cases.append(
        {
            "name": "wire-key-unicode",
            "surface": "wire",
            "description": "a scan of vehicle 'véhicule' on randt/fleet/véhicule/scan: "
            "no valid key to answer on",
            "key": "véhicule",
            "setup": [],
            "payload": lambda s: _f(s, vehicle="véhicule"),
            "expect": {"answer": "none", "codes": ["invalid_id"]},
        }
    )
    cases.append(
        {
            "name": "wire-key-leading-dash",
            "surface": "wire",
            "description": "a scan on randt/fleet/-x/scan (an id may not start with '-')",
            "key": "-x",
            "setup": [],
            "payload": lambda s: _f(s, vehicle="-x"),
            "expect": {"answer": "none", "codes": ["invalid_id"]},
        }
    )

    # sequences and time: each case's session first gets setup scans that must be answered with poses
    def room(s: str, seq: int, **kw: Any) -> dict[str, Any]:
        return {"kind": "room", "session": s, "seq": seq, **kw}

    seq_cases: list[tuple[str, str, list[dict[str, Any]], dict[str, Any], dict[str, Any]]] = [
        (
            "seq-duplicate",
            "seq 0, 1, then 1 again",
            [{"seq": 0}, {"seq": 1}],
            {"seq": 1},
            _err("duplicate_seq"),
        ),
        (
            "seq-backwards",
            "seq 0, 1, 2, then 1",
            [{"seq": 0}, {"seq": 1}, {"seq": 2}],
            {"seq": 1},
            _err("out_of_order"),
        ),
        (
            "seq-jump-2e62",
            "seq 0, then 2^62 (allowed: seq only increases)",
            [{"seq": 0}],
            {"seq": 2**62},
            {"answer": "pose"},
        ),
        (
            "seq-after-jump",
            "seq 0, 2^62, then 1: refused (the session's last seq is 2^62)",
            [{"seq": 0}, {"seq": 2**62}],
            {"seq": 1},
            _err("out_of_order"),
        ),
        (
            "stamp-backwards",
            "seq 0, 1, then 2 stamped 10 s before seq 0 (stamps are not checked: answered)",
            [{"seq": 0}, {"seq": 1}],
            {"seq": 2, "stamp_ns": T0_NS - 10_000_000_000},
            {"answer": "pose"},
        ),
        (
            "stamp-jump-2e62",
            "seq 0, 1, then 2 stamped 2^62 ns later (answered: a pose, or registration_failed)",
            [{"seq": 0}, {"seq": 1}],
            {"seq": 2, "stamp_ns": T0_NS + 2**62},
            {"answer": "pose_or_error", "codes": ["registration_failed"]},
        ),
        (
            "points-extreme",
            "ten points at 3e38 m (finite float32) among a room",
            [{"seq": 0}],
            {"seq": 1, "extreme": 10},
            {"answer": "pose_or_error", "codes": ["registration_failed"]},
        ),
        (
            "v2-after-v1",
            "seq 0 as a v1 scan, then seq 1 as a compact v2 scan of the same session: a pose",
            [{"seq": 0}],
            {"seq": 1, "v2": True},
            {"answer": "pose"},
        ),
    ]
    for name, description, setup, final, expect in seq_cases:
        recipe_setup = [room("{session}", **st) for st in setup]
        payload = {"kind": "room", "session": "{session}", **final}
        cases.append(
            {
                "name": f"wire-{name}",
                "surface": "wire",
                "description": description,
                "key": HOSTILE,
                "setup": recipe_setup,
                "payload": payload,
                "expect": expect,
            }
        )
    for k, case in enumerate(cases):
        case["session"] = f"c{k:03d}"
    return cases


# --------------------------------------------------------------------------------------------
# HTTP cases
# --------------------------------------------------------------------------------------------


def http_cases() -> list[dict[str, Any]]:
    """Path traversal and junk in every path and query parameter of every route (service/api/*.py).

    ``{map}``, ``{vehicle}``, ``{session}`` in a target are replaced by the runner with a map and a
    session that exist (the well-behaved vehicle's), so only the hostile part is wrong.
    """
    V = "validation"
    traversal = {
        "dotdot": "..",
        "pct-dotdot": "%2e%2e",
        "pct-upper-dotdot": "%2E%2E",
        "nul": "a%00b",
        "unicode": "s%C3%A9ance",
        "star": "%2A",
    }
    out: list[tuple[str, str, str, str, dict[str, Any]]] = []

    def add(name: str, method: str, target: str, description: str, status: int, body: str) -> None:
        out.append((name, method, target, description, {"status": status, "body": body}))

    # path parameters: a value that stays one segment is refused by the id pattern (422)
    routes = {
        "map": ("GET", "/maps/{X}"),
        "map-tiles": ("GET", "/maps/{X}/tiles"),
        "map-metadata": ("GET", "/maps/{X}/metadata.yaml"),
        "map-export": ("GET", "/maps/{X}/export"),
        "map-tile": ("GET", "/maps/{X}/tiles/0/0"),
        "map-delete": ("DELETE", "/maps/{X}"),
        "session-vehicle": ("GET", "/sessions/{X}/{session}"),
        "session-session": ("GET", "/sessions/{vehicle}/{X}"),
        "trajectory-vehicle": ("GET", "/sessions/{X}/{session}/trajectory"),
        "trajectory-session": ("GET", "/sessions/{vehicle}/{X}/trajectory"),
    }
    for rname, (method, template) in routes.items():
        for tname, value in traversal.items():
            if method == "DELETE":
                # mutating routes check the bearer token first: no token configured -> 403
                add(
                    f"{rname}-{tname}",
                    method,
                    template.replace("{X}", value),
                    f"{method} {template} with {{X}} = {value}",
                    403,
                    "detail",
                )
            else:
                add(
                    f"{rname}-{tname}",
                    method,
                    template.replace("{X}", value),
                    f"{method} {template} with {{X}} = {value}",
                    422,
                    V,
                )
    # encoded slashes become real slashes (the ASGI path is decoded): no route matches
    for rname, target in (
        ("map", "/maps/..%2F..%2Fetc%2Fpasswd"),
        ("session", "/sessions/..%2F..%2Fetc/passwd"),
        ("tile", "/maps/{map}/tiles/..%2F..%2F/0"),
    ):
        add(
            f"{rname}-encoded-slash",
            "GET",
            target,
            f"{target}: %2F decoded into a separator",
            404,
            "not_found",
        )
    # tile indices
    for tname, value in {
        "dotdot": "..",
        "pct-dotdot": "%2e%2e",
        "nul": "0%00",
        "huge": "9" * 30,
        "float": "1.5",
        "beyond": str(2**31),
    }.items():
        add(f"tile-ix-{tname}", "GET", f"/maps/{{map}}/tiles/{value}/0", f"tile ix = {value}", 422, V)
        add(f"tile-iy-{tname}", "GET", f"/maps/{{map}}/tiles/0/{value}", f"tile iy = {value}", 422, V)
    # query parameters
    queries = {
        "tile-format": ("/maps/{map}/tiles/0/0?format=", ("..%2F..%2Fetc%2Fpasswd", "pcd%00", "%2e%2e")),
        "export-format": ("/maps/{map}/export?format=", ("..%2F..%2Fetc%2Fpasswd", "las%00")),
        "export-bbox": ("/maps/{map}/export?bbox=", ("..%2F..", "nan,nan,1,1", "0,0,inf,1", "1,1,0,0")),
        "tiles-bbox": ("/maps/{map}/tiles?bbox=", ("%2e%2e", "1e999,0,1,1", "1,2,3")),
        "tiles-x": ("/maps/{map}/tiles?radius=1&y=0&x=", ("..", "nan", "inf")),
        "tiles-radius": ("/maps/{map}/tiles?x=0&y=0&radius=", ("-1", "..%2F", "nan")),
        "tiles-pdu": ("/maps/{map}/tiles?pdu_voxel_m=", ("0", "1e-300", "..")),
        "trajectory-format": (
            "/sessions/{vehicle}/{session}/trajectory?format=",
            ("..%2F..%2Fetc%2Fpasswd", "tum%00"),
        ),
        "sessions-state": ("/sessions?state=", ("..%2F..", "active%00")),
    }
    # the route's own checks (bbox parsing, finite x/y) answer 422 {"detail": "..."} (an
    # InvalidRequestError, service/api/errors.py); FastAPI's parameter validation 422 {"detail": [...]}
    own_check = {"export-bbox": (0, 1, 2, 3), "tiles-bbox": (0, 1, 2), "tiles-x": (1, 2)}
    for qname, (prefix, values) in queries.items():
        for k, value in enumerate(values):
            body = "detail" if k in own_check.get(qname, ()) else V
            add(f"query-{qname}-{k}", "GET", prefix + value, f"{prefix}{value}", 422, body)
    add(
        "query-bbox-100k",
        "GET",
        "/maps/{map}/tiles?bbox=" + ",".join(["1"] * 2000),
        "bbox of 2000 numbers",
        422,
        "detail",
    )
    # static files
    for k, target in enumerate(
        (
            "/static/..%2F..%2F..%2Fetc%2Fpasswd",
            "/static/%2e%2e/%2e%2e/%2e%2e/etc/passwd",
            "/static/../../etc/passwd",
            "/static/vendor%00.js",
        )
    ):
        add(f"static-traversal-{k}", "GET", target, f"{target}: outside the static folder", 404, "not_found")
    # closing a session needs the token (none configured: refused before anything else)
    add("close-dotdot", "POST", "/sessions/../x/close", "POST close with vehicle '..'", 403, "detail")
    add(
        "close-traversal",
        "POST",
        "/sessions/%2e%2e/%2e%2e/close",
        "POST close with %2e%2e ids",
        403,
        "detail",
    )
    add("unknown-route", "GET", "/etc/passwd", "a route that does not exist", 404, "not_found")
    add("unknown-map", "GET", "/maps/nosuchmap", "a map that does not exist", 404, "not_found")
    return [
        {
            "name": f"http-{name}",
            "surface": "http",
            "description": description,
            "method": method,
            "target": target,
            "expect": expect,
        }
        for name, method, target, description, expect in out
    ]


# --------------------------------------------------------------------------------------------
# file cases
# --------------------------------------------------------------------------------------------

_PCD_HEAD = (
    "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
    "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
)


def _pcd(n: int, data: str, body: bytes) -> bytes:
    return _PCD_HEAD.format(n=n, data=data).encode() + body


def _ply(
    n: int,
    body: bytes,
    *,
    props: str = "property float x\nproperty float y\nproperty float z\n",
    end: bool = True,
) -> bytes:
    head = f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n{props}" + (
        "end_header\n" if end else ""
    )
    return head.encode() + body


def file_cases() -> list[dict[str, Any]]:
    """Malformed inputs to the readers of ``core/io`` through the CLI (exit codes: cli/errors.py)."""
    pts = room_points(100)
    nan_text = "\n".join("nan nan nan" for _ in range(10)).encode() + b"\n"
    files: list[tuple[str, str, bytes, list[str], int]] = [
        (
            "pcd-truncated-header",
            "cloud.pcd",
            _pcd(100, "binary", b"")[:40],
            ["register", "{case}", "{good}"],
            3,
        ),
        (
            "pcd-short-body",
            "cloud.pcd",
            _pcd(100, "binary", pts[:50].tobytes()),
            ["register", "{case}", "{good}"],
            3,
        ),
        (
            "pcd-points-2e40",
            "cloud.pcd",
            _pcd(2**40, "binary", pts.tobytes()),
            ["register", "{case}", "{good}"],
            3,
        ),
        (
            "pcd-no-x-field",
            "cloud.pcd",
            _pcd(100, "binary", pts.tobytes()).replace(b"FIELDS x y z", b"FIELDS a b c"),
            ["register", "{case}", "{good}"],
            3,
        ),
        (
            "pcd-compressed-lies",
            "cloud.pcd",
            _pcd(100, "binary_compressed", struct.pack("<II", 10, 2**31) + b"\x00" * 10),
            ["register", "{case}", "{good}"],
            3,
        ),
        ("pcd-all-nan", "cloud.pcd", _pcd(10, "ascii", nan_text), ["register", "{case}", "{good}"], 4),
        (
            "pcd-unknown-data",
            "cloud.pcd",
            _pcd(100, "zip", pts.tobytes()),
            ["register", "{case}", "{good}"],
            3,
        ),
        ("ply-vertices-1e12", "cloud.ply", _ply(10**12, pts.tobytes()), ["register", "{case}", "{good}"], 3),
        ("ply-truncated", "cloud.ply", _ply(100, pts[:10].tobytes()), ["register", "{case}", "{good}"], 3),
        (
            "ply-no-end-header",
            "cloud.ply",
            _ply(100, pts.tobytes(), end=False),
            ["register", "{case}", "{good}"],
            3,
        ),
        (
            "ply-list-vertex",
            "cloud.ply",
            _ply(3, b"\x01" * 40, props="property list uchar int x\n"),
            ["register", "{case}", "{good}"],
            3,
        ),
        ("ply-negative-count", "cloud.ply", _ply(-5, pts.tobytes()), ["register", "{case}", "{good}"], 3),
        ("bin-13-bytes", "000000.bin", b"\x00" * 13, ["register", "{case}", "{good}"], 3),
        (
            "bin-nan",
            "000000.bin",
            np.full((100, 4), np.nan, "<f4").tobytes(),
            ["register", "{case}", "{good}"],
            4,
        ),
        (
            "npy-pickle",
            "cloud.npy",
            b"\x93NUMPY\x01\x00v\x00{'descr': '|O', 'fortran_order': False, 'shape': (3,), }"
            + b" " * 49
            + b"\n"
            + b"\x80\x04N.",
            ["register", "{case}", "{good}"],
            3,
        ),
        (
            "kitti-dir-bad-bin",
            "seq/velodyne/000000.bin",
            b"\x00" * 15,
            ["map", "{case_dir}", "--out", "{tmp}/out", "--no-progress"],
            3,
        ),
        (
            "tum-six-columns",
            "traj.tum",
            b"0 1 2 3 4 5\n1 1 2 3 4 5\n",
            ["eval", "--reference", "{case}", "--estimate", "{case}", "--format", "tum"],
            3,
        ),
        (
            "tum-nan-quaternion",
            "traj.tum",
            b"0 0 0 0 nan 0 0 1\n1 0 0 0 0 0 0 1\n",
            ["eval", "--reference", "{case}", "--estimate", "{case}", "--format", "tum"],
            3,
        ),
        (
            "tum-zero-quaternion",
            "traj.tum",
            b"0 0 0 0 0 0 0 0\n1 0 0 0 0 0 0 0\n",
            ["eval", "--reference", "{case}", "--estimate", "{case}", "--format", "tum"],
            3,
        ),
        (
            "kitti-poses-11-columns",
            "poses.txt",
            b"1 0 0 0 0 1 0 0 0 0 1\n",
            ["eval", "--reference", "{case}", "--estimate", "{case}", "--format", "kitti", "--no-calib"],
            3,
        ),
    ]
    return [
        {
            "name": f"file-{name}",
            "surface": "file",
            "description": f"{Path(fname).name}: {name.replace('-', ' ')}",
            "file": f"files/{name}/{fname}",
            "argv": argv,
            "expect": {"exit": code},
            "_bytes": body,
        }
        for name, fname, body, argv, code in files
    ]


# --------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------


def generate() -> tuple[list[dict[str, Any]], dict[str, bytes]]:
    """The manifest and the files (relative path -> bytes) of the corpus."""
    files: dict[str, bytes] = {}
    manifest: list[dict[str, Any]] = []
    for case in wire_cases():
        session = case["session"]
        payload = case["payload"]
        case["setup"] = [{**s, "session": session} for s in case["setup"]]
        if isinstance(payload, dict):
            recipe = {k: (session if v == "{session}" else v) for k, v in payload.items()}
            if recipe["kind"] in ("too_many_points", "nil_array_points"):
                recipe.setdefault("session", session)
                recipe.setdefault("seq", 0)
            data = build_payload(recipe) if recipe["kind"] == "room" else None
            if data is not None and len(data) <= MAX_FILE_BYTES:
                case["payload"] = {"file": f"wire/{case['name']}.bin", "recipe": recipe}
                files[case["payload"]["file"]] = data
            else:
                case["payload"] = {"recipe": recipe}
        else:
            data = payload(session)
            if len(data) > MAX_FILE_BYTES:
                raise ValueError(f"{case['name']}: {len(data)} bytes: give it a recipe")
            case["payload"] = {"file": f"wire/{case['name']}.bin"}
            files[case["payload"]["file"]] = data
        manifest.append(case)
    manifest += http_cases()
    for case in file_cases():
        files[case["file"]] = case.pop("_bytes")
        manifest.append(case)
    names = [c["name"] for c in manifest]
    if len(set(names)) != len(names):
        raise ValueError("duplicate case names")
    return manifest, files


def manifest_text(manifest: list[dict[str, Any]]) -> str:
    return json.dumps({"version": 1, "cases": manifest}, indent=1, ensure_ascii=True) + "\n"


def write(out: Path) -> int:
    """Write the corpus to ``out`` (replacing ``wire/``, ``files/`` and ``cases.json``).

    Returns the number of cases.
    """
    manifest, files = generate()
    for sub in ("wire", "files"):
        shutil.rmtree(out / sub, ignore_errors=True)
    for rel, data in files.items():
        path = out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    (out / "cases.json").write_text(manifest_text(manifest), encoding="utf-8")
    return len(manifest)


def main() -> None:
    parser = argparse.ArgumentParser(prog="corpus.py", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args()
    n = write(args.out)
    print(f"{n} cases written to {args.out}")


if __name__ == "__main__":
    main()
