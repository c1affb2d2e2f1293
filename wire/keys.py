"""Every Zenoh key expression of the wire format (docs/wire-format.md, Key expressions).

- ``randt/fleet/<vehicle>/scan``: vehicle → service, :func:`scan_key`; the service subscribes to
  :data:`ALL_SCANS`;
- ``randt/fleet/<vehicle>/pose``: service → all, :func:`pose_key` (:data:`ALL_POSES`);
- ``randt/fleet/<vehicle>/error``: service → vehicle, :func:`error_key` (:data:`ALL_ERRORS`);
- ``randt/fleet/<vehicle>/correction``: service → all, the pose graph's corrections of a vehicle's
  keyframes, :func:`correction_key` (:data:`ALL_CORRECTIONS`);
- ``randt/map/<map>/tile/<ix>_<iy>``: service → all, and a get answered by the service's queryable
  on :data:`ALL_TILES`, :func:`tile_key` (:func:`map_tiles_key` for one map's tiles); a get on
  ``randt/map/<map>/tile/*?x=..;y=..;radius=..`` is answered with every tile around the point
  (:func:`tiles_near_selector`, :func:`parse_tiles_near`: a vehicle loads the map it localizes on);
- ``randt/service/<instance>``: the liveliness token of a running service, :func:`service_token_key`.

``<vehicle>``, ``<map>`` and ``<instance>`` are ids (:mod:`randt.wire.ids`), so they are single chunks
without wildcards; ``<ix>_<iy>`` is a tile id (``5_-3``). :func:`key_for` gives the key a message is
published on; :func:`vehicle_of_scan_key` and :func:`tile_of_key` read a received key back.
This module does not import Zenoh: key expressions are strings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Final

from randt.core.errors import BadMessageError
from randt.wire.codes import ErrorCode
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
    "MAX_TILES_NEAR_RADIUS_M",
    "ROOT",
    "TilesNear",
    "correction_key",
    "error_key",
    "key_for",
    "map_tiles_key",
    "parse_tiles_near",
    "pose_key",
    "scan_key",
    "service_token_key",
    "tile_key",
    "tile_of_key",
    "tiles_near_selector",
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


#: The largest radius a tiles-near query may ask for (a reply is every tile within it: 1 km is
#: about 8,000 tiles of 20 m, a few hundred MB).
MAX_TILES_NEAR_RADIUS_M: Final = 1000.0


@dataclass(frozen=True)
class TilesNear:
    """A tiles-near query (:func:`parse_tiles_near`): the tiles whose cell comes within
    ``radius_m`` of ``(x, y)`` (map frame, metres; the cylinder of Autoware's partial map loading,
    as HTTP's ``GET /maps/{map}/tiles?x=&y=&radius=``), but those the asker holds at the version it
    names (``have``: tile id -> version)."""

    x: float
    y: float
    radius_m: float
    have: dict[str, int] = field(default_factory=dict)


def tiles_near_selector(
    map_name: str, x: float, y: float, radius_m: float, have: dict[str, int] | None = None
) -> str:
    """The selector of a get for the tiles of ``map_name`` around ``(x, y)``:
    ``randt/map/<map>/tile/*?x=..;y=..;radius=..[;have=<tile>@<version>,...]``."""
    params = f"x={float(x)!r};y={float(y)!r};radius={float(radius_m)!r}"
    if have:
        params += ";have=" + ",".join(f"{tile}@{int(version)}" for tile, version in sorted(have.items()))
    return f"{map_tiles_key(map_name)}?{params}"


def parse_tiles_near(parameters: str) -> TilesNear:
    """The query of a selector's parameters (``x=..;y=..;radius=..[;have=..]``,
    :func:`tiles_near_selector`). Raises :class:`~randt.core.errors.BadMessageError`
    ``invalid_field`` naming the parameter: missing, not a finite number, a radius outside
    ``[0, MAX_TILES_NEAR_RADIUS_M]``, a ``have`` entry not ``<ix>_<iy>@<version>``."""
    values: dict[str, str] = {}
    for part in parameters.split(";"):
        if part:
            name, _, value = part.partition("=")
            values[name] = value

    def number(name: str) -> float:
        try:
            value = float(values[name])
        except KeyError:
            raise BadMessageError(
                f"{name}: a tiles-near query needs x, y and radius", code=ErrorCode.INVALID_FIELD
            ) from None
        except ValueError:
            raise BadMessageError(
                f"{name}: {values[name]!r} is not a number", code=ErrorCode.INVALID_FIELD
            ) from None
        if not math.isfinite(value):
            raise BadMessageError(f"{name}: {value} is not finite", code=ErrorCode.INVALID_FIELD)
        return value

    x, y, radius = number("x"), number("y"), number("radius")
    if not 0.0 <= radius <= MAX_TILES_NEAR_RADIUS_M:
        raise BadMessageError(
            f"radius: {radius:g} m is outside [0, {MAX_TILES_NEAR_RADIUS_M:g}]", code=ErrorCode.INVALID_FIELD
        )
    have: dict[str, int] = {}
    for entry in filter(None, values.get("have", "").split(",")):
        tile, _, version = entry.partition("@")
        ix, _, iy = tile.partition("_")
        try:
            int(ix), int(iy)
            have[tile] = int(version)
        except ValueError:
            raise BadMessageError(
                f"have: {entry!r} is not <ix>_<iy>@<version>", code=ErrorCode.INVALID_FIELD
            ) from None
    return TilesNear(x, y, radius, have)
