"""The messages of the wire format: versioned msgpack maps, their models, encode, decode and peek.

Every message is one msgpack map (packed with ``use_bin_type=True``) whose ``v`` key is the schema
version, :data:`SCHEMA_VERSION`; this module is shared by the service and the vehicle clients (it
does not import Zenoh). ``docs/wire-format.md`` is the reference for key expressions, fields,
units, frames, error codes, limits, the order of the checks and versioning.

**Bounded cost.** Before anything is unpacked, :func:`check_structure` walks the msgpack headers
(never the bodies of ``bin``/``str`` values) within fixed limits: :data:`MAX_OBJECTS`,
:data:`MAX_DEPTH`, :data:`MAX_CONTAINER_LEN`, :data:`MAX_STR_BYTES` and no ``ext`` types.
``msgpack.unpackb`` then runs with the same limits as a second line, so a hostile payload costs
little whatever it declares; the peeks are bounded the same way.

Each step raises :class:`~randt.core.errors.BadMessageError` with a stable ``code`` (one of
:data:`randt.wire.codes.DECODE_CODES`) and a reason naming the field and the problem; nothing else
escapes a ``decode_*`` function, whatever the bytes. :func:`peek_ids` and :func:`peek_seq` read the
addressing fields of a message that failed to decode, so its error can still reach the right vehicle.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any, Final, Literal, TypeVar

import msgpack
import numpy as np
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from randt.core.errors import BadMessageError
from randt.wire.codes import CODE_REGEX, DECODE_CODES, ErrorCode
from randt.wire.ids import ID_REGEX, UNKNOWN_ID, UNSAFE_ID_SAMPLES
from randt.wire.packing import LAYOUT, Codec, compress, decompress, pack_int_columns, unpack_int_columns

if TYPE_CHECKING:
    from randt.core.io.clouds import PointCloud

__all__ = [
    "SCAN_V2",
    "SCAN_VERSIONS",
    "SCHEMA_VERSION",
    "Bounds",
    "CompactScanMessage",
    "CorrectionMessage",
    "ErrorMessage",
    "GeoPrior",
    "GnssFix",
    "PoseMessage",
    "Prior",
    "ScanEncoding",
    "ScanHeader",
    "ScanMessage",
    "SchemaVersion",
    "TileUpdateMessage",
    "WireLimits",
    "WireMessage",
    "check_structure",
    "correction_from_arrays",
    "decode_correction",
    "decode_error",
    "decode_pose",
    "decode_scan",
    "decode_scan_header",
    "decode_tile_update",
    "encode",
    "encode_scan_v2",
    "geo_prior",
    "matrix_to_pose",
    "peek_ids",
    "peek_seq",
    "points_digest",
    "pose_to_matrix",
    "scan_from_arrays",
    "tile_update_from_arrays",
]

log = logging.getLogger(__name__)

#: The schema version of every message in the v1 layout: poses, errors, tile updates and raw scans
#: (docs/wire-format.md, Versioning). Scans may also come as :data:`SCAN_V2`.
SCHEMA_VERSION: Final = 1

#: The version of a compact scan (:class:`CompactScanMessage`): reduced, quantized, compressed.
SCAN_V2: Final = 2

#: The versions :func:`decode_scan` reads (the other decoders read :data:`SCHEMA_VERSION` only).
SCAN_VERSIONS: Final = (SCHEMA_VERSION, SCAN_V2)

#: The type of every message's ``v``: :data:`SCHEMA_VERSION` and nothing else.
SchemaVersion = Literal[1]

_INT64_MAX = 2**63 - 1
_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1
_POINT_SIZE: dict[str, int] = {"xyz": 12, "xyzi": 16}
_F32 = np.dtype("<f4")
_TILE_POINT_SIZE = 16

# Rigid-transform and covariance tolerances: senders may round-trip through float32.
_ROTATION_ATOL = 1e-4
_LAST_ROW_ATOL = 1e-9
_SYMMETRY_RTOL = 1e-6
_PSD_RTOL = 1e-9

_PREVIEW_CHARS = 40


# --------------------------------------------------------------------------------------------
# limits
# --------------------------------------------------------------------------------------------


class WireLimits(BaseModel):
    """What a decoder accepts. The service builds one from its settings; clients use the defaults.

    Attributes
    ----------
    max_points:
        Most points a scan may hold (``too_many_points`` beyond). Not applied to tile updates.
    max_payload_bytes:
        Largest payload accepted, checked before unpacking (``payload_too_large``).
    id_pattern:
        Regular expression a ``vehicle``, ``session`` or ``map`` id must match in full. The default
        is the id rule, :data:`randt.wire.ids.ID_REGEX`; a pattern accepting any of
        :data:`randt.wire.ids.UNSAFE_ID_SAMPLES` (which would break key expressions or file paths) is
        refused.
    max_time_offset_s:
        Per-point time offsets must lie in ``[0, max_time_offset_s]`` seconds.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    max_points: int = Field(default=300_000, ge=1)
    max_payload_bytes: int = Field(default=16 * 1024 * 1024, ge=1)
    id_pattern: str = ID_REGEX
    max_time_offset_s: float = Field(default=1.0, gt=0, allow_inf_nan=False)

    @field_validator("id_pattern")
    @classmethod
    def _check_pattern(cls, value: str) -> str:
        try:
            compiled = _compiled(value)
        except re.error as exc:
            raise ValueError(f"id_pattern is not a regular expression: {exc}") from exc
        for sample in UNSAFE_ID_SAMPLES:
            if compiled.fullmatch(sample):
                raise ValueError(
                    f"id_pattern accepts {sample!r}, which would break key expressions or file paths"
                )
        return value

    def id_ok(self, value: object) -> bool:
        """Whether ``value`` is a str matching :attr:`id_pattern` in full."""
        return isinstance(value, str) and _compiled(self.id_pattern).fullmatch(value) is not None


_DEFAULT_LIMITS = WireLimits()


@functools.lru_cache(maxsize=16)
def _compiled(pattern: str) -> re.Pattern[str]:
    return re.compile(pattern)


def _limits_of(info: ValidationInfo) -> WireLimits:
    context = info.context
    if isinstance(context, dict) and isinstance(context.get("limits"), WireLimits):
        return context["limits"]
    return _DEFAULT_LIMITS


# --------------------------------------------------------------------------------------------
# field types and shared checks
# --------------------------------------------------------------------------------------------


def _as_tuple(value: Any) -> Any:
    """Lists and arrays become tuples (so callers may pass ``T.ravel().tolist()`` or ``T``)."""
    if isinstance(value, np.ndarray):
        return tuple(value.ravel().tolist())
    if isinstance(value, list):
        return tuple(value)
    return value


Floats16 = Annotated[tuple[float, ...], BeforeValidator(_as_tuple), Field(min_length=16, max_length=16)]
Floats36 = Annotated[tuple[float, ...], BeforeValidator(_as_tuple), Field(min_length=36, max_length=36)]
Floats4 = Annotated[tuple[float, ...], BeforeValidator(_as_tuple), Field(min_length=4, max_length=4)]
Vec3 = Annotated[tuple[float, ...], BeforeValidator(_as_tuple), Field(min_length=3, max_length=3)]
Count = Annotated[int, Field(ge=0, le=_INT64_MAX)]


def _fail(code: ErrorCode, reason: str) -> PydanticCustomError:
    """A validation error whose ``type`` is one of :data:`~randt.wire.codes.DECODE_CODES`."""
    return PydanticCustomError(code, "{reason}", {"reason": reason})


def _preview(value: object) -> str:
    """A short, safe description of a received value (never its full repr)."""
    if isinstance(value, str):
        text = repr(value[:_PREVIEW_CHARS])
        return f"{text}... ({len(value)} chars)" if len(value) > _PREVIEW_CHARS else text
    if isinstance(value, bytes | bytearray | memoryview):
        return f"bytes of length {len(value)}"
    if value is None or isinstance(value, bool | int | float):
        return repr(value)
    if isinstance(value, list | tuple):
        return f"an array of {len(value)} items"
    if isinstance(value, dict):
        return f"a map of {len(value)} entries"
    return f"a {type(value).__name__}"


def _check_id(value: str, info: ValidationInfo, *, allow_unknown: bool = False) -> str:
    if allow_unknown and value == UNKNOWN_ID:
        return value
    limits = _limits_of(info)
    if not limits.id_ok(value):
        raise _fail(
            ErrorCode.INVALID_ID, f"{_preview(value)} is not a valid id (must match {limits.id_pattern})"
        )
    return value


def _rigid_problem(values: Sequence[float]) -> str | None:
    """Why 16 row-major values are not a finite rigid transform, or ``None`` if they are."""
    T = np.asarray(values, dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(T)):
        return f"has {int(np.count_nonzero(~np.isfinite(T)))} non-finite entries"
    if not np.allclose(T[3], (0.0, 0.0, 0.0, 1.0), rtol=0.0, atol=_LAST_ROW_ATOL):
        return f"last row must be [0, 0, 0, 1], got {T[3].tolist()}"
    R = T[:3, :3]
    err = float(np.max(np.abs(R @ R.T - np.eye(3))))
    det = float(np.linalg.det(R))
    if err > _ROTATION_ATOL or det <= 0.0:
        return f"rotation block is not a rotation (max |R R^T - I| = {err:.3g}, det = {det:.3g})"
    return None


def _covariance_problem(values: Sequence[float]) -> str | None:
    """Why 36 row-major values are not a symmetric PSD 6x6 matrix, or ``None`` if they are."""
    C = np.asarray(values, dtype=np.float64).reshape(6, 6)
    if not np.all(np.isfinite(C)):
        return f"has {int(np.count_nonzero(~np.isfinite(C)))} non-finite entries"
    scale = float(np.max(np.abs(C)))
    asym = float(np.max(np.abs(C - C.T)))
    if asym > _SYMMETRY_RTOL * scale:
        return f"is not symmetric (max |C - C^T| = {asym:.3g})"
    lowest = float(np.linalg.eigvalsh(0.5 * (C + C.T))[0])
    if lowest < -_PSD_RTOL * scale:
        return f"is not positive semi-definite (smallest eigenvalue {lowest:.3g})"
    return None


def _first_nonfinite(values: np.ndarray) -> tuple[int, int]:
    """Rows of an (N, k) or (N,) array holding a NaN/Inf: their count and the first index (-1 if none)."""
    bad = ~np.isfinite(values)
    if bad.ndim == 2:
        bad = bad.any(axis=1)
    rows = np.flatnonzero(bad)
    return int(rows.size), int(rows[0]) if rows.size else -1


# --------------------------------------------------------------------------------------------
# messages
# --------------------------------------------------------------------------------------------


class _Message(BaseModel):
    """Shared configuration: strict types, immutable, unknown keys ignored (newer v1 senders)."""

    model_config = ConfigDict(strict=True, frozen=True, extra="ignore", allow_inf_nan=False)

    v: SchemaVersion = SCHEMA_VERSION


class Prior(BaseModel):
    """An external pose for a scan (GNSS/INS), with its uncertainty.

    Attributes
    ----------
    pose:
        16 floats, row-major 4x4 ``T_map_sensor`` (maps sensor points into the map frame; metres).
    covariance:
        36 floats, row-major 6x6 covariance of the left perturbation ``(tx, ty, tz, rx, ry, rz)``
        (m², rad², as :mod:`randt.core.transforms`), symmetric positive semi-definite.
    """

    model_config = ConfigDict(strict=True, frozen=True, extra="ignore", allow_inf_nan=True)

    pose: Floats16
    covariance: Floats36

    @model_validator(mode="after")
    def _check(self) -> Prior:
        problem = _rigid_problem(self.pose)
        if problem is not None:
            raise _fail(ErrorCode.INVALID_PRIOR, f"pose {problem}")
        problem = _covariance_problem(self.covariance)
        if problem is not None:
            raise _fail(ErrorCode.INVALID_PRIOR, f"covariance {problem}")
        return self


class GeoPrior(BaseModel):
    """An external pose for a scan in WGS84 (GNSS/INS as receivers give it), with its uncertainty;
    the service places it in its map's frame through the map's geodetic origin (core/geo.py).

    Attributes
    ----------
    latitude, longitude:
        Degrees, WGS84.
    altitude:
        Metres above the WGS84 ellipsoid (``sensor_msgs/NavSatFix``'s altitude).
    orientation:
        4 floats, the quaternion ``(x, y, z, w)`` of the sensor's axes in the local East-North-Up
        frame at the position (unit length within 1e-3).
    covariance:
        36 floats, row-major 6x6 covariance of the left perturbation ``(tx, ty, tz, rx, ry, rz)``
        in East-North-Up axes (m², rad²), symmetric positive semi-definite.
    """

    model_config = ConfigDict(strict=True, frozen=True, extra="ignore", allow_inf_nan=False)

    latitude: float = Field(ge=-90.0, le=90.0)
    longitude: float = Field(ge=-180.0, le=180.0)
    altitude: float = Field(ge=-1e5, le=1e5)
    orientation: Floats4
    covariance: Floats36

    @model_validator(mode="after")
    def _check(self) -> GeoPrior:
        norm = float(np.linalg.norm(self.orientation))
        if not abs(norm - 1.0) <= 1e-3:
            raise _fail(ErrorCode.INVALID_PRIOR, f"orientation: quaternion of length {norm:.6g}, not 1")
        problem = _covariance_problem(self.covariance)
        if problem is not None:
            raise _fail(ErrorCode.INVALID_PRIOR, f"covariance {problem}")
        return self

    def rotation_enu(self) -> np.ndarray:
        """(3, 3) rotation of the sensor's axes into East-North-Up (the quaternion, normalized)."""
        from scipy.spatial.transform import Rotation

        return Rotation.from_quat(self.orientation).as_matrix()

    def covariance_matrix(self) -> np.ndarray:
        """(6, 6) float64 covariance, East-North-Up axes."""
        return np.asarray(self.covariance, dtype=np.float64).reshape(6, 6)


def _one_prior(prior: Prior | None, geo_prior: GeoPrior | None) -> None:
    if prior is not None and geo_prior is not None:
        raise _fail(ErrorCode.INVALID_PRIOR, "a scan carries a prior or a geo_prior, not both")


class ScanMessage(_Message):
    """One LiDAR sweep, vehicle to service, on ``randt/fleet/<vehicle>/scan``.

    Attributes
    ----------
    v:
        Schema version, :data:`SCHEMA_VERSION`.
    vehicle, session:
        Ids (:attr:`WireLimits.id_pattern`); a session is one drive, one matcher on the service.
    seq:
        Sequence number within the session, ``>= 0``, increasing.
    stamp_ns:
        Time of the sweep's first point, nanoseconds since the Unix epoch (UTC).
    fields:
        ``"xyz"`` or ``"xyzi"``: what each point holds.
    points:
        Little-endian float32, 12 (xyz) or 16 (xyzi) bytes per point, sensor frame, metres.
    time_offsets:
        Optional little-endian float32 per point: seconds after ``stamp_ns``, in
        ``[0, max_time_offset_s]``.
    prior:
        Optional :class:`Prior` pose of the sensor at the moment the answer's pose refers to:
        ``stamp_ns``, or the sweep's middle (``stamp_ns`` + period / 2) with ``time_offsets``.
    geo_prior:
        Optional :class:`GeoPrior`: the same in WGS84 (not with ``prior``).
    localize_only:
        Optional, ``true``: the session only localizes on the shared map, never adds to it
        (docs/clients.md, "A session that only localizes"); its first scan decides for the whole
        session. Absent: ``false``.

    A compact (v2) payload decodes to this same model, its bodies expanded to these float32 buffers,
    with :attr:`encoding` telling how it travelled (``None`` for a v1 payload).
    """

    vehicle: str
    session: str
    seq: Count
    stamp_ns: Count
    fields: Literal["xyz", "xyzi"]
    points: bytes
    time_offsets: bytes | None = None
    prior: Prior | None = None
    # (absent rather than nil when not given: a scan without one is the same bytes as before)
    geo_prior: GeoPrior | None = Field(default=None, exclude_if=lambda v: v is None)
    localize_only: bool = Field(default=False, exclude_if=lambda v: not v)

    _encoding: ScanEncoding | None = PrivateAttr(default=None)

    @property
    def encoding(self) -> ScanEncoding | None:
        """How the scan travelled when it was decoded from a v2 payload; ``None`` for v1 (raw)."""
        return self._encoding

    @field_validator("vehicle", "session")
    @classmethod
    def _check_ids(cls, value: str, info: ValidationInfo) -> str:
        return _check_id(value, info)

    @model_validator(mode="after")
    def _check_points(self, info: ValidationInfo) -> ScanMessage:
        _one_prior(self.prior, self.geo_prior)
        limits = _limits_of(info)
        size = _POINT_SIZE[self.fields]
        if len(self.points) % size:
            raise _fail(
                ErrorCode.INVALID_POINTS,
                f"points: {len(self.points)} bytes is not a multiple of {size} (fields {self.fields})",
            )
        n = len(self.points) // size
        if n == 0:
            raise _fail(ErrorCode.EMPTY_SCAN, "points: the scan holds no points")
        if n > limits.max_points:
            raise _fail(
                ErrorCode.TOO_MANY_POINTS, f"points: {n} points exceed the limit of {limits.max_points}"
            )
        if self.time_offsets is not None:
            if len(self.time_offsets) != 4 * n:
                raise _fail(
                    ErrorCode.INVALID_POINTS,
                    f"time_offsets: {len(self.time_offsets)} bytes, expected {4 * n} "
                    f"(one float32 per point, {n} points)",
                )
            offsets = np.frombuffer(self.time_offsets, dtype=_F32)
            bad = ~((offsets >= 0.0) & (offsets <= limits.max_time_offset_s))  # NaN is bad too
            if bad.any():
                first = int(np.argmax(bad))
                raise _fail(
                    ErrorCode.INVALID_POINTS,
                    f"time_offsets: {int(np.count_nonzero(bad))} offsets outside "
                    f"[0, {limits.max_time_offset_s}] s, first at index {first} ({float(offsets[first])})",
                )
        table = self.points_f32()
        if not np.isfinite(table).all():  # one pass over the buffer; details only on failure
            count, first = _first_nonfinite(table[:, :3])
            if count:
                raise _fail(
                    ErrorCode.NONFINITE_POINTS,
                    f"points: {count} points have a non-finite coordinate (NaN or Inf), "
                    f"first at index {first}",
                )
            count, first = _first_nonfinite(table[:, 3])
            raise _fail(
                ErrorCode.NONFINITE_POINTS,
                f"points: {count} points have a non-finite intensity (NaN or Inf), first at index {first}",
            )
        return self

    @property
    def n_points(self) -> int:
        """Number of points ``N``."""
        return len(self.points) // _POINT_SIZE[self.fields]

    def points_f32(self) -> np.ndarray:
        """(N, 3) or (N, 4) float32 read-only view of :attr:`points` (no copy)."""
        return np.frombuffer(self.points, dtype=_F32).reshape(-1, _POINT_SIZE[self.fields] // 4)

    def xyz(self) -> np.ndarray:
        """(N, 3) float64 positions, sensor frame, metres (a new array: float32 widened)."""
        return self.points_f32()[:, :3].astype(np.float64)

    def intensity(self) -> np.ndarray | None:
        """(N,) float32 read-only view of the intensities, or ``None`` for ``fields == "xyz"``."""
        return self.points_f32()[:, 3] if self.fields == "xyzi" else None

    def time_offset_s(self) -> np.ndarray | None:
        """(N,) float64 seconds after :attr:`stamp_ns`, or ``None`` when not sent."""
        if self.time_offsets is None:
            return None
        return np.frombuffer(self.time_offsets, dtype=_F32).astype(np.float64)

    def prior_pose(self) -> np.ndarray | None:
        """(4, 4) float64 ``T_map_sensor`` of the prior, or ``None``."""
        return None if self.prior is None else pose_to_matrix(self.prior.pose)

    def prior_covariance(self) -> np.ndarray | None:
        """(6, 6) float64 covariance of the prior (order tx ty tz rx ry rz), or ``None``."""
        return None if self.prior is None else np.asarray(self.prior.covariance).reshape(6, 6)

    def to_cloud(self) -> PointCloud:
        """The sweep as a :class:`~randt.core.io.PointCloud` (xyz, intensity, time offsets)."""
        from randt.core.io.clouds import PointCloud  # lazy: vehicle clients need not load the file formats

        return PointCloud(xyz=self.xyz(), intensity=self.intensity(), time_offset_s=self.time_offset_s())


class ScanEncoding(BaseModel):
    """How a v2 scan's bodies are encoded (the ``encoding`` map; docs/wire-format.md, Scan v2).

    Attributes
    ----------
    voxel_m:
        Voxel edge the vehicle reduced the sweep with (first point per voxel kept), metres; ``0``: not
        reduced. Informative: the decoder does not need it.
    xyz_quantum_m:
        Coordinate step, metres: ``x = q * xyz_quantum_m`` for the int32 ``q`` of the ``xyz`` body.
    time_quantum_s:
        Time-offset step, seconds: ``t = q * time_quantum_s``.
    intensity_offset, intensity_quantum:
        ``intensity = intensity_offset + u * intensity_quantum`` for the uint8 ``u`` of the
        ``intensity`` body.
    layout:
        ``"delta-zigzag-planar"`` (:mod:`randt.wire.packing`), the only one.
    codec:
        ``"zstd"`` (each body one zstd frame) or ``"none"``.
    """

    model_config = ConfigDict(strict=True, frozen=True, extra="ignore", allow_inf_nan=False)

    voxel_m: float = Field(ge=0.0, le=100.0)
    xyz_quantum_m: float = Field(gt=0.0, le=1.0)
    time_quantum_s: float = Field(gt=0.0, le=0.01)
    intensity_offset: float = Field(ge=-1e30, le=1e30)
    intensity_quantum: float = Field(gt=0.0, le=1e30)
    layout: Literal["delta-zigzag-planar"]
    codec: Literal["zstd", "none"]


class CompactScanMessage(BaseModel):
    """A v2 scan as it travels (docs/wire-format.md, Scan v2); :func:`decode_scan` expands it into
    a :class:`ScanMessage`. Fields as :class:`ScanMessage`, and:

    Attributes
    ----------
    n_points:
        Number of points ``N`` (``1 <= N <= max_points``), checked before any body is decompressed:
        every body must decompress to exactly the size ``N`` implies.
    encoding:
        :class:`ScanEncoding`.
    xyz:
        ``12 N`` bytes before compression: the int32 columns ``x, y, z`` (units of
        ``xyz_quantum_m``) in the layout of ``encoding.layout``.
    time_offsets:
        Optional, ``4 N`` bytes: one int32 column (units of ``time_quantum_s``), same layout.
    intensity:
        Optional, ``N`` bytes: one uint8 per point, in point order.
    """

    model_config = ConfigDict(strict=True, frozen=True, extra="ignore", allow_inf_nan=False)

    v: Literal[2] = SCAN_V2
    vehicle: str
    session: str
    seq: Count
    stamp_ns: Count
    n_points: Count
    encoding: ScanEncoding
    xyz: bytes
    time_offsets: bytes | None = None
    intensity: bytes | None = None
    prior: Prior | None = None
    geo_prior: GeoPrior | None = None
    localize_only: bool = False

    @field_validator("vehicle", "session")
    @classmethod
    def _check_ids(cls, value: str, info: ValidationInfo) -> str:
        return _check_id(value, info)

    @model_validator(mode="after")
    def _check_count(self, info: ValidationInfo) -> CompactScanMessage:
        limits = _limits_of(info)
        if self.n_points == 0:
            raise _fail(ErrorCode.EMPTY_SCAN, "n_points: the scan holds no points")
        if self.n_points > limits.max_points:
            raise _fail(
                ErrorCode.TOO_MANY_POINTS,
                f"n_points: {self.n_points} points exceed the limit of {limits.max_points}",
            )
        _one_prior(self.prior, self.geo_prior)
        return self


def _expand(compact: CompactScanMessage, limits: WireLimits) -> ScanMessage:
    """Decompress and decode a v2 scan's bodies into a validated :class:`ScanMessage` (bounded:
    each body decompresses to exactly the size ``n_points`` implies, or fails)."""
    n, enc = compact.n_points, compact.encoding
    q = unpack_int_columns(decompress(compact.xyz, enc.codec, 12 * n, "xyz"), 3, n)
    with_intensity = compact.intensity is not None
    table = np.empty((n, 4 if with_intensity else 3), dtype=_F32)
    np.multiply(q.T, enc.xyz_quantum_m, out=table[:, :3], casting="unsafe")
    if compact.intensity is not None:
        u = np.frombuffer(decompress(compact.intensity, enc.codec, n, "intensity"), dtype=np.uint8)
        table[:, 3] = enc.intensity_offset + u * enc.intensity_quantum
    offsets = None
    if compact.time_offsets is not None:
        qt = unpack_int_columns(decompress(compact.time_offsets, enc.codec, 4 * n, "time_offsets"), 1, n)
        offsets = (qt[0] * enc.time_quantum_s).astype(_F32).tobytes()  # range: ScanMessage's check
    obj = {
        "v": SCHEMA_VERSION,
        "vehicle": compact.vehicle,
        "session": compact.session,
        "seq": compact.seq,
        "stamp_ns": compact.stamp_ns,
        "fields": "xyzi" if with_intensity else "xyz",
        "points": table.tobytes(),
        "time_offsets": offsets,
        "prior": compact.prior,
        "geo_prior": compact.geo_prior,
        "localize_only": compact.localize_only,
    }
    scan = _validate(ScanMessage, obj, limits)
    scan._encoding = enc
    return scan


def _intensity_scale(values: np.ndarray) -> tuple[float, float]:
    """``(offset, quantum)`` mapping ``values`` onto uint8: exact for integers in [0, 255], else the
    sweep's [min, max] in 255 steps."""
    lo, hi = float(values.min()), float(values.max())
    if lo >= 0.0 and hi <= 255.0 and np.array_equal(values, np.rint(values)):
        return 0.0, 1.0
    return lo, ((hi - lo) / 255.0 if hi > lo else 1.0)


def encode_scan_v2(
    scan: ScanMessage,
    *,
    voxel_m: float = 0.0,
    xyz_quantum_m: float = 0.01,
    time_quantum_s: float = 1e-5,
    codec: Codec = "zstd",
    level: int = 3,
) -> bytes:
    """Pack a validated scan as a compact v2 payload (docs/wire-format.md, Scan v2).

    Points keep their order. Coordinates become int32 multiples of ``xyz_quantum_m`` (error at most
    half a step, plus float32 rounding), time offsets multiples of ``time_quantum_s``, intensities
    uint8 on the sweep's own scale (exact for integers in [0, 255]). Reducing the sweep is the
    sender's business (:func:`randt.clients.publisher.encode_sweep`); ``voxel_m`` only declares it.

    Parameters
    ----------
    scan:
        The sweep, as :func:`scan_from_arrays` built and validated it.
    voxel_m, xyz_quantum_m, time_quantum_s, codec:
        As :class:`ScanEncoding`.
    level:
        zstd compression level (docs/clients.md, "What goes on the link").

    Raises
    ------
    BadMessageError
        ``invalid_points``: a coordinate beyond the int32 range of ``xyz_quantum_m`` steps.
    ValueError
        Quanta outside :class:`ScanEncoding`'s ranges (a caller's bug).
    """
    table = scan.points_f32()
    n = table.shape[0]
    q = np.rint(table[:, :3].T.astype(np.float64) / xyz_quantum_m)  # float64 (3, n)
    if q.min() < _INT32_MIN or q.max() > _INT32_MAX:
        raise BadMessageError(
            f"points: a coordinate beyond +-{2.0**31 * xyz_quantum_m:.6g} m cannot be sent in steps of "
            f"{xyz_quantum_m} m",
            code=ErrorCode.INVALID_POINTS,
        )
    intensity = scan.intensity()
    offset, quantum = (0.0, 1.0) if intensity is None else _intensity_scale(intensity.astype(np.float64))
    enc = ScanEncoding(
        voxel_m=float(voxel_m),
        xyz_quantum_m=float(xyz_quantum_m),
        time_quantum_s=float(time_quantum_s),
        intensity_offset=offset,
        intensity_quantum=quantum,
        layout=LAYOUT,
        codec=codec,
    )
    bodies: dict[str, bytes | None] = {
        "xyz": compress(pack_int_columns(q.astype(np.int32)), codec, level),
        "time_offsets": None,
        "intensity": None,
    }
    offsets = scan.time_offset_s()
    if offsets is not None:  # validated: in [0, max_time_offset_s]
        qt = np.rint(offsets / time_quantum_s).astype(np.int32)[None, :]
        bodies["time_offsets"] = compress(pack_int_columns(qt), codec, level)
    if intensity is not None:
        u = np.clip(np.rint((intensity - offset) / quantum), 0, 255).astype(np.uint8)
        bodies["intensity"] = compress(u.tobytes(), codec, level)
    obj = {
        "v": SCAN_V2,
        "vehicle": scan.vehicle,
        "session": scan.session,
        "seq": scan.seq,
        "stamp_ns": scan.stamp_ns,
        "n_points": n,
        "encoding": enc.model_dump(),
        **bodies,
        "prior": None if scan.prior is None else scan.prior.model_dump(),
    }
    if scan.geo_prior is not None:
        obj["geo_prior"] = scan.geo_prior.model_dump()
    if scan.localize_only:  # (absent when false: the same bytes as before)
        obj["localize_only"] = True
    return msgpack.packb(obj, use_bin_type=True)


class PoseMessage(_Message):
    """The service's answer to one scan, on ``randt/fleet/<vehicle>/pose``.

    Attributes
    ----------
    vehicle, session, seq, stamp_ns:
        Copied from the scan.
    pose:
        16 floats, row-major 4x4 ``T_map_sensor`` (metres); the sensor at ``stamp_ns``, or at the
        sweep's middle when the scan carried time offsets (the matcher deskews to it).
    fitness:
        The matcher's fitness (NVTL; higher is better, 0 means no overlap).
    inlier_ratio:
        Fraction of matched points kept as inliers, in ``[0, 1]``.
    converged:
        Whether the optimiser converged.
    status:
        ``"first"`` (a session's first scan), ``"ok"`` (a match was accepted) or ``"fallback"``
        (rejected; ``pose`` is the motion prediction or the prior).
    covariance:
        36 floats, row-major 6x6 (tx ty tz rx ry rz; m², rad²), or ``None`` when unknown.
    latency_ms:
        Receive-to-publish time on the service, milliseconds.
    map:
        Name of the map the pose is in.
    mode:
        ``"mapping"`` (matched on the session's own keyframes; its points extend the map) or
        ``"localizing"`` (matched on the map around the vehicle: docs/mapping.md, "Localizing on the
        map"); absent on the wire when mapping.
    """

    vehicle: str
    session: str
    seq: Count
    stamp_ns: Count
    pose: Floats16
    fitness: float
    inlier_ratio: float = Field(ge=0.0, le=1.0)
    converged: bool
    status: Literal["first", "ok", "fallback"]
    covariance: Floats36 | None = None
    latency_ms: float
    map: str
    mode: Literal["mapping", "localizing"] = Field(default="mapping", exclude_if=lambda v: v == "mapping")

    @field_validator("vehicle", "session", "map")
    @classmethod
    def _check_ids(cls, value: str, info: ValidationInfo) -> str:
        return _check_id(value, info)

    @model_validator(mode="after")
    def _check_pose(self) -> PoseMessage:
        problem = _rigid_problem(self.pose)
        if problem is not None:
            raise _fail(ErrorCode.INVALID_FIELD, f"pose: {problem}")
        return self

    def matrix(self) -> np.ndarray:
        """(4, 4) float64 ``T_map_sensor``."""
        return pose_to_matrix(self.pose)

    def covariance_matrix(self) -> np.ndarray | None:
        """(6, 6) float64 covariance, or ``None``."""
        return None if self.covariance is None else np.asarray(self.covariance).reshape(6, 6)


class ErrorMessage(_Message):
    """Why the service rejected a scan, on ``randt/fleet/<vehicle>/error``.

    Attributes
    ----------
    vehicle, session:
        Ids of the rejected scan, or :data:`~randt.wire.ids.UNKNOWN_ID` (``"?"``) when it could not be read.
    seq:
        The rejected scan's ``seq``, or ``None`` when unknown.
    code:
        Stable machine-readable code (:class:`~randt.wire.codes.ErrorCode`): one of
        :data:`~randt.wire.codes.DECODE_CODES` for decoding failures, of
        :data:`~randt.wire.codes.SERVICE_CODES`
        for the service's own refusals (:data:`~randt.wire.codes.CODE_REGEX`).
    reason:
        Human-readable: what was wrong and where.
    retry_after_s:
        For a refusal that passes (``sessions_full``, ``vehicle_sessions_full``): seconds after
        which sending again may be admitted; ``None`` otherwise.
    """

    vehicle: str
    session: str
    seq: Count | None = None
    code: str = Field(pattern=CODE_REGEX)
    reason: str
    # (absent from the wire when None: an error without it is byte for byte what it was)
    retry_after_s: float | None = Field(default=None, ge=0, exclude_if=lambda v: v is None)

    @field_validator("vehicle", "session")
    @classmethod
    def _check_ids(cls, value: str, info: ValidationInfo) -> str:
        return _check_id(value, info, allow_unknown=True)


class Bounds(BaseModel):
    """Axis-aligned box, map frame, metres: per-axis ``min`` and ``max`` ``[x, y, z]``."""

    model_config = ConfigDict(strict=True, frozen=True, extra="ignore", allow_inf_nan=False)

    min: Vec3
    max: Vec3


class TileUpdateMessage(_Message):
    """A map tile's new content, on ``randt/map/<map>/tile/<ix>_<iy>``.

    Attributes
    ----------
    map:
        Map name (an id).
    tile:
        ``"<ix>_<iy>"``, equal to ``f"{ix}_{iy}"``.
    ix, iy:
        Tile indices: the tile covers ``[ix * size, (ix + 1) * size)`` in x, likewise in y.
    version:
        Incremented on every change of the tile; 1 for its first content.
    bounds:
        Box around the tile's points (map frame, metres).
    n_points:
        Number of points.
    points:
        Little-endian float32 x, y, z, intensity (16 bytes per point), map frame, metres.
    digest:
        :func:`points_digest` of ``points`` (16 hex digits), or ``None``: the content's name, as in
        the tile's HTTP ETag. A service never sends one ``(tile, version)`` with two digests.
    """

    map: str
    tile: str
    ix: int = Field(ge=_INT32_MIN, le=_INT32_MAX)
    iy: int = Field(ge=_INT32_MIN, le=_INT32_MAX)
    version: int = Field(ge=1, le=_INT64_MAX)
    bounds: Bounds
    n_points: Count
    points: bytes
    digest: str | None = None

    @field_validator("map")
    @classmethod
    def _check_map(cls, value: str, info: ValidationInfo) -> str:
        return _check_id(value, info)

    @model_validator(mode="after")
    def _check_tile(self) -> TileUpdateMessage:
        expected = f"{self.ix}_{self.iy}"
        if self.tile != expected:
            raise _fail(
                ErrorCode.INVALID_FIELD,
                f"tile: {_preview(self.tile)} does not match ix, iy (expected {expected!r})",
            )
        if len(self.points) != _TILE_POINT_SIZE * self.n_points:
            raise _fail(
                ErrorCode.INVALID_POINTS,
                f"points: {len(self.points)} bytes, expected {_TILE_POINT_SIZE * self.n_points} "
                f"({self.n_points} points of {_TILE_POINT_SIZE} bytes, x y z intensity)",
            )
        if self.n_points and any(lo > hi for lo, hi in zip(self.bounds.min, self.bounds.max, strict=True)):
            raise _fail(
                ErrorCode.INVALID_FIELD,
                f"bounds: min {list(self.bounds.min)} exceeds max {list(self.bounds.max)}",
            )
        count, first = _first_nonfinite(self.points_f32())
        if count:
            raise _fail(
                ErrorCode.NONFINITE_POINTS,
                f"points: {count} points have a non-finite value (NaN or Inf), first at index {first}",
            )
        if self.digest is not None and self.digest != points_digest(self.points):
            raise _fail(
                ErrorCode.INVALID_FIELD,
                f"digest: {_preview(self.digest)} is not the digest of points ({points_digest(self.points)})",
            )
        return self

    def points_f32(self) -> np.ndarray:
        """(N, 4) float32 read-only view of :attr:`points` (no copy)."""
        return np.frombuffer(self.points, dtype=_F32).reshape(-1, 4)

    def xyz(self) -> np.ndarray:
        """(N, 3) float64 positions, map frame, metres (a new array)."""
        return self.points_f32()[:, :3].astype(np.float64)

    def intensity(self) -> np.ndarray:
        """(N,) float32 read-only view of the intensities."""
        return self.points_f32()[:, 3]


class CorrectionMessage(_Message):
    """Optimized poses of a session's keyframes, on ``randt/fleet/<vehicle>/correction``.

    The pose graph (docs/mapping.md) moves keyframes when a loop closes or a GNSS fix arrives; the
    per-sweep answers are never rewritten. A client corrects any pose it holds with the keyframe at
    or before it: ``T_corrected = pose[k] @ inv(live[k]) @ T_answered`` (or interpolates between two
    keyframes, as ``GET /sessions/{vehicle}/{session}/trajectory?corrected=true`` does).

    Attributes
    ----------
    vehicle, session:
        The session whose keyframes moved.
    map:
        The map (frame) the optimized poses are in: the shared map, also for a session without
        priors once it is placed there (its answers stay in its own frame: ``live`` to ``pose`` is
        then the frame change as well as the correction).
    revision:
        The graph's revision (increases with every optimization that moved a keyframe).
    n_keyframes:
        Keyframes in this message (only those that moved since the last message).
    seq:
        ``n_keyframes`` little-endian uint64: the ``seq`` of each keyframe's scan.
    pose:
        ``16 * n_keyframes`` little-endian float64: each keyframe's optimized ``T_map_sensor``,
        row-major.
    live:
        ``16 * n_keyframes`` little-endian float64: each keyframe's pose as answered (the live
        estimate), row-major.
    """

    vehicle: str
    session: str
    map: str
    revision: int = Field(ge=1, le=_INT64_MAX)
    n_keyframes: Count
    seq: bytes
    pose: bytes
    live: bytes

    @field_validator("vehicle", "session", "map")
    @classmethod
    def _check_ids(cls, value: str, info: ValidationInfo) -> str:
        return _check_id(value, info)

    @model_validator(mode="after")
    def _check_sizes(self) -> CorrectionMessage:
        n = self.n_keyframes
        for name, size in (("seq", 8), ("pose", 128), ("live", 128)):
            got = len(getattr(self, name))
            if got != size * n:
                raise _fail(
                    ErrorCode.INVALID_FIELD,
                    f"{name}: {got} bytes, expected {size * n} ({n} keyframes of {size} bytes)",
                )
        for name in ("pose", "live"):
            values = np.frombuffer(getattr(self, name), dtype="<f8").reshape(-1, 16)
            for k, row in enumerate(values):
                problem = _rigid_problem(row.tolist())
                if problem is not None:
                    raise _fail(ErrorCode.INVALID_FIELD, f"{name}[{k}]: {problem}")
        return self

    def seqs(self) -> np.ndarray:
        """(N,) uint64 seq of each keyframe's scan."""
        return np.frombuffer(self.seq, dtype="<u8")

    def poses(self) -> np.ndarray:
        """(N, 4, 4) float64 optimized ``T_map_sensor`` (a new array)."""
        return np.frombuffer(self.pose, dtype="<f8").reshape(-1, 4, 4).copy()

    def live_poses(self) -> np.ndarray:
        """(N, 4, 4) float64 poses as answered (a new array)."""
        return np.frombuffer(self.live, dtype="<f8").reshape(-1, 4, 4).copy()


def correction_from_arrays(
    vehicle: str,
    session: str,
    map_name: str,
    revision: int,
    seqs: np.ndarray,
    poses: np.ndarray,
    live: np.ndarray,
) -> CorrectionMessage:
    """A :class:`CorrectionMessage` from ``(N,)`` seqs and two ``(N, 4, 4)`` pose stacks."""
    seqs = np.asarray(seqs, dtype="<u8").reshape(-1)
    return CorrectionMessage(
        vehicle=vehicle,
        session=session,
        map=map_name,
        revision=revision,
        n_keyframes=int(seqs.size),
        seq=seqs.tobytes(),
        pose=np.ascontiguousarray(poses, dtype="<f8").reshape(-1, 16).tobytes(),
        live=np.ascontiguousarray(live, dtype="<f8").reshape(-1, 16).tobytes(),
    )


WireMessage = ScanMessage | PoseMessage | ErrorMessage | TileUpdateMessage | CorrectionMessage
_M = TypeVar(
    "_M", ScanMessage, CompactScanMessage, PoseMessage, ErrorMessage, TileUpdateMessage, CorrectionMessage
)


# --------------------------------------------------------------------------------------------
# structure check: bounded work before unpacking (module docstring, Bounded cost)
# --------------------------------------------------------------------------------------------

#: Most msgpack objects (every key, value and container counts one) a message may hold.
MAX_OBJECTS: Final = 4096
#: Deepest nesting of maps and arrays (a scan: message -> prior -> covariance, 3 levels).
MAX_DEPTH: Final = 8
#: Most entries of one map or array (a scan has 9 top-level keys; a covariance 36 values).
MAX_CONTAINER_LEN: Final = 64
#: Longest string (bytes); ids have at most 64 characters, an error reason a few hundred.
MAX_STR_BYTES: Final = 64 * 1024

# msgpack type bytes -> size of a fixed-size value after the type byte
_FIXED_SIZE: Final[dict[int, int]] = {
    0xC0: 0, 0xC2: 0, 0xC3: 0,  # nil, false, true
    0xCA: 4, 0xCB: 8,  # float32, float64
    0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8,  # uint8..64
    0xD0: 1, 0xD1: 2, 0xD2: 4, 0xD3: 8,  # int8..64
}  # fmt: skip
# type byte -> width of the length field of a str / bin (body follows)
_STR_LEN: Final[dict[int, int]] = {0xD9: 1, 0xDA: 2, 0xDB: 4}
_BIN_LEN: Final[dict[int, int]] = {0xC4: 1, 0xC5: 2, 0xC6: 4}
# type byte -> (width of the count field, entries per count: 1 array, 2 map)
_CONTAINER: Final[dict[int, tuple[int, int]]] = {0xDC: (2, 1), 0xDD: (4, 1), 0xDE: (2, 2), 0xDF: (4, 2)}
_EXT: Final = frozenset({0xC7, 0xC8, 0xC9, 0xD4, 0xD5, 0xD6, 0xD7, 0xD8})


class _NotMsgpackError(ValueError):
    """The bytes are not msgpack (truncated, an invalid type byte), as opposed to a structure limit."""


class _Walker:
    """Walks msgpack objects by their headers only, within an object budget (:func:`check_structure`)."""

    def __init__(self, payload: object, max_objects: int) -> None:
        self.buf = memoryview(payload).cast("B")  # type: ignore[arg-type]
        self.budget = max_objects

    def _uint(self, pos: int, width: int) -> int:
        if pos + width > len(self.buf):
            raise _NotMsgpackError("truncated")
        return int.from_bytes(self.buf[pos : pos + width], "big")

    def skip(self, pos: int) -> int:
        """The position after the object starting at ``pos`` (ValueError on a limit or truncation)."""
        pending = [1]  # objects still to read at each open level
        while pending:
            if pending[-1] == 0:
                pending.pop()
                continue
            pending[-1] -= 1
            self.budget -= 1
            if self.budget < 0:
                raise ValueError("more objects than a message of this format can hold")
            if pos >= len(self.buf):
                raise _NotMsgpackError("truncated")
            b = self.buf[pos]
            count = -1
            if b <= 0x7F or b >= 0xE0:  # positive / negative fixint
                pos += 1
            elif b <= 0x8F:
                count, pos = 2 * (b & 0x0F), pos + 1
            elif b <= 0x9F:
                count, pos = b & 0x0F, pos + 1
            elif b <= 0xBF:
                size = b & 0x1F
                if size > MAX_STR_BYTES:
                    raise ValueError(f"a string of {size} bytes (at most {MAX_STR_BYTES})")
                pos += 1 + size
            elif b in _FIXED_SIZE:
                pos += 1 + _FIXED_SIZE[b]
            elif b in _STR_LEN or b in _BIN_LEN:
                width = _STR_LEN.get(b) or _BIN_LEN[b]
                size = self._uint(pos + 1, width)
                if b in _STR_LEN and size > MAX_STR_BYTES:
                    raise ValueError(f"a string of {size} bytes (at most {MAX_STR_BYTES})")
                pos += 1 + width + size
            elif b in _CONTAINER:
                width, per = _CONTAINER[b]
                n = self._uint(pos + 1, width)
                if n > MAX_CONTAINER_LEN:
                    kind = "map" if per == 2 else "array"
                    raise ValueError(f"a {kind} of {n} entries (at most {MAX_CONTAINER_LEN})")
                count, pos = per * n, pos + 1 + width
            elif b in _EXT:
                raise ValueError("msgpack ext types are not part of this format")
            else:  # 0xC1: never used
                raise _NotMsgpackError(f"invalid type byte 0x{b:02x}")
            if pos > len(self.buf):
                raise _NotMsgpackError("truncated")
            if count > 0:
                if count // 2 > MAX_CONTAINER_LEN:
                    raise ValueError(f"more than {MAX_CONTAINER_LEN} entries")
                if len(pending) >= MAX_DEPTH:
                    raise ValueError(f"nested deeper than {MAX_DEPTH} levels")
                pending.append(count)
        return pos


def check_structure(payload: bytes, *, max_objects: int = MAX_OBJECTS) -> None:
    """Check a payload's msgpack structure before unpacking it, in bounded time.

    Walks type bytes and length fields only (``str``/``bin`` bodies are skipped by offset), so the
    cost is at most ``max_objects`` small steps whatever the payload declares.

    Raises
    ------
    BadMessageError
        ``malformed``: truncated, trailing bytes, an invalid type byte, an ``ext`` value, or beyond
        :data:`MAX_OBJECTS`, :data:`MAX_DEPTH`, :data:`MAX_CONTAINER_LEN` or :data:`MAX_STR_BYTES`.
    """
    walker = _Walker(payload, max_objects)
    try:
        end = walker.skip(0)
    except _NotMsgpackError as exc:
        raise BadMessageError(f"payload: not valid msgpack ({exc})", code=ErrorCode.MALFORMED) from None
    except ValueError as exc:
        reason = f"payload: not a message of this format ({exc})"
        raise BadMessageError(reason, code=ErrorCode.MALFORMED) from None
    if end != len(walker.buf):
        raise BadMessageError("payload: trailing bytes after the message", code=ErrorCode.MALFORMED)


# --------------------------------------------------------------------------------------------
# encode / decode
# --------------------------------------------------------------------------------------------


def encode(message: WireMessage) -> bytes:
    """Pack a message as a msgpack map (``use_bin_type=True``; ``None`` fields as nil).

    Raises
    ------
    TypeError
        ``message`` is not one of the wire messages.
    """
    if not isinstance(message, _Message):
        raise TypeError(f"not a wire message: {type(message).__name__}")
    return msgpack.packb(message.model_dump(), use_bin_type=True)


def _unpack(
    payload: bytes, limits: WireLimits, versions: tuple[int, ...] = (SCHEMA_VERSION,)
) -> dict[str, Any]:
    """Size check, msgpack, top-level map and version: the steps before field validation."""
    size = memoryview(payload).nbytes
    if size > limits.max_payload_bytes:
        raise BadMessageError(
            f"payload: {size} bytes exceed the limit of {limits.max_payload_bytes}",
            code=ErrorCode.PAYLOAD_TOO_LARGE,
        )
    check_structure(payload)
    try:
        obj = msgpack.unpackb(
            payload,
            raw=False,
            use_list=False,
            strict_map_key=True,
            max_map_len=MAX_CONTAINER_LEN,
            max_array_len=MAX_CONTAINER_LEN,
            max_str_len=MAX_STR_BYTES,
            max_bin_len=limits.max_payload_bytes,
            max_ext_len=0,
        )
    except msgpack.ExtraData as exc:
        raise BadMessageError("payload: trailing bytes after the message", code=ErrorCode.MALFORMED) from exc
    except Exception as exc:  # msgpack raises several unrelated types for bad input
        detail = str(exc)[:120] or "truncated or invalid"
        raise BadMessageError(
            f"payload: not valid msgpack ({type(exc).__name__}: {detail})", code=ErrorCode.MALFORMED
        ) from exc
    if not isinstance(obj, dict):
        raise BadMessageError(
            f"payload: the top level must be a map, got {_preview(obj)}", code=ErrorCode.MALFORMED
        )
    if "v" not in obj:
        raise BadMessageError(
            "v: required field is missing (the schema version)", code=ErrorCode.MISSING_FIELD
        )
    version = obj["v"]
    if type(version) is not int:
        raise BadMessageError(
            f"v: the schema version must be an integer, got {_preview(version)}", code=ErrorCode.INVALID_FIELD
        )
    if version not in versions:
        reads = " and ".join(str(v) for v in versions)
        raise BadMessageError(
            f"v: schema version {version} is not supported (this decoder reads {reads})",
            code=ErrorCode.UNSUPPORTED_VERSION,
        )
    return obj


def _location(loc: tuple[int | str, ...]) -> str:
    text = ""
    for part in loc:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text


def _as_bad_message(exc: ValidationError) -> BadMessageError:
    """The first validation problem as a :class:`BadMessageError` (field-declaration order)."""
    errors = exc.errors(include_url=False)
    first = errors[0]
    kind, where = first["type"], _location(first["loc"])
    code: str  # an ErrorCode member, or a DECODE_CODES value pydantic reported
    if kind == "missing":
        code, text = ErrorCode.MISSING_FIELD, "required field is missing"
    elif kind in DECODE_CODES:
        code, text = kind, first["msg"]
    elif kind in ("too_short", "too_long"):
        ctx = first.get("ctx", {})
        bound = (
            f"at least {ctx.get('min_length')}" if kind == "too_short" else f"at most {ctx.get('max_length')}"
        )
        code, text = ErrorCode.INVALID_FIELD, f"expected {bound} values, got {ctx.get('actual_length')}"
    else:
        code, msg = ErrorCode.INVALID_FIELD, first["msg"]
        text = f"{msg[:1].lower()}{msg[1:]}, got {_preview(first.get('input'))}"
        if kind == "bytes_type" and isinstance(first.get("input"), str):
            text += " (pack with use_bin_type=True so bytes travel as msgpack bin)"
    reason = f"{where}: {text}" if where else text
    if len(errors) > 1:
        reason += f" (and {len(errors) - 1} more problems)"
    return BadMessageError(reason, code=code)


def _validate(model: type[_M], obj: dict[str, Any], limits: WireLimits) -> _M:
    try:
        return model.model_validate(obj, context={"limits": limits})
    except ValidationError as exc:
        raise _as_bad_message(exc) from None


def _decode(model: type[_M], payload: bytes, limits: WireLimits | None) -> _M:
    limits = _DEFAULT_LIMITS if limits is None else limits
    memoryview(payload)  # TypeError for objects without the buffer protocol: a caller's bug, not bad input
    try:
        if model is not ScanMessage:
            return _validate(model, _unpack(payload, limits), limits)
        obj = _unpack(payload, limits, SCAN_VERSIONS)
        if obj["v"] == SCAN_V2:
            return _expand(_validate(CompactScanMessage, obj, limits), limits)  # type: ignore[return-value]
        return _validate(model, obj, limits)
    except BadMessageError:
        raise
    except Exception as exc:  # a decoder bug must not take down a transport callback
        log.exception("decoding a %s raised %s; reported as malformed", model.__name__, type(exc).__name__)
        raise BadMessageError(
            f"payload: could not be decoded ({type(exc).__name__})", code=ErrorCode.MALFORMED
        ) from exc


def decode_scan(payload: bytes, limits: WireLimits | None = None) -> ScanMessage:
    """Decode and validate a scan message, v1 (raw float32) or v2 (compact, expanded here).

    Parameters
    ----------
    payload:
        The msgpack bytes (any object with the buffer protocol).
    limits:
        What to accept; ``None`` uses the defaults of :class:`WireLimits`.

    Returns
    -------
    ScanMessage
        Points stay in the unpacked ``bytes``; the array accessors are views or single conversions.
        A v2 payload's bodies are decompressed (at most the size ``n_points`` implies) into the same
        float32 buffers; ``encoding`` says how it travelled.

    Raises
    ------
    BadMessageError
        For any payload that is not a valid scan; ``code`` is one of :data:`~randt.wire.codes.DECODE_CODES`.
    TypeError
        ``payload`` does not support the buffer protocol (a programming error, not bad input).
    """
    return _decode(ScanMessage, payload, limits)


@dataclass(frozen=True)
class GnssFix:
    """A position-only GNSS fix in WGS84 (a ROS 2 robot's ``sensor_msgs/msg/NavSatFix``: no
    orientation), taken as the sensor's position at the scan: latitude and longitude (degrees),
    height above the ellipsoid (metres) and the position's covariance in East-North-Up (3, 3), m².
    Not a prior of the matcher: the pose graph fuses it (and places a session by its fixes)."""

    latitude: float
    longitude: float
    altitude: float
    covariance: tuple[float, ...]  # 9 floats, row-major 3x3, East-North-Up

    def covariance_matrix(self) -> np.ndarray:
        return np.asarray(self.covariance, dtype=np.float64).reshape(3, 3)


@dataclass(frozen=True)
class ScanHeader:
    """What :func:`decode_scan_header` reads of a scan: everything but its bodies.

    A v2 scan's bodies (``xyz``, ``time_offsets``, ``intensity``) stay compressed: its message
    was validated as a :class:`CompactScanMessage` (ids, seq, stamp, prior, encoding, point
    count), and :func:`decode_scan` of the same payload decompresses them where the points are
    used (the service's matcher processes). A v1 scan was validated whole (its points are raw
    float32: the checks are one pass, no decompression).
    """

    v: int
    vehicle: str
    session: str
    seq: int
    stamp_ns: int
    n_points: int
    prior: Prior | None = None
    geo_prior: GeoPrior | None = None
    #: a ROS 2 robot's NavSatFix at the scan (randt.wire.ros2; our own scans carry none)
    gnss_fix: GnssFix | None = None
    #: the session only localizes on the shared map (:attr:`ScanMessage.localize_only`; a ROS 2
    #: robot's from the service's settings)
    localize_only: bool = False

    def prior_pose(self) -> np.ndarray | None:
        """(4, 4) float64 ``T_map_sensor`` of the prior, or ``None``."""
        return None if self.prior is None else pose_to_matrix(self.prior.pose)

    def prior_covariance(self) -> np.ndarray | None:
        """(6, 6) float64 covariance of the prior (order tx ty tz rx ry rz), or ``None``."""
        return None if self.prior is None else np.asarray(self.prior.covariance).reshape(6, 6)


def decode_scan_header(payload: bytes, limits: WireLimits | None = None) -> ScanHeader:
    """Decode and validate a scan message without decompressing its bodies (:class:`ScanHeader`).

    Every error :func:`decode_scan` reports is reported here too, with the same code, except
    those only the bodies reveal: a v2 body that does not decompress to its declared size
    (``invalid_compression``) or decodes to time offsets out of range (``invalid_points``).
    Raises as :func:`decode_scan`.
    """
    limits = _DEFAULT_LIMITS if limits is None else limits
    memoryview(payload)  # TypeError for objects without the buffer protocol (a caller's bug)
    try:
        obj = _unpack(payload, limits, SCAN_VERSIONS)
        if obj["v"] == SCAN_V2:
            c = _validate(CompactScanMessage, obj, limits)
            return ScanHeader(
                c.v, c.vehicle, c.session, c.seq, c.stamp_ns, c.n_points, c.prior, c.geo_prior,
                localize_only=c.localize_only,
            )  # fmt: skip
        m = _validate(ScanMessage, obj, limits)
        return ScanHeader(
            m.v, m.vehicle, m.session, m.seq, m.stamp_ns, m.n_points, m.prior, m.geo_prior,
            localize_only=m.localize_only,
        )  # fmt: skip
    except BadMessageError:
        raise
    except Exception as exc:  # a decoder bug must not take down a transport callback
        log.exception("decoding a scan header raised %s; reported as malformed", type(exc).__name__)
        raise BadMessageError(
            f"payload: could not be decoded ({type(exc).__name__})", code=ErrorCode.MALFORMED
        ) from exc


def decode_pose(payload: bytes, limits: WireLimits | None = None) -> PoseMessage:
    """Decode and validate a pose message (errors as :func:`decode_scan`)."""
    return _decode(PoseMessage, payload, limits)


def decode_error(payload: bytes, limits: WireLimits | None = None) -> ErrorMessage:
    """Decode and validate an error message (errors as :func:`decode_scan`)."""
    return _decode(ErrorMessage, payload, limits)


def decode_tile_update(payload: bytes, limits: WireLimits | None = None) -> TileUpdateMessage:
    """Decode and validate a tile update (errors as :func:`decode_scan`; ``max_points`` not applied)."""
    return _decode(TileUpdateMessage, payload, limits)


def decode_correction(payload: bytes, limits: WireLimits | None = None) -> CorrectionMessage:
    """Decode and validate a keyframe correction (errors as :func:`decode_scan`)."""
    return _decode(CorrectionMessage, payload, limits)


# --------------------------------------------------------------------------------------------
# peeking into messages that failed to decode
# --------------------------------------------------------------------------------------------

_PEEK_KEYS = frozenset({"vehicle", "session", "seq"})


#: Budget of a peek: objects walked (the addressing fields come first in any encoder's output).
_PEEK_OBJECTS: Final = 512
#: Largest encoded value a peek decodes (an id is at most 64 characters; a seq 9 bytes).
_PEEK_VALUE_BYTES: Final = 256


def _peek(payload: object) -> dict[str, Any]:
    """Top-level ``vehicle``, ``session`` and ``seq`` values found before the payload breaks.

    Walks the top-level map with the structure walker's budget (:data:`_PEEK_OBJECTS` objects),
    skipping other values by their headers and decoding only short values of the wanted keys, so it
    costs microseconds on a payload of any size and reads what precedes a truncation or a limit.
    """
    found: dict[str, Any] = {}
    try:
        walker = _Walker(payload, _PEEK_OBJECTS)
        buf = walker.buf
        b = buf[0]
        if 0x80 <= b <= 0x8F:
            n, pos = b & 0x0F, 1
        elif b in (0xDE, 0xDF):
            width = 2 if b == 0xDE else 4
            n, pos = walker._uint(1, width), 1 + width
        else:
            return found
        for _ in range(min(n, MAX_CONTAINER_LEN)):
            key_end = walker.skip(pos)
            end = walker.skip(key_end)
            key = msgpack.unpackb(buf[pos:key_end], raw=False) if key_end - pos <= _PEEK_VALUE_BYTES else None
            if isinstance(key, str) and key in _PEEK_KEYS and key not in found:
                if end - key_end <= _PEEK_VALUE_BYTES:
                    found[key] = msgpack.unpackb(buf[key_end:end], raw=False, use_list=False)
                if len(found) == len(_PEEK_KEYS):
                    break
            pos = end
    except Exception:  # best effort by contract: whatever was read before the failure is kept
        log.debug("peek stopped early", exc_info=True)
    return found


def peek_ids(payload: bytes, limits: WireLimits | None = None) -> tuple[str | None, str | None]:
    """Best-effort ``(vehicle, session)`` of a message, valid or not; never raises.

    An id is returned only when it is a string matching ``limits.id_pattern``, so it is safe to put
    in a key expression; otherwise (absent, wrong type, unsafe, unreadable payload) it is ``None``.
    """
    limits = _DEFAULT_LIMITS if limits is None else limits
    found = _peek(payload)
    vehicle, session = found.get("vehicle"), found.get("session")
    return (vehicle if limits.id_ok(vehicle) else None, session if limits.id_ok(session) else None)


def peek_seq(payload: bytes) -> int | None:
    """Best-effort ``seq`` of a message, valid or not (``None`` if absent or invalid); never raises."""
    seq = _peek(payload).get("seq")
    return seq if type(seq) is int and 0 <= seq <= _INT64_MAX else None


# --------------------------------------------------------------------------------------------
# helpers for senders
# --------------------------------------------------------------------------------------------


def pose_to_matrix(pose: Sequence[float] | np.ndarray | PoseMessage) -> np.ndarray:
    """16 row-major values (or a :class:`PoseMessage`) to a (4, 4) float64 matrix (a new array).

    Raises
    ------
    ValueError
        Not 16 values.
    """
    values = pose.pose if isinstance(pose, PoseMessage) else pose
    T = np.array(values, dtype=np.float64)
    if T.size != 16:
        raise ValueError(f"a pose has 16 values (row-major 4x4), got {T.size}")
    return T.reshape(4, 4)


def matrix_to_pose(T: np.ndarray) -> tuple[float, ...]:
    """A (4, 4) matrix to its 16 row-major values (the wire's ``pose``).

    Raises
    ------
    ValueError
        ``T`` is not 4x4.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"a pose matrix is 4x4, got shape {T.shape}")
    return tuple(T.ravel().tolist())


def scan_from_arrays(
    vehicle: str,
    session: str,
    seq: int,
    stamp_ns: int,
    xyz: np.ndarray,
    intensity: np.ndarray | None = None,
    time_offset_s: np.ndarray | None = None,
    prior_pose: np.ndarray | None = None,
    prior_covariance: np.ndarray | None = None,
    *,
    geo_prior: GeoPrior | None = None,
    localize_only: bool = False,
    limits: WireLimits | None = None,
) -> ScanMessage:
    """Build a validated scan from arrays (points and offsets converted to little-endian float32).

    Parameters
    ----------
    vehicle, session, seq, stamp_ns:
        As :class:`ScanMessage` (``stamp_ns``: first point's time, ns since the Unix epoch).
    xyz:
        (N, 3) positions, sensor frame, metres.
    intensity:
        (N,) intensities, or ``None`` (then ``fields`` is ``"xyz"``).
    time_offset_s:
        (N,) seconds after ``stamp_ns``, or ``None``.
    prior_pose, prior_covariance:
        (4, 4) ``T_map_sensor`` and its (6, 6) covariance (tx ty tz rx ry rz), both or neither.
    geo_prior:
        The prior in WGS84 instead (:class:`GeoPrior`, e.g. :func:`geo_prior`).
    localize_only:
        The session only localizes on the shared map (:attr:`ScanMessage.localize_only`).
    limits:
        Limits to validate against (the defaults when ``None``).

    Returns
    -------
    ScanMessage

    Raises
    ------
    BadMessageError
        The message would be rejected; ``code`` is the one the service would answer with
        (``invalid_points`` also for arrays of the wrong shape).
    """
    limits = _DEFAULT_LIMITS if limits is None else limits
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise BadMessageError(f"xyz: expected shape (N, 3), got {xyz.shape}", code=ErrorCode.INVALID_POINTS)
    n = xyz.shape[0]
    if intensity is None:
        points = np.ascontiguousarray(xyz, dtype=_F32).tobytes()
    else:
        intensity = np.asarray(intensity)
        if intensity.shape != (n,):
            raise BadMessageError(
                f"intensity: expected shape ({n},), got {intensity.shape}", code=ErrorCode.INVALID_POINTS
            )
        table = np.empty((n, 4), dtype=_F32)
        table[:, :3] = xyz
        table[:, 3] = intensity
        points = table.tobytes()
    offsets = None
    if time_offset_s is not None:
        time_offset_s = np.asarray(time_offset_s)
        if time_offset_s.shape != (n,):
            raise BadMessageError(
                f"time_offsets: expected shape ({n},), got {time_offset_s.shape}",
                code=ErrorCode.INVALID_POINTS,
            )
        offsets = np.ascontiguousarray(time_offset_s, dtype=_F32).tobytes()
    if (prior_pose is None) != (prior_covariance is None):
        raise BadMessageError("prior: pose and covariance go together", code=ErrorCode.INVALID_PRIOR)
    prior = None
    if prior_pose is not None:
        prior = {
            "pose": np.asarray(prior_pose, np.float64),
            "covariance": np.asarray(prior_covariance, np.float64),
        }
    obj = {
        "v": SCHEMA_VERSION,
        "vehicle": vehicle,
        "session": session,
        "seq": seq,
        "stamp_ns": stamp_ns,
        "fields": "xyz" if intensity is None else "xyzi",
        "points": points,
        "time_offsets": offsets,
        "prior": prior,
        "geo_prior": geo_prior,
        "localize_only": localize_only,
    }
    return _validate(ScanMessage, obj, limits)


def geo_prior(
    latitude_deg: float,
    longitude_deg: float,
    altitude_m: float,
    R_enu_sensor: np.ndarray,
    covariance_enu: np.ndarray,
) -> GeoPrior:
    """A validated :class:`GeoPrior` from a WGS84 position, the sensor's rotation into the local
    East-North-Up frame (3x3) and the 6x6 covariance in East-North-Up axes (raises
    :class:`~randt.core.errors.BadMessageError` ``invalid_prior`` as the service would)."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R_enu_sensor, dtype=np.float64)
    problem = _rigid_problem(
        tuple(np.block([[R, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]).ravel())
    )
    if problem is not None:
        raise BadMessageError(f"geo_prior: orientation {problem}", code=ErrorCode.INVALID_PRIOR)
    obj = {
        "latitude": float(latitude_deg),
        "longitude": float(longitude_deg),
        "altitude": float(altitude_m),
        "orientation": tuple(Rotation.from_matrix(R).as_quat().tolist()),
        "covariance": tuple(np.asarray(covariance_enu, dtype=np.float64).ravel().tolist()),
    }
    try:
        return GeoPrior.model_validate(obj)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(part) for part in ("geo_prior", *first["loc"]))
        raise BadMessageError(f"{where}: {first['msg']}", code=ErrorCode.INVALID_PRIOR) from None


def tile_update_from_arrays(
    map_name: str,
    ix: int,
    iy: int,
    version: int,
    xyz: np.ndarray,
    intensity: np.ndarray | None = None,
) -> TileUpdateMessage:
    """Build a validated tile update; ``bounds`` is the box of ``xyz`` after float32 rounding.

    Parameters
    ----------
    map_name, ix, iy, version:
        As :class:`TileUpdateMessage`.
    xyz:
        (N, 3) positions, map frame, metres.
    intensity:
        (N,) intensities (zeros when ``None``).

    Raises
    ------
    BadMessageError
        The message would not decode (``code`` as :func:`decode_tile_update` would give).
    """
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise BadMessageError(f"xyz: expected shape (N, 3), got {xyz.shape}", code=ErrorCode.INVALID_POINTS)
    n = xyz.shape[0]
    table = np.zeros((n, 4), dtype=_F32)
    table[:, :3] = xyz
    if intensity is not None:
        intensity = np.asarray(intensity)
        if intensity.shape != (n,):
            raise BadMessageError(
                f"intensity: expected shape ({n},), got {intensity.shape}", code=ErrorCode.INVALID_POINTS
            )
        table[:, 3] = intensity
    lo = table[:, :3].min(axis=0).tolist() if n else [0.0, 0.0, 0.0]
    hi = table[:, :3].max(axis=0).tolist() if n else [0.0, 0.0, 0.0]
    obj = {
        "v": SCHEMA_VERSION,
        "map": map_name,
        "tile": f"{int(ix)}_{int(iy)}",
        "ix": int(ix),
        "iy": int(iy),
        "version": version,
        "bounds": {"min": lo, "max": hi},
        "n_points": n,
        "points": table.tobytes(),
    }
    obj["digest"] = points_digest(obj["points"])
    return _validate(TileUpdateMessage, obj, _DEFAULT_LIMITS)


def tile_update_from_table(
    map_name: str,
    ix: int,
    iy: int,
    version: int,
    xyzi: np.ndarray,
    bounds: tuple[Sequence[float], Sequence[float]],
    digest: str | None = None,
) -> TileUpdateMessage:
    """A tile update from content its sender has checked already: an (N, 4) float32 ``x y z
    intensity`` table of finite values (a service's saved map tile), its box ``(min, max)`` and
    its :func:`points_digest` (computed here when ``None``). Built without validating the content
    again (``model_construct``): :func:`tile_update_from_arrays` is the checked form, for content
    from elsewhere. Every message still decodes as :func:`decode_tile_update` checks it (tests)."""
    points = np.ascontiguousarray(xyzi, dtype=_F32).tobytes()
    n = len(points) // _TILE_POINT_SIZE
    lo, hi = ([float(v) for v in b] for b in bounds) if n else ([0.0] * 3, [0.0] * 3)
    return TileUpdateMessage.model_construct(
        v=SCHEMA_VERSION,
        map=map_name,
        tile=f"{int(ix)}_{int(iy)}",
        ix=int(ix),
        iy=int(iy),
        version=int(version),
        bounds=Bounds.model_construct(min=tuple(lo), max=tuple(hi)),
        n_points=n,
        points=points,
        digest=points_digest(points) if digest is None else digest,
    )


def points_digest(points: bytes) -> str:
    """A tile content's name: the first 16 hex digits of the SHA-256 of its ``points`` bytes
    (float32 x y z intensity, little-endian), as :class:`TileUpdateMessage` carries them."""
    return hashlib.sha256(points).hexdigest()[:16]
