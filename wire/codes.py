"""Error codes: the ``code`` of an error message, one :class:`ErrorCode` member per failure kind.

Two families share the error message and the code pattern (:data:`CODE_REGEX`):

* :data:`DECODE_CODES`: a ``decode_*`` function of :mod:`randt.wire.messages` found the payload invalid
  (it raises :class:`~randt.core.errors.BadMessageError` with one of these as ``code``);
* :data:`SERVICE_CODES`: the scan decoded but the service cannot take it (sequence, admission,
  session state, a failure while matching).

Codes are stable (docs/wire-format.md, Versioning): new ones may be added, an existing one is never
reused for another failure. :class:`ErrorCode` is a :class:`~enum.StrEnum`, so a member is its
string on the wire, in metrics labels and in comparisons (``ErrorCode.DROPPED == "dropped"``).
"""

from __future__ import annotations

from enum import StrEnum
from typing import Final

__all__ = ["CODE_REGEX", "DECODE_CODES", "SERVICE_CODES", "ErrorCode"]

#: What any error code looks like (the ``code`` field of an error message must match it).
CODE_REGEX: Final = r"^[a-z][a-z0-9_]{0,63}$"


class ErrorCode(StrEnum):
    """Every error code this service and its decoders send (meanings in :data:`DECODE_CODES` and
    :data:`SERVICE_CODES`)."""

    # decoding (randt.wire.messages)
    PAYLOAD_TOO_LARGE = "payload_too_large"
    MALFORMED = "malformed"
    UNSUPPORTED_VERSION = "unsupported_version"
    MISSING_FIELD = "missing_field"
    INVALID_FIELD = "invalid_field"
    INVALID_ID = "invalid_id"
    INVALID_POINTS = "invalid_points"
    EMPTY_SCAN = "empty_scan"
    TOO_MANY_POINTS = "too_many_points"
    NONFINITE_POINTS = "nonfinite_points"
    INVALID_PRIOR = "invalid_prior"
    INVALID_COMPRESSION = "invalid_compression"
    # the service's own refusals (service/sessions.py)
    DUPLICATE_SEQ = "duplicate_seq"
    OUT_OF_ORDER = "out_of_order"
    DROPPED = "dropped"
    SESSION_CLOSED = "session_closed"
    SESSION_BUSY = "session_busy"
    SESSION_ERROR = "session_error"
    SESSIONS_FULL = "sessions_full"
    VEHICLE_SESSIONS_FULL = "vehicle_sessions_full"
    REGISTRATION_FAILED = "registration_failed"
    LOST = "lost"
    NOT_ON_MAP = "not_on_map"
    STORAGE_ERROR = "storage_error"
    INTERNAL_ERROR = "internal_error"


#: The codes a ``decode_*`` function raises, with their meaning (docs/wire-format.md, Error codes).
DECODE_CODES: Final[dict[ErrorCode, str]] = {
    ErrorCode.PAYLOAD_TOO_LARGE: "the payload exceeds max_payload_bytes (checked before unpacking)",
    ErrorCode.MALFORMED: "not msgpack, truncated, trailing bytes, or the top level is not a map",
    ErrorCode.UNSUPPORTED_VERSION: "v is an integer other than the schema version",
    ErrorCode.MISSING_FIELD: "a required field is absent",
    ErrorCode.INVALID_FIELD: "a field has the wrong type or value (the reason names the field)",
    ErrorCode.INVALID_ID: "vehicle, session or map does not match the id pattern",
    ErrorCode.INVALID_POINTS: "point bytes not a multiple of the point size, time offsets of the wrong "
    "length or outside [0, max_time_offset_s], or a tile's point bytes not matching n_points",
    ErrorCode.EMPTY_SCAN: "the scan holds no points",
    ErrorCode.TOO_MANY_POINTS: "the scan holds more than max_points points",
    ErrorCode.NONFINITE_POINTS: "a point has a NaN or infinite coordinate or intensity",
    ErrorCode.INVALID_PRIOR: "the prior pose is not a finite rigid transform, or its covariance is not a "
    "finite symmetric positive semi-definite 6x6 matrix",
    ErrorCode.INVALID_COMPRESSION: "a v2 scan's zstd body is not one valid frame, or does not decompress to "
    "exactly the size its n_points implies (the decompressor stops there: no decompression bomb)",
}

#: The codes the service adds for scans that decode but cannot be taken, with their meaning.
SERVICE_CODES: Final[dict[ErrorCode, str]] = {
    ErrorCode.DUPLICATE_SEQ: "seq equals the session's last received one",
    ErrorCode.OUT_OF_ORDER: "seq is below the session's last received one",
    ErrorCode.DROPPED: "the session's queue (or the vehicle's intake queue) was full and this scan made "
    "room for a newer one",
    ErrorCode.SESSION_CLOSED: "the session was closed: publish under a new session id",
    ErrorCode.SESSION_BUSY: "the session is being saved right now: send the scan again",
    ErrorCode.SESSION_ERROR: "the session could not be opened or resumed",
    ErrorCode.SESSIONS_FULL: "the scan would open a session beyond the service's max_sessions, and no "
    "running session has been idle for slot_idle_s",
    ErrorCode.VEHICLE_SESSIONS_FULL: "the scan would open a session beyond max_sessions_per_vehicle for its "
    "vehicle, and none of the vehicle's running sessions has been idle for slot_idle_s",
    ErrorCode.REGISTRATION_FAILED: "the matcher raised on this scan; the session goes on",
    ErrorCode.LOST: "the session has lost its track (no match for longer than a prediction can be "
    "trusted, fallback_horizon_s; or a relocalization not yet verified) or its sweeps do not agree "
    "with the map they fold into (map_agreement_min), so no pose and nothing folded; it answers "
    "poses again once two consecutive matches (two map checks) agree (keep sending; a prior helps)",
    ErrorCode.NOT_ON_MAP: "the session only localizes (localize_only) and the shared map holds too little "
    "around the vehicle to localize on, or the vehicle's place is not known (no prior pose yet): no pose, "
    "nothing folded; it answers poses again where the map holds its surroundings (keep sending)",
    ErrorCode.STORAGE_ERROR: "the scan's pose could not be made durable (disk full, read-only): no pose "
    "was published for it; the session resumes from its stored state",
    ErrorCode.INTERNAL_ERROR: "the service failed on this scan (a bug, logged) or its matcher process died",
}
