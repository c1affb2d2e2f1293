"""The id rule: what a ``vehicle``, ``session``, ``map`` or service ``instance`` name may be.

One regular expression, :data:`ID_REGEX`: 1-64 letters, digits, ``_``, ``.`` and ``-``, starting
with a letter or digit. An id becomes a Zenoh key-expression chunk (``randt/fleet/<vehicle>/scan``)
and a file or directory name (``maps/<map>/``), so it may hold none of ``/ * $ ? #``, no spaces, no
leading dot or dash, and it is never ``.`` or ``..``. Every place that checks an id uses this module:
the wire decoders (:class:`randt.wire.messages.WireLimits`), the service's settings, its store and its
HTTP path parameters, and the vehicle publisher.
"""

from __future__ import annotations

import hashlib
import re
from typing import Final

__all__ = [
    "ID_MAX_LENGTH",
    "ID_PATTERN",
    "ID_REGEX",
    "UNKNOWN_ID",
    "UNSAFE_ID_SAMPLES",
    "is_valid_id",
    "legacy_session_map_name",
    "session_map_name",
    "session_of_map_name",
    "validate_id",
]

#: The id rule, anchored; matched in full (``re.fullmatch``).
ID_REGEX: Final = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"

#: :data:`ID_REGEX` compiled.
ID_PATTERN: Final = re.compile(ID_REGEX)

#: Longest id, in characters.
ID_MAX_LENGTH: Final = 64

#: ``vehicle`` / ``session`` of an error message when the failed message did not say (never an id).
UNKNOWN_ID: Final = "?"

#: Strings that would break a key expression or a file path: no id rule may accept any of them
#: (:class:`randt.wire.messages.WireLimits` refuses a configured ``id_pattern`` that does).
UNSAFE_ID_SAMPLES: Final = ("", "a/b", "*", "**", "$*", "a?b", "a#b", "a b", ".", "..", "a\nb")


def is_valid_id(value: object) -> bool:
    """Whether ``value`` is a ``str`` that is a valid id (:data:`ID_REGEX`, in full)."""
    return isinstance(value, str) and ID_PATTERN.fullmatch(value) is not None


def validate_id(value: object, what: str = "name") -> str:
    """Return ``value`` if it is a valid id, else raise.

    Parameters
    ----------
    value:
        The candidate.
    what:
        What the id names (``"map"``, ``"vehicle"``, ``"session"``), for the message.

    Raises
    ------
    ValueError
        Not a string, or not a valid id (path separators, ``..``, leading dot or dash, empty,
        longer than 64 characters, characters outside ``A-Z a-z 0-9 _ . -``).
    """
    if not isinstance(value, str):
        raise ValueError(f"{what} name must be a string, got {type(value).__name__}")
    if not is_valid_id(value):
        raise ValueError(
            f"invalid {what} name {value!r}: use 1-{ID_MAX_LENGTH} characters from A-Z a-z 0-9 _ . -, "
            "starting with a letter or digit"
        )
    return value


#: Longest escaped-vehicle prefix kept in front of the digest of a hashed session-map name.
_HASHED_PREFIX_MAX: Final = 36

#: Hex digits of SHA-256 in a hashed session-map name (96 bits).
_DIGEST_HEX: Final = 24


def _escape_vehicle(vehicle: str) -> str:
    """``_`` -> ``__``, ``.`` -> ``_-``: the escaped vehicle holds no dot, and only whole pairs
    starting with ``_`` (so it reads back unambiguously, left to right)."""
    return vehicle.replace("_", "__").replace(".", "_-")


def _unescape_vehicle(escaped: str) -> str | None:
    """The inverse of :func:`_escape_vehicle`, or ``None`` if ``escaped`` is not an escaped vehicle."""
    out: list[str] = []
    i = 0
    while i < len(escaped):  # an id's characters, at most 128: not a hot path
        c = escaped[i]
        if c == ".":
            return None
        if c == "_":
            nxt = escaped[i + 1 : i + 2]
            if nxt == "_":
                out.append("_")
            elif nxt == "-":
                out.append(".")
            else:
                return None
            i += 2
            continue
        out.append(c)
        i += 1
    return "".join(out)


def session_map_name(vehicle: str, session: str) -> str:
    """The map of a session without prior poses (its own frame): an injective encoding of both ids.

    ``<escaped vehicle>.<session>``, where the vehicle is escaped (``_`` -> ``__``, ``.`` -> ``_-``)
    so that it holds no dot: the first dot of the name separates the two ids, and no two
    (vehicle, session) pairs share a map (vehicle ``col.a`` + session ``b`` is ``col_-a.b``, vehicle
    ``col`` + session ``a.b`` is ``col.a.b``). Ids of letters, digits and dashes only (the common
    case: ``car-07`` + ``d1`` -> ``car-07.d1``) are unchanged.

    A name longer than the 64 characters of an id becomes ``<escaped vehicle, cut>_.<digest>``
    with 24 hex digits (96 bits) of SHA-256 over both ids: the ``_`` left unpaired before the dot
    marks the hashed form, which therefore never equals an unhashed name; two hashed names collide
    only if SHA-256 does (no encoding of two 64-character ids into 64 characters can be injective).

    Parameters
    ----------
    vehicle, session:
        Valid ids (:func:`validate_id`).

    Raises
    ------
    ValueError
        Either is not a valid id.
    """
    validate_id(vehicle, "vehicle")
    validate_id(session, "session")
    escaped = _escape_vehicle(vehicle)
    name = f"{escaped}.{session}"
    if len(name) <= ID_MAX_LENGTH:
        return name
    digest = hashlib.sha256(f"{vehicle}/{session}".encode()).hexdigest()[:_DIGEST_HEX]
    cut = 0  # the longest run of whole escape tokens (a char, or a "_" pair) that fits
    while cut < len(escaped):
        step = 2 if escaped[cut] == "_" else 1
        if cut + step > _HASHED_PREFIX_MAX:
            break
        cut += step
    prefix = escaped[:cut]
    return f"{prefix}_.{digest}"


def session_of_map_name(name: str) -> tuple[str, str] | None:
    """``(vehicle, session)`` whose own map is ``name`` (unhashed form only), else ``None``.

    ``None`` for the shared map (no dot), a hashed name (see :func:`session_map_name`) and any
    other name no session maps to.
    """
    escaped, dot, session = name.partition(".")
    if not dot:
        return None
    vehicle = _unescape_vehicle(escaped)
    if vehicle is None or not is_valid_id(vehicle) or not is_valid_id(session):
        return None
    return vehicle, session


def legacy_session_map_name(vehicle: str, session: str) -> str:
    """The session-map name used before the injective encoding: ``<vehicle>.<session>``, or
    ``<vehicle[:40]>.<sha1[:12]>`` past 64 characters. It collided (``col.a`` + ``b`` and ``col`` +
    ``a.b`` both gave ``col.a.b``); the store renames such maps once (``Store.migrate_map_names``)."""
    name = f"{vehicle}.{session}"
    if len(name) <= ID_MAX_LENGTH:
        return name
    digest = hashlib.sha1(name.encode()).hexdigest()[:12]
    return f"{vehicle[:40]}.{digest}"
