"""The pose graph's durable input (issue 33): every keyframe offered to the graph, in the order
offered, appended and fsync'd before the graph process gets it. The graph is a deterministic
function of the keyframes it took and their order, so a restarted graph process (or service)
takes the logged keyframes again, in order, and arrives at the same graph (docs/mapping.md,
"In the service": "The graph is durable").
"""

from __future__ import annotations

import json
import os
import struct
import threading
import zlib
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from randt.core.errors import FormatError
from randt.core.io.atomic import append_durably, atomic_open, atomic_write_bytes

__all__ = ["GRAPH_DIRNAME", "GRAPH_FLOORS_FILENAME", "GRAPH_LOG_FILENAME", "GraphLog"]

#: The graph's directory in the service's data directory, and its log's name.
GRAPH_DIRNAME = "graph"
GRAPH_LOG_FILENAME = "keyframes.log"
GRAPH_FLOORS_FILENAME = "floors.json"
_HEAD = struct.Struct("<II")
#: A record larger than this is damage, not a keyframe (far larger than any keyframe's record).
_MAX_RECORD = 256 << 20


def _pack(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        return {"__nd__": [a.dtype.str, list(a.shape), a.tobytes()]}
    if isinstance(value, tuple | list):
        return [_pack(v) for v in value]
    return value


def _unpack(value: Any) -> Any:
    if isinstance(value, dict) and "__nd__" in value:
        dtype, shape, data = value["__nd__"]
        return np.frombuffer(data, dtype=np.dtype(dtype)).reshape(shape).copy()
    if isinstance(value, list):
        return tuple(_unpack(v) for v in value)
    return value


def encode_item(item: tuple[Any, ...]) -> bytes:
    """One record (head and body) of a keyframe item."""
    body = msgpack.packb(_pack(item), use_bin_type=True)
    return _HEAD.pack(len(body), zlib.crc32(body)) + body


def decode_items(data: bytes) -> tuple[list[tuple[Any, ...]], int]:
    """The items of a log's bytes up to the first torn or corrupt record, and where it ends."""
    items: list[tuple[Any, ...]] = []
    at = 0
    view = memoryview(data)
    while at + _HEAD.size <= len(data):
        length, crc = _HEAD.unpack_from(view, at)
        end = at + _HEAD.size + length
        if length > _MAX_RECORD or end > len(data):
            break
        body = bytes(view[at + _HEAD.size : end])
        if zlib.crc32(body) != crc:
            break
        try:
            item = _unpack(msgpack.unpackb(body, raw=False))
        except (ValueError, TypeError, msgpack.UnpackException):
            break
        items.append(item)
        at = end
    return items, at


class GraphLog:
    """The keyframes offered to the graph, in a directory of the store (``DATA/graph/``).

    ``keyframes.log`` holds records appended one by one, ``u32 length of the body | u32 CRC-32 of
    the body | body (msgpack)``; the body is ``(stamp_s, item)``: the keyframe as
    :meth:`randt.service.graph.ServiceGraph.offer` queues it (``("keyframe", map, vehicle,
    session, seq, ...)``, arrays as ``[dtype, shape, bytes]``), or ``("drop", map, vehicle,
    session, seq)`` after a keyframe the graph will never take (dropped by a full queue, or in
    flight at two deaths of the process). A torn or corrupt tail (a crash mid-append) ends the
    log: it is cut off when the log is read. ``floors.json`` (map -> revision) keeps each deleted
    map's revision, the floor of a later map of the same name.
    """

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.directory = Path(directory)
        self.path = self.directory / GRAPH_LOG_FILENAME
        self._lock = threading.Lock()
        self._count: int | None = None

    def read(self) -> list[tuple[Any, ...]]:
        """Every logged record (``(stamp_s, keyframe item)`` as the service appends them), in
        order; a torn or corrupt tail is cut off the file."""
        with self._lock:
            return self._read()

    def _read(self) -> list[tuple[Any, ...]]:
        try:
            data = self.path.read_bytes()
        except FileNotFoundError:
            self._count = 0
            return []
        except OSError as exc:
            raise FormatError(f"cannot read {self.path}: {exc}") from exc
        items, good = decode_items(data)
        if good < len(data):
            with open(self.path, "r+b") as fh:
                fh.truncate(good)
                fh.flush()
                os.fsync(fh.fileno())
        self._count = len(items)
        return items

    def __len__(self) -> int:
        if self._count is None:
            self.read()
        assert self._count is not None
        return self._count

    def append(self, item: tuple[Any, ...]) -> None:
        """Append one keyframe item and fsync it: when this returns it survives a crash.

        Raises
        ------
        FormatError
            It could not be written and synced (disk full, read-only...): the file is cut back.
        """
        if self._count is None:
            self.read()  # (cuts a torn tail first)
        data = encode_item(item)
        with self._lock:
            append_durably(self.path, data, new_dirs=2)
            assert self._count is not None
            self._count += 1

    def without_map(self, map_name: str) -> int:
        """Rewrite the log (atomically) without ``map_name``'s keyframes, and with the other
        keyframes' offers to it (a session without priors joining it) taken out; returns how many
        keyframes went. The rewrite reads and writes the whole log: a map's deletion is rare.

        Raises
        ------
        FormatError
            It could not be read or written (the log is then as it was).
        """
        with self._lock:
            records = self._read()
            kept = [
                (stamp, item if item[-1] != map_name else (*item[:-1], None))
                for stamp, item in records
                if item[1] != map_name
            ]
            gone = len(records) - len(kept)
            if not gone and all(item[-1] != map_name for _, item in records):
                return 0
            try:
                with atomic_open(self.path, "wb") as fh:
                    for record in kept:
                        fh.write(encode_item(record))
            except OSError as exc:
                raise FormatError(f"cannot rewrite {self.path}: {exc}") from exc
            self._count = len(kept)
        return gone

    def floors(self) -> dict[str, int]:
        """Per deleted map, the revision its graph had (the floor of a later map of its name)."""
        path = self.directory / GRAPH_FLOORS_FILENAME
        try:
            floors = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return {}
        except (OSError, ValueError) as exc:
            raise FormatError(f"cannot read {path}: {exc}") from exc
        if not isinstance(floors, dict) or not all(isinstance(v, int) for v in floors.values()):
            raise FormatError(f"{path}: not a map of revisions")
        return floors

    def set_floor(self, map_name: str, revision: int) -> None:
        """Keep ``revision`` as ``map_name``'s floor (the highest one written stays), atomically.

        Raises
        ------
        FormatError
            It could not be written.
        """
        floors = self.floors()
        floors[map_name] = max(revision, floors.get(map_name, 0))
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(
                self.directory / GRAPH_FLOORS_FILENAME, json.dumps(floors, sort_keys=True).encode()
            )
        except OSError as exc:
            raise FormatError(f"cannot write {self.directory / GRAPH_FLOORS_FILENAME}: {exc}") from exc
