"""The wire contract between vehicles, the service and map users, in one place.

``docs/wire-format.md`` is its reference; this package implements it. The service (``service/``)
and the vehicle library (``clients/``) both import it and neither redefines any of it. It imports
``core`` (the error tree, the point-cloud type) and nothing else of ours.

Contents
--------
:mod:`randt.wire.messages`
    The messages (:class:`ScanMessage`, :class:`PoseMessage`, :class:`ErrorMessage`,
    :class:`TileUpdateMessage`, :class:`CorrectionMessage`), their schema version
    :data:`SCHEMA_VERSION`, the compact v2 scan (:class:`CompactScanMessage`,
    :class:`ScanEncoding`, :data:`SCAN_V2`, :func:`encode_scan_v2`),
    the decoder limits :class:`WireLimits`, :func:`encode`, the ``decode_*`` functions (``decode_scan``
    reads v1 and v2), :func:`peek_ids` / :func:`peek_seq`, and the senders' helpers
    (:func:`scan_from_arrays`, ...).
:mod:`randt.wire.packing`
    The bodies of a v2 scan: the ``delta-zigzag-planar`` layout of integer columns, zstd
    compression and bounded decompression.
:mod:`randt.wire.keys`
    Every key expression: :func:`scan_key`, :func:`pose_key`, :func:`error_key`, :func:`tile_key`,
    :func:`correction_key`, :func:`service_token_key`, the wildcards :data:`ALL_SCANS`,
    :data:`ALL_POSES`, :data:`ALL_ERRORS`, :data:`ALL_TILES`, :data:`ALL_CORRECTIONS`, and
    :func:`key_for` (the key of a message).
:mod:`randt.wire.ids`
    The id rule for vehicles, sessions, maps and service instances: :data:`ID_REGEX`,
    :func:`is_valid_id`, :func:`validate_id`.
:mod:`randt.wire.codes`
    The error codes: :class:`ErrorCode` (a ``StrEnum``: members are their strings on the wire),
    :data:`DECODE_CODES` and :data:`SERVICE_CODES` with their meanings.
:mod:`randt.wire.zenoh_config`
    The Zenoh configuration helper (:func:`~randt.wire.zenoh_config.zenoh_config`,
    :func:`~randt.wire.zenoh_config.check_endpoints`). The only module that imports Zenoh, so it is not
    imported here: ``from randt.wire.zenoh_config import zenoh_config``. It also reads a native Zenoh
    config file (``--zenoh-config``).
:mod:`randt.wire.zenoh_security`
    A secured deployment's files (``randt security init``, ``docs/security.md``): the access
    control derived from the key expressions (:func:`~randt.wire.zenoh_security.access_control`), the
    service's, router's and vehicles' Zenoh configs, TLS certificates and passwords. Not imported
    here either (certificates need the ``cryptography`` package).
"""

from __future__ import annotations

from randt.wire.codes import CODE_REGEX, DECODE_CODES, SERVICE_CODES, ErrorCode
from randt.wire.ids import ID_MAX_LENGTH, ID_PATTERN, ID_REGEX, UNKNOWN_ID, is_valid_id, validate_id
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
    SCAN_V2,
    SCAN_VERSIONS,
    SCHEMA_VERSION,
    Bounds,
    CompactScanMessage,
    CorrectionMessage,
    ErrorMessage,
    PoseMessage,
    Prior,
    ScanEncoding,
    ScanMessage,
    SchemaVersion,
    TileUpdateMessage,
    WireLimits,
    WireMessage,
    correction_from_arrays,
    decode_correction,
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
)

__all__ = [
    "ALL_CORRECTIONS",
    "ALL_ERRORS",
    "ALL_POSES",
    "ALL_SCANS",
    "ALL_TILES",
    "CODE_REGEX",
    "DECODE_CODES",
    "ID_MAX_LENGTH",
    "ID_PATTERN",
    "ID_REGEX",
    "SCAN_V2",
    "SCAN_VERSIONS",
    "SCHEMA_VERSION",
    "SERVICE_CODES",
    "UNKNOWN_ID",
    "Bounds",
    "CompactScanMessage",
    "CorrectionMessage",
    "ErrorCode",
    "ErrorMessage",
    "PoseMessage",
    "Prior",
    "ScanEncoding",
    "ScanMessage",
    "SchemaVersion",
    "TileUpdateMessage",
    "WireLimits",
    "WireMessage",
    "correction_from_arrays",
    "correction_key",
    "decode_correction",
    "decode_error",
    "decode_pose",
    "decode_scan",
    "decode_tile_update",
    "encode",
    "encode_scan_v2",
    "error_key",
    "is_valid_id",
    "key_for",
    "map_tiles_key",
    "matrix_to_pose",
    "peek_ids",
    "peek_seq",
    "pose_key",
    "pose_to_matrix",
    "scan_from_arrays",
    "scan_key",
    "service_token_key",
    "tile_key",
    "tile_of_key",
    "tile_update_from_arrays",
    "validate_id",
    "vehicle_of_scan_key",
]
