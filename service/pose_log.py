"""A session's pose log: the record of each acknowledged pose, the log and its closed-off segments.

The worker appends one fixed-size :class:`PoseLogRecord` per pose to ``poses.log`` and fsyncs it
before the pose is published; a snapshot closes the log off into a segment
``poses.<index of its first pose, 10 digits>.log`` (:func:`segment_name`), never written again.
This module holds the format and the reading: :class:`Poses` (consecutive poses as columns), the
parsing of whole records, the segments one after the other from pose 0, and the cut of a torn last
record (a crash during an append fails its CRC). What the store does with them, and in what order
it writes them, is :mod:`randt.service.store`'s module docstring (A session's trajectory, Crash
safety).
"""

from __future__ import annotations

import logging
import os
import re
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from randt.core.errors import FormatError

__all__ = [
    "POSE_LOG_FILENAME",
    "POSE_LOG_RECORD_SIZE",
    "STATUS_FALLBACK",
    "PoseLogRecord",
    "PoseStatus",
    "Poses",
    "assemble",
    "parse_records",
    "read_trajectory_files",
    "segment_files",
    "segment_name",
]

logger = logging.getLogger(__name__)

POSE_LOG_FILENAME = "poses.log"
#: A closed-off pose log: ``poses.<index of its first pose, 10 digits>.log`` (:func:`segment_name`).
_SEGMENT_RE = re.compile(r"^poses\.(\d{10})\.log$")

PoseStatus = Literal["first", "ok", "fallback"]


_POSE_STATUSES: tuple[PoseStatus, ...] = ("first", "ok", "fallback")
# One pose-log record: magic, pose index, seq, stamp_ns, stamp_s, the 4x4 pose (row-major),
# status, padding; then a CRC-32 of those bytes. Little-endian, fixed size.
_LOG_MAGIC = b"RPL1"
_LOG_BODY = struct.Struct("<4sQqqd16dB3x")
_LOG_CRC = struct.Struct("<I")
POSE_LOG_RECORD_SIZE = _LOG_BODY.size + _LOG_CRC.size


@dataclass(frozen=True)
class PoseLogRecord:
    """One acknowledged pose in a session's ``poses.log`` (:meth:`Store.append_pose`).

    Attributes
    ----------
    index:
        The pose's place in the session's trajectory (0 for its first scan).
    seq, stamp_ns:
        The scan's sequence number and time stamp (ns), as the vehicle sent them.
    stamp_s:
        The stamp in seconds exactly as the trajectory keeps it (``stamp_ns * 1e-9``).
    pose:
        (4, 4) float64 ``T_frame_sensor``, the pose published.
    status:
        ``"first"``, ``"ok"`` or ``"fallback"``.
    """

    index: int
    seq: int
    stamp_ns: int
    stamp_s: float
    pose: np.ndarray
    status: PoseStatus

    def to_bytes(self) -> bytes:
        pose = np.asarray(self.pose, dtype=np.float64).reshape(16)
        body = _LOG_BODY.pack(
            _LOG_MAGIC,
            self.index,
            self.seq,
            self.stamp_ns,
            self.stamp_s,
            *pose.tolist(),
            _POSE_STATUSES.index(self.status),
        )
        return body + _LOG_CRC.pack(zlib.crc32(body))

    @classmethod
    def from_bytes(cls, data: bytes) -> PoseLogRecord | None:
        """The record in ``data`` (:data:`POSE_LOG_RECORD_SIZE` bytes), ``None`` if torn or damaged."""
        body, crc = data[: _LOG_BODY.size], data[_LOG_BODY.size :]
        if len(crc) != _LOG_CRC.size or _LOG_CRC.unpack(crc)[0] != zlib.crc32(body):
            return None
        magic, index, seq, stamp_ns, stamp_s, *rest = _LOG_BODY.unpack(body)
        status = int(rest[16])
        if magic != _LOG_MAGIC or status >= len(_POSE_STATUSES):
            return None
        pose = np.array(rest[:16], dtype=np.float64).reshape(4, 4)
        return cls(index, seq, stamp_ns, stamp_s, pose, _POSE_STATUSES[status])


# The same record as a numpy structured type, to read and write whole segments at once.
_LOG_DTYPE = np.dtype(
    [
        ("magic", "S4"),
        ("index", "<u8"),
        ("seq", "<i8"),
        ("stamp_ns", "<i8"),
        ("stamp_s", "<f8"),
        ("pose", "<f8", (16,)),
        ("status", "u1"),
        ("pad", "V3"),
        ("crc", "<u4"),
    ]
)
assert _LOG_DTYPE.itemsize == POSE_LOG_RECORD_SIZE
_STATUS_FIRST, _STATUS_OK, STATUS_FALLBACK = range(3)


@dataclass(frozen=True)
class Poses:
    """Consecutive poses of a session's trajectory, from ``first`` on, as columns: the records of
    a segment or of the log, a commit's own poses, or what a caller saved.

    ``seq`` is -1 where the scan's sequence number is not known (poses given to
    :meth:`Store.save_session` that were never logged); ``status`` indexes ``("first", "ok",
    "fallback")``.
    """

    first: int
    stamps: np.ndarray  # (n,) float64 seconds
    poses: np.ndarray  # (n, 4, 4) float64
    seq: np.ndarray  # (n,) int64
    status: np.ndarray  # (n,) uint8

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    @property
    def end(self) -> int:
        """One past the index of the last pose."""
        return self.first + len(self)

    @classmethod
    def empty(cls, first: int = 0) -> Poses:
        return cls(
            first, np.zeros(0), np.zeros((0, 4, 4)), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.uint8)
        )

    @classmethod
    def given(cls, first: int, stamps: np.ndarray, poses: np.ndarray) -> Poses:
        """Poses a caller saved (their sequence numbers and statuses are not known)."""
        n = stamps.shape[0]
        status = np.full(n, _STATUS_OK, dtype=np.uint8)
        if first == 0 and n:
            status[0] = _STATUS_FIRST
        return cls(first, stamps, poses, np.full(n, -1, dtype=np.int64), status)

    @classmethod
    def of_record(cls, r: PoseLogRecord) -> Poses:
        return cls(
            r.index,
            np.array([r.stamp_s]),
            np.asarray(r.pose, dtype=np.float64).reshape(1, 4, 4),
            np.array([r.seq], dtype=np.int64),
            np.array([_POSE_STATUSES.index(r.status)], dtype=np.uint8),
        )

    def since(self, index: int) -> Poses:
        """The poses from ``index`` on (all of them if ``index <= first``)."""
        k = min(max(index - self.first, 0), len(self))
        if k == 0:
            return self
        return Poses(self.first + k, self.stamps[k:], self.poses[k:], self.seq[k:], self.status[k:])

    def until(self, index: int) -> Poses:
        """The poses before ``index``."""
        k = min(max(index - self.first, 0), len(self))
        return Poses(self.first, self.stamps[:k], self.poses[:k], self.seq[:k], self.status[:k])

    @classmethod
    def joined(cls, parts: list[Poses]) -> Poses | None:
        """``parts`` one after the other, each continuing the previous one (overlaps are skipped);
        ``None`` if one leaves a gap."""
        parts = [p for p in parts if len(p)]
        if not parts:
            return None
        kept = [parts[0]]
        for part in parts[1:]:
            if part.first > kept[-1].end:
                return None
            rest = part.since(kept[-1].end)
            if len(rest):
                kept.append(rest)
        if len(kept) == 1:
            return kept[0]
        return cls(
            kept[0].first,
            np.concatenate([p.stamps for p in kept]),
            np.concatenate([p.poses for p in kept]),
            np.concatenate([p.seq for p in kept]),
            np.concatenate([p.status for p in kept]),
        )

    def to_bytes(self) -> bytes:
        """The poses as pose-log records (:class:`PoseLogRecord`'s layout)."""
        n = len(self)
        table = np.zeros(n, dtype=_LOG_DTYPE)
        table["magic"] = _LOG_MAGIC
        table["index"] = self.first + np.arange(n)
        table["seq"] = self.seq
        table["stamp_ns"] = np.round(self.stamps * 1e9).astype(np.int64)
        table["stamp_s"] = self.stamps
        table["pose"] = self.poses.reshape(n, 16)
        table["status"] = self.status
        body = _LOG_BODY.size
        data = table.tobytes()
        view = memoryview(data)
        size = POSE_LOG_RECORD_SIZE
        table["crc"] = [zlib.crc32(view[o : o + body]) for o in range(0, n * size, size)]
        return table.tobytes()


def parse_records(data: bytes) -> tuple[Poses, int]:
    """The whole, intact, consecutive pose-log records at the start of ``data``, and how many
    bytes they take: reading stops at a torn or damaged record (its CRC, magic or status) or at
    one whose index does not follow the previous one's."""
    size = POSE_LOG_RECORD_SIZE
    n = len(data) // size
    if n == 0:
        return Poses.empty(), 0
    table = np.frombuffer(data, dtype=_LOG_DTYPE, count=n)
    view = memoryview(data)
    body = _LOG_BODY.size
    crc = np.fromiter((zlib.crc32(view[o : o + body]) for o in range(0, n * size, size)), np.uint32, count=n)
    index = table["index"].astype(np.int64)
    good = (crc == table["crc"]) & (table["magic"] == _LOG_MAGIC) & (table["status"] < len(_POSE_STATUSES))
    good &= index == index[0] + np.arange(n)
    k = n if good.all() else int(np.argmin(good))
    if k == 0:
        return Poses.empty(), 0
    part = Poses(
        int(index[0]),
        table["stamp_s"][:k].copy(),
        table["pose"][:k].reshape(k, 4, 4).copy(),
        table["seq"][:k].copy(),
        table["status"][:k].copy(),
    )
    return part, k * size


def segment_name(first: int) -> str:
    """The file name of a pose-log segment whose first pose is the trajectory's pose ``first``."""
    return f"poses.{first:010d}.log"


def segment_files(directory: Path) -> list[tuple[int, Path]]:
    """The session's pose-log segments, ``(first pose, path)``, in trajectory order."""
    try:
        names = os.listdir(directory)
    except FileNotFoundError:
        return []
    except OSError as exc:
        raise FormatError(f"cannot list {directory}: {exc}") from exc
    found = [(m, name) for name in names if (m := _SEGMENT_RE.fullmatch(name))]
    return sorted((int(m.group(1)), directory / name) for m, name in found)


def read_trajectory_files(directory: Path, *, repair: bool) -> tuple[Poses, Poses]:
    """The poses of the session's segments (one after the other from pose 0, each whole) and
    of its active log (whole records up to the first torn or damaged one; with ``repair`` what
    follows them is cut off the file, so the next append continues a clean log).

    Raises
    ------
    FormatError
        A segment is damaged or does not continue the previous one.
    """
    parts: list[Poses] = []
    end = 0
    for first, path in segment_files(directory):
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise FormatError(f"cannot read {path}: {exc}") from exc
        part, good = parse_records(data)
        if good != len(data) or len(part) == 0 or part.first != first:
            raise FormatError(
                f"{path}: damaged pose-log segment ({good // POSE_LOG_RECORD_SIZE} intact records "
                f"of {len(data) / POSE_LOG_RECORD_SIZE:g})"
            )
        if first != end:
            raise FormatError(f"{path}: starts at pose {first}, but the segments before it end at {end}")
        parts.append(part)
        end = part.end
    segments = Poses.joined(parts) or Poses.empty()
    return segments, _read_log(directory / POSE_LOG_FILENAME, repair=repair)


def _read_log(path: Path, *, repair: bool) -> Poses:
    """The whole records of a ``poses.log`` up to the first torn or damaged one (none if no file).

    With ``repair``, what follows them (a torn tail: a crash during an append) is cut off the
    file, so the next append continues a clean log.
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return Poses.empty()
    except OSError as exc:
        raise FormatError(f"cannot read {path}: {exc}") from exc
    log, good = parse_records(data)
    if good != len(data):
        logger.warning(
            "%s: cutting %d bytes after %d whole records (a torn or damaged tail)",
            path,
            len(data) - good,
            len(log),
        )
        if repair:
            try:
                with open(path, "r+b") as fh:
                    fh.truncate(good)
                    fh.flush()
                    os.fsync(fh.fileno())
            except OSError as exc:
                raise FormatError(f"cannot cut the torn tail of {path}: {exc}") from exc
    return log


def assemble(segments: Poses, own: Poses | None, log: Poses, what: str) -> Poses:
    """The trajectory from pose 0: the segments, then the commit's own poses, then the log (each
    may repeat poses of the ones before it, which are the same; none may leave a gap).

    Raises
    ------
    FormatError
        Poses are missing between them.
    """
    end, kept = 0, []
    for name, part in (("segments", segments), ("commit", own), (POSE_LOG_FILENAME, log)):
        if part is None or not len(part):
            continue
        if part.first > end:
            raise FormatError(
                f"{what}: poses {end}..{part.first - 1} are missing ({name} from pose {part.first})"
            )
        kept.append(part)
        end = max(end, part.end)
    return Poses.joined(kept) or Poses.empty()
