"""Every Zenoh key expression of the wire format (docs/wire-format.md, Key expressions).

- ``randt/fleet/<vehicle>/scan``: vehicle → service, :func:`scan_key`; the service subscribes to
  :data:`ALL_SCANS`;
- ``randt/fleet/<vehicle>/pose``: service → all, :func:`pose_key` (:data:`ALL_POSES`);
- ``randt/fleet/<vehicle>/error``: service → vehicle, :func:`error_key` (:data:`ALL_ERRORS`);
- ``randt/fleet/<vehicle>/correction``: service → all, the pose graph's corrections of a vehicle's
  keyframes, :func:`correction_key` (:data:`ALL_CORRECTIONS`);
- ``randt/map/<map>/tile/<ix>_<iy>``: service → all, and a get answered by the service's queryable
  on :data:`ALL_TILES`, :func:`tile_key` (:func:`map_tiles_key` for one map's tiles);
- ``randt/service/<instance>``: the liveliness token of a running service, :func:`service_token_key`.

``<vehicle>``, ``<map>`` and ``<instance>`` are ids (:mod:`randt.wire.ids`), so they are single chunks
without wildcards; ``<ix>_<iy>`` is a tile id (``5_-3``). :func:`key_for` gives the key a message is
published on; :func:`vehicle_of_scan_key` and :func:`tile_of_key` read a received key back.
This module does not import Zenoh: key expressions are strings.
"""

from __future__ import annotations

from typing import Final

from randt.wire.messages import (
    CorrectionMessage,
    ErrorMessage,
    PoseMessage,
    ScanMessage,
    TileUpdateMessage,
    WireMessage,
)

__all__ = [
    "ALL_CORRECTIONS",
    "ALL_ERRORS",
    "ALL_POSES",
    "ALL_SCANS",
    "ALL_TILES",
    "ROOT",
    "correction_key",
    "error_key",
    "key_for",
    "map_tiles_key",
    "pose_key",
    "scan_key",
    "service_token_key",
    "tile_key",
    "tile_of_key",
    "vehicle_of_scan_key",
]

#: First chunk of every key expression of the wire format.
ROOT: Final = "randt"

_FLEET: Final = f"{ROOT}/fleet"
_MAP: Final = f"{ROOT}/map"
_SERVICE: Final = f"{ROOT}/service"


def scan_key(vehicle: str) -> str:
    """``randt/fleet/<vehicle>/scan``: a vehicle's scans (vehicle → service)."""
    return f"{_FLEET}/{vehicle}/scan"


def pose_key(vehicle: str) -> str:
    """``randt/fleet/<vehicle>/pose``: the poses answering a vehicle's scans (service → all)."""
    return f"{_FLEET}/{vehicle}/pose"


def error_key(vehicle: str) -> str:
    """``randt/fleet/<vehicle>/error``: the errors answering a vehicle's scans (service → vehicle)."""
    return f"{_FLEET}/{vehicle}/error"


def correction_key(vehicle: str) -> str:
    """``randt/fleet/<vehicle>/correction``: optimized poses of a vehicle's keyframes (service → all)."""
    return f"{_FLEET}/{vehicle}/correction"


def tile_key(map_name: str, tile: str) -> str:
    """``randt/map/<map>/tile/<ix>_<iy>``: a tile's updates, and the key to get it by.

    ``tile`` is the tile id ``f"{ix}_{iy}"`` (:attr:`~randt.wire.messages.TileUpdateMessage.tile`).
    """
    return f"{_MAP}/{map_name}/tile/{tile}"


def map_tiles_key(map_name: str) -> str:
    """``randt/map/<map>/tile/*``: every tile of one map (to subscribe to its updates)."""
    return tile_key(map_name, "*")


def service_token_key(instance: str) -> str:
    """``randt/service/<instance>``: the liveliness token a service instance holds while it runs."""
    return f"{_SERVICE}/{instance}"


#: Every vehicle's scans: what the service subscribes to.
ALL_SCANS: Final = scan_key("*")
#: Every vehicle's poses.
ALL_POSES: Final = pose_key("*")
#: Every vehicle's errors.
ALL_ERRORS: Final = error_key("*")
#: Every vehicle's keyframe corrections.
ALL_CORRECTIONS: Final = correction_key("*")
#: Every tile of every map: the service's tile queryable.
ALL_TILES: Final = tile_key("*", "*")


def key_for(message: WireMessage) -> str:
    """The key expression a message is published on.

    Raises
    ------
    TypeError
        ``message`` is not a wire message.
    """
    if isinstance(message, ScanMessage):
        return scan_key(message.vehicle)
    if isinstance(message, PoseMessage):
        return pose_key(message.vehicle)
    if isinstance(message, ErrorMessage):
        return error_key(message.vehicle)
    if isinstance(message, TileUpdateMessage):
        return tile_key(message.map, message.tile)
    if isinstance(message, CorrectionMessage):
        return correction_key(message.vehicle)
    raise TypeError(f"no key expression for {type(message).__name__}")


def vehicle_of_scan_key(key: str) -> str:
    """The ``<vehicle>`` chunk of a key ``randt/fleet/<vehicle>/scan``.

    Raises
    ------
    ValueError
        ``key`` is not a scan key.
    """
    parts = key.split("/")
    if len(parts) != 4 or f"{parts[0]}/{parts[1]}" != _FLEET or parts[3] != "scan":
        raise ValueError(f"not a scan key expression: {key!r}")
    return parts[2]


def tile_of_key(key: str) -> tuple[str, str] | None:
    """``(map, tile)`` of a key ``randt/map/<map>/tile/<tile>``, or ``None`` for any other key.

    A get on ``randt/map/**`` reaches the tile queryable with its own key expression: that is not
    one tile, and it is answered with nothing.
    """
    parts = key.split("/")
    if len(parts) != 5 or f"{parts[0]}/{parts[1]}" != _MAP or parts[3] != "tile":
        return None
    return parts[2], parts[4]
