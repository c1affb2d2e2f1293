"""Bodies of a v2 scan (docs/wire-format.md, Scan v2): integer columns delta-coded along the point
order, zigzag-mapped, byte-planar, then compressed; and bounded decompression of what arrives.

Layout ``delta-zigzag-planar`` of ``k`` int32 columns of ``n`` values (``q[c, i]``)::

    d[c, 0] = q[c, 0];  d[c, i] = q[c, i] - q[c, i - 1]        (mod 2**32: int32 wrap-around)
    z[c, i] = (d << 1) ^ (d >> 31)                              (zigzag: small |d| -> small z)
    body    = for c in columns: for b in 0..3: byte b (little-endian) of z[c, 0..n-1]

so a body is ``4 * k * n`` bytes before compression, and the decoder's inverse is exact for every
int32 (the differences and the running sum wrap modulo 2**32 on both sides). Points in their sweep's
native order are spatial neighbours, so most differences are a few centimetres: their zigzag codes
fit one byte, the three high byte planes are nearly all zero and the compressor removes them.

Decompression is bounded: a body must decompress to exactly the size its declared point count
implies, and the decompressor never produces more than that (a zstd bomb stops there, with its own
error). ``zstd`` comes from the standard library on Python 3.14+ (``compression.zstd``, PEP 784)
and from its backport, ``backports.zstd``, before.
"""

from __future__ import annotations

import sys
from typing import Final, Literal

import numpy as np

from randt.core.errors import BadMessageError
from randt.wire.codes import ErrorCode

if sys.version_info >= (3, 14):
    from compression import zstd
else:
    from backports import zstd

__all__ = ["LAYOUT", "Codec", "compress", "decompress", "pack_int_columns", "unpack_int_columns"]

#: The only layout of v2 bodies (module docstring).
LAYOUT: Final = "delta-zigzag-planar"

#: How a body is compressed: one zstd frame, or the layout's bytes as they are.
Codec = Literal["zstd", "none"]

#: Largest zstd window a decoder accepts (2**24 bytes = 16 MiB): bounds the memory a hostile frame
#: header can ask for. Our encoder (level 3, one-shot) uses at most 2**21.
ZSTD_WINDOW_LOG_MAX: Final = 24


def pack_int_columns(q: np.ndarray) -> bytes:
    """The ``delta-zigzag-planar`` body of (k, n) int32 columns (module docstring).

    Parameters
    ----------
    q : (k, n) int32 values, one row per column, in point order.
    """
    q = np.ascontiguousarray(q, dtype=np.int32)
    d = np.empty_like(q)
    d[:, :1] = q[:, :1]
    np.subtract(q[:, 1:], q[:, :-1], out=d[:, 1:])  # int32: wraps modulo 2**32
    z = ((d << 1) ^ (d >> 31)).astype("<i4", copy=False).view("<u4")
    k, n = q.shape
    planes = np.empty((k, 4, n), dtype=np.uint8)  # (column, byte, point): shifts, not a transpose
    for byte in range(4):
        planes[:, byte] = z >> np.uint32(8 * byte)  # (the low byte kept: an unsafe cast)
    return planes.tobytes()


def unpack_int_columns(body: bytes, k: int, n: int) -> np.ndarray:
    """(k, n) int32 columns from a ``delta-zigzag-planar`` body of exactly ``4 * k * n`` bytes."""
    planes = np.frombuffer(body, dtype=np.uint8).reshape(k, 4, n)
    # The little-endian words from their byte planes, most significant first: shifts and ors of
    # whole planes: a strided byte transpose was the decode's costliest step.
    z = planes[:, 3].astype(np.uint32)
    for byte in (2, 1, 0):
        z <<= np.uint32(8)
        z |= planes[:, byte]
    d = (z >> np.uint32(1)) ^ (np.uint32(0) - (z & np.uint32(1)))  # unsigned: wraps modulo 2**32
    return np.cumsum(d, axis=1, dtype=np.uint32).view(np.int32)


def compress(body: bytes, codec: Codec, level: int = 3) -> bytes:
    """``body`` as one zstd frame (``codec == "zstd"``) or unchanged (``"none"``)."""
    if codec == "none":
        return body
    return zstd.compress(body, level=level)


def decompress(data: bytes, codec: str, expected: int, field: str) -> bytes:
    """Exactly ``expected`` bytes from a received body, never more (module docstring).

    Parameters
    ----------
    data : the received ``bin`` value.
    codec : the scan's declared codec (validated before: ``"zstd"`` or ``"none"``).
    expected : the size the declared point count implies.
    field : the field's name, for the error reason.

    Raises
    ------
    BadMessageError
        ``invalid_points`` when an uncompressed body has another size; ``invalid_compression`` when
        a zstd body is not one valid frame, decompresses to fewer bytes, or would decompress to
        more (the decompressor stops at ``expected`` bytes).
    """
    if codec == "none":
        if len(data) != expected:
            raise BadMessageError(
                f"{field}: {len(data)} bytes, expected {expected} (codec none)", code=ErrorCode.INVALID_POINTS
            )
        return bytes(data)
    d = zstd.ZstdDecompressor(options={zstd.DecompressionParameter.window_log_max: ZSTD_WINDOW_LOG_MAX})
    try:
        out = d.decompress(data, max_length=expected)
        if len(out) == expected and not d.eof:
            # a frame that goes on past the expected size: ask for one more byte, never more
            extra = d.decompress(b"", max_length=1)
            if extra or not d.eof:
                raise BadMessageError(
                    f"{field}: the zstd frame decompresses to more than the {expected} bytes its point "
                    "count implies (stopped there: a decompression bomb?)",
                    code=ErrorCode.INVALID_COMPRESSION,
                )
    except zstd.ZstdError as exc:
        raise BadMessageError(
            f"{field}: not a valid zstd frame ({str(exc)[:100]})", code=ErrorCode.INVALID_COMPRESSION
        ) from None
    if len(out) != expected or not d.eof:
        raise BadMessageError(
            f"{field}: the zstd frame ends after {len(out)} bytes, expected {expected} "
            "(truncated, or a point count that does not match the body)",
            code=ErrorCode.INVALID_COMPRESSION,
        )
    if d.unused_data:
        raise BadMessageError(
            f"{field}: {len(d.unused_data)} bytes after the zstd frame (one frame per body)",
            code=ErrorCode.INVALID_COMPRESSION,
        )
    return out
